"""The live view's server: a Foxglove WebSocket server (``foxglove.websocket.v1``) in a
thread of its own, fed by the recorder (:mod:`.live` says what goes live and why this
library).

Nothing of it waits on a client: the recorder's thread appends to a bounded inbox and
wakes the server's thread (asyncio); there each client has two bounded queues and a
sender task of its own, so a slow or frozen client costs its own dropped live messages
(counted: :meth:`LiveServer.stats`), never a period, never a bag message, never another
client's data. The experiment-rate topics' queue is sent first and is deep: a client
that falls behind loses 5 kHz messages, not an experiment's loss. A transient-local
topic (``tuner/result``) is latched as ROS latches it: a client that subscribes late first
gets what was published on it (at most :data:`LATCHED_MAX` messages), so Fig. 9 shows the
whole run to a viewer connected mid-run.
``foxglove-websocket``'s own sending (``send_message``, ``add_channel``) awaits each
client's socket in turn, a frozen one for ever: this module sends through the
per-client queues instead, and uses the library for the handshake, the server info, the
first advertise and the subscriptions (its client states).
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from .live import LiveError, LiveSettings, cannot_listen, every_nth, is_period_topic

#: messages of the 5 kHz topics queued for one client; when full its oldest is dropped
#: (counted)
CLIENT_BACKLOG = 4096
#: messages of the experiment-rate topics (a loss, a result: a few per experiment) queued
#: for one client, sent before the 5 kHz ones; dropped (counted) only past this many, a
#: client frozen for thousands of experiments
CLIENT_WHOLE_BACKLOG = 65536
#: messages waiting between the recorder's thread and the server's (the server's thread
#: starved of the CPU); when full the oldest is dropped (counted)
INBOX_SIZE = 65536
#: messages kept of each transient-local topic, for the clients that subscribe later
LATCHED_MAX = 65536
#: [bytes] the kernel's send buffer of a client's socket: bounds what waits for a slow
#: client beyond its queue (the live view stays fresh), and is ample for the live rate
#: (about 1 MB/s at 250 Hz) across a LAN
CLIENT_SNDBUF = 256 << 10
#: [s] at close, how long the server goes on sending what clients have queued while
#: none of it moves (a frozen client), and then waits for each client's closing handshake
CLOSE_GRACE_S = 1.0
#: [s] at close, the longest it goes on sending to clients that take their messages
#: slowly (a loaded machine): the run's last losses reach a live client
CLOSE_MAX_S = 10.0


@dataclass
class _ClientQueue:
    """One client's queue and sender task (the server's thread only)."""

    addr: str
    queue: deque = field(default_factory=lambda: deque(maxlen=CLIENT_BACKLOG))
    #: the experiment-rate topics' messages: sent before ``queue``'s
    whole: deque = field(default_factory=lambda: deque(maxlen=CLIENT_WHOLE_BACKLOG))
    #: advertisements of channels added while it is connected: sent first, never dropped
    control: deque = field(default_factory=deque)
    wake: Any = None  # asyncio.Event
    task: Any = None  # asyncio.Task
    sent: int = 0
    dropped: int = 0

    def end(self) -> None:
        """Stop its sender; what it still has queued counts as dropped."""
        self.task.cancel()
        self.dropped += len(self.queue) + len(self.whole)
        self.queue.clear()
        self.whole.clear()


class LiveServer:
    """A Foxglove WebSocket server (``foxglove.websocket.v1``) in a thread of its own.

    :meth:`add_channel` and :meth:`offer` are called from the recorder's thread and never
    wait on the server or a client; :meth:`close` stops it (clients' experiment-rate
    messages sent first, :meth:`_stop`) and returns :meth:`stats`. ``log(text)``: where
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
        self._periodic: set[int] = set()  # bag channels of the 5 kHz topics (server thread)
        #: server channel -> (log time, bytes) published so far, of the transient-local
        #: topics (server thread)
        self._latched: dict[int, deque] = {}
        self._clients: dict[Any, _ClientQueue] = {}  # connection -> queue (server thread)
        self._gone: list[_ClientQueue] = []
        self.offered = 0
        self._started = threading.Event()
        self._start_error: str | None = None
        self._thread = threading.Thread(target=self._run, name='live server', daemon=True)
        self._thread.start()
        # the server's thread says whether it listens (None) or why not
        error = self._start_error if self._started.wait(30.0) else 'no answer within 30 s'
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
        self,
        channel: int,
        topic: str,
        schema_name: str,
        schema: str,
        encoding: str = 'ros2msg',
        latched: bool = False,
    ) -> None:
        """Advertise the bag's channel ``channel`` (its topic, ROS type, schema text and
        encoding: ``ros2msg``, ``ros2idl`` for service events) to every client, now and to
        come; ``latched``: a transient-local topic (a late subscriber gets its past)."""
        self._loop.call_soon_threadsafe(
            self._add_channel, channel, topic, schema_name, schema, encoding, latched
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
        """Stop the server (what clients still have queued: :meth:`_stop`)."""
        import asyncio

        if self._thread.is_alive():
            fut = asyncio.run_coroutine_threadsafe(self._stop(), self._loop)
            with contextlib.suppress(Exception):
                fut.result(CLOSE_MAX_S + CLOSE_GRACE_S + 5.0)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5.0)
        return self.stats()

    # -- the server's thread -----------------------------------------------------------
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

            async def _handle_client_text_message(self, client: Any, message: Any) -> None:
                before = dict(client.subscriptions_by_channel)
                await super()._handle_client_text_message(client, message)
                new = {
                    cid: sid
                    for cid, sid in client.subscriptions_by_channel.items()
                    if before.get(cid) != sid
                }
                owner._subscribed(client.connection, new)

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
                    cannot_listen(s.host, s.port, exc)
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
        self, channel: int, topic: str, schema_name: str, schema: str, encoding: str, latched: bool
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
        if is_period_topic(topic):
            self._periodic.add(channel)
        if latched:
            self._latched[cid] = deque(maxlen=LATCHED_MAX)
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
        c.end()
        self._gone.append(c)
        slow = f', {c.dropped} dropped: it did not read them in time' if c.dropped else ''
        self._log(f'live: client {c.addr} disconnected ({c.sent} messages sent{slow})')

    def _subscribed(self, connection: Any, new: dict[int, int]) -> None:
        """A client's new subscriptions (server channel -> subscription id): the past of
        the latched ones first (in the experiment-rate queue)."""
        from foxglove_websocket.server import MessageDataHeader
        from foxglove_websocket.types import BinaryOpcode

        c = self._clients.get(connection)
        if c is None:
            return
        for cid, sid in new.items():
            for t, data in self._latched.get(cid, ()):
                c.whole.append((MessageDataHeader.pack(BinaryOpcode.MESSAGE_DATA, sid, t), data))
        c.wake.set()

    def _pump(self) -> None:
        """Move the inbox into the subscribed clients' queues (a 5 kHz topic's message to
        ``queue``, another's to ``whole``; the oldest dropped when one is full)."""
        from foxglove_websocket.server import MessageDataHeader
        from foxglove_websocket.types import BinaryOpcode

        with self._lock:
            self._wake_pending = False
            batch = list(self._inbox)
            self._inbox.clear()
        for ch, t, data in batch:
            past = self._latched.get(self._channels.get(ch, -1))
            if past is not None:
                past.append((t, data))
        states = {s.connection: s for s in self._server._clients}
        for conn, c in self._clients.items():
            subs = states[conn].subscriptions_by_channel if conn in states else {}
            n0, w0 = len(c.queue), len(c.whole)
            added = whole = 0
            for ch, t, data in batch:
                sid = subs.get(self._channels.get(ch, -1))
                if sid is not None:
                    item = (MessageDataHeader.pack(BinaryOpcode.MESSAGE_DATA, sid, t), data)
                    if ch in self._periodic:
                        c.queue.append(item)
                        added += 1
                    else:
                        c.whole.append(item)
                        whole += 1
            c.dropped += max(0, n0 + added - CLIENT_BACKLOG)
            c.dropped += max(0, w0 + whole - CLIENT_WHOLE_BACKLOG)
            if added or whole:
                c.wake.set()

    async def _send_loop(self, connection: Any, c: _ClientQueue) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            while True:
                await c.wake.wait()
                c.wake.clear()
                while c.control or c.whole or c.queue:
                    if c.control:
                        await connection.send(c.control.popleft())
                        continue
                    header, data = (c.whole or c.queue).popleft()
                    c.sent += 1  # (handed to the connection: written before the await)
                    await connection.send(header + data)
        except ConnectionClosed:
            pass

    async def _stop(self) -> None:
        """The 5 kHz topics' queued messages are dropped (counted); what clients still
        have queued of the others (a loss, a result) is sent while it moves
        (CLOSE_GRACE_S without progress: a frozen client; CLOSE_MAX_S at most). Then each
        client is closed with the closing handshake; one that does not answer within
        CLOSE_GRACE_S is closed by the socket's own close when all was handed to the
        kernel (a slow client still reads what is in flight, the run's last loss among
        it: an abort's reset would discard what it has not read), else aborted (a
        frozen one); then the server."""
        import asyncio
        import time

        def unsent() -> tuple[int, int]:  # (messages queued, bytes in the transports)
            n = b = 0
            for conn, c in self._clients.items():
                n += len(c.whole) + len(c.control)
                if conn.transport is not None:
                    b += conn.transport.get_write_buffer_size()
            return n, b

        for c in self._clients.values():
            c.dropped += len(c.queue)
            c.queue.clear()
        now = time.monotonic()
        end, still = now + CLOSE_MAX_S, now + CLOSE_GRACE_S
        last = unsent()
        while any(last) and now < min(end, still):
            await asyncio.sleep(0.01)
            now, left = time.monotonic(), unsent()
            if left < last or sum(left) < sum(last):  # (it moves)
                still = now + CLOSE_GRACE_S
            last = left

        async def close(conn: Any, c: _ClientQueue) -> None:
            c.end()
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(conn.close(), CLOSE_GRACE_S)
            t = conn.transport
            if t is not None and not t.is_closing():
                if t.get_write_buffer_size() == 0:
                    t.close()  # (FIN after what the kernel holds)
                else:
                    t.abort()

        await asyncio.gather(*(close(conn, c) for conn, c in list(self._clients.items())))
        if self._server is not None:
            self._server._task.cancel()
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(self._server._task, 2.0)
