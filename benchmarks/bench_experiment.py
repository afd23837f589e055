"""Experiment real-time factor: simulated seconds per wall second for the paper's
experiment (1.125 s, 5625 steps) run through the ROS nodes, lock-step.

* one process: ``InProcessBench`` (drive_sim + controller in one thread) with a client
  node doing what the tuner does (Trigger service, loss topic);
* separate processes: ``ros2 run im_drive_sim drive_sim`` and ``ros2 run im_controller
  controller`` as children, the client here;
* one process with the recorder (``im_tuner.record.node.Recorder``) in it, polled
  between steps as the simulated bench and the tuner run it, for each chunk compression;
  runs with and without the recorder alternate (A/B) so that machine noise hits both,
  and the ratio is taken per pair.

Wall time per experiment = from the start call to the loss message. Prints medians.
Run: ``.venv/bin/python benchmarks/bench_experiment.py`` (or ``make bench``).
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 50))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from im_controller.contract import NO_DRIVE_STATE, refusal_code
from im_controller.messages import msg_to_result
from im_drive_sim.runtime import stop_child
from im_tuner.bench import InProcessBench

EXPERIMENTS = 7
SIM_SECONDS = 1.125


class _Client:
    def __init__(self, ctx, spin_until) -> None:
        self.node = Node('bench_tuner', context=ctx)
        self.start = self.node.create_client(Trigger, '/controller/start_experiment')
        self.results = []
        self.node.create_subscription(
            DiagnosticArray,
            '/controller/loss',
            lambda m: self.results.append(msg_to_result(m)),
            100,
        )
        self.spin_until = spin_until

    def run(self, n: int) -> list[float]:
        if not self.spin_until(
            lambda: (
                self.start.service_is_ready() and self.node.count_publishers('/controller/loss') > 0
            ),
            30.0,
        ):
            raise RuntimeError('controller not reachable')
        walls = []
        for _ in range(n + 1):  # the first one warms up (numba caches, DDS)
            t0 = time.perf_counter()
            k = len(self.results)
            while True:
                fut = self.start.call_async(Trigger.Request())
                if not self.spin_until(fut.done, 30.0):
                    raise RuntimeError('start_experiment timed out')
                if fut.result().success:
                    break
                if refusal_code(fut.result().message) != NO_DRIVE_STATE:
                    raise RuntimeError(fut.result().message)
                self.spin_until(lambda: False, 0.05)
            if not self.spin_until(lambda k=k: len(self.results) > k, 120.0):
                raise RuntimeError('no loss result')
            walls.append(time.perf_counter() - t0)
        return walls[1:]


def one_process(n: int = EXPERIMENTS, record: str | None = None) -> list[float]:
    """RTF per experiment with both nodes in this process; ``record``: a chunk
    compression to run the recorder in the same process too (None: no recorder)."""
    ctx = Context()
    rclpy.init(context=ctx)
    tmp = tempfile.mkdtemp(prefix='bench_rec_')
    try:
        bench = InProcessBench(context=ctx)
        rec = None
        if record is not None:
            from im_tuner.record.node import RECORD_POLL_STEPS, Recorder

            rec = Recorder(
                Node('recorder', context=ctx, start_parameter_services=False),
                Path(tmp) / 'bag',
                compression=record,
            )
            bench.add_poller(rec.poll, RECORD_POLL_STEPS)
        client = _Client(ctx, bench.spin_until)
        bench.executor.add_node(client.node)
        walls = client.run(n)
        if rec is not None:
            counts = rec.close()
            lost = sum(c['lost'] for c in counts.values())
            short = [t for t, c in counts.items() if c['recorded'] != c['published']]
            if lost or short:
                raise RuntimeError(f'recorder lost messages: {lost} lost, short on {short}')
            rec.node.destroy_node()
        client.node.destroy_node()
        bench.destroy()
        return [SIM_SECONDS / w for w in walls]
    finally:
        rclpy.try_shutdown(context=ctx)
        shutil.rmtree(tmp, ignore_errors=True)


def recording_ab(compression: str, pairs: int = 3, n: int = 5) -> tuple[list[float], list[float]]:
    """Alternate runs without / with the recorder; returns (RTFs with, per-pair ratios)."""
    with_rec, ratios = [], []
    for _ in range(pairs):
        base = statistics.median(one_process(n))
        rec = one_process(n, record=compression)
        with_rec += rec
        ratios.append(statistics.median(rec) / base)
    return with_rec, ratios


def separate_processes(n: int = EXPERIMENTS) -> list[float]:
    ros2 = str(Path(sys.prefix) / 'bin' / 'ros2')
    procs = [
        subprocess.Popen(
            [ros2, 'run', 'im_drive_sim', 'drive_sim'],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        ),
        subprocess.Popen(
            [ros2, 'run', 'im_controller', 'controller'],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        ),
    ]
    ctx = Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)

    def spin_until(pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                return False
            ex.spin_once(timeout_sec=0.01)
        return True

    try:
        client = _Client(ctx, spin_until)
        ex.add_node(client.node)
        walls = client.run(n)
        return [SIM_SECONDS / w for w in walls]
    finally:
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)
        for p in procs:
            stop_child(p)


def _fmt(name: str, xs: list[float]) -> str:
    return (
        f'{name:<38} median RTF {statistics.median(xs):5.2f}   '
        f'min {min(xs):5.2f}   max {max(xs):5.2f}   ({len(xs)} experiments)'
    )


def main(compressions: tuple[str, ...] = ('zstd', 'lz4', 'none')) -> dict[str, float]:
    one = one_process()
    print(_fmt('experiment, nodes in one process', one), flush=True)
    figures = {'experiment_rtf_1proc': statistics.median(one)}
    for comp in compressions:
        rec, ratios = recording_ab(comp)
        print(
            _fmt(f'  + recorder in process ({comp})', rec)
            + f'   speed kept {statistics.median(ratios):.0%} '
            f'(pairs: {", ".join(f"{r:.2f}" for r in ratios)})',
            flush=True,
        )
        figures[f'experiment_rtf_rec_{comp}'] = statistics.median(rec)
        figures[f'recording_kept_{comp}'] = statistics.median(ratios)
    two = separate_processes()
    print(_fmt('experiment, separate processes', two), flush=True)
    figures['experiment_rtf_2proc'] = statistics.median(two)
    return figures


if __name__ == '__main__':
    main(tuple(sys.argv[1:]) or ('zstd', 'lz4', 'none'))
