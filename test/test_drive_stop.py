"""A real drive on the composed bench: every ``--drive`` form tunes with
recording on, and every way out of a run leaves zero current in the power stage.

The power stage is :mod:`recording_hardware` (the example drive's simulated plant; every
``write`` lands in a memory-mapped file the test reads after the process ended), named
as docs/real-drive.md tells a user to name theirs: ``--drive module:Class`` with the
module on PYTHONPATH.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from recording_hardware import read_log
from test_faults import bag_counts, bag_state, results, ros2

HERE = Path(__file__).parent
STEPS = 5625


def _env(hw_file: Path, **extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(HERE), env.get('PYTHONPATH', '')]).rstrip(os.pathsep)
    env['RECORDING_HW_FILE'] = str(hw_file)
    env.update(extra)
    return env


def _tuner(run: Path, drive: str, budget: int) -> list[str]:
    # These drives cannot pause (a power stage's time is wall time): on a loaded machine a
    # late period is held periods, and an experiment with any is flagged `timing` and
    # re-run (test_realtime_bench checks that), and the held current can make the
    # supervisor stop an experiment or trip a safety limit. What is tested here is the
    # drive's form, the bag and the stop: any timing is accepted and faults are reset.
    return [
        *ros2('im_tuner', 'tuner', '--bench', 'realtime', '--drive', drive),
        *('--budget', str(budget), '--seed', '3', '--remeasure', '0', '--quiet'),
        *('--fault-policy', 'reset'),
        *('--out', str(run), '--ros-args', '-p', f'timing_tolerance:={STEPS}'),
    ]


@pytest.mark.parametrize(
    'drive',
    ['example', 'recording_hardware:RecordingHardware', 'recording_hardware:RecordingDrive'],
)
def test_every_drive_form_tunes_three_evaluations_with_recording(tmp_path, drive):
    run, hw = tmp_path / 'run', tmp_path / 'hw.bin'
    p = subprocess.run(
        _tuner(run, drive, 3), env=_env(hw), capture_output=True, text=True, timeout=300
    )
    assert p.returncode == 0, p.stderr[-3000:]
    recs = results(run)
    # an experiment whose drive faulted (the held current of a late loop can trip a
    # limit) is reset and measured again: a retry is a record with attempt > 1
    final = {(r['kind'], r['eval']): r for r in recs}
    assert list(final) == [('reference', -1), ('eval', 0), ('eval', 1), ('eval', 2)], recs
    assert len(recs) <= len(final) + 2, recs  # retries are the exception, not the rule
    for r in final.values():
        assert r['status'] in ('ok', 'aborted'), r
        assert r['steps'] == STEPS or r['aborted'], r
    bag = run / 'bag_0'
    assert bag_state(bag) == 'closed'
    counts = bag_counts(bag)
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
    custom = meta['rosbag2_bagfile_information']['custom_data']
    assert custom['im_tuner.lost_total'] == '0', custom['im_tuner.counts']
    # every state the drive published is in the bag, and every loss. A late loop publishes
    # none for the periods it missed (how many is the host's: they are held, on the drive's
    # timeline), so state 0 and each period the loop ran published one state, and the
    # timeline covers the run to its last experiment's end.
    last = recs[-1]['t_end_ns'] // 200_000
    published = json.loads(custom['im_tuner.counts'])['/drive/state']['published']
    d = json.loads((run / 'summary.json').read_text())['sessions'][-1]['drive']
    assert counts['/drive/state'] == published == 1 + d['steps'] - d['missed'] > 1, (counts, d)
    assert d['steps'] >= last, (d, last)
    assert len(final) <= counts['/controller/loss'] <= len(recs), (counts, recs)
    if drive != 'example':
        log = read_log(str(hw))
        assert log['writes'] >= counts['/drive/state'], log  # a write before each state
        assert (log['isq_ref'], log['load_torque']) == (0.0, 0.0), log
        assert log['closes'] == 1.0 and log['writes_after_close'] == 0.0, log


@pytest.mark.parametrize('how', ['SIGINT', 'SIGTERM', 'exception'])
def test_every_way_out_leaves_zero_current(tmp_path, procs, wait_until, how):
    """Stopped in the middle of an experiment, with current flowing: the last write to
    the power stage is zero current and zero load torque, then close(), then nothing."""
    run, hw = tmp_path / 'run', tmp_path / 'hw.bin'
    mid = 2 * STEPS + 1000  # inside the second experiment (the load is on after 3500)
    extra = {'RECORDING_HW_RAISE_AFTER': str(mid)} if how == 'exception' else {}
    proc = procs.start(
        _tuner(run, 'recording_hardware:RecordingHardware', 50), env=_env(hw, **extra)
    )
    if how != 'exception':
        wait_until(
            lambda: hw.exists() and read_log(str(hw))['writes'] >= mid,
            120,
            message='the run to reach the middle of its second experiment',
        )
        proc.send_signal(getattr(signal, how))
    out, err = proc.communicate(timeout=120)
    log = read_log(str(hw))
    assert log['max_abs_isq'] > 0.5, log  # current was flowing before the stop
    assert (log['isq_ref'], log['load_torque']) == (0.0, 0.0), log
    assert log['closes'] == 1.0 and log['writes_after_close'] == 0.0, log
    assert bag_state(run / 'bag_0') == 'closed'
    if how == 'exception':
        assert proc.returncode == 1, err[-3000:]
        assert 'Traceback' not in err, err[-3000:]
        assert 'failed: the real-time loop stopped on OSError: fieldbus' in out, out + err
    else:
        assert proc.returncode == 130, err[-3000:]
