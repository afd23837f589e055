"""check_drive's probe: drives the check through DDS, records every state, joint state
and command it sees, and hands the records to the judges (:func:`run_check`)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..contract import COMMAND_TOPIC, JOINT_STATE_TOPIC, STATE_TOPIC, STATUS_TOPIC
from .evaluate import Recording, evaluate
from .judges import (
    watchdog_limits,
)
from .thresholds import (
    DEFAULT_TIMEOUT,
    DISCOVERY_SETTLE_S,
    LOCKSTEP_SILENCE_S,
    NS_PER_S,
    STATE_FIELDS,
    WATCHDOG_ACT_FRACTION,
    ZERO_CURRENT_FRACTION,
    CheckRefused,
    F,
    Item,
)

# ======================================= the probe ==========================================


class Interrupted(Exception):
    """SIGINT/SIGTERM during the check."""


class DriveLost(Exception):
    """The drive stopped publishing states in the middle of the check: exit code 1."""


class Probe:
    """Records every drive/state (with its DDS time stamps), joint state and command."""

    def __init__(self, node, capacity: int = 60000) -> None:
        # ROS imports here, not at module level: the judging functions need none.
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray

        from im_drive_sim.cdr import parse_float64_array

        self.node = node
        self._parse, self._deserialize = parse_float64_array, deserialize_message
        self._Float64MultiArray, self._JointState = Float64MultiArray, JointState
        self._DiagnosticArray = DiagnosticArray
        # A deep keep-last reader: a stall of this process up to 1 s loses nothing, and
        # the drive's reliable writer is never held back by it.
        deep = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=5000,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        noop = lambda _m: None  # noqa: E731 (taken by hand, never by an executor)
        self.state_sub = node.create_subscription(Float64MultiArray, STATE_TOPIC, noop, deep)
        self.joint_sub = node.create_subscription(JointState, JOINT_STATE_TOPIC, noop, 1000)
        self.status_sub = node.create_subscription(DiagnosticArray, STATUS_TOPIC, noop, 10)
        self.cmd_pub = None
        self.stopped = False
        self.waitset = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)
        n = capacity
        self.states = np.full((n, len(STATE_FIELDS)), np.nan)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.source_ns = np.zeros(n, dtype=np.int64)  # drive's publication time [ns, wall]
        self.recv_ns = np.zeros(n, dtype=np.int64)  # DDS reception time [ns, wall]
        self.take_ns = np.zeros(n, dtype=np.int64)  # when this process took it [ns, wall]
        self.seq = np.zeros(n, dtype=np.int64)
        self.n = 0
        self.cmd = np.zeros((n, 3))  # answers_step, isq*, load
        self.cmd_ns = np.zeros(n, dtype=np.int64)  # published at [ns, wall]
        self.m = 0
        self.joints: list[tuple[float, float, float, float]] = []
        self.status: dict[str, str] = {}
        self.answered = -1  # newest step index we answered
        self.created = time.monotonic()  # when this participant joined
        self.stop: Callable[[], bool] = lambda: False

    def open_command(self) -> None:
        from im_drive_sim.drive_sim_node import RECORDED_QOS

        self.cmd_pub = self.node.create_publisher(
            self._Float64MultiArray, COMMAND_TOPIC, RECORDED_QOS
        )
        self._cmd_msg = self._Float64MultiArray(data=[0.0, 0.0, 0.0])

    def poll(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for states; take every pending message. Returns the
        number of new states."""
        if self.stop():
            raise Interrupted
        ws = self.waitset
        ws.clear_entities()
        ws.add_subscription(self.state_sub.handle)
        ws.wait(int(max(0.0, timeout_s) * NS_PER_S))
        got = 0
        width = len(STATE_FIELDS)
        while self.n < len(self.states):
            r = self.state_sub.handle.take_message(self._Float64MultiArray, True)
            if r is None:
                break
            raw, info = r
            data = self._parse(raw, width)  # our compact layout, straight into numpy
            if data is None:  # another layout: the general way
                data = np.asarray(self._deserialize(raw, self._Float64MultiArray).data)
            i = self.n
            self.lengths[i] = len(data)
            if len(data) == width:
                self.states[i] = data
            self.source_ns[i] = info['source_timestamp']
            self.recv_ns[i] = info.get('received_timestamp') or time.time_ns()
            self.take_ns[i] = time.time_ns()
            self.seq[i] = info.get('publication_sequence_number') or 0
            self.n += 1
            got += 1
        while (r := self.joint_sub.handle.take_message(self._JointState, False)) is not None:
            j = r[0]
            if len(j.position) and len(j.velocity) and len(j.effort):
                self.joints.append(
                    (
                        j.header.stamp.sec * NS_PER_S + j.header.stamp.nanosec,
                        j.position[0],
                        j.velocity[0],
                        j.effort[0],
                    )
                )
        while (r := self.status_sub.handle.take_message(self._DiagnosticArray, False)) is not None:
            for st in r[0].status:
                self.status = {kv.key: kv.value for kv in st.values}
        return got

    def newest(self) -> np.ndarray | None:
        """The newest complete state taken (a view), or None."""
        for i in range(self.n - 1, -1, -1):
            if self.lengths[i] == len(STATE_FIELDS):
                return self.states[i]
        return None

    def command(self, answers: int, isq: float, load: float = 0.0) -> None:
        msg = self._cmd_msg
        msg.data[0], msg.data[1], msg.data[2] = float(answers), float(isq), float(load)
        self.cmd_pub.publish(msg)
        if self.m < len(self.cmd):
            self.cmd[self.m] = (answers, isq, load)
            self.cmd_ns[self.m] = time.time_ns()
            self.m += 1
        self.answered = max(self.answered, answers)

    def run(
        self,
        policy: Callable[[int, np.ndarray], float | None],
        done: Callable[[], bool],
        max_wall: float,
    ) -> bool:
        """Answer each new state k with isq* = policy(k, state) (None: stay silent) until
        ``done()``; False when ``max_wall`` s passed first."""
        deadline = time.monotonic() + max_wall
        while not done():
            if time.monotonic() > deadline:
                return False
            if self.poll(min(0.05, max(0.0, deadline - time.monotonic()))) == 0:
                continue
            s = self.newest()
            if s is None:
                continue
            k = int(s[F['step_index']])
            if k <= self.answered:
                continue  # a re-sent state (lock-step) or one already answered
            isq = policy(k, s)
            if isq is not None:
                self.command(k, isq)
        return True

    def safe_stop(self) -> None:
        """Leave the drive commanding zero current (and no load); once."""
        if self.cmd_pub is None or self.stopped:
            return
        self.stopped = True
        from rclpy.duration import Duration

        s = self.newest()
        k = int(s[F['step_index']]) if s is not None else -1
        self.command(k if k > self.answered else -1, 0.0)
        self.command(-1, 0.0)
        # Delivered before this process goes (reliable only promises it while we live).
        self.cmd_pub.wait_for_all_acked(Duration(seconds=0.3))


