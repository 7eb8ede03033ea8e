"""SPM machine, two-level inverter with deadtime, and sensors, simulated at switching level.

Conventions (docs/engine.md, timing convention): sample k is at t_k = k Ts (carrier valley).
`plant_advance` simulates the period [t_k, t_{k+1}] with the duty it is given (the duty the
controller computed from frame k-1), then samples frame k+1: currents at t_{k+1}, the captured
line voltages averaged over [t_k, t_{k+1}] and the duty that was applied over that period.

Inside each period the carrier-comparison instants of the three legs, each with its
deadtime window, split the period into up to 13 segments of constant leg state.  Across a
segment the stator equation  L di/dt = v - R i - e(theta)  is solved exactly (RL step
response, EMF at the segment midpoint).  In a deadtime window the leg voltage follows the
sign of its phase current (i > 0: lower diode, leg at 0; i < 0: upper diode, leg at Vdc),
so those segments are sub-stepped and the sign is re-checked at every sub-step.
The motor neutral floats: the amplitude-invariant Clarke transform removes the common mode.
"""

from __future__ import annotations

import math

import numpy as np
from numba import literally, njit

from fluxdrive.core.bench import BenchConfig
from fluxdrive.core.blocks import pwl, rng_normal, sign
from fluxdrive.core.layout import Layout
from fluxdrive.core.machine import MachineCard
from fluxdrive.core.transforms import SQRT3, clarke, inv_clarke

# ---- machine/inverter/sensor parameter vector (MP_*)
_MP = Layout("MP")
MP_R = _MP.index()  # stator resistance [ohm]
MP_L = _MP.index()  # synchronous inductance [H]
MP_LAM = _MP.index()  # magnet flux linkage [V s]
MP_P = _MP.index()  # pole pairs
MP_J = _MP.index()  # inertia [kg m^2]
MP_B = _MP.index()  # viscous friction [N m s/rad]
MP_VDC = _MP.index()  # DC bus [V]
MP_TS = _MP.index()  # PWM period [s]
MP_TD = _MP.index()  # deadtime [s]
MP_VDEV = _MP.index()  # device on-state drop [V]
MP_H5 = _MP.index()  # 5th flux harmonic [pu of lambda]
MP_H7 = _MP.index()  # 7th flux harmonic [pu of lambda]
MP_SAT = _MP.index()  # inductance drop per (i/I_rated)^2
MP_IRATED = _MP.index()  # rated current [A]
MP_ADC_LSB = _MP.index()  # current ADC step [A]
MP_ADC_RANGE = _MP.index()  # current ADC full scale [A]
MP_NOISE = _MP.index()  # current sensor noise, rms [A]
MP_OFF_A, MP_OFF_B, MP_OFF_C = _MP.indices(3)  # current sensor offsets [A]
MP_GAIN_A, MP_GAIN_B, MP_GAIN_C = _MP.indices(3)  # current sensor gains
MP_CAP_LEVELS = _MP.index()  # capture timer counts per period
MP_VDC_LSB = _MP.index()  # bus ADC step [V]
MP_VDC_RANGE = _MP.index()  # bus ADC full scale [V]
MP_VDC_NOISE = _MP.index()  # bus ADC noise, rms [V]
MP_ENC_CPR = _MP.index()  # encoder counts per mechanical revolution
MP_DEAD_SUBSTEPS = _MP.index()  # sub-steps of a deadtime segment
MP_VDC_GAIN = _MP.index()  # bus ADC gain error
# non-ideal bench (fluxdrive.core.bench; all zero = the ideal bench)
MP_CAP_ON = _MP.index()  # 1: line-voltage capture through comparator/link/timer edges
MP_CAP_VTH_PU = _MP.index()  # comparator threshold [pu of the bus]
MP_CAP_EDGE = _MP.index()  # switching edge 0 -> 100 % [s]
MP_CAP_DRISE = _MP.index()  # link delay of a pulse's start [s]
MP_CAP_DFALL = _MP.index()  # link delay of a pulse's end [s]
MP_CAP_MINPULSE = _MP.index()  # shortest registered pulse [s]
MP_CAP_JITTER = _MP.index()  # edge jitter, rms [s]
MP_CAP_TICK = _MP.index()  # capture timer tick [s]
MP_SKEW_ON = _MP.index()  # 1: phases sampled at their own instants
MP_SKEW_A, MP_SKEW_B, MP_SKEW_C = _MP.indices(3)  # sampled this long before the valley [s]
MP_TH_ON = _MP.index()  # 1: winding thermal model
MP_TH_RTH = _MP.index()  # thermal resistance winding -> ambient [K/W]
MP_TH_DECAY = _MP.index()  # exp(-Ts/tau)
MP_TH_ALPHA = _MP.index()  # copper tempco [1/K]
MP_TH_TREF = _MP.index()  # temperature of the card's resistance [deg C]
MP_TH_TAMB = _MP.index()  # ambient [deg C]
# spatial saturation: 5th and 7th magnet-flux harmonics at rated current [pu of lambda]
MP_SSAT_H5, MP_SSAT_H7 = _MP.indices(2)
# flux-state circuit (inductance saturation, phase asymmetry): the stator flux is integrated
MP_CIRC_ON = _MP.index()  # 1: integrate the armature flux (saturation or asymmetry on)
MP_SAT_ON = _MP.index()  # 1: L_d, L_q from the flux map (InductanceSaturation)
MP_SAT_KD, MP_SAT_S = _MP.indices(2)  # d-axis saturation gain [pu] and exponent
MP_SAT_KQ, MP_SAT_T = _MP.indices(2)  # q-axis saturation gain [pu] and exponent
MP_SAT_KC, MP_SAT_U, MP_SAT_V = _MP.indices(3)  # cross-saturation gain [pu], exponents
MP_LM_AA, MP_LM_AB, MP_LM_BB = _MP.indices(3)  # per-phase L multipliers as an alpha/beta matrix
MP_LI_AA, MP_LI_AB, MP_LI_BB = _MP.indices(3)  # its inverse
MP_RM_AA, MP_RM_AB, MP_RM_BB = _MP.indices(3)  # per-phase R multipliers, alpha/beta matrix
MP_COSS = _MP.index()  # device output capacitance [F] (0: instant deadtime commutation)
MP_SWN_A = _MP.index()  # switching-edge ringing at the edge, rms [A] (0: off)
MP_SWN_WINDOW = _MP.index()  # edges this long before a sample disturb it [s]
MP_SWN_DECAY = _MP.index()  # ringing decay time [s]
MP_N = _MP.close(globals())

