"""The report's figures after the paper's Figs. 5, 8 and 9 (matplotlib, Agg)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from im_controller.config import GAIN_NAMES, GAIN_UNITS

from ..runlog.records import evaluation_name
from .table import best_so_far

if TYPE_CHECKING:
    from .load import Experiment, RunReport

# --------------------------------------------------------------------------- figures
_START_COLOR = 'black'


def _colors(n: int) -> list:
    import matplotlib

    cmap = matplotlib.colormaps['tab10']
    return [cmap(i % 10) for i in range(n)]


def _no_data(ax: Any, text: str) -> None:
    """``text`` in the middle of ``ax``: what the figure would have shown is not there."""
    ax.text(0.5, 0.5, text, ha='center', va='center', transform=ax.transAxes)


def fig5(runs: list[RunReport]):
    """Position reference and load torque of two consecutive experiments (paper Fig. 5)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5.5), layout='constrained')
    ax_p, ax_l = fig.subplots(2, 1, sharex=True)
    rr = next((r for r in runs if r.consecutive), None)
    if rr is None:
        _no_data(ax_p, 'no two consecutive experiments in the bags')
    else:
        e0 = rr.consecutive[0]
        t_ref = (e0.record.t_start_ns or 0) * 1e-9
        th0 = e0.signals['theta_ref'][0]
        for j, e in enumerate(rr.consecutive):
            t = e.t + ((e.record.t_start_ns or 0) * 1e-9 - t_ref)
            what = 'start gains' if e.record.kind == 'reference' else evaluation_name(e.record.eval)
            for ax, y, color, label, gid in (
                (ax_p, e.signals['theta_ref'] - th0, 'C0', 'position reference', 'theta_ref'),
                (ax_l, e.signals['load_cmd'], 'C3', 'load torque', 'load'),
            ):
                ax.plot(
                    t, y, color=color, lw=1.5, label=label if j == 0 else None, gid=f'{gid}:{j}'
                )
                ax.axvline(t[0], color='grey', lw=0.8, ls=':')
            ax_p.annotate(
                f'experiment {e.record.experiment_id}\n({what})',
                (t[0], 0),
                xytext=(4, -4),
                textcoords='offset points',
                va='top',
                fontsize=8,
            )
        ax_p.set_title(
            f'{rr.label}: position reference and load torque of two consecutive experiments'
        )
    ax_p.set_ylabel('position reference θ* − θ*(0) [rad]')
    ax_l.set_ylabel('load torque [N m]')
    ax_l.set_xlabel("sim time from the first experiment's start [s]")
    for ax in (ax_p, ax_l):
        ax.grid(True, alpha=0.3)
    return fig


