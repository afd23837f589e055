"""``ros2 run im_tuner replay``: a live controller re-driven from a recorded bag.

Two short real tuner runs make the bags (reference + 2 evaluations each, about 30 s
together): one lock-step (``--bench inproc``, uncompressed so that a test can alter a
recorded command in place) and one on the composed real-time bench (``--bench
realtime``). The replay runs as a user runs it, a subprocess of the installed command,
and starts its own live ``controller`` process. What it must say is worked out here from
the bag with the ``mcap`` library (not the project's reader): the experiment's span from
its loss message and the recorded settle, the fresh periods from the states'
``applied_step``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from im_controller.contract import LOSS_TOPIC
from im_drive_sim.contract import COMMAND_TOPIC, STATE_INDEX, STATE_TOPIC
from im_tuner.replay.plan import Experiment, ReplayPlan, compare

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
TS_NS = 200_000
MOVE_EXPERIMENT = 1  # the first tuned experiment (0 is the reference)


def ros2(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [ROS2, 'run', 'im_tuner', *args], capture_output=True, text=True, timeout=timeout
    )


def read_with_mcap(bag: Path) -> dict:
    """States, commands, loss messages' raw bytes and the controller's parameters, read
    with the mcap library (CRCs checked)."""
    (path,) = bag.glob('*.mcap')
    out: dict = {STATE_TOPIC: [], COMMAND_TOPIC: [], LOSS_TOPIC: []}
    with open(path, 'rb') as f:
        reader = make_reader(f, validate_crcs=True)
        out['params'] = next(
            json.loads(m.metadata['parameters'])
            for m in reader.iter_metadata()
            if m.name == 'im_tuner.controller'
        )
        topics = ['/' + STATE_TOPIC, '/' + COMMAND_TOPIC, '/' + LOSS_TOPIC]
        for _s, ch, m in reader.iter_messages(topics=topics):
            t = ch.topic[1:]
            if t == LOSS_TOPIC:
                out[t].append(m.data)
            else:
                n = int.from_bytes(m.data[12:16], 'little')
                out[t].append(np.frombuffer(m.data, '<f8', n, 20))
    out[STATE_TOPIC] = np.array(out[STATE_TOPIC])
    out[COMMAND_TOPIC] = np.array(out[COMMAND_TOPIC])
    return out


def loss_values(raw: bytes, eid: int) -> dict[str, str] | None:
    """The key/values of a loss message (DiagnosticArray CDR) if it is experiment ``eid``:
    parsed by hand here, independently of the project's parser."""
    at = 4

    def u32() -> int:
        nonlocal at
        at = (at + 3) & ~3
        v = int.from_bytes(raw[at : at + 4], 'little')
        at += 4
        return v

    def s() -> str:
        nonlocal at
        n = u32()
        v = raw[at : at + n - 1].decode()
        at += n
        return v

    at += 8  # stamp
    s()  # frame_id
    for _ in range(u32()):
        at += 1  # level
        s(), s(), s()
        kv = {}
        for _ in range(u32()):
            k = s()
            kv[k] = s()
        if int(kv['experiment_id']) == eid:
            return kv
    return None


def experiment_span(bag_data: dict, eid: int) -> tuple[int, int]:
    """First and last step of experiment ``eid``: its settle (trajectory.settle of the
    recorded parameters) before its step 0 (t_start_ns), its last state t_end_ns - Ts."""
    kv = next(v for r in bag_data[LOSS_TOPIC] if (v := loss_values(r, eid)) is not None)
    settle = round(bag_data['params']['trajectory.settle'] * 1e9 / TS_NS)
    return int(kv['t_start_ns']) // TS_NS - settle, int(kv['t_end_ns']) // TS_NS - 1