@dataclass
class Options:
    config: str | None = None
    amplitude: float = 0.5
    step_duration: float = 0.02
    command_timeout: float | None = None
    max_speed: float = 30.0
    timeout: float = 10.0
    namespace: str | None = None
    json: str | None = None


def run_check(
    opts: Options, node, log: Callable[[str], None], stop: Callable[[], bool]
) -> tuple[list[Item], dict]:
    """Probe the drive in ``node``'s namespace; return the items and run information."""
    from im_drive_sim.params import load_config

    cfg = load_config(opts.config)
    isq_max = cfg.machine.isq_max
    if not 0 < opts.amplitude <= 0.5 * isq_max:
        raise CheckRefused(
            f'--amplitude {opts.amplitude:g} A: must be in (0, '
            f'{0.5 * isq_max:g}] A (50 % of isq_max {isq_max:g} A)'
        )
    p = Probe(node)
    p.stop = stop
    state_topic = p.state_sub.topic_name
    cmd_topic = node.resolve_topic_name(COMMAND_TOPIC)

    # -- discovery --------------------------------------------------------------------
    deadline = time.monotonic() + opts.timeout
    while not node.get_publishers_info_by_topic(state_topic):
        if time.monotonic() > deadline:
            raise CheckRefused(
                f'no publisher of {state_topic} within {opts.timeout:g} s '
                '(is the drive running, in this namespace and ROS_DOMAIN_ID?)'
            )
        p.poll(0.05)
    # Node names arrive a moment after the endpoints; other commanders with them.
    settle = time.monotonic() + 0.5
    drive_name = drive_ns = None
    while time.monotonic() < settle or drive_name is None:
        pubs = node.get_publishers_info_by_topic(state_topic)
        known = [e for e in pubs if not e.node_name.startswith('_NODE_NAME_UNKNOWN')]
        if known:
            drive_name, drive_ns = known[0].node_name, known[0].node_namespace
        if time.monotonic() > settle + 2.0:
            break
        if node.get_publishers_info_by_topic(cmd_topic):
            _refuse_commander(node, cmd_topic, p)
        p.poll(0.05)
    drive_full = (drive_ns.rstrip('/') + '/' + drive_name) if drive_name else '(unknown node)'

    timeout, timeout_src = _command_timeout(opts, node, drive_name, drive_ns)
    p.open_command()
    try:
        return _probe(
            p, opts, node, cfg, drive_full, timeout, timeout_src, state_topic, cmd_topic, log
        )
    finally:
        p.safe_stop()  # zero current, whatever happened (also on SIGINT and errors)


