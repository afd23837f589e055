"""The loops of the ``drive_sim`` node: lock-step and real time (docs/interfaces.md).

Each runs a :class:`~im_drive_sim.drive_sim_node.DriveSimNode` (``drive``) until it is
asked to stop (``drive.stop_requested``, the context shut down) or ``max_steps`` steps
were taken, serving parameter requests and publishing ``drive/status`` between steps
(:func:`serve`). What a step or a period does is the node's (``lockstep_poll``,
``period``); these say when.
"""

from __future__ import annotations

import time
from typing import Any

import rclpy

from .contract import NS_PER_S
from .pacing import Pacer


def serve(drive: Any, executor: Any, t_start: float, next_status: float) -> float:
    """Between steps: serve pending parameter requests; publish the status once a second.

    Returns the wall time of the next status publication.
    """
    executor.spin_once(timeout_sec=0.0)
    now = time.perf_counter()
    if now >= next_status:
        drive.publish_status(now - t_start)
        return now + 1.0
    return next_status


def run_lockstep(drive: Any, executor: Any) -> None:
    """One step per command answering the current state; see docs/interfaces.md."""
    c = drive.counters
    drive.start()
    since_service = 0
    t_wall0 = last_step = time.perf_counter()
    next_status = t_wall0 + 1.0
    while not drive.stop_requested and rclpy.ok(context=drive.context):
        if drive.max_steps and c.steps >= drive.max_steps:
            break
        wait_s = max(0.0, last_step + drive.republish_period - time.perf_counter())
        if drive.lockstep_poll(int(wait_s * NS_PER_S)):
            last_step = time.perf_counter()
        elif time.perf_counter() - last_step >= drive.republish_period:
            # Idle: serve parameters (and the status: an idle drive still reports),
            # then re-send the state for a late-starting peer.
            next_status = serve(drive, executor, t_wall0, next_status)
            drive.publish_state()
            c.republished += 1
            last_step = time.perf_counter()
            continue
        else:
            continue
        since_service += 1
        if since_service >= drive.service_period_steps:
            since_service = 0
            next_status = serve(drive, executor, t_wall0, next_status)
    drive.publish_status(time.perf_counter() - t_wall0)


def run_realtime(drive: Any, executor: Any) -> None:
    """Step every Ts by the wall clock, holding the last command when none is fresh.

    Each period (:class:`~im_drive_sim.pacing.Pacer`): wait (sleeping in rcl_wait,
    taking commands as they come, then busy-waiting the last ``realtime_spin_margin``)
    until its start, then ``drive.period``. A period that starts more than one period
    late counts as an overrun and the schedule is re-anchored (the simulation never
    skips steps; sim time stays k * Ts).
    """
    c = drive.counters
    if drive.realtime_wait_for_controller:
        # A drive with no controller would only hold zero current: the clock starts
        # when one is matched, so it never misses the first periods.
        drive.get_logger().info('real time: waiting for a controller on drive/command')
        while (
            not drive.stop_requested
            and rclpy.ok(context=drive.context)
            and drive.cmd_sub.get_publisher_count() == 0
        ):
            executor.spin_once(timeout_sec=0.01)
    drive.start()
    pacer = Pacer(drive.config.Ts, drive.spin_margin, wall_clock=drive.wall_clock)
    t_start = pacer.t0
    next_status = t_start + 1.0
    since_service = 0
    while not drive.stop_requested and rclpy.ok(context=drive.context):
        if drive.max_steps and c.steps >= drive.max_steps:
            break
        pacer.wait(drive.wait_command, drive.take_commands)
        c.overruns, c.max_lateness_us = pacer.overruns, pacer.max_lateness_us
        drive.period(pacer.missed)
        since_service += 1
        if since_service >= drive.service_period_steps:
            since_service = 0
            next_status = serve(drive, executor, t_start, next_status)
    drive.publish_status(time.perf_counter() - t_start)
