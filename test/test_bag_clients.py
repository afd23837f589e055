"""A whole tuner bag in the tools a ROS user reaches for first.

One short real tuner run (``ros2 run im_tuner tuner --budget 3``, in-process simulated
bench) makes the bag; then:

* **rosbag2** (``ros2 bag info`` / ``play``; not installable here, there are no wheels):
  a Python mirror of the YAML decoder rosbag2 Jazzy runs on the bag's ``rosbag2`` MCAP
  metadata record (on every read-only open of its MCAP storage) and on ``metadata.yaml``
  -- also on a repaired bag's and on the provisional one a recording bag carries;
* **mcap_ros2**: its two documented whole-file calls, with the topic list
  docs/recorder.md gives (service events excluded), against the bag's own counts and
  rosbags' decoding;
* **rosbags-convert**: the command docs/recorder.md gives, run as written, and the
  converted bag read back with rosbags' ``AnyReader``.

The doc's snippets are checked to be the ones run here, line for line.
"""

from __future__ import annotations

import array
import collections
import dataclasses
import hashlib
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

from im_tuner.record.metadata import bag_metadata, read_metadata_yaml
from im_tuner.record.repair import repair_bag

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
DOC = Path(__file__).resolve().parents[1] / 'docs' / 'recorder.md'
SERVICE_EVENT = '/_service_event'

# -- a mirror of rosbag2 Jazzy's metadata decoder -----------------------------------------
# Mirrors, read on github.com/ros2/rosbag2 branch jazzy (rosbag2_storage 0.26.5, where
# BagMetadata's version is 9):
#   rosbag2_storage/include/rosbag2_storage/yaml.hpp  convert<BagMetadata>::decode and the
#     converters it calls: TopicInformation, TopicMetadata, FileInformation,
#     std::chrono::nanoseconds, time_point, the custom_data map;
#   rosbag2_storage/src/rosbag2_storage/qos.cpp       convert<rclcpp::QoS>::decode (the
#     version-9 string form), convert<rmw_time_t>::decode, to_rclcpp_qos_vector;
#   rosbag2_storage/src/rosbag2_storage/metadata_io.cpp  read_metadata: metadata.yaml's
#     ["rosbag2_bagfile_information"];
#   rosbag2_storage_mcap/src/mcap_storage.cpp  read_metadata: the "rosbag2" records'
#     "serialized_metadata", YAML::Load, convert<BagMetadata>::decode on the ROOT node;
#     then per channel its schema, "offered_qos_profiles" (to_rclcpp_qos_vector) and
#     "topic_type_hash", and the Statistics record.
# Each yaml-cpp read is a check: node[key] of a missing key throws ("invalid node; first
# invalid key"), .as<int>/<uint64_t> needs an integer in range (unsigned: not negative),
# a sequence converter needs a sequence, .as<bool> a boolean. Stricter than yaml-cpp in
# two places, on purpose: .as<std::string> fields must be YAML strings (yaml-cpp would
# take any scalar), and QoS enum names must be ones rmw knows (rmw_qos_*_from_str maps
# any other text to UNKNOWN silently). The tests also require the version-9 QoS form
# (enum names), which rosbag2 Jazzy writes.
INT32 = (-(2**31), 2**31 - 1)
UINT64 = (0, 2**64 - 1)
QOS_NAMES = {  # rmw/src/qos_string_conversions.c, plus "unknown" (rosbag2's encode)
    'history': {'system_default', 'keep_last', 'keep_all', 'unknown'},
    'reliability': {'system_default', 'reliable', 'best_effort', 'best_available', 'unknown'},
    'durability': {'system_default', 'transient_local', 'volatile', 'best_available', 'unknown'},
    'liveliness': {'system_default', 'automatic', 'manual_by_topic', 'best_available', 'unknown'},
}


class Rosbag2DecodeError(Exception):
    """What yaml-cpp would throw inside rosbag2's decode."""


