"""The layout of the drive kernels' arrays: which index of ``P``, ``S`` and ``out`` is what.

* ``P_*`` index ``P`` (``N_PARAMS`` constants, ``sim.make_param_array``);
* ``S_*`` index ``S`` (``N_STATE`` words: the whole simulator state; ``S[0:6]`` is the
  plant state [i_sa, i_sb, psi_ra, psi_rb, omega, theta]);
* ``F_*`` index a published row (``STATE_FIELDS``, the contract's, then ``EXTRA_FIELDS``);
* ``NOISE_COLS``: the columns of the noise block.

Pure data (no numba, no rclpy): the kernels (:mod:`.kernels`, :mod:`.plant`) compile these
values in as constants; docs/drive-model.md describes each.
"""

from __future__ import annotations

from . import contract

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
P_INV_WC = 15  # 1/omega_c (Coulomb smoothing; sim.friction_smoothing_speed)
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
# bench effects (docs/drive-model.md, "Bench effects"); each 0 = off
P_IOFF_A = 46  # current-sensor offset in alpha [A] (phase a sensor)
P_IOFF_B = 47  # ... in beta [A]: (off_a + 2 off_b)/sqrt(3)
P_STRIBECK = 48  # Stribeck gain sqrt(2e) (Ts - Tc)/ws [N m s/rad] (0 = off)
P_INV_WS2 = 49  # 1/ws^2 [s^2/rad^2]
P_VDT = 50  # inverter dead-time voltage error per leg [V]
P_RR_RISE = 51  # alpha dT: the relative rise of Rr over a run (0 = off)
P_INV_TTH = 52  # 1/tau_thermal [1/s]
P_LS_ON = 53  # 1: the load step's amplitude/instant vary (either below non-zero), 0 = off
P_LS_DELAY_N = 54  # largest delay of a load step [periods] (integer valued)
N_PARAMS = 55

#: The words of ``P`` that are a drive file's value as it is (its path in the
#: ``DriveConfig``: ``section.key`` or a top-level key), copied by ``sim.make_param_array``;
#: the other words are computed from them there.
FROM_CONFIG: dict[int, str] = {
    P_NP: 'machine.pole_pairs',
    P_LM: 'machine.Lm',
    P_LS: 'machine.Ls',
    P_LR: 'machine.Lr',
    P_KR: 'machine.kr',
    P_RSIG: 'machine.R_sigma',
    P_B: 'machine.B',
    P_TC: 'machine.coulomb_torque',
    P_UMAX: 'machine.u_max',
    P_ISD_REF: 'machine.rated_flux_current',
    P_ISQ_MAX: 'machine.isq_max',
    P_PSI_MIN: 'control.flux_floor',
    P_DELAY: 'control.computation_delay_steps',
    P_KT: 'machine.Kt',
    P_PSI_RATED: 'machine.rated_flux',
    P_RIP_AMP: 'disturbance.ripple_amplitude',
    P_RIP_HARM: 'disturbance.ripple_harmonic',
    P_RIP_PHASE: 'disturbance.ripple_phase',
    P_RS: 'machine.Rs',
    P_RR: 'machine.Rr',
    P_J: 'machine.J',
    P_CMD_DELAY: 'command_delay',
    P_IOFF_A: 'sensors.current_offset_a',
    P_VDT: 'machine.deadtime_voltage',
}

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
# the load step's variation (P_LS_ON): the command's last value, the value it will act
# with (command x amplitude factor), the periods until it acts, the value acting now
S_LS_CMD = 35
S_LS_TARGET = 36
S_LS_WAIT = 37
S_LS_ACT = 38
N_STATE = 39

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

#: i_alpha, i_beta, speed, random-load increment, encoder edge jitter [s], the load step's
#: relative amplitude error (N(0, std)) and its delay draw (uniform in [0, 1)): a step's
#: row serves a load step commanded then
NOISE_COLS = 7
NOISE_BASE_COLS = 4  # the first four: one stream (PCG64(seed)); the jitter its own (jumped)
N_AMP = 5  # column of the load step's amplitude error (stream PCG64(seed).jumped(2))
N_DELAY = 6  # column of its delay draw (the same stream)
