"""Every traceback and silent case found on a documented path, run as a
user runs it. Each refusal: exit 2, exactly one line on stderr, no traceback, nothing
created or changed in the working directory (test_bad_input's ``_run_case``: a copy of a
template with a real tuner run, its tree compared before and after). And the cases that
must work: ``sim_bench --drive-config im7500w-j3`` takes that drive's gains, and a tuner beside
it learns which drive its first step must model.

(The pure side of each case, cheaper: src/*/test/test_drive_file.py,
test_documented_inputs.py, test_study_drives.py.)
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from test_bad_input import ROS2, _run_case, _tree
from test_tuner import results, tuner

REPO = Path(__file__).resolve().parent.parent
MISSING_BASE = "base 'sub/none.yaml': cannot read"

#: (executable, case, argv, what the one line says)
CASES: list[tuple[str, str, list[str], str]] = [
    *[
        (exe, 'config-missing-relative-base', [flag, 'drives/base_missing.yaml'], MISSING_BASE)
        for exe, flag in (
            ('drive_sim', '--drive-config'),
            ('controller', '--drive-config'),
            ('sim_bench', '--drive-config'),
            ('drive_host', '--drive-config'),
            ('tuner', '--drive-config'),
            ('study', '--drive-config'),
        )
    ],
    ('report', 'evaluation-twice', ['run_eval_twice'], 'line 4: evaluation 1 again'),
    ('report', 'evaluation-skipped', ['run_eval_skipped'], 'evaluation 0 is missing'),
    ('report', 'remeasure-of-none', ['run_remeasure_none'], 're-measurement of evaluation 7'),
    ('report', 'summary-newer-format', ['run_future_summary'], 'summary.json: format version 99'),
    ('report', 'out-into-a-bag', ['run', '--out', 'livebag'], '--out livebag: a bag folder'),
    ('tuner', 'resume-evaluation-twice', ['--resume', 'run_eval_twice'], 'evaluation 1 again'),
    ('tuner', 'resume-evaluation-skipped', ['--resume', 'run_eval_skipped'], 'is missing'),
    ('tuner', 'resume-remeasure-of-none', ['--resume', 'run_remeasure_none'], 'evaluation 7'),
]


@pytest.fixture(scope='module')
def template(tmp_path_factory) -> Path:
    """A real finished run (budget 3, one re-measurement) and copies of it out of order;
    a bag folder being recorded; a drive file whose relative base is missing."""
    root = tmp_path_factory.mktemp('documented_paths_template')
    run = root / 'run'
    proc = tuner(
        *('--algo', 'necga', '--budget', '3', '--seed', '5', '--remeasure', '1'),
        *('--no-record', '--bench', 'inproc', '--quiet', '--out', str(run)),
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = (run / 'results.jsonl').read_text().splitlines(keepends=True)
    kinds = [(json.loads(ln)['kind'], json.loads(ln)['eval']) for ln in lines]
    assert kinds[:4] == [('reference', -1), ('eval', 0), ('eval', 1), ('eval', 2)], kinds
    ghost = json.loads(lines[2])
    ghost.update(kind='remeasure', eval=7)
    for key in ('u', 'best_loss'):
        ghost.pop(key, None)
    variants = {
        # a line pasted twice; one deleted; a re-measurement of an evaluation never run
        'run_eval_twice': ''.join(lines[:3]) + lines[2],
        'run_eval_skipped': lines[0] + lines[2],
        'run_remeasure_none': ''.join(lines[:4]) + json.dumps(ghost) + '\n',
    }
    for name, text in variants.items():
        d = root / name
        d.mkdir()
        (d / 'run.yaml').write_bytes((run / 'run.yaml').read_bytes())
        (d / 'results.jsonl').write_text(text)
    future = root / 'run_future_summary'
    future.mkdir()
    for f in ('run.yaml', 'results.jsonl'):
        (future / f).write_bytes((run / f).read_bytes())
    summary = json.loads((run / 'summary.json').read_text())
    (future / 'summary.json').write_text(json.dumps({'version': 99, **summary}))
    (root / 'livebag').mkdir()  # a recorder's bag before its metadata.yaml is written
    (root / 'livebag' / 'livebag_0.mcap').write_bytes(b'\x89MCAP0\r\n')
    (root / 'drives' / 'sub').mkdir(parents=True)
    (root / 'drives' / 'base_missing.yaml').write_text('base: sub/none.yaml\nTs: 200.0e-6\n')
    return root


@pytest.fixture(scope='module')
def outcomes(template: Path, tmp_path_factory) -> dict[int, dict]:
    base = tmp_path_factory.mktemp('documented_paths_cases')
    with ThreadPoolExecutor(3) as pool:
        futs = {
            i: pool.submit(_run_case, template, base, i, exe, argv)
            for i, (exe, _n, argv, _s) in enumerate(CASES)
        }
        return {i: f.result() for i, f in futs.items()}


@pytest.mark.parametrize('i', range(len(CASES)), ids=[f'{e}-{n}' for e, n, _a, _s in CASES])
def test_one_line_exit_2_nothing_changed(i: int, outcomes: dict[int, dict]) -> None:
    exe, _name, argv, says = CASES[i]
    o = outcomes[i]
    what = f'{exe} {" ".join(argv)}: rc={o["rc"]}\nstderr:\n{o["stderr"][-1500:]}'
    assert o['rc'] == 2, what
    assert 'Traceback' not in o['stderr'] + o['stdout'], what
    lines = o['stderr'].strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: '), what
    assert says in lines[0], what
    assert o['created'] == [] and o['removed'] == [] and o['changed'] == [], (
        f'{what}\ncreated {o["created"]}, removed {o["removed"]}, changed {o["changed"]}'
    )


@pytest.mark.parametrize(
    'argv, says',
    [
        (['--seconds', '0'], '--seconds: must be > 0 s, got 0'),
        (['--seconds', 'nan'], '--seconds: must be finite, got nan'),
        (['--seconds', 'inf'], '--seconds: must be finite, got inf'),
        (['--seconds', '-1'], '--seconds: must be > 0 s, got -1'),
        (['--seconds', '1e-5'], 'shorter than one period'),
        (['--hogs', '-1'], '--hogs: must be >= 0, got -1'),
    ],
)
def test_loop_floor_refuses_bad_numbers_in_one_line(argv, says, tmp_path):
    before = _tree(tmp_path)
    proc = subprocess.run(
        [sys.executable, str(REPO / 'benchmarks' / 'loop_floor.py'), *argv],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-1500:]
    assert lines[0].startswith('error: loop_floor: ') and says in lines[0], lines[0]
    assert 'Traceback' not in proc.stderr and proc.stdout == ''
    assert _tree(tmp_path) == before


def test_reproduction_docs_leaves_the_tree_untouched_without_its_inputs(tmp_path):
    """On a fresh clone (no bags/study_*): it deleted the 12 committed figures, then failed."""
    for f in ('Makefile', 'tools/reproduction_docs.sh'):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_bytes((REPO / f).read_bytes())
    for f in ('reproduction.md', 'reproduction-family.md', 'reproduction/tables.png'):
        (tmp_path / 'docs' / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / 'docs' / f).write_text(f'committed {f}\n')
    (tmp_path / 'bags' / 'study_reproduction').mkdir(parents=True)  # a study half there
    (tmp_path / 'bags' / 'study_reproduction' / 'tables.png').write_text('png\n')
    before = _tree(tmp_path)
    proc = subprocess.run(
        ['make', '--no-print-directory', '-s', 'reproduction-docs'],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode != 0
    # (make's own closing line: `make: ***`, or `make[1]: ***` under `make test`)
    ours = [ln for ln in proc.stderr.splitlines() if not re.match(r'make(\[\d+\])?: \*\*\*', ln)]
    assert len(ours) == 1 and ours[0].startswith('error: reproduction-docs: missing ')
    assert 'bags/study_reproduction/convergence.png' in ours[0]
    assert 'bags/study_reproduction/tables.png' not in ours[0]  # (that one is there)
    assert _tree(tmp_path) == before


# -- a tuner beside sim_bench --drive-config im7500w-j3 --------------------------------------------
def test_sim_bench_takes_its_drives_gains_and_the_tuner_learns_the_drive(tmp_path, procs):
    """``sim_bench --drive-config im7500w-j3`` kept the paper motor's gains (its reference
    aborted), and a tuner beside it took its first step from the paper's 750 W model
    without a word. Now the bench's controller has that drive's experiment and start; a
    tuner whose first step would model another drive is refused (one line naming
    --drive-config, nothing created), and one told the drive runs there."""
    from im_tuner.family import controller_parameters, tuner_setup

    setup = tuner_setup('im7500w-j3')
    assert setup is not None
    bench = procs.start(
        [ROS2, 'run', 'im_tuner', 'sim_bench', '--drive-config', 'im7500w-j3', '--no-record']
    )
    common = ('--bench', 'none', '--discovery-timeout', '60', '--no-record', '--quiet')
    refused = tuner(*common, '--opt', 'first=model', '--budget', '1', '--out', str(tmp_path / 'no'))
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 2 and len(lines) == 1, refused.stderr[-2000:]
    assert lines[0].startswith('error: tuner: --opt first=model: the controller drives im7500w-j3')
    assert 'give --drive-config im7500w-j3' in lines[0] and 'Traceback' not in refused.stderr
    assert list(tmp_path.iterdir()) == []
    run = tmp_path / 'run'
    proc = tuner(
        *common,
        *('--drive-config', 'im7500w-j3', '--budget', '1', '--remeasure', '0', '--seed', '3'),
        *('--out', str(run)),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    run_yaml = yaml.safe_load((run / 'run.yaml').read_text())
    assert run_yaml['bench'] == 'external' and 'first' in run_yaml['options']
    ctl = run_yaml['controller_parameters']
    for name, value in controller_parameters(setup):  # the drive's start and experiment
        assert ctl[name] == pytest.approx(value, rel=1e-12), name
    assert ctl['k_pw'] == setup.experiment.fallback_gains.k_pw > 5.0  # paper's: 0.15
    ref = results(run)[0]
    assert ref['kind'] == 'reference' and not ref['aborted'], ref
    assert 0.9 < ref['loss'] < 1.1  # the start's loss on its own drive (0.98 offline)
    assert bench.poll() is None


def test_sim_bench_processes_gives_the_controller_child_its_drives_gains():
    """``sim_bench --processes --drive-config NAME``: the controller child's command line carries
    the drive's experiment and start; a ``-p`` of the user's wins over the drive's."""
    from im_tuner.bench.sim_bench import _child_args
    from im_tuner.bench.sim_bench_main import parser
    from im_tuner.family import controller_parameters, tuner_setup

    setup = tuner_setup('im3700w-j10')
    assert setup is not None
    cli = parser().parse_args(['--processes', '--drive-config', 'im3700w-j10'])
    user = ['--ros-args', '-p', 'k_pw:=1.5']
    drive, ctl = _child_args(cli, user)
    assert drive == ('--drive-config', 'im3700w-j10', *user)
    given = dict(a.split(':=', 1) for a in ctl if ':=' in a)
    for name, value in controller_parameters(setup):
        want = 1.5 if name == 'k_pw' else value
        assert float(given[name]) == pytest.approx(want, rel=1e-12), name
    assert ctl[-3:] == tuple(user) and ctl.count('k_pw:=1.5') == 1
    assert not any(a.startswith('k_pw:=') and a != 'k_pw:=1.5' for a in ctl)
    cli = parser().parse_args(['--processes', '--drive-config', 'paper_750w'])
    assert _child_args(cli, []) == (
        ('--drive-config', 'paper_750w'),
        ('--drive-config', 'paper_750w'),
    )
