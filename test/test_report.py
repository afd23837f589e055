"""The report end to end: ``ros2 run im_tuner report`` on short real tuner runs.

Two short runs (SPSA and neCGA, 8 evaluations each) are made with the real tuner on
the in-process simulated bench; the report command the tuner prints is run as printed.
The figures are checked on their plotted data: each line against results.jsonl or
against the bag read by the ``mcap`` library (an independent reader), and against the
physics of the experiment (a pi rad move, the load step at 0.7 s). The CSV round-trips
exactly. An interrupted run (results cut mid-line, bag without footer, no summary) and
directories that are not runs are covered too.
"""

from __future__ import annotations

import hashlib
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

from im_tuner.report import (
    CSV_COLUMNS,
    FIGURES,
    load_run,
    make_figures,
    read_csv,
    summary_text,
    write_csv,
)

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
GAINS = ('k_pw', 'k_iw', 'k_pos', 'tau_sm', 'tau_eq')
BUDGET = 8


def run_cmd(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [ROS2, 'run', 'im_tuner', *args], capture_output=True, text=True, timeout=timeout
    )


def results(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / 'results.jsonl').read_text().splitlines()]


def internals_from_mcap(bag: Path) -> np.ndarray:
    """Every controller/internals row, read with the mcap library."""
    (path,) = bag.glob('*.mcap')
    rows = []
    with open(path, 'rb') as f:
        for _s, _c, m in make_reader(f).iter_messages(topics=['/controller/internals']):
            n = int.from_bytes(m.data[12:16], 'little')
            rows.append(np.frombuffer(m.data, '<f8', n, 20))
    return np.array(rows)


def tree_hashes(d: Path) -> dict[str, str]:
    return {
        str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(d.rglob('*'))
        if p.is_file()
    }


