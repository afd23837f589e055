"""Each packaged drive's start at standstill: does its speed loop chatter at the current
limit? The measurement behind docs/drive-family.md, "Start gains".

Pure (no rclpy). One encoder count moves the speed estimate by (1 - a) 2 pi/(N Ts) in a
period (``family.count_step``); the speed loop's P gain turns it into a current step. With
the start's gains scaled by the inertia ratio alone (the earlier rule), that step
was 58-80 % of isq_max on the ratio-10 drives: at standstill the encoder's one-count limit
cycle became a current chatter of several amperes, on ``im7500w-j10`` at the current limit.
``family.start_scale`` caps it at ``family.COUNT_STEP_MAX`` of isq_max.

``python research/family_start.py [EXPERIMENTS] [--realism bench]`` prints, for each drive,
the start by the inertia rule alone (``before``) and by the rule now (``now``): k_pw, k_iw,
the count step, the q-current reference's rms around its median at standstill, the periods
it spends at the limit, and the start's loss with the weights each rule calibrates and with
the weights of the rule before (the same yardstick for both rows). Offline bench, full
model, the drive file's bench (ideal; or the profile asked), drive seed 0, EXPERIMENTS (3)
experiments from rest, alternating +pi, -pi.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass

import numpy as np

from im_controller.config import ExperimentConfig, Gains, trajectory_times
from im_tuner import family as F

__all__ = ['StartFigures', 'inertia_rule_experiment', 'measure_start', 'standstill_windows']


@dataclass(frozen=True)
class StartFigures:
    """A start measured on its drive: gains [A s/rad, A/rad]; count_step [A] and its
    fraction of isq_max; rms [A]: the q-current reference's rms around its median in the
    standstill windows (mean over windows and experiments; rms_max the largest);
    at_limit: periods with |isq*| at isq_max over all experiments; loss: the mean, and the
    mean with ``yardstick``'s weights; aborted: experiments the supervisor stopped."""

    k_pw: float
    k_iw: float
    count_step: float
    count_fraction: float
    rms: float
    rms_max: float
    at_limit: int
    loss: float
    loss_yardstick: float
    aborted: int


def standstill_windows(e: ExperimentConfig) -> tuple[tuple[float, float], ...]:
    """The experiment's settled windows [s from step 0]: from the move's end + 0.1 s (not
    before 0.3 s) to the load step, and from 0.2 s after the load step to the end; on the
    paper's experiment 0.3-0.7 s and 0.9-1.125 s."""
    t = e.trajectory
    t_end = trajectory_times(t.distance, t.a_max, t.v_max)[2]
    return ((max(0.3, t_end + 0.1), t.load_delay), (t.load_delay + 0.2, t.duration))


def inertia_rule_experiment(setup: F.DriveSetup) -> ExperimentConfig:
    """The drive's experiment by the inertia rule alone: the start's k_pw, k_iw scaled by
    the inertia ratio alone, the loss weights calibrated on that start."""
    k = F.drive_scales(setup.drive.machine).inertia
    g = ExperimentConfig().fallback_gains
    return F.with_start(setup, dataclasses.replace(g, k_pw=g.k_pw * k, k_iw=g.k_iw * k))


def _run(setup: F.DriveSetup, e: ExperimentConfig, gains: Gains, n: int):
    """``n`` experiments of ``gains`` from rest on the drive with experiment ``e``: the
    losses, aborts and the recorded q-current references."""
    from im_controller.runner import ExperimentRunner, config_for_drive
    from im_drive_sim.sim import DriveSim
    from im_tuner.offline import run_experiment_offline

    sim = DriveSim(setup.drive, seed=0)
    sim.reset(omega=0.0, fluxed=True)
    cfg = config_for_drive(e, sim)
    runner = ExperimentRunner(cfg, gains)
    runner.reset(sim.theta_meas)
    out = []
    for i in range(n):
        res, sig = run_experiment_offline(sim, gains, cfg, i, runner)
        out.append((res, sig['t'], sig['isq_cmd']))
    return out


