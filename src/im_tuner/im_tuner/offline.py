"""The offline bench: the controller's experiment kernel fused with the drive kernels in
one numba loop, no ROS -- the oracle of the ROS tests and the engine of offline studies.

Per step: ``experiment_step`` on drive state k, the drive steps with the command (exactly
``DriveSim.step_into``), state <- k+1. The drive is driven through its public API
(``DriveSim.run_kernel``: chunks that end on its noise-block boundaries), so a fused run
and a step-by-step run (the node's path, ``python_loop=True``) give bit-identical results.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numba import njit

from im_controller.config import GAIN_NAMES, ExperimentConfig, Gains
from im_controller.control import CONTROL_FIELDS, N_CONTROL_FIELDS
from im_controller.kernel import experiment_step
from im_controller.layout import (
    E_ISQ,
    E_LOAD,
    E_STATUS,
    EXP_FIELDS,
    MODE_FAULT,
    MODE_HOLD,
    MODE_RETURN,
    N_EXP_FIELDS,
    Q_N,
    Q_SETTLE_N,
    Q_TEND,
    Q_TS,
    R_MODE,
    R_N,
    STATUS_DONE,
)
from im_controller.result import LossResult
from im_controller.runner import ExperimentRunner, config_for_drive
from im_drive_sim import kernels as DK
from im_drive_sim.params import DriveConfig
from im_drive_sim.sim import DriveSim

from .tuning import Measurement

N_REC = DK.N_STATE_FIELDS + N_CONTROL_FIELDS + N_EXP_FIELDS
REC_FIELDS: tuple[str, ...] = DK.STATE_FIELDS + CONTROL_FIELDS + EXP_FIELDS


@njit(cache=True)
def run_fused(
    S: np.ndarray,
    P: np.ndarray,
    noise: np.ndarray,
    R: np.ndarray,
    Q: np.ndarray,
    X: np.ndarray,
    C: np.ndarray,
    CF: np.ndarray,
    state: np.ndarray,
    cout: np.ndarray,
    eout: np.ndarray,
    rec: np.ndarray,
    row0: int,
    n_max: int,
    record: bool,
    stop_at_end: bool,
) -> int:
    """At most ``n_max`` steps of the fused loop (module docstring); row ``row0 + i`` of
    ``rec`` gets [state k, controller internals, experiment outputs].  Stops after a
    DONE/ABORTED/FAULT step if ``stop_at_end``.  Returns the steps done."""
    ns = DK.N_STATE_FIELDS
    nc = N_CONTROL_FIELDS
    for i in range(n_max):
        st = experiment_step(R, Q, X, C, CF, state, cout, eout)
        if record:
            row = rec[row0 + i]
            for j in range(ns):
                row[j] = state[j]
            for j in range(nc):
                row[ns + j] = cout[j]
            for j in range(N_EXP_FIELDS):
                row[ns + nc + j] = eout[j]
        DK.step_model(S, P, noise, eout[E_ISQ], eout[E_LOAD])
        DK.write_out(S, P, state)
        if stop_at_end and st >= STATUS_DONE:
            return i + 1
    return n_max


def _run(
    sim: DriveSim,
    runner: ExperimentRunner,
    n: int,
    record: bool,
    stop_at_end: bool,
    python_loop: bool,
) -> tuple[int, np.ndarray]:
    state = np.zeros(DK.N_STATE_FIELDS)
    sim.read_into(state)
    rec = np.zeros((n if record else 1, N_REC))
    done = 0
    if python_loop:
        # The ROS node's path, step by step through the public APIs (for equivalence tests).
        ns, nc = DK.N_STATE_FIELDS, N_CONTROL_FIELDS
        for i in range(n):
            isq, load, st = runner.step(state)
            if record:
                rec[i, :ns] = state
                rec[i, ns : ns + nc] = runner.cout
                rec[i, ns + nc :] = runner.eout
            sim.step_into(isq, load, state)
            done += 1
            if stop_at_end and st >= STATUS_DONE:
                break
        return done, rec[:done]
    done = sim.run_kernel(
        n,
        lambda S, P, noise, offset, cnt: run_fused(
            S,
            P,
            noise,
            runner.R,
            runner.Q,
            runner.X,
            runner.C,
            runner.CF,
            state,
            runner.cout,
            runner.eout,
            rec,
            offset if record else 0,
            cnt,
            record,
            stop_at_end,
        ),
        (lambda: runner.eout[E_STATUS] >= STATUS_DONE) if stop_at_end else None,
    )
    runner.stepped(int(runner.eout[E_STATUS]))
    return done, rec[:done]


def _experiment(
    sim: Any,
    runner: ExperimentRunner,
    experiment_id: int,
    record: bool,
    python_loop: bool,
    gains: Gains | None = None,
) -> tuple[LossResult, np.ndarray]:
    """Experiment ``experiment_id`` (``gains``; None: the runner's) run whole from the next
    step, its settle first: its result and the recorded rows."""
    runner.start(experiment_id, gains)
    n = int(runner.Q[Q_SETTLE_N]) + int(runner.Q[Q_N])
    _done, rec = _run(sim, runner, n, record, True, python_loop)
    res = runner.result()
    assert res is not None, 'experiment did not finish'
    return res, rec


def _signals(rec: np.ndarray, Ts: float, t0_step: float) -> dict[str, np.ndarray]:
    sig = {name: rec[:, j].copy() for j, name in enumerate(REC_FIELDS)}
    sig['t'] = (sig['step_index'] - t0_step) * Ts
    return sig


def run_experiment_offline(
    sim: DriveSim,
    gains: Gains,
    config: ExperimentConfig | None = None,
    experiment_id: int = 0,
    runner: ExperimentRunner | None = None,
    record: bool = True,
    python_loop: bool = False,
) -> tuple[LossResult, dict[str, np.ndarray]]:
    """One whole experiment of ``gains`` on ``sim`` as it is (nothing reset), no ROS.

    ``runner``: the same one for consecutive experiments (None: a new one holding
    ``sim.theta_meas``; ``config``'s Ts and isq_max are the drive's).  ``record``: the
    signals from step 0 (``REC_FIELDS`` + 't' [s]; row n: drive state n, the internals
    and outputs computed from it).  ``python_loop``: the node's path, step by step,
    instead of the fused loop (bit-identical).  Returns (LossResult, signals).
    """
    if runner is None:
        runner = ExperimentRunner(config_for_drive(config, sim), gains)
        runner.reset(sim.theta_meas)
    finish_stopped_move(sim, runner, python_loop)
    settle = int(runner.Q[Q_SETTLE_N])
    k0 = float(sim.step_index + settle)  # step 0 follows the settle (lock-step: exactly)
    res, rec = _experiment(sim, runner, experiment_id, record, python_loop, gains)
    sig = _signals(rec[settle:], runner.config.control.Ts, k0) if record else {}
    return res, sig


def finish_stopped_move(sim: DriveSim, runner: ExperimentRunner, python_loop: bool = False) -> int:
    """After a supervisor stop the fallback gains finish the move (``ready`` is False):
    run exactly the steps until it ends, or until a safety fault stops it -- what the
    lock-step node does (it steps while not ready and pauses once ready or faulted).
    Returns the steps run (0 if no stopped move is being finished)."""
    R, Q = runner.R, runner.Q
    if R[R_MODE] != MODE_RETURN:
        return 0
    # the steps left: the kernel ends the move on the step whose local index nn has
    # nn Ts >= t_end (same float expression, so the same step)
    nn, steps = R[R_N], 1
    while not nn * Q[Q_TS] >= Q[Q_TEND]:
        nn += 1.0
        steps += 1
    done, _ = _run(sim, runner, steps, False, True, python_loop)
    assert R[R_MODE] in (MODE_HOLD, MODE_FAULT), 'the stopped move did not end'
    return done


def hold_offline(
    sim: DriveSim,
    runner: ExperimentRunner,
    steps: int,
    record: bool = False,
    python_loop: bool = False,
) -> dict[str, np.ndarray]:
    """Run ``steps`` steps of whatever the runner is doing (normally the hold)."""
    k0 = float(sim.step_index)
    _done, rec = _run(sim, runner, int(steps), record, False, python_loop)
    return _signals(rec, runner.config.control.Ts, k0) if record else {}


class OfflineBench:
    """The simulated lock-step bench as the tuner drives it, on the pure core (a
    ``Measurer``): a drive at rest, a controller holding it, experiment ids 0, 1, ... and
    the fault policy 'reset' (the controller reset where the drive is)."""

    def __init__(
        self, drive: DriveConfig, drive_seed: int, experiment: ExperimentConfig | None = None
    ) -> None:
        """``experiment``: the drive's (``im_tuner.family.drive_setup``); None: the
        default ``ExperimentConfig()`` (Ts and isq_max are taken from ``drive`` either way);
        the controller starts with its fallback gains."""
        self.sim = DriveSim(drive, seed=drive_seed)
        self.sim.reset(omega=0.0, fluxed=True)  # at rest, half a count in (start_position)
        cfg = config_for_drive(experiment, self.sim)
        self.runner = ExperimentRunner(cfg, cfg.fallback_gains)
        self.runner.reset(self.sim.theta_meas)
        self.next_id = 0

    def measure(self, gains: Gains) -> Measurement:
        """One experiment with ``gains``."""
        t0 = time.perf_counter()
        # a stopped move is finished first; a safety fault during it is reset, as the
        # link does when the start is refused with a safety fault
        finish_stopped_move(self.sim, self.runner)
        if self.runner.faulted:
            self.runner.reset(self.sim.theta_meas)
        res, _ = run_experiment_offline(
            self.sim, gains, self.runner.config, self.next_id, self.runner, record=False
        )
        self.next_id += 1
        m = Measurement.of(res, time.perf_counter() - t0)
        if m.fault:
            self.runner.reset(self.sim.theta_meas)
        return m

    def apply(self, gains: Gains) -> None:
        """Offline there is no controller to leave the final gains on."""


def replay_realtime(
    records: list[dict[str, Any]], drive: DriveConfig, drive_seed: int
) -> list[LossResult]:
    """A real-time run's plant history replayed in lock-step on the pure core, from its
    results.jsonl ``records`` (each experiment's id, gains, ``t_start_ns`` and
    ``gains_step``; the holds between as long as in the run).  Where the run had no held
    or late period every loss equals the recorded one bit for bit.  Assumes no safety
    fault was reset in between (the reset's step is not recorded)."""
    sim = DriveSim(drive, seed=drive_seed)
    sim.reset(omega=0.0, fluxed=True)
    return _replay(sim, records, drive.Ts, python_loop=False)


def _replay(
    sim: Any, records: list[dict[str, Any]], Ts: float, python_loop: bool
) -> list[LossResult]:
    """:func:`replay_realtime` on ``sim``, step by step with ``python_loop`` (a plant with
    no kernel)."""
    runner = ExperimentRunner(config_for_drive(None, sim), Gains())
    runner.reset(sim.theta_meas)
    ts_ns = round(Ts * 1e9)
    out = []
    for rec in records:
        if rec.get('experiment_id') is None or rec.get('t_start_ns') is None:
            continue
        k0 = int(rec['t_start_ns']) // ts_ns
        gains = Gains(*(float(rec['gains'][n]) for n in GAIN_NAMES))
        g_step = int(rec['gains_step'])
        if g_step > sim.step_index:
            _run(sim, runner, g_step - sim.step_index, False, False, python_loop)
        if gains != runner.gains:
            runner.set_gains(gains)
        settle = int(runner.Q[Q_SETTLE_N])
        if k0 - settle < sim.step_index:
            raise ValueError(f'experiment {rec["experiment_id"]} starts before the replay')
        _run(sim, runner, k0 - settle - sim.step_index, False, False, python_loop)
        # its settle, then step 0 at k0
        out.append(_experiment(sim, runner, int(rec['experiment_id']), False, python_loop)[0])
    return out


class StandInPlant:
    """The example drive's stand-in plant (``example_drive.Hardware``) as the offline
    loop's drive (``read_into``/``step_into``, as ``DriveSim``): a write of the clamped
    command, then a read, per step -- what ``ExampleDrive.period`` does with its power
    stage when no period is late. Its state 0 is a first read, as ``ExampleDrive.start``."""

    def __init__(self, config: DriveConfig) -> None:
        from im_drive_sim.example_drive import Hardware

        self.config = config
        self.hw = Hardware(config)
        self.step_index = 0
        self.isq_max = float(config.machine.isq_max)
        self._m = self.hw.read()

    @property
    def theta_meas(self) -> float:
        return float(self._m.theta_meas)

    def read_into(self, state: np.ndarray) -> None:
        m = self._m
        state[0] = self.step_index
        state[1] = self.step_index * round(self.config.Ts * 1e9)
        state[2], state[3], state[4] = m.theta_meas, m.omega_meas, m.torque
        state[5], state[6], state[7], state[8] = m.isd, m.isq, m.i_alpha, m.i_beta
        state[9], state[10], state[11] = m.load_torque, m.theta_meas, m.omega_meas
        # every period fresh: the command answering the state before acted over it
        state[12], state[13] = self.step_index - 1, self.hw.command_delay

    def step_into(self, isq: float, load: float, state: np.ndarray) -> None:
        self.hw.write(max(-self.isq_max, min(self.isq_max, isq)), load)
        self.step_index += 1
        self._m = self.hw.read()
        self.read_into(state)


def replay_stand_in(records: list[dict[str, Any]], drive: DriveConfig) -> list[LossResult]:
    """:func:`replay_realtime` for the example drive (``--drive example``) on its stand-in
    plant, every period fresh: a loss that differs is what the run's held periods did."""
    return _replay(StandInPlant(drive), records, drive.Ts, python_loop=True)


def stand_in_losses(
    drive: DriveConfig, gains: Gains, n: int, seed: int = 0, max_hold: int = 2000
) -> list[float]:
    """The loss of ``gains`` on the example drive's stand-in plant at ideal timing (lock-
    step, every period fresh), ``n`` times, each after a seeded random hold of 1 to
    ``max_hold`` periods: the spread a run's experiment shows from where it starts (the
    rest position within an encoder count, the current's ripple), with no held period."""
    rng = np.random.default_rng(seed)
    sim: Any = StandInPlant(drive)
    runner = ExperimentRunner(config_for_drive(None, sim), gains)
    runner.reset(sim.theta_meas)
    out = []
    for i in range(n):
        _run(sim, runner, int(rng.integers(1, max_hold + 1)), False, False, True)
        out.append(_experiment(sim, runner, i, False, True)[0].loss)
    return out
