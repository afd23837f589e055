"""The live view's parts without ROS: what of the bag's records goes live (every record
once, the 5 kHz topics every Nth), the options' checks, and the server beside a client
that reads and one that never does (im_tuner.record.live)."""

from __future__ import annotations

import argparse
import socket
import struct
import time

import numpy as np
import pytest
from live_client import SUBPROTOCOL, FrozenClient, Watcher

from im_drive_sim.cli import UsageError
from im_tuner.record import live
from im_tuner.record.live import LiveFeed, LiveSettings
from im_tuner.record.live_server import LiveServer
from im_tuner.record.writer import McapWriter


def _records(tmp_path, chunk_size: int, messages: list[tuple[int, int, bytes]]):
    """Write ``messages`` (channel, log time, bytes) through a writer whose observer is a
    LiveFeed of two 5 kHz channels (1, 2) and one other (3); returns what went live."""
    w = McapWriter(tmp_path / 'x.mcap', compression='none', chunk_size=chunk_size)
    feed = LiveFeed(250.0)
    for ch, topic in ((1, '/drive/state'), (2, '/bench1/controller/internals'), (3, '/clock')):
        feed.add_channel(ch, topic)
    got: list[tuple[int, int, bytes]] = []
    w.observer = lambda buf, idx: got.extend(feed.select(buf, idx))
    for i, (ch, t, data) in enumerate(messages):
        w.add_message(ch, i, t, t, data)
        if i % 7 == 0:
            w.observe()  # (as the recorder after a drain)
    w.close()
    return got


def test_every_record_goes_live_once_the_5khz_topics_every_20th(tmp_path):
    rng = np.random.default_rng(3)
    msgs = [
        (int(ch), 1000 + i, rng.bytes(int(rng.integers(8, 300))))
        for i, ch in enumerate(rng.choice([1, 2, 3], size=2000, p=[0.45, 0.45, 0.1]))
    ]
    # small chunks: many flushes between two observations (each record still seen once)
    got = _records(tmp_path, 4096, msgs)
    for ch in (1, 2):
        mine = [m for m in msgs if m[0] == ch]
        assert [m for m in got if m[0] == ch] == mine[::20]
    assert [m for m in got if m[0] == 3] == [m for m in msgs if m[0] == 3]
    assert got == sorted(got, key=lambda m: m[1])  # in the bag's order


def test_the_rate_and_the_topics():
    assert live.every_nth(250.0) == 20 and live.every_nth(0.0) == 1
    assert live.every_nth(5000.0) == 1 and live.every_nth(1.0) == 5000
    assert live.is_period_topic('/drive/command') and live.is_period_topic('/b/drive/state')
    assert not live.is_period_topic('/drive/status') and not live.is_period_topic('/state')
    assert live.rate_arg('full') == 0.0 and live.rate_arg('0') == 0.0
    assert live.rate_arg('100') == 100.0
    for bad in ('-1', 'nan', 'inf', '5001', 'fast'):
        with pytest.raises(argparse.ArgumentTypeError):
            live.rate_arg(bad)
    s = LiveSettings(9000, '::1', 0.0)
    assert s.url == 'ws://[::1]:9000' and s.to_dict()['every_nth'] == 1
    assert s.args() == ['--live', '9000', '--live-host', '::1', '--live-rate', '0']


