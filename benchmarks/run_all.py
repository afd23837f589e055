"""All benchmarks of the workspace, with the targets beside each figure.

Run: ``make bench`` (or ``.venv/bin/python benchmarks/run_all.py``). Figures are medians over
repeated batches on a shared, noisy machine; compare medians and ratios, not single runs.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_experiment
import bench_host
import bench_live
import bench_lockstep
import bench_model
import bench_numeric
import bench_optim
import bench_realtime
import bench_report
import bench_study
import bench_tuner
import bench_user_drive

#: figure -> (unit, target): what is asked of each figure; a positive target is an
#: upper bound, a negative one a lower bound (stored negated), None: informational.
TARGETS = {
    'full_ns_per_step': ('ns/step', 400.0),
    'reduced_ns_per_step': ('ns/step', 150.0),
    'lockstep_1proc_us': ('us/step', 40.0),
    'lockstep_2proc_us': ('us/step', None),
    # lower bounds: real-time factors (simulated s per wall s)
    'experiment_rtf_1proc': ('x', -5.0),
    'experiment_rtf_2proc': ('x', -1.5),
    'experiment_rtf_rec_zstd': ('x', None),
    'experiment_rtf_rec_lz4': ('x', None),
    'experiment_rtf_rec_none': ('x', None),
    # with the recorder in the process, at least 80 % of the speed without
    'recording_kept_zstd': ('ratio', -0.8),
    'recording_kept_lz4': ('ratio', -0.8),
    'recording_kept_none': ('ratio', -0.8),
    # the default tuning run, recording included, and the optimiser's cost
    'tuner_necga_rtf': ('x', -5.0),
    'tuner_spsa_rtf': ('x', -5.0),
    'tuner_necga_ask_tell_us': ('us/eval', 50.0),
    'tuner_spsa_ask_tell_us': ('us/eval', 50.0),
    # the optimiser alone, caches disturbed between calls as in the tuner (bench_optim)
    **{f'optim_{a}_cold_us': ('us/eval', 50.0) for a in ('spsa', 'necga', 'cga', 'pecga', 'rcga')},
    # what holding numpy/OpenBLAS at x86-64-v3 costs the optimisers (held/off)
    **{f'numeric_{a}_ratio': ('ratio', None) for a in ('cmaes', 'tpe', 'safe')},
    'tuner_necga_wall_s': ('s', None),
    'tuner_spsa_wall_s': ('s', None),
    'tuner_necga_sim_s': ('s', None),
    'tuner_spsa_sim_s': ('s', None),
    # the report of a default run (whole command: bag read, 4 figures, CSV)
    'report_necga_s': ('s', 10.0),
    'report_spsa_s': ('s', 10.0),
    # the report's start-up (--help, a refusal) and a whole report of a 25 MB bag
    'report_help_s': ('s', 1.0),
    'report_refusal_s': ('s', 1.0),
    'report_25mb_s': ('s', 3.0),
    'report_25mb_bag_mb': ('MB', None),
    # the offline study, the paper's whole grid (240k experiments), whole command
    'study_full_grid_s': ('s', 300.0),
    'study_reduced_grid_s': ('s', 120.0),
    'study_full_exp_per_s': ('exp/s', None),
    'study_reduced_exp_per_s': ('exp/s', None),
    'study_full_1job_exp_per_s': ('exp/s', None),
    'study_scaling': ('x', None),
    # real-time tuning runs, recording on (composed bench; separate processes)
    'rt_composed_held_late_pct': ('%', 0.1),
    'rt_composed_exp_held_late_pct': ('%', 0.1),
    'rt_processes_exp_held_late_pct': ('%', None),
    'rt_composed_watchdog_trips': ('trips', 0.0),
    'rt_composed_overrun_pct': ('%', 0.05),
    'rt_composed_timing_flagged': ('exp', 0.0),
    **{
        f'rt_composed_{w}_{q}_us': ('us', None)
        for w in ('work', 'answer')
        for q in ('p50', 'p99', 'max')
    },
    'rt_composed_work_p99_us': ('us', 50.0),
    'rt_processes_held_late_pct': ('%', None),
    'rt_processes_overrun_pct': ('%', None),
    'rt_processes_watchdog_trips': ('trips', None),
    'rt_processes_timing_flagged': ('exp', None),
    # the composed loop under load: quiet (the default: SCHED_FIFO 50) p99 <= 50 us and overruns
    # <= 0.05 %; two CPU hogs with SCHED_FIFO 50 and memory locked: overruns <= 0.1 %,
    # worst lateness <= 1 ms
    'rt_other_overrun_pct': ('%', None),
    'rt_other_work_p99_us': ('us', None),
    'rt_fifo_overrun_pct': ('%', 0.05),
    'rt_fifo_work_p99_us': ('us', 50.0),
    'rt_hogs_overrun_pct': ('%', None),
    'rt_hogs_overrun_pct_ratio': ('x', None),
    'rt_hogs_fifo_overrun_pct': ('%', 0.1),
    'rt_hogs_fifo_max_lateness_us': ('us', 1000.0),
    'rt_hogs_fifo_overrun_pct_ratio': ('x', None),
    # a reader frozen for the run: overruns within noise, memory growth <= 10 MB
    'rt_frozen_overrun_pct_ratio': ('x', None),
    'rt_frozen_rss_growth_mb': ('MB', 10.0),
    'rt_composed_rss_growth_mb': ('MB', None),
    'rt_frozen_bag_lost': ('msgs', 0.0),
    # the live view with a frozen client beside the same runs without (side by side): overruns
    # within 1.2x, nothing lost from the bag
    'live_overrun_ratio': ('x', 1.2),
    'live_overrun_pct': ('%', None),
    'live_plain_overrun_pct': ('%', None),
    'live_floor_overrun_pct': ('%', None),
    'live_bag_lost': ('msgs', 0.0),
    # the host's floor: host_check's late share within 1.5x of cyclictest's (same minute)
    **{f'host_cyclictest_{t}_late_pct': ('%', None) for t in ('idle', 'hogs')},
    **{f'host_check_{t}_late_pct': ('%', None) for t in ('idle', 'hogs')},
    **{f'host_check_{t}_tolerance': ('periods', None) for t in ('idle', 'hogs')},
    **{f'host_check_{t}_vs_cyclictest': ('x', 1.5) for t in ('idle', 'hogs')},
}


def optim_figures(res: dict, prefix: str = 'optim') -> dict[str, float]:
    """bench_optim's figures (us per evaluation), flattened: optim_<algo>[_<variant>]_us."""
    out = {}
    for k, v in res.items():
        if isinstance(v, dict):
            out.update(optim_figures(v, f'{prefix}_{k}'))
        else:
            out[f'{prefix}_{k}_us'] = float(v)
    return out


