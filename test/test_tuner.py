"""The tuner end to end, through real DDS: ``ros2 run im_tuner tuner``.

Short runs (about 20 evaluations) of SPSA and neCGA on the in-process simulated bench,
checked against what the bag recorded; resume after SIGKILL equals an uninterrupted run
bit for bit; bad input and a missing controller give one clear line.  The full default
run (200 evaluations) is ``make bench``'s, not the tests'.
"""

from __future__ import annotations

import collections
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
GAINS = ('k_pw', 'k_iw', 'k_pos', 'tau_sm', 'tau_eq')
START = {'k_pw': 0.53, 'k_iw': 20.0, 'k_pos': 30.0, 'tau_sm': 0.005, 'tau_eq': 0.007}
START_LOSS = 0.9803040260343194  # experiment 0 of the hand-tuned start (test_controller_node)


#: no controller is on a test's graph (its own ROS_DOMAIN_ID) unless it starts one: `auto`
#: need not look for one for its default 2 s (``benches.DISCOVERY_TIMEOUT``)
NO_CONTROLLER = ('--discovery-timeout', '0.2')


def tuner(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``ros2 run im_tuner tuner ARGS``; on the default bench (auto) with
    :data:`NO_CONTROLLER` unless ARGS say how long to look or which bench."""
    if '--bench' not in args and '--discovery-timeout' not in args:
        args = (*args, *NO_CONTROLLER)
    return subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', *args], capture_output=True, text=True, timeout=timeout
    )


def report(run: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [ROS2, 'run', 'im_tuner', 'report', str(run), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def results(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / 'results.jsonl').read_text().splitlines()]


def bag_messages(bag: Path, topics: set[str]) -> dict[str, list]:
    """Messages of ``topics`` deserialised by rosbags' standard API (``AnyReader``, types
    from the bag's own schemas)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list] = collections.defaultdict(list)
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, _t, raw in reader.messages(connections=conns):
            out[conn.topic].append(reader.deserialize(raw, conn.msgtype))
    return out


def loss_values(msg) -> dict[str, str]:
    (st,) = msg.status
    return {kv.key: kv.value for kv in st.values}


def check_result_topic(bag: Path, recs: list[dict]) -> None:
    """The bag's /tuner/result holds one message per results.jsonl record, in order: the
    status named by its kind, its experiment id, loss and gains bit for bit."""
    msgs = bag_messages(bag, {'/tuner/result'})['/tuner/result']
    assert [m.status[0].name for m in msgs] == [r['kind'] for r in recs]
    for m, r in zip(msgs, recs, strict=True):
        kv = loss_values(m)
        assert kv['status'] == r['status'] and int(kv['experiment_id']) == r['experiment_id']
        assert float(kv['loss']) == r['loss']
        assert {n: float(kv[n]) for n in GAINS} == r['gains']


def check_run(run: Path, algo: str, budget: int, proc: subprocess.CompletedProcess) -> list[dict]:
    """What every finished run must show: files, records, summary, bag contents."""
    assert proc.returncode == 0, proc.stderr[-3000:]
    recs = results(run)
    kinds = collections.Counter(r['kind'] for r in recs)
    assert kinds['reference'] == 1 and kinds['eval'] == budget and kinds['remeasure'] == 3
    assert [r['eval'] for r in recs if r['kind'] == 'eval'] == list(range(budget))
    assert all(r['status'] in ('ok', 'aborted') for r in recs)
    assert [r['experiment_id'] for r in recs] == list(range(len(recs)))
    ref = recs[0]
    assert ref['kind'] == 'reference' and ref['gains'] == START and ref['loss'] == START_LOSS
    run_yaml = yaml.safe_load((run / 'run.yaml').read_text())
    assert run_yaml['algo'] == algo and run_yaml['budget'] == budget
    assert run_yaml['bench'] == 'inproc'
    assert run_yaml['controller_parameters']['k_pw'] == 0.53
    evals = [r for r in recs if r['kind'] == 'eval']
    box = run_yaml['search_box']
    for r in evals:  # candidates inside the box, the gains are the box map of u
        for n, u in zip(GAINS, r['u'], strict=True):
            lo, hi = box[n]['lo'], box[n]['hi']
            assert 0.0 <= u <= 1.0
            assert r['gains'][n] == lo + (hi - lo) * u
        assert r['sim_s'] == pytest.approx(1.125) if not r['aborted'] else r['sim_s'] < 1.125
    ok = [r for r in evals if not r['aborted']]
    best = min(ok, key=lambda r: r['loss'])
    # best-so-far column is the running minimum over non-aborted evaluations
    running = np.minimum.accumulate([r['loss'] if not r['aborted'] else np.inf for r in evals])
    assert [r['best_loss'] for r in evals] == [None if not np.isfinite(x) else x for x in running]
    summary = json.loads((run / 'summary.json').read_text())
    assert summary['outcome'] == 'done' and summary['evaluations'] == budget
    assert summary['best']['loss'] == best['loss'] and summary['best']['eval'] == best['eval']
    assert summary['aborted'] == sum(r['aborted'] for r in evals)
    sat = next(
        (
            i + 1
            for i, r in enumerate(evals)
            if not r['aborted'] and r['loss'] <= run_yaml['satisfactory_loss']
        ),
        None,
    )
    assert summary['evaluations_to_satisfactory'] == sat
    rem = [r for r in recs if r['kind'] == 'remeasure']
    top = sorted(ok, key=lambda r: r['loss'])
    assert [r['eval'] for r in rem] == [r['eval'] for r in top[:3]]
    assert all(r['gains'] == evals[r['eval']]['gains'] for r in rem)
    chosen = min((r for r in rem if not r['aborted']), key=lambda r: r['loss'])
    applied = summary['applied']
    expect = chosen if chosen['loss'] < ref['loss'] else ref
    assert applied['gains'] == expect['gains']
    assert summary['sim_s'] == pytest.approx(sum(r['sim_s'] for r in recs))
    assert summary['real_time_factor'] > 0 and summary['optimizer_us_per_eval'] > 0
    assert 'best loss' in proc.stdout and 'real-time factor' in proc.stdout
    # the report command, with ros2 as this shell finds it (cli.ros2_command)
    assert f'ros2 run im_tuner report {run}' in proc.stdout
    assert 'report (summary, plots, CSV): ' in proc.stdout
    # The bag: every loss the tuner used is the controller's message, bit for bit; the
    # gains were set by set_parameters_atomically (service events recorded), the last
    # call leaves the applied gains.
    bag = run / 'bag_0'
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['custom_data']['im_tuner.state'] == 'closed'
    counts = json.loads(meta['custom_data']['im_tuner.counts'])
    for topic, c in counts.items():
        assert c['recorded'] == c['published'] and c['lost'] == 0, topic
    # the in-process bench publishes drive/status too (about 1 Hz, and at exit)
    assert counts['/drive/status']['recorded'] >= 1
    ev = '/controller/set_parameters_atomically/_service_event'
    msgs = bag_messages(bag, {'/controller/loss', ev})
    losses = [loss_values(m) for m in msgs['/controller/loss']]
    assert [float(v['loss']) for v in losses] == [r['loss'] for r in recs]
    assert [int(v['experiment_id']) for v in losses] == [r['experiment_id'] for r in recs]
    for v, r in zip(losses, recs, strict=True):
        assert {n: float(v[n]) for n in GAINS} == r['gains']
    requests = [m.request[0] for m in msgs[ev] if len(m.request)]
    last = {p.name: p.value.double_value for p in requests[-1].parameters}
    assert last == applied['gains']
    assert counts['/tuner/result']['recorded'] == len(recs)
    check_result_topic(bag, recs)
    return recs


def test_spsa_short_run(tmp_path):
    run = tmp_path / 'spsa_run'
    # (12 evaluations, 6 pairs: a longer run checks nothing more and costs the suite)
    proc = tuner('--algo', 'spsa', '--budget', '12', '--seed', '3', '--out', str(run), '--quiet')
    recs = check_run(run, 'spsa', 12, proc)
    evals = [r for r in recs if r['kind'] == 'eval']
    # SPSA: evaluations come in pairs u_k +- c_k Delta_k around the iterate, c_k per the
    # paper's c = 0.03, gamma = 0.3 (normalised box), Delta_k = +-1 per gain.
    start_u = np.array(
        [
            (START[n] - yaml.safe_load((run / 'run.yaml').read_text())['search_box'][n]['lo'])
            / (lambda b: b['hi'] - b['lo'])(
                yaml.safe_load((run / 'run.yaml').read_text())['search_box'][n]
            )
            for n in GAINS
        ]
    )
    for k in range(6):
        up, um = np.array(evals[2 * k]['u']), np.array(evals[2 * k + 1]['u'])
        ck = 0.03 / (k + 1) ** 0.3
        np.testing.assert_allclose(np.abs(up - um), 2 * ck, rtol=1e-9)
        if k == 0:  # the first pair is centred on the hand-tuned start
            np.testing.assert_allclose((up + um) / 2, start_u, rtol=1e-12)


def test_necga_short_run(tmp_path):
    run = tmp_path / 'necga_run'
    proc = tuner('--algo', 'necga', '--budget', '12', '--seed', '4', '--out', str(run), '--quiet')
    recs = check_run(run, 'necga', 12, proc)
    # the simulated drive is known: its rated q current beside the ripple (a percentage),
    # for the paper's algorithms too (not only with safe's identification)
    from im_drive_sim.drive_file import load_config

    m = load_config(None).machine
    ripple = json.loads((run / 'summary.json').read_text())['ripple']
    assert ripple['rated_isq_a'] == m.rated_torque / m.Kt and ripple['limit'] is None
    # 16-bit genes: every gain is lo + (hi - lo) v/65535 with integer v
    for r in recs:
        if r['kind'] == 'eval':
            v = np.array(r['u']) * 65535
            np.testing.assert_allclose(v, np.round(v), atol=1e-6)


def _same_evaluations(a: list[dict], b: list[dict]) -> None:
    key = (
        'kind',
        'eval',
        'u',
        'gains',
        'loss',
        'terms',
        'aborted',
        'experiment_id',
        't_start_ns',
        't_end_ns',
        'best_loss',
    )
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert {k: x.get(k) for k in key} == {k: y.get(k) for k in key}


def offline_run(
    algo: str, budget: int, seed: int, remeasure: int = 3, identify: bool = False
) -> tuple[list[dict], object, dict]:
    """The tuner's run (defaults: hand-tuned start, remeasure 3) on the pure core's
    offline bench: the same records as through the ROS nodes, bit for bit; with its
    state and its summary.json (as a dict). ``identify``: safe's default on the
    simulated bench, its first step from the identified drive (within the default ripple
    limit, 1.5). (test_faults.py uses it too.)"""
    from im_drive_sim.drive_file import load_config
    from im_tuner import optim
    from im_tuner.first_step import IdentifiedFirstStep
    from im_tuner.offline import OfflineBench
    from im_tuner.runlog import MemoryRecord
    from im_tuner.space import load_params
    from im_tuner.tuner_cli import _drive_of
    from im_tuner.tuning import TuningRun, run_seeds

    params = load_params(None)
    opt_ss, drive_seed = run_seeds(seed)
    start = params.space.start_u if algo in optim.TAKES_START else None
    more = {'first': 'identify'} if identify else {}
    opt = optim.make_optimizer(algo, params.space.dim, opt_ss, start, **more)
    limit = 1.5 if identify else None
    hook = IdentifiedFirstStep(*_drive_of(None, None, params), None, limit) if identify else None
    run = TuningRun(
        MemoryRecord(),
        params.space,
        opt,
        budget=budget,
        satisfactory_loss=params.satisfactory_loss,
        remeasure=remeasure,
        retries=3,
        reference=True,
        first_step=hook,
        ripple_limit=limit,
    )
    assert run.run(OfflineBench(load_config(None), drive_seed)) == 'done'
    summary = json.loads(json.dumps(run.summary(outcome='done', wall_s=0.0).to_dict()))
    return [r.to_dict() for r in run.records], run.state, summary  # (the records' lines)


def test_a_resumed_realtime_run_keeps_experiment_ids_unique(tmp_path, procs, wait_until):
    """A resumed real-time run does not replay: its controller starts past the run's ids
    (first_experiment_id), so no id repeats in the run; every record names its session,
    and the resumed session's bag has the losses under the same ids as its records."""
    run = tmp_path / 'rt'
    args = ['--bench', 'realtime', '--budget', '3', '--remeasure', '0', '--seed', '4']
    child = procs.start([ROS2, 'run', 'im_tuner', 'tuner', *args, '--quiet', '--out', str(run)])
    res = run / 'results.jsonl'
    wait_until(lambda: res.exists() and res.read_text().count('\n') >= 2, 120, message='2 records')
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=30)
    before = results(run)
    assert 2 <= len(before) < 4
    proc = tuner('--resume', str(run))
    assert proc.returncode == 0, proc.stderr[-3000:]
    first = max(r['experiment_id'] for r in before) + 1
    assert f'experiment ids go on from {first}' in proc.stderr
    recs = results(run)
    assert recs[: len(before)] == before and [r['kind'] for r in recs][-1] == 'eval'
    ids = [r['experiment_id'] for r in recs]
    assert len(set(ids)) == len(ids), ids
    assert [r['session'] for r in recs] == [0] * len(before) + [1] * (len(recs) - len(before))
    assert ids[len(before)] == first, ids
    summary = json.loads((run / 'summary.json').read_text())
    assert [s['session'] for s in summary['sessions']] == [0, 1]
    assert summary['sessions'][1]['first_experiment_id'] == first
    msgs = bag_messages(run / 'bag_1', {'/controller/loss'})
    assert [int(loss_values(m)['experiment_id']) for m in msgs['/controller/loss']] == ids[
        len(before) :
    ]


