"""The Foxglove layouts shipped in share/im_tuner/foxglove/ resolve in a real bag.

One short real tuner run (``ros2 run im_tuner tuner --budget 1 --remeasure 1``: the
reference, one evaluation and its re-measurement, lock-step, recorded) makes the bag. Each
layout is loaded from the installed share directory (``ament_index_python``), every
message path in it is extracted and resolved against the bag with rosbags' ``AnyReader``
(the types from the bag's own schemas): the topic is in the bag with messages, every field
exists on every decoded message, every array index is below the array's length in every
message, every path gives one plottable number per message (a series of one record kind:
at most one, and one in some message), and every label names the field the contract puts
at that index, with the unit docs/interfaces.md documents. The resolver is shown to catch
a wrong topic, field, index, filter and label. The layouts hold the 51 message paths of
Figs. 5 and 8 and the drive signals as before, Fig. 9's 24 on the tuner's result topic
(the loss and each gain per record kind, the experiment id as x), and the sim-time x axes
of Figs. 5 and 8, whose panels each plot one topic against that topic's drive step: on the
bag the load steps on 0.7 s of sim time after the move starts; each Fig. 9 series' points
are results.jsonl's records of its kind, bit for bit. The committed and installed files
are the generator's bytes, the SDK's form holds the same panel configs, and
docs/foxglove.md carries the generator's index table.
"""

from __future__ import annotations

import ast
import itertools
import json
import math
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from ament_index_python.packages import get_package_share_directory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

import im_controller.layout
from im_controller.config import GAIN_NAMES, GAIN_UNITS
from im_controller.layout import CONTROL_FIELDS, INTERNALS_FIELDS
from im_controller.messages import LOSS_KEYS
from im_drive_sim.contract import COMMAND_FIELDS, STATE_FIELDS
from im_tuner.foxglove.layouts import (
    LAYOUTS,
    STEP_FIELDS,
    TITLE_KEY,
    build,
    definitions,
    render,
    render_sdk,
)
from im_tuner.foxglove.signals import index_table

REPO = Path(__file__).resolve().parents[1]
ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
COMMITTED = REPO / 'src' / 'im_tuner' / 'foxglove'
FIELDS = {
    '/drive/state': STATE_FIELDS,
    '/drive/command': COMMAND_FIELDS,
    '/controller/internals': INTERNALS_FIELDS,
}
LOSS_TOPIC = '/controller/loss'
RESULT_TOPIC = '/tuner/result'
KINDS = ('reference', 'eval', 'remeasure')
N_STATE, N_CMD = len(STATE_FIELDS), len(COMMAND_FIELDS)
THETA_MEAS = f'/drive/state.data[{STATE_FIELDS.index("theta_meas")}]'
E_THETA = f'/controller/internals.data[{INTERNALS_FIELDS.index("e_theta")}]'
LABEL = re.compile(r'^(?P<name>\w+): (?P<meaning>.+) \[(?P<unit>[^\]]+)\]$')


# -- the bag --------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def run(tmp_path_factory) -> Path:
    """A real tuner run: the reference experiment, one evaluation and its re-measurement,
    recorded."""
    out = tmp_path_factory.mktemp('foxglove') / 'run'
    args = ('--budget', '1', '--remeasure', '1', '--seed', '1', '--quiet', '--out', str(out))
    args += ('--discovery-timeout', '0.2')  # no controller on the graph: no 2 s look
    proc = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'tuner', *args], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.fixture(scope='module')
def installed() -> dict[str, dict]:
    """Every shipped layout, loaded from the installed share directory."""
    d = Path(get_package_share_directory('im_tuner')) / 'foxglove'
    files = sorted(d.glob('*.json'))
    assert [f.stem for f in files] == sorted(LAYOUTS)
    return {f.stem: json.loads(f.read_text(encoding='utf-8')) for f in files}


# -- Foxglove message paths: the syntax the layouts use -------------------------------------
# docs.foxglove.dev/docs/visualization/message-path-syntax: a topic, then `.field`,
# `[i]` (index), `[:]` (every element) and `{key=="value"}` (keep the elements whose
# field equals the literal). Anything else is refused, so a path this parser does not
# understand cannot pass unchecked.
_STEP = re.compile(
    r'\.(?P<field>[A-Za-z_]\w*)|\[(?P<index>\d+)\]|(?P<all>\[:\])'
    r'|\{(?P<fkey>[A-Za-z_]\w*)==(?P<q>["\'])(?P<fval>[^"\']*)(?P=q)\}'
)


