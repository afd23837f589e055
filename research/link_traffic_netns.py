"""What crosses the network between a drive host and its tuner, counted by nftables.

A drive host (``ros2 run im_tuner drive_host``) in one network namespace, the tuner
(``--bench none``) in another, joined by a veth pair (``test/netns.py``, the set-up of
``test/test_two_computers.py``), ``--loss`` % of the packets dropped each way. nftables
counters on each side's input count the UDP packets and bytes the other side sent, by
the RTPS port they go to (domain ``--domain``: discovery multicast, user multicast,
discovery unicast, user data unicast) over the tuner's run; and, while the run goes on,
the host's graph names every reader of its 5 kHz topics and where it lives.

Printed per direction: packets per second of the tuner's run by kind, and the readers of
the 5 kHz topics (none on the tuner's computer is the design: docs/two-computers.md).
Needs root, iproute2 and nftables.

    python research/link_traffic_netns.py --loss 5 --budget 10 --out /tmp/link
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / 'test'))
import netns
from test_faults import ros2

READERS = r"""
import json, sys, time
import rclpy
from rclpy.node import Node
rclpy.init()
n = Node('link_traffic_probe')
time.sleep(3.0)
out = {}
for t in ('/drive/state', '/drive/command', '/drive/joint_states', '/controller/internals'):
    out[t] = sorted({f'{i.node_namespace.rstrip("/")}/{i.node_name}'
                     for i in n.get_subscriptions_info_by_topic(t)})
print(json.dumps(out))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--loss', type=float, default=5.0, help='packet loss [%%] (default 5)')
    ap.add_argument('--budget', type=int, default=10, help="the tuner's budget (default 10)")
    ap.add_argument('--out', type=Path, required=True, help='directory for the run and bags')
    ap.add_argument('--domain', type=int, default=78, help='ROS_DOMAIN_ID (default 78)')
    a = ap.parse_args()
    why = netns.why_not()
    if why is not None:
        print(f'error: link_traffic_netns: {why}', file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(a.domain))
    with netns.TwoComputers('c') as two:
        two.loss(a.loss)
        try:
            host = netns.start_drive_host(two, a.out, dict(env))
        except RuntimeError as exc:
            print(exc, file=sys.stderr)
            return 1
        try:
            netns.count_traffic(two, a.domain)
            t0 = time.monotonic()
            tuner = subprocess.Popen(
                two.argv('b', ros2('im_tuner', 'tuner', '--bench', 'none', '--budget',
                                   str(a.budget), '--seed', '3', '--remeasure', '0',
                                   '--discovery-timeout', '60', '--out', str(a.out / 'run'))),
                env=two.env(dict(env)), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                text=True,
            )  # fmt: skip
            time.sleep(20.0)  # the run under way: who reads the 5 kHz topics?
            probe = subprocess.run(
                two.argv('a', [sys.executable, '-c', READERS]),
                env=two.env(dict(env)), capture_output=True, text=True, timeout=120,
            )  # fmt: skip
            out, _ = tuner.communicate(timeout=1800)
            took = time.monotonic() - t0
            counts = netns.traffic(two)
        finally:
            host.send_signal(signal.SIGINT)
            host.wait(timeout=60)
    print(f'tuner exit {tuner.returncode} after {took:.0f} s at {a.loss:g} % loss')
    print('\n'.join(out.strip().splitlines()[-6:]))
    for side, frm in (('a', 'tuner -> host'), ('b', 'host -> tuner')):
        c = counts[side]
        parts = ', '.join(f'{k} {c[k][0] / took:.0f}/s' for k in netns.TRAFFIC_KINDS[:-1])
        pk, by = c['all']
        print(f'{frm}: {pk / took:.0f} packets/s, {by / took / 1e3:.1f} kB/s ({parts})')
    try:
        readers = json.loads(probe.stdout.strip().splitlines()[-1])
        for t, nodes in readers.items():
            print(f'readers of {t} (seen on the host): {", ".join(nodes) or "none"}')
    except (ValueError, IndexError):
        print(f'reader probe failed: {probe.stderr[-1000:]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