def fig8(runs: list[RunReport]):
    """Position error, speed error, current reference: best vs start controller (Fig. 8).

    Signals of a negative move are multiplied by -1 so that every move reads as positive."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 8), layout='constrained')
    axes = fig.subplots(3, 1, sharex=True)
    panels = (
        ('e_theta', 'position error [rad]'),
        ('e_omega', 'speed error [rad/s]'),
        ('isq_ref', 'current reference i*sq [A]'),
    )
    curves: list[tuple[str, str, Experiment, Any, float, str]] = []
    starts: dict[tuple[float, ...], tuple[RunReport, Experiment]] = {}
    for rr in runs:  # runs from the same start gains share one start curve
        e = rr.reference
        if e is not None:
            starts.setdefault(tuple(e.record.gains[n] for n in GAIN_NAMES), (rr, e))
    for j, (rr, e) in enumerate(starts.values()):  # several different starts: dashes
        curves.append(
            (
                f'start:{rr.label}',
                f'start gains (loss {e.record.loss:.3f}'
                + (', aborted)' if e.record.aborted else ')')
                + ('' if len(starts) == 1 else f', {rr.label}'),
                e,
                _START_COLOR,
                1.0,
                ('-', '--', ':', '-.')[j % 4],
            )
        )
    for rr, c in zip(runs, _colors(len(runs)), strict=True):
        e = rr.best
        if e is not None:
            curves.append(
                (
                    f'best:{rr.label}',
                    f'{rr.label} best: {evaluation_name(e.record.eval)} (loss {e.record.loss:.3f})',
                    e,
                    c,
                    1.4,
                    '-',
                )
            )
    for gid, label, e, color, lw, ls in curves:
        for ax, (name, _yl) in zip(axes, panels, strict=True):
            ax.plot(
                e.t,
                e.direction * e.signals[name],
                color=color,
                lw=lw,
                ls=ls,
                label=label,
                gid=f'{name}:{gid}',
            )
    delay = (runs[0].run.controller_parameters or {}).get('trajectory.load_delay') if runs else None
    step = float(delay) if delay is not None else None
    for ax, (_n, yl) in zip(axes, panels, strict=True):
        ax.set_ylabel(yl)
        ax.grid(True, alpha=0.3)
        if step is not None:
            ax.axvline(step, color='grey', lw=0.8, ls=':')
    if step is not None:
        axes[0].annotate(
            'load torque step',
            (step, 1),
            xycoords=('data', 'axes fraction'),
            xytext=(3, -3),
            textcoords='offset points',
            va='top',
            fontsize=8,
        )
    axes[-1].set_xlabel("time from the experiment's start [s]")
    if curves:
        axes[0].legend(fontsize=8, loc='lower right')
    else:
        _no_data(axes[0], 'no experiment signals in the bags')
    flipped = any(c[2].direction < 0 for c in curves)
    fig.suptitle(
        'best controller vs start controller under the load torque step'
        + ('\n(negative moves plotted with their sign reversed)' if flipped else ''),
        fontsize=10,
    )
    return fig


def fig9_loss(runs: list[RunReport]):
    """Loss per evaluation and the best so far, each run (paper Fig. 9 a, b)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10.5, 5), layout='constrained')
    ax = fig.subplots()
    for rr, c in zip(runs, _colors(len(runs)), strict=True):
        ev = rr.evals
        if not ev:
            continue
        x = np.array([r.eval for r in ev], float)  # numbered as the summary and CSV number
        y = np.array([r.loss for r in ev], float)
        ab = np.array([bool(r.aborted) for r in ev])
        best = np.array(best_so_far(ev), dtype=float)  # None -> nan
        # the measured losses always; the aborted experiments' penalties only when there are any
        for pts, marker, ms, alpha, what, gid in (
            (~ab, '.', 4, 0.6, 'loss', 'loss'),
            (ab, 'x', 5, 0.8, 'aborted (penalised)', 'aborted'),
        ):
            if gid == 'loss' or pts.any():
                ax.plot(
                    x[pts],
                    y[pts],
                    marker,
                    ms=ms,
                    color=c,
                    alpha=alpha,
                    label=f'{rr.label}: {what}',
                    gid=f'{gid}:{rr.label}',
                )
        ax.step(
            x,
            best,
            where='post',
            color=c,
            lw=2,
            label=f'{rr.label}: best so far',
            gid=f'best:{rr.label}',
        )
        sat = rr.summary.evaluations_to_satisfactory
        if sat:
            ax.plot(
                [x[sat - 1]],  # the sat-th evaluation
                [best[sat - 1]],
                'v',
                color=c,
                ms=9,
                mec='black',
                gid=f'satisfactory:{rr.label}',
            )
    if runs:
        s0 = runs[0].summary
        sat_loss = s0.satisfactory_loss or 0.0  # (every summary the tuner writes has it)
        ax.axhline(
            sat_loss,
            color='grey',
            ls='--',
            lw=1,
            label=f'satisfactory loss {sat_loss:g}',
            gid='satisfactory',
        )
        ref = s0.reference
        if ref is not None and not ref['aborted']:
            ax.axhline(
                ref['loss'],
                color=_START_COLOR,
                ls=':',
                lw=1,
                label=f'start gains {ref["loss"]:.3f}',
                gid='start',
            )
    ax.set_yscale('log')
    ax.set_xlabel('evaluation (numbered from 0, as in the summary)')
    ax.set_ylabel('loss')
    ax.grid(True, which='both', alpha=0.3)
    # beside the axes, not over them: the aborted experiments' penalties are the top points
    ax.legend(fontsize=8, loc='upper left', bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    ax.set_title('loss per evaluation and best so far (▼: first satisfactory)')
    return fig


def fig9_gains(runs: list[RunReport]):
    """Each gain over the evaluations, each run, inside its search box (Fig. 9 c, d)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 10), layout='constrained')
    axes = fig.subplots(len(GAIN_NAMES), 1, sharex=True)
    for rr, c in zip(runs, _colors(len(runs)), strict=True):
        ev = rr.evals
        x = np.array([r.eval for r in ev], float)  # numbered as the summary numbers them
        for ax, n in zip(axes, GAIN_NAMES, strict=True):
            ax.plot(
                x,
                [r.gains[n] for r in ev],
                '.-',
                ms=3,
                lw=0.7,
                color=c,
                label=rr.label,
                gid=f'{n}:{rr.label}',
            )
    box = (runs[0].run.search_box or {}) if runs else {}
    for ax, n in zip(axes, GAIN_NAMES, strict=True):
        b = box.get(n)
        if b:
            for v in (b['lo'], b['hi']):
                ax.axhline(v, color='grey', ls='--', lw=0.8)
            ax.axhline(b['start'], color=_START_COLOR, ls=':', lw=1, gid=f'start:{n}')
        ax.set_ylabel(f'{n} [{GAIN_UNITS[n]}]')
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel('evaluation (numbered from 0, as in the summary)')
    axes[0].legend(fontsize=8)
    axes[0].set_title('gains over the evaluations (dashed: search box; dotted: start)')
    return fig


#: name -> the function that draws it, in the order of load.FIGURES
FIGURE_MAKERS: dict[str, Callable[[list[RunReport]], Any]] = {
    'fig5_trajectory': fig5,
    'fig8_best_vs_start': fig8,
    'fig9_loss': fig9_loss,
    'fig9_gains': fig9_gains,
}
DPI = 110  #: of the PNGs [dots per inch]


def make_figures(runs: list[RunReport]) -> dict[str, Any]:
    """name -> matplotlib Figure (not drawn on any screen)."""
    return {name: make(runs) for name, make in FIGURE_MAKERS.items()}


#: the figures drawn from the records alone, not the bags (``cli`` draws them in a second
#: process while the bags are read)
RECORD_FIGURES = ('fig9_loss', 'fig9_gains')


def load_matplotlib() -> None:
    """Import matplotlib's Figure and Agg canvas now (cli: before the second process is
    forked, so that the two share one import instead of paying for it twice)."""
    import matplotlib.backends.backend_agg
    import matplotlib.figure  # noqa: F401


def save_figures(
    runs: list[RunReport], out: Path, names: Iterable[str] | None = None
) -> dict[str, Path]:
    """Draw the figures ``names`` (default: all) into ``out/<name>.png``; returns
    name -> path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    paths = {}
    for name in FIGURE_MAKERS if names is None else names:
        paths[name] = out / f'{name}.png'
        fig = FIGURE_MAKERS[name](runs)
        # Straight to Agg, not savefig (which draws twice with a layout engine): same pixels
        fig.set_dpi(DPI)
        FigureCanvasAgg(fig).print_png(paths[name])
    return paths