def _at(node: object, key: str, where: str) -> object:
    if not isinstance(node, dict) or key not in node:
        raise Rosbag2DecodeError(f'{where}: invalid node; first invalid key: "{key}"')
    return node[key]


def _int(node: object, key: str, where: str, bounds: tuple[int, int]) -> int:
    v = _at(node, key, where)
    if isinstance(v, bool) or not isinstance(v, int) or not bounds[0] <= v <= bounds[1]:
        raise Rosbag2DecodeError(f'{where}.{key}: bad conversion to an integer in {bounds}: {v!r}')
    return v


def _str(node: object, key: str, where: str) -> str:
    v = _at(node, key, where)
    if not isinstance(v, str):
        raise Rosbag2DecodeError(f'{where}.{key}: not a string: {v!r}')
    return v


def _seq(node: object, key: str, where: str) -> list:
    v = _at(node, key, where)
    if not isinstance(v, list):
        raise Rosbag2DecodeError(f'{where}.{key}: bad conversion (not a sequence): {v!r}')
    return v


def _nanoseconds(node: object, key: str, where: str) -> int:  # convert<nanoseconds>
    return _int(_at(node, key, where), 'nanoseconds', f'{where}.{key}', UINT64)


def _time_point(node: object, key: str, where: str) -> int:  # convert<time_point>
    return _int(_at(node, key, where), 'nanoseconds_since_epoch', f'{where}.{key}', UINT64)


def decode_rmw_time(node: object, where: str) -> int:
    """qos.cpp convert<rmw_time_t>::decode -> nanoseconds."""
    return _int(node, 'sec', where, UINT64) * 10**9 + _int(node, 'nsec', where, UINT64)


def decode_qos(node: object, where: str) -> dict:
    """qos.cpp convert<rclcpp::QoS>::decode: an integer ``history`` in 0..3 (SYSTEM_DEFAULT
    .. UNKNOWN) means the version-8 form (integer enums), anything else the version-9 one
    (enum names). Returns the profile with ``form`` 8 or 9."""
    history = _at(node, 'history', where)
    if isinstance(history, int) and not isinstance(history, bool) and 0 <= history <= 3:
        out: dict = {'form': 8, 'history': history}
        for key in ('reliability', 'durability', 'liveliness'):
            out[key] = _int(node, key, where, INT32)
        keep_last = history == 1
    else:
        out = {'form': 9}
        for key, names in QOS_NAMES.items():
            out[key] = _str(node, key, where)
            if out[key] not in names:
                raise Rosbag2DecodeError(f'{where}.{key}: {out[key]!r} is not an rmw name')
        keep_last = out['history'] == 'keep_last'
    if keep_last:
        out['depth'] = _int(node, 'depth', where, INT32)
    for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        out[key] = decode_rmw_time(_at(node, key, where), f'{where}.{key}')
    v = _at(node, 'avoid_ros_namespace_conventions', where)
    if not isinstance(v, bool):
        raise Rosbag2DecodeError(f'{where}.avoid_ros_namespace_conventions: not a bool: {v!r}')
    return out


def decode_qos_vector(node: object, where: str) -> list[dict]:
    """qos.cpp convert<std::vector<rclcpp::QoS>>::decode (false unless a sequence)."""
    if not isinstance(node, list):
        raise Rosbag2DecodeError(f'{where}: bad conversion (not a sequence): {node!r}')
    return [decode_qos(p, f'{where}[{i}]') for i, p in enumerate(node)]


