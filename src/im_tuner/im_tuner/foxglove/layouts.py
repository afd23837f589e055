"""Foxglove layouts of a run, defined once with Foxglove's SDK (docs/foxglove.md).

Each layout is a :class:`foxglove.layouts.Layout` built from the SDK's typed classes, one
definition for the bag and the live view; every series' index is looked up by field name in
the contract modules and labelled by :func:`im_tuner.foxglove.signals.label`, so a layout
cannot drift from the contract. Pure: no rclpy. Two forms come from it: the shipped file in
Foxglove's mosaic form (:func:`to_studio`, what Studio 1.48 imports) and the SDK's own
(:func:`render_sdk`). The time axes and Fig. 9's series: docs/foxglove.md, "Time axes".

What the SDK's classes cannot express, and how it is done here:

* panel ids: the mosaic form names every panel ``Type!name``; the SDK's panels have no id,
  so :class:`Plot` (a ``PlotPanel``) carries one that the SDK's JSON leaves out;
* ``playbackConfig`` and ``userNodes`` (the mosaic form's): written by :func:`to_studio`;
* a sim-time *timestamp*: ``PlotSeries(timestamp_method='customField', timestamp_path=...)``
  wants a time field of ``sec`` and ``nsec``; the 5 kHz topics are
  ``Float64MultiArray``s whose sim time is a number (``/drive/state.data[1]``, ns), so
  sim time goes on the x axis instead, which Studio 1.48 reads as well.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import foxglove.layouts as fl

from im_controller.config import GAIN_NAMES
from im_controller.contract import INTERNALS_TOPIC
from im_drive_sim.contract import COMMAND_TOPIC, STATE_TOPIC

from ..names import RESULT_TOPIC
from .signals import (
    ARRAY_TOPICS,
    KIND_WORDS,
    LOSS_ID_KEY,
    LOSS_KEY,
    Signal,
    label,
    loss_signals,
    signal,
)

STATE = '/' + STATE_TOPIC
COMMAND = '/' + COMMAND_TOPIC
INTERNALS = '/' + INTERNALS_TOPIC
RESULT = '/' + RESULT_TOPIC

#: Fig. 9's colour of each record kind: the reference grey, the evaluations blue, their
#: re-measurements orange.
KIND_COLOURS: dict[str, str] = {
    'reference': '#7f7f7f',
    'eval': '#1f77b4',
    'remeasure': '#ff7f0e',
}

#: Foxglove's key for a panel's title in its config (``PANEL_TITLE_CONFIG_KEY``).
TITLE_KEY = 'foxglovePanelTitle'

#: The field of each array topic that counts the drive's steps k (sim time k Ts): the
#: x axis of the plots on sim time.
STEP_FIELDS: dict[str, str] = {
    STATE: 'step_index',
    COMMAND: 'answers_step',
    INTERNALS: 'step_index',
}
STEP_AXIS_LABEL = 'drive step k (sim time k Ts)'
EXPERIMENT_AXIS_LABEL = 'experiment id'

#: Height [px] of a legend above its plot: a margin and one row per series.
LEGEND_MARGIN, LEGEND_ROW = 12, 22

Series = tuple[str, ...]  # (message path, label[, colour])


@dataclass(kw_only=True)
class Plot(fl.PlotPanel):
    """An SDK Plot panel with the id the mosaic form names it by (``Plot!<panel_id>``); the
    SDK's own JSON leaves the id out."""

    panel_id: str


def array_path(topic: str, name: str, namespace: str = '') -> Series:
    """The series of field ``name`` of array topic ``topic`` (absolute, without namespace):
    ``<namespace><topic>.data[i]`` with i from the contract, and its label."""
    fields = ARRAY_TOPICS[topic][0]
    i = fields.index(name)  # ValueError for a name the contract does not have
    return f'{namespace}{topic}.data[{i}]', label(signal(topic, i))


def result_path(key: str, kind: str | None = None, namespace: str = '') -> str:
    """The message path of one value of the tuner's result message (one status, named by
    the record's kind, whose ``values`` are key/value strings), by key; ``kind``: only
    from records of that kind (a message of another kind gives no value)."""
    status = 'status[0]' if kind is None else f'status[:]{{name=="{kind}"}}'
    return f'{namespace}{RESULT}.{status}.values[:]{{key=="{key}"}}.value'