@pytest.mark.parametrize('algo', ['cmaes', 'tpe', 'safe'])
def test_resume_after_kill_continues_bit_for_bit(tmp_path, procs, wait_until, algo):
    """SIGKILL mid-run, then --resume: the records are those of the uninterrupted run,
    computed here on the pure core's offline bench (which the ROS nodes reproduce bit for
    bit: test_study.py), not by a second ROS run."""
    budget = 8
    killed = tmp_path / 'killed'
    args = ['--algo', algo, '--budget', str(budget), '--seed', '11', '--quiet']
    child = procs.start(
        [ROS2, 'run', 'im_tuner', 'tuner', *args, *NO_CONTROLLER, '--out', str(killed)]
    )
    res = killed / 'results.jsonl'
    # (safe: the default's first step, identified after two records: seconds of offline
    # tuning, a minute on a loaded machine, before the third)
    wait_until(lambda: res.exists() and res.read_text().count('\n') >= 4, 300, message='4 records')
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=30)
    n_killed = res.read_text().count('\n')
    assert 4 <= n_killed < budget + 4
    proc = tuner('--resume', str(killed))
    assert proc.returncode == 0, proc.stderr[-3000:]
    whole, st, _s = offline_run(algo, budget, 11, identify=algo == 'safe')
    _same_evaluations(whole, results(killed))
    sk = json.loads((killed / 'summary.json').read_text())
    assert sk['evaluations'] == budget and sk['aborted'] == st.aborted
    assert sk['best']['eval'] == st.best['eval'] and sk['best']['loss'] == st.best['loss']
    assert [r['loss'] for r in sk['remeasured']] == [r['loss'] for r in st.remeasured]
    assert sk['sessions'][1]['replayed'] == n_killed