def decode_bag_metadata(node: object) -> dict:
    """yaml.hpp convert<rosbag2_storage::BagMetadata>::decode, in its order of reads."""
    where = 'BagMetadata'
    out: dict = {'version': _int(node, 'version', where, INT32)}
    version = out['version']
    out['storage_identifier'] = _str(node, 'storage_identifier', where)
    out['duration'] = _nanoseconds(node, 'duration', where)
    out['starting_time'] = _time_point(node, 'starting_time', where)
    out['message_count'] = _int(node, 'message_count', where, UINT64)
    out['topics'] = {}
    for i, info in enumerate(_seq(node, 'topics_with_message_count', where)):
        w = f'{where}.topics_with_message_count[{i}]'
        tm = _at(info, 'topic_metadata', w)
        w = f'{w}.topic_metadata'
        topic = {
            'type': _str(tm, 'type', w),
            'serialization_format': _str(tm, 'serialization_format', w),
        }
        if version >= 9:
            topic['qos'] = decode_qos_vector(_at(tm, 'offered_qos_profiles', w), w)
        elif version >= 4:
            qos_text = _str(tm, 'offered_qos_profiles', w)
            topic['qos'] = decode_qos_vector(yaml.safe_load(qos_text) if qos_text else [], w)
        if version >= 7:
            topic['type_description_hash'] = _str(tm, 'type_description_hash', w)
        topic['message_count'] = _int(info, 'message_count', w, UINT64)
        out['topics'][_str(tm, 'name', w)] = topic
    paths = _seq(node, 'relative_file_paths', where)
    if not all(isinstance(p, str) for p in paths):
        raise Rosbag2DecodeError(f'{where}.relative_file_paths: not strings: {paths!r}')
    out['relative_file_paths'] = paths
    if version >= 3:
        out['compression_format'] = _str(node, 'compression_format', where)
        out['compression_mode'] = _str(node, 'compression_mode', where)
    if version >= 5:
        out['files'] = []
        for i, f in enumerate(_seq(node, 'files', where)):
            w = f'{where}.files[{i}]'
            out['files'].append(
                {
                    'path': _str(f, 'path', w),
                    'starting_time': _time_point(f, 'starting_time', w),
                    'duration': _nanoseconds(f, 'duration', w),
                    'message_count': _int(f, 'message_count', w, UINT64),
                }
            )
    if version >= 6:
        custom = _at(node, 'custom_data', where)
        if custom is None:
            custom = {}  # a null node iterates as empty
        if not isinstance(custom, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in custom.items()
        ):
            raise Rosbag2DecodeError(f'{where}.custom_data: not a map of strings: {custom!r}')
        out['custom_data'] = custom
    if version >= 8:
        out['ros_distro'] = _str(node, 'ros_distro', where)
    return out


