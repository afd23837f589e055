"""The controller node through real DDS traffic (docs/controller.md, docs/interfaces.md).

The in-process bench (drive_sim + controller in this process, lock-step) is driven by a
probe node that does what the tuner will: set parameters through the parameter services,
start experiments with the Trigger service and read results from the loss topic.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from im_controller.config import Gains
from im_controller.contract import (
    BUSY,
    NO_DRIVE_STATE,
    SAFETY_FAULT,
    STATE_NOT_FINITE,
    refusal_code,
    started_id,
)
from im_controller.controller_node import INTERNALS_FIELDS
from im_controller.messages import msg_to_result, result_to_msg
from im_controller.runner import ExperimentRunner, config_for_drive
from im_drive_sim.drive_file import load_config
from im_drive_sim.runtime import ParameterOverrideError
from im_drive_sim.sim import DriveSim
from im_tuner.bench import InProcessBench
from im_tuner.offline import run_experiment_offline

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
SEED = 3
UNSTABLE = {'k_pw': 0.05, 'k_pos': 300.0}  # trips the supervisor (docs/controller.md)


class Probe:
    """What the tuner does, over DDS: parameters, start service, loss topic."""

    def __init__(self, context, spin_until) -> None:
        self.node = Node('test_probe', context=context)
        # Drain the 5 kHz internals between bench iterations (an executor serving one
        # callback per spin could not keep up, and Fast DDS caps a reader at 5000 samples).
        self.spin_until = lambda pred, timeout: spin_until(lambda: self._drain() or pred(), timeout)
        self.start_client = self.node.create_client(Trigger, '/controller/start_experiment')
        self.reset_client = self.node.create_client(Trigger, '/controller/reset_fault')
        self.params = AsyncParameterClient(self.node, '/controller')
        self.results = []
        self.internals = []
        self.node.create_subscription(
            DiagnosticArray,
            '/controller/loss',
            lambda m: self.results.append(msg_to_result(m)),
            100,
        )
        self.internals_sub = self.node.create_subscription(
            Float64MultiArray,
            '/controller/internals',
            lambda m: self.internals.append(np.array(m.data)),
            1000,
        )  # when the executor takes one

    def _drain(self) -> None:
        while (r := self.internals_sub.handle.take_message(Float64MultiArray, False)) is not None:
            self.internals.append(np.array(r[0].data))

    def ready(self, timeout: float = 20.0) -> None:
        assert self.spin_until(
            lambda: self.start_client.service_is_ready() and self.params.services_are_ready(),
            timeout,
        )
        # Also wait for the loss topic to be matched, so no result can be missed.
        assert self.spin_until(lambda: self.node.count_publishers('/controller/loss') > 0, timeout)
        # And one answered round trip (a read, re-sent if lost): a server answers before it
        # has discovered a client's response reader only at the answer's loss, and a first
        # start whose answer was lost so (a loaded CI, once) cannot be sent again
        deadline = time.monotonic() + timeout
        while True:
            got = self.params.get_parameters(['k_pw'])
            if self.spin_until(got.done, 2.0):
                break
            assert time.monotonic() < deadline, 'the controller answered no parameter read'

    def call(self, future, timeout: float = 20.0):
        assert self.spin_until(future.done, timeout), 'service call timed out'
        return future.result()

    def start(self) -> Trigger.Response:
        return self.call(self.start_client.call_async(Trigger.Request()))

    def experiment(self, timeout: float = 60.0):
        n = len(self.results)
        resp = self.start()
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            code = refusal_code(resp.message)
            if code == SAFETY_FAULT and 'drive_state_timeout' in resp.message:
                # Real time on a loaded machine: the drive's states paused for longer than
                # state_timeout before any experiment. Reset it, as the tuner
                # does (fault policy 'reset'), and start again.
                reset = self.call(self.reset_client.call_async(Trigger.Request()))
                assert reset.success or refusal_code(reset.message) == NO_DRIVE_STATE
            elif resp.success or code not in (NO_DRIVE_STATE, BUSY):
                break
            # a controller that just came up: the drive re-sends its state every 0.1 s;
            # or one that still runs an experiment started before (a tuner killed
            # mid-experiment: on a loaded machine it may end seconds later)
            assert self.spin_until(lambda: False, 0.1) is False
            resp = self.start()
        assert resp.success, resp.message
        # The result of the experiment this call started: a late loss of one that was in
        # flight when the probe joined (a tuner killed mid-experiment) is not it.
        eid = started_id(resp.message)

        def mine():
            return next((r for r in self.results[n:] if r.experiment_id == eid), None)

        assert self.spin_until(lambda: mine() is not None, timeout), 'no result'
        return mine()

    def set(self, **values) -> list:
        res = self.call(
            self.params.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        )
        return list(res.results)

    def set_atomically(self, **values):
        return self.call(
            self.params.set_parameters_atomically(
                [Parameter(k, value=v) for k, v in values.items()]
            )
        ).result

    def get(self, *names) -> list:
        res = self.call(self.params.get_parameters(list(names)))
        return [parameter_value_to_python(v) for v in res.values]


@contextlib.contextmanager
def probe_of_children(ros_context, *children):
    """A Probe spun by its own executor, against nodes running in child processes."""
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor(context=ros_context)

    def spin_until(pred, timeout):
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline or any(c.poll() is not None for c in children):
                return pred()
            ex.spin_once(timeout_sec=0.01)
        return True

    probe = Probe(ros_context, spin_until)
    ex.add_node(probe.node)
    try:
        probe.ready(30.0)
        yield probe
    finally:
        ex.shutdown()
        probe.node.destroy_node()


@pytest.fixture
def bench(ros_context):
    b = InProcessBench(context=ros_context, drive_overrides=[Parameter('seed', value=SEED)])
    probe = Probe(ros_context, b.spin_until)
    b.executor.add_node(probe.node)
    probe.ready()
    try:
        yield b, probe
    finally:
        probe.node.destroy_node()
        b.destroy()


def offline_losses(gains_seq: list[Gains], seed: int = SEED) -> list:
    """The pure core (no ROS): consecutive experiments on one drive, state carried over."""
    sim = DriveSim(load_config(None), seed=seed)
    sim.reset(omega=0.0, fluxed=True)  # at rest, half an encoder count in, as the node
    runner = ExperimentRunner(config_for_drive(None, sim), gains_seq[0])
    runner.reset(sim.theta_meas)
    return [
        run_experiment_offline(sim, g, runner.config, i, runner, record=False)[0]
        for i, g in enumerate(gains_seq)
    ]


def test_experiments_through_dds_equal_the_pure_core(bench):
    b, probe = bench
    r0 = probe.experiment()
    r1 = probe.experiment()
    # The hand-tuned start reaches pi, rejects the load step and gives a finite loss.
    assert not r0.aborted and math.isfinite(r0.loss) and r0.loss > 0
    assert (r0.experiment_id, r0.direction, r1.experiment_id, r1.direction) == (0, 1, 1, -1)
    # each: its 2500-period settle, then 5625 measured periods (docs/controller.md)
    assert (r0.t_start, r0.t_end, r1.t_start) == (
        2500 * 200_000,
        8125 * 200_000,
        (8125 + 2500) * 200_000,
    )
    theta = b.drive.sim.theta  # the true angle the drive's last state carried
    assert abs(theta - 0.0) < 0.01  # back at 0 after 0 -> pi -> 0
    ref = offline_losses([Gains(), Gains()])
    for got, want in zip((r0, r1), ref, strict=True):
        assert got.loss == pytest.approx(want.loss, rel=1e-9, abs=0)
        assert got.terms == pytest.approx(want.terms, rel=1e-9, abs=0)
        assert got.loss == want.loss, 'lock-step through DDS is bit-identical to the core'
    # Internals were published every step of the experiments (settles included), with
    # their layout; exp_step counts the settle negative, the measured steps from 0.
    n = 2 * 8125
    probe.spin_until(lambda: len(probe.internals) >= n, 10)
    assert probe.spin_until(lambda: len(probe.internals) >= n, 10)
    data = np.array(probe.internals)
    assert data.shape[1] == len(INTERNALS_FIELDS)
    steps = data[:, 0]
    assert np.array_equal(np.unique(steps), np.arange(n))
    exp_step = data[np.argsort(steps, kind='stable'), INTERNALS_FIELDS.index('exp_step')][:n]
    assert exp_step[:8125].tolist() == list(range(-2500, 5625))


def test_gain_changes_apply_between_experiments_and_are_refused_during_one(bench):
    b, probe = bench
    results = probe.set(k_pw=0.6, k_iw=25)  # an integer for a double is accepted
    assert all(r.successful for r in results), [r.reason for r in results]
    assert probe.get('k_pw', 'k_iw') == [0.6, 25.0]
    assert probe.start().success
    # Mid-experiment (the bench has not stepped it to the end yet): refused, not changed.
    res = probe.set(k_pw=1.0)
    assert not res[0].successful and refusal_code(res[0].reason) == BUSY
    resp = probe.start()
    assert not resp.success and refusal_code(resp.message) == BUSY
    n = len(probe.results)
    assert b.spin_until(lambda: len(probe.results) > n, 60)
    r = probe.results[-1]
    assert r.gains == Gains(0.6, 25.0, 30.0, 0.005, 0.007)
    assert probe.get('k_pw') == [0.6]


@pytest.mark.parametrize(
    'name, value, why',
    [
        ('k_pw', 700.0, 'range'),  # above the safe range
        ('k_pw', -0.1, 'range'),
        ('k_iw', float('nan'), ''),
        ('k_pos', float('inf'), ''),
        ('tau_eq', 'fast', 'type'),
        ('k_pw', True, 'type'),
        ('loss.penalty', 0.5, 'range'),
        ('trajectory.load_sign', 'sideways', 'load_sign'),
        ('safety.max_speed', 500.0, 'read-only'),
        ('safety.max_position_error', 5.0, 'read-only'),
        ('safety.isq_max', 20.0, 'read-only'),
    ],
)
def test_bad_parameter_values_are_rejected_with_a_reason(bench, name, value, why):
    _b, probe = bench
    before = probe.get(name)
    res = probe.set(**{name: value})
    assert not res[0].successful
    assert res[0].reason
    if why:
        assert (
            why.lower() in res[0].reason.lower()
            or 'read' in res[0].reason.lower()
            or 'type' in res[0].reason.lower()
        ), res[0].reason
    assert probe.get(name) == before


def test_set_parameters_atomically_is_all_or_nothing(bench):
    _b, probe = bench
    before = probe.get('k_pw', 'k_iw', 'k_pos', 'tau_sm', 'tau_eq')
    bad = probe.set_atomically(k_pw=0.7, k_iw=30.0, k_pos=40.0, tau_sm=0.01, tau_eq=0.5)
    assert not bad.successful and 'tau_eq' in bad.reason
    assert probe.get('k_pw', 'k_iw', 'k_pos', 'tau_sm', 'tau_eq') == before
    good = probe.set_atomically(k_pw=0.7, k_iw=30.0, k_pos=40.0, tau_sm=0.01, tau_eq=0.02)
    assert good.successful, good.reason
    r = probe.experiment()
    assert r.gains == Gains(0.7, 30.0, 40.0, 0.01, 0.02)


def test_supervisor_stops_a_destabilising_gain_set_with_the_penalty(bench):
    _b, probe = bench
    assert all(r.successful for r in probe.set(**UNSTABLE))
    r = probe.experiment()
    assert r.aborted and r.reason in ('term1', 'term2', 'term3')
    assert 0 < r.trip_step < 5625 // 2  # stopped early
    assert r.loss == pytest.approx(10.0 * sum(r.terms), rel=1e-12)
    ref = offline_losses([Gains(k_pw=0.05, k_pos=300.0)])[0]
    assert (r.loss, r.reason, r.trip_step) == (ref.loss, ref.reason, ref.trip_step)


def test_gains_refused_while_the_fallback_finishes_a_stopped_move(bench):
    """After a supervisor stop the fallback gains finish the move: new gains are refused
    until it ends (they would replace the fallback mid-move, at a wall-clock-dependent
    step), then accepted; a completed experiment followed by an aborted one logs both
    (one call site at two severities used to raise in rclpy)."""
    b, probe = bench
    assert not probe.experiment().aborted
    assert all(r.successful for r in probe.set(**UNSTABLE))
    ctl = b.controller
    n = len(ctl.results)
    assert probe.start().success
    # stop as soon as the controller has published the result (the probe would only see
    # it once the bench is idle, i.e. after the move has been finished)
    assert b.spin_until(lambda: len(ctl.results) > n, 60)
    assert ctl.results[-1].aborted
    assert not ctl.runner.ready and not ctl.runner.running  # finishing the stopped move
    step = b.drive.sim.step_index
    fut = probe.params.set_parameters_atomically([Parameter('k_pw', value=0.6)])
    # serve the call without stepping the bench: the move is still being finished
    deadline = time.monotonic() + 20
    while not fut.done() and time.monotonic() < deadline:
        b.executor.spin_once(timeout_sec=0.01)
    res = fut.result().result
    assert not res.successful and 'finishing the stopped move' in res.reason
    assert b.drive.sim.step_index == step and probe.get('k_pw') == [UNSTABLE['k_pw']]
    assert b.spin_until(lambda: ctl.runner.ready, 30)
    assert probe.set_atomically(k_pw=0.6).successful
    assert probe.get('k_pw') == [0.6]


def test_the_timing_tolerance_changes_between_experiments_only(bench):
    """``timing_tolerance`` (a tuner's ``--timing-tolerance auto`` raises it when its host
    gets louder): an integer >= 0, set between experiments and judging the next; refused
    while an experiment runs, as gains are; a double or a negative refused, unchanged."""
    b, probe = bench
    ctl = b.controller
    assert probe.get('timing_tolerance') == [0] and ctl.runner.timing_tolerance == 0
    assert probe.set_atomically(timing_tolerance=12).successful
    assert probe.get('timing_tolerance') == [12] and ctl.runner.timing_tolerance == 12
    for bad in (3.5, -1):
        assert not probe.set_atomically(timing_tolerance=bad).successful
    assert probe.get('timing_tolerance') == [12] and ctl.runner.timing_tolerance == 12
    n = len(ctl.results)
    assert probe.start().success
    fut = probe.params.set_parameters_atomically([Parameter('timing_tolerance', value=20)])
    # serve the call without stepping the bench: the experiment is still running
    deadline = time.monotonic() + 20
    while not fut.done() and time.monotonic() < deadline:
        b.executor.spin_once(timeout_sec=0.01)
    res = fut.result().result
    assert not res.successful and refusal_code(res.reason) == BUSY, res.reason
    assert ctl.runner.timing_tolerance == 12
    assert b.spin_until(lambda: len(ctl.results) > n, 60) and ctl.runner.ready
    assert probe.set_atomically(timing_tolerance=20).successful
    assert ctl.runner.timing_tolerance == 20


def test_loss_message_round_trip_is_exact():
    r = offline_losses([Gains()])[0]
    assert msg_to_result(result_to_msg(r, 'controller')) == r


def test_separate_processes_give_the_same_losses_as_one_process(procs, ros_context, tmp_path):
    """drive_sim and controller as two processes: the same losses, bit for bit -- on a
    cold numba cache (a fresh install: each compiles its kernels before it answers, so
    the first experiment is not the compiler's and is not aborted by the drive-state
    watchdog, as it was before both warmed up at start)."""
    env = {**os.environ, 'NUMBA_CACHE_DIR': str(tmp_path / 'numba')}
    drive = procs.start([ROS2, 'run', 'im_drive_sim', 'drive_sim', '--seed', str(SEED)], env=env)
    ctl = procs.start([ROS2, 'run', 'im_controller', 'controller'], env=env)
    with probe_of_children(ros_context, drive, ctl) as probe:
        got = [probe.experiment(120.0), probe.experiment(120.0)]
    ref = offline_losses([Gains(), Gains()])
    assert [g.loss for g in got] == [r.loss for r in ref]
    assert [g.terms for g in got] == [r.terms for r in ref]


class FakeDrive:
    """The controller node in this process against a hand-driven drive: ``send(k, **f)``
    publishes state k (a still motor at 0 rad unless fields ``f`` say otherwise)."""

    def __init__(self, ex, ctl, state_pub, commands, probe, wire) -> None:
        self.ex, self.ctl, self.state_pub, self.commands = ex, ctl, state_pub, commands
        self.probe, self.wire = probe, wire
        from im_drive_sim.sim import STATE_FIELDS

        self.idx = {n: i for i, n in enumerate(STATE_FIELDS)}

    def spin_until(self, pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not pred() and time.monotonic() < deadline:
            self.ex.spin_once(timeout_sec=0.005)
            self.ctl.take()
            self.ctl.answer()
            self.ctl.watchdog()
        return pred()

    def send(self, k: int, **fields: float) -> None:
        w = self.wire.values
        w[:] = 0.0
        w[0], w[1] = k, k * 200_000
        for name, v in fields.items():
            w[self.idx[name]] = v
        self.state_pub.publish(self.wire.payload())

    def answered(self, k: int, **fields: float) -> tuple:
        """Send state k and return the command that answers it."""
        self.send(k, **fields)
        assert self.spin_until(lambda: any(c[0] == k for c in self.commands[-3:]), 5), (
            f'no answer to state {k}'
        )
        return next(c for c in reversed(self.commands) if c[0] == k)


@contextlib.contextmanager
def fake_drive(ros_context, **params):
    from rclpy.executors import SingleThreadedExecutor

    from im_controller.controller_node import ControllerNode
    from im_drive_sim.cdr import Float64ArrayWire
    from im_drive_sim.contract import COMMAND_TOPIC, STATE_TOPIC
    from im_drive_sim.qos import LOCKSTEP_QOS
    from im_drive_sim.sim import STATE_FIELDS

    ctl = ControllerNode(
        context=ros_context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]
    )
    fake = Node('fake_drive', context=ros_context)
    state_pub = fake.create_publisher(Float64MultiArray, STATE_TOPIC, LOCKSTEP_QOS)
    commands: list[tuple] = []
    fake.create_subscription(
        Float64MultiArray, COMMAND_TOPIC, lambda m: commands.append(tuple(m.data)), LOCKSTEP_QOS
    )
    probe = Probe(ros_context, None)
    ex = SingleThreadedExecutor(context=ros_context)
    for n in (ctl, fake, probe.node):
        ex.add_node(n)
    fd = FakeDrive(ex, ctl, state_pub, commands, probe, Float64ArrayWire(len(STATE_FIELDS)))
    probe.spin_until = fd.spin_until
    try:
        assert fd.spin_until(lambda: state_pub.get_subscription_count() > 0, 10)
        assert fd.spin_until(probe.start_client.service_is_ready, 10)
        fd.send(0)
        assert fd.spin_until(lambda: ctl.last_state is not None, 5)
        yield fd
    finally:
        ex.shutdown()
        for n in (probe.node, fake, ctl):
            n.destroy_node()


def test_watchdog_zero_current_and_abort_when_the_drive_goes_silent(ros_context):
    """A drive that stops publishing mid-experiment: zero current, aborted with a reason."""
    # no settle: the experiment's step 0 is the first state (the fault mid-experiment)
    with fake_drive(ros_context, state_timeout=0.05, **{'trajectory.settle': 0.0}) as fd:
        ctl, probe, commands = fd.ctl, fd.probe, fd.commands
        assert probe.start().success
        for k in range(1, 50):  # a few steps of the experiment, answered one by one
            fd.answered(k)
        # The drive goes silent: within the timeout (plus polling) the watchdog fires.
        t0 = time.monotonic()
        assert fd.spin_until(lambda: ctl.runner.faulted, 5)
        assert time.monotonic() - t0 < 1.0
        assert fd.spin_until(lambda: len(probe.results) == 1, 5)
        r = probe.results[0]
        assert r.aborted and r.reason == 'drive_state_timeout' and r.steps == 50
        assert fd.spin_until(lambda: commands[-1][1:] == (0.0, 0.0), 5)  # zero current, no load
        assert commands[-1][0] == -1.0
        # A start is refused until the fault is reset ...
        resp = probe.start()
        assert not resp.success and refusal_code(resp.message) == SAFETY_FAULT
        assert 'drive_state_timeout' in resp.message  # the fault's reason code, named
        # ... and the reset is refused while the drive stays silent (a dead drive must not
        # be reset into experiment after experiment) ...
        reset_cli = probe.node.create_client(Trigger, '/controller/reset_fault')
        refused = probe.call(reset_cli.call_async(Trigger.Request()))
        assert not refused.success and refusal_code(refused.message) == NO_DRIVE_STATE
        assert ctl.runner.faulted
        # ... until the drive speaks again (here: the last state re-sent, as lock-step does)
        fd.send(50)
        assert fd.spin_until(lambda: ctl.silent_since_trip() is None, 5)
        reset = probe.call(reset_cli.call_async(Trigger.Request()))
        assert reset.success and 'drive_state_timeout' in reset.message
        assert probe.start().success


@pytest.mark.parametrize('running', [False, True], ids=['idle', 'mid-experiment'])
def test_the_tuners_goodbye_is_zero_current_at_once(ros_context, running):
    """A tuner that ends its run says goodbye (a heartbeat stamped zero, three times):
    the controller goes to zero current and FAULT (tuner_lost) at once, not
    tuner_timeout (here 30 s) later; mid-experiment the experiment is aborted with that
    reason. A second goodbye trips nothing more; the next tuner's reset clears it."""
    from std_msgs.msg import Header

    from im_controller.contract import HEARTBEAT_GOODBYES, TUNER_LOST
    from im_tuner.link import Heartbeat

    # holding between experiments, as a real bench does (answering every state)
    params = {'state_timeout': 5.0, 'tuner_timeout': 30.0, 'lockstep_idle': 'hold'}
    params['trajectory.settle'] = 0.0
    with fake_drive(ros_context, **params) as fd:
        ctl, probe = fd.ctl, fd.probe
        beat = Heartbeat(probe.node, '/controller/heartbeat', period=0.05)
        assert fd.spin_until(lambda: ctl.heartbeat_from == '/test_probe', 10)
        if running:
            assert probe.start().success
            for k in range(1, 30):
                fd.answered(k)
        t0 = time.monotonic()
        beat.stop()  # the tuner's end: its goodbye
        assert fd.spin_until(lambda: ctl.runner.faulted, 5)
        assert time.monotonic() - t0 < 5.0 and ctl.tuner_trips == 1
        assert ctl.runner.fault_reason == 'tuner_lost'
        assert fd.answered(31)[1:] == (0.0, 0.0)  # zero current, no load
        if running:
            assert fd.spin_until(lambda: len(probe.results) == 1, 5)
            assert probe.results[0].aborted and probe.results[0].reason == 'tuner_lost'
        # another goodbye (a copy, a late one) trips nothing more
        bye = probe.node.create_publisher(Header, '/controller/heartbeat', 1)
        for _ in range(HEARTBEAT_GOODBYES):
            bye.publish(Header(frame_id='/test_probe'))
        fd.spin_until(lambda: ctl.tuner_trips > 1, 0.3)
        assert ctl.tuner_trips == 1
        resp = probe.start()
        assert not resp.success and refusal_code(resp.message) == TUNER_LOST
        reset_cli = probe.node.create_client(Trigger, '/controller/reset_fault')
        assert probe.call(reset_cli.call_async(Trigger.Request())).success
        assert not ctl.runner.faulted
        if running:
            return
        # the next tuner's goodbye on the same controller, mid-experiment this time: said
        # as an error where the last was information (rclpy fixes the severity of each
        # logging call at its first use: one call for both ended the controller)
        beat = Heartbeat(probe.node, '/controller/heartbeat', period=0.05)
        assert fd.spin_until(lambda: not ctl._tuner_tripped, 10)
        assert probe.start().success
        for k in range(32, 60):
            fd.answered(k)
        beat.stop()
        assert fd.spin_until(lambda: ctl.runner.faulted, 5) and ctl.tuner_trips == 2
        assert fd.spin_until(lambda: len(probe.results) == 1, 5)
        assert probe.results[0].aborted and probe.results[0].reason == 'tuner_lost'


