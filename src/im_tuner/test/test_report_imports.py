"""The report's start-up: what ``ros2 run im_tuner report`` imports before it has a run.

``--help`` and a refusal must answer without the heavy modules (they took 2.9 s
when the report's text pulled the tuner's command line, rclpy, and the optimisers with
pycma, optuna and scipy). Each check runs in a fresh interpreter and reads
``sys.modules`` (a module list, not a wall time: speed is measured in
benchmarks/bench_report.py). Also: the bench modes the report uses to say whether the drive
was simulated agree with the tuner's own.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

#: never imported by the report's command line before it has a run to read
HEAVY = ('rclpy', 'matplotlib', 'cma', 'scipy', 'optuna', 'dask', 'numba', 'numpy')

_PROBE = """
import contextlib, io, json, sys
from im_tuner.report.cli import main
out, err = io.StringIO(), io.StringIO()
with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
    try:
        code = main(json.loads(sys.argv[1]))
    except SystemExit as exc:  # argparse's --help
        code = exc.code
heavy = json.loads(sys.argv[2])
print(json.dumps({
    'code': code,
    'stdout': out.getvalue(),
    'stderr': err.getvalue(),
    'loaded': sorted({m.split('.')[0] for m in sys.modules} & set(heavy)),
}))
"""


def _probe(args: list[str]) -> dict:
    proc = subprocess.run(
        [sys.executable, '-c', _PROBE, json.dumps(args), json.dumps(HEAVY)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_help_imports_nothing_heavy():
    r = _probe(['--help'])
    assert r['code'] == 0 and r['loaded'] == []
    assert r['stdout'].startswith('usage: ros2 run im_tuner report') and 'RUN_DIR' in r['stdout']


@pytest.mark.parametrize(
    'args, expect',
    [
        (['/nonexistent/run'], '/nonexistent/run: not a directory'),
        ([], 'the following arguments are required: RUN_DIR'),
        (['.', '--plots'], 'unrecognized arguments: --plots'),
    ],
)
def test_a_refusal_imports_nothing_heavy(tmp_path, args, expect):
    r = _probe([str(tmp_path) if a == '.' else a for a in args])
    assert r['code'] == 2 and r['stdout'] == '' and r['loaded'] == []
    assert r['stderr'].startswith('error: report: ') and expect in r['stderr']
    assert r['stderr'].count('\n') == 1


def test_not_a_run_is_refused_before_anything_heavy(tmp_path):
    """A directory without run.yaml: refused after reading it, still nothing heavy."""
    r = _probe([str(tmp_path)])
    assert r['code'] == 2 and 'not a tuning run (no run.yaml)' in r['stderr']
    assert r['loaded'] == []


def test_the_package_names_load_on_first_use():
    code = (
        'import json, sys\n'
        'import im_tuner.report as rep\n'
        'before = sorted(m for m in sys.modules if m.startswith("im_tuner.report."))\n'
        'names = sorted(n for n in rep.__all__ if getattr(rep, n) is None)\n'
        'print(json.dumps([before, names, "write_csv" in dir(rep), rep.FIGURES]))\n'
    )
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    before, none_names, listed, figures = json.loads(proc.stdout)
    assert before == []  # importing the package imports none of its modules
    assert none_names == [] and listed  # every public name resolves
    assert figures == ['fig5_trajectory', 'fig8_best_vs_start', 'fig9_loss', 'fig9_gains']
    import im_tuner.report as rep

    with pytest.raises(AttributeError):
        rep.no_such_name  # noqa: B018
    from im_tuner.report.load import ReportError as FromLoad

    assert rep.ReportError is FromLoad  # one exception class, wherever it is imported from


def test_bench_modes_have_one_copy_the_tuner_imports():
    from im_tuner import benches, tuner_args, tuner_cli

    assert tuner_args.BENCHES is benches.BENCHES  # --bench's choices
    for name in ('SIM_BENCHES', 'IN_PROCESS_BENCHES', 'LOCKSTEP_BENCHES', 'is_simulated'):
        # the tuner's command line keeps no copy of its own
        for mod in (tuner_args, tuner_cli):
            assert getattr(mod, name, getattr(benches, name)) is getattr(benches, name), name
    # an external bench is never simulated; nor is a hardware class in the loop
    assert not benches.is_simulated('none', 'sim')
    assert not benches.is_simulated('external', 'sim')
    assert not benches.is_simulated('realtime', 'my_pkg.hw:Hardware')
    assert benches.is_simulated('inproc', None) and benches.is_simulated('realtime', 'example')


_NO_ROS_PROBE = """
import importlib, json, pkgutil, sys
names = []
for pkg in json.loads(sys.argv[1]):
    mod = importlib.import_module(pkg)
    names.append(pkg)
    for info in pkgutil.walk_packages(getattr(mod, '__path__', []), pkg + '.'):
        if info.name.endswith('.__main__'):
            continue  # runs the command line
        importlib.import_module(info.name)
        names.append(info.name)
ros = sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rosidl_runtime_py'))
print(json.dumps({'modules': names, 'ros': ros}))
"""


@pytest.mark.parametrize(
    'packages',
    [
        ['im_tuner.report', 'im_tuner.study'],
        ['im_tuner.runlog', 'im_tuner.rundir', 'im_tuner.tuning', 'im_tuner.bench.spec'],
    ],
    ids=['report+study', 'run log, tuning, bench spec'],
)
def test_every_module_of_the_pure_side_imports_no_rclpy(packages):
    """The report, the study, the run log and the bench spec load no rclpy, each
    of their modules imported (not only the package names)."""
    proc = subprocess.run(
        [sys.executable, '-c', _NO_ROS_PROBE, json.dumps(packages)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r['ros'] == [], r['ros']
    assert len(r['modules']) >= len(packages)
    if 'im_tuner.study' in packages:  # walked, not only the package names
        assert {'im_tuner.report.load', 'im_tuner.study.runs', 'im_tuner.study.cli'} <= set(
            r['modules']
        )
