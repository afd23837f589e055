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
    # (no controller on the test's graph: auto need not look for one for 2 s)
    return subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', *args, '--discovery-timeout', '0.2'],
        capture_output=True,
        text=True,
        timeout=timeout,
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


def test_check_drive_passes_on_the_heaviest_drive_with_its_amplitude(procs, tmp_path):
    """check_drive's default 0.5 A step is the paper motor's: on im7500w-j10 (38x its J/Kt)
    it accelerates the shaft by 1 count; the drive's own amplitude (family.check_amplitude:
    the paper's acceleration, at most 40 % of isq_max) passes every item."""
    from im_tuner.family import check_amplitude

    name = 'im7500w-j10'
    amp = check_amplitude(drive_setup(name).drive)
    assert 10.0 < amp <= 0.4 * 34.84
    drive = procs.start([ROS2, 'run', 'im_drive_sim', 'drive_sim', '--drive-config', name])
    out_json = tmp_path / 'check.json'
    check = ['--drive-config', name, '--amplitude', f'{amp:.4g}', '--json', str(out_json)]
    p = procs.start([ROS2, 'run', 'im_drive_sim', 'check_drive', *check])
    out, err = p.communicate(timeout=90)
    assert p.returncode == 0, f'{out}\n{err}'
    data = json.loads(out_json.read_text())
    assert all(i['passed'] for i in data['items'])
    assert drive.poll() is None
