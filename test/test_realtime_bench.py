"""The real bench at 5 kHz: losses that are the paper's loss, or are flagged.

* the composed real-time bench (``tuner --bench realtime``: drive and controller in one
  process, one wall-clock loop, recording on) runs every experiment on exactly 5625 drive
  periods, all driven by fresh answers, and its losses equal, bit for bit, the lock-step
  replay of the same plant history: it measures the paper's loss;
* a controller in its own process that falls behind the drive (slowed on purpose) has
  its experiments flagged ``timing``; the tuner re-runs them within ``--retries`` and
  never reports one as a loss; the external-bench run still leaves a closed bag.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader

from im_controller.config import GAIN_NAMES, Gains
from im_drive_sim.drive_file import load_config
from im_tuner.offline import OfflineBench, replay_realtime

sys.path.insert(0, str(Path(__file__).parent))
from test_faults import DISCOVERY_S, bag_counts, bag_state, results, ros2

STEPS = 5625
# wall-clock timing is asserted: alone, after the tests that run on two workers
pytestmark = pytest.mark.serial
SLOW = str(Path(__file__).with_name('slow_controller.py'))
#: the tolerance the tests give the controller [periods of 5625]
TOLERANCE = 1500
#: the loop's real-time options (as ros2_control_node; CI runs as root: granted)
RT = ('--thread-priority', '50', '--lock-memory')
FLOOR_S = 2.0


@pytest.fixture(scope='module')
def floor() -> dict:
    """This machine's own floor for a 5 kHz loop, measured first (benchmarks/loop_floor.py's
    compiled wait, SCHED_FIFO, for FLOOR_S s): overruns and worst lateness. A VM starts
    some periods late whatever the code does (0.1-2 % here and on CI's machines); the tests
    below judge what the code does with them, and say the floor when they fail."""
    code = (
        'import json, sys; sys.path.insert(0, sys.argv[1]); import loop_floor as F; '
        'from im_drive_sim import rt; rt.apply(rt.RtOptions(50, -1, True)); '
        f'print(json.dumps(F.measure({FLOOR_S})))'
    )
    bench = str(Path(__file__).resolve().parents[1] / 'benchmarks')
    p = subprocess.run([sys.executable, '-c', code, bench], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    return {k: out[k] for k in ('overrun_pct', 'max_lateness_us')}


def assert_flagged_as_counted(recs: list[dict], floor: dict) -> None:
    """What the code controls about timing, whatever the machine: an experiment is flagged
    ``timing`` exactly when its held + late periods exceed the tolerance, a flagged one
    carries no loss (its number is ``off_timing_loss``), and it is re-run with the same
    gains (the next record of the same kind and evaluation)."""
    for i, r in enumerate(recs):
        if r['status'] == 'lost':
            continue
        per = r['periods']
        off = per['held'] + per['late'] > TOLERANCE
        assert (r['status'] == 'timing') == off, (r, floor)
        if off:
            assert r['loss'] is None and isinstance(r['off_timing_loss'], float), r
            again = recs[i + 1]
            assert (again['kind'], again['eval'], again['gains']) == (
                r['kind'],
                r['eval'],
                r['gains'],
            ), (again, floor)


def measured(recs: list[dict]) -> list[tuple[str, str]]:
    """(kind, status) of the records that count: timing and lost attempts were re-run. A
    drive that cannot pause holds its old current through the host's stalls (10-60 ms on
    this VM now and then), which can trip a safety limit on gains that run fine on time
    (reproduced by stopping the tuner's process for 60 ms every 0.3 s: the reference
    aborted on max_position_error with 654 held periods): an experiment that aborted while
    holding more periods than the tuner's default tolerance is counted, as the code must,
    and read here as the host's (``ok``)."""
    from im_tuner.names import DEFAULT_TIMING_TOLERANCE

    def status(r: dict) -> str:
        held = r['periods']['held'] + r['periods']['late']
        host = r['status'] == 'aborted' and held > DEFAULT_TIMING_TOLERANCE
        return 'ok' if host else r['status']

    return [(r['kind'], status(r)) for r in recs if r['status'] not in ('timing', 'lost')]