# ---- plant state vector (PS_*)
_PS = Layout("PS")
PS_IA, PS_IB = _PS.indices(2)  # true stator current, alpha/beta [A]
PS_THM = _PS.index()  # mechanical angle (unwrapped) [rad]
PS_WM = _PS.index()  # mechanical speed [rad/s]
PS_T = _PS.index()  # time of the last sample [s]
PS_K = _PS.index()  # its index
PS_TE = _PS.index()  # average electrical torque over the last period [N m]
PS_TL = _PS.index()  # average load torque over the last period [N m]
PS_TW = _PS.index()  # winding temperature [deg C] (thermal model)
PS_SSAT_X = _PS.index()  # (|i|/I_rated)^2 of the spatial saturation applied over the last period
PS_N = _PS.close(globals())

# ---- frame vector (what the drive's MCU knows at sample k): FR_*
_FR = Layout("FR")
FR_IA, FR_IB, FR_IC = _FR.indices(3, "i_a i_b i_c")  # sampled phase currents [A]
# captured line voltages, average over the last period [V]
FR_VAB, FR_VBC, FR_VCA = _FR.indices(3, "v_ab v_bc v_ca")
FR_VDC = _FR.index("vdc")  # DC-bus ADC [V]
FR_DA, FR_DB, FR_DC = _FR.indices(3, "duty_a duty_b duty_c")  # applied over the last period
FR_EN = _FR.index("pwm_enabled")  # 1.0 if PWM was enabled over the last period
FR_ENC = _FR.index("encoder_counts")  # cumulative encoder counts
FR_SEQ = _FR.index("seq")  # sample index k
FR_FLAGS = _FR.index("flags")  # status bits (FLAG_*)
FR_N = _FR.close(globals())
# the frame's column names, in column order: the one naming of the frame row that the CAN
# protocol, captures and fault messages use
FRAME_COLUMNS: tuple[str, ...] = _FR.names
FLAG_CLIP = 1  # a current ADC channel clipped at full scale
# the power stage had no fresh duty command for this period (PhaseFrame.STATUS_STALE_COMMAND);
# with FR_EN = 0 its watchdog switched the PWM off: a lost interval (observers coast it)
FLAG_STALE = 16

# ---- truth vector (simulation only): TR_*
_TR = Layout("TR")
TR_THETA_E = _TR.index()  # electrical rotor angle in [0, 2 pi) [rad]
TR_WM = _TR.index()  # mechanical speed [rad/s]
TR_TE = _TR.index()  # electrical torque, average over the last period [N m]
TR_TL = _TR.index()  # load torque, average over the last period [N m]
TR_IA, TR_IB, TR_IC = _TR.indices(3)  # true phase currents [A]
TR_T = _TR.index()  # sample time [s]
TR_N = _TR.close(globals())

LEG_BOTTOM, LEG_TOP, LEG_DIODE = 0, 1, 2
CAP_MAX_EDGES = 32  # line-level edges recorded per period (a line has <= ~10)

# ---- a period's scratch (`plant_period`'s `work`): blocks, not fields, and no state (a
# period writes each entry before it reads it), so it is no Layout and not in PS_*; a loop
# allocates one and hands it to every period
W_EV = 0  # event times of the period (<= 20: two ends, 12 leg instants, 3 skewed samples)
W_VS = W_EV + 20  # volt-seconds real/ideal (6), skewed current samples (3), noise rms (3)
W_CAP_N = W_VS + 12  # the capture model's edge count per line (3)
W_CAP_T = W_CAP_N + 3  # its edge times, 3 lines x CAP_MAX_EDGES
W_CAP_S = W_CAP_T + 3 * CAP_MAX_EDGES  # its edge levels, 3 lines x CAP_MAX_EDGES
WORK_N = W_CAP_S + 3 * CAP_MAX_EDGES


def machine_params(
    card: MachineCard,
    current_offset_a=(0.0, 0.0, 0.0),
    current_gain=(1.0, 1.0, 1.0),
    dead_substeps: int = 4,
    deadtime_s: float | None = None,
    dc_bus_v: float | None = None,
    vdc_adc_gain: float = 1.0,
    bench: BenchConfig | None = None,
) -> np.ndarray:
    """Parameter vector for the plant kernels from a machine card, sensor faults and the
    non-ideal bench (None: ideal)."""
    mp = np.zeros(MP_N)
    mp[MP_R] = card.resistance_ohm
    mp[MP_L] = card.inductance_h
    mp[MP_LAM] = card.flux_linkage_vs
    mp[MP_P] = card.pole_pairs
    mp[MP_J] = card.inertia_kgm2
    mp[MP_B] = card.viscous_nms
    mp[MP_VDC] = card.dc_bus_v if dc_bus_v is None else dc_bus_v
    mp[MP_TS] = card.ts_s
    mp[MP_TD] = card.deadtime_s if deadtime_s is None else deadtime_s
    mp[MP_VDEV] = card.device_drop_v
    mp[MP_H5] = card.flux_h5
    mp[MP_H7] = card.flux_h7
    mp[MP_SAT] = card.saturation
    mp[MP_IRATED] = card.rated_current_a
    mp[MP_ADC_RANGE] = card.current_range_a
    mp[MP_ADC_LSB] = 2.0 * card.current_range_a / 2**card.current_adc_bits
    mp[MP_NOISE] = card.current_noise_a
    mp[MP_OFF_A : MP_OFF_C + 1] = current_offset_a
    mp[MP_GAIN_A : MP_GAIN_C + 1] = current_gain
    mp[MP_CAP_LEVELS] = 2.0**card.capture_bits
    mp[MP_VDC_RANGE] = card.dc_bus_range_v
    mp[MP_VDC_LSB] = card.dc_bus_range_v / 2**card.dc_bus_adc_bits
    mp[MP_VDC_NOISE] = card.dc_bus_noise_v
    mp[MP_ENC_CPR] = 4.0 * card.encoder_lines
    mp[MP_DEAD_SUBSTEPS] = dead_substeps
    mp[MP_VDC_GAIN] = vdc_adc_gain
    if bench is not None:
        _bench_params(mp, card, bench)
    return mp


def _bench_params(mp: np.ndarray, card: MachineCard, bench: BenchConfig) -> None:
    cap = bench.voltage_capture
    if cap is not None:
        bits = card.capture_bits if cap.resolution_bits is None else cap.resolution_bits
        mp[MP_CAP_ON] = 1.0
        mp[MP_CAP_VTH_PU] = cap.threshold_pu
        mp[MP_CAP_EDGE] = cap.edge_time_s
        mp[MP_CAP_DRISE] = cap.delay_rise_s
        mp[MP_CAP_DFALL] = cap.delay_fall_s
        mp[MP_CAP_MINPULSE] = cap.min_pulse_s
        mp[MP_CAP_JITTER] = cap.jitter_s
        mp[MP_CAP_TICK] = card.ts_s / 2.0**bits
    if bench.current_sample_skew_s is not None and any(bench.current_sample_skew_s):
        mp[MP_SKEW_ON] = 1.0
        mp[MP_SKEW_A : MP_SKEW_C + 1] = bench.current_sample_skew_s
    if (
        bench.thermal is not None
        and card.thermal_resistance_k_per_w > 0.0
        and card.thermal_time_constant_s > 0.0
    ):
        mp[MP_TH_ON] = 1.0
        mp[MP_TH_RTH] = card.thermal_resistance_k_per_w
        mp[MP_TH_DECAY] = math.exp(-card.ts_s / card.thermal_time_constant_s)
        mp[MP_TH_ALPHA] = card.copper_tempco_per_k
        mp[MP_TH_TREF] = card.resistance_ref_c
        mp[MP_TH_TAMB] = bench.thermal.ambient_c
    mp[MP_SSAT_H5], mp[MP_SSAT_H7] = bench.spatial_saturation_h5_h7()
    _circuit_params(mp, bench)
    if bench.current_sensor_gain is not None:
        mp[MP_GAIN_A : MP_GAIN_C + 1] *= bench.current_sensor_gain
    mp[MP_COSS] = bench.output_capacitance_f
    noise = bench.switching_noise
    if noise is not None and noise.ringing_a > 0.0 and noise.window_s > 0.0:
        mp[MP_SWN_A] = noise.ringing_a
        mp[MP_SWN_WINDOW] = noise.window_s
        mp[MP_SWN_DECAY] = noise.decay_s