@pytest.mark.parametrize(
    'field, value', [('theta_meas', math.nan), ('omega_meas', math.inf), ('theta_meas', -math.inf)]
)
def test_non_finite_drive_state_zero_current_abort_and_reset(ros_context, field, value):
    """A NaN or inf in the drive state mid-experiment: that very state is answered with
    zero current and no load, the experiment ends aborted ('non_finite_measurement', not
    a loss to trust), the controller stays in FAULT (zero current) and keeps running;
    after reset_fault with a sane state it runs experiments again."""
    with fake_drive(ros_context, state_timeout=5.0, **{'trajectory.settle': 0.0}) as fd:
        ctl, probe = fd.ctl, fd.probe
        assert probe.start().success
        for k in range(1, 40):
            fd.answered(k)
        cmd = fd.answered(40, **{field: value})
        assert cmd == (40.0, 0.0, 0.0)
        assert ctl.runner.faulted and ctl.runner.fault_reason == 'non_finite_measurement'
        assert fd.spin_until(lambda: len(probe.results) == 1, 5)
        r = probe.results[0]
        assert r.aborted and r.reason == 'non_finite_measurement' and r.steps == 41
        assert math.isfinite(r.loss)
        # still alive, still safe: no start, and no reset while the state is not finite
        assert not probe.start().success
        reset_cli = probe.node.create_client(Trigger, '/controller/reset_fault')
        refused = probe.call(reset_cli.call_async(Trigger.Request()))
        assert not refused.success and refusal_code(refused.message) == STATE_NOT_FINITE
        assert ctl.runner.faulted
        # a sane state: taken but not answered (lock-step pauses in FAULT; zero current
        # was the last command), and now the reset is accepted
        fd.send(41)
        assert fd.spin_until(lambda: int(ctl.last_state[0]) == 41, 5)
        assert fd.commands[-1] == (40.0, 0.0, 0.0)
        reset = probe.call(reset_cli.call_async(Trigger.Request()))
        assert reset.success and 'non_finite_measurement' in reset.message
        assert not ctl.runner.faulted
        assert probe.start().success
        isq = [fd.answered(k)[1] for k in range(42, 60)]
        assert all(math.isfinite(x) for x in isq)


