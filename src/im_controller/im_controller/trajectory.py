"""The experiment's reference: the minimum-time rest-to-rest move (trapezoid, or
triangle if v_max is not reached) and the kernel parameter vector Q built from a config."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import layout as L
from .config import ExperimentConfig, trajectory_times, validate_experiment_config


@njit(cache=True)
def traj_pos(t: float, Q: np.ndarray) -> float:
    """Distance travelled s(t) [rad] of the move (0 before, exactly ``distance`` after)."""
    a = Q[L.Q_AMAX]
    if t <= 0.0:
        return 0.0
    if t < Q[L.Q_TACC]:
        return 0.5 * a * t * t
    if t < Q[L.Q_TDEC]:
        ta = Q[L.Q_TACC]
        return 0.5 * a * ta * ta + Q[L.Q_VPEAK] * (t - ta)
    if t < Q[L.Q_TEND]:
        r = Q[L.Q_TEND] - t
        return Q[L.Q_DIST] - 0.5 * a * r * r
    return Q[L.Q_DIST]


@njit(cache=True)
def _traj_arrays(
    t: np.ndarray, Q: np.ndarray, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray
) -> None:
    a = Q[L.Q_AMAX]
    for i in range(t.shape[0]):
        ti = t[i]
        pos[i] = traj_pos(ti, Q)
        if ti <= 0.0 or ti >= Q[L.Q_TEND]:
            vel[i] = 0.0
            acc[i] = 0.0
        elif ti < Q[L.Q_TACC]:
            vel[i] = a * ti
            acc[i] = a
        elif ti < Q[L.Q_TDEC]:
            vel[i] = Q[L.Q_VPEAK]
            acc[i] = 0.0
        else:
            vel[i] = a * (Q[L.Q_TEND] - ti)
            acc[i] = -a


def make_experiment_params(cfg: ExperimentConfig) -> np.ndarray:
    """Kernel parameter vector ``Q`` from a validated config."""
    c, lo, tr, sf = cfg.control, cfg.loss, cfg.trajectory, cfg.safety
    Q = np.zeros(L.N_QPARAMS)
    Q[L.Q_TS] = c.Ts
    Q[L.Q_TS_NS] = float(round(c.Ts * 1e9))
    Q[L.Q_N] = float(round(tr.duration / c.Ts))
    Q[L.Q_SETTLE_N] = float(round(tr.settle / c.Ts))
    # ceil: the load is on from the first sample at or after load_delay (0.7 s -> n = 3500)
    Q[L.Q_LOAD_N] = float(math.ceil(tr.load_delay / c.Ts - 1e-9))
    Q[L.Q_LOAD] = tr.load_torque
    Q[L.Q_LOAD_FIXED] = 1.0 if tr.load_sign == 'fixed' else 0.0
    Q[L.Q_A1], Q[L.Q_A2], Q[L.Q_A3] = lo.a1, lo.a2, lo.a3
    Q[L.Q_THR1], Q[L.Q_THR2], Q[L.Q_THR3] = lo.threshold1, lo.threshold2, lo.threshold3
    Q[L.Q_ISQ_MAX] = c.isq_max
    Q[L.Q_SAT_RATIO] = lo.sat_ratio
    Q[L.Q_ISQF_A] = math.exp(-c.Ts / lo.isqf_tau)
    t_acc, t_dec, t_end, v_peak = trajectory_times(tr.distance, tr.a_max, tr.v_max)
    Q[L.Q_DIST] = tr.distance
    Q[L.Q_AMAX] = tr.a_max
    Q[L.Q_VPEAK] = v_peak
    Q[L.Q_TACC], Q[L.Q_TDEC], Q[L.Q_TEND] = t_acc, t_dec, t_end
    Q[L.Q_MAX_ERR] = sf.max_position_error
    Q[L.Q_MAX_SPEED] = sf.max_speed
    n_load = Q[L.Q_LOAD_N]
    Q[L.Q_RIP1_A] = float(math.ceil((t_end + L.RIPPLE_AFTER_MOVE) / c.Ts - 1e-9))
    Q[L.Q_RIP1_B] = n_load
    Q[L.Q_RIP2_A] = n_load + float(round(L.RIPPLE_AFTER_LOAD / c.Ts))
    Q[L.Q_RIP2_B] = Q[L.Q_N]
    Q[L.Q_ID_K] = float(max(1, round(L.MOTION_BLOCK / c.Ts)))
    Q[L.Q_ID_WDEAD] = L.MOTION_DEAD_BAND * v_peak
    return Q


def trajectory(
    t: np.ndarray, cfg: ExperimentConfig | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move profile at times ``t`` [s] after the reference change: (s [rad], ds/dt [rad/s],
    d2s/dt2 [rad/s^2]) for a positive move of ``trajectory.distance``."""
    cfg = validate_experiment_config(ExperimentConfig() if cfg is None else cfg)
    Q = make_experiment_params(cfg)
    tt = np.ascontiguousarray(np.asarray(t, dtype=np.float64).ravel())
    pos, vel, acc = np.empty_like(tt), np.empty_like(tt), np.empty_like(tt)
    _traj_arrays(tt, Q, pos, vel, acc)
    return pos, vel, acc