class Unresolved(AssertionError):
    """A message path that does not resolve in the bag."""


def parse_path(path: str) -> tuple[str, list[tuple[str, Any]]]:
    """``(topic, steps)``; a step is ('field', name), ('index', i), ('all', None) or
    ('filter', (key, value))."""
    m = re.match(r'^(/[A-Za-z_][\w/]*)', path)
    if not m:
        raise Unresolved(f'{path}: no topic')
    topic, rest, steps = m.group(1), path[m.end() :], []
    while rest:
        s = _STEP.match(rest)
        if not s:
            raise Unresolved(f'{path}: cannot parse {rest!r}')
        if s.group('field'):
            steps.append(('field', s.group('field')))
        elif s.group('index'):
            steps.append(('index', int(s.group('index'))))
        elif s.group('all'):
            steps.append(('all', None))
        else:
            steps.append(('filter', (s.group('fkey'), s.group('fval'))))
        rest = rest[s.end() :]
    return topic, steps


def evaluate(msg: object, path: str, steps: list[tuple[str, Any]]) -> list[object]:
    """The values ``steps`` select in one decoded message (Unresolved: a field that does
    not exist, an index beyond the array)."""
    items = [msg]
    for kind, arg in steps:
        out: list[object] = []
        for it in items:
            if kind == 'field':
                if not hasattr(it, arg):
                    raise Unresolved(f'{path}: {type(it).__name__} has no field {arg!r}')
                out.append(getattr(it, arg))
            elif kind == 'index':
                if not arg < len(it):
                    raise Unresolved(f'{path}: index {arg} beyond an array of {len(it)}')
                out.append(it[arg])
            elif kind == 'all':
                out.extend(it)
            else:
                key, value = arg
                if not hasattr(it, key):
                    raise Unresolved(f'{path}: filter on a field {key!r} that does not exist')
                if str(getattr(it, key)) == value:
                    out.append(it)
        items = out
    return items


def plottable(v: object) -> float:
    """The number Foxglove's Plot draws for a value: numbers and numeric strings."""
    if isinstance(v, bool) or not isinstance(v, int | float | str):
        raise Unresolved(f'not a plottable value: {v!r}')
    return float(v)


def by_kind(steps: list[tuple[str, Any]]) -> bool:
    """A path of one record kind (``.status[:]{name=="eval"}``): a message of another kind
    gives it no value."""
    return any(kind == 'filter' and arg[0] == 'name' for kind, arg in steps)


def resolve(bag: Path, paths: list[str]) -> dict[str, list[float | None]]:
    """Resolve every path in every message of its topic: path -> the value of each message
    (one per message, in log-time order; None where a path of one record kind has none,
    which is no point in the plot)."""
    parsed = {p: parse_path(p) for p in paths}
    out: dict[str, list[float | None]] = {p: [] for p in paths}
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        conns = {c.topic: c for c in reader.connections}
        for p, (topic, _steps) in parsed.items():
            if topic not in conns:
                raise Unresolved(f'{p}: topic {topic} is not in the bag')
            if conns[topic].msgcount == 0:
                raise Unresolved(f'{p}: topic {topic} has no messages')
        wanted = [conns[t] for t in {t for t, _s in parsed.values()}]
        for c, _t, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, c.msgtype)
            for p, (topic, steps) in parsed.items():
                if topic == c.topic:
                    values = evaluate(msg, p, steps)
                    if len(values) == 0 and by_kind(steps):
                        out[p].append(None)
                    elif len(values) != 1:
                        raise Unresolved(f'{p}: {len(values)} values in a message, not one')
                    else:
                        out[p].append(plottable(values[0]))
    for p, vs in out.items():
        if all(v is None for v in vs):
            raise Unresolved(f'{p}: no value in any message')
    return out


def points(values: dict[str, list[float | None]], series: str, x: str) -> list[tuple]:
    """The (x, y) points Foxglove draws for ``series`` against ``x`` on one topic: the
    n-th message's value of each, where both have one."""
    return [(a, b) for a, b in zip(values[x], values[series], strict=True) if None not in (a, b)]