def measure_start(
    setup: F.DriveSetup, e: ExperimentConfig, yardstick: ExperimentConfig, n: int = 3
) -> StartFigures:
    """The start ``e.fallback_gains`` of ``setup``'s drive with experiment ``e`` over ``n``
    experiments; its loss also with ``yardstick``'s weights (the same experiments)."""
    g = e.fallback_gains
    lim = setup.drive.machine.isq_max
    runs = _run(setup, e, g, n)
    rms, at_limit = [], 0
    for _, t, isq in runs:
        for a, b in standstill_windows(e):
            w = isq[(t >= a) & (t < b)]
            if w.size:  # an aborted experiment ends early
                rms.append(float(np.sqrt(np.mean((w - np.median(w)) ** 2))))
        at_limit += int(np.count_nonzero(np.abs(isq) >= lim))
    same = dataclasses.replace(yardstick, fallback_gains=g)
    other = [r.loss for r, _, _ in _run(setup, same, g, n)] if yardstick.loss != e.loss else None
    step = F.count_step(setup.drive, g.k_pw)
    losses = [r.loss for r, _, _ in runs]
    return StartFigures(
        k_pw=g.k_pw,
        k_iw=g.k_iw,
        count_step=step,
        count_fraction=step / lim,
        rms=float(np.mean(rms)) if rms else float('nan'),
        rms_max=max(rms) if rms else float('nan'),
        at_limit=at_limit,
        loss=float(np.mean(losses)),
        loss_yardstick=float(np.mean(other if other is not None else losses)),
        aborted=sum(int(r.aborted) for r, _, _ in runs),
    )


def start_table(
    names: tuple[str, ...] = F.DRIVE_NAMES, n: int = 3, realism: str | None = None
) -> str:
    """Markdown: per drive, the start by the inertia rule alone and by the rule now, on the
    drive file's bench or the profile ``realism`` (the weights are the ideal bench's)."""
    head = (
        '| drive | rule | k_pw [A s/rad] | k_iw [A/rad] | one count [A] (% of isq_max) | '
        'standstill isq* rms [A] (max) | periods at the limit | start loss | loss, '
        "before's weights | aborted |\n|" + '---|' * 10
    )
    rows = [head]
    for name in names:
        s = F.drive_setup(name, realism=realism)
        before = inertia_rule_experiment(s)
        rules = [('before = now', before)]
        if s.experiment != before:
            rules = [('before', before), ('now', s.experiment)]
        for rule, e in rules:
            f = measure_start(s, e, before, n)
            rows.append(
                f'| {name} | {rule} | {f.k_pw:.4g} | {f.k_iw:.4g} | {f.count_step:.3g} '
                f'({100 * f.count_fraction:.1f} %) | {f.rms:.3g} ({f.rms_max:.3g}) | '
                f'{f.at_limit} | {f.loss:.4f} | {f.loss_yardstick:.4f} | {f.aborted}/{n} |'
            )
    return '\n'.join(rows)


USAGE = 'usage: python research/family_start.py [EXPERIMENTS >= 1] [--realism ideal|bench]'


def main(argv: list[str] | None = None) -> int:
    """``python research/family_start.py [EXPERIMENTS] [--realism ideal|bench]``."""
    from im_drive_sim.params import REALISM_PROFILES

    args = list(sys.argv[1:] if argv is None else argv)
    realism = None
    if '--realism' in args:
        i = args.index('--realism')
        realism = args[i + 1] if i + 1 < len(args) else ''
        del args[i : i + 2]
    bad = realism is not None and realism not in REALISM_PROFILES
    if bad or len(args) > 1 or (args and not (args[0].isdigit() and int(args[0]) >= 1)):
        print(f'error: family_start: {USAGE}', file=sys.stderr)
        return 2
    print(start_table(n=int(args[0]) if args else 3, realism=realism))
    return 0


if __name__ == '__main__':
    sys.exit(main())