def test_resume_after_kill_equals_uninterrupted_run(tmp_path, procs, wait_until):
    """SIGKILL, report, --resume, report, --resume again: the records and the summary are
    those of the uninterrupted run, computed on the pure core's offline bench (which the
    ROS nodes reproduce bit for bit: test_study.py, and the three resume tests above)
    rather than by a second ROS run (it took a third of this test's time)."""
    # budget 8 (+ reference + 3 re-measurements): every experiment is 1.625 s of drive time
    args = ['--algo', 'necga', '--budget', '8', '--seed', '11', '--quiet']
    whole, _st, sw = offline_run('necga', 8, 11)
    killed = tmp_path / 'killed'
    child = procs.start(
        [ROS2, 'run', 'im_tuner', 'tuner', *args, *NO_CONTROLLER, '--out', str(killed)]
    )
    res = killed / 'results.jsonl'
    wait_until(lambda: res.exists() and res.read_text().count('\n') >= 4, 120, message='4 records')
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=30)
    n_killed = res.read_text().count('\n')
    assert 4 <= n_killed < 12
    # The killed session's bag is still marked as being recorded ...
    meta0 = yaml.safe_load((killed / 'bag_0' / 'metadata.yaml').read_text())
    assert meta0['rosbag2_bagfile_information']['custom_data']['im_tuner.state'] == 'recording'
    # The report reads what the killed run left (partial results, a bag without footer).
    rep = report(killed, '--out', str(tmp_path / 'rep_killed'))
    assert rep.returncode == 0, rep.stderr[-3000:]
    assert 'outcome: interrupted' in rep.stdout and 'bag_0: NOT CLOSED' in rep.stdout
    assert (tmp_path / 'rep_killed' / 'evaluations.csv').read_text().count(
        '\n'
    ) == 1 + res.read_text().count('\n')
    proc = tuner('--resume', str(killed))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert 'replaying' in proc.stderr
    # one drive line per session that reported its drive, each named: the killed one
    # never did (a SIGINTed one would say 'drive (session 1, bag_0)')
    assert proc.stdout.count('  drive (') == 1 and '  drive (this session)' in proc.stdout
    assert 'simulated experiment time' in proc.stdout
    _same_evaluations(whole, results(killed))
    sk = json.loads((killed / 'summary.json').read_text())
    assert sk['applied']['on_controller'] is True
    for k in (
        'best',
        'applied',
        'evaluations',
        'aborted',
        'evaluations_to_satisfactory',
        'remeasured',
    ):
        assert sw[k] == sk[k], k
    assert [s['bag'] for s in sk['sessions']] == ['bag_0', 'bag_1']
    assert sk['sessions'][1]['replayed'] == n_killed
    # ... and repaired by the resume; the new session has its own bag.
    meta0 = yaml.safe_load((killed / 'bag_0' / 'metadata.yaml').read_text())
    assert meta0['rosbag2_bagfile_information']['custom_data']['im_tuner.state'] == 'repaired'
    meta1 = yaml.safe_load((killed / 'bag_1' / 'metadata.yaml').read_text())
    assert meta1['rosbag2_bagfile_information']['custom_data']['im_tuner.state'] == 'closed'
    # The report of the resumed run finds every loss in its session's bag.
    rep = report(killed, '--out', str(tmp_path / 'rep_resumed'))
    assert rep.returncode == 0, rep.stderr[-3000:]
    assert f'losses in the bags vs results.jsonl: {len(results(killed))} equal' in rep.stdout
    assert 'DIFFER' not in rep.stdout and 'not in a bag' not in rep.stdout
    assert 'bag_0: complete (repaired)' in rep.stdout and 'bag_1: closed' in rep.stdout
    # A finished run resumed again has nothing left to do: it says so, changes no result
    # and makes no new session (no replay, no bag)
    again = tuner('--resume', str(killed))
    assert again.returncode == 0, again.stderr[-3000:]
    assert 'the run is finished (8 of 8 evaluations' in again.stdout
    assert 'nothing to resume' in again.stdout and 'replaying' not in again.stderr
    assert not (killed / 'bag_2').exists()
    assert json.loads((killed / 'summary.json').read_text()) == sk
    _same_evaluations(whole, results(killed))


