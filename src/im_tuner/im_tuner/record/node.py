"""The recorder: every topic on the graph into a rosbag2 MCAP bag, with nothing lost.

``ros2 run im_tuner recorder`` records like ``ros2 bag record -a`` (docs/recorder.md): a
subscription per topic as it appears, messages taken in the recorder's own loop
(:mod:`im_tuner.record.take`), per-publisher sequence-number gaps counted as lost, the
counts in the log, ``metadata.yaml`` and an MCAP metadata record at close. The simulated
bench and the tuner run a :class:`Recorder` in their own process and call
:meth:`Recorder.poll` between steps."""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from im_drive_sim.outbox import R_HEAD, R_LOST, R_TAIL

from . import take as rcl_take
from .counts import closing_custom_data, counts_report
from .live import LIVE_METADATA, LiveError, LiveFeed, LiveSettings, live_line
from .live_server import LiveServer
from .metadata import (
    TopicRecord,
    bag_metadata,
    prepare_bag_dir,
    qos_yaml,
    rosbag2_record,
    storage_file_name,
    write_metadata_yaml,
)
from .run_info import run_metadata, version
from .schemas import MsgDefError, schema_for
from .status import TopicStatus
from .topic_info import endpoint_qos, endpoint_type_hash, message_class
from .writer import MESSAGE_HEADER_BYTES, McapWriteError, McapWriter

#: Lock-step steps between two polls of a recorder sharing the bench's process (far below
#: Fast DDS's 5000 samples per reader).
RECORD_POLL_STEPS = 64
#: Longest a closing recorder keeps taking messages that are still arriving [s].
CLOSE_MAX_WAIT = 1.0


class RecorderError(Exception):
    """The recorder cannot start or continue (bad output, rcl error)."""


