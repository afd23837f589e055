"""The offline study, ``ros2 run im_tuner study``: a run of the study is a tuner run.

* A sample of study runs, re-run through the ROS node network with the tuner command the
  study wrote for them (``runs.csv``), gives the same losses bit for bit: reference,
  every evaluation (aborted ones included) and the re-measurement.
* Results do not depend on the number of workers; the seeds are shared across
  configurations; L_ref is the hand-tuned start's loss.
* The command writes its tables (paper values beside), CSV, figures, markdown; ``--from``
  re-tabulates without new experiments; bad input: one line, exit 2, nothing written.
"""

from __future__ import annotations

import csv
import hashlib
import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from im_tuner.study import runs as S
from im_tuner.study.results import load
from im_tuner.study.stats import PAPER

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
START_LOSS = 0.9803040260343194  # experiment 0 of the hand-tuned start (test_controller_node)


def study(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [ROS2, 'run', 'im_tuner', 'study', *args], capture_output=True, text=True, timeout=timeout
    )


def results(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / 'results.jsonl').read_text().splitlines()]


@pytest.fixture(scope='module')
def small(tmp_path_factory):
    """A 4-run, 8-evaluation study of the whole grid, through the command."""
    out = tmp_path_factory.mktemp('study') / 'small'
    proc = study('--runs', '4', '--budget', '8', '--jobs', '2', '--out', str(out))
    assert proc.returncode == 0, proc.stderr
    return out, proc


