"""The induction machine and its mechanics, compiled: the plant of the drive simulator.

The voltage-fed machine in the stationary frame (stator current, rotor flux) and the
shaft (inertia, viscous and Coulomb friction, load), integrated by classic RK4 over one
period Ts with the voltage and the load torque held (``plant_rk4``). Free numba functions
over ``S`` and ``P`` (layout: :mod:`.model_layout`); docs/drive-model.md.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import model_layout as L

SQRT3 = math.sqrt(3.0)


@njit(cache=True)
def friction_torque(w: float, b: float, tc: float, iwc: float, ds: float, iws2: float) -> float:
    """Friction [N m] at speed w [rad/s], viscous + Coulomb + Stribeck:

    b w + tc tanh(w iwc) + ds w exp(-(w/ws)^2), each term only if its constant is non-zero;
    the Stribeck term as MathWorks Simscape's rotational friction (``sim.stribeck_gain``,
    ``sim.friction_smoothing_speed``). b = B, tc = Tc, iwc = 1/omega_c, iws2 = 1/ws^2 as
    scalars: callers load them from P once, outside their RK4 stages.
    """
    tf = b * w
    if tc != 0.0:
        tf += tc * math.tanh(w * iwc)
    if ds != 0.0:
        tf += ds * w * math.exp(-w * w * iws2)
    return tf


@njit(cache=True)
def friction_of(w: float, P: np.ndarray) -> float:
    """``friction_torque`` at speed w [rad/s] with the constants of P [N m]."""
    return friction_torque(w, P[L.P_B], P[L.P_TC], P[L.P_INV_WC], P[L.P_STRIBECK], P[L.P_INV_WS2])


@njit(cache=True)
def rotor_resistance_scale(t: float, P: np.ndarray) -> float:
    """Rr(t)/Rr0 = 1 + alpha dT (1 - exp(-t/tau_th)) at time t [s] (1.0 when drift is off).

    The rotor warms by dT over the run with the thermal time constant tau_th;
    alpha dT = P[L.P_RR_RISE]."""
    rise = P[L.P_RR_RISE]
    if rise == 0.0:
        return 1.0
    return 1.0 + rise * (1.0 - math.exp(-t * P[L.P_INV_TTH]))


@njit(cache=True)
def deadtime_error(isa: float, isb: float, vdt: float) -> tuple[float, float]:
    """Mean voltage error [V] (alpha, beta) of the inverter's dead time over a period.

    Each leg x loses vdt against its phase current: du_x = -vdt sign(i_x), with
    i_a = i_alpha, i_b = (-i_alpha + sqrt(3) i_beta)/2, i_c = (-i_alpha - sqrt(3) i_beta)/2;
    amplitude-invariant Clarke: du_alpha = (2 du_a - du_b - du_c)/3,
    du_beta = (du_b - du_c)/sqrt(3)."""
    ib = 0.5 * (-isa + SQRT3 * isb)
    ic = 0.5 * (-isa - SQRT3 * isb)
    da = -vdt * np.sign(isa)
    db = -vdt * np.sign(ib)
    dc = -vdt * np.sign(ic)
    return (2.0 * da - db - dc) / 3.0, (db - dc) / SQRT3


@njit(cache=True)
def applied_voltage(S: np.ndarray, ua: float, ub: float, P: np.ndarray) -> tuple[float, float]:
    """The voltage [V] the machine gets for the inverter command (ua, ub): the command
    plus the dead-time error for the currents at the period start (held over the period)."""
    vdt = P[L.P_VDT]
    if vdt == 0.0:
        return ua, ub
    da, db = deadtime_error(S[L.S_ISA], S[L.S_ISB], vdt)
    return ua + da, ub + db


@njit(cache=True)
def plant_deriv(
    isa: float,
    isb: float,
    pa: float,
    pb: float,
    w: float,
    ua: float,
    ub: float,
    tl: float,
    P: np.ndarray,
    g: float,
):
    """Right-hand side of the voltage-fed IM in the stationary frame (notes' equations).

    sigma Ls di_s/dt = -R_sigma i_s + (kr/tau_r) psi_r - j kr omega_e psi_r + u_s
    dpsi_r/dt = (Lm i_s - psi_r)/tau_r + j omega_e psi_r
    J domega/dt = 1.5 p kr (psi_ra i_sb - psi_rb i_sa) - T_friction(omega) - T_L
    with the rotor resistance g Rr (g = ``rotor_resistance_scale``, 1.0 nominal).
    Returns (di_sa, di_sb, dpsi_ra, dpsi_rb, domega); dtheta/dt = omega.
    """
    kr = P[L.P_KR]
    we = P[L.P_NP] * w
    krt = P[L.P_KR_TAUR]
    rsig = P[L.P_RSIG]
    itr = P[L.P_INV_TAUR]
    if g != 1.0:  # a warm rotor: every Rr term scales (kr/tau_r, 1/tau_r, kr^2 Rr)
        krt = krt * g
        itr = itr * g
        rsig = P[L.P_RS] + (rsig - P[L.P_RS]) * g
    isl = P[L.P_INV_SIGLS]
    lm = P[L.P_LM]
    disa = (-rsig * isa + krt * pa + kr * we * pb + ua) * isl
    disb = (-rsig * isb + krt * pb - kr * we * pa + ub) * isl
    dpa = (lm * isa - pa) * itr - we * pb
    dpb = (lm * isb - pb) * itr + we * pa
    tf = friction_of(w, P)
    dw = (P[L.P_KTE] * (pa * isb - pb * isa) - tf - tl) * P[L.P_INV_J]
    return disa, disb, dpa, dpb, dw


@njit(cache=True)
def plant_rk4(S: np.ndarray, ua: float, ub: float, tl: float, P: np.ndarray) -> None:
    """One classic RK4 step of length Ts on S[0:6] with u and T_L held (ZOH); the rotor
    resistance of the period start (its drift is slow) held too."""
    h = P[L.P_TS]
    g = rotor_resistance_scale(S[L.S_STEP] * h, P)
    h2 = 0.5 * h
    x0 = S[L.S_ISA]
    x1 = S[L.S_ISB]
    x2 = S[L.S_PSIA]
    x3 = S[L.S_PSIB]
    x4 = S[L.S_OMEGA]
    a0, a1, a2, a3, a4 = plant_deriv(x0, x1, x2, x3, x4, ua, ub, tl, P, g)
    w2 = x4 + h2 * a4
    b0, b1, b2, b3, b4 = plant_deriv(
        x0 + h2 * a0, x1 + h2 * a1, x2 + h2 * a2, x3 + h2 * a3, w2, ua, ub, tl, P, g
    )
    w3 = x4 + h2 * b4
    c0, c1, c2, c3, c4 = plant_deriv(
        x0 + h2 * b0, x1 + h2 * b1, x2 + h2 * b2, x3 + h2 * b3, w3, ua, ub, tl, P, g
    )
    w4 = x4 + h * c4
    d0, d1, d2, d3, d4 = plant_deriv(
        x0 + h * c0, x1 + h * c1, x2 + h * c2, x3 + h * c3, w4, ua, ub, tl, P, g
    )
    h6 = h / 6.0
    S[L.S_ISA] = x0 + h6 * (a0 + 2.0 * (b0 + c0) + d0)
    S[L.S_ISB] = x1 + h6 * (a1 + 2.0 * (b1 + c1) + d1)
    S[L.S_PSIA] = x2 + h6 * (a2 + 2.0 * (b2 + c2) + d2)
    S[L.S_PSIB] = x3 + h6 * (a3 + 2.0 * (b3 + c3) + d3)
    S[L.S_OMEGA] = x4 + h6 * (a4 + 2.0 * (b4 + c4) + d4)
    S[L.S_THETA] = S[L.S_THETA] + h6 * (x4 + 2.0 * (w2 + w3) + w4)
