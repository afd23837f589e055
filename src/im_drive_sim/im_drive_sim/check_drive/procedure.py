"""check_drive's procedure: what the check does to the drive, in order -- find it (and
refuse to run beside another commander), learn its command timeout, then the items'
experiments (mode, fields, rate, latency, step response, watchdog) through a
:class:`~.probe.Probe`, whose recording :func:`~.evaluate.evaluate` judges
(:func:`run_check`). ROS is imported inside the functions: importing this module needs
none."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..contract import COMMAND_TOPIC, STATE_INDEX as F, TOPIC_TYPES
from ..rt import RtOptions
from . import thresholds as TH
from .evaluate import Recording, evaluate
from .probe import DriveLost, Probe
from .response import watchdog_limits


@dataclass
class Options:
    drive_config: str | None = None
    amplitude: float = 0.5
    step_duration: float = 0.02
    command_timeout: float | None = None
    max_speed: float = 30.0
    timeout: float = 10.0
    namespace: str | None = None
    json: Path | None = None
    #: the check's own scheduling (``--thread-priority`` ...; :mod:`im_drive_sim.rt`)
    rt: RtOptions = field(default_factory=RtOptions)


def run_check(
    opts: Options, node, log: Callable[[str], None], stop: Callable[[], bool]
) -> tuple[list[TH.Item], dict]:
    """Probe the drive in ``node``'s namespace; return the items and run information."""
    from im_drive_sim.drive_file import load_config

    cfg = load_config(opts.drive_config)
    isq_max = cfg.machine.isq_max
    if not 0 < opts.amplitude <= 0.5 * isq_max:
        raise TH.CheckRefused(
            f'--amplitude {opts.amplitude:g} A: must be in (0, '
            f'{0.5 * isq_max:g}] A (50 % of isq_max {isq_max:g} A)'
        )
    p = Probe(node)
    p.stop = stop
    state_topic = p.state_sub.topic_name
    cmd_topic = node.resolve_topic_name(COMMAND_TOPIC)

    # -- discovery -----------------------------------------------------------------------------
    deadline = time.monotonic() + opts.timeout
    while not node.get_publishers_info_by_topic(state_topic):
        if time.monotonic() > deadline:
            raise TH.CheckRefused(
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
    # the drive must know our publisher before it is judged (a simulator in real time
    # starts its clock only then; across a network matching takes a moment)
    deadline = time.monotonic() + opts.timeout
    while p.cmd_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        p.poll(0.02)
    try:
        ts, ts_ns = cfg.Ts, cfg.Ts_ns
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

        # -- mode: does step_index advance without commands? -----------------------------------
        if not p.run(lambda k, s: None, lambda: p.newest() is not None, opts.timeout):
            raise TH.CheckRefused(
                f'{state_topic} has a publisher but no state came within {opts.timeout:g} s'
            )
        k_idle0 = int(p.newest()[F['step_index']])
        t0, n0 = time.monotonic(), p.n

        def decided() -> bool:
            # Real time: the step index advances without commands. Lock-step: the drive
            # re-sends the same state while it waits (every 0.1 s). At least 0.3 s; then as
            # long as neither is seen, up to --timeout: a drive in real time may start its
            # clock only once it has matched our publisher (the simulator waits for a
            # commander), which takes a moment after a process start or across a network.
            waited = time.monotonic() - t0
            moved = int(p.newest()[F['step_index']]) - k_idle0
            resent = int(np.count_nonzero(p.states[n0 : p.n, F['step_index']] == k_idle0))
            return waited > opts.timeout or (waited > 0.3 and (moved >= 5 or resent >= 3))

        p.run(lambda k, s: None, decided, opts.timeout + 1.0)
        idle_advance = int(p.newest()[F['step_index']]) - k_idle0
        realtime = idle_advance >= 5
        mode = 'realtime' if realtime else 'lockstep'
        status_mode = p.status.get('mode')
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
            if time.monotonic() >= p.created + TH.DISCOVERY_SETTLE_S:
                break
        rate_wall = time.monotonic() - t0
        phases = {'rate': (i_rate0, p.n)}
        check_alone()

        # -- latency: small level changes, every 25 steps --------------------------------------
        trans: list[tuple[int, float, float]] = []
        levels = [0.0, a, 0.0, -a, 0.0, a, 0.0, -a, 0.0]
        i0 = p.n
        schedule([(25, lv) for lv in levels], trans)
        phases['latency'] = (i0, p.n)

        # -- step response ---------------------------------------------------------------------
        n_step = max(10, round(opts.step_duration / ts))
        step_trans: list[tuple[int, float, float]] = []
        aborted = {'why': ''}

        def overspeed(s: np.ndarray) -> bool:
            speed = abs(s[F['omega_meas']])
            if speed > opts.max_speed:
                aborted['why'] = f'aborted: |omega_meas| {speed:.1f} > {opts.max_speed:g} rad/s'
                return True
            return False

        i0 = p.n
        schedule([(25, 0.0), (n_step, a), (n_step, -a), (n_step // 2, 0.0)], step_trans, overspeed)
        phases['step'] = (i0, p.n)
        k_step_end = p.answered
        check_alone()

        # -- watchdog --------------------------------------------------------------------------
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
        info['status_mode'] = status_mode
        mode_note = (
            f'drive/status says mode={status_mode}' if status_mode not in (None, mode) else ''
        )
        p.safe_stop()  # before judging: the drive is not left waiting for commands meanwhile

        rec = Recording(
            **{
                k: getattr(p, k)[: p.n].copy()
                for k in ('states', 'lengths', 'source_ns', 'recv_ns', 'take_ns', 'seq')
            },
            cmd=p.cmd[: p.m].copy(),
            cmd_ns=p.cmd_ns[: p.m].copy(),
            joints=np.array(p.joints, dtype=float).reshape(-1, 4),
            endpoints={
                topic: [
                    e.topic_type
                    for e in (
                        node.get_subscriptions_info_by_topic(cmd_topic)
                        if topic == COMMAND_TOPIC
                        else node.get_publishers_info_by_topic(node.resolve_topic_name(topic))
                    )
                ]
                for topic in TOPIC_TYPES
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
            m_rate0=m_rate0,
            rate_wall=rate_wall,
            trans=trans,
            step_trans=step_trans,
            k_step_end=k_step_end,
            aborted_why=aborted['why'],
            step_steps=n_step,
            watchdog=wd,
            phases=phases,
            command_timeout=timeout,
            command_timeout_source=timeout_src,
        )
        kept_up: dict = {}
        items = evaluate(rec, kept_up)
        info['conditions'] = kept_up
        return items, info
    finally:
        p.safe_stop()  # zero current, whatever happened (also on SIGINT and errors)


def _watchdog_realtime(p: Probe, schedule, w: float, timeout: float, overspeed, ts: float) -> dict:
    """Command w, go silent until zero current (or too long), then command -w for as long
    as w was on (so the shaft ends near rest) and check that the current follows.

    Times are on the drive's clock from the state in which the drive first shows the last
    command applied (its ``applied_step`` label): neither the link's delay nor the offset
    of two computers' clocks enters. A drive whose labels never show it is timed from the
    check's publication instead (``ref``)."""
    _lo, hi = watchdog_limits(timeout)
    i_on = p.n
    schedule([(25, w)])
    i_silent, t_last, k_last = p.n, int(p.cmd_ns[p.m - 1]), int(p.cmd[p.m - 1, 0])
    st: dict = {'zero_at': None, 'zero_run': 0, 'why': '', 'ref': None, 'i': i_on}
    end = time.monotonic() + 2 * hi + 1.0

    def covered() -> float:
        """The drive's time [s] from ``ref`` (else our last command) to its newest state."""
        ref = st['ref'] if st['ref'] is not None else t_last
        return (int(p.source_ns[p.n - 1]) - ref) * 1e-9 if p.n > i_silent else 0.0

    def done() -> bool:
        for i in range(st['i'], p.n):
            s = p.states[i]
            if st['ref'] is None and s[F['applied_step']] >= k_last:
                st['ref'] = int(p.source_ns[i])  # the drive applied our last command
                st['ref_step'] = int(s[F['step_index']])
            if i < i_silent:
                continue
            if abs(s[F['isq']]) < TH.ZERO_CURRENT_FRACTION * w:
                if st['zero_at'] is None:
                    st['zero_at'] = i
                st['zero_run'] += 1
            else:
                st['zero_at'], st['zero_run'] = None, 0
            if overspeed(s):
                st['why'] = 'aborted silence: overspeed'
        st['i'] = p.n
        return (
            st['zero_run'] >= 10 or bool(st['why']) or covered() > 2 * hi or time.monotonic() > end
        )

    p.run(lambda k, s: None, done, 2 * hi + 1.5)  # silent
    ref, coverage = st['ref'] if st['ref'] is not None else t_last, covered()
    t_zero = t_act = t_before = None
    if st['zero_at'] is not None:
        t_zero = (p.source_ns[st['zero_at']] - ref) * 1e-9
        i = st['zero_at']  # back along the fall to where it began
        while i > i_silent and p.states[i - 1, F['isq']] < TH.WATCHDOG_ACT_FRACTION * w:
            i -= 1
        t_act = (p.source_ns[i] - ref) * 1e-9
        # the last state received before it, still carrying the current: the fall began
        # after it (states lost in between leave the time between the two open)
        t_before = (p.source_ns[i - 1] - ref) * 1e-9 if i > i_silent else None
    if st['why']:
        p.command(max(p.answered, int(p.newest()[0])), 0.0)
    # Steps at +w: as many at -w bring the shaft back near rest.
    on = int(np.count_nonzero(p.states[i_on : p.n, F['isq']] > w / 2))
    # resume with -w; it must reach -w within 50 ms (the check's clock: publication to
    # reception, so the link's delay both ways is inside)
    i_res, j_res, t_res = p.n, p.m, None
    k_res = schedule([(max(on, 50), -w)])
    for i in range(i_res, p.n):
        s = p.states[i]
        if s[F['step_index']] > k_res and abs(s[F['isq']] + w) < TH.ZERO_CURRENT_FRACTION * w:
            t_res = (p.recv_ns[i] - p.cmd_ns[j_res]) * 1e-9
            break
    if t_res is not None and t_res > 0.05:
        t_res = None
    return {
        't_act': t_act,
        't_before': t_before,
        't_zero': t_zero,
        'resumed_s': t_res,
        'aborted': st['why'],
        'ref': 'applied' if st['ref'] is not None else 'published',
        # the last command answered state k_last; the drive first showed it in ref_step
        'k_last': k_last,
        'ref_step': st.get('ref_step'),
        'coverage_s': coverage,
        'rows_on': (i_on, i_silent),
        'rows_resume': (i_res, p.n),
    }


def _watchdog_lockstep(p: Probe) -> dict:
    """Silence for LOCKSTEP_SILENCE_S: only re-sends of the same state allowed; then one
    command must make it step."""
    k_last = p.answered
    t0 = time.monotonic()
    i0 = p.n
    p.run(lambda k, s: None, lambda: time.monotonic() - t0 >= TH.LOCKSTEP_SILENCE_S, 2.0)
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
    raise TH.CheckRefused(
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
        return TH.DEFAULT_TIMEOUT, 'default'
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
            return TH.DEFAULT_TIMEOUT, 'default: drive has no parameter service'
        future = client.call_async(GetParameters.Request(names=['command_timeout']))
        # a drive that just started may be compiling its loop before it serves requests
        # (numba, a cold cache: seconds): up to --timeout, as for its first state
        executor.spin_until_future_complete(future, timeout_sec=max(3.0, opts.timeout))
        res = future.result()
        if res is None:
            return TH.DEFAULT_TIMEOUT, 'default: no parameter answer'
        v = res.values[0] if res.values else None
        if v is not None and v.type == ParameterType.PARAMETER_DOUBLE:
            return float(v.double_value), 'drive parameter'
        return TH.DEFAULT_TIMEOUT, 'default: drive has no command_timeout'
    finally:
        executor.shutdown()
        helper.destroy_node()