# -- what a layout holds --------------------------------------------------------------------
def leaves(node: Any) -> Iterator[str]:
    """The panel ids of a mosaic tree."""
    if isinstance(node, str):
        yield node
    else:
        assert set(node) <= {'first', 'second', 'direction', 'splitPercentage'}, node
        assert node['direction'] in ('row', 'column')
        yield from leaves(node['first'])
        yield from leaves(node['second'])


def panels(layout: dict) -> list[str]:
    """Every panel id the layout shows (inside tabs too); checks the structure."""
    assert set(layout) == {'configById', 'globalVariables', 'userNodes', 'playbackConfig', 'layout'}
    ids = list(leaves(layout['layout']))
    for pid in list(ids):
        if pid.startswith('Tab!'):
            cfg = layout['configById'][pid]
            assert 0 <= cfg['activeTabIdx'] < len(cfg['tabs'])
            for tab in cfg['tabs']:
                ids.extend(leaves(tab['layout']))
    assert len(ids) == len(set(ids)), 'a panel shown twice'
    assert sorted(ids) == sorted(layout['configById']), 'panels without a config, or configs unused'
    return ids


def series(layout: dict) -> list[tuple[str, str, str | None]]:
    """``(panel id, message path, label)`` of every Plot series and custom x axis (label
    None)."""
    out = []
    for pid in panels(layout):
        if not pid.startswith('Plot!'):
            continue
        cfg = layout['configById'][pid]
        assert cfg['xAxisVal'] in ('timestamp', 'custom')
        for p in cfg['paths']:
            assert p['enabled'] is True and p['timestampMethod'] == 'receiveTime'
            out.append((pid, p['value'], p['label']))
        if cfg['xAxisVal'] == 'custom':
            out.append((pid, cfg['xAxisPath']['value'], None))
    return out


# -- what the contract documents ------------------------------------------------------------
def interfaces_units() -> dict[str, dict[int, tuple[str, str]]]:
    """docs/interfaces.md's tables: topic -> index -> (field, unit)."""
    text = (REPO / 'docs' / 'interfaces.md').read_text(encoding='utf-8')
    out: dict[str, dict[int, tuple[str, str]]] = {}
    for topic, heading in (('/drive/state', 'drive/state'), ('/drive/command', 'drive/command')):
        section = text.split(f'### `{heading}` (data[')[1].split('\n### ')[0]
        rows = re.findall(r'^\| (\d+) \| `(\w+)` \| ([^|]+) \|', section, re.M)
        out[topic] = {int(i): (name, unit.strip()) for i, name, unit in rows}
    return out


def control_units() -> dict[str, str]:
    """The units im_controller.layout documents for CONTROL_FIELDS (its docstring)."""
    tree = ast.parse(Path(im_controller.layout.__file__).read_text(encoding='utf-8'))
    body = tree.body
    for a, b in itertools.pairwise(body):
        if isinstance(a, ast.AnnAssign) and getattr(a.target, 'id', '') == 'CONTROL_FIELDS':
            doc = b.value.value
            units = re.search(r'units: ([^)]+)\)', doc).group(1).split(', ')
            return {
                n: ('-' if u == '0/1' else u) for n, u in zip(CONTROL_FIELDS, units, strict=True)
            }
    raise AssertionError('CONTROL_FIELDS has no docstring of units')


def check_label(path: str, text: str | None) -> None:
    """The label names the field at the path's index (or the loss key) with its documented
    unit (AssertionError otherwise)."""
    topic, steps = parse_path(path)
    if text is None:  # a custom x axis: the result message's experiment id, or a drive step
        if topic in FIELDS:
            assert steps == [('field', 'data'), ('index', FIELDS[topic].index(STEP_FIELDS[topic]))]
        else:
            assert topic == RESULT_TOPIC and steps[-2] == ('filter', ('key', 'experiment_id'))
            assert not by_kind(steps), path  # every message's: the pairing stays aligned
        return
    m = LABEL.match(text)
    assert m, f'{path}: label {text!r} is not "name: meaning [unit]"'
    name, unit = m.group('name'), m.group('unit')
    if topic in FIELDS:
        assert steps[:-1] == [('field', 'data')] and steps[-1][0] == 'index', path
        i = steps[-1][1]
        assert name == FIELDS[topic][i], f'{path} is {FIELDS[topic][i]}, labelled {name}'
        documented = interfaces_units().get(topic, {}).get(i)
        if documented is not None:
            assert documented[0] == name and unit == documented[1], (
                f'{path}: {text} vs {documented}'
            )
        elif name in control_units():
            assert unit == control_units()[name], f'{path}: {text} vs {control_units()[name]}'
    else:
        assert topic == RESULT_TOPIC, path
        kind = steps[2][1][1]
        assert steps[:3] == [('field', 'status'), ('all', None), ('filter', ('name', kind))]
        assert kind in KINDS, path
        assert {'reference': 'reference', 'eval': 'evaluations', 'remeasure': 're-measurements'}[
            kind
        ] == m.group('meaning'), f'{path}: a series of {kind} records labelled {text}'
        key = steps[-2][1][1]
        assert steps[-2] == ('filter', ('key', key)) and key in LOSS_KEYS, path
        assert name == key, f'{path} is {key}, labelled {name}'
        if key in GAIN_NAMES:
            assert unit == GAIN_UNITS[key], f'{path}: {text}'


