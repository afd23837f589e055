"""Numba kernels of the IM drive simulator: plant, vector control, measurement.

Free functions over two float64 arrays (documented in docs/drive-model.md):

* ``P`` (``N_PARAMS``): constants precomputed once from the configuration by
  ``sim.make_param_array`` so the per-step kernels do no Python-level work;
* ``S`` (``N_STATE``): the complete simulator state (plant, encoder, speed filter,
  flux estimator, PI integrators, delayed voltage, load lag, random-load state, noise
  cursor).  ``S[0:6]`` is the plant state [i_sa, i_sb, psi_ra, psi_rb, omega, theta].

and ``noise`` (``(block, 4)``): pre-scaled Gaussian samples (i_alpha, i_beta, speed,
random-load increments) generated in Python from ``Generator(PCG64(seed))``; one row is
consumed per step, the cursor ``S[S_NPOS]`` wraps at the end of the block (the Python
side refills the block exactly when it wraps).

Per-step kernels allocate nothing.  Step semantics: ``step_*`` advances from time k Ts to
(k+1) Ts and leaves the measurements sampled at (k+1) Ts in ``S``; ``write_out`` writes the
published fields (``STATE_FIELDS`` order, plus ``EXTRA_FIELDS`` if ``out`` is long enough).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import contract

TWO_PI = 2.0 * math.pi

# ---------------------------------------------------------------- parameter indices
P_TS = 0  # step [s]
P_TS_NS = 1  # step [ns] (integer valued)
P_NP = 2  # pole pairs
P_LM = 3  # magnetising inductance [H]
P_LS = 4  # stator inductance [H]
P_LR = 5  # rotor inductance [H]
P_KR = 6  # Lm/Lr
P_RSIG = 7  # R_sigma = Rs + kr^2 Rr [ohm]
P_INV_SIGLS = 8  # 1/(sigma Ls) [1/H]
P_KR_TAUR = 9  # kr/tau_r [1/s]
P_INV_TAUR = 10  # 1/tau_r [1/s]
P_KTE = 11  # 1.5 p kr (torque = KTE (psi_ra i_sb - psi_rb i_sa))
P_INV_J = 12  # 1/J
P_B = 13  # viscous friction
P_TC = 14  # Coulomb torque (0 = off)
P_INV_WC = 15  # 1/omega_c (Coulomb smoothing)
P_UMAX = 16  # voltage limit Udc/sqrt(3)
P_ISD_REF = 17  # rated flux current
P_ISQ_MAX = 18
P_KP = 19  # sigma Ls wc
P_KI_TS = 20  # R_sigma wc Ts
P_SIGLS = 21  # sigma Ls (controller nominal)
P_PSI_MIN = 22  # flux floor
P_EST_A = 23  # exp(-Ts/tau_r) (estimator)
P_ENC_K = 24  # counts/(2 pi)
P_ENC_RES = 25  # 2 pi/counts
P_ENC_RES_TS = 26  # (2 pi/counts)/Ts
P_SPD_A = 27  # exp(-Ts/tau_speed) (0 when disabled)
P_DELAY = 28  # computation delay steps (0 or 1)
P_MODEL = 29  # 0 full, 1 reduced
P_KT = 30  # reduced: torque constant at rated flux
P_PSI_RATED = 31  # Lm isd_rated
P_ISQ_A = 32  # reduced: exp(-Ts/tau_i)
P_ISQ_AH = 33  # reduced: exp(-Ts/(2 tau_i))
P_ISQ_INT = 34  # reduced: tau_i (1 - exp(-Ts/tau_i)) (exact integral weight)
P_SLIP_K = 35  # reduced: Lm/(tau_r psi_rated) (slip per A of isq)
P_LOAD_A = 36  # exp(-Ts/tau_load) (0 = ideal)
P_RIP_AMP = 37
P_RIP_HARM = 38
P_RIP_PHASE = 39
P_LN_A = 40  # exp(-Ts/tau_loadnoise)
P_RS = 41
P_RR = 42
P_J = 43
P_ISQ_A0 = 44  # reduced: isq(0+) weight, 1 for tau_i > 0, 0 for an ideal (tau_i = 0) loop
P_CMD_DELAY = 45  # command delay d (1 or 2): the command given at state k acts over k+d-1 -> k+d
N_PARAMS = 46

# -------------------------------------------------------------------- state indices
S_ISA = 0  # true stator current alpha [A]
S_ISB = 1
S_PSIA = 2  # true rotor flux alpha [Wb]
S_PSIB = 3
S_OMEGA = 4  # true mechanical speed [rad/s]
S_THETA = 5  # true mechanical angle [rad] (multi-turn)
S_STEP = 6  # step index k (integer valued)
S_COUNT = 7  # encoder count (integer valued, multi-turn)
S_COUNT_PREV = 8
S_THETA_MEAS = 9  # count * 2 pi/counts [rad]
S_OMEGA_RAW = 10  # backward difference [rad/s]
S_OMEGA_F = 11  # filtered speed (noise free)
S_OMEGA_MEAS = 12  # filtered speed + noise (what the controller sees)
S_ISD = 13  # sampled current in the estimated flux frame [A]
S_ISQ = 14
S_RHO = 15  # estimated flux angle at the sample [rad, electrical]
S_SLIP_INT = 16  # integral of omega_sl [rad] (wrapped to +-pi)
S_PSI_HAT = 17  # estimated rotor flux [Wb]
S_OMEGA_SL = 18  # slip frequency [rad/s]
S_INT_D = 19  # PI integrators [V]
S_INT_Q = 20
S_UA = 21  # voltage applied during the last step [V]
S_UB = 22
S_UA_NEXT = 23  # voltage computed, waiting (computation delay 1)
S_UB_NEXT = 24
S_VSAT = 25  # 1 if the voltage limit was active in the last step
S_ISQ_REF = 26  # clamped isq* of the last step [A]
S_TLOAD = 27  # total load torque applied during the last step [N m]
S_TLOAD_F = 28  # lagged load command
S_LOAD_NOISE = 29  # random-load state
S_NPOS = 30  # noise row cursor
S_RED_ISQ = 31  # reduced: true isq [A]
S_RED_SLIP = 32  # reduced: true flux angle minus p theta [rad]
S_PEND_ISQ = 33  # command delay 2: the command latched for the next period, isq* [A]
S_PEND_TL = 34  # ... and its load torque [N m]
N_STATE = 35

STATE_FIELDS = contract.STATE_FIELDS  # the published layout (contract.py)
EXTRA_FIELDS = ('encoder_count', 'u_alpha', 'u_beta', 'psi_r', 'voltage_saturated', 'isq_ref')
RUN_FIELDS = STATE_FIELDS + EXTRA_FIELDS
(
    F_STEP,
    F_TIME_NS,
    F_THETA_MEAS,
    F_OMEGA_MEAS,
    F_TORQUE,
    F_ISD,
    F_ISQ,
    F_I_ALPHA,
    F_I_BETA,
    F_LOAD,
    F_THETA,
    F_OMEGA,
    F_APPLIED,
    F_CMD_DELAY,
    F_COUNT,
    F_U_ALPHA,
    F_U_BETA,
    F_PSI_R,
    F_VSAT,
    F_ISQ_REF,
) = range(len(RUN_FIELDS))
N_STATE_FIELDS = len(STATE_FIELDS)
N_RUN_FIELDS = len(RUN_FIELDS)

NOISE_COLS = 4  # i_alpha, i_beta, speed, random-load increment


# ------------------------------------------------------------------------- plant
@njit(cache=True)
def friction_torque(w: float, b: float, tc: float, iwc: float) -> float:
    """Friction [N m] at speed w [rad/s]: b w + tc tanh(w iwc) (Coulomb term if tc != 0).

    b = B, tc = Tc, iwc = 1/omega_c as scalars: callers load them from P once, outside
    their RK4 stages (loads from P inside would be repeated after every store to S).
    """
    tf = b * w
    if tc != 0.0:
        tf += tc * math.tanh(w * iwc)
    return tf


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
):
    """Right-hand side of the voltage-fed IM in the stationary frame (notes' equations).

    sigma Ls di_s/dt = -R_sigma i_s + (kr/tau_r) psi_r - j kr omega_e psi_r + u_s
    dpsi_r/dt = (Lm i_s - psi_r)/tau_r + j omega_e psi_r
    J domega/dt = 1.5 p kr (psi_ra i_sb - psi_rb i_sa) - B omega - Tc tanh(omega/omega_c) - T_L
    Returns (di_sa, di_sb, dpsi_ra, dpsi_rb, domega); dtheta/dt = omega.
    """
    kr = P[P_KR]
    we = P[P_NP] * w
    krt = P[P_KR_TAUR]
    rsig = P[P_RSIG]
    isl = P[P_INV_SIGLS]
    itr = P[P_INV_TAUR]
    lm = P[P_LM]
    disa = (-rsig * isa + krt * pa + kr * we * pb + ua) * isl
    disb = (-rsig * isb + krt * pb - kr * we * pa + ub) * isl
    dpa = (lm * isa - pa) * itr - we * pb
    dpb = (lm * isb - pb) * itr + we * pa
    tf = friction_torque(w, P[P_B], P[P_TC], P[P_INV_WC])
    dw = (P[P_KTE] * (pa * isb - pb * isa) - tf - tl) * P[P_INV_J]
    return disa, disb, dpa, dpb, dw


@njit(cache=True)
def plant_rk4(S: np.ndarray, ua: float, ub: float, tl: float, P: np.ndarray) -> None:
    """One classic RK4 step of length Ts on S[0:6] with u and T_L held (ZOH)."""
    h = P[P_TS]
    h2 = 0.5 * h
    x0 = S[S_ISA]
    x1 = S[S_ISB]
    x2 = S[S_PSIA]
    x3 = S[S_PSIB]
    x4 = S[S_OMEGA]
    a0, a1, a2, a3, a4 = plant_deriv(x0, x1, x2, x3, x4, ua, ub, tl, P)
    w2 = x4 + h2 * a4
    b0, b1, b2, b3, b4 = plant_deriv(
        x0 + h2 * a0, x1 + h2 * a1, x2 + h2 * a2, x3 + h2 * a3, w2, ua, ub, tl, P
    )
    w3 = x4 + h2 * b4
    c0, c1, c2, c3, c4 = plant_deriv(
        x0 + h2 * b0, x1 + h2 * b1, x2 + h2 * b2, x3 + h2 * b3, w3, ua, ub, tl, P
    )
    w4 = x4 + h * c4
    d0, d1, d2, d3, d4 = plant_deriv(
        x0 + h * c0, x1 + h * c1, x2 + h * c2, x3 + h * c3, w4, ua, ub, tl, P
    )
    h6 = h / 6.0
    S[S_ISA] = x0 + h6 * (a0 + 2.0 * (b0 + c0) + d0)
    S[S_ISB] = x1 + h6 * (a1 + 2.0 * (b1 + c1) + d1)
    S[S_PSIA] = x2 + h6 * (a2 + 2.0 * (b2 + c2) + d2)
    S[S_PSIB] = x3 + h6 * (a3 + 2.0 * (b3 + c3) + d3)
    S[S_OMEGA] = x4 + h6 * (a4 + 2.0 * (b4 + c4) + d4)
    S[S_THETA] = S[S_THETA] + h6 * (x4 + 2.0 * (w2 + w3) + w4)


@njit(cache=True)
def plant_powers(
    isa: float,
    isb: float,
    pa: float,
    pb: float,
    w: float,
    ua: float,
    ub: float,
    tl: float,
    P: np.ndarray,
):
    """Power terms [W] for the energy balance (amplitude-invariant: factor 1.5).

    Returns (p_in = 1.5 u.i_s, p_cu_s = 1.5 Rs |i_s|^2, p_cu_r = 1.5 Rr |i_r|^2,
    p_friction = (B omega + Tc tanh(omega/omega_c)) omega, p_load = T_L omega)
    with the rotor current i_r = (psi_r - Lm i_s)/Lr.
    """
    ira = (pa - P[P_LM] * isa) / P[P_LR]
    irb = (pb - P[P_LM] * isb) / P[P_LR]
    tf = friction_torque(w, P[P_B], P[P_TC], P[P_INV_WC])
    return (
        1.5 * (ua * isa + ub * isb),
        1.5 * P[P_RS] * (isa * isa + isb * isb),
        1.5 * P[P_RR] * (ira * ira + irb * irb),
        tf * w,
        tl * w,
    )


@njit(cache=True)
def stored_energy(x: np.ndarray, P: np.ndarray):
    """(magnetic, kinetic) energy [J] of plant state x = [i_sa, i_sb, psi_ra, psi_rb, omega, ...].

    W_mag = 1.5 * 0.5 (Ls |i_s|^2 + 2 Lm i_s.i_r + Lr |i_r|^2),  W_kin = 0.5 J omega^2.
    """
    lm = P[P_LM]
    ira = (x[2] - lm * x[0]) / P[P_LR]
    irb = (x[3] - lm * x[1]) / P[P_LR]
    wm = 0.75 * (
        P[P_LS] * (x[0] * x[0] + x[1] * x[1])
        + 2.0 * lm * (x[0] * ira + x[1] * irb)
        + P[P_LR] * (ira * ira + irb * irb)
    )
    return wm, 0.5 * P[P_J] * x[4] * x[4]


@njit(cache=True)
def plant_rk4_energy(
    x: np.ndarray, ua: float, ub: float, tl: float, P: np.ndarray, e: np.ndarray
) -> None:
    """RK4 step of the plant augmented with the energy integrals (diagnostics, tests).

    x[0:6] is advanced exactly as ``plant_rk4`` does (the augmented components do not feed
    back), e[0:5] += RK4 quadrature of ``plant_powers`` over the step.
    """
    h = P[P_TS]
    h2 = 0.5 * h
    x0, x1, x2, x3, x4 = x[0], x[1], x[2], x[3], x[4]
    a0, a1, a2, a3, a4 = plant_deriv(x0, x1, x2, x3, x4, ua, ub, tl, P)
    pa_ = plant_powers(x0, x1, x2, x3, x4, ua, ub, tl, P)
    y0, y1, y2, y3, y4 = x0 + h2 * a0, x1 + h2 * a1, x2 + h2 * a2, x3 + h2 * a3, x4 + h2 * a4
    b0, b1, b2, b3, b4 = plant_deriv(y0, y1, y2, y3, y4, ua, ub, tl, P)
    pb_ = plant_powers(y0, y1, y2, y3, y4, ua, ub, tl, P)
    w2 = y4
    y0, y1, y2, y3, y4 = x0 + h2 * b0, x1 + h2 * b1, x2 + h2 * b2, x3 + h2 * b3, x4 + h2 * b4
    c0, c1, c2, c3, c4 = plant_deriv(y0, y1, y2, y3, y4, ua, ub, tl, P)
    pc_ = plant_powers(y0, y1, y2, y3, y4, ua, ub, tl, P)
    w3 = y4
    y0, y1, y2, y3, y4 = x0 + h * c0, x1 + h * c1, x2 + h * c2, x3 + h * c3, x4 + h * c4
    d0, d1, d2, d3, d4 = plant_deriv(y0, y1, y2, y3, y4, ua, ub, tl, P)
    pd_ = plant_powers(y0, y1, y2, y3, y4, ua, ub, tl, P)
    w4 = y4
    h6 = h / 6.0
    x[0] = x0 + h6 * (a0 + 2.0 * (b0 + c0) + d0)
    x[1] = x1 + h6 * (a1 + 2.0 * (b1 + c1) + d1)
    x[2] = x2 + h6 * (a2 + 2.0 * (b2 + c2) + d2)
    x[3] = x3 + h6 * (a3 + 2.0 * (b3 + c3) + d3)
    x[4] = x4 + h6 * (a4 + 2.0 * (b4 + c4) + d4)
    x[5] = x[5] + h6 * (x4 + 2.0 * (w2 + w3) + w4)
    for j in range(5):
        e[j] += h6 * (pa_[j] + 2.0 * (pb_[j] + pc_[j]) + pd_[j])


# ------------------------------------------------------------------- measurement
@njit(cache=True)
def _wrap(a: float) -> float:
    """Wrap an angle to [-pi, pi) (keeps sin/cos arguments small over long runs)."""
    if a >= math.pi or a < -math.pi:
        a -= TWO_PI * math.floor((a + math.pi) / TWO_PI)
    return a


@njit(cache=True)
def sample(
    S: np.ndarray, P: np.ndarray, n_ia: float, n_ib: float, n_w: float, advance: bool
) -> None:
    """Sample the measurements at the current time and run the flux estimator.

    Encoder: count = floor(theta * (counts/(2 pi))), theta_meas = count * (2 pi/counts).
    Speed: raw = (count - count_prev) * (2 pi/counts)/Ts; filtered y = a y + (1 - a) raw,
    a = exp(-Ts/tau_speed); omega_meas = y + noise.
    advance=True first moves the current-model estimator from the previous sample:
    psi_hat <- a_r psi_hat + (1 - a_r) Lm isd_prev (exact ZOH), slip_int += omega_sl_prev Ts.
    Then rho = p theta_meas + slip_int, (isd, isq) = rotation of the sampled currents by -rho,
    omega_sl = Lm isq/(tau_r max(psi_hat, flux_floor)).  Reduced model: ideal orientation,
    (isd, isq) = (isd_rated, isq_true) + noise.
    """
    c = math.floor(S[S_THETA] * P[P_ENC_K])
    if advance:
        S[S_COUNT_PREV] = S[S_COUNT]
        S[S_OMEGA_RAW] = (c - S[S_COUNT_PREV]) * P[P_ENC_RES_TS]
        a = P[P_SPD_A]
        S[S_OMEGA_F] = a * S[S_OMEGA_F] + (1.0 - a) * S[S_OMEGA_RAW]
    else:
        S[S_COUNT_PREV] = c
    S[S_COUNT] = c
    S[S_THETA_MEAS] = c * P[P_ENC_RES]
    S[S_OMEGA_MEAS] = S[S_OMEGA_F] + n_w
    if P[P_MODEL] == 0.0:
        if advance:
            ea = P[P_EST_A]
            psi_prev = S[S_PSI_HAT]
            S[S_PSI_HAT] = ea * psi_prev + (1.0 - ea) * P[P_LM] * S[S_ISD]
            S[S_SLIP_INT] = _wrap(S[S_SLIP_INT] + S[S_OMEGA_SL] * P[P_TS])
        rho = P[P_NP] * S[S_THETA_MEAS] + S[S_SLIP_INT]
        cr = math.cos(rho)
        sr = math.sin(rho)
        ia = S[S_ISA] + n_ia
        ib = S[S_ISB] + n_ib
        S[S_RHO] = rho
        S[S_ISD] = cr * ia + sr * ib
        S[S_ISQ] = -sr * ia + cr * ib
        psi = S[S_PSI_HAT]
        if psi < P[P_PSI_MIN]:
            psi = P[P_PSI_MIN]
        S[S_OMEGA_SL] = P[P_LM] * S[S_ISQ] * P[P_INV_TAUR] / psi
    else:
        S[S_RHO] = P[P_NP] * S[S_THETA] + S[S_RED_SLIP]
        S[S_ISD] = P[P_ISD_REF] + n_ia
        S[S_ISQ] = S[S_RED_ISQ] + n_ib
        S[S_OMEGA_SL] = P[P_SLIP_K] * S[S_RED_ISQ]


@njit(cache=True)
def _load(S: np.ndarray, P: np.ndarray, tl_cmd: float, n_load: float) -> float:
    """Load torque for this step (held over the step): lagged command + ripple + random."""
    a = P[P_LOAD_A]
    tlf = a * S[S_TLOAD_F] + (1.0 - a) * tl_cmd
    S[S_TLOAD_F] = tlf
    tl = tlf
    if P[P_RIP_AMP] != 0.0:
        tl += P[P_RIP_AMP] * math.sin(P[P_RIP_HARM] * S[S_THETA] + P[P_RIP_PHASE])
    v = P[P_LN_A] * S[S_LOAD_NOISE] + n_load
    S[S_LOAD_NOISE] = v
    tl += v
    S[S_TLOAD] = tl
    return tl


@njit(cache=True)
def _next_noise_row(S: np.ndarray, noise: np.ndarray) -> int:
    r = int(S[S_NPOS])
    nxt = r + 1
    if nxt >= noise.shape[0]:
        nxt = 0
    S[S_NPOS] = nxt
    return r


# ---------------------------------------------------------------------- control
@njit(cache=True)
def current_control(S: np.ndarray, P: np.ndarray, isq_ref: float):
    """dq PI current control in the estimated rotor-flux frame; returns (u_alpha, u_beta).

    u_d = kp e_d + I_d - omega_s sigma Ls isq - (kr/tau_r) psi_hat
    u_q = kp e_q + I_q + omega_s sigma Ls isd + kr omega_e psi_hat
    with omega_e = p omega_meas, omega_s = omega_e + omega_sl, kp = sigma Ls wc,
    ki = R_sigma wc.  Circular limit |u| <= Udc/sqrt(3) with d-axis priority; anti-windup by
    conditional integration (an axis' integrator is frozen while its output is clipped and
    its error pushes further into the limit).  The voltage is rotated by
    rho + omega_s Ts (0.5 + delay) (the mean flux angle while it is applied).
    """
    if isq_ref > P[P_ISQ_MAX]:
        isq_ref = P[P_ISQ_MAX]
    elif isq_ref < -P[P_ISQ_MAX]:
        isq_ref = -P[P_ISQ_MAX]
    S[S_ISQ_REF] = isq_ref
    isd = S[S_ISD]
    isq = S[S_ISQ]
    psi = S[S_PSI_HAT]
    we = P[P_NP] * S[S_OMEGA_MEAS]
    ws = we + S[S_OMEGA_SL]
    sl = P[P_SIGLS]
    ed = P[P_ISD_REF] - isd
    eq = isq_ref - isq
    kp = P[P_KP]
    ud0 = kp * ed + S[S_INT_D] - ws * sl * isq - P[P_KR_TAUR] * psi
    uq0 = kp * eq + S[S_INT_Q] + ws * sl * isd + P[P_KR] * we * psi
    um = P[P_UMAX]
    ud = ud0
    if ud > um:
        ud = um
    elif ud < -um:
        ud = -um
    uql = math.sqrt(um * um - ud * ud)
    uq = uq0
    if uq > uql:
        uq = uql
    elif uq < -uql:
        uq = -uql
    S[S_VSAT] = 1.0 if (ud != ud0 or uq != uq0) else 0.0
    kit = P[P_KI_TS]
    if not ((ud0 > ud and ed > 0.0) or (ud0 < ud and ed < 0.0)):
        S[S_INT_D] += kit * ed
    if not ((uq0 > uq and eq > 0.0) or (uq0 < uq and eq < 0.0)):
        S[S_INT_Q] += kit * eq
    ang = S[S_RHO] + ws * P[P_TS] * (0.5 + P[P_DELAY])
    ca = math.cos(ang)
    sa = math.sin(ang)
    return ca * ud - sa * uq, sa * ud + ca * uq


@njit(cache=True)
def step_full(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, isq_ref: float, tl_cmd: float
) -> None:
    """One Ts step of the full model with vector control (k -> k+1)."""
    r = _next_noise_row(S, noise)
    ua, ub = current_control(S, P, isq_ref)
    if P[P_DELAY] != 0.0:
        ua_now = S[S_UA_NEXT]
        ub_now = S[S_UB_NEXT]
        S[S_UA_NEXT] = ua
        S[S_UB_NEXT] = ub
        ua = ua_now
        ub = ub_now
    S[S_UA] = ua
    S[S_UB] = ub
    tl = _load(S, P, tl_cmd, noise[r, 3])
    plant_rk4(S, ua, ub, tl, P)
    S[S_STEP] += 1.0
    sample(S, P, noise[r, 0], noise[r, 1], noise[r, 2], True)


@njit(cache=True)
def step_voltage_kernel(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, ua: float, ub: float, tl_cmd: float
) -> None:
    """One Ts step of the bare full model with given stationary-frame voltages (no control)."""
    r = _next_noise_row(S, noise)
    S[S_UA] = ua
    S[S_UB] = ub
    S[S_UA_NEXT] = ua
    S[S_UB_NEXT] = ub
    S[S_VSAT] = 0.0
    tl = _load(S, P, tl_cmd, noise[r, 3])
    plant_rk4(S, ua, ub, tl, P)
    S[S_STEP] += 1.0
    sample(S, P, noise[r, 0], noise[r, 1], noise[r, 2], True)


@njit(cache=True)
def step_reduced(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, isq_ref: float, tl_cmd: float
) -> None:
    """One Ts step of the reduced model (ideal field orientation, k -> k+1).

    isq(t) = isq* + (isq_k - isq*) exp(-t/tau_i) exactly; the mechanics
    J domega/dt = Kt isq(t) - B omega - Tc tanh(omega/omega_c) - T_L by RK4 with isq(t)
    evaluated exactly at the stage times 0, Ts/2, Ts.
    """
    r = _next_noise_row(S, noise)
    if isq_ref > P[P_ISQ_MAX]:
        isq_ref = P[P_ISQ_MAX]
    elif isq_ref < -P[P_ISQ_MAX]:
        isq_ref = -P[P_ISQ_MAX]
    S[S_ISQ_REF] = isq_ref
    tl = _load(S, P, tl_cmd, noise[r, 3])
    i0 = S[S_RED_ISQ]
    di = i0 - isq_ref
    i_0 = isq_ref + di * P[P_ISQ_A0]  # isq(0+): continuous unless the lag is ideal
    i_h = isq_ref + di * P[P_ISQ_AH]
    i_1 = isq_ref + di * P[P_ISQ_A]
    kt = P[P_KT]
    ij = P[P_INV_J]
    b = P[P_B]
    tc = P[P_TC]
    iwc = P[P_INV_WC]
    h = P[P_TS]
    h2 = 0.5 * h
    w0 = S[S_OMEGA]
    f = friction_torque(w0, b, tc, iwc)
    k1 = (kt * i_0 - f - tl) * ij
    w2 = w0 + h2 * k1
    f = friction_torque(w2, b, tc, iwc)
    k2 = (kt * i_h - f - tl) * ij
    w3 = w0 + h2 * k2
    f = friction_torque(w3, b, tc, iwc)
    k3 = (kt * i_h - f - tl) * ij
    w4 = w0 + h * k3
    f = friction_torque(w4, b, tc, iwc)
    k4 = (kt * i_1 - f - tl) * ij
    h6 = h / 6.0
    S[S_OMEGA] = w0 + h6 * (k1 + 2.0 * (k2 + k3) + k4)
    S[S_THETA] = S[S_THETA] + h6 * (w0 + 2.0 * (w2 + w3) + w4)
    # True flux angle relative to p theta: exact integral of omega_sl = SLIP_K isq(t).
    S[S_RED_SLIP] = _wrap(S[S_RED_SLIP] + P[P_SLIP_K] * (isq_ref * h + di * P[P_ISQ_INT]))
    S[S_RED_ISQ] = i_1
    S[S_STEP] += 1.0
    sample(S, P, noise[r, 0], noise[r, 1], noise[r, 2], True)


@njit(cache=True)
def step_model(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, isq_ref: float, tl_cmd: float
) -> None:
    """One step of the configured model (P[P_MODEL]: 0 full, 1 reduced).

    Command delay (P[P_CMD_DELAY]): 1, the command acts over this step (given at state k,
    it drives k -> k+1); 2, a power stage that latches its command at the period start:
    this step runs the command given one step earlier and the new one waits for the next
    step (given at state k, it drives k+1 -> k+2). Zero before the first command."""
    if P[P_CMD_DELAY] == 2.0:
        latched_isq = S[S_PEND_ISQ]
        latched_tl = S[S_PEND_TL]
        S[S_PEND_ISQ] = isq_ref
        S[S_PEND_TL] = tl_cmd
        isq_ref = latched_isq
        tl_cmd = latched_tl
    if P[P_MODEL] == 0.0:
        step_full(S, P, noise, isq_ref, tl_cmd)
    else:
        step_reduced(S, P, noise, isq_ref, tl_cmd)


# ----------------------------------------------------------------------- output
@njit(cache=True)
def write_out(S: np.ndarray, P: np.ndarray, out: np.ndarray) -> None:
    """Write STATE_FIELDS (and EXTRA_FIELDS if len(out) >= N_RUN_FIELDS) for the current time."""
    out[F_STEP] = S[S_STEP]
    out[F_TIME_NS] = S[S_STEP] * P[P_TS_NS]
    out[F_THETA_MEAS] = S[S_THETA_MEAS]
    out[F_OMEGA_MEAS] = S[S_OMEGA_MEAS]
    if P[P_MODEL] == 0.0:
        out[F_TORQUE] = P[P_KTE] * (S[S_PSIA] * S[S_ISB] - S[S_PSIB] * S[S_ISA])
        ia = S[S_ISA]
        ib = S[S_ISB]
    else:
        out[F_TORQUE] = P[P_KT] * S[S_RED_ISQ]
        rho = S[S_RHO]
        c = math.cos(rho)
        s = math.sin(rho)
        ia = c * P[P_ISD_REF] - s * S[S_RED_ISQ]
        ib = s * P[P_ISD_REF] + c * S[S_RED_ISQ]
    out[F_ISD] = S[S_ISD]
    out[F_ISQ] = S[S_ISQ]
    out[F_I_ALPHA] = ia
    out[F_I_BETA] = ib
    out[F_LOAD] = S[S_TLOAD]
    out[F_THETA] = S[S_THETA]
    out[F_OMEGA] = S[S_OMEGA]
    # the core applies each command over the period d - 1 periods after the state it was
    # given for (a node in real time overwrites this with the command it really applied)
    out[F_APPLIED] = max(S[S_STEP] - P[P_CMD_DELAY], -1.0)
    if out.shape[0] > F_CMD_DELAY:
        out[F_CMD_DELAY] = P[P_CMD_DELAY]
    if out.shape[0] >= N_RUN_FIELDS:
        out[F_COUNT] = S[S_COUNT]
        out[F_U_ALPHA] = S[S_UA]
        out[F_U_BETA] = S[S_UB]
        if P[P_MODEL] == 0.0:
            out[F_PSI_R] = math.sqrt(S[S_PSIA] * S[S_PSIA] + S[S_PSIB] * S[S_PSIB])
        else:
            out[F_PSI_R] = P[P_PSI_RATED]
        out[F_VSAT] = S[S_VSAT]
        out[F_ISQ_REF] = S[S_ISQ_REF]


@njit(cache=True)
def step_into_kernel(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, isq_ref: float, tl_cmd: float, out: np.ndarray
) -> None:
    """Fast path: one step, then the published fields at the new time into ``out``."""
    step_model(S, P, noise, isq_ref, tl_cmd)
    write_out(S, P, out)


@njit(cache=True)
def run_batch(
    S: np.ndarray,
    P: np.ndarray,
    noise: np.ndarray,
    isq_ref: np.ndarray,
    tl: np.ndarray,
    out: np.ndarray,
    start: int,
    n: int,
    record: bool,
) -> None:
    """Steps k = start .. start+n-1 with isq_ref[k], tl[k]; row k of ``out`` = state after step k.

    ``record=False`` skips the output (benchmarks); ``out`` may then be any 2-D array.
    """
    for k in range(start, start + n):
        step_model(S, P, noise, isq_ref[k], tl[k])
        if record:
            write_out(S, P, out[k])


@njit(cache=True)
def run_voltage_batch(
    S: np.ndarray,
    P: np.ndarray,
    noise: np.ndarray,
    ua: np.ndarray,
    ub: np.ndarray,
    tl: np.ndarray,
    out: np.ndarray,
    start: int,
    n: int,
) -> None:
    """Bare full model over given stationary voltages; row k of ``out`` = state after step k."""
    for k in range(start, start + n):
        step_voltage_kernel(S, P, noise, ua[k], ub[k], tl[k])
        write_out(S, P, out[k])


@njit(cache=True)
def reset_kernel(
    S: np.ndarray, P: np.ndarray, theta: float, omega: float, fluxed: bool, step_index: float
) -> None:
    """Set the initial state at time step_index*Ts (see ``DriveSim.reset``).

    fluxed (full model): rotor flux Lm isd_rated and stator current isd_rated aligned with
    the estimator angle rho0 = p theta_meas (exact orientation), PI integrators and the
    applied voltage at their steady-state values (I_d = R_sigma isd, I_q = 0,
    u_dq = (Rs isd, omega_e Ls isd)).  Speed filter starts at omega (noise free sample).
    """
    for j in range(S.shape[0]):
        S[j] = 0.0
    S[S_THETA] = theta
    S[S_OMEGA] = omega
    S[S_STEP] = step_index
    S[S_OMEGA_F] = omega
    sample(S, P, 0.0, 0.0, 0.0, False)
    if P[P_MODEL] == 0.0 and fluxed:
        rho = P[P_NP] * S[S_THETA_MEAS]
        c = math.cos(rho)
        s = math.sin(rho)
        isd = P[P_ISD_REF]
        psi = P[P_PSI_RATED]
        S[S_ISA] = isd * c
        S[S_ISB] = isd * s
        S[S_PSIA] = psi * c
        S[S_PSIB] = psi * s
        S[S_PSI_HAT] = psi
        S[S_INT_D] = P[P_RSIG] * isd
        S[S_INT_Q] = 0.0
        ud = P[P_RS] * isd
        uq = P[P_NP] * omega * P[P_LS] * isd
        S[S_UA] = c * ud - s * uq
        S[S_UB] = s * ud + c * uq
        S[S_UA_NEXT] = S[S_UA]
        S[S_UB_NEXT] = S[S_UB]
        sample(S, P, 0.0, 0.0, 0.0, False)
