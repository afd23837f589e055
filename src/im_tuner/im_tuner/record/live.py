"""The live view: a Foxglove WebSocket server carrying what the recorder writes to the bag.

``--live [PORT]`` (the tuner on every bench, ``drive_host``, ``recorder``) starts one in
the recorder: every message the bag gets passes :class:`LiveFeed` (the writer hands it the
chunk's new rows, :meth:`im_tuner.record.writer.McapWriter.observe`), which keeps the
experiment-rate topics whole and every Nth message of the drive's 5 kHz topics
(:data:`PERIOD_TOPICS`, N = :data:`PERIOD_RATE_HZ` / ``--live-rate``: 250 Hz by default,
20 of 20), and hands (channel, log time, CDR bytes) to :class:`LiveServer`. Each channel
is the bag's: the same topic, message encoding ``cdr``, schema name the ROS type, the
bag's schema encoding (``ros2msg``; ``ros2idl`` for service events) and text, log time
the bag's; so the shipped
Foxglove layouts work unchanged live and on the bag.

Nothing of it waits: the recorder's thread appends to a bounded inbox and wakes the
server's thread (asyncio, a thread of its own); there each client has a bounded queue
(:data:`CLIENT_BACKLOG` messages, the oldest dropped when full) and a sender task of its
own, so a slow or frozen client costs its own dropped live messages (counted, said at
the end: :meth:`LiveServer.stats`), never a period, never a bag message, never another
client's data.

Why ``foxglove-websocket`` (the older Python server of the protocol) and not
``foxglove-sdk``'s ``start_server``: every foxglove-sdk release on PyPI (0.5.0 to 0.30.3,
checked: 0.5.0, 0.6.2, 0.8.1, 0.10.1, 0.14.3, 0.15.3, 0.16.6, 0.20.0, 0.25.3, 0.28.0,
0.29.2, 0.30.3) answers HTTP 400 to a client that asks only for the subprotocol
``foxglove.websocket.v1``, the one Foxglove Studio 1.48 and the open viewers built on it
(Lichtblick) speak; the SDK accepts only ``foxglove.sdk.v1``. ``foxglove-websocket``
speaks ``foxglove.websocket.v1``; its sending awaits each client in turn, so this module
sends through per-client queues instead (``send_message`` is not used).

The pure part (:func:`check_endpoint`, :class:`LiveSettings`, :class:`LiveFeed`) imports
no rclpy, asyncio server or websockets; the server is imported when one starts.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from im_controller.contract import INTERNALS_TOPIC
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
#: messages queued for one client; when full its oldest is dropped (counted)
CLIENT_BACKLOG = 4096
#: messages waiting between the recorder's thread and the server's (the server's thread
#: starved of the CPU); when full the oldest is dropped (counted)
INBOX_SIZE = 65536
#: [bytes] the kernel's send buffer of a client's socket: bounds what waits for a slow
#: client beyond its queue (the live view stays fresh), and is ample for the live rate
#: (about 1 MB/s at 250 Hz) across a LAN
CLIENT_SNDBUF = 256 << 10
#: the bag's metadata record and metadata.yaml ``custom_data`` key of :meth:`LiveServer.stats`
LIVE_METADATA = 'im_tuner.live'
#: [s] at close, how long the server still sends what clients have queued, and then
#: waits for each client's closing handshake
CLOSE_GRACE_S = 1.0


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
            raise LiveError(_cannot_listen(host, port, exc)) from None


def _cannot_listen(host: str, port: int, exc: OSError) -> str:
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
    import argparse
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
            f'{text!r}: a rate in (0, {PERIOD_RATE_HZ:g}] Hz, or full (every message)'
        )
    return value


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


@dataclass
class _ClientQueue:
    """One client's queue and sender task (the server's thread only)."""

    addr: str
    queue: deque = field(default_factory=lambda: deque(maxlen=CLIENT_BACKLOG))
    #: advertisements of channels added while it is connected: sent first, never dropped
    control: deque = field(default_factory=deque)
    wake: Any = None  # asyncio.Event
    task: Any = None  # asyncio.Task
    sent: int = 0
    dropped: int = 0


class LiveServer:
    """A Foxglove WebSocket server (``foxglove.websocket.v1``) in a thread of its own.

    :meth:`add_channel` and :meth:`offer` are called from the recorder's thread and never
    wait on the server or a client; :meth:`close` stops it (clients' queues get
    :data:`CLOSE_GRACE_S` to empty) and returns :meth:`stats`. ``log(text)``: where
    start, connect and disconnect are said (the recorder's ROS logger)."""

    def __init__(
        self, settings: LiveSettings, log: Callable[[str], None], name: str = 'im_tuner'
    ) -> None:
        """Starts the server; LiveError if it cannot listen (nothing is left running)."""
        import asyncio

        self.settings = settings
        self._log = log
        self._name = name
        self._loop = asyncio.new_event_loop()
        self._server: Any = None
        self._inbox: deque = deque(maxlen=INBOX_SIZE)
        self._inbox_dropped = 0
        self._wake_pending = False
        self._lock = threading.Lock()  # the inbox's drop count and wake flag
        self._channels: dict[int, int] = {}  # bag channel -> server channel (server thread)
        self._clients: dict[Any, _ClientQueue] = {}  # connection -> queue (server thread)
        self._gone: list[_ClientQueue] = []
        self.offered = 0
        self._started = threading.Event()
        self._start_error: str | None = None
        self._thread = threading.Thread(target=self._run, name='live server', daemon=True)
        self._thread.start()
        error = self._wait_started()
        if error is not None:
            self._thread.join(5.0)
            raise LiveError(error)
        n = every_nth(settings.rate_hz)
        log(
            f'live: Foxglove WebSocket server on {settings.url} (the 5 kHz topics '
            + ('whole)' if n == 1 else f'every {n}th message)')
        )

    # -- the recorder's thread ---------------------------------------------------------
    def add_channel(
        self, channel: int, topic: str, schema_name: str, schema: str, encoding: str = 'ros2msg'
    ) -> None:
        """Advertise the bag's channel ``channel`` (its topic, ROS type, schema text and
        encoding: ``ros2msg``, ``ros2idl`` for service events) to every client, now and to
        come."""
        self._loop.call_soon_threadsafe(
            self._add_channel, channel, topic, schema_name, schema, encoding
        )

    def offer(self, messages: list[tuple[int, int, bytes]]) -> None:
        """Hand (bag channel, log time [ns], CDR bytes) messages over; returns at once."""
        if not messages:
            return
        self.offered += len(messages)
        with self._lock:
            over = len(self._inbox) + len(messages) - INBOX_SIZE
            if over > 0:
                self._inbox_dropped += over
            self._inbox.extend(messages)
            if self._wake_pending:
                return
            self._wake_pending = True
        with contextlib.suppress(RuntimeError):  # (closed meanwhile)
            self._loop.call_soon_threadsafe(self._pump)

    def stats(self) -> dict[str, Any]:
        """What the live view got: messages offered, sent and dropped per client."""
        clients = [*self._gone, *self._clients.values()]
        return {
            **self.settings.to_dict(),
            'offered': self.offered,
            'clients': len(clients),
            'sent': sum(c.sent for c in clients),
            'dropped': sum(c.dropped for c in clients) + self._inbox_dropped,
            'dropped_before_clients': self._inbox_dropped,
            'per_client': [
                {'client': c.addr, 'sent': c.sent, 'dropped': c.dropped} for c in clients
            ],
        }

    def close(self) -> dict[str, Any]:
        """Stop the server (what clients still have queued gets CLOSE_GRACE_S)."""
        import asyncio

        if self._thread.is_alive():
            fut = asyncio.run_coroutine_threadsafe(self._stop(), self._loop)
            with contextlib.suppress(Exception):
                fut.result(CLOSE_GRACE_S + 5.0)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5.0)
        return self.stats()

    # -- the server's thread -----------------------------------------------------------
    def _wait_started(self, timeout: float = 30.0) -> str | None:
        """Wait for the server's thread to say whether it listens (None) or why not."""
        if not self._started.wait(timeout):
            return f'no answer within {timeout:g} s'
        return self._start_error

    def _run(self) -> None:
        import asyncio
        import logging

        from foxglove_websocket.server import FoxgloveServer

        asyncio.set_event_loop(self._loop)
        owner = self

        class _Server(FoxgloveServer):
            async def _handle_connection(self, connection: Any, path: str = '/') -> None:
                owner._connected(connection)
                try:
                    await super()._handle_connection(connection, path)
                finally:
                    owner._disconnected(connection)

        quiet = logging.getLogger('im_tuner.live.foxglove_websocket')
        quiet.setLevel(logging.WARNING)

        async def start() -> None:
            s = self.settings
            self._server = _Server(s.host, s.port, self._name, logger=quiet)
            self._server.start()
            done, _ = await asyncio.wait(
                [self._server._opened, self._server._task], return_when=asyncio.FIRST_COMPLETED
            )
            task = self._server._task
            if task in done and task.exception() is not None:
                exc = task.exception()
                self._start_error = (
                    _cannot_listen(s.host, s.port, exc)
                    if isinstance(exc, OSError)
                    else f'--live {s.port} on {s.host}: {exc}'
                )

        try:
            self._loop.run_until_complete(start())
        except Exception as exc:  # (said by the starting thread, one line)
            self._start_error = f'--live {self.settings.port} on {self.settings.host}: {exc}'
        self._started.set()
        if self._start_error is None:
            self._loop.run_forever()
        with contextlib.suppress(Exception):
            self._loop.run_until_complete(self._loop.shutdown_asyncgens())
        self._loop.close()

    def _add_channel(
        self, channel: int, topic: str, schema_name: str, schema: str, encoding: str
    ) -> None:
        """Register the channel with the library's server (new clients get it in their
        first advertise) and queue its advertise to the connected ones: the library's
        ``add_channel`` awaits each client's socket in turn, a frozen one for ever."""
        import json

        from foxglove_websocket.types import Channel, ChannelId

        server = self._server
        cid = server._next_channel_id
        server._next_channel_id = ChannelId(cid + 1)
        chan = Channel(
            id=cid,
            topic=topic,
            encoding='cdr',
            schemaName=schema_name,
            schema=schema,
            schemaEncoding=encoding,
        )
        server._channels[cid] = chan
        self._channels[channel] = cid
        text = json.dumps({'op': 'advertise', 'channels': [chan]}, separators=(',', ':'))
        for c in self._clients.values():
            c.control.append(text)
            c.wake.set()

    def _connected(self, connection: Any) -> None:
        import asyncio

        addr = ':'.join(map(str, (connection.remote_address or ('?',))[:2]))
        sock = connection.transport.get_extra_info('socket') if connection.transport else None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, CLIENT_SNDBUF)
        c = _ClientQueue(addr, wake=asyncio.Event())
        c.task = asyncio.ensure_future(self._send_loop(connection, c))
        self._clients[connection] = c
        self._log(f'live: client {addr} connected ({len(self._clients)} connected)')

    def _disconnected(self, connection: Any) -> None:
        c = self._clients.pop(connection, None)
        if c is None:
            return
        c.task.cancel()
        c.dropped += len(c.queue)
        c.queue.clear()
        self._gone.append(c)
        slow = f', {c.dropped} dropped: it did not read them in time' if c.dropped else ''
        self._log(f'live: client {c.addr} disconnected ({c.sent} messages sent{slow})')

    def _pump(self) -> None:
        """Move the inbox into the subscribed clients' queues (oldest dropped when full)."""
        from foxglove_websocket.server import MessageDataHeader
        from foxglove_websocket.types import BinaryOpcode

        with self._lock:
            self._wake_pending = False
            batch = list(self._inbox)
            self._inbox.clear()
        states = {s.connection: s for s in self._server._clients}
        for conn, c in self._clients.items():
            subs = states[conn].subscriptions_by_channel if conn in states else {}
            n0 = len(c.queue)
            added = 0
            for ch, t, data in batch:
                sid = subs.get(self._channels.get(ch, -1))
                if sid is not None:
                    c.queue.append(
                        (MessageDataHeader.pack(BinaryOpcode.MESSAGE_DATA, sid, t), data)
                    )
                    added += 1
            c.dropped += max(0, n0 + added - CLIENT_BACKLOG)
            if added:
                c.wake.set()

    async def _send_loop(self, connection: Any, c: _ClientQueue) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            while True:
                await c.wake.wait()
                c.wake.clear()
                while c.control or c.queue:
                    if c.control:
                        await connection.send(c.control.popleft())
                        continue
                    header, data = c.queue.popleft()
                    c.sent += 1  # (handed to the connection: written before the await)
                    await connection.send(header + data)
        except ConnectionClosed:
            pass

    async def _stop(self) -> None:
        """What clients have queued gets CLOSE_GRACE_S, then each is closed with the
        closing handshake (its last messages arrive: an aborted socket's reset could
        drop them in the client's buffer), a client that does not take it within
        CLOSE_GRACE_S aborted (a frozen one); then the server."""
        import asyncio
        import time

        deadline = time.monotonic() + CLOSE_GRACE_S
        while time.monotonic() < deadline and any(
            c.queue or c.control for c in self._clients.values()
        ):
            await asyncio.sleep(0.01)

        async def close(conn: Any, c: _ClientQueue) -> None:
            c.task.cancel()
            c.dropped += len(c.queue)
            c.queue.clear()
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(conn.close(), CLOSE_GRACE_S)
            if conn.transport is not None and not conn.transport.is_closing():
                conn.transport.abort()

        await asyncio.gather(*(close(conn, c) for conn, c in list(self._clients.items())))
        if self._server is not None:
            self._server._task.cancel()
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(self._server._task, 2.0)


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
