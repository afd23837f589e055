"""Foxglove layouts of a run's bag, built from the contracts (docs/foxglove.md).

Each layout is Foxglove's layout JSON: ``configById`` (one config per panel id ``Type!name``),
the ``layout`` mosaic tree (``{first, second, direction, splitPercentage}`` nodes, panel ids
as leaves), ``globalVariables``, ``userNodes`` and ``playbackConfig``. Every panel is a Plot
whose series are message paths (``/drive/state.data[2]``) with a ``label``; the index of
every path is looked up by field name in the contract modules (never written here), and
the label is :func:`im_tuner.foxglove.signals.label` of that field, so a layout cannot
drift from the contract. Pure: no rclpy.

Time axes: the 5 kHz topics are ``Float64MultiArray`` without a header, so their plots run
on the bag's receive time (``timestampMethod: receiveTime``, the MCAP log time). The
paper's Fig. 9 plots the loss topic against its ``experiment_id`` (Plot's ``custom`` x
axis): one point per experiment. Foxglove plots a numeric string as its number, which is
how the loss message carries its values.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from typing import Any

from im_controller.config import GAIN_NAMES
from im_controller.contract import INTERNALS_TOPIC
from im_drive_sim.contract import COMMAND_TOPIC, STATE_TOPIC

from .signals import (
    ARRAY_TOPICS,
    LOSS_ID_KEY,
    LOSS_KEY,
    LOSS_TOPIC,
    Signal,
    label,
    loss_signals,
    signal,
)

__all__ = ['LAYOUTS', 'array_path', 'build', 'loss_path', 'render']

STATE = '/' + STATE_TOPIC
COMMAND = '/' + COMMAND_TOPIC
INTERNALS = '/' + INTERNALS_TOPIC
LOSS = '/' + LOSS_TOPIC

#: Foxglove's key for a panel's title in its config (``PANEL_TITLE_CONFIG_KEY``).
TITLE_KEY = 'foxglovePanelTitle'

Series = tuple[str, str]  # (message path, label)


def array_path(topic: str, name: str, namespace: str = '') -> Series:
    """The series of field ``name`` of array topic ``topic`` (absolute, without namespace):
    ``<namespace><topic>.data[i]`` with i from the contract, and its label."""
    fields = ARRAY_TOPICS[topic][0]
    i = fields.index(name)  # ValueError for a name the contract does not have
    return f'{namespace}{topic}.data[{i}]', label(signal(topic, i))


def loss_path(key: str, namespace: str = '') -> str:
    """The message path of one value of the loss message (a DiagnosticArray with one
    status whose ``values`` are key/value strings), by key."""
    return f'{namespace}{LOSS}.status[0].values[:]{{key=="{key}"}}.value'


def _loss_series(key: str, namespace: str) -> Series:
    s: Signal = loss_signals()[key]
    return loss_path(key, namespace), label(s)


def _plot(title: str, series: Iterable[Series], x_path: str | None = None) -> dict[str, Any]:
    """A Plot panel's config: series on the receive-time axis, or against ``x_path`` (one
    point per message, with a line through them)."""
    paths = []
    for value, text in series:
        p: dict[str, Any] = {
            'value': value,
            'enabled': True,
            'timestampMethod': 'receiveTime',
            'label': text,
        }
        if x_path is not None:
            p['showLine'] = True
        paths.append(p)
    cfg: dict[str, Any] = {
        TITLE_KEY: title,
        'paths': paths,
        'showXAxisLabels': True,
        'showYAxisLabels': True,
        'showLegend': True,
        'legendDisplay': 'floating',
        'showPlotValuesInLegend': False,
        'isSynced': True,
        'xAxisVal': 'timestamp' if x_path is None else 'custom',
        'sidebarDimension': 240,
    }
    if x_path is not None:
        cfg['xAxisPath'] = {'value': x_path, 'enabled': True}
    return cfg


def _stack(ids: Sequence[Any], direction: str) -> Any:
    """A mosaic node splitting ``ids`` (panel ids or nodes) evenly along ``direction``
    ('row': side by side, 'column': one above the other)."""
    if len(ids) == 1:
        return ids[0]
    return {
        'first': ids[0],
        'second': _stack(ids[1:], direction),
        'direction': direction,
        'splitPercentage': round(100.0 / len(ids), 3),
    }


def _layout(config_by_id: dict[str, Any], tree: Any) -> dict[str, Any]:
    return {
        'configById': config_by_id,
        'globalVariables': {},
        'userNodes': {},
        'playbackConfig': {'speed': 1.0},
        'layout': tree,
    }


# ----------------------------------------------------------------------------- layouts
def _column(ns: str, plots: dict[str, tuple[str, list[tuple[str, str]]]]) -> dict[str, Any]:
    """A layout of plots one above the other: panel id -> (title, its series as (topic,
    field) of an array message, on namespace ``ns``)."""
    panels = {
        f'Plot!{pid}': _plot(title, [array_path(topic, field, ns) for topic, field in series])
        for pid, (title, series) in plots.items()
    }
    return _layout(panels, _stack(list(panels), 'column'))


def fig5_trajectory(ns: str = '') -> dict[str, Any]:
    """Paper Fig. 5: the position reference (the raw trajectory theta*) and the measured
    position, the position error and the load torque, on receive time; seek to an
    experiment to see its pi rad move and the load step 0.7 s after the move starts."""
    return _column(
        ns,
        {
            'fig5_position': (
                'Fig. 5 position: reference and measured [rad]',
                [(INTERNALS, 'theta_ref'), (STATE, 'theta_meas')],
            ),
            'fig5_error': ('Fig. 5 position error [rad]', [(INTERNALS, 'e_theta')]),
            'fig5_load': (
                'Fig. 5 load torque: commanded and applied [N m]',
                [(INTERNALS, 'load_cmd'), (STATE, 'load_torque')],
            ),
        },
    )


def fig8_errors(ns: str = '') -> dict[str, Any]:
    """Paper Fig. 8: (a) position error, (b) speed error, (c) current reference i*sq (with
    the measured q-axis current), on receive time."""
    return _column(
        ns,
        {
            'fig8a_position_error': ('Fig. 8 (a) position error [rad]', [(INTERNALS, 'e_theta')]),
            'fig8b_speed_error': ('Fig. 8 (b) speed error [rad/s]', [(INTERNALS, 'e_omega')]),
            'fig8c_current': (
                'Fig. 8 (c) current reference and measured q-axis current [A]',
                [(INTERNALS, 'isq_ref'), (STATE, 'isq')],
            ),
        },
    )


def fig9_loss_gains(ns: str = '') -> dict[str, Any]:
    """Paper Fig. 9: the loss of every experiment (a, b) and the gains it ran with (c, d:
    the paper shows k_pw; here all five), against the controller's experiment id."""
    x = loss_path(LOSS_ID_KEY, ns)
    loss = {
        'Plot!fig9_loss': _plot(
            'Fig. 9 (a, b) loss per experiment', [_loss_series(LOSS_KEY, ns)], x
        )
    }
    gains = {
        f'Plot!fig9_{g}': _plot(f'Fig. 9 (c, d) {g} per experiment', [_loss_series(g, ns)], x)
        for g in GAIN_NAMES
    }
    ids = list(gains)
    rows = _stack([_stack(ids[:3], 'row'), _stack(ids[3:], 'row')], 'column')
    tree = {
        'first': 'Plot!fig9_loss',
        'second': rows,
        'direction': 'column',
        'splitPercentage': 40.0,
    }
    return _layout({**loss, **gains}, tree)


