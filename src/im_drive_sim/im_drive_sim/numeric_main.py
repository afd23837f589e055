"""``python -m im_drive_sim.numeric_main [--env]``: this machine's numeric baseline
(:mod:`im_drive_sim.numeric`), or with ``--env`` the variables that set it, for a shell
(``env $(python -m im_drive_sim.numeric_main --env) dask worker tcp://...``)."""

from __future__ import annotations

import sys

from . import numeric


def main(argv: list[str] | None = None) -> int:
    """``python -m im_drive_sim.numeric_main [--env]``."""
    args = sys.argv[1:] if argv is None else argv
    problem = numeric.switch_problem()
    if problem or args not in ([], ['--env']):
        usage = 'usage: python -m im_drive_sim.numeric_main [--env]'
        print(f'error: im_drive_sim.numeric_main: {problem or usage}', file=sys.stderr)
        return 2
    if args == ['--env']:
        p = numeric.apply()
        print(' '.join(f'{k}={v}' for k, v in p.env.items()))  # no spaces: `env $(...)`
        return 0
    print(f'numeric baseline: {numeric.describe(numeric.status())}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
