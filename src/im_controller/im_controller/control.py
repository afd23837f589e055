"""Cascaded position controller of the IM drive: the numba kernels.

The equations and the reasoning: docs/controller.md, "Discrete equations".

Arrays (float64, allocated once): parameters ``C`` (``C_*``), state ``X`` (``X_*``),
internals ``out`` (``O_*``, names in ``CONTROL_FIELDS``).  The kernel allocates nothing.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .config import ControlConfig, Gains
from .layout import CONTROL_FIELDS

C_KPW = 0  # k_pw [A s/rad]
C_KPOS = 1  # k_pos [1/s]
C_A_SM = 2  # exp(-Ts/tau_sm) (0 for tau_sm = 0)
C_G_SM = 3  # 1 - a_sm
C_A_EQ = 4
C_G_EQ = 5
C_KI_TS = 6  # k_iw Ts [A/(rad/s)]
C_INV_TS = 7  # 1/Ts [1/s]
C_ISQ_MAX = 8  # [A]
C_FF = 9  # FF_MODEL or FF_UNDELAYED
N_CPARAMS = 10

FF_MODEL = 0.0
FF_UNDELAYED = 1.0

X_SM = 0  # theta_sm [rad]
X_M = 1  # theta_m [rad]
X_I = 2  # integrator [A]
N_CSTATE = 3

# the layout (names, units) lives with the other array layouts, in a module without numba
(
    O_THETA_REF,
    O_THETA_SM,
    O_THETA_M,
    O_OMEGA_FF,
    O_OMEGA_REF,
    O_E_THETA,
    O_E_OMEGA,
    O_P,
    O_I,
    O_ISQ,
    O_SAT,
) = range(len(CONTROL_FIELDS))
N_CONTROL_FIELDS = len(CONTROL_FIELDS)


def _lag(Ts: float, tau: float) -> float:
    """Exact pole exp(-Ts/tau) of 1/(1 + s tau); tau = 0 -> 0 (pass-through)."""
    return math.exp(-Ts / tau) if tau > 0.0 else 0.0


def fill_control_params(C: np.ndarray, gains: Gains, control: ControlConfig) -> None:
    """Write the kernel parameter vector in place (inputs already validated)."""
    Ts = control.Ts
    C[C_KPW] = gains.k_pw
    C[C_KPOS] = gains.k_pos
    a = _lag(Ts, gains.tau_sm)
    C[C_A_SM] = a
    C[C_G_SM] = 1.0 - a
    a = _lag(Ts, gains.tau_eq)
    C[C_A_EQ] = a
    C[C_G_EQ] = 1.0 - a
    C[C_KI_TS] = gains.k_iw * Ts
    C[C_INV_TS] = 1.0 / Ts
    C[C_ISQ_MAX] = control.isq_max
    C[C_FF] = FF_MODEL if control.feedforward == 'model' else FF_UNDELAYED


def make_control_params(gains: Gains, control: ControlConfig) -> np.ndarray:
    """New parameter vector ``C`` for validated gains and control config."""
    C = np.zeros(N_CPARAMS)
    fill_control_params(C, gains, control)
    return C


@njit(cache=True)
def control_reset(X: np.ndarray, theta_meas: float) -> None:
    """Start holding the current position: theta_sm = theta_m = theta_meas, integrator 0."""
    X[X_SM] = theta_meas
    X[X_M] = theta_meas
    X[X_I] = 0.0


@njit(cache=True)
def control_step(
    X: np.ndarray,
    C: np.ndarray,
    theta_ref: float,
    theta_meas: float,
    omega_meas: float,
    out: np.ndarray,
) -> float:
    """One control period; returns isq* [A] and writes the internals into ``out``.

    theta_ref [rad]: raw reference theta*; theta_meas [rad], omega_meas [rad/s]: measurements
    sampled at this step.  Equations: docs/controller.md.  No allocation.
    """
    sm_old = X[X_SM]
    m_old = X[X_M]
    sm = C[C_A_SM] * sm_old + C[C_G_SM] * theta_ref
    m = C[C_A_EQ] * m_old + C[C_G_EQ] * sm
    if C[C_FF] == FF_MODEL:
        w_ff = (m - m_old) * C[C_INV_TS]
    else:
        w_ff = (sm - sm_old) * C[C_INV_TS]
    e_th = m - theta_meas
    w_ref = C[C_KPOS] * e_th + w_ff
    e_w = w_ref - omega_meas
    p = C[C_KPW] * e_w
    lim = C[C_ISQ_MAX]
    i_old = X[X_I]
    di = C[C_KI_TS] * e_w
    u_try = p + i_old + di
    # Conditional integration: freeze while the output is clamped and the error pushes
    # further into the clamp; otherwise integrate (so it unwinds at once when e_w reverses).
    if (u_try > lim and e_w > 0.0) or (u_try < -lim and e_w < 0.0):
        i_new = i_old
    else:
        i_new = i_old + di
    # The integrator alone never needs to exceed the clamp; bounding it keeps recovery
    # fast even after a gain change moved it.
    if i_new > lim:
        i_new = lim
    elif i_new < -lim:
        i_new = -lim
    u = p + i_new
    sat = 0.0
    if u > lim:
        isq = lim
        sat = 1.0
    elif u < -lim:
        isq = -lim
        sat = 1.0
    else:
        isq = u
    X[X_SM] = sm
    X[X_M] = m
    X[X_I] = i_new
    out[O_THETA_REF] = theta_ref
    out[O_THETA_SM] = sm
    out[O_THETA_M] = m
    out[O_OMEGA_FF] = w_ff
    out[O_OMEGA_REF] = w_ref
    out[O_E_THETA] = e_th
    out[O_E_OMEGA] = e_w
    out[O_P] = p
    out[O_I] = i_new
    out[O_ISQ] = isq
    out[O_SAT] = sat
    return isq
