"""The driving example (flux_pll.py) made fast: the same equations, compiled with numba.

One jitted function steps one frame on a state vector; `run()` loops it over a block of
frames inside compiled code (replay, sweeps), `step()` calls it once per frame (a run this
variant drives, the graph's observer node).  Same numbers as FluxPllObserver (a test checks
them against each other)."""

import math

import numpy as np
from fluxdrive.drive.observers import ES_EA, ES_EB, ES_LA, ES_LB, ES_N, ES_TH, ES_VALID, ES_W
from fluxdrive.drive.plant import FR_IA, FR_IB, FR_IC, FR_VAB, FR_VBC, FR_VCA
from numba import njit

from my_observer.flux_pll import TWO_PI, FluxPllObserver

# state vector: previous current known, previous alpha/beta current, LPF state, rotation
# rate, PLL angle and frequency
S_HAVE, S_IA, S_IB, S_EA, S_EB, S_RATE, S_TH, S_INTEG, S_N = range(9)
# parameters: Ts, R, L, w_c, PLL kp/ki, LPF and rate-filter poles, |w| floor
P_TS, P_R, P_L, P_WC, P_KP, P_KI, P_AWC, P_ARATE, P_WFLOOR, P_N = range(10)


@njit(cache=True)
def step_kernel(fr, st, p, out):
    """One frame: FluxPllObserver.step on arrays (`out` zeroed by the caller)."""
    ia = (2.0 * fr[FR_IA] - fr[FR_IB] - fr[FR_IC]) / 3.0
    ib = (fr[FR_IB] - fr[FR_IC]) / math.sqrt(3.0)
    if st[S_HAVE] == 0.0:
        st[S_HAVE], st[S_IA], st[S_IB] = 1.0, ia, ib
        return
    ts, wc = p[P_TS], p[P_WC]
    va, vb = (fr[FR_VAB] - fr[FR_VCA]) / 3.0, fr[FR_VBC] / math.sqrt(3.0)
    pa, pb = st[S_IA], st[S_IB]
    st[S_IA], st[S_IB] = ia, ib
    xa = va - p[P_R] * 0.5 * (ia + pa) - p[P_L] * (ia - pa) / ts  # EMF over the step
    xb = vb - p[P_R] * 0.5 * (ib + pb) - p[P_L] * (ib - pb) / ts
    ga = (1.0 - p[P_AWC]) / wc
    ea, eb = st[S_EA], st[S_EB]
    na, nb = p[P_AWC] * ea + ga * xa, p[P_AWC] * eb + ga * xb
    rate = math.atan2(ea * nb - eb * na, ea * na + eb * nb) / ts
    st[S_RATE] = p[P_ARATE] * st[S_RATE] + (1.0 - p[P_ARATE]) * rate
    st[S_EA], st[S_EB] = na, nb
    w = st[S_RATE]
    if abs(w) < p[P_WFLOOR]:
        w = math.copysign(p[P_WFLOOR], w)
    g = wc / w  # inverse HPF (1 - j w_c/w)
    la, lb = na + g * nb, nb - g * na
    c, s = math.cos(st[S_TH]), math.sin(st[S_TH])
    err = math.atan2(lb * c - la * s, la * c + lb * s)  # flux angle in the estimated frame
    st[S_INTEG] += p[P_KI] * ts * err
    out[ES_TH], out[ES_W] = st[S_TH], st[S_INTEG]
    out[ES_LA], out[ES_LB], out[ES_EA], out[ES_EB] = la, lb, xa, xb
    out[ES_VALID] = 1.0 if abs(err) < 0.5 else 0.0
    th = st[S_TH] + ts * (p[P_KP] * err + st[S_INTEG])
    st[S_TH] = (th + math.pi) % TWO_PI - math.pi


@njit(cache=True)
def run_kernel(frames, st, p):
    est = np.zeros((frames.shape[0], ES_N))
    for k in range(frames.shape[0]):
        step_kernel(frames[k], st, p, est[k])
    return est


class FluxPllNumbaObserver(FluxPllObserver):
    """FluxPllObserver with its step compiled: the same constructor keywords."""

    name = "flux_pll_numba"

    def __init__(self, card, cutoff_hz=None, pll_hz=None, rate_lpf_hz=None):
        super().__init__(card, cutoff_hz, pll_hz, rate_lpf_hz)
        self.p = np.zeros(P_N)
        self.p[P_TS], self.p[P_R], self.p[P_L], self.p[P_WC] = self.ts, self.r, self.l, self.wc
        self.p[P_KP], self.p[P_KI], self.p[P_AWC] = self.kp, self.ki, self.a_wc
        self.p[P_ARATE], self.p[P_WFLOOR] = self.a_rate, self.w_floor

    def reset(self):
        self.st = np.zeros(S_N)

    def step(self, fr):
        out = np.zeros(ES_N)
        step_kernel(np.asarray(fr, dtype=np.float64), self.st, self.p, out)
        return out

    def run(self, frames):
        return run_kernel(np.ascontiguousarray(frames, dtype=np.float64), self.st, self.p)