def phase_matrix(k_abc) -> np.ndarray:
    """Per-phase multipliers k_a, k_b, k_c of a diagonal phase quantity (x_j = k_j y_j) as
    the symmetric alpha/beta matrix: Clarke(diag(k) inv_clarke(y)) for zero-sequence-free y."""
    ka, kb, kc = (float(x) for x in k_abc)
    off = (kc - kb) / (2.0 * SQRT3)
    return np.array([[(4.0 * ka + kb + kc) / 6.0, off], [off, 0.5 * (kb + kc)]])


def _circuit_params(mp: np.ndarray, bench: BenchConfig) -> None:
    """The flux-state circuit's numbers; all zero (branch off) for a linear, balanced machine."""
    unit = (1.0, 1.0, 1.0)
    sat = bench.inductance_saturation
    asym = bench.phase_asymmetry
    l_pu = unit if asym is None else asym.inductance_pu
    r_pu = unit if asym is None else asym.resistance_pu
    sat_on = sat is not None and sat.on
    if not sat_on and l_pu == unit and r_pu == unit:
        return
    mp[MP_CIRC_ON] = 1.0
    lm = phase_matrix(l_pu)
    li = np.linalg.inv(lm)
    rm = phase_matrix(r_pu)
    mp[MP_LM_AA], mp[MP_LM_AB], mp[MP_LM_BB] = lm[0, 0], lm[0, 1], lm[1, 1]
    mp[MP_LI_AA], mp[MP_LI_AB], mp[MP_LI_BB] = li[0, 0], li[0, 1], li[1, 1]
    mp[MP_RM_AA], mp[MP_RM_AB], mp[MP_RM_BB] = rm[0, 0], rm[0, 1], rm[1, 1]
    if sat is not None and sat_on:
        mp[MP_SAT_ON] = 1.0
        mp[MP_SAT_KD], mp[MP_SAT_S] = sat.d_pu, sat.d_exponent
        mp[MP_SAT_KQ], mp[MP_SAT_T] = sat.q_pu, sat.q_exponent
        mp[MP_SAT_KC] = sat.cross_pu
        mp[MP_SAT_U], mp[MP_SAT_V] = sat.cross_exponent_d, sat.cross_exponent_q


def plant_state(
    theta_e0_rad: float = 0.0, omega_m0: float = 0.0, pole_pairs: int = 4, winding_c: float = 25.0
):
    st = np.zeros(PS_N)
    st[PS_THM] = theta_e0_rad / pole_pairs
    st[PS_WM] = omega_m0
    st[PS_TW] = winding_c
    return st


def winding_resistance(st: np.ndarray, mp: np.ndarray) -> float:
    """The plant's winding resistance now [ohm] (the card's value unless the thermal model
    is on)."""
    return float(_resistance(st, mp))


# ------------------------------------------------------------------ machine equations
@njit(cache=True, inline="always")
def _magnet_flux_derivative(lam, h5, h7, th):
    """d(lambda_pm)/d(theta_e) as alpha/beta, including optional 5th/7th harmonics.
    lambda_pm(th) = lam [e^{j th} + h5 e^{-j5 th} + h7 e^{j7 th}]."""
    # j e^{j th} = (-sin, cos)
    s1 = math.sin(th)
    c1 = math.cos(th)
    da = -s1
    db = c1
    if h5 != 0.0 or h7 != 0.0:
        # d/dth of h5 e^{-j5th} = -5j h5 e^{-j5th} = -5 h5 (sin5th, cos5th)... as (re, im);
        # e^{j5th}, e^{j7th} by complex products from e^{jth} (cheaper than four sin/cos)
        c2 = c1 * c1 - s1 * s1
        s2 = 2.0 * s1 * c1
        c4 = c2 * c2 - s2 * s2
        s4 = 2.0 * s2 * c2
        c5 = c4 * c1 - s4 * s1
        s5 = s4 * c1 + c4 * s1
        c7 = c5 * c2 - s5 * s2
        s7 = s5 * c2 + c5 * s2
        da += -5.0 * h5 * s5 - 7.0 * h7 * s7
        db += -5.0 * h5 * c5 + 7.0 * h7 * c7
    return lam * da, lam * db


@njit(cache=True, inline="always")
def _inductance(mp, ia, ib):
    sat = mp[MP_SAT]
    if sat == 0.0:
        return mp[MP_L]
    x = (ia * ia + ib * ib) / (mp[MP_IRATED] * mp[MP_IRATED])
    return mp[MP_L] * max(1.0 - sat * x, 0.3)


@njit(cache=True, inline="always")
def _resistance(st, mp):
    """Winding resistance at the winding temperature: R_ref (1 + alpha (T_w - T_ref))."""
    if mp[MP_TH_ON] == 0.0:
        return mp[MP_R]
    return mp[MP_R] * (1.0 + mp[MP_TH_ALPHA] * (st[PS_TW] - mp[MP_TH_TREF]))


@njit(cache=True, inline="always")
def _thermal_step(st, mp, r, i2_mean):
    """One thermal node over one period (exact for a constant loss over the period):
    C dT/dt = P - (T - T_amb)/R_th, P = 1.5 R |i_ab|^2 (amplitude-invariant alpha/beta:
    the sum of the three phases' i^2 is 1.5 |i_ab|^2); decay = exp(-Ts/tau), tau = R_th C."""
    p_cu = 1.5 * r * i2_mean
    t_inf = mp[MP_TH_TAMB] + p_cu * mp[MP_TH_RTH]
    st[PS_TW] = t_inf + (st[PS_TW] - t_inf) * mp[MP_TH_DECAY]