def rosbag2_open_mcap(path: Path) -> dict:
    """mcap_storage.cpp MCAPStorage::read_metadata (what ``ros2 bag info``/``play`` run):
    the ``rosbag2`` records, then the channels and the Statistics record."""
    with open(path, 'rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        records = [m.metadata for m in reader.iter_metadata() if m.name == 'rosbag2']
    assert summary is not None and summary.statistics is not None  # .value() throws
    decoded = []
    for rec in records:
        text = rec.get('serialized_metadata', '')
        if text:
            decoded.append(decode_bag_metadata(yaml.safe_load(text)))
    version = decoded[-1]['version'] if decoded else 9  # BagMetadata's default
    channels = {}
    for cid, ch in summary.channels.items():
        schema = summary.schemas[ch.schema_id]  # "Could not find schema for topic"
        qos_text = ch.metadata.get('offered_qos_profiles', '')
        qos = yaml.safe_load(qos_text) if qos_text else []
        assert version >= 9
        channels[ch.topic] = {
            'type': schema.name,
            'serialization_format': ch.message_encoding,
            'qos': decode_qos_vector(qos, f'channel {ch.topic}'),
            'type_description_hash': ch.metadata.get('topic_type_hash', ''),
            'message_count': summary.statistics.channel_message_counts.get(cid, 0),
        }
    return {'records': decoded, 'channels': channels, 'statistics': summary.statistics}


# -- the bag ------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> Path:
    """A whole tuner bag: the reference and 3 evaluations (no re-measurement: what the
    readers are asked holds for 4 experiments as for 7, in about 57 % of the time), about
    71 000 messages on 17 topics."""
    run = tmp_path_factory.mktemp('bag_clients') / 'run'
    args = (
        '--budget',
        '3',
        '--remeasure',
        '0',
        '--seed',
        '1',
        '--quiet',
        '--discovery-timeout',
        '0.2',
        '--out',
        str(run),
    )
    proc = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', *args],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run / 'bag_0'


def _mcap(bag: Path) -> Path:
    (path,) = bag.glob('*.mcap')
    return path


def _service_event_topics(meta: dict) -> set[str]:
    return {
        t['topic_metadata']['name']
        for t in meta['topics_with_message_count']
        if t['topic_metadata']['name'].endswith(SERVICE_EVENT)
    }


def test_rosbag2_decodes_the_record_and_metadata_yaml(bag):
    """The record is metadata.yaml's map without its outer key: with the key, rosbag2's
    decode (and a yaml-cpp run of it) throws 'invalid node; first invalid key: "version"'."""
    meta = read_metadata_yaml(bag)
    opened = rosbag2_open_mcap(_mcap(bag))
    (record,) = opened['records']
    from_file = decode_bag_metadata(
        yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    )
    # the record is the very map of metadata.yaml (bar the outer key), read the same
    assert record == from_file
    assert record['version'] == 9 and record['ros_distro'] == 'jazzy'
    assert record['storage_identifier'] == 'mcap' and record['custom_data']['im_tuner.state'] == (
        'closed'
    )
    stats = opened['statistics']
    assert record['message_count'] == stats.message_count == meta['message_count'] > 100_000
    assert record['starting_time'] == stats.message_start_time
    # in ns of log (wall) time: 4+ experiments of 1.625 s simulated take 0.5-3 s of wall
    # time on the lock-step bench, depending on the machine; in seconds it would be < 10
    assert record['duration'] == stats.message_end_time - stats.message_start_time > 10**8
    assert record['relative_file_paths'] == [_mcap(bag).name]
    assert record['files'] == [
        {
            'path': _mcap(bag).name,
            'starting_time': stats.message_start_time,
            'duration': record['duration'],
            'message_count': stats.message_count,
        }
    ]
    # per topic, the record, metadata.yaml and what rosbag2 rebuilds from the channels agree
    assert set(record['topics']) == set(opened['channels'])
    assert len(record['topics']) == 18  # (tuner/result among them)
    for name, topic in record['topics'].items():
        assert topic == opened['channels'][name], name
        assert topic['serialization_format'] == 'cdr'
        assert topic['type_description_hash'].startswith('RIHS01_'), name
        assert {(q['form'], q['reliability']) for q in topic['qos']} == {(9, 'reliable')}, name
    # state 0, then 8125 states per experiment (its 0.5 s settle and 1.125 s): the
    # reference and 3 evaluations at least (more if re-run)
    assert record['topics']['/drive/state']['message_count'] >= 1 + 4 * 8125
    assert record['topics']['/drive/state']['type'] == 'std_msgs/msg/Float64MultiArray'
    assert record['topics']['/controller/start_experiment/_service_event']['type'] == (
        'std_srvs/srv/Trigger_Event'
    )
    # the mirror is not a rubber stamp: the layout the bags had before fails in it
    with pytest.raises(Rosbag2DecodeError, match='first invalid key: "version"'):
        decode_bag_metadata(
            {
                'rosbag2_bagfile_information': yaml.safe_load((bag / 'metadata.yaml').read_text())[
                    'rosbag2_bagfile_information'
                ]
            }
        )


def test_rosbag2_decodes_the_provisional_and_the_repaired_metadata_yaml(bag, tmp_path):
    provisional = bag_metadata([('x_0.mcap', 0, 0, 0)], [], {'im_tuner.state': 'recording'})
    got = decode_bag_metadata(provisional['rosbag2_bagfile_information'])
    assert got['topics'] == {} and got['message_count'] == 0 and got['duration'] == 0

    # a killed recorder: the end of the file (last chunk, record, summary) gone, repaired
    cut = tmp_path / 'cut'
    shutil.copytree(bag, cut)
    path = _mcap(cut)
    os.truncate(path, path.stat().st_size * 2 // 3)
    report = repair_bag(cut)
    assert (
        not report.was_complete and 0 < report.messages < read_metadata_yaml(bag)['message_count']
    )
    got = decode_bag_metadata(read_metadata_yaml(cut))
    assert got['custom_data']['im_tuner.state'] == 'repaired'
    assert got['message_count'] == report.messages
    assert {n: t['message_count'] for n, t in got['topics'].items()} == report.topics
    opened = rosbag2_open_mcap(path)
    assert opened['records'] == []  # written at close: rosbag2 then reads the channels only
    assert opened['statistics'].message_count == report.messages
    assert {n: t['message_count'] for n, t in opened['channels'].items()} == report.topics


# -- mcap_ros2 ----------------------------------------------------------------------------
def _doc_blocks(lang: str) -> list[str]:
    """The fenced ``lang`` code blocks of docs/recorder.md."""
    blocks, current = [], None
    for line in DOC.read_text().splitlines(keepends=True):
        if current is None and line.strip() == f'```{lang}':
            current = []
        elif current is not None and line.strip() == '```':
            blocks.append(''.join(current))
            current = None
        elif current is not None:
            current.append(line)
    return blocks


def _plain(x: object) -> object:
    """A decoded message as plain data: mcap_ros2's (slots) and rosbags' (dataclasses)."""
    if isinstance(x, (bool, int, float, str)) or x is None:
        return x
    if isinstance(x, (np.ndarray, array.array, list, tuple, bytes)):
        return [_plain(v) for v in (x.tolist() if isinstance(x, np.ndarray) else x)]
    if dataclasses.is_dataclass(x):  # rosbags: __msgtype__ and constants are fields too
        return {
            f.name: _plain(getattr(x, f.name))
            for f in dataclasses.fields(x)
            if not (f.name.startswith('__') or f.name.isupper())
        }
    return {k: _plain(getattr(x, k)) for k in type(x).__slots__}


def _rosbags_first_last(bag: Path) -> dict[str, tuple[object, object]]:
    """Each topic's first and last message, deserialised by rosbags' AnyReader."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    raws: dict[str, list] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        for conn, _t, raw in reader.messages():
            raws.setdefault(conn.topic, [conn.msgtype, raw, raw])[2] = raw
        return {
            t: (_plain(reader.deserialize(a, typ)), _plain(reader.deserialize(b, typ)))
            for t, (typ, a, b) in raws.items()
        }


def test_mcap_ros2_documented_calls_read_the_whole_bag(bag):
    """read_ros2_messages(path) alone stops at the first service event
    (DecoderNotFoundError: no decoder for ros2idl). The two blocks of docs/recorder.md,
    run as written (their ``print`` collects), read every other message of the bag."""
    from mcap.exceptions import DecoderNotFoundError

    with warnings.catch_warnings():  # 0.6.0 deprecates the module (see the doc)
        warnings.simplefilter('ignore', DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages

    iter_block, read_block = (
        b for b in _doc_blocks('python') if 'read_ros2_messages' in b or 'iter_decoded' in b
    )
    meta = read_metadata_yaml(bag)
    types, counts = {}, {}
    for t in meta['topics_with_message_count']:
        types[t['topic_metadata']['name']] = t['topic_metadata']['type']
        counts[t['topic_metadata']['name']] = t['message_count']
    events = _service_event_topics(meta)
    assert len(events) >= 8 and sum(counts[t] for t in events) >= 14
    path = str(_mcap(bag))

    # without the topics, what users hit: the first service event ends the read
    with pytest.raises(DecoderNotFoundError):
        for _m in read_ros2_messages(path):
            pass

    class Collected:
        """What a block's ``print(topic, msg)`` calls saw: counts, type names, first/last."""

        def __init__(self) -> None:
            self.counts: collections.Counter = collections.Counter()
            self.classes: dict[str, set[str]] = collections.defaultdict(set)
            self.first_last: dict[str, list] = {}

        def __call__(self, topic: str, msg: object) -> None:
            self.counts[topic] += 1
            self.classes[topic].add(type(msg).__name__)
            self.first_last.setdefault(topic, [msg, None])[1] = msg

    def run(block: str, namespace: dict) -> Collected:
        out = namespace['print'] = Collected()
        # the one line that names a bag, in the first block
        block = re.sub(r'^path = .*$', f'path = {path!r}', block, count=1, flags=re.M)
        exec(compile(block, str(DOC), 'exec'), namespace)
        return out

    namespace: dict = {}
    iterated = run(iter_block, namespace)
    assert set(namespace['topics']) == set(types) - events
    read = run(read_block, namespace)

    expected = {t: counts[t] for t in types if t not in events and counts[t]}
    assert sum(expected.values()) == meta['message_count'] - sum(counts[t] for t in events)
    for got in (iterated, read):
        assert dict(got.counts) == expected
        # the right type: every message of a topic decoded to the class of the topic's type
        assert got.classes == {t: {types[t].rsplit('/', 1)[1]} for t in expected}

    # the values: each topic's first and last message as rosbags decodes them
    theirs = _rosbags_first_last(bag)
    for got in (iterated, read):
        for topic, (a, b) in got.first_last.items():
            assert (_plain(a), _plain(b)) == theirs[topic], topic


# -- rosbags-convert ---------------------------------------------------------------------
def _raw_by_topic(bag: Path, deserialize: bool) -> dict[str, list[tuple[int, str]]]:
    """Per topic, (log time, SHA-1 of the CDR bytes) of every message, by AnyReader."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list] = collections.defaultdict(list)
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        for conn, t, raw in reader.messages():
            out[conn.topic].append((t, hashlib.sha1(raw).hexdigest()))
            if deserialize:
                reader.deserialize(raw, conn.msgtype)
    return out


def test_rosbags_convert_with_the_documented_command(bag, tmp_path):
    """rosbags-convert fails on service-event topics (rosbags cannot write a
    message definition for a pkg/srv type); the command docs/recorder.md gives, run as
    written, converts every other message."""
    ((command,),) = (
        [line for line in b.splitlines() if line.startswith('rosbags-convert ')]
        for b in _doc_blocks('sh')
        if 'rosbags-convert' in b
    )
    path = f'{Path(sys.prefix) / "bin"}{os.pathsep}{os.environ["PATH"]}'
    env = {**os.environ, 'BAG': str(bag), 'PATH': path}
    for extra in ('', ' --dst-storage mcap'):
        out = tmp_path / (extra.split()[-1] if extra else 'default')
        out.mkdir()
        proc = subprocess.run(
            ['bash', '-c', command + extra],
            cwd=out,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
    assert len(list((tmp_path / 'default' / 'converted').glob('*.db3'))) == 1
    assert len(list((tmp_path / 'mcap' / 'converted').glob('*.mcap'))) == 1

    source = _raw_by_topic(bag, deserialize=False)
    events = _service_event_topics(read_metadata_yaml(bag))
    assert sum(len(source[t]) for t in events) >= 14
    kept = {t: v for t, v in source.items() if t not in events}
    for storage in ('default', 'mcap'):
        converted = tmp_path / storage / 'converted'
        # every other message, same log time, same bytes; every one deserialised
        assert _raw_by_topic(converted, deserialize=True) == kept, storage
        meta = read_metadata_yaml(converted)
        assert meta['message_count'] == sum(len(v) for v in kept.values()) > 100_000