def at(topic: str, name: str) -> str:
    """The message path of a field, its index from the contract."""
    return f'{topic}.data[{FIELDS[topic].index(name)}]'


# -- the tests ------------------------------------------------------------------------------
def test_every_path_of_every_layout_resolves_in_a_recorded_bag(run, installed):
    bag = run / 'bag_0'
    results = [json.loads(line) for line in (run / 'results.jsonl').read_text().splitlines()]
    assert [r['kind'] for r in results] == ['reference', 'eval', 'remeasure']
    every = {p for layout in installed.values() for _pid, p, _l in series(layout)}
    values = resolve(bag, sorted(every))
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    for p, vs in values.items():
        assert len(vs) == counts[parse_path(p)[0]] > 0, p
        assert all(v is None or math.isfinite(v) for v in vs), p
        assert None not in vs or by_kind(parse_path(p)[1]), p
    for name, layout in installed.items():
        for _pid, p, text in series(layout):
            check_label(p, text)
        assert len(series(layout)) > 0, name
    # the numbers mean what the labels say: the loss and gains of each experiment as the
    # run recorded them, bit for bit, against the experiment id (Fig. 9's x axis), one
    # series per record kind; the bag holds one result message per record
    assert counts[RESULT_TOPIC] == len(results)
    x = result_value('experiment_id')
    for kind in KINDS:
        mine = [r for r in results if r['kind'] == kind]
        assert mine, kind
        got = points(values, result_value('loss', kind), x)
        assert got == [(r['experiment_id'], r['loss']) for r in mine if r['loss'] is not None]
        for g in GAIN_NAMES:
            got = points(values, result_value(g, kind), x)
            assert got == [(r['experiment_id'], r['gains'][g]) for r in mine]
    # Fig. 5: the position reference is the pi rad move there and back; the measured
    # position follows it; the load steps to one value
    theta_ref = values[at('/controller/internals', 'theta_ref')]
    theta_meas = values[at('/drive/state', 'theta_meas')]
    assert max(theta_ref) - min(theta_ref) == pytest.approx(math.pi, abs=1e-9)
    # (lock-step, seeded: the same every run; the measured range exceeds the move by 0.071 rad)
    assert abs(max(theta_meas) - max(theta_ref)) < 0.05 * math.pi
    assert abs(min(theta_meas) - min(theta_ref)) < 0.05 * math.pi
    load = {round(v, 12) for v in values[at('/controller/internals', 'load_cmd')]}
    assert len(load) == 3 and 0.0 in load  # off, and on against each direction of the move
    # the drive's step index counts the states (a lock-step drive may re-send one)
    steps = values[at('/drive/state', 'step_index')]
    assert steps[0] == 0.0 and {b - a for a, b in itertools.pairwise(steps)} <= {0.0, 1.0}
    assert set(values[at('/drive/state', 'command_delay')]) == {1.0}  # the simulator's d


def test_drive_signals_label_every_index_of_the_5khz_topics_once(installed):
    seen: dict[str, list[int]] = {t: [] for t in FIELDS}
    for _pid, p, _text in series(installed['drive_signals']):
        topic, steps = parse_path(p)
        seen[topic].append(steps[-1][1])
    for topic, fields in FIELDS.items():
        assert sorted(seen[topic]) == list(range(len(fields))), topic