def _plot(
    panel_id: str,
    title: str,
    series: Iterable[Series],
    x_path: str | None = None,
    x_label: str | None = None,
    legend_above: bool = True,
) -> Plot:
    """A Plot panel: series (path, label[, colour]) on the receive-time axis, or against
    ``x_path`` (one point per message, with a line through them); the legend above the
    plot (``legend_above``), else floating over it (panels of several series, too small
    for a legend above)."""
    paths = [
        fl.PlotSeries(
            value=s[0],
            label=s[1],
            color=s[2] if len(s) > 2 else None,
            enabled=True,
            timestamp_method='receiveTime',
            show_line=True if x_path is not None else None,
        )
        for s in series
    ]
    config = fl.PlotConfig(
        paths=paths,
        show_x_axis_labels=True,
        show_y_axis_labels=True,
        show_legend=True,
        legend_display='top' if legend_above else 'floating',
        show_plot_values_in_legend=False,
        is_synced=True,
        x_axis_val='timestamp' if x_path is None else 'custom',
        x_axis_path=None if x_path is None else fl.PlotXAxisPath(value=x_path, enabled=True),
        x_axis_label=x_label,
        sidebar_dimension=LEGEND_MARGIN + LEGEND_ROW * len(paths) if legend_above else None,
    )
    return Plot(panel_id=panel_id, title=title, config=config)


def _split(direction: str, contents: Sequence[fl.Content]) -> fl.Content:
    """``contents`` in equal shares, side by side ('row') or one above the other
    ('column'); a single one as it is."""
    if len(contents) == 1:
        return contents[0]
    assert direction in ('row', 'column')
    return fl.SplitContainer(
        direction='row' if direction == 'row' else 'column',
        items=[fl.SplitItem(content=c) for c in contents],
    )


# ----------------------------------------------------------------------------- layouts
def _rows(pid: str, title: str, rows: list[list[tuple[str, str, str, str]]], ns: str) -> fl.Layout:
    """Rows of panels, top to bottom, each of panels side by side: one field of an array
    topic against that topic's drive step (sim time) per panel, given as (id after
    ``pid``, title after ``title``, topic, field)."""

    def panel(i: str, t: str, topic: str, name: str) -> Plot:
        x = array_path(topic, STEP_FIELDS[topic], ns)[0]
        return _plot(pid + i, title + t, [array_path(topic, name, ns)], x, STEP_AXIS_LABEL)

    return fl.Layout(
        content=_split('column', [_split('row', [panel(*p) for p in row]) for row in rows])
    )


def fig5_trajectory(ns: str = '') -> fl.Layout:
    """Paper Fig. 5 on sim time: the position reference (the raw trajectory theta*) beside
    the measured position, the position error, and the load torque commanded beside the
    load torque applied: each experiment's pi rad move and its load step 0.7 s (3500 steps
    at 5 kHz) after the move starts."""
    rows = [
        [
            ('position_reference', 'position reference theta* [rad]', INTERNALS, 'theta_ref'),
            ('position_measured', 'measured position [rad]', STATE, 'theta_meas'),
        ],
        [('error', 'position error [rad]', INTERNALS, 'e_theta')],
        [
            ('load_commanded', 'load torque commanded [N m]', INTERNALS, 'load_cmd'),
            ('load_applied', 'load torque applied [N m]', STATE, 'load_torque'),
        ],
    ]
    return _rows('fig5_', 'Fig. 5 ', rows, ns)


def fig8_errors(ns: str = '') -> fl.Layout:
    """Paper Fig. 8 on sim time: (a) position error, (b) speed error, (c) the current
    reference i*sq beside the measured q-axis current."""
    rows = [
        [('a_position_error', '(a) position error [rad]', INTERNALS, 'e_theta')],
        [('b_speed_error', '(b) speed error [rad/s]', INTERNALS, 'e_omega')],
        [
            ('c_current_reference', '(c) current reference i*sq [A]', INTERNALS, 'isq_ref'),
            ('c_current_measured', '(c) measured q-axis current [A]', STATE, 'isq'),
        ],
    ]
    return _rows('fig8', 'Fig. 8 ', rows, ns)


def fig9_loss_gains(ns: str = '') -> fl.Layout:
    """Paper Fig. 9: the loss of every experiment (a, b) and the gains it ran with (c, d:
    the paper shows k_pw; here all five), against the controller's experiment id, from
    the tuner's result topic: one series per record kind (reference, evaluations,
    re-measurements)."""
    x = result_path(LOSS_ID_KEY, namespace=ns)

    def per_experiment(pid: str, title: str, key: str) -> Plot:
        s: Signal = loss_signals()[key]  # a series per record kind: `name: kind [unit]`
        series = [
            (result_path(key, kind, ns), f'{s.name}: {words} [{s.unit}]', KIND_COLOURS[kind])
            for kind, words in KIND_WORDS.items()
        ]
        return _plot(pid, title, series, x, EXPERIMENT_AXIS_LABEL)

    loss = per_experiment('fig9_loss', 'Fig. 9 (a, b) loss per experiment', LOSS_KEY)
    gains = [
        per_experiment(f'fig9_{g}', f'Fig. 9 (c, d) {g} per experiment', g) for g in GAIN_NAMES
    ]
    return fl.Layout(
        content=fl.SplitContainer(
            direction='column',
            items=[
                fl.SplitItem(proportion=2, content=loss),
                fl.SplitItem(
                    proportion=3,
                    content=_split('column', [_split('row', gains[:3]), _split('row', gains[3:])]),
                ),
            ],
        )
    )


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