@njit(cache=True, inline="always")
def _spatial_saturation(st, mp, ia, ib, th, lind):
    """Load-dependent magnet-flux harmonics h5 = s5 x, h7 = s7 x with x = (|i|/I_r)^2
    (lambda_pm gains lambda (h5 e^{-j5th} + h7 e^{j7th}); in the rotor frame d carries
    (h5 + h7) cos 6th, q (h7 - h5) sin 6th).  x is held over a period; when it changes at a
    period boundary the stator flux stays continuous, so the current takes the difference:
    L di = -lambda dx (s5 e^{-j5th} + s7 e^{j7th}).  Returns (ia, ib, x)."""
    x = (ia * ia + ib * ib) / (mp[MP_IRATED] * mp[MP_IRATED])
    dx = x - st[PS_SSAT_X]
    if dx != 0.0:
        k = mp[MP_LAM] * dx / lind
        s5 = mp[MP_SSAT_H5]
        s7 = mp[MP_SSAT_H7]
        ia -= k * (s5 * math.cos(5.0 * th) + s7 * math.cos(7.0 * th))
        ib -= k * (-s5 * math.sin(5.0 * th) + s7 * math.sin(7.0 * th))
        st[PS_SSAT_X] = x
    return ia, ib, x


@njit(cache=True, inline="always")
def _flux_map(mp, x, y):
    """Current per unit of I_rated from armature flux per unit of L I_rated (d, q: x, y) by
    the flux map of InductanceSaturation, and its Jacobian d(i)/d(psi) (symmetric)."""
    kd = mp[MP_SAT_KD]
    kq = mp[MP_SAT_KQ]
    kc = mp[MP_SAT_KC]
    s_ = mp[MP_SAT_S]
    t_ = mp[MP_SAT_T]
    u_ = mp[MP_SAT_U]
    v_ = mp[MP_SAT_V]
    ax = abs(x)
    ay = abs(y)
    xs = ax**s_
    yt = ay**t_
    xu = ax**u_
    yv = ay**v_
    cd = kc / (v_ + 2.0) * xu * ay ** (v_ + 2.0)  # cross term of i_d / x
    cq = kc / (u_ + 2.0) * ax ** (u_ + 2.0) * yv  # cross term of i_q / y
    gd = x * (1.0 + kd * xs + cd)
    gq = y * (1.0 + kq * yt + cq)
    jdd = 1.0 + kd * (s_ + 1.0) * xs + (u_ + 1.0) * cd
    jqq = 1.0 + kq * (t_ + 1.0) * yt + (v_ + 1.0) * cq
    jdq = kc * x * xu * y * yv
    return gd, gq, jdd, jdq, jqq


@njit(cache=True, inline="always")
def _circuit_current(mp, psa, psb, th, lind):
    """Current (alpha/beta) from the armature flux psi - lambda_pm (alpha/beta): the per-phase
    inductance multipliers M give the balanced machine's flux x = M^-1 psi, the flux map (or
    x/L) its current.  Returns (i_alpha, i_beta, x_alpha, x_beta)."""
    xa = mp[MP_LI_AA] * psa + mp[MP_LI_AB] * psb
    xb = mp[MP_LI_AB] * psa + mp[MP_LI_BB] * psb
    if mp[MP_SAT_ON] == 0.0:
        return xa / lind, xb / lind, xa, xb
    c = math.cos(th)
    s = math.sin(th)
    irated = mp[MP_IRATED]
    psib = lind * irated
    gd, gq, _, _, _ = _flux_map(mp, (c * xa + s * xb) / psib, (c * xb - s * xa) / psib)
    return (c * gd - s * gq) * irated, (s * gd + c * gq) * irated, xa, xb


@njit(cache=True)
def _circuit_flux(mp, ia, ib, th, lind):
    """The armature flux (alpha/beta) that carries current (ia, ib): the flux map inverted
    by Newton (it is monotonic and convex, so Newton from the linear flux converges), then
    psi = M x."""
    xa = lind * ia
    xb = lind * ib
    if mp[MP_SAT_ON] > 0.0:
        c = math.cos(th)
        s = math.sin(th)
        irated = mp[MP_IRATED]
        td = (c * ia + s * ib) / irated
        tq = (c * ib - s * ia) / irated
        x = td
        y = tq
        for _ in range(50):
            gd, gq, jdd, jdq, jqq = _flux_map(mp, x, y)
            rd = gd - td
            rq = gq - tq
            det = jdd * jqq - jdq * jdq
            x -= (jqq * rd - jdq * rq) / det
            y -= (jdd * rq - jdq * rd) / det
            if abs(rd) + abs(rq) < 1e-14:
                break
        psib = lind * irated
        xa = (c * x - s * y) * psib
        xb = (s * x + c * y) * psib
    return mp[MP_LM_AA] * xa + mp[MP_LM_AB] * xb, mp[MP_LM_AB] * xa + mp[MP_LM_BB] * xb


@njit(cache=True, inline="always")
def _circuit_step(mp, psa, psb, ia, ib, va, vb, ea, eb, r, hs, th, lind):
    """One midpoint (RK2) step of d(psi)/dt = v - R M_R i(psi) - e over hs.  Returns the new
    flux, current, and the balanced flux x and current at the midpoint (for the torque)."""
    ra = r * (mp[MP_RM_AA] * ia + mp[MP_RM_AB] * ib)
    rb = r * (mp[MP_RM_AB] * ia + mp[MP_RM_BB] * ib)
    pma = psa + 0.5 * hs * (va - ra - ea)
    pmb = psb + 0.5 * hs * (vb - rb - eb)
    ima, imb, xma, xmb = _circuit_current(mp, pma, pmb, th, lind)
    ra = r * (mp[MP_RM_AA] * ima + mp[MP_RM_AB] * imb)
    rb = r * (mp[MP_RM_AB] * ima + mp[MP_RM_BB] * imb)
    psa += hs * (va - ra - ea)
    psb += hs * (vb - rb - eb)
    ia_n, ib_n, _, _ = _circuit_current(mp, psa, psb, th, lind)
    return psa, psb, ia_n, ib_n, xma, xmb, ima, imb


@njit(cache=True, inline="always")
def _leg_voltage(state, i_phase, vdc, vdev):
    """Leg-to-negative-rail voltage for a leg state and its phase current.
    Returns (real voltage incl. device drops, ideal level seen by the capture timer)."""
    if state == LEG_TOP:
        return vdc - vdev * sign(i_phase), vdc
    if state == LEG_BOTTOM:
        return -vdev * sign(i_phase), 0.0
    # both switches off: the freewheeling diode picked by the current sign conducts
    if i_phase > 0.0:
        return -vdev, 0.0
    if i_phase < 0.0:
        return vdc + vdev, vdc
    return 0.5 * vdc, 0.5 * vdc  # no current: the leg floats (only exactly at i = 0)


@njit(cache=True, inline="always")
def _ramp_mean(t0, t1, tc):
    """Mean over [t0, t1] (times since the ramp's start) of min(1, t/tc)."""
    g0 = t0 * t0 / (2.0 * tc) if t0 < tc else t0 - 0.5 * tc
    g1 = t1 * t1 / (2.0 * tc) if t1 < tc else t1 - 0.5 * tc
    return (g1 - g0) / (t1 - t0)