def test_a_fault_in_the_settle_ends_the_experiment_before_step_0(ros_context):
    """A NaN in the settle (the fallback gains holding, before step 0): zero current at
    once, the experiment ends aborted with no step measured -- the tuner re-runs such an
    experiment and never tells it as a loss (its loss, 0, measured nothing)."""
    with fake_drive(ros_context, state_timeout=5.0) as fd:
        ctl, probe = fd.ctl, fd.probe
        assert probe.start().success
        for k in range(1, 30):
            assert fd.answered(k)[2] == 0.0  # no load in the settle
        assert fd.answered(30, theta_meas=math.nan) == (30.0, 0.0, 0.0)
        assert fd.spin_until(lambda: len(probe.results) == 1, 5)
        r = probe.results[0]
        assert r.aborted and r.reason == 'non_finite_measurement' and r.steps == 0
        assert r.t_start == 30 * 200_000 and ctl.runner.faulted


def test_real_time_mode_runs_an_experiment(procs, ros_context):
    """drive_sim and controller both in real time (5 kHz wall clock), two processes."""
    drive = procs.start([ROS2, 'run', 'im_drive_sim', 'drive_sim', '--mode', 'realtime'])
    ctl = procs.start([ROS2, 'run', 'im_controller', 'controller', '--mode', 'realtime'])
    with probe_of_children(ros_context, drive, ctl) as probe:
        t0 = time.monotonic()
        r = probe.experiment(30.0)
        wall = time.monotonic() - t0
    # On the drive's timeline: the experiment spans drive periods, however many states
    # the controller (its own process: it misses many on a 2-core machine) could answer
    # in time; each period was fresh, held or late, and the result says whether it ran on
    # the paper's timing (tolerance 0, the default). A controller that misses most states
    # may be stopped by the supervisor: then it is flagged too.
    assert r.fresh + r.held + r.late == r.steps
    assert r.timing == (r.held + r.late > 0)
    assert wall < 8.0  # no hang
    if r.aborted:
        assert r.timing and r.steps == r.trip_step + 1, r
        return
    # paced by the wall clock: 1.125 s of experiment takes at least that long (lock-step
    # on an idle bench would take ~0.1 s); exactly 5625 drive periods
    assert wall > 1.0 and r.steps == 5625 and r.t_end - r.t_start == 1_125_000_000, (wall, r)
    if not r.timing:  # commands all in time: the loss is close to lock-step's
        assert r.loss == pytest.approx(offline_losses([Gains()])[0].loss, rel=0.5)