@pytest.mark.parametrize(
    'args, expect',
    [
        (['--budget', '0'], 'argument --budget: must be >= 1, got 0'),
        (['--algo', 'pso'], "invalid choice: 'pso'"),
        (['--algo', 'necga', '--opt', 'eta=30'], 'eta'),
        (['--algo', 'spsa', '--opt', 'eta=5'], '--opt eta does not apply to --algo spsa'),
        (['--seed', '-1'], 'argument --seed: must be >= 0, got -1'),
        (['--budget', 'ten'], "argument --budget: not an integer: 'ten'"),
        (['--fault-policy', 'ignore'], 'invalid choice'),
        (['--ripple-limit', '0.5'], "--ripple-limit: a ratio >= 1 or 'off', got '0.5'"),
        (['--ripple-limit', '2', '--no-reference'], 'not with --no-reference'),
    ],
)
def test_bad_command_line_one_line_exit_2(tmp_path, args, expect):
    out = tmp_path / 'run'
    proc = tuner(*args, '--out', str(out), timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: tuner:') and expect in lines[0], (
        proc.stderr
    )
    assert not out.exists()


def test_bad_files_one_line_exit_2(tmp_path):
    bad = tmp_path / 'tuner.yaml'
    bad.write_text('satisfactory_loss: 0.8\nsearch_box:\n  k_pw: {lo: 1.0, hi: 0.5, start: 0.7}\n')
    for args, expect in (
        (['--params', str(bad)], 'search_box must have exactly'),
        (['--params', str(tmp_path / 'missing.yaml')], 'cannot read'),
        (['--resume', str(tmp_path)], 'not a tuning run'),
        (['--resume', str(tmp_path), '--seed', '3'], 'do not also give --seed'),
        (['--resume', str(tmp_path), '--ripple-limit', '2'], 'do not also give --ripple-limit'),
    ):
        proc = tuner(*args, timeout=60)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and expect in lines[0], proc.stderr
    full = yaml.safe_load(bad.read_text())
    full['search_box'] = {n: {'lo': 0.0, 'hi': 1.0, 'start': 0.5} for n in GAINS}
    full['search_box']['k_iw'] = {'lo': 0.0, 'hi': 90000.0, 'start': 20.0}
    bad.write_text(yaml.safe_dump(full))
    proc = tuner('--params', str(bad), timeout=60)
    assert proc.returncode == 2 and "leaves the controller's accepted range" in proc.stderr
    existing = tmp_path / 'existing'
    existing.mkdir()
    (existing / 'keep.txt').write_text('x')
    proc = tuner('--out', str(existing), timeout=60)
    assert proc.returncode == 2 and 'already exists' in proc.stderr
    assert sorted(p.name for p in existing.iterdir()) == ['keep.txt']


