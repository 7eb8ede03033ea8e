"""Drive protection in the controller kernel: each trip goes to PWM off with a latched
reason, cleared only by an explicit reset (engine side)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.control import (
    CO_EN,
    CO_FAULT,
    CO_MODE,
    CO_N,
    CS_MODE,
    CS_N,
    FAULT_BAD_SAMPLE,
    FAULT_LOSS_OF_LOCK,
    FAULT_OVERCURRENT,
    FAULT_OVERCURRENT_I2T,
    FAULT_OVERSPEED,
    FAULT_OVERVOLTAGE,
    FAULT_UNDERVOLTAGE,
    MODE_CLOSED_LOOP,
    MODE_FAULT,
    ControllerConfig,
    controller_clear_fault,
    controller_reset,
    controller_step,
)
from fluxdrive.drive.observers import ES_N, ES_TH, ES_VALID, ES_W
from fluxdrive.drive.plant import FR_ENC, FR_IA, FR_IB, FR_IC, FR_N, FR_VDC

CARD = MachineCard()


def _setup(source="encoder"):
    cp = ControllerConfig(position_source=source).to_params(CARD)
    cs = np.zeros(CS_N)
    controller_reset(cs)
    return cs, cp


def _frame(i_a=0.0, vdc=72.0, enc=0.0):
    fr = np.zeros(FR_N)
    fr[FR_IA], fr[FR_IB], fr[FR_IC] = i_a, -i_a / 2, -i_a / 2
    fr[FR_VDC] = vdc
    fr[FR_ENC] = enc
    return fr


def _step(cs, cp, fr, est=None, w_ref=0.0):
    out = np.zeros(CO_N)
    controller_step(cs, cp, fr, np.zeros(ES_N) if est is None else est, w_ref, 0.0, out)
    return out


@pytest.mark.parametrize(
    "frame, code",
    [
        (_frame(i_a=2.2 * CARD.rated_current_a), FAULT_OVERCURRENT),
        (_frame(vdc=99.0), FAULT_OVERVOLTAGE),
        (_frame(vdc=10.0), FAULT_UNDERVOLTAGE),
        (_frame(i_a=float("nan")), FAULT_BAD_SAMPLE),
    ],
)
def test_instant_trips_latch_pwm_off_until_reset(frame, code):
    cs, cp = _setup()
    out = _step(cs, cp, frame)
    assert out[CO_EN] == 0.0 and out[CO_FAULT] == code and out[CO_MODE] == MODE_FAULT
    for _ in range(5):  # a healthy frame does not clear it
        out = _step(cs, cp, _frame())
        assert out[CO_EN] == 0.0 and out[CO_FAULT] == code
    assert controller_clear_fault(cs) == code
    out = _step(cs, cp, _frame())
    assert out[CO_EN] == 1.0 and out[CO_FAULT] == 0


def test_i2t_trips_after_the_integral_limit():
    """1.8 pu continuous: ((1.8)^2 - 1) * t = 10 pu^2 s  ->  t = 4.46 s."""
    cs, cp = _setup()
    fr = _frame(i_a=1.8 * CARD.rated_current_a)
    ts = CARD.ts_s
    expected = 10.0 / (1.8**2 - 1.0)
    tripped_at = None
    for k in range(int(6.0 / ts)):
        out = _step(cs, cp, fr)
        if out[CO_FAULT] != 0:
            tripped_at = k * ts
            break
    assert out[CO_FAULT] == FAULT_OVERCURRENT_I2T
    assert tripped_at == pytest.approx(expected, rel=0.01)


def test_overspeed_trips():
    cs, cp = _setup()
    cpr = 4 * CARD.encoder_lines
    w_m = 1.6 * CARD.rated_speed_rad_s
    counts_per_period = w_m * CARD.ts_s / (2 * math.pi) * cpr
    out = None
    for k in range(3000):
        out = _step(cs, cp, _frame(enc=math.floor(k * counts_per_period)))
        if out[CO_FAULT]:
            break
    assert out[CO_FAULT] == FAULT_OVERSPEED


@pytest.mark.parametrize(
    "closed_loop, valid, trips", [(False, 0.0, False), (False, 1.0, True), (True, 0.0, True)]
)
def test_overspeed_on_the_estimate_only_where_it_is_a_speed(closed_loop, valid, trips):
    """Sensorless, the over-speed trip reads the estimate's speed where it is one: in closed
    loop (the drive rides it; an invalid one is also loss of lock's business) or when the
    observer says it holds the rotor.  Before the handover an invalid estimate -- a PLL
    wandering on a flux near 0 after PWM off -- at twice the trip speed trips nothing."""
    cs, cp = _setup("estimate")
    if closed_loop:
        cs[CS_MODE] = MODE_CLOSED_LOOP
    est = np.zeros(ES_N)
    est[ES_W] = 2.0 * ControllerConfig().overspeed_pu * CARD.rated_speed_rad_s * CARD.pole_pairs
    est[ES_VALID] = valid
    codes = [_step(cs, cp, _frame(), est)[CO_FAULT] for _ in range(50)]
    assert bool(codes[0] == FAULT_OVERSPEED) == trips
    assert FAULT_OVERSPEED not in codes or trips


def test_loss_of_lock_after_invalid_timeout_in_closed_loop():
    cs, cp = _setup("estimate")
    cs[CS_MODE] = MODE_CLOSED_LOOP
    est = np.zeros(ES_N)
    est[ES_TH] = 0.0
    est[ES_W] = 25.0
    est[ES_VALID] = 0.0
    n_timeout = int(ControllerConfig().invalid_timeout_s / CARD.ts_s)
    tripped_at = None
    for k in range(n_timeout + 5):
        out = _step(cs, cp, _frame(), est, w_ref=6.0)
        if out[CO_FAULT]:
            tripped_at = k
            break
    assert out[CO_FAULT] == FAULT_LOSS_OF_LOCK
    assert tripped_at is not None and n_timeout - 2 <= tripped_at <= n_timeout + 2