@pytest.fixture(scope='module')
def runs(tmp_path_factory) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    base = tmp_path_factory.mktemp('runs')
    out = {}
    for algo, seed in (('spsa', 3), ('necga', 5)):
        run = base / f'{algo}_run'
        proc = run_cmd(
            'tuner',
            '--algo',
            algo,
            '--budget',
            str(BUDGET),
            '--seed',
            str(seed),
            '--out',
            str(run),
            '--quiet',
            *('--discovery-timeout', '0.2'),  # no controller on the graph: no 2 s look
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        out[algo] = (run, proc)
    return out


def test_the_printed_report_command_writes_summary_plots_and_csv(runs):
    run, proc = runs['necga']
    line = next(x for x in proc.stdout.splitlines() if 'ros2 run im_tuner report' in x)
    cmd = shlex.split(line[line.index('CSV): ') + 6 :])
    # ros2 as the shell that ran the tuner finds it: on its PATH, else this venv's own
    assert Path(cmd[0]).name == 'ros2' and cmd[1:4] == ['run', 'im_tuner', 'report'], cmd
    assert Path(cmd[4]) == run
    before = tree_hashes(run)
    # the printed command, as printed, from the directory the tuner ran in
    rep = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert rep.returncode == 0, rep.stderr[-3000:]
    out = run / 'report'
    for name in FIGURES:
        png = out / f'{name}.png'
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 20_000
    import matplotlib.image

    assert matplotlib.image.imread(out / 'fig8_best_vs_start.png').shape[0] > 600
    recs = results(run)
    assert len(read_csv(out / 'evaluations.csv')) == len(recs)
    # the summary: printed and kept; the report changed nothing else in the run
    text = (out / 'summary.txt').read_text()
    assert text in rep.stdout
    summary = json.loads((run / 'summary.json').read_text())
    best = summary['best']
    assert f'best loss: {best["loss"]:.4f} (evaluation {best["eval"] + 1}' in text
    assert f'{summary["evaluations"]}/{BUDGET} evaluations' in text
    assert f'aborted experiments: {summary["aborted"]} of {BUDGET}' in text
    sat = summary['evaluations_to_satisfactory']
    assert (f'after {sat} evaluations' if sat else 'not reached') in text
    assert f'losses in the bags vs results.jsonl: {len(recs)} equal' in text
    meta = yaml.safe_load((run / 'bag_0' / 'metadata.yaml').read_text())
    counts = json.loads(meta['rosbag2_bagfile_information']['custom_data']['im_tuner.counts'])
    n_state = counts['/drive/state']['recorded']
    assert f'{n_state} / {n_state} ok' in text and '/drive/state' in text
    assert 'bag_0: closed;' in text
    after = tree_hashes(run)
    assert {k: v for k, v in after.items() if not k.startswith('report/')} == before


def test_figures_show_what_their_captions_say(runs):
    run, _ = runs['necga']
    rr = load_run(run, 'necga')
    figs = make_figures([rr])
    recs = results(run)
    cfg = yaml.safe_load((run / 'run.yaml').read_text())
    params = cfg['controller_parameters']
    fields = params['internals_fields']
    col = {n: i for i, n in enumerate(fields)}
    rows = internals_from_mcap(run / 'bag_0')
    evals = [r for r in recs if r['kind'] == 'eval']

    def line(fig, gid):
        found = [ln for ax in fig.axes for ln in ax.get_lines() if ln.get_gid() == gid]
        assert len(found) == 1, gid
        return found[0]

    # Fig. 9 (a, b): every evaluation's loss, the best so far, the satisfactory level
    f9 = figs['fig9_loss']
    assert f9.axes[0].get_ylabel() == 'loss'
    assert f9.axes[0].get_xlabel() == 'evaluation (numbered from 0, as in the summary)'
    ok = [r for r in evals if not r['aborted']]
    x, y = line(f9, 'loss:necga').get_data()
    assert list(x) == [r['eval'] for r in ok] and list(y) == [r['loss'] for r in ok]
    bx, by = line(f9, 'best:necga').get_data()
    assert list(bx) == list(range(BUDGET))
    # the legend beside the axes, where it hides no point (an aborted penalty is the top)
    legend = f9.axes[0].get_legend()
    assert legend.get_bbox_to_anchor().x0 >= f9.axes[0].get_window_extent().x1
    assert [None if np.isnan(v) else v for v in by] == [r['best_loss'] for r in evals]
    assert line(f9, 'satisfactory').get_ydata()[0] == cfg['satisfactory_loss']
    assert line(f9, 'start').get_ydata()[0] == recs[0]['loss']
    # Fig. 9 (c, d): each gain's path, in its unit, inside the search box
    g9 = figs['fig9_gains']
    assert [ax.get_ylabel() for ax in g9.axes] == [
        'k_pw [A s/rad]',
        'k_iw [A/rad]',
        'k_pos [1/s]',
        'tau_sm [s]',
        'tau_eq [s]',
    ]
    for n in GAINS:
        gx, gy = line(g9, f'{n}:necga').get_data()
        assert list(gx) == [r['eval'] for r in evals]
        assert list(gy) == [r['gains'][n] for r in evals]
        assert line(g9, f'start:{n}').get_ydata()[0] == cfg['search_box'][n]['start']
    # Fig. 8: the best evaluation's and the start controller's experiments, from the bag
    f8 = figs['fig8_best_vs_start']
    assert [ax.get_ylabel() for ax in f8.axes] == [
        'position error [rad]',
        'speed error [rad/s]',
        'current reference i*sq [A]',
    ]
    best = min(ok, key=lambda r: r['loss'])
    for rec, who in ((best, 'best:necga'), (recs[0], 'start:necga')):
        k0 = rec['t_start_ns'] // 200_000
        want = rows[(rows[:, 0] >= k0) & (rows[:, 0] < k0 + rec['steps'])]
        assert len(want) == rec['steps'] == 5625
        assert want[:, col['exp_step']].tolist() == list(range(5625))
        for name in ('e_theta', 'e_omega', 'isq_ref'):
            t, v = line(f8, f'{name}:{who}').get_data()
            np.testing.assert_array_equal(v, rec['direction'] * want[:, col[name]])
            np.testing.assert_allclose(t, np.arange(5625) * 200e-6, rtol=0, atol=1e-12)
        # physics: the current reference holds the load (1.75 N m opposing the move)
        # after the step at 0.7 s, so it has the sign of the move; the position error
        # has settled at the end
        _t, isq = line(f8, f'isq_ref:{who}').get_data()
        k_step = int(params['trajectory.load_delay'] / 200e-6)
        assert abs(np.median(isq[k_step - 500 : k_step])) < 0.2  # at rest, no load
        assert np.median(isq[k_step + 1000 :]) > 1.0  # holding the load
        _t, e = line(f8, f'e_theta:{who}').get_data()
        assert abs(e[-1]) < 0.01
    # Fig. 5: two consecutive experiments: a pi rad move there and back, the load step
    f5 = figs['fig5_trajectory']
    assert f5.axes[0].get_ylabel().startswith('position reference')
    assert f5.axes[1].get_ylabel() == 'load torque [N m]'
    dist, t_load = params['trajectory.distance'], params['trajectory.load_delay']
    torque, dur = params['trajectory.load_torque'], params['trajectory.duration']
    # the second starts after the first's end and its own 0.5 s settle (docs/controller.md)
    gap = dur + params['trajectory.settle']
    for j, sign in ((0, 1), (1, -1)):
        t, th = line(f5, f'theta_ref:{j}').get_data()
        assert t[0] == pytest.approx(j * gap) and len(t) == 5625
        assert th[0] == pytest.approx(0 if j == 0 else dist, abs=1e-9)
        assert th[-1] == pytest.approx(dist if j == 0 else 0, abs=1e-9)
        assert np.all(np.diff(th) * sign >= -1e-12)  # monotonic move
        _t, load = line(f5, f'load:{j}').get_data()
        before = (t - j * gap) < t_load - 1e-6
        assert np.all(load[before] == 0)
        # 'oppose_move': a positive load torque opposes positive rotation
        # (docs/interfaces.md), so the command carries the move's sign
        assert np.all(load[~before] == sign * torque)


def test_csv_round_trip(runs, tmp_path):
    run, _ = runs['spsa']
    rr = load_run(run, 'spsa', signals=False)
    path = tmp_path / 'e.csv'
    assert write_csv([rr], path) == len(rr.records)
    back = read_csv(path)
    with open(path) as f:
        assert f.readline().strip().split(',') == list(CSV_COLUMNS)
    best = None  # the best non-aborted evaluation loss so far (evaluation rows only)
    for rec, row in zip(results(run), back, strict=True):
        assert row['run'] == 'spsa' and row['bag'] == 'bag_0'
        # the columns that are a field of the line each (the rest: below)
        scalar = [c for c in CSV_COLUMNS if c in rec and c != 'best_loss']
        assert len(scalar) == 17
        for k in scalar:
            want = rec[k] if rec[k] != '' else None
            assert row[k] == want, k
        # (a lost or off-timing record has no terms: empty cells)
        assert [row['term1'], row['term2'], row['term3']] == (rec['terms'] or [None] * 3)
        assert {n: row[n] for n in GAINS} == rec['gains']
        assert [row[f'u{i}'] for i in range(5)] == (rec['u'] or [None] * 5)
        if rec['kind'] == 'eval' and rec['status'] == 'ok':
            best = rec['loss'] if best is None else min(best, rec['loss'])
        assert row['best_loss'] == (best if rec['kind'] == 'eval' else None)
        if 'best_loss' in rec:  # a measured evaluation's own record says the same
            assert row['best_loss'] == rec['best_loss']


def test_several_runs_overlaid(runs, tmp_path):
    out = tmp_path / 'cmp'
    proc = run_cmd('report', str(runs['spsa'][0]), str(runs['necga'][0]), '--out', str(out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = read_csv(out / 'evaluations.csv')
    assert {r['run'] for r in rows} == {'spsa seed 3', 'necga seed 5'}
    assert proc.stdout.count('\nrun ') + proc.stdout.startswith('run ') == 2
    rrs = [load_run(runs['spsa'][0], 'spsa'), load_run(runs['necga'][0], 'necga')]
    figs = make_figures(rrs)
    gids = {
        ln.get_gid()
        for f in figs.values()
        for ax in f.axes
        for ln in ax.get_lines()
        if ln.get_gid()
    }
    for label in ('spsa', 'necga'):
        assert {f'best:{label}', f'loss:{label}', f'k_pw:{label}', f'e_theta:best:{label}'} <= gids
    # both runs start from the same hand-tuned gains: one start curve, not two
    assert sum(g.startswith('e_theta:start:') for g in gids) == 1


def test_interrupted_run_is_reported_from_what_it_left(runs, tmp_path):
    """A copy of a finished run made to look killed: the last results line torn, no
    summary.json, the bag cut in a chunk with no footer and metadata still 'recording'."""
    src, _ = runs['spsa']
    run = tmp_path / 'killed'
    shutil.copytree(src, run)
    shutil.rmtree(run / 'report', ignore_errors=True)
    (run / 'summary.json').unlink()
    lines = (run / 'results.jsonl').read_text().splitlines(keepends=True)
    keep = 7
    (run / 'results.jsonl').write_text(''.join(lines[:keep]) + lines[keep][:40])
    (mcap,) = (run / 'bag_0').glob('*.mcap')
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    meta_path = run / 'bag_0' / 'metadata.yaml'
    meta = yaml.safe_load(meta_path.read_text())
    meta['rosbag2_bagfile_information']['custom_data'] = {'im_tuner.state': 'recording'}
    meta_path.write_text(yaml.safe_dump(meta))
    before = tree_hashes(run)
    proc = run_cmd('report', str(run))
    assert proc.returncode == 0, proc.stderr[-3000:]
    after = {k: v for k, v in tree_hashes(run).items() if not k.startswith('report/')}
    assert after == before  # the torn line and the cut bag are left as they were
    out = proc.stdout
    assert 'outcome: interrupted' in out and f'{keep - 1}/{BUDGET} evaluations' in out
    assert 'NOT CLOSED' in out and 'not known (bag not closed by the recorder)' in out
    assert len(read_csv(run / 'report' / 'evaluations.csv')) == keep
    for name in FIGURES:
        assert (run / 'report' / f'{name}.png').stat().st_size > 10_000
    rr = load_run(run, 'k')
    assert rr.summary_source == 'results.jsonl' and rr.reference is not None
    # the loss messages found in the half bag equal the records; later ones are missing
    c = rr.loss_check
    assert c['differ'] == 0 and c['matched'] >= 1 and c['matched'] + c['missing'] == keep
    assert rr.summary.outcome == 'interrupted (killed: no final summary)'
    # a summary.json that does not match the records (an earlier session's) or is not one
    # (damaged: it is written atomically, not torn by a kill): the outcome says which
    shutil.copy(src / 'summary.json', run / 'summary.json')
    o = load_run(run, 'k', signals=False).summary.outcome
    assert o.startswith(f'interrupted (killed: summary.json counts {BUDGET} evaluations'), o
    assert o.endswith(f'results.jsonl {keep - 1} and {keep})'), o
    (run / 'summary.json').write_text('{"not": json')
    o = load_run(run, 'k', signals=False).summary.outcome
    assert o == 'not known (summary.json is not a summary; rebuilt from results.jsonl)'


@pytest.mark.parametrize(
    'make, expect',
    [
        (lambda d: d / 'nothing_here', 'not a directory'),
        (lambda d: (d / 'empty').mkdir() or d / 'empty', 'not a tuning run (no run.yaml)'),
        (lambda d: (d / 'file.txt').write_text('x') and d / 'file.txt', 'not a directory'),
    ],
)
def test_not_a_run_one_line_exit_2(tmp_path, make, expect):
    target = make(tmp_path)
    before = sorted(p.name for p in tmp_path.rglob('*'))
    proc = run_cmd('report', str(target))
    assert proc.returncode == 2 and proc.stdout == ''
    assert proc.stderr.count('\n') == 1 and expect in proc.stderr, proc.stderr
    assert proc.stderr.startswith('error: report: ')
    assert sorted(p.name for p in tmp_path.rglob('*')) == before


def test_a_bag_directory_is_not_a_run_and_bad_options_are_refused(runs, tmp_path):
    run, _ = runs['necga']
    for args, expect in (
        ([str(run / 'bag_0')], f'a bag: its run is {run}, its statistics `report --bag-info'),
        ([], 'the following arguments are required: RUN_DIR'),
        ([str(run), '--plots'], 'unrecognized arguments: --plots'),
        ([str(run), '--out', str(run / 'run.yaml')], 'is not a directory'),
    ):
        proc = run_cmd('report', *args)
        assert proc.returncode == 2 and proc.stderr.count('\n') == 1, proc.stderr
        assert expect in proc.stderr, proc.stderr


def test_an_external_bench_is_not_called_simulated(runs, tmp_path):
    """On an external bench (``--bench none``) or with a hardware class in the
    loop the experiment time is the drive's clock, and the summary says so; a simulated
    bench (the simulator, or the example drive's stand-in) says simulated."""
    src, _ = runs['necga']
    sim_s = json.loads((src / 'summary.json').read_text())['sim_s']
    sim_line = f'simulated experiment time {sim_s:.1f} s'
    real_line = f"experiment time (the drive's clock) {sim_s:.1f} s"
    for bench, drive, simulated in (
        ('inproc', 'sim', True),
        ('realtime', 'example', True),
        ('none', 'sim', False),
        ('none', None, False),
        ('realtime', 'my_pkg.hw:Hardware', False),
    ):
        run = tmp_path / f'{bench}_{drive}'
        shutil.copytree(src, run, ignore=shutil.ignore_patterns('report'))
        cfg = yaml.safe_load((run / 'run.yaml').read_text())
        cfg['bench'], cfg['drive'] = bench, drive
        (run / 'run.yaml').write_text(yaml.safe_dump(cfg, sort_keys=False))
        text = summary_text(load_run(run, 'x', signals=False))
        assert (sim_line in text, real_line in text) == (simulated, not simulated), text
        assert ('simulat' in text) == simulated, (bench, drive)
    # the command, as printed, on the external bench
    proc = run_cmd('report', str(tmp_path / 'none_sim'))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert real_line in proc.stdout and 'simulat' not in proc.stdout


def test_the_report_imports_no_rclpy_and_no_optimiser(runs, tmp_path):
    """A whole report (bags read, figures drawn) needs none of rclpy, pycma, optuna, dask
    or scipy's statistics and optimisers (numba imports scipy's base package itself)."""
    run, _ = runs['spsa']
    code = (
        'import contextlib, io, json, sys\n'
        'from im_tuner.report.cli import main\n'
        'quiet = io.StringIO()\n'
        'with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):\n'
        '    code = main(sys.argv[1:])\n'
        'print(json.dumps([code, sorted(sys.modules)]))\n'
    )
    proc = subprocess.run(
        [sys.executable, '-c', code, str(run), '--out', str(tmp_path / 'rep')],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    code, modules = json.loads(proc.stdout)
    assert code == 0 and 'matplotlib' in modules and 'im_tuner.record.reader' in modules
    for name in ('rclpy', 'cma', 'optuna', 'dask', 'scipy.stats', 'scipy.optimize'):
        assert name not in modules, name
    for name in FIGURES:  # the two processes drew all four
        assert (tmp_path / 'rep' / f'{name}.png').stat().st_size > 20_000