def test_the_paper_figures_show_what_the_paper_does(installed):
    """Fig. 5: position reference and load torque; Fig. 8: position error, speed error,
    current reference; Fig. 9: loss and the speed controller's gain per experiment."""

    def names(layout: dict) -> set[str]:
        return {LABEL.match(t).group('name') for _p, _v, t in series(layout) if t}

    assert {'theta_ref', 'theta_meas', 'load_cmd'} <= names(installed['fig5_trajectory'])
    assert {'e_theta', 'e_omega', 'isq_ref'} <= names(installed['fig8_errors'])
    assert {'loss', *GAIN_NAMES} == names(installed['fig9_loss_gains'])
    for pid, cfg in installed['fig9_loss_gains']['configById'].items():
        assert cfg['xAxisVal'] == 'custom', pid  # per experiment, not over time


def result_value(key: str, kind: str | None = None) -> str:
    status = 'status[0]' if kind is None else f'status[:]{{name=="{kind}"}}'
    return f'{RESULT_TOPIC}.{status}.values[:]{{key=="{key}"}}.value'


def test_the_layouts_hold_their_paths_and_the_sim_time_axes(installed):
    """The paths of each layout (each series and custom x axis): Figs. 5 and 8 and the
    drive signals the 51 of the hand-written layouts; Fig. 9 the loss and each gain per
    record kind on the tuner's result topic and the experiment id as x (24; the
    hand-written layout had 12 on the loss topic, which does not say an experiment's kind);
    and the x axis of each Fig. 5 and Fig. 8 panel: the drive step of its topic."""
    s, i = '/drive/state', '/controller/internals'
    today = {
        'fig5_trajectory': [
            at(i, 'theta_ref'),
            at(s, 'theta_meas'),
            at(i, 'e_theta'),
            at(i, 'load_cmd'),
            at(s, 'load_torque'),
        ],
        'fig8_errors': [at(i, 'e_theta'), at(i, 'e_omega'), at(i, 'isq_ref'), at(s, 'isq')],
        'fig9_loss_gains': [
            *(result_value(k, kind) for k in ('loss', *GAIN_NAMES) for kind in KINDS),
            *[result_value('experiment_id')] * (1 + len(GAIN_NAMES)),
        ],
        'drive_signals': [f'{t}.data[{k}]' for t, fs in FIELDS.items() for k in range(len(fs))],
    }
    assert sum(len(v) for k, v in today.items() if k != 'fig9_loss_gains') == 51
    assert len(today['fig9_loss_gains']) == 24
    steps = {t: at(t, STEP_FIELDS[t]) for t in FIELDS}
    sim_time = {
        'fig5_trajectory': [steps[i], steps[s], steps[i], steps[i], steps[s]],
        'fig8_errors': [steps[i], steps[i], steps[i], steps[s]],
        'fig9_loss_gains': [],
        'drive_signals': [],
    }
    for name, layout in installed.items():
        got = [p for _pid, p, _l in series(layout)]
        assert sorted(got) == sorted(today[name] + sim_time[name]), name
        for pid in panels(layout):
            cfg = layout['configById'][pid]
            if pid.startswith('Plot!') and name != 'drive_signals':
                assert cfg['legendDisplay'] == 'top', pid  # the legend off the points
                # room above the plot for a row per series
                assert cfg['sidebarDimension'] >= 22 * len(cfg['paths']), pid
            if name == 'fig9_loss_gains':  # one colour per kind, the same in every panel
                colours = [p['color'] for p in cfg['paths']]
                assert len(set(colours)) == len(KINDS) == len(colours), pid
                assert colours == [
                    c['color'] for c in layout['configById']['Plot!fig9_loss']['paths']
                ], pid
            if cfg.get('xAxisVal') != 'custom':
                continue
            # Foxglove pairs a series' n-th message with the x path's n-th: one topic each
            x_topic = parse_path(cfg['xAxisPath']['value'])[0]
            assert {parse_path(p['value'])[0] for p in cfg['paths']} == {x_topic}, pid
    for pid in panels(installed['drive_signals']):
        cfg = installed['drive_signals']['configById'][pid]
        assert not pid.startswith('Plot!') or cfg['xAxisVal'] == 'timestamp', pid