class ChunkTimer:
    """Calls ``tick()`` every ``period`` [s] on a daemon thread until :meth:`stop`: the
    recorder's open chunk closed by wall time when nobody polls it, so that nothing taken
    waits in memory where a SIGKILL loses it (docs/recorder.md, "Crash safety"). An
    exception from ``tick()`` ends the thread and is kept in :attr:`error` for the owner
    to raise (the thread has no one to report to)."""

    def __init__(self, tick: Callable[[], None], period: float, name: str) -> None:
        self.period = float(period)
        self.error: BaseException | None = None
        self._tick = tick
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            try:
                self._tick()
            except BaseException as exc:  # kept for the owner: a thread cannot raise
                self.error = exc
                return

    def stop(self, timeout: float = 5.0) -> None:
        """End the thread (after a tick under way, if any); idempotent."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)


@dataclass
class _Topic:
    name: str
    type: str
    channel: int
    sub: object  # rclpy Subscription (None: a tapped topic, Recorder.add_tap)
    reliable: bool
    qos_profiles: list[dict]
    type_hash: str


class Recorder:
    """Records every topic of the graph seen by ``node``'s context into a bag.

    Call :meth:`poll` often: it discovers new topics (at most every ``discovery_period``
    s), takes every waiting message and closes chunks that are full or ``max_chunk_age``
    old; with ``flush_timer`` a :class:`ChunkTimer` does it when the owner
    has not polled (docs/recorder.md, "Crash safety"). :meth:`close` finishes the bag and
    returns the counts."""

    def __init__(
        self,
        node: Node,
        out: Path | str,
        *,
        compression: str = 'lz4',
        chunk_size: int = 1 << 20,
        max_chunk_age: float = 0.5,
        discovery_period: float = 0.2,
        extra_metadata: dict[str, dict] | None = None,
        command: list[str] | None = None,
        background_writes: bool = True,
        taps: dict[str, Any] | None = None,
        exclude: tuple[str, ...] | list[str] = (),
        flush_timer: bool = True,
        live: LiveSettings | None = None,
    ) -> None:
        """``taps``: topics to take from a real-time loop's outbox instead of DDS
        (:meth:`add_tap`); ``exclude``: topics never recorded (named in the metadata);
        ``live``: a Foxglove WebSocket server carrying what the bag gets (``.live``)."""
        self.node = node
        self.log = node.get_logger()
        #: the live view (started first: a port it cannot have leaves no bag)
        self.live: LiveServer | None = None
        self.live_stats: dict[str, Any] | None = None
        if live is not None:
            try:
                self.live = LiveServer(live, self.log.info)
            except LiveError as exc:
                raise RecorderError(str(exc)) from None
        self._feed = LiveFeed(live.rate_hz if live is not None else 0.0)
        try:
            self.out = prepare_bag_dir(Path(out))
            self.file_name = storage_file_name(self.out)
            self.writer = McapWriter(
                self.out / self.file_name,
                compression=compression,
                chunk_size=chunk_size,
                library=f'im_tuner recorder {version("im_tuner", "dev")}',
                background=background_writes,
                max_span=max_chunk_age,
            )
        except McapWriteError as exc:
            self._close_live()
            raise RecorderError(str(exc)) from None
        except BaseException:
            self._close_live()
            raise
        if self.live is not None:
            live_server = self.live
            self.writer.observer = lambda buf, idx: live_server.offer(self._feed.select(buf, idx))
        self.max_chunk_age = max_chunk_age
        self._max_span_ns = round(max_chunk_age * 1e9)
        #: poll, drain, discover, add_metadata and close take turns with the chunk timer
        self._lock = threading.RLock()
        self._last_poll = time.monotonic()
        self._timer: ChunkTimer | None = None
        self.discovery_period = discovery_period
        self.topics: dict[str, _Topic] = {}
        #: topics taken from a real-time loop's outbox instead of DDS (add_tap): the
        #: topic and its ring (im_drive_sim.outbox.Channel)
        self._taps: list[tuple[_Topic, Any]] = []
        self.unrecordable: dict[str, str] = {}
        self.excluded = frozenset(exclude)
        #: topics this process publishes about itself (the child's status): never recorded
        self.own_topics: set[str] = set()
        self.unmatched: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._take = rcl_take.TakeBuffers()
        self._pubs = rcl_take.new_publisher_table()
        self._ctrl = rcl_take.new_ctrl()
        self._ctrl[rcl_take.C_MAX_SPAN_NS] = self._max_span_ns
        self._subs = np.zeros(0, np.uint64)
        self._chans = np.zeros(0, np.int64)
        self._next_discovery = 0.0
        self._chunk_opened: float | None = None
        self.messages = 0
        self.writer.add_metadata('im_tuner.run', run_metadata(command))
        if self.excluded:
            self.add_metadata('im_tuner.excluded_topics', {'topics': sorted(self.excluded)})
        for name, data in (extra_metadata or {}).items():
            self.add_metadata(name, data)
        # A provisional metadata.yaml marks the directory as a bag being recorded.
        write_metadata_yaml(
            self.out, bag_metadata([(self.file_name, 0, 0, 0)], [], {'im_tuner.state': 'recording'})
        )
        # Load the take kernel (numba: seconds to compile) before any reader matches: a
        # reliable KEEP_ALL reader that is not taken fills up, and then back-pressures the
        # 5 kHz publishers -- a stalled drive, aborted experiments.
        if taps:
            self.add_tap(taps)
        self.drain()
        self.discover()
        if flush_timer:
            self._timer = ChunkTimer(self._tick, max_chunk_age / 4, 'recorder chunk timer')

    # -- topics ------------------------------------------------------------------------
    def add_metadata(self, name: str, data: dict) -> None:
        """An MCAP metadata record (values turned into strings)."""
        with self._lock:
            self.writer.add_metadata(
                name, {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
            )

    def discover(self) -> int:
        """Subscribe to topics that appeared; returns how many were added."""
        added = 0
        with self._lock:
            for name, types in self.node.get_topic_names_and_types():
                if (
                    name in self.topics
                    or name in self.unrecordable
                    or name in self.excluded
                    or name in self.own_topics
                ):
                    continue
                infos = self.node.get_publishers_info_by_topic(name)
                if not infos:
                    continue  # nothing to record until something publishes
                if len(types) > 1:
                    self.log.warning(f'{name} has several types {types}; recording {types[0]}')
                if self._subscribe(name, types[0], infos):
                    added += 1
                    self.drain()  # the new reader is taken at once, not after every one
            self._check_matches()
        return added

    def _schema(self, type_name: str) -> int:
        if type_name not in self._schemas:
            try:
                encoding, text = schema_for(type_name)
            except MsgDefError as exc:
                self.log.warning(
                    f'{type_name}: no message definition ({exc}); recorded without schema text'
                )
                encoding, text = 'ros2msg', ''
            self._schemas[type_name] = self.writer.add_schema(
                type_name, encoding, text.encode('utf-8')
            )
        return self._schemas[type_name]

    def _add_channel(self, name: str, type_name: str, infos: list) -> tuple[int, list[dict], str]:
        """A bag channel for topic ``name`` (its schema first), with its publishers' QoS
        profiles and type hash, as rosbag2 writes them; returns (channel, profiles, hash)."""
        profiles = [endpoint_qos(i) for i in infos]
        type_hash = endpoint_type_hash(infos[0]) if infos else ''
        schema = self._schema(type_name)
        channel = self.writer.add_channel(
            name,
            schema,
            'cdr',
            {'offered_qos_profiles': qos_yaml(profiles), 'topic_type_hash': type_hash},
        )
        if self.live is not None:  # the same channel live: topic, type, schema text
            self._feed.add_channel(channel, name)
            _name, encoding, text = self.writer.schemas[schema]
            # (a transient-local topic's late subscriber gets what was published, as in ROS)
            latched = any(p.get('durability') == 'transient_local' for p in profiles)
            self.live.add_channel(channel, name, type_name, text.decode(), encoding, latched)
        return channel, profiles, type_hash

    def add_tap(self, channels: dict[str, Any]) -> None:
        """Record these topics from a real-time loop's outbox (``im_drive_sim.outbox``:
        topic -> Channel with a ``tap`` ring) instead of subscribing: every message the
        loop handed over, whatever DDS readers do (a frozen one cannot cost the bag a
        message). Call before the loop starts; each :meth:`poll` drains the rings."""
        for name, ch in channels.items():
            if name in self.topics:
                raise RecorderError(f'{name} is already recorded from DDS')
            infos = self.node.get_publishers_info_by_topic(name)
            channel, profiles, type_hash = self._add_channel(name, ch.type_name, infos)
            t = _Topic(name, ch.type_name, channel, None, True, profiles, type_hash)
            self.topics[name] = t
            self._taps.append((t, ch))
            # compile (or load) the kernel now: never in the first poll beside a live loop
            r, ck = ch.tap, self.writer.chunk
            rcl_take.drain_ring(
                r.buf, r.lens, r.stamps, r.ctrl, 0, t.channel, ck.buf, ck.idx, ck.st, 0
            )

    def drain_taps(self) -> int:
        """Copy what the loop handed over since the last call into the chunk."""
        total = 0
        for t, ch in self._taps:
            r = ch.tap
            head = int(r.ctrl[R_HEAD])  # read under the GIL: its bytes are there
            while int(r.ctrl[R_TAIL]) < head:
                ck = self.writer.chunk
                n = rcl_take.drain_ring(
                    r.buf, r.lens, r.stamps, r.ctrl, head, t.channel,
                    ck.buf, ck.idx, ck.st, self._max_span_ns,
                )  # fmt: skip
                total += n
                if int(r.ctrl[R_TAIL]) < head:  # the chunk is full, or spans max_chunk_age
                    self._flush()
                    self.writer.chunk.grow(MESSAGE_HEADER_BYTES + int(ch.slot))
        return total

    def _subscribe(self, name: str, type_name: str, infos) -> bool:
        try:
            cls = message_class(type_name)
        except (ImportError, AttributeError) as exc:
            self.unrecordable[name] = f'{type_name}: type support not installed ({exc})'
            self.log.error(f'cannot record {name}: {self.unrecordable[name]}')
            return False
        reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
        transient = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_ALL,
            depth=0,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
        )
        channel, profiles, type_hash = self._add_channel(name, type_name, infos)
        sub = self.node.create_subscription(cls, name, lambda _m: None, qos, raw=True)
        self.topics[name] = _Topic(name, type_name, channel, sub, reliable, profiles, type_hash)
        self._subs = np.append(self._subs, np.uint64(sub.handle.pointer))
        self._chans = np.append(self._chans, np.int64(channel))
        if not reliable:
            self.log.warning(
                f'{name}: a publisher is best-effort; recording best-effort '
                '(losses there are counted, not prevented)'
            )
        return True

    def wait_matched(self, timeout: float) -> bool:
        """Wait until every publisher on the recorded topics is matched (bounded).

        Call before the publishers start when the first message matters. Returns whether
        all matched; the ones that did not are reported at close."""
        deadline = time.monotonic() + timeout
        while True:
            self.discover()
            if all(s.matched_publishers >= s.publishers for s in self.topic_status().values()):
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)

    def topic_status(self) -> dict[str, TopicStatus]:
        """Per topic taken from DDS: messages recorded, publishers matched / on the graph
        (the child's status topic, :mod:`.status`)."""
        with self._lock:
            counts = self.counts()
            return {
                t.name: TopicStatus(
                    counts.get(t.name, {}).get('recorded', 0),
                    t.sub.get_publisher_count(),  # type: ignore[attr-defined]
                    self.node.count_publishers(t.name),
                )
                for t in self.topics.values()
                if t.sub is not None
            }

    def _check_matches(self) -> None:
        for name, s in self.topic_status().items():
            missing = s.publishers - s.matched_publishers
            if missing > 0 and self.unmatched.get(name, 0) < missing:
                self.log.warning(
                    f'{name}: {missing} publisher(s) not matched by the '
                    'recorder (incompatible QoS?); their messages are not '
                    'recorded'
                )
            if missing > 0:
                self.unmatched[name] = max(self.unmatched.get(name, 0), missing)

    # -- the loop ----------------------------------------------------------------------
    def _age_check(self, now: float) -> None:
        """Close the open chunk when it is full or its first message is ``max_chunk_age``
        old: by its log time (the wall clock it was received at), or -- should the wall
        clock step back -- by ``now`` (monotonic [s]) since a poll first saw it."""
        ck = self.writer.chunk
        if not ck.count:
            self._chunk_opened = None
            return
        if self._chunk_opened is None:
            self._chunk_opened = now
        if (
            ck.used >= self.writer.chunk_size
            or time.time_ns() - ck.first_log_time >= self._max_span_ns
            or now - self._chunk_opened >= self.max_chunk_age
        ):
            self._flush()

    def _flush(self) -> None:
        """Close the open chunk (the next one's age is counted from its first poll)."""
        self.writer.flush_chunk()
        self._chunk_opened = None

    def poll(self, now: float | None = None) -> int:
        """Discover (when due), take everything waiting, close old chunks. Messages taken."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if self._timer is not None and self._timer.error is not None:
                raise RecorderError(f'the chunk timer failed: {self._timer.error!r}')
            self._last_poll = time.monotonic()
            if now >= self._next_discovery:
                self._next_discovery = now + self.discovery_period
                self.discover()
            n = self.drain()
            self._age_check(now)
            return n

    def _tick(self) -> None:
        """The chunk timer's round: when the owner has not polled for a timer period,
        take what is waiting (the graph is not looked at) and close an old chunk."""
        with self._lock:
            now = time.monotonic()
            if self.writer.closed or self._timer is None:
                return
            if now - self._last_poll < self._timer.period:
                return
            self.drain()
            self._age_check(now)

    def drain(self) -> int:
        """Take every waiting message into the open chunk (closing full chunks)."""
        with self._lock:
            total = self.drain_taps()
            tb = self._take
            while True:
                ch = self.writer.chunk
                code, n = rcl_take.drain(
                    self._subs,
                    self._chans,
                    tb.ser,
                    tb.info,
                    ch.buf,
                    ch.idx,
                    ch.st,
                    self._pubs,
                    self._ctrl,
                )
                total += n
                if code == rcl_take.DONE:
                    break
                if code == rcl_take.FULL:
                    self._flush()
                    self.writer.chunk.grow(MESSAGE_HEADER_BYTES + tb.pending_size)
                elif code == rcl_take.PUBS_FULL:
                    grown = rcl_take.new_publisher_table(2 * self._pubs.shape[0])
                    grown[: self._pubs.shape[0]] = self._pubs
                    self._pubs = grown
                elif code == rcl_take.ERROR:
                    raise RecorderError(
                        f'rcl_take_serialized_message failed with code '
                        f'{int(self._ctrl[rcl_take.C_ERROR])}'
                    )
            if self.writer.chunk.used >= self.writer.chunk_size:
                self._flush()
            self.writer.observe()  # (the live view: what was taken, at once)
            self.messages += total
            return total

    # -- counts and closing --------------------------------------------------------------
    def counts(self) -> dict[str, dict[str, int]]:
        """Per topic: recorded, published (seen by sequence numbers), lost, publishers."""
        rows = self._pubs[: int(self._ctrl[rcl_take.C_NPUBS])]
        out = {}
        for t, ch in self._taps:
            out[t.name] = {
                'recorded': int(ch.tap.ctrl[R_TAIL]),
                'published': int(ch.put_count),
                'lost': int(ch.tap.ctrl[R_LOST]),  # the ring was full
                'publishers': 1,
                'published_before_recording': 0,
                'unmatched_publishers': 0,
            }
        for t in self.topics.values():
            if t.sub is None:
                continue
            r = rows[rows[:, rcl_take.P_CHANNEL] == t.channel]
            out[t.name] = {
                'recorded': int(np.sum(r[:, rcl_take.P_COUNT])),
                'published': int(np.sum(r[:, rcl_take.P_LAST] - r[:, rcl_take.P_FIRST] + 1)),
                'lost': int(np.sum(r[:, rcl_take.P_GAPS])),
                'publishers': len(r),
                'published_before_recording': int(np.sum(r[:, rcl_take.P_FIRST] - 1)),
                'unmatched_publishers': int(self.unmatched.get(t.name, 0)),
            }
        return out

    def close(
        self, settle: float = 0.0, max_wait: float = CLOSE_MAX_WAIT
    ) -> dict[str, dict[str, int]]:
        """Take what is left, finish the bag (summary, metadata.yaml); returns the counts.

        ``settle`` [s]: keep taking until nothing arrived for this long, but for
        ``max_wait`` s at most; a bag cut that way says so (docs/recorder.md, "Crash
        safety")."""
        if self.writer.closed:
            return self.counts()
        if self._timer is not None:  # from here on only this thread touches the chunk
            self._timer.stop()
            self._timer = None
        self.discover()
        self.drain()
        cut = ''
        if settle > 0:
            t0 = quiet_since = time.monotonic()
            while time.monotonic() - quiet_since < settle:
                if time.monotonic() - t0 >= max_wait:
                    cut = (
                        f'cut after {max_wait:g} s of taking: messages were still '
                        'arriving (a live publisher); what they published after the cut '
                        'is not in the bag'
                    )
                    break
                if self.drain():
                    quiet_since = time.monotonic()
                else:
                    time.sleep(min(0.005, settle / 4))
        self._check_matches()
        self.writer.flush_chunk()
        self._close_live()
        if self.live_stats is not None:
            self.add_metadata(LIVE_METADATA, self.live_stats)
        counts = self.counts()
        custom = closing_custom_data(counts, self.unrecordable, cut)
        if self.live_stats is not None:  # (the tuner reads it there: live.read_live_stats)
            custom[LIVE_METADATA] = json.dumps(self.live_stats, sort_keys=True)
        if cut:
            self.node.get_logger().warn(f'bag {self.out.name}: {cut}')
        w = self.writer
        topics = [
            TopicRecord(
                t.name, t.type, w.channel_counts.get(t.channel, 0), t.qos_profiles, t.type_hash
            )
            for t in self.topics.values()
        ]
        meta = bag_metadata(
            [(self.file_name, w.t_start or 0, w.t_end or 0, w.message_count)], topics, custom
        )
        self.writer.add_metadata('rosbag2', rosbag2_record(meta))
        self.writer.add_metadata(
            'im_tuner.counts', {k: json.dumps(v, sort_keys=True) for k, v in counts.items()}
        )
        self.writer.close()
        write_metadata_yaml(self.out, meta)
        self._subs = np.zeros(0, np.uint64)
        self._chans = np.zeros(0, np.int64)
        for t in self.topics.values():
            if t.sub is not None:
                with contextlib.suppress(Exception):
                    self.node.destroy_subscription(t.sub)
        self._take.close()
        self.log.info(counts_report(self.out, self.writer.message_count, counts, self.unrecordable))
        return counts

    def _close_live(self) -> None:
        """Stop the live server (once); its figures in ``live_stats`` and the log."""
        if self.live is None:
            return
        live, self.live = self.live, None
        self.live_stats = live.close()
        self.log.info(live_line(self.live_stats))