def drive_signals(ns: str = '') -> fl.Layout:
    """Every index of drive/state, drive/command and controller/internals, labelled, on
    receive time: one tab per topic, its panels in two columns."""
    tabs = []
    for topic, groups in DRIVE_PANELS.items():
        placed = [n for _s, _t, names in groups for n in names]
        fields = ARRAY_TOPICS[topic][0]
        if sorted(placed) != sorted(fields):
            raise ValueError(f'drive_signals: the panels of {topic} place {placed}, not {fields}')
        plots: list[fl.Content] = [
            _plot(
                f'{topic.strip("/").replace("/", "_")}_{slug}',
                f'{ns}{topic}: {title}',
                [array_path(topic, n, ns) for n in names],
                legend_above=False,
            )
            for slug, title, names in groups
        ]
        half = (len(plots) + 1) // 2
        if len(plots) < 4:
            content = _split('column', plots)
        else:
            content = _split(
                'row', [_split('column', plots[:half]), _split('column', plots[half:])]
            )
        tabs.append(fl.TabItem(title=f'{ns}{topic}', content=content))
    return fl.Layout(content=fl.TabContainer(tabs=tabs, selected_tab_index=0))


#: The shipped layouts: file name (without .json) -> definition (namespace -> layout).
LAYOUTS = {
    'fig5_trajectory': fig5_trajectory,
    'fig8_errors': fig8_errors,
    'fig9_loss_gains': fig9_loss_gains,
    'drive_signals': drive_signals,
}


def definitions(namespace: str = '') -> dict[str, fl.Layout]:
    """Every layout as the SDK's object, for topics under ``namespace`` ('' or
    '/bench1'): name -> layout."""
    return {name: make(namespace) for name, make in LAYOUTS.items()}


# -------------------------------------------------------------- the mosaic (file) form
def _config(panel: Plot) -> dict[str, Any]:
    """A panel's config in the mosaic form: the SDK's serialisation of its ``PlotConfig``
    (unset fields left out) with the title under Foxglove's title key."""
    cfg: dict[str, Any] = json.loads(panel.config.to_json())
    if panel.title is not None:
        cfg = {TITLE_KEY: panel.title, **cfg}
    return cfg


def to_studio(layout: fl.Layout, name: str) -> dict[str, Any]:
    """The layout in Foxglove's file form as the app exports it: ``configById`` (the same
    panel configs, one per id ``Type!name``), the containers as the ``layout`` mosaic tree (a
    split of n items becomes n - 1 binary nodes, each item's share as ``splitPercentage``),
    ``globalVariables``, ``userNodes`` and ``playbackConfig``; ``name`` names a tab
    container (``Tab!<name>``, one per layout). TypeError for a container or panel this
    form is not written for here."""
    config_by_id: dict[str, Any] = {}

    def add(pid: str, cfg: dict[str, Any]) -> str:
        if pid in config_by_id:
            raise ValueError(f'{name}: two panels are named {pid}')
        config_by_id[pid] = cfg
        return pid

    def node(content: fl.Content) -> Any:
        if isinstance(content, Plot):
            return add(f'Plot!{content.panel_id}', _config(content))
        if isinstance(content, fl.SplitContainer):
            return split(content.direction, content.items)
        if isinstance(content, fl.TabContainer):
            tabs = [{'title': t.title, 'layout': node(t.content)} for t in content.tabs]
            return add(f'Tab!{name}', {'activeTabIdx': content.selected_tab_index, 'tabs': tabs})
        raise TypeError(f'{name}: no mosaic form for {type(content).__name__}')

    def split(direction: str, items: Sequence[fl.SplitItem]) -> Any:
        if len(items) == 1:
            return node(items[0].content)
        total = sum(i.proportion for i in items)
        return {
            'first': node(items[0].content),
            'second': split(direction, items[1:]),
            'direction': direction,
            'splitPercentage': round(100.0 * items[0].proportion / total, 3),
        }

    tree = node(layout.content)
    return {
        'configById': config_by_id,
        'globalVariables': dict(layout.variables or {}),
        'userNodes': {},
        'playbackConfig': {'speed': 1.0},
        'layout': tree,
    }


def build(namespace: str = '') -> dict[str, dict[str, Any]]:
    """Every layout in the shipped file form, for topics under ``namespace``: name ->
    layout."""
    return {name: to_studio(layout, name) for name, layout in definitions(namespace).items()}


def render(layout: dict[str, Any]) -> str:
    """A layout as the file's text (2-space JSON, ASCII, a final newline): the same bytes
    for the same contract on every machine. Strict JSON: no NaN or Infinity, which
    Python writes by default and JavaScript's ``JSON.parse`` (Foxglove's) refuses."""
    return json.dumps(layout, indent=2, ensure_ascii=True, allow_nan=False) + '\n'


def render_sdk(layout: fl.Layout) -> str:
    """A layout in the SDK's own form (``Layout.to_json()``), as :func:`render` writes
    text."""
    return render(json.loads(layout.to_json()))