def test_on_the_sim_time_axis_the_load_steps_0_7_s_after_the_move(run, installed):
    """Fig. 5's x axis is the drive step k; on the lock-step bag k Ts is the drive's sim
    time, and each experiment's load steps on 0.7 s after its move starts (3500 steps at
    5 kHz), as the experiment defines it; the log time between them is the computer's."""
    cfg = installed['fig5_trajectory']['configById']
    x_internals = cfg['Plot!fig5_load_commanded']['xAxisPath']['value']
    load_path = cfg['Plot!fig5_load_commanded']['paths'][0]['value']
    ref_path = cfg['Plot!fig5_position_reference']['paths'][0]['value']
    assert cfg['Plot!fig5_position_reference']['xAxisPath']['value'] == x_internals
    x_state = cfg['Plot!fig5_position_measured']['xAxisPath']['value']
    time_ns = at('/drive/state', 'time_ns')
    v = resolve(run / 'bag_0', [x_internals, load_path, ref_path, x_state, time_ns])
    ts_ns = max(v[time_ns]) / max(v[x_state])
    assert ts_ns == 200_000.0  # the simulated drive's 5 kHz
    assert v[time_ns] == [k * ts_ns for k in v[x_state]]  # sim time = k Ts on every state
    k, load, ref = v[x_internals], v[load_path], v[ref_path]
    assert k == sorted(k)
    on = [n for n in range(1, len(k)) if load[n - 1] == 0.0 and load[n] != 0.0]
    assert len(on) == 3  # the reference, the evaluation and its re-measurement
    previous = 0
    for n in on:
        first_move = next(m for m in range(previous + 1, n) if ref[m] != ref[m - 1])
        # the move starts one step before the reference first changes (experiment step 0)
        assert (k[n] - (k[first_move] - 1)) * ts_ns == pytest.approx(0.7e9, abs=1.0)
        previous = n


def test_the_file_form_and_the_sdk_form_are_one_definition():
    """Each shipped file holds the SDK's panel configs as the SDK serialises them (the
    title under Foxglove's title key), one for each panel of the SDK's layout."""

    def sdk_panels(node: dict) -> Iterator[dict]:
        if node['type'] == 'panel':
            yield node
        elif node['type'] == 'split':
            for item in node['items']:
                yield from sdk_panels(item['content'])
        else:
            assert node['type'] == 'tabs', node['type']
            for tab in node['tabs']:
                yield from sdk_panels(tab['content'])

    files = build()
    for name, layout in definitions().items():
        sdk = json.loads(render_sdk(layout))
        assert sdk['version'] == 1
        want = {p['title']: p['config'] for p in sdk_panels(sdk['content'])}
        studio = files[name]['configById']
        got = {
            c[TITLE_KEY]: {k: v for k, v in c.items() if k != TITLE_KEY}
            for pid, c in studio.items()
            if pid.startswith('Plot!')
        }
        assert got == want, name
        assert len(got) == len([p for p in studio if p.startswith('Plot!')]), name


@pytest.mark.parametrize(
    ('path', 'label', 'why'),
    [
        (f'/drive/state.data[{N_STATE}]', None, f'index {N_STATE} beyond an array of {N_STATE}'),
        (f'/drive/command.data[{N_CMD}]', None, f'index {N_CMD} beyond an array of {N_CMD}'),
        ('/drive/stat.data[2]', None, 'topic /drive/stat is not in the bag'),
        ('/drive/state.dat[2]', None, "no field 'dat'"),
        ('/controller/loss.status[0].values[:]{key=="losss"}.value', None, '0 values'),
        ('/controller/loss.status[1].key', None, 'index 1 beyond an array of 1'),
        ('/controller/loss.status[0].values[:]{name=="loss"}.value', None, "field 'name'"),
        ('/drive/state.data[2] + 1', None, 'cannot parse'),
        (
            '/tuner/result.status[:]{name=="evals"}.values[:]{key=="loss"}.value',
            None,
            'no value in any message',
        ),
        (THETA_MEAS, 'omega_meas: measured speed [rad/s]', 'labelled omega_meas'),
        (THETA_MEAS, 'theta_meas: measured position [deg]', 'theta_meas: measured'),
        (E_THETA, 'e_theta: position error [rad/s]', 'vs rad'),
    ],
)
def test_the_resolver_catches_a_wrong_path_or_label(run, path, label, why):
    with pytest.raises(AssertionError, match=re.escape(why)):
        resolve(run / 'bag_0', [path])
        check_label(path, label)


def test_committed_and_installed_layouts_are_the_generators_bytes(installed):
    share = Path(get_package_share_directory('im_tuner')) / 'foxglove'
    texts = {name: render(layout) for name, layout in build().items()}
    assert sorted(p.name for p in COMMITTED.iterdir()) == sorted(f'{n}.json' for n in texts)
    for name, text in texts.items():
        assert (COMMITTED / f'{name}.json').read_bytes() == text.encode('ascii'), name
        assert (share / f'{name}.json').read_bytes() == text.encode('ascii'), name


