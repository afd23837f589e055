"""The live view: what of the bag goes live, to a Foxglove WebSocket server.

``--live [PORT]`` (the tuner on every bench, ``drive_host``, ``recorder``) starts one in
the recorder (:mod:`.live_server`): every message the bag gets passes :class:`LiveFeed`
(the writer hands it the chunk's new rows, :meth:`im_tuner.record.writer.McapWriter.observe`),
which keeps the experiment-rate topics whole and every Nth message of the drive's 5 kHz
topics (:data:`PERIOD_TOPICS`, N = :data:`PERIOD_RATE_HZ` / ``--live-rate``: 250 Hz by
default, 1 of 20), and hands (channel, log time, CDR bytes) to the server. Each channel
is the bag's: the same topic, message encoding ``cdr``, schema name the ROS type, the
bag's schema encoding (``ros2msg``; ``ros2idl`` for service events) and text, log time
the bag's; so the shipped Foxglove layouts work unchanged live and on the bag.

The server is ``foxglove-websocket``'s, not ``foxglove-sdk``'s: the SDK's accepts only the
subprotocol ``foxglove.sdk.v1``, not ``foxglove.websocket.v1``, the one Foxglove Studio 1.48
and the viewers built on it speak (research/NOTES.md).

This module is pure (numpy, the contracts): the options' declaration and checks
(:data:`OPTIONS`, :func:`live_settings`, :func:`check_endpoint`), :class:`LiveFeed`, the
figures said at the end (:func:`live_line`, :func:`read_live_stats`).
"""

from __future__ import annotations

import argparse
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from im_controller.contract import INTERNALS_TOPIC
from im_drive_sim.cli import int_in, plain
from im_drive_sim.contract import COMMAND_TOPIC, STATE_TOPIC

from .mcap_format import MESSAGE_HEADER_BYTES

#: the port ``--live`` takes when given bare (Foxglove's and foxglove_bridge's default)
DEFAULT_PORT = 8765
#: where the server listens unless ``--live-host`` says otherwise: this computer only
DEFAULT_HOST = '127.0.0.1'
#: [Hz] the live rate of the 5 kHz topics by default (``--live-rate``; 0: every message)
DEFAULT_RATE_HZ = 250.0
#: [Hz] the rate of the drive's per-period topics: one message per period of Ts = 200 us,
#: every packaged drive's (a drive of another Ts gets N of this rate all the same)
PERIOD_RATE_HZ = 5000.0
#: the topics published once per drive period (relative to the bench's namespace): the
#: live view sends every Nth of them
PERIOD_TOPICS = (STATE_TOPIC, COMMAND_TOPIC, INTERNALS_TOPIC)
#: the bag's metadata record and metadata.yaml ``custom_data`` key of
#: :meth:`.live_server.LiveServer.stats`
LIVE_METADATA = 'im_tuner.live'


class LiveError(Exception):
    """The live server cannot start (the port in use, an address not of this computer)."""


