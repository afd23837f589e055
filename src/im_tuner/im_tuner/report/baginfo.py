"""``ros2 run im_tuner report --bag-info BAG_DIR [--json]``: a bag's statistics, as ``ros2 bag
info`` gives them, plus the recorder's own counts no ROS tool shows; what each figure is:
docs/report.md, "Bag statistics". Any bag the project writes, through
:func:`im_tuner.record.reader.read_bag`: no rclpy."""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

from .errors import ReportError

#: the recorder's per-topic counts shown, in the order shown
COUNT_KEYS = ('recorded', 'published', 'lost')


def bag_info(bag_dir: Path) -> dict[str, Any]:
    """The statistics of the bag in ``bag_dir`` (a dict, as ``--json`` prints it).

    Raises :class:`ReportError` (one line) for a path that is not a bag."""
    from ..record.reader import BagReadError, read_bag
    from ..rundir import writer_of

    bag_dir = Path(bag_dir)
    try:
        bag = read_bag(bag_dir)
    except BagReadError as exc:
        raise ReportError(f'--bag-info {exc}') from None
    except (OSError, ValueError) as exc:
        raise ReportError(f'--bag-info {bag_dir}: cannot read the bag ({exc})') from None
    t0, t1 = bag.t_range_ns
    rc = bag.recorder_counts or {}
    topics = []
    for name in sorted(bag.topics):
        t = bag.topics[name]
        c = rc.get(name)
        topics.append(
            {
                'topic': name,
                'type': t.type,
                'count': t.count,
                'rate_hz': t.rate_hz,
                'bytes': t.bytes,
                'first_ns': t.first_ns if t.count else None,
                'last_ns': t.last_ns if t.count else None,
                # the recorder's counts (None: the bag was not closed by the recorder)
                **{
                    k: (None if c is None else int(c.get(k, 0)))
                    for k in (*COUNT_KEYS, 'published_before_recording')
                },
            }
        )
    spans = [c.span_s for c in bag.chunk_stats]
    outbox = bag.metadata.get('im_tuner.outbox')
    return {
        'bag': str(bag_dir),
        'files': [{'name': bag.file.name, 'bytes': bag.file.stat().st_size}],
        'storage': 'mcap',
        'state': bag.state,
        'complete': bag.complete,
        # the process recording it now ('pid N (command)'; None: no one, e.g. killed)
        'recording_by': None if bag.complete else writer_of(bag.file),
        'unread_bytes': bag.unread_bytes,
        'messages': bag.messages,
        'bytes': sum(t.bytes for t in bag.topics.values()),
        'start_ns': t0 if bag.messages else None,
        'end_ns': t1 if bag.messages else None,
        'duration_s': (t1 - t0) * 1e-9 if bag.messages else 0.0,
        'compression': sorted({c.compression or 'none' for c in bag.chunk_stats}),
        'chunks': bag.chunks,
        # complete chunks whose CRC fails or that do not decompress: left out of the counts
        'damaged_chunks': [asdict(d) | {'text': d.describe()} for d in bag.damaged],
        'max_chunk_span_s': max(spans) if spans else None,
        'first_chunk_span_s': spans[0] if spans else None,
        'recorder_counts': bag.recorder_counts is not None,
        'lost_total': (sum(int(c.get('lost', 0)) for c in rc.values()) if rc else None),
        # recorded by the recorder's counts but not in the file (a file cut short after
        # the recorder closed it): the sum over topics of recorded - count
        'not_in_file': sum(
            max(0, int(c.get('recorded', 0)) - (bag.topics[n].count if n in bag.topics else 0))
            for n, c in rc.items()
        ),
        # the composed real-time loop's hand-over counts (put, published, lost_...)
        'outbox': {k: json.loads(v) for k, v in outbox.items()} if outbox else None,
        'topics': topics,
    }


def _when(ns: int | None) -> str:
    if ns is None:
        return '-'
    t = _dt.datetime.fromtimestamp(ns // 1_000_000_000, _dt.UTC)
    sec, frac = divmod(ns, 1_000_000_000)
    return f'{t:%Y-%m-%d %H:%M:%S}.{frac:09d} UTC ({sec}.{frac:09d})'


def _size(n: int) -> str:
    for unit, k in (('GiB', 1 << 30), ('MiB', 1 << 20), ('KiB', 1 << 10)):
        if n >= k:
            return f'{n / k:.1f} {unit}'
    return f'{n} B'


def _state(info: dict[str, Any]) -> str:
    if info['complete']:
        return info['state']
    if info['recording_by']:
        return (
            f'being recorded now by {info["recording_by"]}: read up to its last complete '
            f'chunk ({info["unread_bytes"]} bytes after it not read yet)'
        )
    said = f'metadata.yaml says {info["state"]}, but ' if info['state'] == 'closed' else ''
    return (
        f'{said}the MCAP file is NOT CLOSED: read up to its last complete chunk '
        f'({info["unread_bytes"]} bytes after it not read)'
    )


def format_info(info: dict[str, Any]) -> str:
    """The statistics as aligned text: the totals, then one row per topic."""
    files = ', '.join(f'{f["name"]} ({_size(f["bytes"])})' for f in info['files'])
    span = info['max_chunk_span_s']
    chunks = f'{info["chunks"]} chunks, {", ".join(info["compression"]) or "-"}' + (
        f'; longest {span:.3f} s of log time (first {info["first_chunk_span_s"]:.3f} s)'
        if span is not None
        else ''
    )
    lost = info['lost_total']
    L = [
        f'Bag:        {info["bag"]}',
        f'Files:      {files}',
        f'State:      {_state(info)}',
        f'Storage:    {info["storage"]}; {chunks}',
        *(
            f'DAMAGED:    {d["text"]}; its messages are left out of every count'
            for d in info['damaged_chunks']
        ),
        f'Duration:   {info["duration_s"]:.3f} s',
        f'Start:      {_when(info["start_ns"])}',
        f'End:        {_when(info["end_ns"])}',
        f'Messages:   {info["messages"]} ({_size(info["bytes"])} of message data); '
        + (
            f"lost {lost} (the recorder's count)"
            if lost is not None
            else "recorder's counts not in the bag (not closed by the recorder)"
        )
        + (
            f'; {info["not_in_file"]} the recorder counted are NOT in the file'
            if info['not_in_file']
            else ''
        ),
        '',
    ]
    head = ('topic', 'type', 'count', 'rate [Hz]', 'size [B]', *COUNT_KEYS)
    rows = [
        (
            t['topic'],
            t['type'],
            str(t['count']),
            '-' if t['rate_hz'] is None else f'{t["rate_hz"]:.1f}',
            str(t['bytes']),
            *('-' if t[k] is None else str(t[k]) for k in COUNT_KEYS),
        )
        for t in info['topics']
    ]
    widths = [max(len(r[i]) for r in (head, *rows)) for i in range(len(head))]

    def line(r: tuple[str, ...]) -> str:
        cells = [r[i].ljust(widths[i]) if i < 2 else r[i].rjust(widths[i]) for i in range(len(r))]
        return '  '.join(cells).rstrip()

    L.append(line(head))
    L.extend(line(r) for r in rows)
    before = [t for t in info['topics'] if t['published_before_recording']]
    if before:
        L.append('')
        L.append(
            'published before recording began (not lost): '
            + ', '.join(f'{t["topic"]} {t["published_before_recording"]}' for t in before)
        )
    return '\n'.join(L)
