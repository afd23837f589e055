"""rosbag2 bag directories: creating one, its ``metadata.yaml`` (rosbag2's version 9 layout,
ROS 2 Jazzy), QoS and count summaries. No rclpy here."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ..rundir import claim_out_dir, is_bag_dir

ROSBAG2_VERSION = 9
ROS_DISTRO = 'jazzy'
#: metadata.yaml read through libyaml when PyYAML has it (the same SafeLoader constructors)
_YAML_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
#: rosbag2's spelling of an infinite QoS duration.
_INFINITE = {'sec': 9223372036, 'nsec': 854775807}


class BagError(Exception):
    """The bag directory cannot be used (exists, not writable, not a bag)."""


def prepare_bag_dir(out: Path) -> Path:
    """Create the bag directory ``out``; refuse an existing bag or an unwritable place.

    An existing *empty* directory is accepted. Nothing is created when this raises.
    """
    return claim_out_dir(
        Path(out),
        BagError,
        lambda d: 'a bag' if is_bag_dir(d) else 'not empty',
    )


def storage_file_name(out: Path) -> str:
    return f'{Path(out).name}_0.mcap'


def qos_to_dict(
    history: str,
    depth: int,
    reliability: str,
    durability: str,
    deadline_ns: int = 0,
    lifespan_ns: int = 0,
    liveliness: str = 'automatic',
    lease_ns: int = 0,
) -> dict:
    """One offered QoS profile in rosbag2's version-9 form (lower-case enum names)."""

    def dur(ns: int) -> dict:
        if ns <= 0 or ns >= 9223372036854775807:
            return dict(_INFINITE)
        return {'sec': ns // 1_000_000_000, 'nsec': ns % 1_000_000_000}

    return {
        'history': history,
        'depth': int(depth),
        'reliability': reliability,
        'durability': durability,
        'deadline': dur(deadline_ns),
        'lifespan': dur(lifespan_ns),
        'liveliness': liveliness,
        'liveliness_lease_duration': dur(lease_ns),
        'avoid_ros_namespace_conventions': False,
    }


def qos_yaml(profiles: list[dict]) -> str:
    """The MCAP channel metadata value ``offered_qos_profiles`` (a YAML string)."""
    return yaml.safe_dump(profiles, sort_keys=False, default_flow_style=False)


@dataclass
class TopicRecord:
    """What the bag says about one topic."""

    name: str
    type: str
    message_count: int = 0
    offered_qos_profiles: list[dict] = field(default_factory=list)
    type_description_hash: str = ''


def bag_metadata(
    files: list[tuple[str, int, int, int]],
    topics: list[TopicRecord],
    custom_data: dict[str, str] | None = None,
) -> dict:
    """The ``metadata.yaml`` content. ``files``: (relative path, start ns, end ns, count)."""
    starts = [s for _, s, _, n in files if n]
    ends = [e for _, _, e, n in files if n]
    t0 = min(starts) if starts else 0
    t1 = max(ends) if ends else 0
    total = sum(n for *_, n in files)
    return {
        'rosbag2_bagfile_information': {
            'version': ROSBAG2_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': t1 - t0},
            'starting_time': {'nanoseconds_since_epoch': t0},
            'message_count': total,
            'topics_with_message_count': [
                {
                    'topic_metadata': {
                        'name': t.name,
                        'type': t.type,
                        'serialization_format': 'cdr',
                        'offered_qos_profiles': t.offered_qos_profiles,
                        'type_description_hash': t.type_description_hash,
                    },
                    'message_count': t.message_count,
                }
                for t in topics
            ],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [p for p, *_ in files],
            'files': [
                {
                    'path': p,
                    'starting_time': {'nanoseconds_since_epoch': s},
                    'duration': {'nanoseconds': max(0, e - s)},
                    'message_count': n,
                }
                for p, s, e, n in files
            ],
            'custom_data': {str(k): str(v) for k, v in (custom_data or {}).items()},
            'ros_distro': ROS_DISTRO,
        }
    }


def rosbag2_record(metadata: dict) -> dict[str, str]:
    """The MCAP metadata record ``rosbag2`` for :func:`bag_metadata`'s ``metadata``.

    As rosbag2's MCAP storage (Jazzy) writes it: one key, ``serialized_metadata``, the map
    *inside* ``metadata.yaml``'s ``rosbag2_bagfile_information`` in YAML (``version`` at the
    top; with the outer key every ``ros2 bag`` command fails on the bag).
    """
    inner = metadata['rosbag2_bagfile_information']
    return {'serialized_metadata': yaml.safe_dump(inner, sort_keys=False)}


def write_metadata_yaml(out: Path, metadata: dict) -> None:
    """Write ``metadata.yaml`` atomically (a crash never leaves half a file)."""
    path = Path(out) / 'metadata.yaml'
    tmp = path.with_suffix('.yaml.tmp')
    with open(tmp, 'w', encoding='utf-8') as f:
        yaml.safe_dump(metadata, f, sort_keys=False, default_flow_style=False)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_metadata_yaml(out: Path) -> dict:
    """The map inside ``out/metadata.yaml``'s ``rosbag2_bagfile_information``."""
    with open(Path(out) / 'metadata.yaml', encoding='utf-8') as f:
        return yaml.load(f, Loader=_YAML_LOADER)['rosbag2_bagfile_information']
