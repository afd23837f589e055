"""`ros2 run im_tuner tuner --drive-config <packaged drive>`: the run names the drive, the
controller ran the drive's experiment and the optimiser started from the drive's start
(docs/drive-family.md); an unknown name is refused in one line, exit 2, nothing created."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from im_controller.config import GAIN_NAMES
from im_tuner.family import drive_setup

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
DRIVE = 'im3700w-j3'


def tuner(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', *args], capture_output=True, text=True, timeout=timeout
    )


def test_tuner_on_a_packaged_drive(tmp_path):
    run = tmp_path / 'run'
    proc = tuner(
        *('--drive-config', DRIVE, '--budget', '2', '--remeasure', '0', '--seed', '5'),
        *('--out', str(run), '--quiet', '--no-record'),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    setup = drive_setup(DRIVE)
    cfg = yaml.safe_load((run / 'run.yaml').read_text())
    assert cfg['drive_config'] == DRIVE
    box = cfg['search_box']
    start = dict(zip(GAIN_NAMES, setup.params.space.start, strict=True))
    assert {n: b['start'] for n, b in box.items()} == pytest.approx(start, rel=1e-12)
    ctl = cfg['controller_parameters']
    e = setup.experiment
    assert ctl['trajectory.a_max'] == pytest.approx(e.trajectory.a_max, rel=1e-12)
    assert ctl['trajectory.load_torque'] == pytest.approx(e.trajectory.load_torque, rel=1e-12)
    assert ctl['loss.a3'] == pytest.approx(e.loss.a3, rel=1e-12)
    assert ctl['fallback_gains.k_pw'] == pytest.approx(e.fallback_gains.k_pw, rel=1e-12)
    recs = [json.loads(x) for x in (run / 'results.jsonl').read_text().splitlines()]
    ref = [r for r in recs if r['kind'] == 'reference']
    # the reference (the drive's start) measured on the drive: near the paper's 0.98, not aborted
    assert len(ref) == 1 and not ref[0]['aborted'] and 0.9 < ref[0]['loss'] < 1.1


def test_unknown_drive_name_refused_in_one_line(tmp_path):
    run = tmp_path / 'run'
    proc = tuner('--drive-config', 'im2200w-j3', '--budget', '2', '--out', str(run), timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and 'im2200w-j3' in lines[0] and 'im7500w-j10' in lines[0]
    assert not run.exists()
