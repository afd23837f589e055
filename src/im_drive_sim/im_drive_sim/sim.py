"""Programmatic API of the IM drive simulator: ``DriveSim``.

Model, control, measurement and step semantics are documented in docs/drive-model.md.
Units SI; angles mechanical unless stated; dq quantities are amplitude-invariant peaks.

Example::

    from im_drive_sim.sim import DriveSim
    sim = DriveSim()                      # packaged paper_750w.yaml, full model
    sim.reset(omega=0.0, fluxed=True)    # at rest, half an encoder count in
    sim.step(isq_ref=1.0, load_torque=0.0)
    print(sim.time_ns, sim.theta_meas, sim.omega_meas, sim.torque)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from operator import attrgetter
from typing import Any

import numpy as np

from . import kernels as K, model_layout as L, plant
from .drive_file import load_config
from .params import DriveConfig, MachineParams

STATE_FIELDS: tuple[str, ...] = L.STATE_FIELDS
"""Fields written by ``step_into``/``read_into``, in order (units in docs/drive-model.md)."""
RUN_FIELDS: tuple[str, ...] = L.RUN_FIELDS
"""Fields returned by ``run``: STATE_FIELDS + encoder_count, u_alpha, u_beta, psi_r,
voltage_saturated, isq_ref."""

NOISE_BLOCK = 4096
"""Rows of pre-generated noise per block (one row per step)."""


def _lag(Ts: float, tau: float) -> float:
    """Exact discretisation pole exp(-Ts/tau) of 1/(1 + s tau); tau = 0 -> 0 (no lag)."""
    return math.exp(-Ts / tau) if tau > 0.0 else 0.0


def make_param_array(cfg: DriveConfig) -> np.ndarray:
    """Precompute the kernel constant vector ``P`` (indices ``model_layout.P_*``) from a config."""
    m, c, s, d = cfg.machine, cfg.control, cfg.sensors, cfg.disturbance
    Ts = cfg.Ts
    P = np.zeros(L.N_PARAMS)
    for i, path in L.FROM_CONFIG.items():
        P[i] = float(attrgetter(path)(cfg))
    sigls = m.sigma * m.Ls
    P[L.P_TS] = Ts
    P[L.P_TS_NS] = float(cfg.Ts_ns)
    P[L.P_INV_SIGLS] = 1.0 / sigls
    P[L.P_KR_TAUR] = m.kr / m.tau_r
    P[L.P_INV_TAUR] = 1.0 / m.tau_r
    P[L.P_KTE] = 1.5 * m.pole_pairs * m.kr
    P[L.P_INV_J] = 1.0 / m.J
    P[L.P_INV_WC] = 1.0 / friction_smoothing_speed(m)
    P[L.P_KP] = sigls * c.current_bandwidth
    P[L.P_KI_TS] = m.R_sigma * c.current_bandwidth * Ts
    P[L.P_SIGLS] = sigls
    P[L.P_EST_A] = math.exp(-Ts / m.tau_r)
    P[L.P_ENC_K] = s.encoder_counts / (2.0 * math.pi)
    P[L.P_ENC_RES] = 2.0 * math.pi / s.encoder_counts
    P[L.P_ENC_RES_TS] = (2.0 * math.pi / s.encoder_counts) / Ts
    P[L.P_SPD_A] = _lag(Ts, s.speed_filter_tau)
    P[L.P_MODEL] = 0.0 if cfg.model == 'full' else 1.0
    tau_i = c.reduced_current_lag
    P[L.P_ISQ_A] = _lag(Ts, tau_i)
    P[L.P_ISQ_AH] = _lag(0.5 * Ts, tau_i)
    P[L.P_ISQ_INT] = tau_i * (1.0 - P[L.P_ISQ_A])
    P[L.P_ISQ_A0] = 1.0 if tau_i > 0.0 else 0.0
    P[L.P_SLIP_K] = m.Lm / (m.tau_r * m.rated_flux)
    P[L.P_LOAD_A] = _lag(Ts, d.load_lag_tau)
    P[L.P_LN_A] = _lag(Ts, d.load_noise_tau)
    P[L.P_IOFF_B] = (s.current_offset_a + 2.0 * s.current_offset_b) / math.sqrt(3.0)
    P[L.P_STRIBECK] = stribeck_gain(m)
    P[L.P_INV_WS2] = 1.0 / (m.stribeck_speed * m.stribeck_speed)
    P[L.P_RR_RISE] = m.rr_temp_coeff * m.rr_temp_rise
    P[L.P_INV_TTH] = 1.0 / m.rr_temp_tau
    # a load step waits U{0, ..., N} periods (docs/drive-model.md, "Bench effects")
    P[L.P_LS_DELAY_N] = float(round(d.load_step_delay_max / Ts))
    on = d.load_step_amplitude_std != 0.0 or P[L.P_LS_DELAY_N] != 0.0
    P[L.P_LS_ON] = 1.0 if on else 0.0
    return P


def friction_smoothing_speed(m: MachineParams) -> float:
    """omega_c [rad/s], the smoothing speed of the Coulomb term Tc tanh(w/omega_c):
    ``coulomb_speed``; with the Stribeck rise on, at most w_brk/10 (Simscape's rule,
    w_brk = ws/sqrt(2) the breakaway speed), so that the Coulomb term has its full Tc
    (tanh(10)) where the Stribeck term peaks: the friction reaches the breakaway torque."""
    if m.static_torque == 0.0:
        return m.coulomb_speed
    return min(m.coulomb_speed, m.stribeck_speed / (10.0 * math.sqrt(2.0)))


def stribeck_gain(m: MachineParams) -> float:
    """ds [N m s/rad] of the Stribeck term ds w exp(-(w/ws)^2) (``plant.friction_torque``):
    sqrt(2e) (Ts - Tc)/ws, whose peak at w_brk = ws/sqrt(2) is Ts - Tc; 0 when off."""
    if m.static_torque == 0.0:
        return 0.0
    return math.sqrt(2.0 * math.e) * (m.static_torque - m.coulomb_torque) / m.stribeck_speed


def start_position(config: DriveConfig) -> float:
    """Where a drive at rest starts [rad]: half an encoder count, 0.5 * 2 pi / counts.

    theta = 0 is the edge between counts -1 and 0, where a round-off at step 0 would pick
    the count; inside a count none does, and the encoder still reads 0.0 rad
    (research/NOTES.md, "From the source of im_drive_sim.sim").
    """
    return math.pi / config.sensors.encoder_counts


def _column(x: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """``x`` as a contiguous 1-D float64 array; a scalar broadcast to ``shape`` if given."""
    a = np.asarray(x, dtype=np.float64)
    return np.ascontiguousarray(np.broadcast_to(a, shape) if shape and a.ndim == 0 else a.ravel())


def _state_word(index: int, doc: str) -> Any:
    """A read-only float property of :class:`DriveSim`: its state word ``S[index]``."""
    return property(lambda self: float(self.S[index]), doc=doc)


def _published(index: int, doc: str) -> Any:
    """A read-only float property of :class:`DriveSim`: the published field ``index`` at
    the current time (``kernels.write_out``)."""
    return property(lambda self: float(self._read()[index]), doc=doc)


class DriveSim:
    """Induction-motor drive: full (or reduced) model, vector control, encoder measurement.

    One ``step`` = one control period Ts (default 200 us).  State k is at time k*Ts; after
    ``step`` the object describes time (k+1)*Ts.  Deterministic: the same config, seed,
    ``reset`` arguments and inputs give bit-identical outputs (noise is pre-generated in
    blocks of ``NOISE_BLOCK`` rows from ``numpy.random.Generator(PCG64(seed))``, the encoder
    jitter from ``PCG64(seed).jumped()``, the load step's variation from
    ``PCG64(seed).jumped(2)``).

    Parameters
    ----------
    config: validated ``DriveConfig``; ``None`` loads the packaged ``paper_750w.yaml``.
    seed: overrides ``config.seed`` for the noise streams (integer >= 0).
    """

    def __init__(self, config: DriveConfig | None = None, seed: int | None = None) -> None:
        self.config: DriveConfig = load_config() if config is None else config
        if seed is not None and (
            isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0
        ):
            raise ValueError(f'seed must be an integer >= 0, got {seed!r}')
        self.seed: int = int(self.config.seed if seed is None else seed)
        self.P: np.ndarray = make_param_array(self.config)
        self.S: np.ndarray = np.zeros(L.N_STATE)
        self._noise: np.ndarray = np.zeros((NOISE_BLOCK, L.NOISE_COLS))
        # the first columns drawn as one (block, 4) stream: their draws do not depend on the jitter
        self._base: np.ndarray = np.zeros((NOISE_BLOCK, L.NOISE_BASE_COLS))
        self._jitter: np.ndarray = np.zeros(NOISE_BLOCK)
        s, d = self.config.sensors, self.config.disturbance
        self._jitter_std: float = s.encoder_jitter
        self._step_var: bool = self.P[L.P_LS_ON] != 0.0
        self._step_amp_std: float = d.load_step_amplitude_std
        ln_a = self.P[L.P_LN_A]
        self._noise_scale = np.array(
            [
                s.current_noise_std,
                s.current_noise_std,
                s.speed_noise_std,
                d.load_noise_std * math.sqrt(1.0 - ln_a * ln_a),
            ]
        )
        self._noise_on: bool = bool(np.any(self._noise_scale > 0.0))
        self._rng: np.random.Generator | None = None
        self._rng_jitter: np.random.Generator | None = None
        self._rng_step: np.random.Generator | None = None
        self._left: int = NOISE_BLOCK
        self._scratch = np.zeros(L.N_RUN_FIELDS)
        self.reset()

    # ------------------------------------------------------------------ noise
    def _refill(self) -> None:
        """Fill the noise block in place (no allocation) and rewind the kernel cursor."""
        if self._noise_on:
            assert self._rng is not None
            self._rng.standard_normal(out=self._base)
            self._base *= self._noise_scale
            self._noise[:, : L.NOISE_BASE_COLS] = self._base
        if self._jitter_std > 0.0:
            assert self._rng_jitter is not None
            self._rng_jitter.standard_normal(out=self._jitter)
            np.multiply(self._jitter, self._jitter_std, out=self._noise[:, L.NOISE_BASE_COLS])
        if self._step_var:  # the load step's variation: its own stream, in place
            assert self._rng_step is not None
            self._rng_step.standard_normal(out=self._jitter)
            np.multiply(self._jitter, self._step_amp_std, out=self._noise[:, L.N_AMP])
            self._rng_step.random(out=self._jitter)
            self._noise[:, L.N_DELAY] = self._jitter
        self.S[L.S_NPOS] = 0.0
        self._left = NOISE_BLOCK

    # ------------------------------------------------------------------ control
    def reset(
        self,
        theta: float | None = None,
        omega: float = 0.0,
        fluxed: bool = True,
        step_index: int = 0,
    ) -> None:
        """Set the state at time ``step_index * Ts``.

        theta [rad, mechanical, multi-turn]; None: :func:`start_position` (half an encoder
        count), omega [rad/s, mechanical].
        fluxed=True (full model): rotor flux at rated (steady state at isd = rated, isq = 0)
        with the estimator exactly oriented; False: de-energised (all currents, fluxes,
        integrators zero).  The reduced model is always fluxed.  Also resets PI integrators,
        filters (speed filter starts at ``omega``), encoder, load lag and the noise streams.
        """
        if theta is None:
            theta = start_position(self.config)
        for name, v in (('theta', theta), ('omega', omega)):
            if not math.isfinite(v):
                raise ValueError(f'{name} must be finite, got {v!r}')
        if isinstance(step_index, bool) or int(step_index) != step_index or step_index < 0:
            raise ValueError(f'step_index must be an integer >= 0, got {step_index!r}')
        self._rng = np.random.Generator(np.random.PCG64(self.seed))
        # the jitter's own stream: the other columns' draws do not depend on it
        self._rng_jitter = np.random.Generator(np.random.PCG64(self.seed).jumped())
        # the load step's variation: a third stream (the others' draws do not depend on it)
        self._rng_step = np.random.Generator(np.random.PCG64(self.seed).jumped(2))
        self._refill()
        K.reset_kernel(self.S, self.P, float(theta), float(omega), bool(fluxed), float(step_index))

    def _consume(self) -> None:
        self._left -= 1
        if self._left == 0:
            # The kernel already wrapped its cursor to 0; give it fresh samples.
            self._refill()

    def step(self, isq_ref: float, load_torque: float) -> None:
        """One Ts step with vector control (full) or the isq lag (reduced).

        isq_ref: torque-current command [A], clamped to +-isq_max.
        load_torque: load-machine torque command [N m] (opposes positive speed).
        """
        self.step_into(isq_ref, load_torque, self._scratch)

    def step_into(self, isq_ref: float, load_torque: float, out: np.ndarray) -> None:
        """Fast path: one step, then write ``STATE_FIELDS`` at the new time into ``out``.

        ``out``: preallocated float64 array of length >= len(STATE_FIELDS) (>= len(RUN_FIELDS)
        also fills the extra fields).  ``out`` describes time (k+1)*Ts after the step.
        """
        if not (math.isfinite(isq_ref) and math.isfinite(load_torque)):
            raise ValueError(f'non-finite input: isq_ref={isq_ref!r}, load_torque={load_torque!r}')
        K.step_into_kernel(self.S, self.P, self._noise, float(isq_ref), float(load_torque), out)
        self._consume()

    def warm_up(self, out: np.ndarray) -> None:
        """Compile (or load from numba's cache) the step kernel for output arrays like
        ``out`` (its alignment is part of numba's signature), on scratch copies of the
        model's state: nothing changes. A real-time loop calls this before its first
        period, which must not wait seconds for a compiler."""
        saved = out.copy()
        K.step_into_kernel(self.S.copy(), self.P, self._noise.copy(), 0.0, 0.0, out)
        out[:] = saved
        K.clear_command(self.S.copy())  # a safe stop's, which must act at once

    def clear_command(self) -> None:
        """Drop the command latched for the next step (delay 2): it runs zero current
        and no load instead (a safe stop or a watchdog trip acts at once), and a load step
        waiting in the load machine's command cycle is dropped (``kernels.clear_command``)."""
        K.clear_command(self.S)

    def read_into(self, out: np.ndarray) -> None:
        """Write ``STATE_FIELDS`` for the current time (no stepping) into ``out``."""
        K.write_out(self.S, self.P, out)

    def step_voltage(self, u_alpha: float, u_beta: float, load_torque: float) -> None:
        """One Ts step of the bare full model with given stationary voltages (no control).

        u_alpha, u_beta: [V] peak amplitude-invariant, held over the step (ZOH).
        Measurements and the flux estimator still run.  Full model only.
        """
        if self.config.model != 'full':
            raise RuntimeError('step_voltage needs model: full')
        if not (math.isfinite(u_alpha) and math.isfinite(u_beta) and math.isfinite(load_torque)):
            raise ValueError('non-finite input to step_voltage')
        K.step_voltage_kernel(
            self.S, self.P, self._noise, float(u_alpha), float(u_beta), float(load_torque)
        )
        self._consume()

    def run_kernel(
        self,
        n: int,
        kernel: Callable[[np.ndarray, np.ndarray, np.ndarray, int, int], int],
        stop: Callable[[], bool] | None = None,
    ) -> int:
        """Let a caller's numba loop step this model for at most ``n`` steps.

        ``kernel(S, P, noise, offset, count)`` must step the model with
        ``kernels.step_model(S, P, noise, ...)`` at most ``count`` times (``offset`` = the
        steps done before this call) and return how many it took: fewer than ``count``
        stops the run. It is called on chunks that end on the noise-block boundaries, as
        :meth:`run` does, so the model sees the same noise as step by step. ``stop()``,
        checked after each chunk, ends the run early too. Returns the steps taken.
        (This is how a controller kernel is fused with the drive, e.g. the offline bench.)
        """
        done = 0
        while done < n:
            cnt = min(n - done, self._left)
            k = int(kernel(self.S, self.P, self._noise, done, cnt))
            self._left -= k
            if self._left == 0:
                self._refill()
            done += k
            if k < cnt or (stop is not None and stop()):
                break
        return done

    def run(self, isq_ref: np.ndarray, load_torque: np.ndarray) -> dict[str, np.ndarray]:
        """Step len(isq_ref) times inside numba; returns ``{field: array}`` for RUN_FIELDS.

        Row k is the state after step k (time (k+1) Ts), as ``step_into`` would write it.
        isq_ref [A], load_torque [N m]: 1-D arrays of equal length (scalars broadcast).
        """
        isq = _column(isq_ref)
        tl = _column(load_torque, isq.shape)
        if isq.shape != tl.shape:
            raise ValueError(f'isq_ref and load_torque lengths differ: {isq.shape} vs {tl.shape}')
        if not (np.all(np.isfinite(isq)) and np.all(np.isfinite(tl))):
            raise ValueError('non-finite values in run inputs')
        return self._run_rows(
            isq.shape[0],
            lambda out, s0, c: K.run_batch(self.S, self.P, self._noise, isq, tl, out, s0, c, True),
        )

    def run_voltage(
        self, u_alpha: np.ndarray, u_beta: np.ndarray, load_torque: np.ndarray
    ) -> dict[str, np.ndarray]:
        """Batch version of ``step_voltage`` (bare full model); same output as ``run``."""
        if self.config.model != 'full':
            raise RuntimeError('run_voltage needs model: full')
        ua, ub = _column(u_alpha), _column(u_beta)
        tl = _column(np.broadcast_to(load_torque, ua.shape))
        if ub.shape != ua.shape:
            raise ValueError('u_alpha and u_beta lengths differ')
        return self._run_rows(
            ua.shape[0],
            lambda out, s0, c: K.run_voltage_batch(
                self.S, self.P, self._noise, ua, ub, tl, out, s0, c
            ),
        )

    def _run_rows(self, n: int, kernel: Any) -> dict[str, np.ndarray]:
        """``n`` steps by ``kernel(out, start, count)`` (in noise-block chunks), one row of
        ``out`` (``RUN_FIELDS``) a step; the columns by name."""
        out = np.empty((n, L.N_RUN_FIELDS))

        def rows(S: np.ndarray, P: np.ndarray, noise: np.ndarray, start: int, count: int) -> int:
            kernel(out, start, count)
            return count

        self.run_kernel(n, rows)
        return {name: out[:, j] for j, name in enumerate(RUN_FIELDS)}

    # ------------------------------------------------------------------ state
    def state_vector(self) -> np.ndarray:
        """Copy of the complete internal state (indices ``model_layout.S_*``; S[0:6] is the plant
        state [i_sa A, i_sb A, psi_ra Wb, psi_rb Wb, omega rad/s, theta rad])."""
        return self.S.copy()

    def _read(self) -> np.ndarray:
        K.write_out(self.S, self.P, self._scratch)
        return self._scratch

    @property
    def step_index(self) -> int:
        """Step k (the object describes time k*Ts)."""
        return int(self.S[L.S_STEP])

    @property
    def time_ns(self) -> int:
        """Exact simulated time k*Ts [ns]."""
        return int(self.S[L.S_STEP]) * self.config.Ts_ns

    @property
    def time(self) -> float:
        """Simulated time k*Ts [s]."""
        return self.time_ns * 1e-9

    theta_meas = _state_word(L.S_THETA_MEAS, 'Encoder angle count*2pi/counts [rad, mechanical].')
    omega_meas = _state_word(
        L.S_OMEGA_MEAS, 'Speed estimate (filtered backward difference + noise) [rad/s].'
    )

    @property
    def encoder_count(self) -> int:
        """Multi-turn encoder count floor(theta * counts/(2 pi))."""
        return int(self.S[L.S_COUNT])

    theta = _state_word(L.S_THETA, 'True mechanical angle [rad].')
    omega = _state_word(L.S_OMEGA, 'True mechanical speed [rad/s].')
    torque = _published(L.F_TORQUE, 'Electromagnetic torque [N m].')
    i_alpha = _published(L.F_I_ALPHA, 'True stator current alpha [A, peak amplitude-invariant].')
    i_beta = _published(L.F_I_BETA, 'True stator current beta [A].')
    isd = _state_word(
        L.S_ISD, 'Sampled d current in the estimated flux frame (as the controller sees it) [A].'
    )
    isq = _state_word(L.S_ISQ, 'Sampled q current in the estimated flux frame [A].')
    psi_r = _published(L.F_PSI_R, 'True rotor flux magnitude [Wb] (reduced: rated flux).')
    psi_hat = _state_word(L.S_PSI_HAT, 'Estimated rotor flux (current model) [Wb].')
    u_alpha = _state_word(
        L.S_UA, 'Stator voltage alpha applied during the last step [V] (0 in the reduced model).'
    )
    u_beta = _state_word(L.S_UB, 'Stator voltage beta applied during the last step [V].')
    load_torque = _state_word(
        L.S_TLOAD, 'Total load torque applied during the last step [N m] (lag + ripple + random).'
    )
    isq_ref = _state_word(L.S_ISQ_REF, 'Clamped isq* of the last step [A].')

    @property
    def rotor_resistance(self) -> float:
        """The plant's rotor resistance now [ohm]: Rr0 (1 + alpha dT (1 - exp(-t/tau_th)))
        (``machine.rr_temp_*``; the controller keeps the nominal Rr0)."""
        return self.config.machine.Rr * float(plant.rotor_resistance_scale(self.time, self.P))

    @property
    def voltage_saturated(self) -> bool:
        """True if the circular voltage limit was active in the last step."""
        return bool(self.S[L.S_VSAT] != 0.0)