def test_the_cli_prints_the_installed_layouts_and_refuses_bad_input(tmp_path):
    py = [sys.executable, '-m', 'im_tuner.foxglove']
    share = Path(get_package_share_directory('im_tuner')) / 'foxglove'
    proc = subprocess.run(py, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [str(share / f'{n}.json') for n in LAYOUTS]
    # a namespaced bench: the same layouts with every topic under it
    proc = subprocess.run(
        [*py, '--out', str(tmp_path / 'ns'), '--namespace', '/bench1'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    ns = json.loads((tmp_path / 'ns' / 'fig8_errors.json').read_text())
    assert [v for _pid, v, _l in series(ns)] == [
        '/bench1' + v for _pid, v, _l in series(build()['fig8_errors'])
    ]
    # the SDK's own form
    proc = subprocess.run(
        [*py, '--out', str(tmp_path / 'sdk'), '--sdk'], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    for name, layout in definitions().items():
        assert (tmp_path / 'sdk' / f'{name}.json').read_text() == render_sdk(layout), name
    for bad, why in (
        (['--namespace', 'bench1', '--out', str(tmp_path / 'x')], 'not a ROS namespace'),
        (['--sdk'], '--sdk needs --out'),
        (['--table', '--sdk'], 'takes no other option'),
        (['--out', str(tmp_path / 'missing' / 'x')], 'does not exist'),
        (['--namespace', '/b'], 'needs --out'),
        (['--table', '--out', str(tmp_path / 'x')], 'takes no other option'),
        (['--nope'], 'unrecognized arguments'),
        (['--out', ''], 'an empty path'),
        (['--namespace', '', '--out', str(tmp_path / 'x')], '--namespace: empty'),
        (['--out', '/proc/im_tuner_layouts'], 'cannot write /proc/im_tuner_layouts'),
    ):
        before = sorted(tmp_path.rglob('*'))
        proc = subprocess.run([*py, *bad], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and proc.stdout == '', bad
        assert proc.stderr.count('\n') == 1 and why in proc.stderr, proc.stderr
        assert sorted(tmp_path.rglob('*')) == before, bad


# JavaScript's JSON.parse, as Foxglove reads an imported layout, then every panel the
# mosaic trees (the top one and each tab's) name has a config and every config is shown.
NODE_CHECK = """
const fs = require('fs');
const leaves = (n) => typeof n === 'string' ? [n] : [...leaves(n.first), ...leaves(n.second)];
for (const f of process.argv.slice(1)) {
  const l = JSON.parse(fs.readFileSync(f, 'utf8'));
  let ids = leaves(l.layout);
  for (const id of ids.filter((i) => i.startsWith('Tab!')))
    for (const t of l.configById[id].tabs) ids = ids.concat(leaves(t.layout));
  const configs = Object.keys(l.configById).sort();
  if (JSON.stringify([...ids].sort()) !== JSON.stringify(configs)) throw new Error(f);
  for (const id of ids.filter((i) => i.startsWith('Plot!')))
    for (const p of l.configById[id].paths)
      if (typeof p.value !== 'string' || !p.value.startsWith('/')) throw new Error(id);
  console.log(f.split('/').pop(), ids.length);
}
"""


def test_javascript_reads_every_installed_layout(installed):
    """Optional (needs Node.js, no network): the layouts parse as Foxglove parses them."""
    node = shutil.which('node')
    if node is None:
        pytest.skip('Node.js is not installed (optional check)')
    share = Path(get_package_share_directory('im_tuner')) / 'foxglove'
    files = [str(share / f'{n}.json') for n in LAYOUTS]
    proc = subprocess.run(
        [node, '-e', NODE_CHECK, *files], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    shown = {line.split()[0]: int(line.split()[1]) for line in proc.stdout.splitlines()}
    assert shown == {f'{n}.json': len(panels(installed[n])) for n in LAYOUTS}


def test_the_doc_carries_the_generators_index_table_and_names_every_layout():
    doc = (REPO / 'docs' / 'foxglove.md').read_text(encoding='utf-8')
    assert index_table() in doc
    for name in LAYOUTS:
        assert f'`{name}.json`' in doc, name