def _probe(
    p: Probe,
    opts: Options,
    node,
    cfg,
    drive_full: str,
    timeout: float,
    timeout_src: str,
    state_topic: str,
    cmd_topic: str,
    log: Callable[[str], None],
) -> tuple[list[Item], dict]:
    ts, ts_ns = cfg.Ts, cfg.Ts_ns
    isq_max = cfg.machine.isq_max
    a = opts.amplitude
    counts_per_rad = cfg.sensors.encoder_counts / (2.0 * math.pi)

    info = {
        'drive': drive_full,
        'namespace': node.get_namespace(),
        'Ts_s': ts,
        'isq_max_A': isq_max,
        'amplitude_A': a,
        'command_timeout_s': timeout,
        'command_timeout_source': timeout_src,
    }

    def check_alone() -> None:
        if len(node.get_publishers_info_by_topic(cmd_topic)) > 1:
            _refuse_commander(node, cmd_topic, p)

    # -- mode: does step_index advance without commands? ---------------------------------
    if not p.run(lambda k, s: None, lambda: p.newest() is not None, opts.timeout):
        raise CheckRefused(
            f'{state_topic} has a publisher but no state came within {opts.timeout:g} s'
        )
    k_idle0 = int(p.newest()[F['step_index']])
    t_end = time.monotonic() + 0.3
    p.run(lambda k, s: None, lambda: time.monotonic() > t_end, 1.0)
    idle_advance = int(p.newest()[F['step_index']]) - k_idle0
    realtime = idle_advance >= 5
    mode = 'realtime' if realtime else 'lockstep'
    status_mode = p.status.get('mode')
    mode_note = ''
    if status_mode is not None and status_mode != mode:
        mode_note = f'drive/status says mode={status_mode}'
    info['mode'] = mode
    log(
        f'check_drive: drive {drive_full}, mode {mode} (by behaviour; drive/status: '
        f'{status_mode or "not seen yet"}), Ts {ts * 1e6:g} us, isq_max {isq_max:g} A, '
        f'step +-{a:g} A, command_timeout {timeout:g} s ({timeout_src})'
    )
    check_alone()

    def schedule(
        segments: list[tuple[int, float]],
        record: list | None = None,
        guard: Callable[[np.ndarray], bool] | None = None,
    ) -> int:
        """Answer states with piecewise-constant isq*: ``segments`` of (steps, isq*),
        counted in step indices from the first state answered. ``record`` collects
        (k, level, previous level) at every change; ``guard(state)`` True aborts to zero.
        Returns the first step index answered."""
        total = sum(n for n, _ in segments)
        bounds = np.cumsum([n for n, _ in segments])
        st = {'k0': None, 'last': None, 'done': False}

        def policy(k: int, s: np.ndarray) -> float | None:
            if st['k0'] is None:
                st['k0'] = k
            rel = k - st['k0']
            if guard is not None and guard(s):
                st['done'] = True
                return 0.0  # abort to zero current at once
            if rel >= total:
                st['done'] = True
                return None  # the next phase answers this state
            level = segments[int(np.searchsorted(bounds, rel, side='right'))][1]
            if record is not None and level != st['last']:
                record.append((k, level, 0.0 if st['last'] is None else st['last']))
            st['last'] = level
            return level

        if not p.run(policy, lambda: st['done'], 5.0 + total * ts * 20):
            raise DriveLost(
                f'the drive stopped stepping (last state '
                f'{int(p.newest()[0])}, {p.n} states received)'
            )
        return st['k0']

    # -- rate: zero current, answer every state; and no current before the whole graph is
    # known (another commander discovered late must still refuse the check) -------------
    i_rate0, m_rate0 = p.n, p.m
    t0 = time.monotonic()
    while True:
        schedule([(2500 if realtime else 500, 0.0)])
        if time.monotonic() >= p.created + DISCOVERY_SETTLE_S:
            break
    rate_wall = time.monotonic() - t0
    i_rate1 = p.n
    check_alone()

    # -- latency: small level changes, every 25 steps -----------------------------------
    trans: list[tuple[int, float, float]] = []
    levels = [0.0, a, 0.0, -a, 0.0, a, 0.0, -a, 0.0]
    schedule([(25, lv) for lv in levels], trans)

    # -- step response ----------------------------------------------------------------
    n_step = max(10, round(opts.step_duration / ts))
    step_trans: list[tuple[int, float, float]] = []
    aborted = {'why': ''}

    def overspeed(s: np.ndarray) -> bool:
        if abs(s[F['omega_meas']]) > opts.max_speed:
            aborted['why'] = (
                f'aborted: |omega_meas| {abs(s[F["omega_meas"]]):.1f} > {opts.max_speed:g} rad/s'
            )
            return True
        return False

    schedule([(25, 0.0), (n_step, a), (n_step, -a), (n_step // 2, 0.0)], step_trans, overspeed)
    k_step_end = p.answered
    check_alone()

    # -- watchdog -----------------------------------------------------------------------
    w = a / 2
    if realtime:
        wd = _watchdog_realtime(p, schedule, w, timeout, overspeed, ts)
    else:
        wd = _watchdog_lockstep(p)
    schedule([(50 if realtime else 10, 0.0)])
    check_alone()
    # A status message (about 1 Hz) to cross-check the mode, if none came yet.
    if status_mode is None and realtime:
        t_end = time.monotonic() + 1.2
        p.run(lambda k, s: 0.0, lambda: bool(p.status) or time.monotonic() > t_end, 2.0)
        status_mode = p.status.get('mode')
        if status_mode is not None and status_mode != mode:
            mode_note = f'drive/status says mode={status_mode}'
    info['status_mode'] = status_mode
    p.safe_stop()  # before judging: the drive is not left waiting for commands meanwhile

    rec = Recording(
        states=p.states[: p.n].copy(),
        lengths=p.lengths[: p.n].copy(),
        source_ns=p.source_ns[: p.n].copy(),
        recv_ns=p.recv_ns[: p.n].copy(),
        take_ns=p.take_ns[: p.n].copy(),
        seq=p.seq[: p.n].copy(),
        cmd=p.cmd[: p.m].copy(),
        cmd_ns=p.cmd_ns[: p.m].copy(),
        joints=np.array(p.joints, dtype=float).reshape(-1, 4),
        endpoints={
            STATE_TOPIC: [e.topic_type for e in node.get_publishers_info_by_topic(state_topic)],
            COMMAND_TOPIC: [e.topic_type for e in node.get_subscriptions_info_by_topic(cmd_topic)],
            JOINT_STATE_TOPIC: [
                e.topic_type
                for e in node.get_publishers_info_by_topic(
                    node.resolve_topic_name(JOINT_STATE_TOPIC)
                )
            ],
            STATUS_TOPIC: [
                e.topic_type
                for e in node.get_publishers_info_by_topic(node.resolve_topic_name(STATUS_TOPIC))
            ],
        },
        ts=ts,
        ts_ns=ts_ns,
        isq_max=isq_max,
        rated_flux_current=cfg.machine.rated_flux_current,
        counts_per_rad=counts_per_rad,
        amplitude=a,
        realtime=realtime,
        idle_advance=idle_advance,
        mode_note=mode_note,
        i_rate0=i_rate0,
        i_rate1=i_rate1,
        m_rate0=m_rate0,
        rate_wall=rate_wall,
        trans=trans,
        step_trans=step_trans,
        k_step_end=k_step_end,
        aborted_why=aborted['why'],
        watchdog=wd,
        command_timeout=timeout,
        command_timeout_source=timeout_src,
    )
    return evaluate(rec), info


def _watchdog_realtime(p: Probe, schedule, w: float, timeout: float, overspeed, ts: float) -> dict:
    """Command w, go silent until zero current (or too long), then command -w for as long
    as w was on (so the shaft ends near rest) and check that the current follows."""
    _lo, hi = watchdog_limits(timeout)
    i_on = p.n
    schedule([(25, w)])
    i_silent, t_last = p.n, p.cmd_ns[p.m - 1]
    st = {'zero_at': None, 'zero_run': 0, 'why': ''}
    end = time.monotonic() + 2 * hi + 0.05

    def silent(k: int, s: np.ndarray) -> None:
        return None

    def done() -> bool:
        for i in range(st.get('i', i_silent), p.n):
            s = p.states[i]
            if abs(s[F['isq']]) < ZERO_CURRENT_FRACTION * w:
                if st['zero_at'] is None:
                    st['zero_at'] = i
                st['zero_run'] += 1
            else:
                st['zero_at'], st['zero_run'] = None, 0
            if overspeed(s):
                st['why'] = 'aborted silence: overspeed'
        st['i'] = p.n
        return st['zero_run'] >= 10 or bool(st['why']) or time.monotonic() > end

    p.run(silent, done, 2 * hi + 1.0)
    t_zero = t_act = None
    if st['zero_at'] is not None:
        t_zero = (p.source_ns[st['zero_at']] - t_last) * 1e-9
        i = st['zero_at']  # back along the fall to where it began
        while i > i_silent and p.states[i - 1, F['isq']] < WATCHDOG_ACT_FRACTION * w:
            i -= 1
        t_act = (p.source_ns[i] - t_last) * 1e-9
    if st['why']:
        p.command(max(p.answered, int(p.newest()[0])), 0.0)
    # Steps at +w: as many at -w bring the shaft back near rest.
    on = int(np.count_nonzero(p.states[i_on : p.n, F['isq']] > w / 2))
    # resume with -w; it must reach -w within 50 ms
    i_res, j_res, t_res = p.n, p.m, None
    k_res = schedule([(max(on, 50), -w)])
    for i in range(i_res, p.n):
        s = p.states[i]
        if s[F['step_index']] > k_res and abs(s[F['isq']] + w) < ZERO_CURRENT_FRACTION * w:
            t_res = (p.source_ns[i] - p.cmd_ns[j_res]) * 1e-9
            break
    if t_res is not None and t_res > 0.05:
        t_res = None
    return {'t_act': t_act, 't_zero': t_zero, 'resumed_s': t_res, 'aborted': st['why']}


def _watchdog_lockstep(p: Probe) -> dict:
    """Silence for LOCKSTEP_SILENCE_S: only re-sends of the same state allowed; then one
    command must make it step."""
    k_last = p.answered
    t0 = time.monotonic()
    i0 = p.n
    p.run(lambda k, s: None, lambda: time.monotonic() - t0 >= LOCKSTEP_SILENCE_S, 2.0)
    silence = time.monotonic() - t0
    ks = p.states[i0 : p.n, F['step_index']]
    advanced = int(np.count_nonzero(ks > k_last + 1))
    s = p.newest()
    k = int(s[F['step_index']])
    t1 = time.monotonic()
    p.command(k, 0.0)
    resumed = None
    while time.monotonic() - t1 < 2.0:
        p.poll(0.05)
        if int(p.newest()[F['step_index']]) > k:
            resumed = time.monotonic() - t1
            break
    return {'silence_s': silence, 'advanced': advanced, 'resumed_s': resumed}


def _clean(obj):
    """JSON-ready: non-finite floats -> None, numpy scalars -> Python."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def _refuse_commander(node, topic: str, p: Probe) -> None:
    """Raise CheckRefused naming the other publishers of ``topic`` (their node names are
    discovered a moment after the endpoints: wait up to 1 s for them)."""
    deadline = time.monotonic() + 1.0
    while True:
        others = [
            e
            for e in node.get_publishers_info_by_topic(topic)
            if not (e.node_name == node.get_name() and e.node_namespace == node.get_namespace())
        ]
        if time.monotonic() > deadline or not any(
            e.node_name.startswith('_NODE_NAME_UNKNOWN') for e in others
        ):
            break
        p.poll(0.05)
    names = sorted({(e.node_namespace.rstrip('/') + '/' + e.node_name) for e in others})
    raise CheckRefused(
        f'{", ".join(names) or "another node"} already publishes {topic}: a '
        'controller is connected and two commanders would fight; stop it first'
    )


def _command_timeout(
    opts: Options, node, drive_name: str | None, drive_ns: str | None
) -> tuple[float, str]:
    """The expected watchdog time: --command-timeout, else the drive node's
    ``command_timeout`` parameter, else 0.05 s."""
    if opts.command_timeout is not None:
        return opts.command_timeout, '--command-timeout'
    if drive_name is None:
        return DEFAULT_TIMEOUT, 'default'
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import GetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    helper = Node('check_drive_params', context=node.context)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(helper)
    try:
        srv = drive_ns.rstrip('/') + '/' + drive_name + '/get_parameters'
        client = helper.create_client(GetParameters, srv)
        if not client.wait_for_service(timeout_sec=2.0):
            return DEFAULT_TIMEOUT, 'default: drive has no parameter service'
        future = client.call_async(GetParameters.Request(names=['command_timeout']))
        executor.spin_until_future_complete(future, timeout_sec=3.0)
        res = future.result()
        if res is None:
            return DEFAULT_TIMEOUT, 'default: no parameter answer'
        v = res.values[0] if res.values else None
        if v is not None and v.type == ParameterType.PARAMETER_DOUBLE:
            return float(v.double_value), 'drive parameter'
        return DEFAULT_TIMEOUT, 'default: drive has no command_timeout'
    finally:
        executor.shutdown()
        helper.destroy_node()