@pytest.mark.parametrize(
    'args, expect',
    [
        (['--ros-args', '-p', 'k_pw:=900.0'], 'k_pw'),
        (['--ros-args', '-p', 'k_pw:=abc'], 'k_pw'),
        (['--ros-args', '-p', 'mode:=fast'], "'mode'"),
        (['--ros-args', '-p', 'safety.max_speed:=-1.0'], 'safety.max_speed'),
        (['--drive-config', '/nonexistent/motor.yaml'], 'motor.yaml'),
    ],
)
def test_bad_start_up_input_is_one_line_and_exit_2(procs, args, expect):
    p = procs.start([ROS2, 'run', 'im_controller', 'controller', *args])
    _, err = p.communicate(timeout=30)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1, err
    assert lines[0].startswith('error: controller:') and expect in lines[0]


def test_start_overrides_say_what_the_node_enforces(ros_context):
    """`-p safety.isq_max:=2.0` at start is applied (a tighter clamp; the drive
    file's 7 A is the ceiling): get_parameters says 2.0 and the controller commands at most
    2 A, where the 7 A controller commands 5.55 A. An integer for a double (`k_iw:=25`) is
    taken at start as through set_parameters. A typo'd override, which neither the drive
    nor the controller composed with it declares, is refused by name; so is a request to
    set an undeclared parameter."""
    with pytest.raises(ParameterOverrideError, match='no such parameter: k_pww'):
        InProcessBench(context=ros_context, controller_overrides=[Parameter('k_pww', value=1.0)])
    b = InProcessBench(
        context=ros_context,
        drive_overrides=[Parameter('seed', value=SEED)],
        controller_overrides=[
            Parameter('safety.isq_max', value=2.0),
            Parameter('k_iw', value=25),
        ],
    )
    probe = Probe(ros_context, b.spin_until)
    b.executor.add_node(probe.node)
    try:
        probe.ready()
        assert probe.get('safety.isq_max', 'k_iw') == [2.0, 25.0]
        r = probe.experiment()
        assert r.gains == Gains(k_iw=25.0)
        col = INTERNALS_FIELDS.index('isq_cmd')
        exp = [x for x in probe.internals if int(x[INTERNALS_FIELDS.index('exp_step')]) >= 0]
        isq = np.array([x[col] for x in exp])
        assert np.max(np.abs(isq)) == 2.0  # clamped there, and the clamp is reached
        res = probe.set(k_pww=3.0)
        assert not res[0].successful and 'k_pww' in res[0].reason
    finally:
        probe.node.destroy_node()
        b.destroy()
