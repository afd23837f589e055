"""The example drive's stand-in plant, compiled: ``--drive example``.

The same plant as ``example_drive.Hardware`` (first-order current loop, torque = kt isq,
inertia and viscous friction, a 4096-count encoder, a low-pass filtered backward-
difference speed), bit for bit (``src/im_drive_sim/test/test_hardware_abi.py``), written
in the compiled form of docs/real-drive.md: numba-jitted ``write``/``read``/``elapse`` on
the class and the plant's words in a float64 array ``state``. The composed bench's loop
calls them by address without the GIL (``hardware_abi``), so the rehearsal runs at the
simulator's timing; its twin in C is ``share/im_drive_sim/examples/example_drive.c``.

A template for a Python user's compiled drive: keep the three functions' signatures,
replace their bodies with your inverter's interface (a shared memory with its firmware,
a numba-callable SDK function), and return a negative code for a drive fault.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .params import DriveConfig

#: the words of ``state``
(
    S_TS,  # [s]
    S_KT,  # [N m/A]
    S_INV_J,  # [1/(kg m^2)]
    S_B,  # [N m s/rad]
    S_ISD,  # [A] the flux current
    S_POLES,  # pole pairs
    S_A_I,  # the current loop's pole per period
    S_A_W,  # the speed filter's pole per period
    S_CPR,  # encoder counts per rad
    S_DELAY,  # the command delay [periods]
    S_ISQ_REF,  # the command acting now [A]
    S_LOAD_REF,  # [N m]
    S_NEXT_ISQ,  # delay 2: the command written, acting from the next period
    S_NEXT_LOAD,
    S_ISQ,  # the true plant state
    S_THETA,
    S_OMEGA,
    S_COUNT,  # the encoder count
    S_THETA_MEAS,  # the measurement's position [rad]
    S_OMEGA_MEAS,  # and filtered speed [rad/s]
) = range(20)
N_STATE = 20


@njit(cache=True, nogil=True)
def _integrate(s: np.ndarray) -> float:
    """One period under the held command (``Hardware._integrate``); returns the torque."""
    ts = s[S_TS]
    s[S_ISQ] = s[S_A_I] * s[S_ISQ] + (1.0 - s[S_A_I]) * s[S_ISQ_REF]
    torque = s[S_KT] * s[S_ISQ]
    s[S_OMEGA] += (torque - s[S_LOAD_REF] - s[S_B] * s[S_OMEGA]) * s[S_INV_J] * ts
    s[S_THETA] += s[S_OMEGA] * ts
    if s[S_DELAY] == 2.0:
        s[S_ISQ_REF] = s[S_NEXT_ISQ]
        s[S_LOAD_REF] = s[S_NEXT_LOAD]
    return torque


@njit(cache=True, nogil=True)
def _encoder(s: np.ndarray) -> None:
    """The encoder and the speed estimate (``Hardware._encoder``)."""
    cpr = s[S_CPR]
    count = math.floor(s[S_THETA] * cpr)
    raw = (count - s[S_COUNT]) / (cpr * s[S_TS])
    s[S_COUNT] = count
    s[S_THETA_MEAS] = count / cpr
    s[S_OMEGA_MEAS] = s[S_A_W] * s[S_OMEGA_MEAS] + (1.0 - s[S_A_W]) * raw


class CompiledHardware:
    """The stand-in power stage, compiled (module docstring)."""

    def __init__(self, config: DriveConfig) -> None:
        m, sn = config.machine, config.sensors
        s = np.zeros(N_STATE)
        s[S_TS] = config.Ts
        s[S_KT] = m.Kt
        s[S_INV_J] = 1.0 / m.J
        s[S_B] = m.B
        s[S_ISD] = m.rated_flux_current
        s[S_POLES] = m.pole_pairs
        s[S_A_I] = math.exp(-config.Ts * config.control.current_bandwidth)
        s[S_A_W] = math.exp(-config.Ts / sn.speed_filter_tau) if sn.speed_filter_tau > 0 else 0.0
        s[S_CPR] = sn.encoder_counts / (2.0 * math.pi)
        s[S_DELAY] = config.command_delay
        #: the plant's words (the compiled form's contract)
        self.state = s
        #: over which period a write acts (the drive file's ``command_delay``)
        self.command_delay = int(config.command_delay)

    @staticmethod
    @njit(cache=True, nogil=True)
    def write(state: np.ndarray, isq_ref: float, load_torque: float) -> int:
        """Apply isq* [A] (already clamped) and the load torque [N m]; 0 = done."""
        if state[S_DELAY] == 2.0:
            state[S_NEXT_ISQ] = isq_ref
            state[S_NEXT_LOAD] = load_torque
        else:
            state[S_ISQ_REF] = isq_ref
            state[S_LOAD_REF] = load_torque
        return 0

    @staticmethod
    @njit(cache=True, nogil=True)
    def read(state: np.ndarray, m: np.ndarray) -> int:
        """Integrate one period, sample the sensors into ``m`` (the Measurement order)."""
        load = state[S_LOAD_REF]  # the load torque that acts over this period
        torque = _integrate(state)
        _encoder(state)
        isd, isq = state[S_ISD], state[S_ISQ]
        theta = state[S_THETA_MEAS]
        rho = state[S_POLES] * theta  # the field angle (slip neglected)
        c, s = math.cos(rho), math.sin(rho)
        m[0] = theta
        m[1] = state[S_OMEGA_MEAS]
        m[2] = torque
        m[3] = isd
        m[4] = isq
        m[5] = c * isd - s * isq
        m[6] = s * isd + c * isq
        m[7] = load
        return 0

    @staticmethod
    @njit(cache=True, nogil=True)
    def elapse(state: np.ndarray, periods: int) -> int:
        """Stand-in only: ``periods`` went by unsampled, the last command held."""
        for _ in range(periods):
            _integrate(state)
            _encoder(state)
        return 0
