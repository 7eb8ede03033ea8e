"""A user variant that can drive: the flux observer with a PLL, in plain Python (no numba).

LPF 1/(s + w_c) of the EMF in place of the integrator, the inverse HPF (1 - j w_c/w) at the
filter output's own rotation rate (low-passed), and a type-2 PLL on the flux angle.  Written
from docs/engine.md, not from the kernels, so it is also an independent check of them."""

import math

import numpy as np
from fluxdrive.drive.observers import ES_EA, ES_EB, ES_LA, ES_LB, ES_N, ES_TH, ES_VALID, ES_W
from fluxdrive.drive.observers import Observer
from fluxdrive.drive.plant import FR_IA, FR_IB, FR_IC, FR_VAB, FR_VBC, FR_VCA

TWO_PI = 2.0 * math.pi


class FluxPllObserver(Observer):
    """Frequencies default to the card's per-unit rules (docs/engine.md): w_c 0.5 f_e, PLL
    0.125 f_e, rotation-rate LPF 0.01 f_e, |w| floored at f_e/40 rad/s."""

    name = "flux_pll"

    def __init__(self, card, cutoff_hz=None, pll_hz=None, rate_lpf_hz=None):
        f_e = card.rated_electrical_hz
        self.ts, self.r, self.l = card.ts_s, card.resistance_ohm, card.inductance_h
        self.wc = TWO_PI * float(cutoff_hz or 0.5 * f_e)
        wn = TWO_PI * float(pll_hz or 0.125 * f_e)
        self.kp, self.ki = 2.0 * wn, wn * wn
        self.a_wc = math.exp(-self.wc * self.ts)
        self.a_rate = math.exp(-TWO_PI * float(rate_lpf_hz or 0.01 * f_e) * self.ts)
        self.w_floor = f_e / 40.0
        self.reset()

    def reset(self):
        self.ip = None  # previous alpha/beta current
        self.ea = self.eb = 0.0  # LPF state (V s)
        self.w_rate = 0.0  # low-passed rotation rate of the LPF output (rad/s)
        self.th = self.integ = 0.0  # PLL angle for this sample, frequency estimate

    def step(self, fr):
        ia = (2.0 * fr[FR_IA] - fr[FR_IB] - fr[FR_IC]) / 3.0
        ib = (fr[FR_IB] - fr[FR_IC]) / math.sqrt(3.0)
        out = np.zeros(ES_N)
        if self.ip is None:
            self.ip = (ia, ib)
            return out
        va, vb = (fr[FR_VAB] - fr[FR_VCA]) / 3.0, fr[FR_VBC] / math.sqrt(3.0)
        pa, pb = self.ip
        self.ip = (ia, ib)
        xa = va - self.r * 0.5 * (ia + pa) - self.l * (ia - pa) / self.ts  # EMF over the step
        xb = vb - self.r * 0.5 * (ib + pb) - self.l * (ib - pb) / self.ts
        ga = (1.0 - self.a_wc) / self.wc
        na, nb = self.a_wc * self.ea + ga * xa, self.a_wc * self.eb + ga * xb
        rate = math.atan2(self.ea * nb - self.eb * na, self.ea * na + self.eb * nb) / self.ts
        self.w_rate = self.a_rate * self.w_rate + (1.0 - self.a_rate) * rate
        self.ea, self.eb = na, nb
        w = (
            self.w_rate
            if abs(self.w_rate) >= self.w_floor
            else math.copysign(self.w_floor, self.w_rate)
        )
        g = self.wc / w  # inverse HPF (1 - j w_c/w)
        la, lb = na + g * nb, nb - g * na
        c, s = math.cos(self.th), math.sin(self.th)
        err = math.atan2(lb * c - la * s, la * c + lb * s)  # flux angle in the estimated frame
        self.integ += self.ki * self.ts * err
        out[ES_TH], out[ES_W] = self.th, self.integ
        out[ES_LA], out[ES_LB], out[ES_EA], out[ES_EB] = la, lb, xa, xb
        out[ES_VALID] = 1.0 if abs(err) < 0.5 else 0.0
        th = self.th + self.ts * (self.kp * err + self.integ)
        self.th = (th + math.pi) % TWO_PI - math.pi
        return out