def test_bench_none_without_controller_says_what_to_start(tmp_path):
    t0 = time.monotonic()
    proc = tuner(
        '--bench', 'none', '--discovery-timeout', '0.5', '--out', str(tmp_path / 'run'), timeout=60
    )
    assert proc.returncode == 1
    assert 'no controller reachable' in proc.stderr
    assert (
        'start the drive host first' in proc.stderr
        and 'ros2 run im_tuner drive_host' in proc.stderr
    )
    # ... and what to try when one runs but discovery is slow (a loaded machine)
    assert 'give it longer, e.g. --discovery-timeout 20' in proc.stderr
    assert time.monotonic() - t0 < 30


def test_auto_uses_a_controller_already_on_the_graph(tmp_path, procs, ros_context, wait_until):
    """A bench already running (here the simulated one, started by hand): the tuner uses it
    and starts no simulator of its own; the external default fault policy is 'stop'."""
    from rclpy.node import Node

    bench = procs.start([ROS2, 'run', 'im_tuner', 'sim_bench', '--no-record', '--seed', '5'])
    probe = Node('probe', context=ros_context)
    try:
        wait_until(
            lambda: (
                '/controller/start_experiment'
                in [n for n, _ in probe.get_service_names_and_types()]
            ),
            60,
            message='the bench controller',
        )
    finally:
        probe.destroy_node()
    run = tmp_path / 'ext'
    proc = tuner(
        '--budget',
        '3',
        '--remeasure',
        '0',
        '--seed',
        '1',
        '--out',
        str(run),
        '--discovery-timeout',
        '10',
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    run_yaml = yaml.safe_load((run / 'run.yaml').read_text())
    assert run_yaml['bench'] == 'external' and run_yaml['fault_policy'] == 'stop'
    recs = results(run)
    assert [r['kind'] for r in recs] == ['reference', 'eval', 'eval', 'eval']
    assert recs[0]['loss'] == START_LOSS  # the bench's experiment 0: nothing else ran first
    assert 'on the external bench' in proc.stderr
    assert bench.poll() is None  # the bench is left running


def test_sigint_ends_the_session_cleanly_and_resumably(tmp_path, procs, wait_until):
    run = tmp_path / 'int'
    child = procs.start(
        [ROS2, 'run', 'im_tuner', 'tuner', '--budget', '40', '--seed', '2', '--out', str(run)]
    )
    res = run / 'results.jsonl'
    # (the default's first step is identified after two records: up to a minute loaded)
    wait_until(lambda: res.exists() and res.read_text().count('\n') >= 4, 300, message='4 records')
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=60)
    assert child.returncode == 130, err[-2000:]
    assert '--resume' in out
    summary = json.loads((run / 'summary.json').read_text())
    assert summary['outcome'] == 'interrupted' and 3 <= summary['evaluations'] < 40
    meta = yaml.safe_load((run / 'bag_0' / 'metadata.yaml').read_text())
    custom = meta['rosbag2_bagfile_information']['custom_data']
    assert custom['im_tuner.state'] == 'closed'
    counts = json.loads(custom['im_tuner.counts'])
    assert all(c['recorded'] == c['published'] for c in counts.values())
    # the checkpoint matches the records: a resume would continue from here
    ck = json.loads((run / 'checkpoint.json').read_text())
    assert ck['records'] == len(results(run))


