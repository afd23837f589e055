"""The live view (``--live``): a Foxglove WebSocket client sees the bag's channels and
messages while the run goes on; a frozen client changes nothing of the run; bad input is
one line, exit 2, nothing created (docs/foxglove.md, "Watch a run live").

The clients speak ``foxglove.websocket.v1`` over a plain socket (test/live_client.py), as
Foxglove Studio 1.48 does.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from live_client import SUBPROTOCOL, FrozenClient, Watcher
from mcap.reader import make_reader

from im_tuner.record.reader import parse_float64_multiarray

VENV = Path(sys.prefix)
ROS2 = str(VENV / 'bin' / 'ros2')
#: [s] a whole short run on a loaded 2-core machine, start-up (numba's cache) included
RUN_TIMEOUT = 400
#: the bench's topics every live client must get messages on (the 5 kHz ones decimated)
PERIOD_TOPICS = ('/drive/state', '/drive/command', '/controller/internals')

_DOMAINS = itertools.count(60)


@pytest.fixture(autouse=True)
def own_domain(monkeypatch):
    """Each test in a DDS domain of its own (the children inherit it): a bench left on a
    graph by a failed test cannot meet the next one's. (60 up from the worker's: below
    the next worker's, 100 up, and above test_faults', conftest.py.)"""
    base = int(os.environ['ROS_DOMAIN_ID'])
    monkeypatch.setenv('ROS_DOMAIN_ID', str((base + next(_DOMAINS)) % 233))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def tuner(procs, out: Path, *args: str, cwd: Path | None = None):
    return procs.start(
        [ROS2, 'run', 'im_tuner', 'tuner', '--out', str(out), '--seed', '7', *args],
        cwd=cwd,
    )


def bag_messages(run: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Topic -> [(log time, CDR bytes)] of the run's bag."""
    out: dict[str, list[tuple[int, bytes]]] = {}
    with open(next((run / 'bag_0').glob('*.mcap')), 'rb') as f:
        for _schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append((message.log_time, message.data))
    return out


def bag_channels(run: Path) -> dict[str, tuple[str, str, str, str]]:
    """Topic -> (message encoding, schema name, schema encoding, schema text)."""
    with open(next((run / 'bag_0').glob('*.mcap')), 'rb') as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {
        c.topic: (
            c.message_encoding,
            summary.schemas[c.schema_id].name,
            summary.schemas[c.schema_id].encoding,
            summary.schemas[c.schema_id].data.decode(),
        )
        for c in summary.channels.values()
    }


def losses(run: Path) -> list[tuple[str, float | None]]:
    rows = [json.loads(line) for line in (run / 'results.jsonl').read_text().splitlines()]
    return [(r['kind'], r.get('loss')) for r in rows]