#: The drive-signals layout's panels, by topic: (panel id suffix, title, the fields it
#: plots, by name). Quantities that read together share a panel; every field of each
#: topic appears in exactly one (:func:`drive_signals` checks it against the contract).
DRIVE_PANELS: dict[str, tuple[tuple[str, str, tuple[str, ...]], ...]] = {
    STATE: (
        ('steps', 'steps', ('step_index', 'applied_step')),
        ('time', 'sim time', ('time_ns',)),
        ('position', 'position', ('theta_meas', 'theta')),
        ('speed', 'speed', ('omega_meas', 'omega')),
        ('torque', 'torque', ('torque', 'load_torque')),
        ('dq', 'currents, rotor-flux frame', ('isd', 'isq')),
        ('alphabeta', 'currents, stationary frame', ('i_alpha', 'i_beta')),
        ('delay', 'command delay', ('command_delay',)),
    ),
    COMMAND: (
        ('step', 'state answered', ('answers_step',)),
        ('isq', 'current reference', ('isq_ref',)),
        ('load', 'load torque', ('load_torque',)),
    ),
    INTERNALS: (
        ('step', 'step answered', ('step_index',)),
        ('position', 'position references', ('theta_ref', 'theta_sm', 'theta_m')),
        ('position_error', 'position error', ('e_theta',)),
        ('speed', 'speed references', ('omega_ff', 'omega_ref')),
        ('speed_error', 'speed error', ('e_omega',)),
        (
            'current',
            'speed PI and current references',
            ('p_term', 'i_term', 'isq_ref', 'isq_cmd', 'isq_f'),
        ),
        ('load', 'load torque', ('load_cmd',)),
        ('flags', 'saturated, counted', ('saturated', 'counted')),
        ('runner', 'runner status and reason codes', ('status', 'reason')),
        ('exp_step', 'experiment step', ('exp_step',)),
        ('integrands', 'loss integrands f1, f2, f3', ('f1', 'f2', 'f3')),
        ('terms', 'running loss terms', ('term1', 'term2', 'term3')),
    ),
}