@njit(cache=True, inline="always")
def _ramp_above_half(t0, t1, tc):
    """Fraction of [t0, t1] (times since the ramp's start) where min(1, t/tc) >= 1/2."""
    return (t1 - min(max(0.5 * tc, t0), t1)) / (t1 - t0)


@njit(cache=True, inline="always")
def _leg_voltage_coss(state, i_phase, vdc, vdev, u0, hs, t1, t2, td, coss):
    """_leg_voltage over the sub-step [u0, u0 + hs] with the devices' output capacitance:
    in a deadtime window the current that would flip the leg to the other diode charges
    2 C_oss through V_dc first, a ramp of t_c = 2 C_oss V_dc/|i|; the next gate turn-on ends
    the window (hard switching).  Returns the mean leg voltage and the ideal level the
    capture sees (the level flips where the ramp crosses half the bus)."""
    if state != LEG_DIODE or i_phase == 0.0:
        return _leg_voltage(state, i_phase, vdc, vdev)
    tc = 2.0 * coss * vdc / abs(i_phase)
    if u0 < t2 or t2 < t1 + td:  # the bottom switch turned off at t1: the leg was at 0
        if i_phase > 0.0:
            return -vdev, 0.0  # the bottom diode takes the current, no swing
        w0 = u0 - t1
        f = _ramp_mean(w0, w0 + hs, tc)
        return vdev + f * vdc, vdc * _ramp_above_half(w0, w0 + hs, tc)
    if i_phase < 0.0:  # after the top switch turned off: the leg was at V_dc
        return vdc + vdev, vdc
    w0 = u0 - t2
    f = _ramp_mean(w0, w0 + hs, tc)
    return (1.0 - f) * vdc - vdev, vdc * (1.0 - _ramp_above_half(w0, w0 + hs, tc))


@njit(cache=True, inline="always")
def _switching_noise_rms(mp, vs_out, enabled, ia, ib, t1a, t2a, t1b, t2b, t1c, t2c):
    """Rms of the switching-synchronous disturbance of each phase's sample into
    vs_out[9:12]: every leg's voltage edge dt (< window) before the sample instant adds
    ringing^2 exp(-2 dt/decay) to the variance.  A leg's voltage edges: for i > 0 at the top
    switch's turn-on (t1 + td) and turn-off (t2); for i < 0 at t1 and t2 + td."""
    ts = mp[MP_TS]
    td = mp[MP_TD]
    a0 = mp[MP_SWN_A]
    win = mp[MP_SWN_WINDOW]
    tau = mp[MP_SWN_DECAY]
    for j in range(3):
        vs_out[9 + j] = 0.0
    if not enabled:
        return
    pa, pb, pc = inv_clarke(ia, ib)
    for j in range(3):
        t_sample = ts - (mp[MP_SKEW_A + j] if mp[MP_SKEW_ON] > 0.0 else 0.0)
        var = 0.0
        for leg in range(3):
            i_leg = pa if leg == 0 else (pb if leg == 1 else pc)
            t1 = t1a if leg == 0 else (t1b if leg == 1 else t1c)
            t2 = t2a if leg == 0 else (t2b if leg == 1 else t2c)
            up = t1 + td if i_leg > 0.0 else t1
            down = t2 if i_leg > 0.0 else t2 + td
            for te in (up, down):
                dt = t_sample - te
                if 0.0 < te < ts and 0.0 <= dt < win:
                    var += a0 * a0 * math.exp(-2.0 * dt / tau)
        vs_out[9 + j] = math.sqrt(var)


@njit(cache=True, inline="always")
def _leg_state(t, t1, t2, td, enabled):
    """Centre-aligned leg: top gate on over [t1+td, t2], bottom gate on outside
    [t1, t2+td]; in between neither conducts (deadtime)."""
    if not enabled:
        return LEG_DIODE
    if t < t1 or t >= t2 + td:
        return LEG_BOTTOM
    if t >= t1 + td and t < t2:
        return LEG_TOP
    return LEG_DIODE


@njit(cache=True)
def _insertion_sort(a, n):
    for i in range(1, n):
        x = a[i]
        j = i - 1
        while j >= 0 and a[j] > x:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = x


@njit(cache=True, inline="always")
def _cap_track(cap_t, cap_s, cap_n, j, t, v_line, vdc):
    """Record an edge of line j's ideal level (-1, 0, +1 of the bus) at time t."""
    s = 0.0
    if v_line > 0.5 * vdc:
        s = 1.0
    elif v_line < -0.5 * vdc:
        s = -1.0
    n = int(cap_n[j])
    if (n == 0 or cap_s[j, n - 1] != s) and n < cap_t.shape[1]:
        cap_t[j, n] = t
        cap_s[j, n] = s
        cap_n[j] = n + 1


@njit(cache=True, inline="always")
def _switching_events(mp, ev, enabled, skew_on, t1a, t2a, t1b, t2b, t1c, t2c):
    """Sorted instants in [0, Ts] where a leg state can change (each leg's comparator
    crossings and the ends of their deadtime windows) or a skewed current sample is taken;
    returns their count."""
    ts = mp[MP_TS]
    td = mp[MP_TD]
    n = 0
    ev[n] = 0.0
    n += 1
    if enabled:
        for tx in (
            t1a,
            t1a + td,
            t2a,
            t2a + td,
            t1b,
            t1b + td,
            t2b,
            t2b + td,
            t1c,
            t1c + td,
            t2c,
            t2c + td,
        ):
            if 0.0 < tx < ts:
                ev[n] = tx
                n += 1
    if skew_on:
        # phase j is sampled skew_j before the next valley: a segment boundary there
        for j in range(3):
            if mp[MP_SKEW_A + j] > 0.0:
                ev[n] = ts - mp[MP_SKEW_A + j]
                n += 1
    ev[n] = ts
    n += 1
    _insertion_sort(ev, n)
    return n


@njit(cache=True, inline="always")
def _phase_current_sample(vs_out, j, ia, ib):
    """Phase j's current at its (skewed) sampling instant into vs_out[6 + j]."""
    pa_, pb_, pc_ = inv_clarke(ia, ib)
    vs_out[6 + j] = pa_ if j == 0 else (pb_ if j == 1 else pc_)


@njit(cache=True, inline="always")
def _mechanics(st, mp, wm, thm0, te, tl):
    """Speed and angle over the period (semi-implicit in the viscous term)."""
    ts = mp[MP_TS]
    j = mp[MP_J]
    bv = mp[MP_B]
    wm_new = (wm * (j / ts) + te - tl) / (j / ts + bv)
    st[PS_THM] = thm0 + 0.5 * (wm + wm_new) * ts
    st[PS_WM] = wm_new