def main() -> int:
    figures: dict[str, float] = {}
    print('== model step (numba kernels, batch) ==', flush=True)
    model = bench_model.main()
    figures.update({f'{m}_ns_per_step': r['median_ns'] for m, r in model.items()})
    print('\n== lock-step round trip over DDS (drive_sim + minimal responder) ==', flush=True)
    figures.update(bench_lockstep.main())
    print("\n== the paper's experiment through the nodes (lock-step) ==", flush=True)
    figures.update(bench_experiment.main())
    print('\n== optimisers: ask+tell per evaluation, dim 5 ==', flush=True)
    figures.update(optim_figures(bench_optim.main()))
    print(
        '\n== the numeric baseline (x86-64-v3) against native dispatch: ask+tell [us] ==',
        flush=True,
    )
    numeric = bench_numeric.main()
    figures.update({k: v for k, v in numeric.items() if isinstance(v, float)})
    print(
        '\n== the default tuning run: ros2 run im_tuner tuner (200 evaluations, recorded) ==',
        flush=True,
    )
    figures.update(bench_tuner.main())
    print(
        "\n== the report: start-up (--help, a refusal) and a 25 MB bag's whole report ==",
        flush=True,
    )
    figures.update(bench_report.main())
    print(
        "\n== the host's floor: host_check's measurement beside cyclictest, and the waits ==",
        flush=True,
    )
    figures.update(bench_host.main([]))
    print(
        '\n== real time at 5 kHz: tuner --bench realtime / realtime-processes '
        '(budget 20, recorded, 3 runs) ==',
        flush=True,
    )
    figures.update(bench_realtime.main())
    print(
        '\n== the live view: tuner --bench realtime --live with a frozen client beside the same '
        'runs without, and the floor (budget 6, 4 pairs) ==',
        flush=True,
    )
    figures.update(bench_live.main())
    print(
        "\n== a user's drive at the simulator's timing: each form of a power stage on the "
        'composed bench beside the floor (budget 10, quiet and beside two hogs) ==',
        flush=True,
    )
    figures.update(bench_user_drive.main(['--stops', '10']))
    print(
        "\n== the offline study: ros2 run im_tuner study (the paper's grid, every core) ==",
        flush=True,
    )
    figures.update(bench_study.main())
    print('\n== summary (medians) ==')
    for name, value in figures.items():
        unit, target = TARGETS.get(name, ('', None))
        if target is None:
            verdict, bound = '', ''
        elif target < 0:  # a lower bound, stored negated
            verdict = '  ok' if value >= -target else '  BELOW TARGET'
            bound = f'(target >= {-target:g})'
        else:
            verdict = '  ok' if value <= target else '  ABOVE TARGET'
            bound = f'(target <= {target:g})'
        print(f'{name:<26} {value:9.2f} {unit:<8} {bound}{verdict}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
