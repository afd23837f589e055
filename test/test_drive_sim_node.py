"""The drive simulator node through real DDS traffic (docs/interfaces.md).

Each test starts ``ros2 run im_drive_sim drive_sim`` as a child process (ended by PID)
and talks to it from this process with :class:`im_drive_sim.client.DriveClient`.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.node import Node

from im_drive_sim.client import DriveClient
from im_drive_sim.drive_file import load_config
from im_drive_sim.sim import STATE_FIELDS, DriveSim

F = {name: i for i, name in enumerate(STATE_FIELDS)}
ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')


def policy(state: np.ndarray) -> tuple[float, float]:
    """A deterministic closed loop: PD position control to 1 rad, load step at step 700."""
    k = int(state[F['step_index']])
    isq = float(
        np.clip(20.0 * (1.0 - state[F['theta_meas']]) - 0.4 * state[F['omega_meas']], -7.0, 7.0)
    )
    return isq, (1.75 if k >= 700 else 0.0)


def drive_proc(procs, *args: str, env: dict | None = None) -> subprocess.Popen:
    return procs.start([ROS2, 'run', 'im_drive_sim', 'drive_sim', *args], env=env)


def core_states(steps: int, seed: int) -> np.ndarray:
    """States 0..steps of the pure core closed by ``policy`` (no ROS)."""
    sim = DriveSim(load_config(None), seed=seed)
    sim.reset(omega=0.0, fluxed=True)  # at rest, half an encoder count in, as the node
    ref = np.zeros((steps + 1, len(STATE_FIELDS)))
    sim.read_into(ref[0])
    for k in range(steps):
        sim.step_into(*policy(ref[k]), ref[k + 1])
    return ref


def run_closed_loop(
    ctx, steps: int, timeout: float = 60.0, after_command=None, proc=None
) -> np.ndarray:
    """Answer states 0..steps-1 with ``policy``; return the states 0..steps.
    ``after_command(client, k)`` runs after each answer (to send extra commands).
    ``proc``: the drive's process, which exits after its last step; it is reaped before
    this node is destroyed (a destroy next to an exited, unreaped drive once spun for
    minutes inside Fast DDS)."""
    node = Node('test_controller', context=ctx)
    try:
        client = DriveClient(node)
        states = np.full((steps + 1, len(STATE_FIELDS)), np.nan)
        deadline = time.monotonic() + timeout
        while True:
            s = client.wait_new_state(max(0.0, deadline - time.monotonic()))
            assert s is not None, f'no new state after step {client.answered}'
            k = int(s[F['step_index']])
            states[k] = s
            if k == steps:
                return states
            client.command(k, *policy(s))
            if after_command is not None:
                after_command(client, k)
    finally:
        if proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=30)
        node.destroy_node()


def test_lockstep_is_deterministic_and_equals_the_core(procs, ros_context):
    steps = 1500
    runs = []
    for _ in range(2):
        p = drive_proc(procs, '--seed', '7', '--max-steps', str(steps))
        runs.append(run_closed_loop(ros_context, steps, proc=p))
        _out, err = p.communicate(timeout=30)
        assert p.returncode == 0, err
    a, b = runs
    assert not np.isnan(a).any()
    assert np.array_equal(a, b), 'same inputs must give bit-identical states'
    # Step index and exact time stamps.
    np.testing.assert_array_equal(a[:, F['step_index']], np.arange(steps + 1))
    np.testing.assert_array_equal(a[:, F['time_ns']], np.arange(steps + 1) * 200_000)
    # The node adds nothing: the pure core with the same commands gives the same states.
    ref = core_states(steps, seed=7)
    assert np.array_equal(a, ref)
    # The loop really moved the motor towards 1 rad and fought the load.
    assert abs(a[699, F['theta']] - 1.0) < 0.05
    assert a[-1, F['load_torque']] == 1.75


def test_ros2_run_from_a_plain_shell_and_exit_after_max_steps(procs, ros_context):
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ('AMENT_PREFIX_PATH', 'VIRTUAL_ENV', 'PYTHONPATH')
    }
    env['PATH'] = '/usr/bin:/bin'
    p = drive_proc(procs, '--max-steps', '200', env=env)
    states = run_closed_loop(ros_context, 200, proc=p)
    _out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    assert 'stopped at step 200' in err
    assert states[-1, F['step_index']] == 200


@pytest.mark.serial  # its period timing is asserted: alone, not beside another test
def test_realtime_mode_paces_at_5khz(procs, ros_context, host_floor):
    """2500 states (0.5 s of sim time) arrive every 200 us of wall time."""
    host_floor.require()
    steps = 2500
    # the drive's loop SCHED_FIFO (docs/real-drive.md, "Real-time set-up"; CI runs as root):
    # this test's own client, a Python process answering every state, competes with it
    # for the 2 cores (without it: 40 % of the periods late, typical period 367 us)
    p = drive_proc(
        procs,
        '--mode',
        'realtime',
        '--max-steps',
        str(steps),
        '--thread-priority',
        '50',
        '--cpu-affinity',
        str(max(os.sched_getaffinity(0))),
    )
    node = Node('test_rt_controller', context=ros_context)
    client = DriveClient(node)
    assert client.wait_for_drive(20.0)
    ks, ts = [], []
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        s = client.wait_new_state(1.0)
        if s is None:
            if p.poll() is not None:
                break
            continue
        k = int(s[F['step_index']])
        ks.append(k)
        ts.append(client.source_timestamp_ns * 1e-9)  # when the drive published it
        client.command(k, 0.5, 0.0)
        if k >= steps:
            break
    node.destroy_node()
    _out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    ks_a, ts_a = np.array(ks), np.array(ts)
    # The drive paces from its own start; on a cold machine discovery can match this
    # client a few hundred ms later, so count from the first state received.
    # (this client, at normal priority beside a SCHED_FIFO drive, may miss stretches of
    # states -- it took 135-2500 of them -- : the drive's own publication times of the
    # states it took are what count)
    assert ks_a[-1] == steps and len(ks_a) >= 100
    # The drive counted what it did: every step was fresh or held; and how late its
    # periods started, on this host in these seconds (a host that stalls a SCHED_FIFO
    # loop for milliseconds now and then, as this 2-core VM does, shows it here).
    summary = err[err.rindex('stopped at step') :].splitlines()[0]
    counts = dict(kv.split('=') for kv in summary.split(': ', 1)[1].split(', '))
    assert int(counts['steps']) == steps
    assert int(counts['fresh']) + int(counts['held']) == steps
    overruns, worst = int(counts['overruns']), float(counts['max_lateness_us']) * 1e-6
    # Stated tolerance, on the drive's own publication times (a shared 2-core machine,
    # the responder competing for the CPU). A drive paced right publishes state k at
    # t0 + k x 200 us plus that period's start lateness, where t0 steps up each time it
    # re-anchored after a start more than a period late: 6-17 times per run on this
    # 2-core VM, idle or not, each by up to 1-3.5 ms (the host stalling a SCHED_FIFO loop).
    # * the period: the slope of the states' times over k within the stretches between
    #   those steps (a span a period or more longer than its periods ends a stretch),
    #   pooled least squares, within 1 %. (The median of the spans, used before, read
    #   205.3 us in an idle CI run with 13 overruns: a client taking few states samples
    #   the long spans unevenly.)
    # * the slip over the run: at most the re-anchors' sum (overruns x the worst
    #   lateness), give or take the two end states' own lateness (under a period plus its
    #   work).
    # How much the run slipped in all is the host's, not the drive's: beside a busy
    # process one 0.5 s run met a 10.5 ms stall (13 overruns, the average period 222 us)
    # 8 s after the floor's measurement found at worst 2.1 ms -- the loop's own DDS
    # threads run at normal priority beside it and can hold what its publish needs. The
    # drive counted every one of them (the slip check), and the run says them.
    dk = np.diff(ks_a)
    excess = np.diff(ts_a) - dk * 200e-6
    stretch = np.concatenate([[0], np.cumsum(excess > 150e-6)])
    n_in = np.bincount(stretch)
    k_c = ks_a - (np.bincount(stretch, ks_a) / n_in)[stretch]
    t_c = ts_a - (np.bincount(stretch, ts_a) / n_in)[stretch]
    period = float(np.sum(k_c * t_c) / np.sum(k_c * k_c))
    slip = (ts_a[-1] - ts_a[0]) - (ks_a[-1] - ks_a[0]) * 200e-6
    said = (
        f'drive: {overruns} overruns, worst start {worst * 1e6:.0f} us late, '
        f'{stretch[-1] + 1} stretches; {host_floor.describe()}; drive says: {err[-600:]}'
    )
    assert period == pytest.approx(200e-6, rel=0.01), f'period {period * 1e6:.2f} us; {said}'
    jitter = 300e-6
    allowed_slip = overruns * worst + jitter
    assert -jitter <= slip <= allowed_slip, (
        f'the schedule slipped {slip * 1e6:.0f} us over {ks_a[-1] - ks_a[0]} periods '
        f'(allowed {allowed_slip * 1e6:.0f} us); {said}'
    )
    # it received this client's commands; whether any came within its period (fresh) is
    # this Python client's speed beside a SCHED_FIFO drive on 2 cores, not the drive's:
    # fresh was 0 of 2500 in a CI run of 2026-11-28, every answer a period late
    assert int(counts['commands']) > 0, counts


def test_realtime_holds_the_last_command_when_none_comes(procs):
    p = drive_proc(
        procs,
        '--mode',
        'realtime',
        '--max-steps',
        '500',
        '--ros-args',
        '-p',
        'realtime_wait_for_controller:=false',
    )
    _out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    summary = err[err.rindex('stopped at step') :].splitlines()[0]
    counts = dict(kv.split('=') for kv in summary.split(': ', 1)[1].split(', '))
    assert counts['steps'] == '500' and counts['held'] == '500' and counts['fresh'] == '0'


def test_a_stuck_child_is_reported_with_the_stacks_of_its_threads(procs):
    """A drive that does not end in time (here: lock-step, no controller) is reported with
    every thread's Python stack (``kill -USR1 <pid>``, as any executable of the workspace
    prints it), so a hang is found from the one failure."""
    p = drive_proc(procs)
    with pytest.raises(subprocess.TimeoutExpired) as caught:
        p.communicate(timeout=8)
    said = str(caught.value)
    assert ' seconds; its stderr ends:' in said, said
    assert 'Current thread' in said and 'run_lockstep' in said, said
    assert p.poll() is None  # asked for its stacks, not ended: the fixture ends it by PID


@pytest.mark.parametrize(
    'old, new, key',
    [
        ('Rs: 3.7 ', 'Rs: -3.7 ', 'machine.Rs'),
        ('Lm: 0.205 ', 'Lm: .nan ', 'machine.Lm'),
        ('encoder_counts: 4096 ', 'encoder_counts: 40.96 ', 'sensors.encoder_counts'),
        ('Rs: 3.7 ', 'Rs: [3.7 ', 'yaml'),
    ],
)
def test_bad_parameter_file_is_rejected_with_a_clear_message(procs, tmp_path, old, new, key):
    from im_drive_sim.params import default_config_path

    text = default_config_path().read_text()
    assert old in text
    bad = tmp_path / 'bad_motor.yaml'
    bad.write_text(text.replace(old, new))
    p = drive_proc(procs, '--drive-config', str(bad))
    _out, err = p.communicate(timeout=30)
    assert p.returncode == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith('error:') and 'bad_motor.yaml' in lines[0]
    assert key.lower() in lines[0].lower()


def test_missing_parameter_file_and_bad_mode(procs, tmp_path):
    p = drive_proc(procs, '--drive-config', str(tmp_path / 'nope.yaml'))
    _, err = p.communicate(timeout=30)
    assert p.returncode == 2 and 'nope.yaml' in err
    p = drive_proc(procs, '--ros-args', '-p', 'mode:=fast')
    _, err = p.communicate(timeout=30)
    assert p.returncode == 2 and "'mode'" in err


def test_clock_and_joint_states_carry_exact_sim_time(procs, ros_context):
    from rclpy.executors import SingleThreadedExecutor
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState

    steps = 300
    side = Node('test_side', context=ros_context)
    clocks, joints = [], []
    side.create_subscription(Clock, '/clock', clocks.append, 1000)
    side.create_subscription(JointState, 'drive/joint_states', joints.append, 1000)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(side)
    # The drive outlives the last answered step (it then re-sends state `steps` every
    # 0.1 s), so its last samples are delivered before it is stopped.
    drive_proc(procs, '--max-steps', str(steps + 100))
    # Answer states from this thread; spin the side node between steps.
    node = Node('test_controller2', context=ros_context)
    client = DriveClient(node)
    states = {}
    # Step only once both side subscriptions get samples (the drive re-sends state 0 while
    # it waits), so every later /clock and joint_states sample must arrive: reliable QoS.
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (clocks and joints):
        ex.spin_once(timeout_sec=0.05)  # state 0 (with its clock) is re-sent every 0.1 s
    while time.monotonic() < deadline:
        s = client.wait_new_state(0.05)
        ex.spin_once(timeout_sec=0.0)
        if s is None:
            continue
        k = int(s[0])
        states[k] = s.copy()
        if k == steps:
            break
        client.command(k, 1.0, 0.0)
    end = time.monotonic() + 5.0
    last_ns = steps * 200_000

    def stamp(t) -> int:
        return t.sec * 10**9 + t.nanosec

    while time.monotonic() < end and not (
        any(stamp(m.clock) == last_ns for m in clocks)
        and any(stamp(j.header.stamp) == last_ns for j in joints)
    ):
        ex.spin_once(timeout_sec=0.05)
    ex.shutdown()
    side.destroy_node()
    node.destroy_node()
    clock_ns = sorted({m.clock.sec * 10**9 + m.clock.nanosec for m in clocks})
    assert clock_ns, 'no /clock received'
    # Every 25 steps for /clock, every 10 for joint_states, exact (re-sent state 0 repeats).
    assert clock_ns == [k * 200_000 for k in range(0, steps + 1, 25)]
    joint_ns = sorted({stamp(j.header.stamp) for j in joints})
    assert joint_ns == [k * 200_000 for k in range(0, steps + 1, 10)]
    for j in joints:
        t = j.header.stamp.sec * 10**9 + j.header.stamp.nanosec
        assert t % 2_000_000 == 0
        k = t // 200_000
        if k in states:
            assert j.position[0] == states[k][F['theta_meas']]
            assert j.effort[0] == states[k][F['torque']]


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_sigint_and_sigterm_stop_cleanly(procs, ros_context, mode, sig):
    p = drive_proc(procs, '--mode', mode)
    node = Node('test_signal_watcher', context=ros_context)
    try:
        client = DriveClient(node)
        assert client.wait_for_drive(20.0), 'drive_sim did not come up'
        assert client.wait_state(5.0) is not None
    finally:
        node.destroy_node()
    p.send_signal(sig)
    _out, err = p.communicate(timeout=20)
    assert p.returncode == 0, err
    assert 'stopped at step' in err and 'Traceback' not in err


def test_realtime_counts_late_commands_and_holds_them(procs, ros_context):
    """Commands answering an older state are late: counted, never fresh, still held.
    command_timeout is 1 s: this test answers from Python beside the other tests, and a
    stall of its own past a 0.05 s watchdog would be a true trip to zero current (CI once
    saw the last state at 0 A that way); the watchdog has its own test below."""
    steps = 1500
    p = drive_proc(
        procs,
        '--mode',
        'realtime',
        '--max-steps',
        str(steps),
        '--ros-args',
        '-p',
        'command_timeout:=1.0',
    )
    node = Node('test_late_controller', context=ros_context)
    states: list[np.ndarray] = []
    try:
        client = DriveClient(node)
        assert client.wait_for_drive(20.0)
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and p.poll() is None:
            s = client.wait_new_state(0.5)
            if s is None:
                continue
            states.append(s.copy())
            k = int(s[F['step_index']])
            if k >= 3:  # (answers_step < 0 would mean 'untagged', i.e. always fresh)
                client.command(k - 3, 2.0, 0.0)  # always answers a state 3 periods old
    finally:
        node.destroy_node()
    _out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    summary = err[err.rindex('stopped at step') :].splitlines()[0]
    counts = dict(kv.split('=') for kv in summary.split(': ', 1)[1].split(', '))
    assert int(counts['fresh']) == 0
    assert int(counts['late']) > 0 and int(counts['late']) == int(counts['commands'])
    assert int(counts['held']) == steps
    assert int(counts['watchdog_trips']) == 0, summary
    # The late commands were applied (held): isq follows the 2 A reference once the
    # current loop has settled (300 periods of rise from 0 A after the first command took
    # effect: on a busy machine this test's first answer may come many periods in).
    S = np.array(states)
    k = S[:, F['step_index']].astype(int)
    applied = k[S[:, F['applied_step']] >= 0]
    assert applied.size > 0, 'no command took effect'
    isq = S[:, F['isq']][k >= applied[0] + 300]
    assert isq.size > 100, f'{isq.size} states 300 periods after the first command ({applied[0]})'
    assert np.all(np.abs(isq - 2.0) < 0.2), f'isq {isq.min():.3f}..{isq.max():.3f} A'


# alone: a stall of this test's own answering loop longer than the timeout, beside another
# test, is a true second trip (its counts are asserted)
@pytest.mark.serial
def test_realtime_watchdog_zero_current_when_commands_stop_and_resume(procs, ros_context):
    """Commands of 2 A, then silence: after command_timeout the drive commands zero current
    (the measured isq falls to about 0), counts one trip, and resumes on the next command.
    The timeout is 0.2 s, not the 0.05 s a real bench would use: this test answers each
    state from Python beside the other tests, and a stall of its own longer than the
    timeout would be a true second trip."""
    timeout = 0.2
    p = drive_proc(
        procs,
        '--mode',
        'realtime',
        '--max-steps',
        '9000',
        '--ros-args',
        '-p',
        f'command_timeout:={timeout}',
    )
    node = Node('test_wd_controller', context=ros_context)
    states: list[np.ndarray] = []
    phase_end: dict[str, int] = {}
    try:
        client = DriveClient(node)
        assert client.wait_for_drive(20.0)
        phase = 'command'
        silent_since = None
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and p.poll() is None:
            s = client.wait_new_state(0.5)
            if s is None:
                continue
            states.append(s.copy())
            k = int(s[F['step_index']])
            if phase == 'command':
                client.command(k, 2.0, 0.0)
                if k >= 800:
                    phase, phase_end['command'] = 'silent', k
                    silent_since = time.monotonic()
            elif phase == 'silent':
                # stay silent for 4 timeouts of wall time (whatever the machine's pace)
                if time.monotonic() - silent_since > 4 * timeout:
                    phase, phase_end['silent'] = 'resumed', k
            else:
                client.command(k, 2.0, 0.0)
                if k >= phase_end['silent'] + 600:
                    break
    finally:
        node.destroy_node()
    p.send_signal(signal.SIGINT)
    _out, err = p.communicate(timeout=30)
    S = np.array(states)
    k = S[:, F['step_index']].astype(int)
    isq = S[:, F['isq']]
    stop, back = phase_end['command'], phase_end['silent']
    # commanding: isq follows 2 A
    assert np.all(np.abs(isq[(k > stop - 300) & (k <= stop)] - 2.0) < 0.2)
    # silent: the last stretch before the commands resume is at zero current
    assert np.all(np.abs(isq[(k > back - 50) & (k <= back)]) < 0.1), (
        f'isq while silent: {isq[(k > back - 50) & (k <= back)]}'
    )
    # resumed: 2 A again
    assert np.all(np.abs(isq[(k > back + 300) & (k <= back + 600)] - 2.0) < 0.2)
    summary = err[err.rindex('stopped at step') :].splitlines()[0]
    counts = dict(kv.split('=') for kv in summary.split(': ', 1)[1].split(', '))
    assert int(counts['watchdog_trips']) == 1
    assert 0 < int(counts['watchdog_steps']) < back - stop
    assert f'watchdog: no command on drive/command for {timeout:g} s' in err
    assert 'watchdog: commands resumed' in err