@njit(cache=True)
def _period(st, mp, da, db, dc, enabled, t_load, ev, vs_out, cap_t, cap_s, cap_n, effects):
    """Integrate [t_k, t_k + Ts] at switching level.  Writes the line volt-seconds
    (real and ideal-level) into vs_out[0:6], the phase currents at the skewed sampling
    instants into vs_out[6:9] and the switching-noise rms into vs_out[9:12]; records
    line-level edges for the capture model (cap_*); updates currents, speed, angle, winding
    temperature.  `effects` is a constant at the call (numba compiles one variant per
    value): False leaves out the bench-effect branches (flux-state circuit, C_oss
    commutation, switching noise), which must all be off in `mp`; each is written
    `if effects and ...`, a branch on the argument itself, which numba prunes before it
    compiles (and inlines) the branch's helpers."""
    literally(effects)
    ts = mp[MP_TS]
    td = mp[MP_TD]
    vdc = mp[MP_VDC]
    vdev = mp[MP_VDEV]
    r = _resistance(st, mp)
    p = mp[MP_P]
    lam = mp[MP_LAM]
    n_sub = int(mp[MP_DEAD_SUBSTEPS])
    cap_on = enabled and mp[MP_CAP_ON] > 0.0
    skew_on = mp[MP_SKEW_ON] > 0.0
    th_on = mp[MP_TH_ON] > 0.0
    half = 0.5 * ts
    t1a = (1.0 - da) * half
    t2a = (1.0 + da) * half
    t1b = (1.0 - db) * half
    t2b = (1.0 + db) * half
    t1c = (1.0 - dc) * half
    t2c = (1.0 + dc) * half
    n = _switching_events(mp, ev, enabled, skew_on, t1a, t2a, t1b, t2b, t1c, t2c)

    ia = st[PS_IA]
    ib = st[PS_IB]
    wm = st[PS_WM]
    thm0 = st[PS_THM]
    we = p * wm
    lind = _inductance(mp, ia, ib)
    h5 = mp[MP_H5]
    h7 = mp[MP_H7]
    if mp[MP_SSAT_H5] != 0.0 or mp[MP_SSAT_H7] != 0.0:
        ia, ib, xl = _spatial_saturation(st, mp, ia, ib, p * thm0, lind)
        h5 += mp[MP_SSAT_H5] * xl
        h7 += mp[MP_SSAT_H7] * xl
    circ_on = mp[MP_CIRC_ON] > 0.0
    psa = 0.0
    psb = 0.0
    if effects and circ_on:
        psa, psb = _circuit_flux(mp, ia, ib, p * thm0, lind)
    coss = mp[MP_COSS]
    if effects and mp[MP_SWN_A] > 0.0:
        _switching_noise_rms(mp, vs_out, enabled, ia, ib, t1a, t2a, t1b, t2b, t1c, t2c)
    # line volt-seconds, real (v_*) and ideal-level (q_*), in registers: stores into vs_out
    # would be reloaded after every store the compiler cannot prove apart (cap_t, st)
    v_ab = v_bc = v_ca = q_ab = q_bc = q_ca = 0.0
    te_int = 0.0
    i2_int = 0.0
    if cap_on:
        for j in range(3):
            cap_n[j] = 0.0
    zero_lock = (not enabled) and (ia * ia + ib * ib) < 1e-6
    for s in range(n - 1):
        ta = ev[s]
        tb = ev[s + 1]
        if skew_on:
            for j in range(3):
                if ta == ts - mp[MP_SKEW_A + j]:
                    _phase_current_sample(vs_out, j, ia, ib)
        h = tb - ta
        if h <= 1e-15:
            continue
        tm = 0.5 * (ta + tb)
        sa = _leg_state(tm, t1a, t2a, td, enabled)
        sb = _leg_state(tm, t1b, t2b, td, enabled)
        sc = _leg_state(tm, t1c, t2c, td, enabled)
        nsub = 1
        if sa == LEG_DIODE or sb == LEG_DIODE or sc == LEG_DIODE:
            nsub = n_sub
        hs = h / nsub
        a_rl = math.exp(-r * hs / lind)
        for u in range(nsub):
            tmid = ta + (u + 0.5) * hs
            th = p * (thm0 + wm * tmid)
            dla, dlb = _magnet_flux_derivative(lam, h5, h7, th)
            ea = we * dla
            eb = we * dlb
            if zero_lock:
                # PWM off, no current, EMF below the bus: all diodes block, legs float.
                pa, pb, pc = inv_clarke(ea, eb)
                va0 = pa + 0.5 * vdc
                vb0 = pb + 0.5 * vdc
                vc0 = pc + 0.5 * vdc
                if max(pa, pb, pc) - min(pa, pb, pc) < vdc:
                    v_ab += (va0 - vb0) * hs  # the capture sees the same levels
                    v_bc += (vb0 - vc0) * hs
                    v_ca += (vc0 - va0) * hs
                    q_ab += (va0 - vb0) * hs
                    q_bc += (vb0 - vc0) * hs
                    q_ca += (vc0 - va0) * hs
                    continue
                zero_lock = False
            iph_a, iph_b, iph_c = inv_clarke(ia, ib)
            if effects and coss > 0.0 and enabled:
                u0 = ta + u * hs
                va0, qa = _leg_voltage_coss(sa, iph_a, vdc, vdev, u0, hs, t1a, t2a, td, coss)
                vb0, qb = _leg_voltage_coss(sb, iph_b, vdc, vdev, u0, hs, t1b, t2b, td, coss)
                vc0, qc = _leg_voltage_coss(sc, iph_c, vdc, vdev, u0, hs, t1c, t2c, td, coss)
            else:
                va0, qa = _leg_voltage(sa, iph_a, vdc, vdev)
                vb0, qb = _leg_voltage(sb, iph_b, vdc, vdev)
                vc0, qc = _leg_voltage(sc, iph_c, vdc, vdev)
            if cap_on:
                t_sub = ta + u * hs
                _cap_track(cap_t, cap_s, cap_n, 0, t_sub, qa - qb, vdc)
                _cap_track(cap_t, cap_s, cap_n, 1, t_sub, qb - qc, vdc)
                _cap_track(cap_t, cap_s, cap_n, 2, t_sub, qc - qa, vdc)
            va, vb = clarke(va0, vb0, vc0)
            if effects and circ_on:  # flux-state circuit: saturation / asymmetry (midpoint steps)
                psa, psb, ia_n, ib_n, xma, xmb, ima, imb = _circuit_step(
                    mp, psa, psb, ia, ib, va, vb, ea, eb, r, hs, th, lind
                )
                # reluctance torque of the saturated machine, 1.5 p (x x i); zero when linear
                te_int += 1.5 * p * (xma * imb - xmb * ima) * hs
            elif r > 0.0:  # exact RL step response over hs (v and e held)
                ia_n = a_rl * ia + (1.0 - a_rl) * (va - ea) / r
                ib_n = a_rl * ib + (1.0 - a_rl) * (vb - eb) / r
            else:
                ia_n = ia + hs * (va - ea) / lind
                ib_n = ib + hs * (vb - eb) / lind
            # torque from d(lambda_pm)/d(theta) x i (power balance), average current
            te_int += 1.5 * p * (dla * 0.5 * (ia + ia_n) + dlb * 0.5 * (ib + ib_n)) * hs
            if th_on:
                i2_int += 0.5 * (ia * ia + ib * ib + ia_n * ia_n + ib_n * ib_n) * hs
            if not enabled:
                # diode commutation ends when a phase current reaches zero: clamp
                na, nb, nc = inv_clarke(ia_n, ib_n)
                if na * iph_a < 0.0 or nb * iph_b < 0.0 or nc * iph_c < 0.0:
                    ia_n = 0.0
                    ib_n = 0.0
                    psa = 0.0
                    psb = 0.0
                    zero_lock = True
            ia = ia_n
            ib = ib_n
            # line volt-seconds: real leg voltages, and the ideal levels the capture sees
            v_ab += (va0 - vb0) * hs
            v_bc += (vb0 - vc0) * hs
            v_ca += (vc0 - va0) * hs
            q_ab += (qa - qb) * hs
            q_bc += (qb - qc) * hs
            q_ca += (qc - qa) * hs
    vs_out[0] = v_ab
    vs_out[1] = v_bc
    vs_out[2] = v_ca
    vs_out[3] = q_ab
    vs_out[4] = q_bc
    vs_out[5] = q_ca
    if skew_on:
        for j in range(3):
            if mp[MP_SKEW_A + j] == 0.0:
                _phase_current_sample(vs_out, j, ia, ib)
    if th_on:
        _thermal_step(st, mp, r, i2_int / ts)
    te = te_int / ts
    _mechanics(st, mp, wm, thm0, te, t_load)
    st[PS_IA] = ia
    st[PS_IB] = ib
    st[PS_TE] = te
    st[PS_TL] = t_load


