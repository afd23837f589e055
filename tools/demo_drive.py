"""Demo of the simulated drive bench (``make demo`` until the tuner lands).

Starts ``ros2 run im_drive_sim drive_sim`` (lock-step) as a child process and closes the
loop over DDS with a plain hand-tuned cascade (P position, PI speed) doing the paper's
experiment once: a pi-rad move, a 1.75 N m load step 0.7 s after it, 1.125 s in all
(5625 steps). Prints a summary and writes a plot and the samples to ``bags/demo_drive/``.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)

import rclpy
from rclpy.node import Node

from im_drive_sim.client import DriveClient
from im_drive_sim.runtime import stop_child
from im_drive_sim.sim import STATE_FIELDS

F = {name: i for i, name in enumerate(STATE_FIELDS)}
TS = 200e-6
STEPS = 5625
ISQ_MAX = 7.0


def reference(t: float, a_max: float = 600.0, w_max: float = 40.0, dist: float = math.pi) -> float:
    """Minimum-time (trapezoidal-speed) position reference for a move of ``dist`` rad."""
    t_acc = w_max / a_max
    if a_max * t_acc**2 > dist:  # triangular profile
        t_acc = math.sqrt(dist / a_max)
        w_max = a_max * t_acc
    t_flat = (dist - a_max * t_acc**2) / w_max
    if t <= 0:
        return 0.0
    if t < t_acc:
        return 0.5 * a_max * t * t
    if t < t_acc + t_flat:
        return 0.5 * a_max * t_acc**2 + w_max * (t - t_acc)
    if t < 2 * t_acc + t_flat:
        td = 2 * t_acc + t_flat - t
        return dist - 0.5 * a_max * td * td
    return dist


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--out', default='bags/demo_drive', help='output folder')
    ap.add_argument('--model', choices=('full', 'reduced'), default='full')
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    ros2 = str(Path(sys.prefix) / 'bin' / 'ros2')
    drive = subprocess.Popen(
        [ros2, 'run', 'im_drive_sim', 'drive_sim', '--model', args.model, '--max-steps', str(STEPS)]
    )
    rclpy.init()
    node = Node('demo_controller')
    client = DriveClient(node)
    kp_w, ki_w, k_pos = 0.53, 20.0, 30.0  # the hand-tuned start of the notes
    integ = 0.0
    log = np.zeros((STEPS + 1, len(STATE_FIELDS) + 2))
    t_wall = time.perf_counter()
    try:
        if not client.wait_for_drive(30.0):
            print('error: drive_sim did not come up', file=sys.stderr)
            return 1
        while True:
            s = client.wait_new_state(10.0)
            if s is None:
                print('error: no state from drive_sim for 10 s', file=sys.stderr)
                return 1
            k = int(s[F['step_index']])
            t = k * TS
            theta_ref = reference(t)
            omega_ref = k_pos * (theta_ref - s[F['theta_meas']])
            err = omega_ref - s[F['omega_meas']]
            isq = kp_w * err + integ
            if abs(isq) < ISQ_MAX:  # conditional integration (anti-windup)
                integ += ki_w * TS * err
            isq = max(-ISQ_MAX, min(ISQ_MAX, isq))
            load = 1.75 if t >= 0.7 else 0.0
            log[k, : len(STATE_FIELDS)] = s
            log[k, -2:] = theta_ref, isq
            if k >= STEPS:
                break
            client.command(k, isq, load)
            if k % 1125 == 0:
                print(
                    f'  t = {t:5.3f} s  theta = {s[F["theta_meas"]]:+.4f} rad  '
                    f'ref = {theta_ref:+.4f} rad  isq* = {isq:+.2f} A',
                    flush=True,
                )
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        try:
            drive.wait(timeout=5)  # it stops by itself after --max-steps
        except subprocess.TimeoutExpired:
            stop_child(drive)
    wall = time.perf_counter() - t_wall
    e = log[:, -2] - log[:, F['theta']]
    print(
        f'\nexperiment: {STEPS} steps ({STEPS * TS:.3f} s sim) in {wall:.2f} s wall '
        f'(real-time factor {STEPS * TS / wall:.2f})'
    )
    print(
        f'final position {log[-1, F["theta"]]:.4f} rad (ref {math.pi:.4f}), '
        f'max |error| {np.abs(e).max():.4f} rad, '
        f'integral |error| {np.abs(e).sum() * TS:.5f} rad s'
    )
    np.savetxt(
        out / 'samples.csv',
        log,
        delimiter=',',
        header=','.join([*STATE_FIELDS, 'theta_ref', 'isq_ref']),
        comments='',
    )
    try:
        import matplotlib

        matplotlib.use('Agg')
        import matplotlib.pyplot as plt

        t = log[:, F['time_ns']] * 1e-9
        fig, ax = plt.subplots(3, 1, sharex=True, figsize=(8, 7))
        ax[0].plot(t, log[:, -2], label='theta* [rad]')
        ax[0].plot(t, log[:, F['theta_meas']], label='theta measured [rad]')
        ax[1].plot(t, log[:, F['omega_meas']], label='omega measured [rad/s]')
        ax[2].plot(t, log[:, -1], label='isq* [A]')
        ax[2].plot(t, log[:, F['isq']], label='isq [A]', alpha=0.7)
        ax[2].plot(t, log[:, F['load_torque']], label='load torque [N m]')
        for a in ax:
            a.grid(True)
            a.legend(loc='upper right')
        ax[2].set_xlabel('sim time [s]')
        fig.suptitle('im_drive_sim demo: pi-rad move, 1.75 N m load step at 0.7 s')
        fig.tight_layout()
        fig.savefig(out / 'demo_drive.png', dpi=110)
        print(f'plot: {out / "demo_drive.png"}   samples: {out / "samples.csv"}')
    except ImportError:
        print(f'samples: {out / "samples.csv"} (matplotlib missing: no plot)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
