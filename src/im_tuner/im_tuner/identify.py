"""The drive's mechanics from the start's experiments: J, Kt, B and Tc with uncertainties.

The controller's kernel sums, during every experiment, the rows of

    J z0 = Kt z1 - B z2 - Tc z3 - z4

(``im_controller.kernel.motion_step``: z0 the change of the encoder's mean speed between
two 20 ms blocks [rad/s], z1..z4 the triangle-weighted integrals of isq [A s], omega_meas
[rad], sign(omega_meas) [s] and the load torque [N m s]) as M = sum z z^T (5 x 5,
``LossResult.motion``).  The move gives J/Kt, the load step the scale, the two directions
B against Tc.  With a = (J, -Kt, B, Tc), M = [[A, v], [v^T, s]] and the drive file's
Gaussian prior N(a0, diag(sd0^2)) (an unobservable direction stays at the file's value):

    a = (A / s2 + P0)^-1 (-v / s2 + P0 a0),   cov(a) = INFLATION (A / s2 + P0)^-1,

s2 the residual variance of the plain least-squares fit; ``INFLATION``: neighbouring rows
share a block.  What the rows leave out (static friction, quantisation, delay) biases J
and Kt alike in every run: ``MODEL_ERROR`` is added to their sd in quadrature
(research/NOTES.md, "From the source of im_tuner/identify.py").  Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from im_controller.layout import N_MOTION
from im_drive_sim.params import MachineParams

#: covariance inflation for rows that share a block (module docstring)
INFLATION = 2.0
#: the model's own error in J and Kt, relative, added to their sd (module docstring)
MODEL_ERROR = 0.01
#: fewer rows than this identify nothing (a run of 4 unknowns needs a move and a hold)
MIN_ROWS = 20
#: prior standard deviations, relative to the file's value (J, Kt) or to the rated
#: torque (B at 1 rad/s... see _prior): wide for J, the number people know least
PRIOR_J = 1.0
PRIOR_KT = 0.3
PRIOR_TC = 0.1  # of the rated torque
PRIOR_B_SPEED = 100.0  # B's prior sd is PRIOR_TC rated torque at this speed [rad/s]


#: The identified figures, each with its standard deviation (SI): :class:`Identified`'s
#: fields, and the study's per-run columns.
FIGURES = ('J', 'J_sd', 'Kt', 'Kt_sd', 'B', 'B_sd', 'Tc', 'Tc_sd')


@dataclass(frozen=True)
class Identified:
    """The identified J [kg m^2], Kt [N m/A of measured isq], B [N m s/rad], Tc [N m] with
    one sd each, the drive file's (``*_file``), the rows and experiments used, and the rms
    residual per row [N m s]."""

    J: float
    J_sd: float
    Kt: float
    Kt_sd: float
    B: float
    B_sd: float
    Tc: float
    Tc_sd: float
    J_file: float
    Kt_file: float
    B_file: float
    Tc_file: float
    rows: int
    residual: float
    experiments: int

    def line(self) -> str:
        """One line for a log: identified +- sd (the file's)."""

        def one(name: str, v: float, sd: float, f: float, unit: str) -> str:
            return f'{name} {v:.4g} +- {sd:.2g} {unit} (file {f:.4g})'

        return (
            '; '.join(
                (
                    one('J', self.J, self.J_sd, self.J_file, 'kg m^2'),
                    one('Kt', self.Kt, self.Kt_sd, self.Kt_file, 'N m/A'),
                    one('B', self.B, self.B_sd, self.B_file, 'N m s/rad'),
                    one('Tc', self.Tc, self.Tc_sd, self.Tc_file, 'N m'),
                )
            )
            + f' [{self.rows} rows of {self.experiments} experiments]'
        )


def sum_motion(motions: Iterable[Sequence[float]]) -> tuple[np.ndarray, int, int]:
    """The experiments' sums added: (M 5 x 5 [symmetric], rows, experiments).  Sums of
    another length (a controller without them: ()) are skipped."""
    M = np.zeros((5, 5))
    rows = 0
    n = 0
    for mo in motions:
        if len(mo) != N_MOTION or not all(math.isfinite(x) for x in mo):
            continue
        rows += int(mo[0])
        j = 1
        for a in range(5):
            for b in range(a, 5):
                M[a, b] += mo[j]
                if a != b:
                    M[b, a] += mo[j]
                j += 1
        n += 1
    return M, rows, n


def _prior(m: MachineParams) -> tuple[np.ndarray, np.ndarray]:
    """a0 = (J, -Kt, B, Tc) of the file and the prior's standard deviations."""
    tc_file = float(m.coulomb_torque)
    a0 = np.array([m.J, -m.Kt, m.B, tc_file])
    sd = np.array(
        [
            PRIOR_J * m.J,
            PRIOR_KT * m.Kt,
            PRIOR_TC * m.rated_torque / PRIOR_B_SPEED,
            PRIOR_TC * m.rated_torque,
        ]
    )
    return a0, sd


def identify(motions: Iterable[Sequence[float]], machine: MachineParams) -> Identified | None:
    """J, Kt, B, Tc from the experiments' motion sums (module docstring); None when they
    hold fewer than ``MIN_ROWS`` rows or the fit is singular."""
    M, rows, n = sum_motion(motions)
    if rows < MIN_ROWS:
        return None
    A, v, s = M[:4, :4], M[:4, 4], M[4, 4]
    a0, sd0 = _prior(machine)
    P0 = np.diag(1.0 / sd0**2)
    # residual variance at the (lightly regularised) least-squares point: the data's noise
    try:
        a_ls = np.linalg.solve(A + P0 * 1e-9 * np.trace(A) / np.trace(P0), -v)
    except np.linalg.LinAlgError:
        return None
    ss = float(a_ls @ A @ a_ls + 2.0 * a_ls @ v + s)
    s2 = max(ss, 0.0) / max(rows - 4, 1)
    if not (s2 > 0.0 and math.isfinite(s2)):
        s2 = 1e-30
    H = A / s2 + P0
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    a = cov @ (-v / s2 + P0 @ a0)
    if not np.all(np.isfinite(a)):
        return None
    floor = np.array([MODEL_ERROR * a[0], MODEL_ERROR * a[1], 0.0, 0.0])
    sd = np.sqrt(np.maximum(np.diag(cov) * INFLATION, 0.0) + floor**2)
    res = float(a @ A @ a + 2.0 * a @ v + s)
    return Identified(
        J=float(a[0]),
        J_sd=float(sd[0]),
        Kt=float(-a[1]),
        Kt_sd=float(sd[1]),
        B=float(a[2]),
        B_sd=float(sd[2]),
        Tc=float(a[3]),
        Tc_sd=float(sd[3]),
        J_file=float(machine.J),
        Kt_file=float(machine.Kt),
        B_file=float(machine.B),
        Tc_file=float(a0[3]),
        rows=rows,
        residual=math.sqrt(max(res, 0.0) / rows),
        experiments=n,
    )


def same_gains(g: dict[str, float], ref: dict[str, float]) -> bool:
    """Whether gains ``g`` are ``ref`` (the start's gains through the normalised box and
    back differ in the last bits)."""
    return g.keys() == ref.keys() and all(math.isclose(g[k], ref[k], rel_tol=1e-9) for k in g)


def start_motions(records: Iterable[Any]) -> list[tuple[float, ...]]:
    """The motion sums of the completed experiments of the start (the reference's gains)
    among ``records``: what identifies the drive before the search leaves the start."""
    records = list(records)
    ref = next((r for r in records if r.kind == 'reference'), None)
    if ref is None:
        return []
    return [
        tuple(r.motion)
        for r in records
        if r.kind in ('reference', 'eval')
        and r.status == 'ok'
        and same_gains(r.gains, ref.gains)
        and r.motion is not None
    ]