def test_processes_bench(tmp_path):
    """drive_sim and controller as child processes, the recorder as a third."""
    run = tmp_path / 'procs'
    proc = tuner(
        '--bench',
        'processes',
        '--budget',
        '2',
        '--remeasure',
        '0',
        '--seed',
        '9',
        '--out',
        str(run),
        '--quiet',
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    recs = results(run)
    assert [r['kind'] for r in recs] == ['reference', 'eval', 'eval']
    assert recs[0]['loss'] == START_LOSS  # same physics as in one process
    assert yaml.safe_load((run / 'run.yaml').read_text())['bench'] == 'processes'
    msgs = bag_messages(run / 'bag_0', {'/controller/loss'})
    assert [float(loss_values(m)['loss']) for m in msgs['/controller/loss']] == [
        r['loss'] for r in recs
    ]
    check_result_topic(run / 'bag_0', recs)  # from the tuner to the recorder child
    meta = yaml.safe_load((run / 'bag_0' / 'metadata.yaml').read_text())
    counts = json.loads(meta['rosbag2_bagfile_information']['custom_data']['im_tuner.counts'])
    for topic, c in counts.items():
        assert c['recorded'] == c['published'] and c['lost'] == 0, (topic, c)


def test_auto_refuses_to_add_a_second_drive(tmp_path, procs, ros_context, wait_until):
    """A drive on the graph without a controller: the tuner must not start a simulated
    drive beside it (two drives on /drive/state); it says what to start instead."""
    from rclpy.node import Node

    procs.start([ROS2, 'run', 'im_drive_sim', 'drive_sim'])
    probe = Node('probe2', context=ros_context)
    try:
        wait_until(lambda: probe.count_publishers('/drive/state') > 0, 60, message='the drive')
    finally:
        probe.destroy_node()
    run = tmp_path / 'run'
    proc = tuner('--budget', '2', '--out', str(run), '--discovery-timeout', '5', timeout=120)
    assert proc.returncode == 1
    assert 'a drive is publishing /drive/state but no controller' in proc.stderr
    assert 'ros2 run im_controller controller' in proc.stderr


# -- rosbags' standard API, a rebuilt checkpoint, one tuner per run ---------------------------
@pytest.fixture(scope='module')
def run6(tmp_path_factory) -> Path:
    """`ros2 run im_tuner tuner --budget 6`: the run the checks below read."""
    run = tmp_path_factory.mktemp('run6') / 'run'
    proc = tuner('--budget', '6', '--seed', '21', '--out', str(run), '--quiet')
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run


def test_without_algo_the_tuner_runs_safe_from_the_hand_tuned_start(run6):
    """``--algo`` defaults to safe with its own defaults; its evaluation 1 is the
    hand-tuned start again (the reference is the first experiment from rest), and its
    step size stays inside the trust region sigma_max = 0.08."""
    run_yaml = yaml.safe_load((run6 / 'run.yaml').read_text())
    # (auto started the simulated drive: the tuner knows it, the first step identified)
    assert run_yaml['algo'] == 'safe' and run_yaml['options'] == {'first': 'identify'}
    evals = [r for r in results(run6) if r['kind'] == 'eval']
    assert len(evals) == 6 and evals[0]['gains'] == pytest.approx(START, rel=1e-12)  # (via u)
    opt = json.loads((run6 / 'checkpoint.json').read_text())['optimizer']
    assert opt['config']['sigma0'] == 0.05 and opt['config']['sigma_max'] == 0.08
    assert 0.005 <= opt['sigma'] <= 0.08 and opt['evaluations'] == 6


def test_budget_6_bag_opens_in_rosbags_anyreader_every_message_decodes(run6):
    """AnyReader (types from the bag only, hashes checked on open) decodes every message of
    every connection with ``reader.deserialize(raw, conn.msgtype)``, service events
    included; the mcap library (CRCs checked) reads the same count, and mcap_ros2 decodes
    every ros2msg channel."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    bag = run6 / 'bag_0'
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    expected = {
        t['topic_metadata']['name']: t['message_count'] for t in meta['topics_with_message_count']
    }
    decoded: collections.Counter = collections.Counter()
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert set(conns) == set(expected)
        for conn, _t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            decoded[conn.topic] += 1
            if conn.msgtype == 'std_srvs/srv/Trigger_Event':
                assert msg.info.event_type in (0, 1, 2, 3)
    assert dict(decoded) == {t: n for t, n in expected.items() if n}
    events = [t for t in conns if t.endswith('/_service_event')]
    assert '/controller/start_experiment/_service_event' in events
    assert decoded['/controller/start_experiment/_service_event'] >= 2 * (1 + 6 + 3)
    assert decoded['/controller/set_parameters_atomically/_service_event'] >= 2 * 6
    (mcap_file,) = bag.glob('*.mcap')
    counts: collections.Counter = collections.Counter()
    factory, decoders = DecoderFactory(), {}
    with open(mcap_file, 'rb') as f:
        for schema, channel, message in make_reader(f, validate_crcs=True).iter_messages():
            counts[channel.topic] += 1
            if schema.encoding == 'ros2msg':
                if channel.id not in decoders:
                    decoders[channel.id] = factory.decoder_for('cdr', schema)
                decoders[channel.id](message.data)
            else:  # service events: IDL with rosbag2's section headers
                assert schema.encoding == 'ros2idl' and channel.topic in events
                assert schema.data.decode().startswith('=' * 80 + '\nIDL: ')
    assert counts == decoded


def test_a_corrupt_checkpoint_is_rebuilt_from_the_results(run6, tmp_path):
    """A run killed after 4 records whose checkpoint is garbage resumes from results.jsonl
    (the optimiser replayed, the plant replayed) and ends exactly as the whole run."""
    import shutil

    cut = tmp_path / 'cut'
    shutil.copytree(run6, cut, ignore=shutil.ignore_patterns('bag_*', 'report'))
    lines = (cut / 'results.jsonl').read_text().splitlines(keepends=True)
    (cut / 'results.jsonl').write_text(''.join(lines[:4]) + '{"kind": "ev')  # + a torn line
    (cut / 'summary.json').unlink()
    (cut / 'checkpoint.json').write_bytes(b'\x00garbage{')
    proc = tuner('--resume', str(cut))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (
        'checkpoint.json: not JSON' in proc.stderr and 'rebuilt from results.jsonl' in proc.stderr
    )
    _same_evaluations(results(run6), results(cut))


def test_one_tuner_per_run_directory_and_report_says_running(tmp_path, procs, wait_until):
    run = tmp_path / 'live'
    child = procs.start(
        [
            ROS2,
            'run',
            'im_tuner',
            'tuner',
            '--budget',
            '200',
            '--seed',
            '2',
            '--no-record',
            '--quiet',
            '--out',
            str(run),
        ]
    )
    res = run / 'results.jsonl'
    wait_until(lambda: res.exists() and res.read_text().count('\n') >= 2, 120, message='2 records')
    before = res.read_bytes()
    second = tuner('--resume', str(run), timeout=60)
    assert second.returncode == 2
    (line,) = second.stderr.strip().splitlines()
    assert (
        line.startswith(f'error: tuner: --resume: {run}: in use by pid ')
        and 'im_tuner' in line
        and 'tuner' in line
    ), line
    assert res.read_bytes()[: len(before)] == before  # nothing written by the refused one
    rep = report(run, '--out', str(tmp_path / 'rep_live'))
    assert rep.returncode == 0, rep.stderr[-2000:]
    assert 'outcome: running (a tuner has it: pid ' in rep.stdout
    child.send_signal(signal.SIGINT)
    assert child.wait(timeout=60) == 130
    rep = report(run, '--out', str(tmp_path / 'rep_after'))
    assert rep.returncode == 0 and 'outcome: interrupted' in rep.stdout


def test_summary_names_each_sessions_drive_line_and_the_clock(run6):
    """A resumed run's summary said 'drive (this session)' for every session, and called a
    real drive's experiment time 'simulated'."""
    from im_tuner.progress import format_summary
    from im_tuner.rundir import RunDir

    s = RunDir(run6).read_summary()
    run = RunDir(run6).read_config()
    assert s is not None and 'simulated experiment time' in format_summary(s, run, run6)
    s.sessions = [s.sessions[0], dict(s.sessions[0], bag='bag_1')]
    text = format_summary(s, run, run6)
    assert text.count('  drive (') == 2
    assert '  drive (session 1, bag_0)' in text and '  drive (this session)' in text
    run.bench = 'external'
    text = format_summary(s, run, run6)
    assert "experiment time (the drive's clock)" in text and 'simulated' not in text


def _tree(root: Path) -> dict[str, bytes | None]:
    return {
        str(p.relative_to(root)): None if p.is_dir() else p.read_bytes()
        for p in sorted(root.rglob('*'))
    }


def test_a_resume_whose_replay_does_not_match_changes_nothing(run6, tmp_path):
    """The replay of the plant history checks every loss bit for bit; when one differs
    the resume is refused (exit 2) and leaves no new bag behind (it left bag_N/)."""
    import shutil

    run = tmp_path / 'tampered'
    shutil.copytree(run6, run, ignore=shutil.ignore_patterns('bag_*', 'report'))
    lines = (run / 'results.jsonl').read_text().splitlines(keepends=True)[:4]
    last = json.loads(lines[3])
    last['loss'] *= 1.5  # the last record: told to the optimiser after its last ask
    (run / 'results.jsonl').write_text(''.join(lines[:3]) + json.dumps(last) + '\n')
    (run / 'summary.json').unlink()
    (run / 'checkpoint.json').unlink()  # rebuilt from the records
    before = _tree(run)
    proc = tuner('--resume', str(run))
    assert proc.returncode == 2, proc.stderr[-2000:]
    err = proc.stderr.strip().splitlines()
    assert err[-1].startswith('error: tuner: replay: ') and 'Traceback' not in proc.stderr
    assert _tree(run) == before


# -- what the summary tells the user ----------------------------------------------------------
def _summary(**over):
    from im_tuner.runlog import Summary

    s = {
        'outcome': 'done',
        'evaluations': 0,
        'budget': 1,
        'reference': None,
        'best': None,
        'applied': None,
        'evaluations_to_satisfactory': None,
        'satisfactory_loss': 0.85,
        'aborted': 0,
        'safety_faults': 0,
        'lost': 0,
        'timing': 0,
        'real_time_factor': None,
        'wall_s': 1.0,
        'loop_wall_s': 1.0,
        'sim_s': 0.0,
        'optimizer_us_per_eval': None,
        'sessions': [],
    }
    return Summary.from_dict(s | over)


@pytest.mark.unit
def test_a_timing_failure_says_where_to_run_the_controller():
    from im_tuner.progress import format_summary
    from im_tuner.runlog import Evaluation, Lost, RunConfig, Timing
    from im_tuner.tuner_session import failure_advice

    ok = Evaluation(eval=0, status='ok', gains={}, u=[0.5], loss=0.5, terms=[0.5], aborted=False)
    timing = [ok, Timing(kind='eval', eval=1, gains={}, off_timing_loss=0.4)]
    failed = 'failed: evaluation 1: no result after 4 attempts with the same gains (timing: ...)'
    for bench in ('realtime-processes', 'external'):
        (text,) = failure_advice(failed, timing, bench)
        assert "in the drive's process" in text and '--bench realtime --drive' in text
        assert 'did not answer every 200 us' in text
    (text,) = failure_advice(failed, timing, 'realtime')  # already composed: the host
    assert '--timing-tolerance auto' in text and '--bench realtime --drive' not in text
    assert 'host_check' in text and 'the host started periods late' in text
    check = {'late_pct': 0.25, 'tolerance': 41}
    loop = {'period_work_us': {'p50': 6.0}, 'realtime': {'host_check': check}}
    (text,) = failure_advice(failed, timing, 'realtime', loop)
    assert 'late 0.250 % of periods, 95 % of experiments meet 41' in text, text
    # a drive whose own read/write takes 1 ms: the drive is too slow, not the machine
    (text,) = failure_advice(failed, timing, 'realtime', {'period_work_us': {'p50': 1004.0}})
    assert 'the drive is too slow' in text and 'p50 1004 us of the 200 us period' in text
    assert 'host' not in text, text
    assert failure_advice('done', timing, 'external') == []
    assert failure_advice(failed, [Lost(kind='eval', eval=1, gains={})], 'external') == []
    run = RunConfig(algo='safe', seed=1, bench='realtime-processes', drive='sim')
    s = _summary(outcome=failed, what_to_do=failure_advice(failed, timing, 'external'))
    out = format_summary(s, run, Path('run'))
    assert out.splitlines()[-1].startswith('  what to do: the experiments kept coming out')


@pytest.mark.unit
def test_a_hardware_class_is_not_called_simulated_and_faults_between_experiments_count():
    from im_tuner.progress import format_summary
    from im_tuner.runlog import RunConfig

    run = RunConfig(algo='safe', seed=1, bench='realtime', drive='my_pkg.my_hw:MyHardware')
    sess = {'faults_outside': ['refused: safety fault (drive_state_timeout) [safety_fault]']}
    out = format_summary(_summary(safety_faults=1, sessions=[sess]), run, Path('run'))
    assert "experiment time (the drive's clock)" in out and 'simulated' not in out
    assert '(safety faults 1, 1 of them met between experiments)' in out
    run.drive = 'example'  # the example's stand-in plant is simulated
    assert 'simulated experiment time' in format_summary(_summary(), run, Path('run'))


def test_a_second_drive_host_on_a_domain_is_refused_in_one_line(
    tmp_path, procs, ros_context, wait_until
):
    """Two drives on one ROS domain would each take the other's controller's commands:
    a drive host that finds another drive there refuses to start (exit 2, one line,
    nothing created)."""
    from rclpy.node import Node

    first = procs.start([ROS2, 'run', 'im_tuner', 'drive_host', '--no-record'])
    probe = Node('probe', context=ros_context)
    try:
        wait_until(lambda: probe.count_publishers('/drive/state') > 0, 120, message='host 1')
    finally:
        probe.destroy_node()
    second = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'drive_host', '--out', str(tmp_path / 'bag2')],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert second.returncode == 2, second.stderr[-2000:]
    (line,) = [ln for ln in second.stderr.splitlines() if ln.startswith('error:')]
    assert 'a drive host or drive already runs here' in line, second.stderr[-2000:]
    assert 'Traceback' not in second.stderr and not (tmp_path / 'bag2').exists()
    assert first.poll() is None  # the first host runs on


def test_the_identified_first_step_models_the_drive_file_given(tmp_path):
    """``--drive-config NAME``: the first step is computed on NAME's model identified from
    the start (not the packaged default's), the identification says NAME's J and Kt, and
    the step beats the start (im7500w-j10: J 0.3773 kg m^2, 150x the default's)."""
    from im_drive_sim.drive_file import load_config

    run = tmp_path / 'run'
    p = tuner(
        '--drive-config', 'im7500w-j10', '--budget', '2', '--seed', '1', '--remeasure', '0',
        '--no-record', '--quiet', '--out', str(run),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-3000:]
    m = load_config('im7500w-j10').machine
    idf = json.loads((run / 'summary.json').read_text())['identification']
    assert (idf['J_file'], idf['Kt_file']) == (m.J, m.Kt), idf
    assert abs(idf['J'] / m.J - 1.0) < 0.05, idf
    recs = results(run)
    start = next(r['loss'] for r in recs if r['kind'] == 'reference')
    first = [r for r in recs if r.get('eval') == 1 and r['status'] == 'ok']
    assert first and first[0]['loss'] < 0.8 * start, (start, first)