# (the real-time bench alone, as its other tests: beside another test its periods run late)
@pytest.mark.parametrize(
    'bench', ['inproc', 'processes', pytest.param('realtime', marks=pytest.mark.serial)]
)
def test_a_live_client_gets_the_bags_channels_and_messages(bench, procs, tmp_path):
    port = free_port()
    watcher = Watcher(port, timeout=RUN_TIMEOUT).start()
    run = tmp_path / 'run'
    p = tuner(procs, run, '--bench', bench, '--budget', '3', '--live', str(port))
    out, err = p.communicate(timeout=RUN_TIMEOUT)
    assert p.returncode == 0, err
    watcher.join(30.0)
    assert watcher.subprotocol == SUBPROTOCOL

    # the bag's channels, as the bag has them: topic, encoding, schema name and text
    channels = bag_channels(run)
    advertised = {
        c['topic']: (c['encoding'], c['schemaName'], c['schemaEncoding'], c['schema'])
        for c in watcher.channels.values()
    }
    assert advertised == channels

    bag = bag_messages(run)
    got = watcher.messages
    assert set(PERIOD_TOPICS) | {'/controller/loss'} <= set(got)
    missing = [t for t in bag if t not in got]
    assert not missing, (
        f'no live message on {missing} (the bag has {[len(bag[t]) for t in missing]})'
    )
    # the experiments' losses, live, byte for byte the bag's: every one the recorder took
    # after this client subscribed (a loaded machine may answer the channel's advertisement
    # after the first losses: as with foxglove_bridge, a subscription gets what comes after
    # it), in order, to the run's last
    recorded, live = bag['/controller/loss'], got['/controller/loss']
    assert len(recorded) == len(losses(run)) >= 4
    assert live == recorded[len(recorded) - len(live) :]
    after = [m for m in recorded if m[0] > watcher.subscribed_at['/controller/loss']]
    assert len(live) >= len(after)
    # the 5 kHz topics at 250 Hz: every 20th of the bag's messages from the first live
    # one on (the client subscribed after the first few), but for those a loaded machine
    # made the server drop for this client (counted below)
    summary = json.loads((run / 'summary.json').read_text())
    said = summary['sessions'][-1]['live']
    for topic in PERIOD_TOPICS:
        live, recorded = got[topic], bag[topic]
        first = recorded.index(live[0])
        every = recorded[first::20]
        at = {m: i for i, m in enumerate(every)}
        where = [at[m] for m in live]  # (KeyError: a message not among every 20th)
        assert where == sorted(set(where)), topic  # in order, none twice
        assert len(every) - len(live) <= said['dropped'] + 1, topic
    # a state decoded: the values of the bag's message of the same log time
    t, data = got['/drive/state'][len(got['/drive/state']) // 2]
    same = [d for tb, d in bag['/drive/state'] if tb == t]
    assert len(same) == 1
    live_values, bag_values = parse_float64_multiarray(data), parse_float64_multiarray(same[0])
    assert len(live_values) == 14 and list(live_values) == list(bag_values)
    # said at the end, and in summary.json
    assert said['url'] == f'ws://127.0.0.1:{port}' and said['every_nth'] == 20
    assert said['clients'] == 1
    assert said['sent'] == sum(len(m) for m in got.values())
    assert f'live (ws://127.0.0.1:{port}): ' in out
    if said['dropped'] == 0:
        assert 'none dropped' in out


def test_a_frozen_client_changes_nothing_of_the_run(procs, tmp_path):
    """Connected, subscribed to everything, never reading, for a whole lock-step run: the
    same losses and bag counts as the same run without --live; its drops said."""
    args = ('--bench', 'inproc', '--budget', '4')
    plain = tuner(procs, tmp_path / 'plain', *args)
    _out, err = plain.communicate(timeout=RUN_TIMEOUT)
    assert plain.returncode == 0, err

    port = free_port()
    live = tuner(procs, tmp_path / 'live', *args, '--live', str(port))
    frozen = FrozenClient(port, set(PERIOD_TOPICS) | {'/controller/loss'}, RUN_TIMEOUT)
    out, err = live.communicate(timeout=RUN_TIMEOUT)
    frozen.close()
    assert live.returncode == 0, err

    assert losses(tmp_path / 'live') == losses(tmp_path / 'plain')
    counts = {
        name: {t: len(m) for t, m in bag_messages(tmp_path / name).items()}
        for name in ('plain', 'live')
    }
    for topic in (*PERIOD_TOPICS, '/controller/loss', '/drive/joint_states'):
        assert counts['live'][topic] == counts['plain'][topic], topic
    summary = json.loads((tmp_path / 'live' / 'summary.json').read_text())
    said = summary['sessions'][-1]['live']
    assert said['clients'] == 1 and said['dropped'] > 0
    assert said['sent'] + said['dropped'] <= said['offered']
    assert f'{said["dropped"]} dropped for clients that did not read them in time' in out
    for name in ('plain', 'live'):  # the recorder lost nothing either way
        meta = yaml.safe_load((tmp_path / name / 'bag_0' / 'metadata.yaml').read_text())
        assert meta['rosbag2_bagfile_information']['custom_data']['im_tuner.lost_total'] == '0'


def _refused(p: subprocess.Popen, says: str) -> None:
    _out, err = p.communicate(timeout=120)
    lines = err.strip().splitlines()
    assert p.returncode == 2, err
    assert len(lines) == 1 and says in lines[0], err


@pytest.fixture
def busy_port():
    """A port something listens on."""
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        s.listen(1)
        yield s.getsockname()[1]


@pytest.mark.parametrize(
    'args,says',
    [
        (['--live', '{busy}'], 'is in use on 127.0.0.1'),
        (['--live', '{busy}', '--bench', 'processes'], 'is in use on 127.0.0.1'),
        (['--live', '--no-record'], '--no-record records none'),
        (['--live-host', '0.0.0.0'], 'without --live would be ignored'),
        (['--live-rate', '100'], 'without --live would be ignored'),
        (['--live', '8765', '--live-host', 'no-such-host.invalid'], 'not an address or a name'),
        (['--live', '8765', '--live-host', '192.0.2.1'], 'not an address of this computer'),
        (['--live', '0'], 'argument --live: must be >= 1, got 0'),
        (['--live', '70000'], 'argument --live: must be'),
        (['--live', '--live-rate', '-5'], 'full or 0 (every message)'),
        (['--live', '--live-rate', '6000'], 'full or 0 (every message)'),
    ],
)
def test_bad_live_input_is_one_line_exit_2_nothing_created(args, says, busy_port, procs, tmp_path):
    argv = [a.format(busy=busy_port) for a in args]
    p = procs.start([ROS2, 'run', 'im_tuner', 'tuner', '--budget', '1', *argv], cwd=tmp_path)
    _refused(p, says)
    assert not list(tmp_path.iterdir())  # no run directory, no bag


@pytest.mark.parametrize('exe', ['drive_host', 'recorder'])
def test_the_drive_host_and_recorder_refuse_a_busy_port(exe, busy_port, procs, tmp_path):
    p = procs.start(
        [ROS2, 'run', 'im_tuner', exe, '--out', str(tmp_path / 'bag'), '--live', str(busy_port)],
        cwd=tmp_path,
    )
    _refused(p, 'is in use on 127.0.0.1')
    assert not list(tmp_path.iterdir())


def test_a_slow_client_reads_to_the_last_loss_after_the_close(monkeypatch):
    """A client that reads slowly (8 ms a message: a loaded machine) with the sockets'
    buffers small (16 kB each way) is hundreds of states (seconds) behind when the run's
    last loss is offered and the server closed at once: the server goes on sending while
    the client takes, and closes the socket (not a reset) once everything is in the
    kernel's hands, so the client reads every state and then the loss; bounded."""
    from im_tuner.record import live_server
    from im_tuner.record.live import LiveSettings
    from im_tuner.record.live_server import CLOSE_GRACE_S, CLOSE_MAX_S, LiveServer

    monkeypatch.setattr(live_server, 'CLIENT_SNDBUF', 16 << 10)
    port = free_port()
    server = LiveServer(LiveSettings(port), lambda _text: None)
    try:
        server.add_channel(5, '/drive/state', 'std_msgs/msg/Float64MultiArray', 'float64[] data')
        server.add_channel(6, '/controller/loss', 'diagnostic_msgs/msg/DiagnosticArray', 'x')
        watcher = Watcher(port, timeout=60.0, pause=0.008, rcvbuf=16 << 10).start()
        deadline = time.monotonic() + 30.0
        while not (
            len(server._server._clients) == 1
            and all(len(c.subscriptions) == 2 for c in server._server._clients)
        ):
            assert time.monotonic() < deadline, 'no subscription within 30 s'
            time.sleep(0.01)
        payload = bytes(range(200))
        server.offer([(5, k, payload) for k in range(600)])
        deadline = time.monotonic() + 60.0
        while server.stats()['sent'] < 600:
            assert time.monotonic() < deadline, 'the states not handed over within 60 s'
            time.sleep(0.01)
        behind = 600 - len(watcher.messages.get('/drive/state', []))
        server.offer([(6, 600, b'the last loss')])
        t0 = time.monotonic()
        stats = server.close()
        stop_s = time.monotonic() - t0
        watcher.join(60.0)
    finally:
        server.close()
    assert behind > 250, behind  # (what the close found in flight)
    assert watcher.messages['/controller/loss'] == [(600, b'the last loss')]
    assert [t for t, _d in watcher.messages['/drive/state']] == list(range(600))
    assert stats['sent'] == 601 and stats['dropped'] == 0
    assert stop_s < CLOSE_MAX_S + 2 * CLOSE_GRACE_S + 1.0


def test_an_interrupted_live_run_says_its_rate_and_resumes_with_the_live_view(
    procs, tmp_path, wait_until
):
    """The start-up line names N and the rate it gives (300 Hz: every 17th, 294.1 Hz); the
    resume command an interrupted run prints gives its live options again."""
    port = free_port()
    run = tmp_path / 'int'
    args = ('--bench', 'inproc', '--budget', '40', '--live', str(port), '--live-rate', '300')
    child = tuner(procs, run, *args)
    res = run / 'results.jsonl'
    wait_until(lambda: res.exists() and res.read_text().count('\n') >= 2, 300, message='2 records')
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=RUN_TIMEOUT)
    assert child.returncode == 130, err[-2000:]
    assert f'live: ws://127.0.0.1:{port} (Foxglove' in out + err
    assert 'the 5 kHz topics every 17th: 294.1 Hz' in out + err
    assert f'--resume {run} --live {port} --live-rate 300`' in out
