"""The ``bench`` profile's values on each packaged drive: the table of docs/drive-family.md
("The bench per drive"), printed by ``python -m im_drive_sim.bench_table``.

Pure (no rclpy). The values (``params.bench_profile``: scaled by the drive's rating) are
read from each drive's loaded config (``realism: bench``), not recomputed here.
"""

from __future__ import annotations

import math
import sys

from .drive_file import load_config
from .family import DRIVE_NAMES
from .params import rating_scales

#: (heading, how a config gives the value, format)
_COLUMNS = (
    ('rated torque [N m]', lambda c: c.machine.rated_torque, '.4g'),
    ('DC bus [V]', lambda c: c.machine.Udc, '.4g'),
    ('rated current [A rms]', lambda c: c.machine.rated_current / math.sqrt(2.0), '.3g'),
    ('viscous B [N m s/rad] (file)', lambda c: c.machine.B, '.3g'),
    ('Coulomb Tc [N m]', lambda c: c.machine.coulomb_torque, '.4g'),
    ('breakaway Ts [N m]', lambda c: c.machine.static_torque, '.4g'),
    ('ripple [N m]', lambda c: c.disturbance.ripple_amplitude, '.4g'),
    ('random load std [N m]', lambda c: c.disturbance.load_noise_std, '.4g'),
    ('dead time [V]', lambda c: c.machine.deadtime_voltage, '.4g'),
    ('current noise std [A]', lambda c: c.sensors.current_noise_std, '.4g'),
    (
        'current offsets a, b [A]',
        lambda c: (c.sensors.current_offset_a, c.sensors.current_offset_b),
        '.4g',
    ),
)


def _cell(v: object, fmt: str) -> str:
    if isinstance(v, tuple):
        return ', '.join(format(x, fmt) for x in v)
    return format(v, fmt)


def bench_table(names: tuple[str, ...] = DRIVE_NAMES) -> str:
    """Markdown: each drive's rating, its scales (rated torque, bus, rated current over the
    750 W's) and its ``bench`` values of the rating-bound effects."""
    head = ['drive', 'scales: torque, bus, current'] + [h for h, _, _ in _COLUMNS]
    rows = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for name in names:
        cfg = load_config(name, overrides={'realism': 'bench'})
        r = rating_scales(cfg.machine)
        cells = [name, f'{r["torque"]:.4g}, {r["bus"]:.4g}, {r["current"]:.4g}']
        cells += [_cell(get(cfg), fmt) for _, get, fmt in _COLUMNS]
        rows.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(rows)


def main(argv: list[str] | None = None) -> int:
    """``python -m im_drive_sim.bench_table``: the table on stdout."""
    args = sys.argv[1:] if argv is None else argv
    if args:
        print('error: im_drive_sim.bench_table: takes no arguments', file=sys.stderr)
        return 2
    print(bench_table())
    return 0


if __name__ == '__main__':
    sys.exit(main())
