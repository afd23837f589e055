"""Foxglove WebSocket clients (``foxglove.websocket.v1``) for the live view's tests.

:class:`Watcher` subscribes to every channel as it is advertised and keeps every message;
:class:`FrozenClient` does the handshake, subscribes to the channels it was told of and
never reads its socket again (a small receive buffer, so that the server sees it full).
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import threading
import time
from dataclasses import dataclass, field

SUBPROTOCOL = 'foxglove.websocket.v1'


def connect_when_listening(port: int, timeout: float, rcvbuf: int = 0) -> socket.socket:
    """A TCP connection to 127.0.0.1:``port`` once something listens there (polled on a
    steady clock until ``timeout`` s)."""
    deadline = time.monotonic() + timeout
    while True:
        s = socket.socket()
        if rcvbuf:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        try:
            s.connect(('127.0.0.1', port))
            return s
        except OSError:
            s.close()
            if time.monotonic() > deadline:
                raise AssertionError(
                    f'nothing listened on port {port} within {timeout} s'
                ) from None
            time.sleep(0.05)


def _send_text(s: socket.socket, text: str) -> None:
    """One masked text frame (a client's)."""
    _send_frame(s, 0x1, text.encode())


def _send_frame(s: socket.socket, opcode: int, data: bytes) -> None:
    """One final masked frame (a client's) of ``opcode``."""
    mask = os.urandom(4)
    n = len(data)
    head = bytes([0x80 | opcode])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 1 << 16:
        head += bytes([0x80 | 126]) + struct.pack('>H', n)
    else:
        head += bytes([0x80 | 127]) + struct.pack('>Q', n)
    s.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))


class _Frames:
    """Reads a server's (unmasked) frames from a socket."""

    def __init__(self, s: socket.socket) -> None:
        self.s = s
        self.buf = b''

    def _need(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.s.recv(1 << 16)
            if not chunk:
                raise ConnectionError('closed')
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def handshake(self) -> str:
        """Send the upgrade request; return the subprotocol the server chose."""
        key = base64.b64encode(os.urandom(16)).decode()
        self.s.sendall(
            (
                'GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n'
                f'Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n'
                f'Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n'
            ).encode()
        )
        while b'\r\n\r\n' not in self.buf:
            chunk = self.s.recv(4096)
            if not chunk:
                raise ConnectionError('closed during the handshake')
            self.buf += chunk
        head, self.buf = self.buf.split(b'\r\n\r\n', 1)
        lines = head.decode().split('\r\n')
        assert ' 101 ' in lines[0], lines[0]
        return next(
            (
                v.strip()
                for k, v in (x.split(':', 1) for x in lines[1:])
                if k.lower() == 'sec-websocket-protocol'
            ),
            '',
        )

    def frame(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next whole message (fragments joined)."""
        op0, parts = None, []
        while True:
            b0, b1 = self._need(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack('>H', self._need(2))[0]
            elif n == 127:
                n = struct.unpack('>Q', self._need(8))[0]
            payload = self._need(n)
            op = b0 & 0x0F
            if op >= 8:  # control: close ends; a ping is answered, as every client must
                if op == 8:  # (the server's keepalive closes a client that does not, after
                    raise ConnectionError('closed by the server')  # 40 s: a loaded run)
                if op == 9:
                    _send_frame(self.s, 0xA, payload)
                continue
            op0 = op if op0 is None else op0
            parts.append(payload)
            if b0 & 0x80:
                return op0, b''.join(parts)


@dataclass
class Watcher:
    """A client that subscribes to every channel and keeps every message (a thread)."""

    port: int
    timeout: float = 120.0
    subprotocol: str = ''
    channels: dict[int, dict] = field(default_factory=dict)  #: id -> the advertised channel
    #: topic -> [(log time [ns], CDR bytes)]
    messages: dict[str, list[tuple[int, bytes]]] = field(default_factory=dict)
    error: BaseException | None = None
    #: [s] a pause after each message read (a slow client: a loaded machine)
    pause: float = 0.0
    #: [bytes] the socket's receive buffer (0: the system's, which grows as it reads)
    rcvbuf: int = 0
    #: topic -> when this client sent its subscription [ns, the system clock: the bag's
    #: log times are the recorder's on the same clock]
    subscribed_at: dict[str, int] = field(default_factory=dict)

    def start(self) -> Watcher:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            s = connect_when_listening(self.port, self.timeout, self.rcvbuf)
            f = _Frames(s)
            self.subprotocol = f.handshake()
            subs: dict[int, str] = {}
            while True:
                op, data = f.frame()
                if op == 1:
                    msg = json.loads(data)
                    if msg['op'] == 'advertise':
                        new = []
                        for c in msg['channels']:
                            self.channels[c['id']] = c
                            if c['id'] not in subs.values():
                                sid = len(subs) + 1
                                subs[sid] = c['id']
                                new.append({'id': sid, 'channelId': c['id']})
                        now = time.time_ns()
                        for sub in new:
                            self.subscribed_at[self.channels[sub['channelId']]['topic']] = now
                        _send_text(s, json.dumps({'op': 'subscribe', 'subscriptions': new}))
                elif op == 2 and data[0] == 1:
                    sid, t = struct.unpack_from('<IQ', data, 1)
                    topic = self.channels[subs[sid]]['topic']
                    self.messages.setdefault(topic, []).append((t, data[13:]))
                    if self.pause:
                        time.sleep(self.pause)
        except (ConnectionError, OSError):
            pass  # the server ended (the run is over)
        except BaseException as exc:
            self.error = exc

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)
        assert not self._thread.is_alive(), f'the live client still reads after {timeout} s'
        if self.error is not None:
            raise self.error


class FrozenClient:
    """Connected, handshake done, subscribed to every channel advertised once ``topics``
    are, then never reads its socket (its receive buffer ``rcvbuf`` bytes)."""

    def __init__(self, port: int, topics: set[str], timeout: float, rcvbuf: int = 4096) -> None:
        self.sock = connect_when_listening(port, timeout, rcvbuf)
        self.sock.settimeout(timeout)
        f = _Frames(self.sock)
        assert f.handshake() == SUBPROTOCOL
        channels: dict[int, str] = {}
        while not topics <= set(channels.values()):
            op, data = f.frame()
            if op == 1:
                msg = json.loads(data)
                if msg['op'] == 'advertise':
                    channels |= {c['id']: c['topic'] for c in msg['channels']}
        subs = [{'id': i + 1, 'channelId': c} for i, c in enumerate(sorted(channels))]
        _send_text(self.sock, json.dumps({'op': 'subscribe', 'subscriptions': subs}))
        self.topics = set(channels.values())

    def close(self) -> None:
        self.sock.close()
