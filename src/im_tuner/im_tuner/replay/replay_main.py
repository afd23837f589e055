"""``ros2 run im_tuner replay BAG_DIR``: re-drive a live controller from a recorded bag and
compare its commands with the recorded ones (docs/replay.md; exit codes there). The command
line and the bag are checked before rclpy is imported (:mod:`.plan` is pure)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from im_drive_sim.cli import Parser, UsageError, int_in, parse_cli, quiet_interrupts, run_cli

from ..progress import Line

EXIT_MISMATCH = 1
EXIT_INCONCLUSIVE = 3


def parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_tuner replay',
        description="Play a recorded run's drive states (and /clock) from its bag into a live "
        "controller started with the recorded parameters, making the tuner's requests "
        '(gains, starts) where the bag says, and compare the commands it answers with '
        'the recorded ones: every period of a lock-step bag bit for bit, every fresh '
        'period of a real-time one (docs/replay.md).',
    )
    ap.add_argument(
        'bag', type=Path, metavar='BAG_DIR', help='a bag directory of a tuner run (RUN/bag_0)'
    )
    ap.add_argument(
        '--experiment',
        type=int_in(0, 2**31 - 1),
        metavar='N',
        help='compare experiment N only (the states before it are replayed too: the '
        "controller's filters and integrator carry over); default: every period up to "
        'the last experiment with a result',
    )
    ap.add_argument('--json', action='store_true', help='print the result as one JSON object')
    ap.add_argument('--quiet', action='store_true', help='no progress lines')
    return ap


class _Progress(Line):
    """``replay: state i/n (p %), ETA m:ss`` on stderr (a line every 10 % off a terminal)."""

    def __call__(self, i: int, n: int) -> None:
        self.update(i, n, f'replay: state {i}/{n} ({100 * i // n} %), {self.eta(i, n)}')


def result_dict(plan: Any, cmp: Any, failure: str | None, wall_s: float) -> dict[str, Any]:
    """What the replay found, as printed with ``--json``."""
    a, b = plan.window
    return {
        'bag': str(plan.bag),
        'mode': plan.mode,
        'experiment': None if plan.target is None else plan.target.eid,
        'first_step': a,
        'last_step': b,
        'periods': b - a + 1,
        'states_fed': len(plan.states),
        'compared': cmp.compared,
        'fresh_only': plan.mode == 'realtime',
        'differing': cmp.differing,
        'max_abs_diff': cmp.max_abs_diff,
        'first_mismatch': cmp.first,
        'failure': failure,
        'match': cmp.match and failure is None,
        'wall_s': round(wall_s, 3),
    }


def result_line(r: dict[str, Any]) -> str:
    what = 'every experiment' if r['experiment'] is None else f'experiment {r["experiment"]}'
    scope = (
        f'steps {r["first_step"]}..{r["last_step"]} ({r["periods"]} periods, '
        + ('the fresh ones compared' if r['fresh_only'] else 'every period compared')
        + f'), {r["mode"]} bag'
    )
    if r['match']:
        return (
            f'replay: MATCH {what}: {r["compared"]} commands bit for bit '
            f'(max |diff| {r["max_abs_diff"]:g}); {scope}'
        )
    text = f'replay: MISMATCH {what}: {r["differing"]} of {r["compared"]} commands differ'
    f = r['first_mismatch']
    if f is not None:
        text += (
            f', the first at step {f["step"]} ({f["field"]} recorded {f["recorded"]!r}, '
            f'replayed {f["replayed"]!r}); max |diff| {r["max_abs_diff"]:g}'
        )
    if r['failure']:
        text += f'; {r["failure"]}'
    return f'{text}; {scope}'


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv

    def body() -> int:
        cli = parse_cli(parser(), argv)
        from .plan import ReplayError, compare, load_plan

        try:
            plan = load_plan(cli.bag, cli.experiment)
        except ReplayError as exc:
            raise UsageError(str(exc)) from None
        with quiet_interrupts('replay'):  # rclpy, the controller's kernels: nothing held yet
            from .node import ReplayFailed, ReplayInconclusive, replay

        t0 = time.monotonic()
        failure = None
        try:
            line = _Progress(cli.quiet, 10)
            replayed = replay(plan, line, lambda t: line.note(f'replay: {t}'))
        except ReplayInconclusive as exc:
            print(f'replay: INCONCLUSIVE: {exc}', file=sys.stderr, flush=True)
            return EXIT_INCONCLUSIVE
        except ReplayFailed as exc:
            failure, replayed = exc.args[0], exc.args[1]
        r = result_dict(plan, compare(plan, replayed), failure, time.monotonic() - t0)
        print(json.dumps(r) if cli.json else result_line(r), flush=True)
        return 0 if r['match'] else EXIT_MISMATCH

    try:
        return run_cli('replay', body)
    except KeyboardInterrupt:
        print('replay: interrupted', file=sys.stderr, flush=True)
        return 130


if __name__ == '__main__':
    from im_drive_sim.cli import executable

    executable('replay', main)