@njit(cache=True)
def _effects_on(mp):
    """Is any bench effect on that `_period(..., False)` leaves out?"""
    return mp[MP_CIRC_ON] > 0.0 or mp[MP_COSS] > 0.0 or mp[MP_SWN_A] > 0.0


@njit(cache=True)
def _simulate_period(st, mp, da, db, dc, enabled, t_load, ev, vs_out, cap_t, cap_s, cap_n):
    """`_period` in the variant `mp` needs, chosen per period (one branch): the effect
    branches, loop-invariant as they are, slow the sub-step loop of a machine without them."""
    if _effects_on(mp):
        _period(st, mp, da, db, dc, enabled, t_load, ev, vs_out, cap_t, cap_s, cap_n, True)
    else:
        _period(st, mp, da, db, dc, enabled, t_load, ev, vs_out, cap_t, cap_s, cap_n, False)


@njit(cache=True)
def _adc(x, lsb, full_scale):
    q = math.floor(x / lsb + 0.5) * lsb
    if q > full_scale:
        return full_scale, True
    if q < -full_scale:
        return -full_scale, True
    return q, False


@njit(cache=True)
def _capture_line(mp, rng, cap_t, cap_s, n, j, ts):
    """Registered high time of line j over the period, signed, as a fraction of Ts.

    Each run of constant nonzero level [t0, t1] is a pulse.  Its edges ramp over t_e
    (0 -> 100 % of the bus, centred on the ideal edge); the comparator (threshold v_th, per
    unit of the bus) toggles at t0 - t_e/2 + v_th t_e and t1 - t_e/2 + (pk - v_th) t_e, pk =
    min(1, (t1 - t0)/t_e) the pulse's peak; the link adds t_rise / t_fall, the timer adds
    jitter and floors to its tick.  A pulse with pk < v_th, or registered narrower than the
    minimum pulse, is lost.  A run touching the window's boundary keeps that boundary (the
    level was already/still high there)."""
    tick = mp[MP_CAP_TICK]
    vth = mp[MP_CAP_VTH_PU]
    te = mp[MP_CAP_EDGE]
    jit = mp[MP_CAP_JITTER]
    acc = 0.0
    for m in range(n):
        s = cap_s[j, m]
        if s == 0.0:
            continue
        t0 = cap_t[j, m]
        t1 = cap_t[j, m + 1] if m + 1 < n else ts
        left = m > 0
        right = m + 1 < n
        pk = 1.0
        if te > 0.0 and left and right:
            pk = min(1.0, (t1 - t0) / te)
            if pk < vth:
                continue  # the ramp never reaches the threshold: the pulse vanishes
        r0 = 0.0
        if left:
            r0 = t0 - 0.5 * te + vth * te + mp[MP_CAP_DRISE]
            if jit > 0.0:
                r0 += jit * rng_normal(rng)
            r0 = min(max(math.floor(r0 / tick) * tick, 0.0), ts)
        r1 = ts
        if right:
            r1 = t1 - 0.5 * te + (pk - vth) * te + mp[MP_CAP_DFALL]
            if jit > 0.0:
                r1 += jit * rng_normal(rng)
            r1 = min(max(math.floor(r1 / tick) * tick, 0.0), ts)
        w = r1 - r0
        if left and right and w < mp[MP_CAP_MINPULSE]:
            continue  # shorter than the capture input's minimum pulse: not registered
        if w > 0.0:
            acc += s * w
    return acc / ts


