"""Two computers on one machine, for the tests: two network namespaces joined by a veth
pair, made and removed by the test itself (iproute2), and packet loss or an outage on
the link (nftables: this kernel has no netem).

Each namespace has its own network stack: DDS in one reaches the other only over the
veth, as over a cable. Fast DDS would take its shared-memory transport between two
participants on one machine, past the veth, so the processes run with
``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``; discovery is ``SUBNET`` (multicast on the veth).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

IP = shutil.which('ip')
NFT = shutil.which('nft')


def why_not() -> str | None:
    """Why two namespaces cannot be made here (None: they can)."""
    if IP is None:
        return 'no `ip` (iproute2) on this machine'
    if NFT is None:
        return 'no `nft` (nftables) on this machine: packet loss cannot be made'
    if os.geteuid() != 0:
        return 'network namespaces need root (CAP_NET_ADMIN)'
    name = f'im_probe_{os.getpid()}'
    p = subprocess.run([IP, 'netns', 'add', name], capture_output=True, text=True)
    if p.returncode != 0:
        return f'`ip netns add` refused here: {p.stderr.strip()}'
    subprocess.run([IP, 'netns', 'del', name], capture_output=True)
    return None


def _run(*argv: str, stdin: str | None = None) -> None:
    subprocess.run(argv, check=True, capture_output=True, text=True, input=stdin)


class TwoComputers:
    """``a`` (10.x.0.1) and ``b`` (10.x.0.2), joined by a veth pair; ``with`` makes and
    removes them (the veth goes with its namespace)."""

    def __init__(self, tag: str = '') -> None:
        n = os.getpid() % 100_000
        self.ns = {'a': f'im_{tag}{n}_a', 'b': f'im_{tag}{n}_b'}
        self.dev = {'a': f'im{n}a', 'b': f'im{n}b'}  # <= 15 characters
        net = 16 + n % 200
        self.addr = {'a': f'10.{net}.0.1', 'b': f'10.{net}.0.2'}

    def __enter__(self) -> TwoComputers:
        try:
            for side in ('a', 'b'):
                _run(IP or 'ip', 'netns', 'add', self.ns[side])
            _run(
                IP or 'ip', 'link', 'add', self.dev['a'], 'type', 'veth', 'peer', 'name',
                self.dev['b'],
            )  # fmt: skip
            for side in ('a', 'b'):
                ns, dev = self.ns[side], self.dev[side]
                _run(IP or 'ip', 'link', 'set', dev, 'netns', ns)
                _run(IP or 'ip', '-n', ns, 'addr', 'add', f'{self.addr[side]}/24', 'dev', dev)
                _run(IP or 'ip', '-n', ns, 'link', 'set', 'lo', 'up')
                _run(IP or 'ip', '-n', ns, 'link', 'set', dev, 'up')
                # multicast (SUBNET discovery) out of the veth
                _run(IP or 'ip', '-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        for ns in self.ns.values():
            subprocess.run([IP or 'ip', 'netns', 'del', ns], capture_output=True)

    def argv(self, side: str, argv: list[str]) -> list[str]:
        """``argv`` run in namespace ``side`` (the same PID: ``ip netns exec`` execs it)."""
        return [IP or 'ip', 'netns', 'exec', self.ns[side], *argv]

    @staticmethod
    def env(base: dict[str, str]) -> dict[str, str]:
        """The environment of a process on either computer."""
        env = dict(base)
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'
        env['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'
        return env

    def loss(self, percent: float) -> None:
        """Drop ``percent`` % of the packets each computer receives on the veth, at random
        (nftables ``numgen random``, in steps of 0.01 %); 0: none; 100: the cable out (an
        outage: a link set down would also drop its routes)."""
        for side in ('a', 'b'):
            ns = self.ns[side]
            nft = [IP or 'ip', 'netns', 'exec', ns, NFT or 'nft']
            subprocess.run([*nft, 'delete', 'table', 'inet', 'imloss'], capture_output=True)
            if percent > 0:
                per_10k = round(percent * 100)
                match = f'numgen random mod 10000 < {per_10k}' if percent < 100 else ''
                rules = (
                    'table inet imloss {\n  chain input {\n'
                    '    type filter hook input priority 0; policy accept;\n'
                    f'    iifname "{self.dev[side]}" {match} drop\n'
                    '  }\n}\n'
                )
                _run(*nft, '-f', '-', stdin=rules)


#: what :meth:`TwoComputers.traffic` counts, by the RTPS port a packet goes to (DDSI-RTPS
#: 2.x, 9.6.1.1: PB 7400, DG 250, PG 2, d0 0, d1 10, d2 1, d3 11), then every packet
TRAFFIC_KINDS = (
    'discovery multicast',
    'user multicast',
    'discovery unicast',
    'user unicast',
    'all',
)


def count_traffic(two: TwoComputers, domain: int) -> None:
    """Count (again from 0) the packets each computer receives on the veth, by
    TRAFFIC_KINDS (nftables counters, before the loss rule drops any)."""
    base = 7400 + 250 * domain
    for side in ('a', 'b'):
        dev = two.dev[side]
        rules = (
            'table inet imcount {\n  chain input {\n'
            '    type filter hook input priority -10; policy accept;\n'
            f'    iifname "{dev}" udp dport {base} counter\n'
            f'    iifname "{dev}" udp dport {base + 1} counter\n'
            f'    iifname "{dev}" udp dport {base + 10}-{base + 249} udp dport & 1 == 0 counter\n'
            f'    iifname "{dev}" udp dport {base + 11}-{base + 249} udp dport & 1 == 1 counter\n'
            f'    iifname "{dev}" counter\n'
            '  }\n}\n'
        )
        nft = [IP or 'ip', 'netns', 'exec', two.ns[side], NFT or 'nft']
        subprocess.run([*nft, 'delete', 'table', 'inet', 'imcount'], capture_output=True)
        _run(*nft, '-f', '-', stdin=rules)


def traffic(two: TwoComputers) -> dict[str, dict[str, tuple[int, int]]]:
    """Per receiving side: (packets, bytes) by TRAFFIC_KINDS since :func:`count_traffic`."""
    import re

    out = {}
    for side in ('a', 'b'):
        nft = [IP or 'ip', 'netns', 'exec', two.ns[side], NFT or 'nft']
        text = subprocess.run(
            [*nft, 'list', 'table', 'inet', 'imcount'], capture_output=True, text=True, check=True
        ).stdout
        found = re.findall(r'counter packets (\d+) bytes (\d+)', text)
        out[side] = {k: (int(p), int(b)) for k, (p, b) in zip(TRAFFIC_KINDS, found, strict=True)}
    return out


def start_drive_host(
    two: TwoComputers, out: Path, env: dict[str, str], timeout: float = 180.0
) -> subprocess.Popen:
    """``ros2 run im_tuner drive_host`` on computer ``a`` (seed 5, tuner watchdog 1 s),
    its bag ``out/host_bag`` and its log ``out/host.log``; returned once it says it is
    ready (RuntimeError with the log's tail if it does not within ``timeout`` s)."""
    import sys
    import time

    ros2 = [str(Path(sys.prefix) / 'bin' / 'ros2'), 'run', 'im_tuner', 'drive_host']
    log_path = out / 'host.log'
    with open(log_path, 'w') as log:
        host = subprocess.Popen(
            two.argv('a', [*ros2, '--out', str(out / 'host_bag'), '--seed', '5',
                           '--tuner-timeout', '1.0']),
            env=two.env(env), stdout=log, stderr=log,
        )  # fmt: skip
    deadline = time.monotonic() + timeout
    while 'drive host ready' not in log_path.read_text():
        if time.monotonic() > deadline or host.poll() is not None:
            if host.poll() is None:
                host.kill()
                host.wait()
            raise RuntimeError(log_path.read_text()[-2000:])
        time.sleep(0.2)
    return host


def bag_topics(bag: Path) -> dict[str, int]:
    """Message count per topic of a closed bag (its metadata.yaml)."""
    import yaml

    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    return {
        t['topic_metadata']['name']: int(t['message_count'])
        for t in info['topics_with_message_count']
    }
