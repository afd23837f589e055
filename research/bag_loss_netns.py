"""Does the tuner's bag hold every loss when the network drops packets? (CI, 2026-11-28)

A drive host (``ros2 run im_tuner drive_host``) in one network namespace, the tuner
(``--bench none``, budget 4, no re-measurement) in another, joined by a veth pair with
nftables dropping ``--loss`` % of the packets both ways (``test/netns.py``, the set-up of
``test/test_two_computers.py``). For each of ``--runs`` tuner runs on the same host it
prints the exit code, the wall time, the losses the run counted (results.jsonl) and the
``/controller/loss`` messages in its bag, with any warning the tuner printed about it.

Before the recorder's status (record/status.py) the tuner stopped its recorder as soon as
it had the last loss itself; at 15 % loss 1 run in 6 had a bag without its last two
losses. Needs root, iproute2 and nftables; exits 1 when a bag lacks a loss.

    python research/bag_loss_netns.py --loss 15 --runs 6 --out /tmp/bag_loss
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--loss', type=float, default=15.0, help='packet loss [%%] (default 15)')
    ap.add_argument('--runs', type=int, default=6, help='tuner runs (default 6)')
    ap.add_argument('--out', type=Path, required=True, help='directory for the runs and bags')
    ap.add_argument('--domain', type=int, default=77, help='ROS_DOMAIN_ID (default 77)')
    a = ap.parse_args()
    why = netns.why_not()
    if why is not None:
        print(f'error: bag_loss_netns: {why}', file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(a.domain))
    short = 0
    with netns.TwoComputers('q') as two:
        try:
            host = netns.start_drive_host(two, a.out, dict(env), timeout=120.0)
        except RuntimeError as exc:
            print(exc, file=sys.stderr)
            return 1
        try:
            for i in range(a.runs):
                run = a.out / f'run_{i}'
                two.loss(a.loss)
                t0 = time.monotonic()
                p = subprocess.run(
                    two.argv('b', ros2('im_tuner', 'tuner', '--bench', 'none', '--budget',
                                       '4', '--seed', '3', '--quiet', '--remeasure', '0',
                                       '--discovery-timeout', '60', '--out', str(run))),
                    env=two.env(dict(env)), capture_output=True, text=True, timeout=600,
                )  # fmt: skip
                took = time.monotonic() - t0
                two.loss(0)
                results = run / 'results.jsonl'
                recs = (
                    [json.loads(x) for x in results.read_text().splitlines() if x.strip()]
                    if results.exists()
                    else []
                )
                counted = sum(r.get('status') in ('ok', 'aborted') for r in recs)
                in_bag = netns.bag_topics(run / 'bag_0').get('/controller/loss', 0)
                warned = [x for x in p.stderr.splitlines() if 'bag holds fewer' in x]
                short += in_bag < counted
                print(
                    f'run {i}: exit {p.returncode}, {took:.1f} s, losses counted {counted}, '
                    f'in the bag {in_bag}' + (f'; {warned[0]}' if warned else ''),
                    flush=True,
                )
        finally:
            host.send_signal(signal.SIGINT)
            host.wait(60)
    print(f'{short} of {a.runs} bags lack a loss the run counted (packet loss {a.loss:g} %)')
    return 1 if short else 0


if __name__ == '__main__':
    sys.exit(main())