@njit(cache=True)
def _sample(st, mp, rng, vs, da, db, dc, enabled, frame, truth, cap_t, cap_s, cap_n):
    """Fill frame/truth for the sample at the end of the period just simulated."""
    ts = mp[MP_TS]
    ia_t, ib_t, ic_t = inv_clarke(st[PS_IA], st[PS_IB])
    sa_, sb_, sc_ = ia_t, ib_t, ic_t
    if mp[MP_SKEW_ON] > 0.0:
        sa_, sb_, sc_ = vs[6], vs[7], vs[8]
    noise = mp[MP_NOISE]
    lsb = mp[MP_ADC_LSB]
    rng_ = mp[MP_ADC_RANGE]
    flags = 0
    n0 = rng_normal(rng) * noise if noise > 0.0 else 0.0
    n1 = rng_normal(rng) * noise if noise > 0.0 else 0.0
    n2 = rng_normal(rng) * noise if noise > 0.0 else 0.0
    if mp[MP_SWN_A] > 0.0:  # switching-synchronous ringing, drawn only where it is on
        n0 += rng_normal(rng) * vs[9] if vs[9] > 0.0 else 0.0
        n1 += rng_normal(rng) * vs[10] if vs[10] > 0.0 else 0.0
        n2 += rng_normal(rng) * vs[11] if vs[11] > 0.0 else 0.0
    x, c0 = _adc(mp[MP_GAIN_A] * sa_ + mp[MP_OFF_A] + n0, lsb, rng_)
    frame[FR_IA] = x
    x, c1 = _adc(mp[MP_GAIN_B] * sb_ + mp[MP_OFF_B] + n1, lsb, rng_)
    frame[FR_IB] = x
    x, c2 = _adc(mp[MP_GAIN_C] * sc_ + mp[MP_OFF_C] + n2, lsb, rng_)
    frame[FR_IC] = x
    if c0 or c1 or c2:
        flags |= FLAG_CLIP
    # DC bus ADC
    vdc = mp[MP_VDC]
    vn = rng_normal(rng) * mp[MP_VDC_NOISE] if mp[MP_VDC_NOISE] > 0.0 else 0.0
    vlsb = mp[MP_VDC_LSB]
    vdc_meas = min(
        max(math.floor((vdc * mp[MP_VDC_GAIN] + vn) / vlsb + 0.5) * vlsb, 0.0), mp[MP_VDC_RANGE]
    )
    frame[FR_VDC] = vdc_meas
    # capture timer: high time of each line-to-line PWM voltage, 2^bits counts a period,
    # scaled by the measured bus; device drops are invisible to it.
    if enabled and mp[MP_CAP_ON] > 0.0:
        for j in range(3):
            frac = _capture_line(mp, rng, cap_t, cap_s, int(cap_n[j]), j, ts)
            frame[FR_VAB + j] = frac * vdc_meas
    else:
        levels = mp[MP_CAP_LEVELS]
        for j in range(3):
            frac = vs[3 + j] / (ts * vdc)
            frame[FR_VAB + j] = math.floor(frac * levels + 0.5) / levels * vdc_meas
    frame[FR_DA] = da
    frame[FR_DB] = db
    frame[FR_DC] = dc
    frame[FR_EN] = 1.0 if enabled else 0.0
    frame[FR_ENC] = math.floor(st[PS_THM] / (2.0 * math.pi) * mp[MP_ENC_CPR])
    frame[FR_SEQ] = st[PS_K]
    frame[FR_FLAGS] = flags
    truth[TR_THETA_E] = (mp[MP_P] * st[PS_THM]) % (2.0 * math.pi)
    truth[TR_WM] = st[PS_WM]
    truth[TR_TE] = st[PS_TE]
    truth[TR_TL] = st[PS_TL]
    truth[TR_IA] = ia_t
    truth[TR_IB] = ib_t
    truth[TR_IC] = ic_t
    truth[TR_T] = st[PS_T]


# ---- load configuration (LD_*)
_LD = Layout("LD")
LD_DYNO = _LD.index()  # speed-proportional dyno torque [N m s/rad]
LD_BRAKE_BAND = _LD.index()  # passive-brake speed band [rad/s] (0: active torque)
LD_N = _LD.close(globals())


def load_config(dyno_nm_per_rad_s: float, brake_band_rad_s: float) -> np.ndarray:
    """The LD_* row of `load_torque`."""
    cfg = np.zeros(LD_N)
    cfg[LD_DYNO] = dyno_nm_per_rad_s
    cfg[LD_BRAKE_BAND] = brake_band_rad_s
    return cfg


@njit(cache=True)
def load_torque(t, wm, load_t, load_y, load_cfg):
    """Load torque [N m] opposing positive speed: a piecewise-linear profile (constant,
    step, ramp) plus a speed-proportional dyno term.  With a brake band > 0 the profile
    torque acts as a passive brake (hysteresis dyno): it opposes the motion and fades
    linearly to zero inside +-band, so it can stop the rotor but never drive it backwards.
    With band = 0 it is an active torque (a dyno in torque mode)."""
    tl = pwl(load_t, load_y, t)
    band = load_cfg[LD_BRAKE_BAND]
    if band > 0.0:
        tl *= min(max(wm / band, -1.0), 1.0)
    return tl + load_cfg[LD_DYNO] * wm


@njit(cache=True)
def plant_initial_frame(st, mp, rng, frame, truth):
    """Frame 0 (t = 0): currents sampled, no voltage history, PWM off."""
    vs = np.zeros(12)
    inv_a, inv_b, inv_c = inv_clarke(st[PS_IA], st[PS_IB])
    vs[6] = inv_a
    vs[7] = inv_b
    vs[8] = inv_c
    st[PS_T] = 0.0
    st[PS_K] = 0.0
    cap_t = np.zeros((1, 1))
    _sample(st, mp, rng, vs, 0.5, 0.5, 0.5, False, frame, truth, cap_t, cap_t, np.zeros(3))


@njit(cache=True)
def plant_period(st, mp, rng, duty, enabled, load_t, load_y, load_cfg, frame, truth, work):
    """Simulate one PWM period with `duty` (3 values in [0, 1]) and sample the next frame;
    `work` (WORK_N floats, contents free) is the period's scratch, allocated once by the
    caller's loop: a period allocates nothing."""
    ev = work[W_EV:W_VS]
    vs = work[W_VS:W_CAP_N]
    cap_n = work[W_CAP_N:W_CAP_T]
    if mp[MP_CAP_ON] > 0.0:
        cap_t = work[W_CAP_T:W_CAP_S].reshape((3, CAP_MAX_EDGES))
        cap_s = work[W_CAP_S:WORK_N].reshape((3, CAP_MAX_EDGES))
    else:
        cap_t = work[W_CAP_T : W_CAP_T + 1].reshape((1, 1))
        cap_s = cap_t
    da = min(max(duty[0], 0.0), 1.0)
    db = min(max(duty[1], 0.0), 1.0)
    dc = min(max(duty[2], 0.0), 1.0)
    tl = load_torque(st[PS_T], st[PS_WM], load_t, load_y, load_cfg)
    _simulate_period(st, mp, da, db, dc, enabled, tl, ev, vs, cap_t, cap_s, cap_n)
    st[PS_K] += 1.0
    st[PS_T] = st[PS_K] * mp[MP_TS]
    _sample(st, mp, rng, vs, da, db, dc, enabled, frame, truth, cap_t, cap_s, cap_n)


@njit(cache=True)
def plant_advance(st, mp, rng, duty, enabled, load_t, load_y, load_cfg, frame, truth):
    """`plant_period` with a scratch of its own: for callers that step one period at a time
    from Python (the plant node, the emulator), where one allocation is nothing."""
    work = np.empty(WORK_N)
    plant_period(st, mp, rng, duty, enabled, load_t, load_y, load_cfg, frame, truth, work)


def deadtime_volt_second_loss(vdc_v: float, deadtime_s: float, ts_s: float) -> float:
    """Expected average per-leg voltage error sign(i) Vdc td/Ts (docs/engine.md, inverter)."""
    return vdc_v * deadtime_s / ts_s


__all__ = [n for n in dir() if n.isupper() and not n.startswith("_")] + [
    "machine_params",
    "load_config",
    "plant_state",
    "winding_resistance",
    "plant_advance",
    "plant_period",
    "plant_initial_frame",
    "load_torque",
    "deadtime_volt_second_loss",
    "SQRT3",
]
