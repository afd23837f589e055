"""The same bits on every x86-64 CPU: a study and a tuner run at two levels of
numpy's and OpenBLAS's dispatch give byte-identical tables and results.

A level is what a machine offers, emulated by the environment its processes start with
(``LEVELS``): ``native`` is this machine (AVX-512 on CI's Intel Xeons and on AMD Zen 4),
``avx2`` a machine without AVX-512 (numpy's dispatch held at X86_V3, OpenBLAS's Zen core
type: an AMD Zen 2/3).  With the baseline (``im_drive_sim.numeric``, on by default) every
process of the project -- the study and its forkserver workers, the tuner and the nodes
it starts -- runs numpy at X86_V3 and OpenBLAS at Haswell with one thread whatever the
level, so the outputs are equal byte for byte, and equal to the digest taken on another
machine (``STUDY_TABLES_SHA256``: an AMD EPYC).  The control: with the baseline off, the
same study at two levels that every x86-64-v3 machine can emulate (native, and SSE4.2
with OpenBLAS's Nehalem kernels) gives other tables -- the comparison can fail.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from im_drive_sim import numeric

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
#: the machine each level emulates: the variables its processes start with
LEVELS = {
    'native': {},
    'avx2': {
        'NPY_DISABLE_CPU_FEATURES': 'X86_V4,AVX512_ICL,AVX512_SPR',
        'OPENBLAS_CORETYPE': 'Zen',
    },
    'sse4': {
        'NPY_DISABLE_CPU_FEATURES': 'X86_V3,X86_V4,AVX512_ICL,AVX512_SPR',
        'OPENBLAS_CORETYPE': 'Nehalem',
    },
}
#: the study: the algorithms whose state goes through numpy's SIMD loops and OpenBLAS
STUDY = ('study', '--algos', 'cmaes,tpe,safe', '--runs', '2', '--budget', '40', '--quiet')
#: the control's study: cmaes alone (numpy's SIMD loops and OpenBLAS in every ask) already
#: differs between two levels without the baseline, in a sixth of STUDY's time
CONTROL = ('study', '--algos', 'cmaes', '--runs', '2', '--budget', '40', '--quiet')
#: sha256 of that study's tables.csv on the baseline (`ros2 run im_tuner study --algos
#: cmaes,tpe,safe --runs 2 --budget 40`), the same at the avx2 and the x86-64-v3 level
#: here and on every x86-64-v3 CPU (an AMD EPYC, Zen 4 with AVX-512, gave the digest of
#: the code of its day).  Retaken when safe's rows or the statistics in tables.csv change:
#: last for the first step from the model's best points when one is predicted within the
#: ripple limit.
STUDY_TABLES_SHA256 = 'c31dd4ffda73bf255b6f3ac4a1ff9ac324673c6bc0de6680f30729bf6a98fa35'
#: results.jsonl fields that are wall-clock readings, not results
WALL_FIELDS = ('time', 'wall_s')

pytestmark = pytest.mark.skipif(
    numeric.apply().state != 'held',
    reason=f'this machine is not on the numeric baseline: {numeric.apply().reason}',
)


def _env(level: str, baseline: bool = True) -> dict[str, str]:
    """This process's environment without the baseline's variables (set here by
    conftest.py), as a machine of ``level`` would start a process.  Nor the suite's cache
    of first steps (IM_TUNER_PRIOR_CACHE): each level computes its own."""
    drop = (*numeric.VARIABLES, numeric.SWITCH, 'IM_TUNER_PRIOR_CACHE')
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(LEVELS[level])
    if not baseline:
        env[numeric.SWITCH] = 'off'
    return env


def _run(argv: list[str], cwd: Path, env: dict[str, str], timeout: float = 600) -> None:
    cwd.mkdir(parents=True, exist_ok=True)
    p = subprocess.run(
        [ROS2, 'run', 'im_tuner', *argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]


def _study_files(d: Path) -> dict[str, bytes]:
    return {n: (d / n).read_bytes() for n in ('tables.csv', 'runs.csv')}


def _study_arrays(d: Path) -> dict[str, np.ndarray]:
    with np.load(d / 'study.npz') as z:  # every array but the timings
        return {k: z[k] for k in z.files if k not in ('opt_s', 'exp_s')}


def test_a_study_gives_byte_identical_tables_at_two_levels(tmp_path: Path) -> None:
    outs = {}
    for level in ('native', 'avx2'):
        _run([*STUDY, '--out', 'study'], tmp_path / level, _env(level))
        outs[level] = tmp_path / level / 'study'
    a, b = outs['native'], outs['avx2']
    assert _study_files(a) == _study_files(b)
    arrays_a, arrays_b = _study_arrays(a), _study_arrays(b)
    for k, v in arrays_a.items():
        assert v.tobytes() == arrays_b[k].tobytes(), k
    for d in (a, b):
        st = json.loads((d / 'study.json').read_text())['numeric']
        assert st['state'] == 'held' and st['numpy'] == ['X86_V3'], st
        assert st['openblas'] == ['Haswell x1', 'Haswell x1'], st  # numpy's and scipy's
    digest = hashlib.sha256((a / 'tables.csv').read_bytes()).hexdigest()
    assert digest == STUDY_TABLES_SHA256, 'the study differs from the one taken on another CPU'


def test_without_the_baseline_two_levels_give_other_tables(tmp_path: Path) -> None:
    """The control: a study (``CONTROL``), the baseline off, at two levels any x86-64-v3
    machine can emulate, differs (the comparison above is not blind to the dispatch)."""
    outs = {}
    for level in ('native', 'sse4'):
        _run([*CONTROL, '--jobs', '1', '--out', 'study'], tmp_path / level, _env(level, False))
        outs[level] = tmp_path / level / 'study'
        st = json.loads((outs[level] / 'study.json').read_text())['numeric']
        assert st['state'] == 'off', st
        # (a study without spsa and necga: its write-up times neither, no 'nan us')
        md = (outs[level] / 'reproduction.md').read_text()
        assert 'Timing (conclusion on computation)' in md and 'nan' not in md
    assert (outs['native'] / 'tables.csv').read_bytes() != (
        outs['sse4'] / 'tables.csv'
    ).read_bytes()


def _results(run: Path) -> list[dict]:
    lines = [json.loads(x) for x in (run / 'results.jsonl').read_text().splitlines()]
    return [{k: v for k, v in r.items() if k not in WALL_FIELDS} for r in lines]


def test_a_tuner_run_gives_identical_results_at_two_levels(tmp_path: Path) -> None:
    """cmaes (numpy and OpenBLAS in every ask) on the simulated bench: every record equal
    but for its wall-clock fields; run.yaml's numeric baseline held at both levels."""
    argv = ['tuner', '--algo', 'cmaes', '--budget', '8', '--seed', '5', '--no-record']
    argv += ['--discovery-timeout', '0.2']  # no controller on the graph: no 2 s look
    runs = {}
    for level in ('native', 'avx2'):
        _run([*argv, '--quiet', '--out', 'run'], tmp_path / level, _env(level))
        runs[level] = tmp_path / level / 'run'
    a, b = (_results(runs[level]) for level in ('native', 'avx2'))
    assert len(a) >= 10 and a == b
    for run in runs.values():
        st = json.loads((run / 'summary.json').read_text())['sessions'][0]['numeric']
        assert st['state'] == 'held' and st['numpy'] == ['X86_V3'], st
        assert (run / 'run.yaml').read_text() == (runs['native'] / 'run.yaml').read_text()