def test_composed_realtime_run_measures_the_paper_loss_bit_for_bit(tmp_path):
    run = tmp_path / 'run'
    p = subprocess.run(
        [
            *ros2('im_tuner', 'tuner', '--bench', 'realtime', '--budget', '3', '--seed', '4'),
            # the blind search's gains, whose loss the defined experiment repeats within
            # 0.03-0.8 % (checked below); the drive model's first point (the default on a
            # simulated bench) is a high-gain controller whose consecutive losses differ
            # by up to ~5 % (0.447 lock-step vs 0.470 real-time, CI of 2026-11-26)
            *('--opt', 'first=none'),
            # real-time scheduling of the loop, as ros2_control_node (CI runs as root)
            *('--thread-priority', '50', '--lock-memory'),
            '--remeasure',
            '1',
            '--quiet',
            '--out',
            str(run),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr[-3000:]
    recs = results(run)
    assert [r['kind'] for r in recs] == ['reference', 'eval', 'eval', 'eval', 'remeasure']
    for r in recs:
        # exactly 5625 drive periods, every one driven by the answer to the state before
        assert r['status'] in ('ok', 'aborted'), r
        assert r['steps'] == STEPS and r['t_end_ns'] - r['t_start_ns'] == 1_125_000_000, r
        assert r['periods'] == {'fresh': STEPS, 'held': 0, 'late': 0}, r
    summary = json.loads((run / 'summary.json').read_text())
    assert summary['timing'] == 0
    d = summary['sessions'][0]['drive']
    assert d['watchdog_trips'] == 0, d
    assert d['held'] + d['late'] <= 0.001 * d['steps'], d
    loop = d['loop']
    assert loop['periods'] == d['steps'] and loop['answers_missed'] == 0, loop
    # every period start in one bin of the lateness histogram
    assert sum(loop['lateness_histogram'].values()) == loop['periods'], loop
    for k in ('drive_period_us', 'controller_answer_us', 'period_work_us'):
        assert 0 < loop[k]['p50'] <= loop[k]['p99'] <= loop[k]['max'], loop
    assert 'drive (composed loop): per-period work p50' in p.stdout
    # what the loop ran with, in the summary and in the bag's metadata
    sched = loop['realtime']
    assert sched['requested'] == {'thread_priority': 50, 'cpu_affinity': -1, 'lock_memory': True}
    assert sched['kernel'] and sched['cpu_model'] and isinstance(sched['preempt_rt'], bool)
    if os.geteuid() == 0:
        assert (sched['policy'], sched['priority'], sched['memory_locked']) == (
            'SCHED_FIFO',
            50,
            True,
        ), sched
        # no option refused (the host check may warn about a busy host: its own line)
        assert sched['refused'] == [] and 'warning: --' not in p.stderr, p.stderr
    else:  # refused in one line each, and the run went on
        assert len(sched['refused']) == p.stderr.count('warning: --') >= 1, p.stderr
    with next((run / 'bag_0').glob('*.mcap')).open('rb') as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta['im_tuner.realtime']['policy'] == sched['policy']
    assert json.loads(meta['im_tuner.realtime']['affinity']) == sched['affinity']
    # the bag: closed, nothing lost, every state of the run in it
    assert bag_state(run / 'bag_0') == 'closed'
    meta = yaml.safe_load((run / 'bag_0' / 'metadata.yaml').read_text())
    custom = meta['rosbag2_bagfile_information']['custom_data']
    assert custom['im_tuner.lost_total'] == '0', custom['im_tuner.counts']
    assert bag_counts(run / 'bag_0')['/drive/state'] >= 5 * STEPS
    # the same plant history replayed in lock-step: the same losses, bit for bit
    seed = yaml.safe_load((run / 'run.yaml').read_text())['drive_seed']
    replayed = replay_realtime(recs, load_config(None), seed)
    assert [r.experiment_id for r in replayed] == [r['experiment_id'] for r in recs]
    assert [r.loss for r in replayed] == [r['loss'] for r in recs]
    assert all(r.steps == STEPS and not r.timing for r in replayed)
    # the defined experiment: the same gains one after another in lock-step (no hold
    # between experiments; real time held ~40 periods while the tuner set the next gains)
    # give the same losses within the bench's noise (docs/controller.md: 0.03-0.8 %)
    lock = OfflineBench(load_config(None), seed)
    for r in recs:
        m = lock.measure(Gains(*(float(r['gains'][n]) for n in GAIN_NAMES)))
        if not (m.aborted or r['aborted']):
            assert m.loss == pytest.approx(r['loss'], rel=0.035), (r, m.loss)


def test_the_host_is_checked_before_the_first_experiment_and_auto_takes_its_tolerance(tmp_path):
    """``--timing-tolerance auto`` on the composed bench: a 2 s check of the host's loop
    wait before anything runs, one line saying the tolerance it chose (the larger of the
    default and twice what 95 % of the check's experiment-long windows meet), and that choice
    everywhere the run records its tolerance: run.yaml, the controller, the summary, the
    loop's real-time record and the bag. The simulator pauses when late: it completes
    whatever the host did."""
    run = tmp_path / 'run'
    p = subprocess.run(
        [
            *ros2('im_tuner', 'tuner', '--bench', 'realtime', '--budget', '1', '--seed', '4'),
            *('--opt', 'first=none', '--remeasure', '0', '--out', str(run), *RT),
            *('--timing-tolerance', 'auto'),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    # said first, before the run began (its first line names the run directory)
    line = p.stdout.splitlines()[0]
    assert line.startswith('timing tolerance auto: '), p.stdout[:2000]
    run_yaml = yaml.safe_load((run / 'run.yaml').read_text())
    check = run_yaml['host_check']
    chosen = max(10, 2 * check['tolerance'])  # (host.AUTO_MARGIN)
    assert check['auto'] is True and check['tolerance_chosen'] == chosen, check
    assert f'timing tolerance auto: {chosen} held periods per experiment' in line, line
    assert check['periods'] >= 10_000 and 1.9 < check['seconds'] < 10, check
    assert run_yaml['timing_tolerance'] == chosen
    assert run_yaml['controller_parameters']['timing_tolerance'] == chosen
    summary = json.loads((run / 'summary.json').read_text())
    assert summary['timing_tolerance'] == chosen
    sched = summary['sessions'][0]['drive']['loop']['realtime']
    assert sched['host_check']['tolerance_chosen'] == chosen
    if os.geteuid() == 0 and os.path.exists('/dev/cpu_dma_latency'):
        assert sched['pm_qos'] == {'held': True, 'latency_us': 0, 'reason': ''}, sched
        assert check['pm_qos_held'] is True, check
    with next((run / 'bag_0').glob('*.mcap')).open('rb') as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert json.loads(meta['im_tuner.realtime']['host_check'])['tolerance_chosen'] == chosen
    assert json.loads(meta['im_tuner.realtime']['pm_qos']) == sched['pm_qos']


def test_a_drive_that_declares_command_delay_2_runs_fresh_experiments(tmp_path, floor, host_floor):
    """A drive file with ``command_delay: 2`` (a power stage that latches its command at
    the period start, docs/real-drive.md): the simulator composed in real time runs every
    period fresh under the declared delay, and its losses equal, bit for bit, the
    lock-step replay on a delay-2 drive; the example drive (wall clock, its stand-in
    latching the command) labels its periods by the same delay, so they count fresh. The
    example drive cannot pause: the machine's late starts hold periods (its floor), and an
    attempt past the tolerance is flagged and re-run (``assert_flagged_as_counted``); a run
    the host made later than its floor is judged against the host (``run_judged``)."""
    cfg = load_config(None)
    drive_file = tmp_path / 'delay2.yaml'
    drive_file.write_text(yaml.safe_dump({**cfg.to_dict(), 'command_delay': 2}))
    d2 = load_config(drive_file)
    assert d2.command_delay == 2
    made: list[Path] = []  # every run's directory, each attempt its own
    for drive in ('sim', 'example'):

        def start(_tol: int, drive: str = drive) -> tuple[subprocess.CompletedProcess, Path]:
            run = tmp_path / f'{drive}_{len(made)}'
            made.append(run)
            p = subprocess.run(
                [
                    *ros2('im_tuner', 'tuner', '--bench', 'realtime', '--budget', '1'),
                    *('--seed', '4', '--drive', drive, '--drive-config', str(drive_file)),
                    *('--remeasure', '0', '--no-record', '--quiet', '--out', str(run)),
                    *('--retries', '6', *RT, '--ros-args', '-p', f'timing_tolerance:={TOLERANCE}'),
                ],
                capture_output=True,
                text=True,
                timeout=300,
            )
            return p, run

        if drive == 'sim':  # it pauses when the loop is late: the host holds nothing
            p, run = start(TOLERANCE)
        else:
            host_floor.require()
            p, run, _ = host_floor.run_judged(start)
        assert p.returncode == 0, (floor, p.stdout + p.stderr[-3000:])
        recs = results(run)
        assert_flagged_as_counted(recs, floor)
        assert measured(recs) == [('reference', 'ok'), ('eval', 'ok')], (recs, floor)
        for r in recs:
            if drive == 'sim':  # it pauses when the loop is late: every period fresh
                assert r['periods'] == {'fresh': STEPS, 'held': 0, 'late': 0}, r
            elif r['status'] == 'ok':  # the wall clock: late starts hold periods
                assert r['periods']['fresh'] >= STEPS - TOLERANCE, r
        if drive == 'sim':
            seed = yaml.safe_load((run / 'run.yaml').read_text())['drive_seed']
            replayed = replay_realtime(recs, d2, seed)
            assert [r.loss for r in replayed] == [r['loss'] for r in recs]
            # ... and not those of the delay-1 drive
            assert [r.loss for r in replay_realtime(recs, cfg, seed)] != [r['loss'] for r in recs]


def test_a_stalled_period_on_a_drive_that_cannot_pause_is_held_and_flagged(
    tmp_path, floor, host_floor
):
    """The simulated drive in its hardware-like mode (a power stage cannot pause: a late
    period start follows periods that went by with the old current held), composed with
    the controller; the loop stalls 0.6 s once (the drive's test hook, at step 6000). 0.6 s
    = 3000 periods is longer than an experiment's 0.5 s settle: wherever the stall falls
    once the reference has begun (the loop runs from the bench's start, so where step 6000
    falls depends on the machine's start-up), it holds >= 500 periods of a measured part,
    and the experiment it holds >= the tolerance of is flagged ``timing`` and re-run.
    What else the machine's own late starts (its floor) hold is judged as counted
    (``assert_flagged_as_counted``), never assumed away; a run the host made later than
    its floor is judged against the host (``run_judged``)."""
    host_floor.require()
    stall, stall_s = 6000, 0.6
    attempts = iter(range(2))

    def start(_tol: int) -> tuple[subprocess.CompletedProcess, Path]:
        run = tmp_path / f'run_{next(attempts)}'
        p = subprocess.run(
            [
                *ros2('im_tuner', 'tuner', '--bench', 'realtime', '--budget', '1', '--seed', '4'),
                *('--remeasure', '0', '--no-record', '--quiet', '--out', str(run)),
                *('--retries', '6', *RT, '--ros-args', '-p', 'hardware_like:=true'),
                *('-p', f'test_stall_step:={stall}', '-p', f'test_stall_duration:={stall_s}'),
                *('-p', f'timing_tolerance:={TOLERANCE}'),
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        return p, run

    p, run, _ = host_floor.run_judged(start)
    assert p.returncode == 0, (floor, p.stdout + p.stderr[-3000:])
    recs = results(run)
    d = json.loads((run / 'summary.json').read_text())['sessions'][0]['drive']
    assert d['loop']['missed_periods'] >= 0.99 * stall_s * 5000, d['loop']  # it stalled
    assert_flagged_as_counted(recs, floor)
    assert measured(recs) == [('reference', 'ok'), ('eval', 'ok')], (recs, floor)
    # the experiment whose timeline the stall fell in: ran on the drive's timeline
    k0 = [r['t_start_ns'] // 200_000 for r in recs if r['status'] != 'lost']
    ran = [r for r in recs if r['status'] != 'lost']
    hit = [r for r, k in zip(ran, k0, strict=True) if k <= stall < k + r['steps']]
    if hit:
        # it fell inside a measured part: >= the rest of the stall's periods were held,
        # counted on the timeline, flagged, never a loss
        (stalled,) = hit
        assert stalled['status'] == 'timing', (stalled, floor)
        assert stalled['periods']['held'] > TOLERANCE and stalled['loss'] is None, stalled
    else:
        # it began in a settle (2500 periods before a measured part): the stall outlasts
        # the settle, so that experiment's first periods went by held, counted; or it
        # began before the bench started the reference (a slow start-up): nothing of an
        # experiment was held by it, and the checks above are what can be judged
        settle = 2500
        into = [(r, k) for r, k in zip(ran, k0, strict=True) if k - settle <= stall < k]
        for r, k in into:
            held_at_least = stall + round(stall_s * 5000) - k - 2  # (the start's jitter)
            assert r['periods']['held'] >= held_at_least, (r, k, floor)
    assert not any(r['status'] == 'timing' and r['loss'] is not None for r in recs)


def test_a_controller_that_falls_behind_is_flagged_rerun_and_never_a_loss(procs, tmp_path):
    drive = procs.start(ros2('im_drive_sim', 'drive_sim', '--mode', 'realtime', '--seed', '2'))
    ctl = procs.start([sys.executable, SLOW, '--delay-us', '2000'])
    run = tmp_path / 'run'
    p = subprocess.run(
        [
            *ros2('im_tuner', 'tuner', '--bench', 'none', '--budget', '1', '--retries', '1'),
            '--no-reference',
            '--remeasure',
            '0',
            '--fault-policy',
            'reset',
            '--seed',
            '3',
            '--discovery-timeout',
            DISCOVERY_S,
            '--quiet',
            '--out',
            str(run),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert drive.poll() is None and ctl.poll() is None
    # two attempts, both off the paper timing: the run fails, with no loss reported
    assert p.returncode == 1, p.stdout + p.stderr[-3000:]
    assert 'no result after 2 attempts' in p.stdout + p.stderr
    recs = results(run)
    assert [(r['eval'], r['attempt'], r['status']) for r in recs] == [
        (0, 1, 'timing'),
        (0, 2, 'timing'),
    ]
    for r in recs:
        assert r['loss'] is None and isinstance(r['off_timing_loss'], float)
        per = r['periods']
        assert per['fresh'] + per['held'] + per['late'] == r['steps']
        assert per['held'] + per['late'] > 0 and r['reason'].startswith('timing: ')
    summary = json.loads((run / 'summary.json').read_text())
    assert summary['timing'] == 2 and summary['evaluations'] == 0 and summary['best'] is None
    # the external run's bag (the loss topic) is closed, with both flagged results in it
    assert bag_state(run / 'bag_0') == 'closed'
    assert bag_counts(run / 'bag_0')['/controller/loss'] == 2
    assert bag_counts(run / 'bag_0')['/tuner/result'] == 2  # the tuner's records


def test_a_recorder_child_that_does_not_close_its_bag_is_reported(tmp_path, monkeypatch):
    """The tuner checks its recorder child's exit: one that ignores SIGINT (it had to be
    killed, RECORDER_CLOSE_TIMEOUT after the SIGINT, made short here) left its bag
    unclosed, and close_recording says so (the tuner then ends 'failed', not 'done' with
    exit 0)."""
    from im_tuner.bench import recorder_watch
    from im_tuner.bench.forms import Children

    monkeypatch.setattr(recorder_watch, 'RECORDER_CLOSE_TIMEOUT', 2.0)
    said: list[str] = []

    stubborn = subprocess.Popen(
        [
            sys.executable,
            '-c',
            'import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); '
            'print("up", flush=True); time.sleep(60)',
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert stubborn.stdout.readline() == 'up\n'  # SIGINT is ignored from here on
    bench = object.__new__(Children)  # only what close_recording reads
    bench.children, bench.ended, bench.bag = {'recorder': stubborn}, [], None
    bench.watch = None  # no tuner node: nothing to wait for before the stop
    bench.host = type('Host', (), {'warn': staticmethod(said.append)})()
    problems = bench.close_recording()
    assert problems == ['the recorder did not close its bag (killed by signal 9)']
    assert stubborn.returncode == -9 and bench.close_recording() == []
