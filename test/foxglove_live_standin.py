"""A stand-in for the tuner's live Foxglove server: a recorded run's bag, replayed live.

Until the tuner's own ``--live PORT`` server exists, test/test_foxglove_viewer.py starts this
in its place. It is the older Python server, ``foxglove-websocket`` (subprotocol
``foxglove.websocket.v1``, the one Foxglove Studio 1.48 speaks; foxglove-sdk's server accepts
only ``foxglove.sdk.v1``). It advertises what the live server will: one channel per topic of
the bag, message encoding ``cdr``, schema name the ROS type, schema encoding and text as the
bag holds them (``ros2msg``; ``ros2idl`` for the service events), and sends each message's
CDR bytes paced by its log time. Topics above 1 kHz (the 5 kHz drive and controller topics)
are decimated to 250 Hz (every k-th message), the rate the live server sends them at by
default.

    python test/foxglove_live_standin.py --port PORT [--clients N] -- TUNER_COMMAND... --out RUN

runs the tuner command (which records to RUN), then serves RUN's bag. The replay starts once
N clients are connected and one subscribed to the loss topic (the viewer's pages; at most
60 s wait), so that a short run is seen whole. Prints ``serving PORT`` when listening and
``replayed N messages`` at the end; exits with the tuner's code if it failed, else 0.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import subprocess
import sys
import time
from pathlib import Path

from foxglove_websocket.server import FoxgloveServer, FoxgloveServerListener
from mcap.reader import make_reader

#: the rate the 5 kHz topics are sent at, and the rate above which a topic is decimated (Hz)
LIVE_RATE_HZ = 250.0
FAST_HZ = 1000.0
#: the longest wait for the viewer's clients before the replay starts anyway (s)
CLIENT_WAIT_S = 60.0
LOSS_TOPIC = '/controller/loss'


class _Subscribed(FoxgloveServerListener):
    """The channels a client subscribed to."""

    def __init__(self) -> None:
        self.channels: set[int] = set()

    def on_subscribe(self, server: FoxgloveServer, channel_id: int) -> None:
        self.channels.add(channel_id)

    def on_unsubscribe(self, server: FoxgloveServer, channel_id: int) -> None:
        pass


async def replay(port: int, run: Path, clients: int) -> int:
    """Serve ``run``'s bag on 127.0.0.1:``port``; return the number of messages sent."""
    bag = sorted((run / 'bag_0').glob('*.mcap'))[0]
    with bag.open('rb') as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    stats = summary.statistics
    span_s = max(1e-9, (stats.message_end_time - stats.message_start_time) / 1e9)
    logger = logging.getLogger('standin')
    logger.setLevel(logging.WARNING)
    async with FoxgloveServer('127.0.0.1', port, 'im_tuner', logger=logger) as server:
        await server.wait_opened()
        ids: dict[int, int] = {}
        every: dict[int, int] = {}
        for cid, c in summary.channels.items():
            s = summary.schemas[c.schema_id]
            ids[cid] = await server.add_channel(
                {
                    'topic': c.topic,
                    'encoding': c.message_encoding,
                    'schemaName': s.name,
                    'schema': s.data.decode(),
                    'schemaEncoding': s.encoding,
                }
            )
            rate = stats.channel_message_counts.get(cid, 0) / span_s
            every[cid] = max(1, round(rate / LIVE_RATE_HZ)) if rate > FAST_HZ else 1
        subscribed = _Subscribed()
        server.set_listener(subscribed)
        loss = next(ids[cid] for cid, c in summary.channels.items() if c.topic == LOSS_TOPIC)
        print(f'serving {port}', flush=True)
        deadline = time.monotonic() + CLIENT_WAIT_S
        # (the server keeps its connections in a private tuple: a stand-in may look)
        while time.monotonic() < deadline and (
            len(server._clients) < clients or loss not in subscribed.channels
        ):
            await asyncio.sleep(0.05)
        sent, seen = 0, dict.fromkeys(ids, 0)
        t0_wall, t0_log = time.monotonic(), None
        with bag.open('rb') as f:
            for _schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
                t0_log = message.log_time if t0_log is None else t0_log
                seen[channel.id] += 1
                if (seen[channel.id] - 1) % every[channel.id]:
                    continue
                wait = (message.log_time - t0_log) / 1e9 - (time.monotonic() - t0_wall)
                if wait > 0:
                    await asyncio.sleep(wait)
                await server.send_message(ids[channel.id], time.time_ns(), message.data)
                sent += 1
        await asyncio.sleep(1.0)  # the last messages reach the clients before the server closes
    return sent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--port', type=int, required=True)
    ap.add_argument('--clients', type=int, default=1, help='clients to wait for')
    ap.add_argument('command', nargs='+', help='the tuner command, with --out RUN')
    a = ap.parse_args()
    run = Path(a.command[a.command.index('--out') + 1])
    code = subprocess.run(a.command, check=False).returncode
    if code != 0:
        sys.exit(code)
    print(f'replayed {asyncio.run(replay(a.port, run, a.clients))} messages', flush=True)


if __name__ == '__main__':
    main()
