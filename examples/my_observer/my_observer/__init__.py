"""A new observer variant in under 50 lines: VESC-style flux integrator, rotor flux clamped."""
import math

import numpy as np
from fluxdrive.drive.observers import ES_EA, ES_EB, ES_LA, ES_LB, ES_N, ES_TH, ES_VALID, ES_W, Observer
from fluxdrive.drive.plant import FR_IA, FR_IB, FR_IC, FR_VAB, FR_VBC, FR_VCA


class ClampedFluxObserver(Observer):
    """eta' = v - R i - L di/dt, each axis of eta clamped to +-lambda; theta = atan2(eta)."""

    name = "clamped_flux"

    def __init__(self, card, clamp=1.0, speed_lpf_hz=20.0):
        self.ts, self.r, self.l = card.ts_s, card.resistance_ohm, card.inductance_h
        self.lim = float(clamp) * card.flux_linkage_vs
        self.a = 1.0 - math.exp(-2.0 * math.pi * float(speed_lpf_hz) * self.ts)
        self.reset()

    def reset(self):
        self.ip, self.eta, self.th, self.w = None, np.zeros(2), 0.0, 0.0

    def step(self, fr):
        ia = (2 * fr[FR_IA] - fr[FR_IB] - fr[FR_IC]) / 3          # Clarke
        ib = (fr[FR_IB] - fr[FR_IC]) / math.sqrt(3)
        va = (fr[FR_VAB] - fr[FR_VCA]) / 3                          # line -> alpha/beta
        vb = fr[FR_VBC] / math.sqrt(3)
        out = np.zeros(ES_N)
        i = np.array([ia, ib])
        if self.ip is None:
            self.ip = i
            return out
        e = np.array([va, vb]) - self.r * 0.5 * (i + self.ip) - self.l * (i - self.ip) / self.ts
        self.ip = i
        self.eta = np.clip(self.eta + self.ts * e, -self.lim, self.lim)
        th = math.atan2(self.eta[1], self.eta[0])
        dth = (th - self.th + math.pi) % (2 * math.pi) - math.pi
        self.th, self.w = th, self.w + self.a * (dth / self.ts - self.w)
        out[ES_TH], out[ES_W] = th, self.w
        out[ES_LA], out[ES_LB] = self.eta
        out[ES_EA], out[ES_EB] = e
        out[ES_VALID] = 1.0
        return out