def run_tuner(command: str, run: Path) -> list[dict]:
    """Run a study's tuner command (through the ROS nodes) into ``run``; its records."""
    cmd = shlex.split(command)
    assert cmd[:4] == ['ros2', 'run', 'im_tuner', 'tuner']
    proc = subprocess.run(
        # (no controller on the test's graph: auto need not look for one for 2 s)
        [ROS2, *cmd[1:], '--out', str(run), '--quiet', '--discovery-timeout', '0.2'],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return [x for x in results(run) if x['status'] != 'lost']


def assert_same_run(
    recs: list[dict],
    *,
    budget: int,
    ref_loss: float,
    start,
    losses,
    aborted,
    faults,
    best_eval: int,
    remeasured: float,
) -> None:
    """The tuner's records equal the study's run bit for bit."""
    ref = [x for x in recs if x['kind'] == 'reference']
    evals = [x for x in recs if x['kind'] == 'eval']
    rem = [x for x in recs if x['kind'] == 'remeasure']
    assert len(ref) == 1 and len(evals) == budget and len(rem) == (best_eval >= 0)
    assert ref[0]['loss'] == ref_loss
    assert tuple(ref[0]['gains'].values()) == tuple(start)
    assert [x['loss'] for x in evals] == list(losses)
    assert [x['aborted'] for x in evals] == list(aborted)
    assert [x['fault'] for x in evals] == list(faults)
    if best_eval >= 0:  # (a run in which everything was aborted has nothing to re-measure)
        assert rem[0]['eval'] == best_eval and rem[0]['loss'] == remeasured


def test_study_runs_through_the_ros_nodes_give_the_same_losses(small, tmp_path):
    out, _ = small
    res = load(out)
    rows = list(csv.DictReader((out / 'runs.csv').open()))
    cells = {c.label: i for i, c in enumerate(res.cells)}
    # the sample: the SPSA run of the paper's cell with the most aborted experiments (that
    # still has a final controller), and the neCGA run of the paper's cell with the most
    spsa = [r for r in rows if r['config'] == 'a=0.0183 c=0.03' and int(r['best_eval']) >= 0]
    pick = [max(spsa, key=lambda r: (int(r['aborted']), -int(r['run'])))]
    necga = [r for r in rows if r['config'] == 'n=25 eta=12']
    pick.append(max(necga, key=lambda r: (int(r['aborted']), -int(r['run']))))
    sampled_aborts = 0
    for row in pick:
        c, r = cells[row['config']], int(row['run'])
        recs = run_tuner(row['tuner_command'], tmp_path / f'{row["algo"]}_{r}')
        assert_same_run(
            recs,
            budget=res.spec.budget,
            ref_loss=res.ref_loss[c, r],
            start=res.start[c, r],
            losses=res.losses[c, r].tolist(),
            aborted=res.aborted[c, r].tolist(),
            faults=res.faults[c, r].tolist(),
            best_eval=res.best_eval[c, r],
            remeasured=res.remeasured[c, r],
        )
        sampled_aborts += int(res.aborted[c, r].sum())
    # the sample exercises the supervisor's stop and the fallback's finishing move
    assert sampled_aborts >= 1


def test_results_do_not_depend_on_the_number_of_workers(small):
    out, _ = small
    via_cli = load(out)  # 2 workers
    spec = S.StudySpec(runs=2, budget=8)
    one = S.run_study(spec, jobs=1)
    for name in S.StudyResult.ARRAYS:
        if name in ('opt_s', 'exp_s'):
            continue  # wall-clock timing
        a, b = getattr(one, name), getattr(via_cli, name)
        b = b[:, :2] if b.ndim >= 2 else b[:2]
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert one.l_ref == via_cli.l_ref


def test_tables_are_identical_for_any_number_of_workers(tmp_path):
    files = {}
    for jobs in ('1', '2'):
        out = tmp_path / f'jobs{jobs}'
        proc = study('--runs', '2', '--budget', '4', '--jobs', jobs, '--out', str(out), '--quiet')
        assert proc.returncode == 0, proc.stderr
        files[jobs] = {
            n: (out / n).read_text().replace(str(out), 'OUT') for n in ('tables.csv', 'runs.csv')
        }
    assert files['1'] == files['2']


def test_a_dask_cluster_gives_byte_identical_tables(tmp_path):
    """The study on a Dask LocalCluster of 2 worker processes equals --jobs 1,
    byte for byte, for the paper's algorithm and three beyond it."""
    from distributed import LocalCluster

    args = ('--runs', '2', '--budget', '6', '--algos', 'necga,cmaes,tpe,safe', '--quiet')
    one = tmp_path / 'jobs1'
    proc = study(*args, '--jobs', '1', '--out', str(one))
    assert proc.returncode == 0, proc.stderr
    dsk = tmp_path / 'dask'
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as lc:
        proc = study(*args, '--cluster', lc.scheduler_address, '--out', str(dsk))
    assert proc.returncode == 0, proc.stderr
    assert (one / 'tables.csv').read_bytes() == (dsk / 'tables.csv').read_bytes()
    a, b = ((d / 'runs.csv').read_text().replace(str(d), 'OUT') for d in (one, dsk))
    assert a == b
    assert json.loads((dsk / 'study.json').read_text())['jobs'] == 2  # the cluster's threads


def test_seeds_starts_and_the_normalisation(small):
    res = load(small[0])
    spsa = [i for i, c in enumerate(res.cells) if c.algo == 'spsa']
    necga = [i for i, c in enumerate(res.cells) if c.algo == 'necga']
    # SPSA: a random start per run, the same in every SPSA cell (common random numbers)
    starts = res.start[spsa]
    assert np.all(starts == starts[0])
    assert len({tuple(s) for s in starts[0]}) == res.spec.runs
    # neCGA: the hand-tuned start, so its reference experiment is the one from rest
    assert np.all(res.start[necga] == np.array([0.53, 20.0, 30.0, 0.005, 0.007]))
    assert np.all(res.ref_loss[necga] == START_LOSS)
    # L_ref: the hand-tuned start in the experiments after the first; each starts after
    # its standstill settle, so they read as the first one from rest does, within the
    # bench's noise (docs/controller.md: 0.979-0.981; 1.121 without the settle)
    assert res.l_first == START_LOSS
    assert abs(res.l_ref - START_LOSS) < 0.005 and res.l_ref_sem < 1e-3
    assert len(set(res.run_seed.tolist())) == res.spec.runs


def test_outputs_tables_figures_and_paper_values(small):
    out, proc = small
    for name in (
        'tables.txt',
        'tables.csv',
        'runs.csv',
        'tables.png',
        'convergence.png',
        'reproduction.md',
        'study.npz',
        'study.json',
        'starts/run_000.yaml',
    ):
        assert (out / name).is_file(), name
    text = proc.stdout
    assert text.startswith((out / 'tables.txt').read_text())
    for title in ('Table I', 'Table II', 'Table III'):
        assert title in text
    assert '| 0.70' in text and '| 92' in text  # the paper's n=25 values beside ours
    assert "The paper's conclusions in simulation" in text
    # tables.csv carries the paper's value of every cell
    rows = list(csv.DictReader((out / 'tables.csv').open()))
    final = {
        (r['algo'], int(r['row']), int(r['col'])): float(r['paper'])
        for r in rows
        if r['statistic'] == 'final'
    }
    assert final == PAPER['final']
    # the figure shows the paper's values and ours
    from im_tuner.study.figures import fig_tables
    from im_tuner.study.stats import compute

    st = compute(load(out))
    fig = fig_tables(st)
    ax = fig.axes[0]
    paper = next(ln for ln in ax.lines if ln.get_gid() == 'paper:final')
    np.testing.assert_array_equal(
        paper.get_ydata(), [PAPER['final'][(c.algo, c.row, c.col)] for c in st.res.cells]
    )
    ours = [c.final.value for c in st.cells]
    heights = [b.get_height() for b in ax.containers[0]]
    np.testing.assert_allclose(heights, np.nan_to_num(ours))
    md = (out / 'reproduction.md').read_text()
    assert "## Which of the paper's conclusions hold in simulation" in md


def test_from_retabulates_without_new_experiments(small, tmp_path):
    out, _ = small
    h = hashlib.sha256((out / 'study.npz').read_bytes()).hexdigest()
    dst = tmp_path / 'loose'
    proc = study('--from', str(out), '--satisfactory', '1.5', '--out', str(dst))
    assert proc.returncode == 0, proc.stderr
    assert hashlib.sha256((out / 'study.npz').read_bytes()).hexdigest() == h
    strict = list(csv.DictReader((out / 'tables.csv').open()))
    loose = list(csv.DictReader((dst / 'tables.csv').open()))

    def pct(rows):
        return [float(r['value']) for r in rows if r['statistic'] == 'satisfactory']

    assert all(b >= a for a, b in zip(pct(strict), pct(loose), strict=True))
    assert sum(pct(loose)) > sum(pct(strict))
    assert {r['threshold'] for r in loose} == {'1.5'}


@pytest.mark.parametrize(
    'args, expect',
    [
        (['--runs', '0'], '--runs must be an integer >= 1'),
        (['--budget', '-3'], 'argument --budget: must be >= 1, got -3'),
        (['--algos', 'spsa,foo'], "no study grid for 'foo'"),
        (['--jobs', '0'], 'argument --jobs: must be >= 1, got 0'),
        (['--model', 'exact'], "invalid choice: 'exact'"),
        (['--satisfactory', '-1'], '--satisfactory must be a normalised loss > 0'),
        (['--seed', '-2'], 'argument --seed: must be >= 0, got -2'),
        (['--from', '/nonexistent/study'], 'not a study directory'),
        (['--params', '/nonexistent.yaml'], 'cannot read'),
        (['--cluster', 'localhost'], 'Dask scheduler address tcp://HOST:PORT'),
        (['--cluster', 'tcp://127.0.0.1:8786', '--jobs', '2'], 'exclude each other'),
    ],
)
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, args, expect):
    out = tmp_path / 'never'
    proc = study(*args, '--out', str(out), timeout=60)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: study: ') and expect in lines[0], (
        proc.stderr
    )
    assert not out.exists()


def test_refuses_to_overwrite_a_study(small):
    out, _ = small
    proc = study('--runs', '1', '--budget', '1', '--out', str(out), timeout=60)
    assert proc.returncode == 2 and 'already holds a study' in proc.stderr
