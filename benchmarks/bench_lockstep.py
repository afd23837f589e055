"""Lock-step round trip of the drive interface: us per 200 us simulation step.

One round trip = the drive publishes state k, a minimal responder takes it and answers
with a command, the drive takes the command, steps the model and publishes state k+1.

* one process: the drive node (DriveSimNode.lockstep_poll) and the responder interleaved
  in one thread, over real DDS (Fast DDS intra-process path);
* two processes: ``ros2 run im_drive_sim drive_sim`` as a child, the responder here.

Run: ``.venv/bin/python benchmarks/bench_lockstep.py`` (or ``make bench``). Prints medians
over repeated batches; the machines are shared and noisy.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from im_drive_sim.client import DriveClient
from im_drive_sim.drive_sim_node import DriveSimNode
from im_drive_sim.runtime import stop_child

BATCH = 5000
REPEATS = 7


def _respond(client: DriveClient, s) -> None:
    # A minimal controller: P on speed, so the model does real work.
    client.command(int(s[0]), max(-7.0, min(7.0, -0.05 * s[3] + 0.5)), 0.0)


def one_process(batch: int = BATCH, repeats: int = REPEATS) -> list[float]:
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        drive = DriveSimNode(context=ctx, parameter_overrides=[Parameter('model', value='full')])
        node = Node('bench_responder', context=ctx)
        client = DriveClient(node)
        if not client.wait_for_drive(10.0):
            raise RuntimeError('drive and responder did not match')
        drive.start()
        per_step = []
        for rep in range(repeats + 1):  # the first batch warms up
            t = time.perf_counter()
            for _ in range(batch):
                s = client.wait_state(1.0)
                if s is None:
                    raise RuntimeError('state lost')
                _respond(client, s)
                if not drive.lockstep_poll(1_000_000_000):
                    raise RuntimeError('command lost')
            if rep:
                per_step.append((time.perf_counter() - t) / batch * 1e6)
        node.destroy_node()
        drive.destroy_node()
        return per_step
    finally:
        rclpy.try_shutdown(context=ctx)


def two_processes(batch: int = BATCH, repeats: int = REPEATS) -> list[float]:
    ros2 = str(Path(sys.prefix) / 'bin' / 'ros2')
    total = batch * (repeats + 1) + 10
    proc = subprocess.Popen(
        [ros2, 'run', 'im_drive_sim', 'drive_sim', '--max-steps', str(total)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = Node('bench_responder2', context=ctx)
        client = DriveClient(node)
        if not client.wait_for_drive(20.0):
            raise RuntimeError('drive_sim did not appear')
        per_step = []
        for rep in range(repeats + 1):
            t = time.perf_counter()
            n = 0
            while n < batch:
                s = client.wait_new_state(5.0)
                if s is None:
                    raise RuntimeError('state lost')
                _respond(client, s)
                n += 1
            if rep:
                per_step.append((time.perf_counter() - t) / batch * 1e6)
        node.destroy_node()
        return per_step
    finally:
        rclpy.try_shutdown(context=ctx)
        stop_child(proc)


def _fmt(name: str, xs: list[float]) -> str:
    return (
        f'{name:<34} median {statistics.median(xs):7.1f} us/step   '
        f'min {min(xs):7.1f}   max {max(xs):7.1f}   (rtf {200.0 / statistics.median(xs):.1f})'
    )


def main() -> dict[str, float]:
    one = one_process()
    print(_fmt('lock-step round trip, 1 process', one), flush=True)
    two = two_processes()
    print(_fmt('lock-step round trip, 2 processes', two), flush=True)
    return {
        'lockstep_1proc_us': statistics.median(one),
        'lockstep_2proc_us': statistics.median(two),
    }


if __name__ == '__main__':
    main()