def check_endpoint(host: str, port: int) -> None:
    """Whether a server can listen on ``host``:``port`` now: binds a socket there and
    releases it (LiveError with the reason, one line). ``port`` 0: any free port."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise LiveError(
            f'--live-host {host}: not an address or a name this computer resolves ({exc})'
        ) from None
    family, kind, proto, _name, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        # as the server binds (asyncio sets SO_REUSEADDR): a port left in TIME_WAIT by a
        # run just ended is free, one a process listens on is not
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
            s.listen(1)
        except OSError as exc:
            raise LiveError(cannot_listen(host, port, exc)) from None


def cannot_listen(host: str, port: int, exc: OSError) -> str:
    """Why a server cannot listen on ``host``:``port``, in one line."""
    import errno

    if exc.errno == errno.EADDRINUSE:
        return (
            f'--live {port}: port {port} is in use on {host} (another server, or another '
            'run with --live): give another port'
        )
    if exc.errno == errno.EADDRNOTAVAIL:
        return f'--live-host {host}: not an address of this computer ({exc.strerror})'
    return f'--live {port} on {host}: cannot listen there ({exc.strerror})'


def rate_arg(text: str) -> float:
    """``--live-rate``: a rate in (0, 5000] Hz, or ``full``/0 (every message: 0.0)."""
    import math

    if text.strip().lower() == 'full':
        return 0.0
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if value == 0.0:
        return 0.0
    if not (0.0 < value <= PERIOD_RATE_HZ):
        raise argparse.ArgumentTypeError(
            f'{text!r}: a rate in (0, {PERIOD_RATE_HZ:g}] Hz, or full or 0 (every message)'
        )
    return value


#: the live view's options, declared once: the tuner's (``tuner_args`` takes them: its
#: ``--help`` and docs/tuner.md's table), ``drive_host``'s and ``recorder``'s
#: (:func:`add_live_options`); ``option()``'s keywords: Markdown help, argparse's, shown
OPTIONS: dict[str, dict[str, Any]] = {
    '--live': {
        'help': 'watch the run live in Foxglove: a Foxglove WebSocket server '
        '(`foxglove.websocket.v1`) on port PORT (8765 when given bare) carrying every topic '
        "the bag records, on the bag's channels (topic, `ros2msg` schema (`ros2idl` for the "
        'service events), CDR bytes, log time), so the shipped layouts work live as on the '
        'bag; the 5 kHz topics at '
        '`--live-rate`. In Foxglove: "Open connection", "Foxglove WebSocket", '
        '`ws://127.0.0.1:PORT` ([foxglove.md](foxglove.md#watch-a-run-live)). A slow or '
        "frozen client costs only its own live messages (counted in the bag's `im_tuner.live` "
        "metadata; the tuner's last lines and summary.json `sessions[i].live` too), never a "
        'period or a bag message. Refused (one '
        'line, exit 2, nothing created) with `--no-record`, or when the port cannot be '
        "listened on. A session's own: give it again with `--resume` (the command an "
        'interrupted run prints does)',
        'arg': {'type': int_in(1, 65535), 'nargs': '?', 'const': DEFAULT_PORT, 'metavar': 'PORT'},
        'shown': 'off',
    },
    '--live-host': {
        'help': 'with `--live`: the address the server listens on. The default is this '
        "computer only; any other (`0.0.0.0`: every interface) opens the run's data, every "
        'topic of the bag, to whoever reaches this computer on the network: no '
        'authentication, no encryption',
        'arg': {'metavar': 'HOST'},
        'shown': f'`{DEFAULT_HOST}`',
    },
    '--live-rate': {
        'help': "with `--live`: the live rate of the drive's 5 kHz topics (`drive/state`, "
        '`drive/command`, `controller/internals`): every Nth message, N = 5000 / HZ rounded '
        '(the start-up line says N and the rate it gives; the '
        'bag keeps every one); `full` or 0: every message (about 15 000 a second of '
        'simulated time: more than a browser draws). The other topics go whole',
        'arg': {'type': rate_arg, 'metavar': 'HZ|full'},
        'shown': f'{DEFAULT_RATE_HZ:g}',
    },
}


def add_live_options(ap: argparse.ArgumentParser) -> None:
    """The live view's options (:data:`OPTIONS`) on an executable's parser."""
    for flag, o in OPTIONS.items():
        ap.add_argument(
            flag,
            help=f'{plain(o["help"])} (default: {plain(o["shown"])})',
            default=None,
            **o['arg'],
        )


def live_settings(
    live: int | None,
    host: str | None,
    rate_hz: float | None,
    *,
    no_record: bool,
    check: bool = True,
) -> LiveSettings | None:
    """The live view asked for on a command line (None: none), checked as it will run:
    ``--live-host``/``--live-rate`` without ``--live``, ``--live`` with ``--no-record``
    (it serves what the recorder writes), a host or port it cannot listen on: UsageError
    (one line). ``check``: bind the port and release it (call before anything is
    created); False: the settings of a command line checked before."""
    from im_drive_sim.cli import UsageError

    if live is None:
        given = [f for f, v in (('--live-host', host), ('--live-rate', rate_hz)) if v is not None]
        if given:
            raise UsageError(
                f'{" and ".join(given)} without --live would be ignored: give --live [PORT]'
            )
        return None
    if no_record:
        raise UsageError(
            '--live serves what the recorder writes to the bag, and --no-record records '
            'none: give one or the other'
        )
    settings = LiveSettings(
        live,
        DEFAULT_HOST if host is None else host,
        DEFAULT_RATE_HZ if rate_hz is None else rate_hz,
    )
    if check:
        try:
            check_endpoint(settings.host, settings.port)
        except LiveError as exc:
            raise UsageError(str(exc)) from None
    return settings


def every_nth(rate_hz: float) -> int:
    """How many of a 5 kHz topic's messages make one live message at ``rate_hz`` (0: 1,
    every message)."""
    return 1 if rate_hz <= 0 else max(1, round(PERIOD_RATE_HZ / rate_hz))


def is_period_topic(topic: str) -> bool:
    """Whether ``topic`` (fully qualified) is one of the drive's 5 kHz topics, under any
    namespace."""
    return any(topic == '/' + t or topic.endswith('/' + t) for t in PERIOD_TOPICS)


@dataclass(frozen=True)
class LiveSettings:
    """Where the live server listens and how much of the 5 kHz topics it sends."""

    port: int = DEFAULT_PORT
    host: str = DEFAULT_HOST
    #: [Hz] the 5 kHz topics' live rate; 0: every message
    rate_hz: float = DEFAULT_RATE_HZ

    @property
    def url(self) -> str:
        host = f'[{self.host}]' if ':' in self.host else self.host
        return f'ws://{host}:{self.port}'

    def args(self) -> list[str]:
        """The options that give these settings to ``ros2 run im_tuner recorder``."""
        return [
            '--live',
            str(self.port),
            '--live-host',
            self.host,
            '--live-rate',
            f'{self.rate_hz:g}',
        ]

    def describe(self) -> str:
        """Where to connect and what the 5 kHz topics get, as the start-up line says it."""
        n = every_nth(self.rate_hz)
        rate = 'whole' if n == 1 else f'every {n}th: {PERIOD_RATE_HZ / n:.4g} Hz'
        wide = self.host in ('0.0.0.0', '::')
        where = (
            f'{self.url}, every interface: from another computer ws://<this computer>:{self.port}'
            if wide
            else self.url
        )
        return f'{where} (Foxglove: Open connection, Foxglove WebSocket; the 5 kHz topics {rate})'

    def to_dict(self) -> dict[str, Any]:
        return {'url': self.url, 'rate_hz': self.rate_hz, 'every_nth': every_nth(self.rate_hz)}


@dataclass
class LiveFeed:
    """Picks what the live view gets of the rows the bag writer adds (pure: numpy).

    ``every``: bag channel id -> N for the decimated channels (every Nth message by count
    of that channel, the first included); ``counts``: messages seen per decimated
    channel."""

    rate_hz: float = DEFAULT_RATE_HZ
    every: dict[int, int] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)

    def add_channel(self, channel: int, topic: str) -> None:
        n = every_nth(self.rate_hz)
        if n > 1 and is_period_topic(topic):
            self.every[channel] = n
            self.counts[channel] = 0

    def select(self, buf: np.ndarray, idx: np.ndarray) -> list[tuple[int, int, bytes]]:
        """The live messages among Message records ``idx`` (rows channel, log time [ns],
        offset in ``buf``) of a chunk buffer ``buf``: (channel, log time, CDR bytes)."""
        if not len(idx):
            return []
        keep = np.ones(len(idx), bool)
        chans = idx[:, 0]
        for ch, n in self.every.items():
            mine = chans == ch
            k = int(np.count_nonzero(mine))
            if k:
                keep[mine] = (self.counts[ch] + np.arange(k)) % n == 0
                self.counts[ch] += k
        out = []
        for ch, t, off in idx[keep].tolist():
            length = int.from_bytes(buf[off + 1 : off + 9].tobytes(), 'little')  # record body
            out.append((ch, t, buf[off + MESSAGE_HEADER_BYTES : off + 9 + length].tobytes()))
        return out


def live_line(stats: dict[str, Any]) -> str:
    """The live view's figures in one line (the recorder's log, the tuner's end)."""
    head = f'live ({stats["url"]}): {stats["offered"]} messages offered'
    if not stats['clients']:
        return head + ', no client connected'
    dropped = stats['dropped']
    slow = (
        f'; {dropped} dropped for clients that did not read them in time (the bag has them all)'
        if dropped
        else ', none dropped'
    )
    return head + f', {stats["sent"]} sent to {stats["clients"]} client(s){slow}'


def read_live_stats(bags: list[Path]) -> dict[str, Any] | None:
    """The live view's figures of a session, from its bags' metadata.yaml (a recorder
    replaced mid-run: one bag each, added up); None: no bag says any."""
    import json

    from .metadata import read_metadata_yaml

    found = []
    for bag in bags:
        try:
            custom = read_metadata_yaml(bag)['custom_data']
            found.append(json.loads(custom[LIVE_METADATA]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    if not found:
        return None
    total = dict(found[-1])
    for key in ('offered', 'clients', 'sent', 'dropped', 'dropped_before_clients'):
        total[key] = sum(int(f.get(key, 0)) for f in found)
    total['per_client'] = [c for f in found for c in f.get('per_client', [])]
    return total
