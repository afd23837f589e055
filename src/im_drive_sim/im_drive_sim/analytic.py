"""Closed forms for the induction machine: T-equivalent-circuit steady state, rotor-flux
build-up, field-oriented steady state.  Used by the tests and docs/drive-model.md.

Conventions.  The simulator works with amplitude-invariant space vectors: a balanced
three-phase set with phase peak value X gives |x_alphabeta| = X; powers carry the factor
1.5 (P = 1.5 Re(u i*)).  The per-phase T-circuit therefore holds with *peak* phasors:
``U_peak = sqrt(2) U_rms`` (for a delta winding use the star-equivalent phase voltage
U_line/sqrt(3)), currents come out as peaks, ``I_rms = |I| / sqrt(2)``.

    Z = Rs + j w Lls + (j w Lm) || (Rr/s + j w Llr),      I_s = U / Z
    I_r = -I_s j w Lm / (Rr/s + j w Lr)                    (rotor current, stator side)
    T_e = 1.5 p |I_r|^2 Rr / (s w)      P_in = 1.5 Re(U I_s*)      PF = P_in/(1.5 |U||I_s|)
    psi_r = Lm I_s + Lr I_r  (rotor flux phasor, peak)
with w the electrical supply angular frequency and s the slip (omega_mech = (1 - s) w/p).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .params import MachineParams


@dataclass(frozen=True)
class SteadyState:
    """Equivalent-circuit operating point (peak amplitude-invariant phasors, SI)."""

    slip: float  # [-]
    omega_supply: float  # [rad/s] electrical supply frequency
    omega_mech: float  # [rad/s] rotor speed (1 - s) w/p
    u_peak: float  # [V] phase voltage amplitude
    i_s: complex  # [A] stator current phasor (peak), voltage phasor real
    i_r: complex  # [A] rotor current phasor referred to the stator (peak)
    psi_r: complex  # [Wb] rotor flux phasor (peak)
    torque: float  # [N m] electromagnetic torque
    p_in: float  # [W] electrical input power
    q_in: float  # [var] reactive input power
    p_cu_s: float  # [W] stator copper loss
    p_cu_r: float  # [W] rotor copper loss
    p_mech: float  # [W] mechanical power T_e omega_mech

    @property
    def i_s_peak(self) -> float:
        """Stator current amplitude [A]."""
        return abs(self.i_s)

    @property
    def i_s_rms(self) -> float:
        """Stator phase current rms [A] (star equivalent)."""
        return abs(self.i_s) / math.sqrt(2.0)

    @property
    def power_factor(self) -> float:
        """cos(phi) = P_in / (1.5 |U| |I_s|)."""
        return self.p_in / (1.5 * self.u_peak * abs(self.i_s))

    @property
    def speed_rpm(self) -> float:
        """Rotor speed [rpm]."""
        return self.omega_mech * 60.0 / (2.0 * math.pi)


def phase_peak_from_line_rms(u_line_rms: float) -> float:
    """Star-equivalent phase peak voltage sqrt(2) U_line/sqrt(3) [V] (220 V -> 179.6 V)."""
    return math.sqrt(2.0) * u_line_rms / math.sqrt(3.0)


def steady_state(m: MachineParams, u_peak: float, f_supply: float, slip: float) -> SteadyState:
    """Steady state at phase voltage amplitude ``u_peak`` [V], supply ``f_supply`` [Hz],
    slip ``slip`` (!= 0) from the T-equivalent circuit (see module docstring)."""
    if slip == 0.0:
        raise ValueError('slip must be non-zero (use a tiny slip for no-load)')
    w = 2.0 * math.pi * f_supply
    zr = m.Rr / slip + 1j * w * m.Llr
    zm = 1j * w * m.Lm
    z = m.Rs + 1j * w * m.Lls + zm * zr / (zm + zr)
    u = complex(u_peak, 0.0)
    i_s = u / z
    i_r = -i_s * zm / (zm + zr)
    psi_r = m.Lm * i_s + m.Lr * i_r
    s_in = 1.5 * u * i_s.conjugate()
    torque = 1.5 * m.pole_pairs * abs(i_r) ** 2 * m.Rr / (slip * w)
    omega_mech = (1.0 - slip) * w / m.pole_pairs
    return SteadyState(
        slip=slip,
        omega_supply=w,
        omega_mech=omega_mech,
        u_peak=u_peak,
        i_s=i_s,
        i_r=i_r,
        psi_r=psi_r,
        torque=torque,
        p_in=s_in.real,
        q_in=s_in.imag,
        p_cu_s=1.5 * m.Rs * abs(i_s) ** 2,
        p_cu_r=1.5 * m.Rr * abs(i_r) ** 2,
        p_mech=torque * omega_mech,
    )


def slip_for_torque(
    m: MachineParams, u_peak: float, f_supply: float, torque: float, tol: float = 1e-13
) -> float:
    """Slip in (0, s_breakdown) at which the circuit gives ``torque`` [N m] (bisection)."""
    # Torque rises monotonically from s = 0 to the breakdown slip; find it first.
    lo, hi = 1e-9, 1.0
    for _ in range(200):
        a = lo + (hi - lo) / 3.0
        b = hi - (hi - lo) / 3.0
        if (
            steady_state(m, u_peak, f_supply, a).torque
            < steady_state(m, u_peak, f_supply, b).torque
        ):
            lo = a
        else:
            hi = b
    s_bd = 0.5 * (lo + hi)
    if steady_state(m, u_peak, f_supply, s_bd).torque < torque:
        raise ValueError(f'torque {torque} N m exceeds the breakdown torque')
    lo, hi = 1e-12, s_bd
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if steady_state(m, u_peak, f_supply, mid).torque < torque:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def flux_buildup(m: MachineParams, isd: float, t: float) -> float:
    """Rotor flux after an isd step at t = 0 (ideal current source, field-oriented):
    psi_r(t) = Lm isd (1 - exp(-t/tau_r)) [Wb]."""
    return m.Lm * isd * (1.0 - math.exp(-t / m.tau_r))


def foc_steady_state(m: MachineParams, isd: float, isq: float, omega_mech: float) -> dict:
    """Field-oriented steady state at currents (isd, isq) [A] and speed [rad/s]:
    psi_r = Lm isd, omega_sl = Lm isq/(tau_r psi_r), T = 1.5 p kr psi_r isq,
    u_d = Rs isd - omega_s sigma Ls isq, u_q = Rs isq + omega_s Ls isd."""
    psi = m.Lm * isd
    w_sl = m.Lm * isq / (m.tau_r * psi)
    w_s = m.pole_pairs * omega_mech + w_sl
    sls = m.sigma * m.Ls
    return {
        'psi_r': psi,
        'omega_sl': w_sl,
        'omega_s': w_s,
        'torque': 1.5 * m.pole_pairs * m.kr * psi * isq,
        'u_d': m.Rs * isd - w_s * sls * isq,
        'u_q': m.Rs * isq + w_s * m.Ls * isd,
    }