@pytest.fixture(scope='module')
def bags(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp('replay_runs')
    out = {}
    for name, extra in (
        ('lockstep', ['--bench', 'inproc', '--compression', 'none']),
        ('realtime', ['--bench', 'realtime']),
    ):
        run = base / name
        proc = ros2(
            'tuner',
            '--algo',
            'spsa',
            '--budget',
            '2',
            '--remeasure',
            '0',
            '--seed',
            '3',
            '--out',
            str(run),
            '--quiet',
            *extra,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        out[name] = run / 'bag_0'
    return out


def test_lockstep_experiment_bit_for_bit(bags):
    bag = bags['lockstep']
    data = read_with_mcap(bag)
    proc = ros2('replay', str(bag), '--experiment', str(MOVE_EXPERIMENT), '--json', '--quiet')
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    r = json.loads(proc.stdout)
    first, last = experiment_span(data, MOVE_EXPERIMENT)
    assert (r['first_step'], r['last_step']) == (first, last)
    # every period of the experiment, its 0.5 s settle and its 1.125 s: 2500 + 5625
    assert r['periods'] == last - first + 1 == 8125
    assert r['compared'] == r['periods'] and r['differing'] == 0 and r['max_abs_diff'] == 0.0
    assert r['match'] and r['mode'] == 'lockstep' and not r['fresh_only']
    # the states before it were fed too (the filters and integrator carry over)
    assert r['states_fed'] == last + 1


def test_lockstep_whole_bag_every_command(bags):
    bag = bags['lockstep']
    data = read_with_mcap(bag)
    proc = ros2('replay', str(bag))
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    n = len(data[COMMAND_TOPIC])
    assert proc.stdout.startswith(f'replay: MATCH every experiment: {n} commands bit for bit')
    # progress lines on stderr, the last one at 100 %
    progress = [x for x in proc.stderr.splitlines() if x.startswith('replay: state ')]
    assert len(progress) >= 5 and progress[-1].startswith(f'replay: state {n}/{n} (100 %)')


def test_realtime_every_fresh_period(bags):
    bag = bags['realtime']
    data = read_with_mcap(bag)
    proc = ros2('replay', str(bag), '--experiment', str(MOVE_EXPERIMENT), '--json', '--quiet')
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    r = json.loads(proc.stdout)
    first, last = experiment_span(data, MOVE_EXPERIMENT)
    assert (r['first_step'], r['last_step'], r['periods']) == (first, last, 8125)
    # the fresh periods, from the states: the command answering k drove the period
    # ending at state k + d fresh when that state shows applied_step == k
    S = data[STATE_TOPIC]
    applied = dict(zip(S[:, 0].astype(int), S[:, STATE_INDEX['applied_step']], strict=False))
    d = int(S[0, STATE_INDEX['command_delay']])
    answered = set(data[COMMAND_TOPIC][:, 0].astype(int))
    fresh = [k for k in range(first, last + 1) if k in answered and applied.get(k + d) == k]
    assert r['fresh_only'] and r['mode'] == 'realtime'
    assert r['compared'] == len(fresh) > 0.99 * r['periods']
    assert r['match'] and r['differing'] == 0 and r['max_abs_diff'] == 0.0


def test_only_fresh_periods_count_on_a_realtime_bag():
    """The compared set: a real-time bag's fresh periods inside the window; a lock-step
    bag's every period (pure: a plan made by hand)."""
    states = np.zeros((6, 14))
    states[:, 0] = np.arange(6)
    cmds = np.zeros((6, 3))
    cmds[:, 0] = np.arange(6)
    cmds[:, 1] = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    fresh = np.array([True, True, False, True, True, True])
    exp = Experiment(0, 1, 4, (0.53, 20.0, 30.0, 0.005, 0.007), 1)
    plan = ReplayPlan(Path('x'), 'realtime', {}, states, cmds, fresh, [exp], exp, np.zeros(0))
    assert plan.compared_mask().tolist() == [False, True, False, True, True, False]
    replayed = cmds.copy()
    replayed[2, 1] = 99.0  # a held period's answer: not compared
    assert compare(plan, replayed).match
    replayed[3, 1] = np.nextafter(3.0, 4.0)  # one ulp on a fresh one: a mismatch
    c = compare(plan, replayed)
    assert (c.compared, c.differing, c.first) == (
        3,
        1,
        {'step': 3, 'field': 'isq_ref', 'recorded': 3.0, 'replayed': float(np.nextafter(3.0, 4.0))},
    )
    plan.mode = 'lockstep'
    assert plan.compared_mask().tolist() == [False, True, True, True, True, False]
    replayed[3, 1] = np.nan  # never answered
    c = compare(plan, replayed)
    assert c.differing == 2 and c.max_abs_diff == np.inf


def alter_command(src: Path, dst: Path, step: int) -> tuple[float, float]:
    """Copy the bag ``src`` to ``dst`` with the recorded command answering ``step`` made
    one ulp larger in place (uncompressed chunks; the chunk's CRC made right again, so
    the mcap library reads it as a sound bag). Returns (original, altered) isq_ref."""
    shutil.copytree(src, dst)
    (path,) = dst.glob('*.mcap')
    data = read_with_mcap(src)
    (row,) = [c for c in data[COMMAND_TOPIC] if c[0] == step]
    old = struct.pack('<3d', *row)
    new_isq = float(np.nextafter(row[1], np.inf))
    buf = bytearray(path.read_bytes())
    assert buf.count(old) == 1
    at = buf.index(old)
    buf[at : at + 24] = struct.pack('<3d', row[0], new_isq, row[2])
    pos = 8  # after the magic: top-level records, opcode u8 + length u64
    while pos < len(buf):
        op, n = struct.unpack_from('<BQ', buf, pos)
        body = pos + 9
        if op == 0x06 and body <= at < body + n:  # the chunk holding it
            clen = struct.unpack_from('<I', buf, body + 28)[0]
            assert bytes(buf[body + 32 : body + 32 + clen]) == b''  # not compressed
            rec = body + 32 + clen + 8
            struct.pack_into('<I', buf, body + 24, zlib.crc32(buf[rec : body + n]))
            break
        pos = body + n
    path.write_bytes(bytes(buf))
    assert any(c[0] == step and c[1] == new_isq for c in read_with_mcap(dst)[COMMAND_TOPIC])
    return float(row[1]), new_isq


def test_an_altered_command_is_a_mismatch_at_its_period(bags, tmp_path):
    data = read_with_mcap(bags['lockstep'])
    first, last = experiment_span(data, MOVE_EXPERIMENT)
    step = first + 2500 + 3600  # local step 3600: the load is on (from 3500)
    assert first < step < last
    original, altered = alter_command(bags['lockstep'], tmp_path / 'bag', step)
    proc = ros2('replay', str(tmp_path / 'bag'), '--experiment', str(MOVE_EXPERIMENT), '--json')
    assert proc.returncode == 1, proc.stdout + proc.stderr[-3000:]
    r = json.loads(proc.stdout)
    assert not r['match'] and r['differing'] == 1 and r['compared'] == 8125
    assert r['first_mismatch'] == {
        'step': step,
        'field': 'isq_ref',
        'recorded': altered,
        'replayed': original,
    }
    assert r['max_abs_diff'] == altered - original > 0
    text = ros2('replay', str(tmp_path / 'bag'), '--experiment', str(MOVE_EXPERIMENT), '--quiet')
    assert text.returncode == 1
    assert text.stdout.startswith(
        f'replay: MISMATCH experiment {MOVE_EXPERIMENT}: 1 of 8125 commands differ, '
        f'the first at step {step} (isq_ref recorded {altered!r}, replayed {original!r})'
    )


def tree(d: Path) -> dict[str, str]:
    return {
        str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else ''
        for p in sorted(d.rglob('*'))
    }


@pytest.mark.parametrize(
    'case',
    ['missing', 'file', 'empty-dir', 'not-mcap', 'run-dir', 'experiment-out-of-range', 'two-mcap'],
)
def test_bad_input_one_line_exit_2_nothing_created(bags, tmp_path, case):
    shutil.copytree(bags['lockstep'].parent, tmp_path / 'run')
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'x_0.mcap').write_bytes(b'not an mcap file at all')
    (tmp_path / 'two').mkdir()  # (a split bag: not read as its first file)
    for name in ('a.mcap', 'b.mcap'):
        shutil.copy(next((tmp_path / 'run' / 'bag_0').glob('*.mcap')), tmp_path / 'two' / name)
    args, expect = {
        'missing': ([str(tmp_path / 'nope')], 'no such directory'),
        'file': ([str(tmp_path / 'run' / 'run.yaml')], 'not a directory'),
        'empty-dir': ([str(tmp_path / 'empty')], 'not a bag (no .mcap file)'),
        'not-mcap': ([str(tmp_path / 'junk')], 'not an MCAP file'),
        'run-dir': ([str(tmp_path / 'run')], 'a run directory: give its bag'),
        'experiment-out-of-range': (
            [str(tmp_path / 'run' / 'bag_0'), '--experiment', '3'],
            'not in the bag (it holds experiments 0..2)',
        ),
        'two-mcap': ([str(tmp_path / 'two')], 'several .mcap files (a.mcap, b.mcap)'),
    }[case]
    before = tree(tmp_path)
    proc = ros2('replay', *args, timeout=60)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith('error: replay: ') and expect in lines[0]
    assert proc.stdout == '' and 'Traceback' not in proc.stderr
    assert tree(tmp_path) == before