def test_the_settings_are_checked_before_anything():
    assert live.live_settings(None, None, None, no_record=True) is None
    with pytest.raises(UsageError, match='without --live would be ignored'):
        live.live_settings(None, '0.0.0.0', None, no_record=False)
    with pytest.raises(UsageError, match='--no-record records none'):
        live.live_settings(8765, None, None, no_record=True)
    with socket.socket() as busy:
        busy.bind(('127.0.0.1', 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        with pytest.raises(UsageError, match=f'port {port} is in use on 127.0.0.1'):
            live.live_settings(port, None, None, no_record=False)
        # (not checked: the settings of a command line checked before)
        assert live.live_settings(port, None, 10.0, no_record=False, check=False) == (
            LiveSettings(port, '127.0.0.1', 10.0)
        )
    with pytest.raises(UsageError, match='not an address of this computer'):
        live.live_settings(8765, '192.0.2.1', None, no_record=False)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def _wait(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f'timed out after {timeout} s waiting for {what}'
        time.sleep(0.01)


def test_a_frozen_client_loses_its_own_messages_only():
    port = _free_port()
    said: list[str] = []
    server = LiveServer(LiveSettings(port), said.append)
    try:
        server.add_channel(5, '/drive/state', 'std_msgs/msg/Float64MultiArray', 'float64[] data')
        server.add_channel(6, '/controller/loss', 'diagnostic_msgs/msg/DiagnosticArray', 'x')
        frozen = FrozenClient(port, {'/drive/state', '/controller/loss'}, 30.0)
        watcher = Watcher(port, timeout=30.0).start()
        _wait(lambda: len(watcher.channels) == 2, 30.0, 'the advertise')
        _wait(lambda: sum('connected' in s for s in said) == 2, 30.0, 'two clients')

        def subscribed() -> bool:  # (the library's client states: both subscribed to both)
            states = server._server._clients
            return len(states) == 2 and all(len(c.subscriptions) == 2 for c in states)

        _wait(subscribed, 30.0, 'both subscriptions')
        server.offer([(6, 1, b'first')])
        _wait(lambda: '/controller/loss' in watcher.messages, 30.0, 'the first message')
        # about 4 MB, in the bursts of a recorder's polls, a channel added midway
        payload = bytes(range(200))
        t = 2
        for burst in range(200):
            if burst == 100:
                server.add_channel(7, '/drive/status', 'diagnostic_msgs/msg/DiagnosticArray', 'y')
            server.offer([(5, t + k, payload) for k in range(100)] + [(6, t + 100, b'loss')])
            t += 101
            n = (burst + 1) * 100

            def states(n: int = n) -> bool:
                return len(watcher.messages.get('/drive/state', [])) == n

            _wait(states, 30.0, f'{n} states')
        stats = server.close()
        watcher.join(30.0)
    finally:
        server.close()
    frozen.close()
    assert watcher.subprotocol == SUBPROTOCOL
    # the reading client: every message, in order, with the bag's log time and bytes
    state = watcher.messages['/drive/state']
    assert len(state) == 200 * 100 and [m[0] for m in state] == sorted(m[0] for m in state)
    assert all(data == payload for _t, data in state)
    assert len(watcher.messages['/controller/loss']) == 201
    assert {c['topic'] for c in watcher.channels.values()} == {
        '/drive/state',
        '/controller/loss',
        '/drive/status',
    }
    # the frozen one: most dropped, counted; everything accounted for
    per = {c['sent'] == 1 + 200 * 101: c for c in stats['per_client']}
    assert per[True]['dropped'] == 0
    assert per[False]['dropped'] > 10_000
    assert per[False]['sent'] + per[False]['dropped'] == 1 + 200 * 101
    assert stats['offered'] == 1 + 200 * 101 and stats['dropped'] == per[False]['dropped']
    assert said[0].startswith(f'live: Foxglove WebSocket server on ws://127.0.0.1:{port} ')
    assert struct.calcsize('<BIQ') == 13  # (the message data header the clients read)


def test_a_late_client_gets_the_past_of_a_transient_local_topic_only():
    """A transient-local topic (tuner/result) is latched as ROS latches it: a client that
    subscribes after its messages were offered gets them first, in order, then the new
    ones; a volatile topic's past is not sent."""
    port = _free_port()
    said: list[str] = []
    server = LiveServer(LiveSettings(port), said.append)
    try:
        server.add_channel(
            5, '/tuner/result', 'diagnostic_msgs/msg/DiagnosticArray', 'x', latched=True
        )
        server.add_channel(6, '/controller/loss', 'diagnostic_msgs/msg/DiagnosticArray', 'x')
        server.offer([(5, 10, b'r0'), (6, 11, b'l0'), (5, 12, b'r1'), (5, 13, b'r2')])
        watcher = Watcher(port, timeout=30.0).start()
        _wait(lambda: len(watcher.messages.get('/tuner/result', [])) == 3, 30.0, 'the past')
        _wait(lambda: len(server._server._clients) == 1, 30.0, 'the client state')
        server.offer([(6, 20, b'l1'), (5, 21, b'r3')])
        _wait(lambda: len(watcher.messages.get('/tuner/result', [])) == 4, 30.0, 'the new one')
        _wait(lambda: len(watcher.messages.get('/controller/loss', [])) == 1, 30.0, 'a loss')
        server.close()
        watcher.join(30.0)
    finally:
        server.close()
    assert watcher.messages['/tuner/result'] == [(10, b'r0'), (12, b'r1'), (13, b'r2'), (21, b'r3')]
    assert watcher.messages['/controller/loss'] == [(20, b'l1')]


def test_the_live_host_warning_is_for_an_address_other_computers_reach():
    """``--live-host`` warns (the run's topics open to the network) only for an address
    that is not this computer's loopback; a name is resolved first."""
    from im_tuner.tuner_session import is_loopback

    for host in ('127.0.0.1', '127.0.0.2', '::1', 'localhost'):
        assert is_loopback(host), host
    for host in ('0.0.0.0', '::', '192.0.2.1', 'no-such-host.invalid'):
        assert not is_loopback(host), host


def test_the_printed_resume_command_quotes_its_live_host(tmp_path):
    """The resume command an interrupted run prints runs as printed: each value quoted
    for the shell (a host with a zone index, a run directory with a space)."""
    import shlex

    from im_tuner.tuner_args import parse_options
    from im_tuner.tuner_session import resume_command

    run = tmp_path / 'my run'
    cli = parse_options(['--live', '9000', '--live-host', 'fe80::1%eth0', '--live-rate', '300'])
    command = resume_command('ros2', run, cli)
    assert shlex.split(command) == [
        'ros2', 'run', 'im_tuner', 'tuner', '--resume', str(run),
        '--live', '9000', '--live-host', 'fe80::1%eth0', '--live-rate', '300',
    ]  # fmt: skip
    assert resume_command('ros2', tmp_path, parse_options([])).endswith(f'--resume {tmp_path}')
