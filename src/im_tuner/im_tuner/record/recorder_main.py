"""``ros2 run im_tuner recorder``: checks its command line before the node is imported."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from im_drive_sim.cli import Parser, UsageError, check_then_run, executable, finite_float, int_in

from .live import add_live_options
from .mcap_format import COMPRESSIONS

CHUNK_SIZE_RANGE = (4096, 1 << 28)
#: a ROS 2 topic name (design.ros2.org, "Topic and Service name mapping"): tokens of
#: letters, digits and underscores, not starting with a digit, joined by '/'
_TOPIC = re.compile(r'/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*')


def topic_name(text: str) -> str:
    """An ``--exclude-topics`` entry: a topic name, taken exactly (as ``ros2 bag record
    --exclude-topics`` takes it); a pattern or a malformed name is refused, since it
    would exclude nothing."""
    if not _TOPIC.fullmatch(text) or '__' in text:
        raise argparse.ArgumentTypeError(
            f'{text!r} is not a ROS topic name (letters, digits, _ and /, e.g. /drive/state); '
            'topics are named exactly, not by pattern'
        )
    return text if text.startswith('/') else '/' + text


class _RecorderParser(Parser):
    """``--repair DIR`` repairs in place and exits: a recording option beside it would be
    ignored, so it is refused (as the tuner refuses ``--compression`` with
    ``--no-record``)."""

    def parse_known_args(self, args=None, namespace=None):
        ns, rest = super().parse_known_args(args, namespace)
        if getattr(ns, 'repair', None) is not None:
            given = [
                a.option_strings[0]
                for a in self._actions
                if a.dest not in ('repair', 'help') and getattr(ns, a.dest) != a.default
            ]
            if given:
                raise UsageError(
                    f'--repair {ns.repair} repairs that bag in place and exits: '
                    f'{", ".join(given)} would be ignored'
                )
        return ns, rest


def parser() -> argparse.ArgumentParser:
    ap = _RecorderParser(
        prog='ros2 run im_tuner recorder',
        description='Record every topic on the ROS graph to a rosbag2 MCAP bag, losslessly '
        '(reliable KEEP_ALL, per-topic published/recorded/lost counts).',
    )
    ap.add_argument(
        '--out',
        metavar='DIR',
        type=Path,
        help='bag directory to create (default: bags/recording_<UTC time>)',
    )
    ap.add_argument(
        '--compression',
        choices=COMPRESSIONS,
        default='lz4',
        help='MCAP chunk compression (default: lz4, the cheapest; zstd: smaller files)',
    )
    ap.add_argument(
        '--chunk-size',
        type=int_in(*CHUNK_SIZE_RANGE),
        default=1 << 20,
        metavar='BYTES',
        help='close chunks at this size (default 1 MiB; '
        f'{CHUNK_SIZE_RANGE[0]} to {CHUNK_SIZE_RANGE[1]})',
    )
    ap.add_argument(
        '--max-chunk-age',
        type=finite_float(0.0, 3600.0, lo_open=True, unit='s'),
        default=0.5,
        metavar='S',
        help='most log time one chunk spans, and the age of its first message at which '
        'it is closed and written: bounds what a SIGKILL loses (default 0.5)',
    )
    ap.add_argument(
        '--exclude-topics',
        nargs='+',
        type=topic_name,
        default=[],
        metavar='TOPIC',
        help='topics (fully qualified, /drive/state) not to record, as ros2 bag record '
        "--exclude-topics: a tuner on another computer leaves a drive host's 5 kHz "
        "topics to the host's own bag",
    )
    ap.add_argument(
        '--repair',
        metavar='DIR',
        type=Path,
        help='repair a bag left by a crash (rewrite summary, index and metadata.yaml), then exit',
    )
    add_live_options(ap)
    return ap


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('recorder', parser, 'im_tuner.record.child:main')


if __name__ == '__main__':
    executable('recorder', main)
