"""Numba kernels of the IM drive simulator: measurement, flux estimator, vector control,
the model's step and the published output. The plant itself (machine, shaft, RK4) is in
:mod:`.plant`; the arrays' layout (``P_*``, ``S_*``, ``F_*``) in :mod:`.model_layout`.

Free functions over ``P`` (constants, ``sim.make_param_array``), ``S`` (the whole
simulator state) and ``noise`` (``(block, NOISE_COLS)``, drawn and scaled by ``DriveSim``;
columns: ``model_layout.NOISE_COLS``): one row a step, the cursor ``S[S_NPOS]`` wrapping
at the end of the block, which the Python side refills exactly then.

Per-step kernels allocate nothing.  Step semantics: ``step_*`` advances from time k Ts to
(k+1) Ts and leaves the measurements sampled at (k+1) Ts in ``S``; ``write_out`` writes the
published fields (``STATE_FIELDS`` order, plus ``EXTRA_FIELDS`` if ``out`` is long enough).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import model_layout as L
from .model_layout import (
    N_STATE_FIELDS as N_STATE_FIELDS,
    STATE_FIELDS as STATE_FIELDS,
)  # re-exported: see below
from .plant import applied_voltage, friction_torque, plant_rk4

# STATE_FIELDS and N_STATE_FIELDS stand here too, beside ``write_out`` that fills them:
# the fused offline bench (im_tuner.offline) reads them with the kernels.

TWO_PI = 2.0 * math.pi


# ------------------------------------------------------------------- measurement
@njit(cache=True)
def _wrap(a: float) -> float:
    """Wrap an angle to [-pi, pi) (keeps sin/cos arguments small over long runs)."""
    if a >= math.pi or a < -math.pi:
        a -= TWO_PI * math.floor((a + math.pi) / TWO_PI)
    return a


@njit(cache=True)
def sample(
    S: np.ndarray,
    P: np.ndarray,
    n_ia: float,
    n_ib: float,
    n_w: float,
    n_t: float,
    advance: bool,
) -> None:
    """Sample the measurements at the current time and run the flux estimator.

    Encoder: count = floor((theta + omega n_t) * (counts/(2 pi))), theta_meas = count *
    (2 pi/counts); n_t [s] is the edge jitter (the counter latched n_t off the sample).
    Speed: raw = (count - count_prev) * (2 pi/counts)/Ts; filtered y = a y + (1 - a) raw,
    a = exp(-Ts/tau_speed); omega_meas = y + noise.
    advance=True first moves the current-model estimator from the previous sample:
    psi_hat <- a_r psi_hat + (1 - a_r) Lm isd_prev (exact ZOH), slip_int += omega_sl_prev Ts.
    Then rho = p theta_meas + slip_int, (isd, isq) = rotation by -rho of the sampled currents
    (true + noise + the current sensors' offset in alpha, beta),
    omega_sl = Lm isq/(tau_r max(psi_hat, flux_floor)).  Reduced model: ideal orientation,
    (isd, isq) = (isd_rated, isq_true) + noise.
    """
    th = S[L.S_THETA]
    if n_t != 0.0:  # encoder edge jitter: the position the counter saw
        th += S[L.S_OMEGA] * n_t
    c = math.floor(th * P[L.P_ENC_K])
    if advance:
        S[L.S_COUNT_PREV] = S[L.S_COUNT]
        S[L.S_OMEGA_RAW] = (c - S[L.S_COUNT_PREV]) * P[L.P_ENC_RES_TS]
        a = P[L.P_SPD_A]
        S[L.S_OMEGA_F] = a * S[L.S_OMEGA_F] + (1.0 - a) * S[L.S_OMEGA_RAW]
    else:
        S[L.S_COUNT_PREV] = c
    S[L.S_COUNT] = c
    S[L.S_THETA_MEAS] = c * P[L.P_ENC_RES]
    S[L.S_OMEGA_MEAS] = S[L.S_OMEGA_F] + n_w
    if P[L.P_MODEL] == 0.0:
        if advance:
            ea = P[L.P_EST_A]
            psi_prev = S[L.S_PSI_HAT]
            S[L.S_PSI_HAT] = ea * psi_prev + (1.0 - ea) * P[L.P_LM] * S[L.S_ISD]
            S[L.S_SLIP_INT] = _wrap(S[L.S_SLIP_INT] + S[L.S_OMEGA_SL] * P[L.P_TS])
        rho = P[L.P_NP] * S[L.S_THETA_MEAS] + S[L.S_SLIP_INT]
        cr = math.cos(rho)
        sr = math.sin(rho)
        ia = S[L.S_ISA] + n_ia + P[L.P_IOFF_A]
        ib = S[L.S_ISB] + n_ib + P[L.P_IOFF_B]
        S[L.S_RHO] = rho
        S[L.S_ISD] = cr * ia + sr * ib
        S[L.S_ISQ] = -sr * ia + cr * ib
        psi = S[L.S_PSI_HAT]
        if psi < P[L.P_PSI_MIN]:
            psi = P[L.P_PSI_MIN]
        S[L.S_OMEGA_SL] = P[L.P_LM] * S[L.S_ISQ] * P[L.P_INV_TAUR] / psi
    else:
        S[L.S_RHO] = P[L.P_NP] * S[L.S_THETA] + S[L.S_RED_SLIP]
        S[L.S_ISD] = P[L.P_ISD_REF] + n_ia
        S[L.S_ISQ] = S[L.S_RED_ISQ] + n_ib
        S[L.S_OMEGA_SL] = P[L.P_SLIP_K] * S[L.S_RED_ISQ]


@njit(cache=True)
def load_step_acting(
    S: np.ndarray, P: np.ndarray, tl_cmd: float, n_amp: float, u_delay: float
) -> float:
    """The load torque [N m] the load machine applies for the command ``tl_cmd`` when its
    steps vary (P[L.P_LS_ON]): on each change (edge) of the command, the new value times an
    amplitude factor 1 + n_amp (n_amp ~ N(0, std), drawn then and held until the next
    edge) acts after floor(u_delay (N + 1)) periods, U{0..N} (u_delay uniform in [0, 1),
    N = P[L.P_LS_DELAY_N]); the value acting before stays until then. An edge while one
    waits replaces it (the old acting value holds until the new one's delay ends)."""
    if tl_cmd != S[L.S_LS_CMD]:
        S[L.S_LS_CMD] = tl_cmd
        S[L.S_LS_TARGET] = tl_cmd * (1.0 + n_amp)
        S[L.S_LS_WAIT] = math.floor(u_delay * (P[L.P_LS_DELAY_N] + 1.0))
    if S[L.S_LS_WAIT] > 0.0:
        S[L.S_LS_WAIT] -= 1.0
    else:
        S[L.S_LS_ACT] = S[L.S_LS_TARGET]
    return S[L.S_LS_ACT]


@njit(cache=True)
def _load(S: np.ndarray, P: np.ndarray, tl_cmd: float, noise: np.ndarray, r: int) -> float:
    """Load torque for this step (held over the step): the load machine's step (its
    variation, ``load_step_acting``, when on), lagged, + ripple + random (noise row r)."""
    if P[L.P_LS_ON] != 0.0:
        tl_cmd = load_step_acting(S, P, tl_cmd, noise[r, L.N_AMP], noise[r, L.N_DELAY])
    n_load = noise[r, 3]
    a = P[L.P_LOAD_A]
    tlf = a * S[L.S_TLOAD_F] + (1.0 - a) * tl_cmd
    S[L.S_TLOAD_F] = tlf
    tl = tlf
    if P[L.P_RIP_AMP] != 0.0:
        tl += P[L.P_RIP_AMP] * math.sin(P[L.P_RIP_HARM] * S[L.S_THETA] + P[L.P_RIP_PHASE])
    v = P[L.P_LN_A] * S[L.S_LOAD_NOISE] + n_load
    S[L.S_LOAD_NOISE] = v
    tl += v
    S[L.S_TLOAD] = tl
    return tl


@njit(cache=True)
def _next_noise_row(S: np.ndarray, noise: np.ndarray) -> int:
    r = int(S[L.S_NPOS])
    nxt = r + 1
    if nxt >= noise.shape[0]:
        nxt = 0
    S[L.S_NPOS] = nxt
    return r


@njit(cache=True)
def _clamp_isq(S: np.ndarray, P: np.ndarray, isq_ref: float) -> float:
    """isq* [A] clamped to +-isq_max, kept in S as the last step's reference."""
    if isq_ref > P[L.P_ISQ_MAX]:
        isq_ref = P[L.P_ISQ_MAX]
    elif isq_ref < -P[L.P_ISQ_MAX]:
        isq_ref = -P[L.P_ISQ_MAX]
    S[L.S_ISQ_REF] = isq_ref
    return isq_ref


@njit(cache=True)
def _one_period_later(S: np.ndarray, i: int, j: int, a: float, b: float) -> tuple[float, float]:
    """A one-period pipeline of a pair held in ``S[i]``, ``S[j]``: keeps (a, b) for the
    next period and returns the pair kept in the last one."""
    was_a = S[i]
    was_b = S[j]
    S[i] = a
    S[j] = b
    return was_a, was_b


@njit(cache=True)
def _advance_full(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, r: int, ua: float, ub: float, tl_cmd: float
) -> None:
    """The full model over one period with the inverter commanded (ua, ub) [V]: the load
    of the period, the voltage the machine gets (the command plus the dead-time error),
    kept as the period's ``u_alpha``, ``u_beta``, the plant's RK4 step, then the sample at
    the new time (noise row r)."""
    tl = _load(S, P, tl_cmd, noise, r)
    ua, ub = applied_voltage(S, ua, ub, P)  # the inverter's dead-time error
    S[L.S_UA] = ua  # recorded as applied, not as commanded (they differ by the dead time)
    S[L.S_UB] = ub
    plant_rk4(S, ua, ub, tl, P)
    S[L.S_STEP] += 1.0
    sample(S, P, noise[r, 0], noise[r, 1], noise[r, 2], noise[r, 4], True)


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
    isq_ref = _clamp_isq(S, P, isq_ref)
    isd = S[L.S_ISD]
    isq = S[L.S_ISQ]
    psi = S[L.S_PSI_HAT]
    we = P[L.P_NP] * S[L.S_OMEGA_MEAS]
    ws = we + S[L.S_OMEGA_SL]
    sl = P[L.P_SIGLS]
    ed = P[L.P_ISD_REF] - isd
    eq = isq_ref - isq
    kp = P[L.P_KP]
    ud0 = kp * ed + S[L.S_INT_D] - ws * sl * isq - P[L.P_KR_TAUR] * psi
    uq0 = kp * eq + S[L.S_INT_Q] + ws * sl * isd + P[L.P_KR] * we * psi
    um = P[L.P_UMAX]
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
    S[L.S_VSAT] = 1.0 if (ud != ud0 or uq != uq0) else 0.0
    kit = P[L.P_KI_TS]
    if not ((ud0 > ud and ed > 0.0) or (ud0 < ud and ed < 0.0)):
        S[L.S_INT_D] += kit * ed
    if not ((uq0 > uq and eq > 0.0) or (uq0 < uq and eq < 0.0)):
        S[L.S_INT_Q] += kit * eq
    ang = S[L.S_RHO] + ws * P[L.P_TS] * (0.5 + P[L.P_DELAY])
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
    if P[L.P_DELAY] != 0.0:  # computation delay: this step applies the previous voltage
        ua, ub = _one_period_later(S, L.S_UA_NEXT, L.S_UB_NEXT, ua, ub)
    _advance_full(S, P, noise, r, ua, ub, tl_cmd)


@njit(cache=True)
def step_voltage_kernel(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, ua: float, ub: float, tl_cmd: float
) -> None:
    """One Ts step of the bare full model with given stationary-frame voltages (no control)."""
    r = _next_noise_row(S, noise)
    S[L.S_UA_NEXT] = ua
    S[L.S_UB_NEXT] = ub
    S[L.S_VSAT] = 0.0
    _advance_full(S, P, noise, r, ua, ub, tl_cmd)


@njit(cache=True)
def step_reduced(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, isq_ref: float, tl_cmd: float
) -> None:
    """One Ts step of the reduced model (ideal field orientation, k -> k+1).

    isq(t) = isq* + (isq_k - isq*) exp(-t/tau_i) exactly; the mechanics
    J domega/dt = Kt isq(t) - T_friction(omega) - T_L by RK4 with isq(t)
    evaluated exactly at the stage times 0, Ts/2, Ts.
    """
    r = _next_noise_row(S, noise)
    isq_ref = _clamp_isq(S, P, isq_ref)
    tl = _load(S, P, tl_cmd, noise, r)
    i0 = S[L.S_RED_ISQ]
    di = i0 - isq_ref
    i_0 = isq_ref + di * P[L.P_ISQ_A0]  # isq(0+): continuous unless the lag is ideal
    i_h = isq_ref + di * P[L.P_ISQ_AH]
    i_1 = isq_ref + di * P[L.P_ISQ_A]
    kt = P[L.P_KT]
    ij = P[L.P_INV_J]
    b = P[L.P_B]
    tc = P[L.P_TC]
    iwc = P[L.P_INV_WC]
    ds = P[L.P_STRIBECK]
    iws2 = P[L.P_INV_WS2]
    h = P[L.P_TS]
    h2 = 0.5 * h
    w0 = S[L.S_OMEGA]
    f = friction_torque(w0, b, tc, iwc, ds, iws2)
    k1 = (kt * i_0 - f - tl) * ij
    w2 = w0 + h2 * k1
    f = friction_torque(w2, b, tc, iwc, ds, iws2)
    k2 = (kt * i_h - f - tl) * ij
    w3 = w0 + h2 * k2
    f = friction_torque(w3, b, tc, iwc, ds, iws2)
    k3 = (kt * i_h - f - tl) * ij
    w4 = w0 + h * k3
    f = friction_torque(w4, b, tc, iwc, ds, iws2)
    k4 = (kt * i_1 - f - tl) * ij
    h6 = h / 6.0
    S[L.S_OMEGA] = w0 + h6 * (k1 + 2.0 * (k2 + k3) + k4)
    S[L.S_THETA] = S[L.S_THETA] + h6 * (w0 + 2.0 * (w2 + w3) + w4)
    # True flux angle relative to p theta: exact integral of omega_sl = SLIP_K isq(t).
    S[L.S_RED_SLIP] = _wrap(S[L.S_RED_SLIP] + P[L.P_SLIP_K] * (isq_ref * h + di * P[L.P_ISQ_INT]))
    S[L.S_RED_ISQ] = i_1
    S[L.S_STEP] += 1.0
    sample(S, P, noise[r, 0], noise[r, 1], noise[r, 2], noise[r, 4], True)


@njit(cache=True)
def step_model(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, isq_ref: float, tl_cmd: float
) -> None:
    """One step of the configured model (P[L.P_MODEL]: 0 full, 1 reduced).

    Command delay (P[L.P_CMD_DELAY]): 1, the command acts over this step (given at state k,
    it drives k -> k+1); 2, a power stage that latches its command at the period start:
    this step runs the command given one step earlier and the new one waits for the next
    step (given at state k, it drives k+1 -> k+2). Zero before the first command."""
    if P[L.P_CMD_DELAY] == 2.0:
        isq_ref, tl_cmd = _one_period_later(S, L.S_PEND_ISQ, L.S_PEND_TL, isq_ref, tl_cmd)
    if P[L.P_MODEL] == 0.0:
        step_full(S, P, noise, isq_ref, tl_cmd)
    else:
        step_reduced(S, P, noise, isq_ref, tl_cmd)


@njit(cache=True)
def clear_command(S: np.ndarray) -> None:
    """A safe stop, the watchdog: zero current and no load over the next step, at once.
    The command latched for it (delay 2) and a load step waiting in the load machine's
    command cycle (``load_step_acting``) are dropped (the load lag, ripple and random load
    are the shaft's: they stay)."""
    S[L.S_PEND_ISQ] = 0.0
    S[L.S_PEND_TL] = 0.0
    S[L.S_LS_CMD] = 0.0
    S[L.S_LS_TARGET] = 0.0
    S[L.S_LS_ACT] = 0.0
    S[L.S_LS_WAIT] = 0.0


# ----------------------------------------------------------------------- output
@njit(cache=True)
def write_out(S: np.ndarray, P: np.ndarray, out: np.ndarray) -> None:
    """Write STATE_FIELDS (and EXTRA_FIELDS if len(out) >= L.N_RUN_FIELDS) for the current time."""
    out[L.F_STEP] = S[L.S_STEP]
    out[L.F_TIME_NS] = S[L.S_STEP] * P[L.P_TS_NS]
    out[L.F_THETA_MEAS] = S[L.S_THETA_MEAS]
    out[L.F_OMEGA_MEAS] = S[L.S_OMEGA_MEAS]
    if P[L.P_MODEL] == 0.0:
        out[L.F_TORQUE] = P[L.P_KTE] * (S[L.S_PSIA] * S[L.S_ISB] - S[L.S_PSIB] * S[L.S_ISA])
        ia = S[L.S_ISA]
        ib = S[L.S_ISB]
    else:
        out[L.F_TORQUE] = P[L.P_KT] * S[L.S_RED_ISQ]
        rho = S[L.S_RHO]
        c = math.cos(rho)
        s = math.sin(rho)
        ia = c * P[L.P_ISD_REF] - s * S[L.S_RED_ISQ]
        ib = s * P[L.P_ISD_REF] + c * S[L.S_RED_ISQ]
    out[L.F_ISD] = S[L.S_ISD]
    out[L.F_ISQ] = S[L.S_ISQ]
    out[L.F_I_ALPHA] = ia
    out[L.F_I_BETA] = ib
    out[L.F_LOAD] = S[L.S_TLOAD]
    out[L.F_THETA] = S[L.S_THETA]
    out[L.F_OMEGA] = S[L.S_OMEGA]
    # the core applies each command over the period d - 1 periods after the state it was
    # given for (a node in real time overwrites this with the command it really applied)
    out[L.F_APPLIED] = max(S[L.S_STEP] - P[L.P_CMD_DELAY], -1.0)
    if out.shape[0] > L.F_CMD_DELAY:
        out[L.F_CMD_DELAY] = P[L.P_CMD_DELAY]
    if out.shape[0] >= L.N_RUN_FIELDS:
        out[L.F_COUNT] = S[L.S_COUNT]
        out[L.F_U_ALPHA] = S[L.S_UA]
        out[L.F_U_BETA] = S[L.S_UB]
        if P[L.P_MODEL] == 0.0:
            out[L.F_PSI_R] = math.sqrt(S[L.S_PSIA] * S[L.S_PSIA] + S[L.S_PSIB] * S[L.S_PSIB])
        else:
            out[L.F_PSI_R] = P[L.P_PSI_RATED]
        out[L.F_VSAT] = S[L.S_VSAT]
        out[L.F_ISQ_REF] = S[L.S_ISQ_REF]


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
    S[L.S_THETA] = theta
    S[L.S_OMEGA] = omega
    S[L.S_STEP] = step_index
    S[L.S_OMEGA_F] = omega
    sample(S, P, 0.0, 0.0, 0.0, 0.0, False)
    if P[L.P_MODEL] == 0.0 and fluxed:
        rho = P[L.P_NP] * S[L.S_THETA_MEAS]
        c = math.cos(rho)
        s = math.sin(rho)
        isd = P[L.P_ISD_REF]
        psi = P[L.P_PSI_RATED]
        S[L.S_ISA] = isd * c
        S[L.S_ISB] = isd * s
        S[L.S_PSIA] = psi * c
        S[L.S_PSIB] = psi * s
        S[L.S_PSI_HAT] = psi
        S[L.S_INT_D] = P[L.P_RSIG] * isd
        S[L.S_INT_Q] = 0.0
        ud = P[L.P_RS] * isd
        uq = P[L.P_NP] * omega * P[L.P_LS] * isd
        S[L.S_UA] = c * ud - s * uq
        S[L.S_UB] = s * ud + c * uq
        S[L.S_UA_NEXT] = S[L.S_UA]
        S[L.S_UB_NEXT] = S[L.S_UB]
        sample(S, P, 0.0, 0.0, 0.0, 0.0, False)