def drive_signals(ns: str = '') -> dict[str, Any]:
    """Every index of drive/state, drive/command and controller/internals, labelled: one
    tab per topic, its panels in two columns."""
    panels: dict[str, Any] = {}
    tabs = []
    for topic, groups in DRIVE_PANELS.items():
        placed = [n for _s, _t, names in groups for n in names]
        fields = ARRAY_TOPICS[topic][0]
        if sorted(placed) != sorted(fields):
            raise ValueError(f'drive_signals: the panels of {topic} place {placed}, not {fields}')
        ids = []
        for slug, title, names in groups:
            pid = f'Plot!{topic.strip("/").replace("/", "_")}_{slug}'
            panels[pid] = _plot(f'{ns}{topic}: {title}', [array_path(topic, n, ns) for n in names])
            ids.append(pid)
        half = (len(ids) + 1) // 2
        if len(ids) < 4:
            tree = _stack(ids, 'column')
        else:
            tree = _stack([_stack(ids[:half], 'column'), _stack(ids[half:], 'column')], 'row')
        tabs.append({'title': f'{ns}{topic}', 'layout': tree})
    panels['Tab!drive_signals'] = {'activeTabIdx': 0, 'tabs': tabs}
    return _layout(panels, 'Tab!drive_signals')


#: The shipped layouts: file name (without .json) -> builder (namespace -> layout).
LAYOUTS = {
    'fig5_trajectory': fig5_trajectory,
    'fig8_errors': fig8_errors,
    'fig9_loss_gains': fig9_loss_gains,
    'drive_signals': drive_signals,
}


def build(namespace: str = '') -> dict[str, dict[str, Any]]:
    """Every layout, for topics under ``namespace`` ('' or '/bench1'): name -> layout."""
    return {name: make(namespace) for name, make in LAYOUTS.items()}


def render(layout: dict[str, Any]) -> str:
    """A layout as the file's text (2-space JSON, ASCII, a final newline): the same bytes
    for the same contract on every machine. Strict JSON: no NaN or Infinity, which
    Python writes by default and JavaScript's ``JSON.parse`` (Foxglove's) refuses."""
    return json.dumps(layout, indent=2, ensure_ascii=True, allow_nan=False) + '\n'
