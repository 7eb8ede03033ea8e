"""The scope's instrument maths against known signals (fluxdrive.analysis.instrument) and
its raw export read back by the project's bag reader and an independent MCAP reader
(fluxdrive.io.scope_export)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluxdrive.analysis.instrument import (
    FLATTOP_A,
    EdgeTrigger,
    SampleBuffer,
    amplitude_spectrum,
    contiguous,
    in_view,
    window,
)
from fluxdrive.core.machine import ConfigError

TS = 1e-4  # 10 kHz


def tone(n: int, f_hz: float, a: float, dc: float = 0.0, phase: float = 0.3) -> np.ndarray:
    return dc + a * np.sin(2 * math.pi * f_hz * np.arange(n) * TS + phase)


@pytest.mark.parametrize("name", ["rectangular", "hann", "flattop"])
def test_tone_on_a_bin_reads_its_amplitude_in_hz(name):
    # 2000 samples at 10 kHz: bins every 5 Hz; 250 Hz lies on bin 50
    sp = amplitude_spectrum(tone(2000, 250.0, 1.7, dc=0.4), TS, name)
    assert sp.df_hz == pytest.approx(5.0)
    assert sp.f_hz[-1] == pytest.approx(5000.0)  # up to Nyquist
    f, a = sp.peak(1.0)
    assert f == pytest.approx(250.0)
    assert a == pytest.approx(1.7, rel=1e-9)
    assert sp.amplitude[0] == pytest.approx(0.4, rel=1e-9)  # DC reads the mean


def test_ac_coupling_removes_the_dc_leakage():
    # a tone on a large DC: the flat-top's main lobe (±4 bins) carries the DC into bins
    # 1..4, the first at a1/a0 = 1.93 times the DC; with the mean removed they are
    # clean and the tone reads the same
    x = tone(2000, 250.0, 0.5, dc=13.5)
    dc = amplitude_spectrum(x, TS, "flattop")
    assert dc.amplitude[1] == pytest.approx(13.5 * FLATTOP_A[1] / FLATTOP_A[0], rel=1e-6)
    ac = amplitude_spectrum(x, TS, "flattop", remove_mean=True)
    assert ac.amplitude[0] < 1e-12 and ac.amplitude[1:5].max() < 1e-12
    assert ac.peak(1.0) == pytest.approx((250.0, 0.5), rel=1e-9)


def test_window_shapes_and_coherent_gains():
    n = 4096
    assert window("rectangular", n).sum() == n
    assert window("hann", n).sum() == pytest.approx(n / 2)  # coherent gain 1/2
    assert window("flattop", n).sum() == pytest.approx(n * FLATTOP_A[0])
    assert window("hann", n)[0] == 0.0 and window("hann", n)[n // 2] == pytest.approx(1.0)
    assert window("flattop", n).max() == pytest.approx(sum(FLATTOP_A), rel=1e-6)


def cosine_sum_response(a: tuple[float, ...], delta_bins: float) -> float:
    """A cosine-sum window's (w = Σ (-1)^k a_k cos(2πkn/N)) response to a tone delta_bins
    off a bin, relative to on the bin: a sum of sincs shifted by k bins (large N), whose
    signs the DFT's linear phase (-1)^k cancels against the window's."""
    r = a[0] * np.sinc(delta_bins) + sum(
        ak / 2 * (np.sinc(delta_bins - k) + np.sinc(delta_bins + k)) for k, ak in enumerate(a) if k
    )
    return float(abs(r) / a[0])


@pytest.mark.parametrize(
    ("name", "coeffs", "loss"),
    # a tone half a bin off: the window's scalloping loss
    [("rectangular", (1.0,), 0.363), ("hann", (0.5, 0.5), 0.151), ("flattop", FLATTOP_A, 0.0011)],
)
def test_scalloping_between_bins(name, coeffs, loss):
    # 8000 samples: bins 1.25 Hz apart; 253.125 Hz is half-way between 252.5 and 253.75
    sp = amplitude_spectrum(tone(8000, 253.125, 1.0), TS, name)
    f, a = sp.peak(200.0, 300.0)
    assert abs(f - 253.125) == pytest.approx(0.625)
    # within the leakage of the tone's negative-frequency image, 405 bins away: the
    # rectangular window's sidelobe there is 1/(π·405) = 8e-4, the others' far less
    assert a == pytest.approx(cosine_sum_response(coeffs, 0.5), abs=1e-3)
    assert 1 - a == pytest.approx(loss, abs=1e-3)  # the figures the module doc states


def test_bad_window_and_samples_are_one_line():
    with pytest.raises(ConfigError, match="'blackman' is not one of rectangular, hann, flattop"):
        window("blackman", 8)
    with pytest.raises(ValueError, match="NaN"):
        amplitude_spectrum(np.array([1.0, np.nan, 2.0]), TS)


def rising_crossings(f_hz: float, level: float, a: float, phase: float, n: int) -> list[int]:
    """The first sample at or above `level` of each upward crossing of a sin(2πft + phase)."""
    x = tone(n, f_hz, a, phase=phase)
    up = np.flatnonzero((x[1:] >= level) & (x[:-1] < level)) + 1
    return up.tolist()


def test_edge_trigger_fires_every_edge_and_rearms():
    n = 5000  # 0.5 s of a 50 Hz tone: 25 rising edges through 0.3
    x = tone(n, 50.0, 1.0, phase=0.0)
    expected = rising_crossings(50.0, 0.3, 1.0, 0.0, n)
    trig = EdgeTrigger("rising", level=0.3, hysteresis=0.1)
    ev = trig.feed(np.arange(n), x)
    assert [e.seq for e in ev] == expected and len(ev) == 25
    assert not any(e.auto for e in ev)
    # in blocks of any size (as envelopes arrive), overlapping ones included: the same
    trig2 = EdgeTrigger("rising", level=0.3, hysteresis=0.1)
    got: list[int] = []
    rng = np.random.default_rng(3)
    i = 0
    while i < n:
        j = min(n, i + int(rng.integers(1, 700)))
        lo = max(0, i - 5)  # 5 samples again: ignored
        got += [e.seq for e in trig2.feed(np.arange(lo, j), x[lo:j])]
        i = j
    assert got == expected


def test_falling_edge_and_hysteresis_against_noise():
    n = 4000
    rng = np.random.default_rng(7)
    clean = tone(n, 25.0, 1.0, phase=0.0)
    noisy = clean + rng.uniform(-0.05, 0.05, n)
    falls = np.flatnonzero((clean[1:] < 0) & (clean[:-1] >= 0)) + 1  # 10 falling edges
    with_h = EdgeTrigger("falling", level=0.0, hysteresis=0.2).feed(np.arange(n), noisy)
    assert len(with_h) == len(falls) == 10
    # each within the noise's reach of the clean crossing: |Δx| <= 0.05 at slope 2π·25
    reach = int(math.ceil(0.05 / (2 * math.pi * 25 * TS)))
    assert all(abs(e.seq - f) <= reach for e, f in zip(with_h, falls, strict=True))
    # without hysteresis the noise fires the trigger several times per edge
    without = EdgeTrigger("falling", level=0.0, hysteresis=0.0).feed(np.arange(n), noisy)
    assert len(without) > len(falls)


def test_holdoff_single_and_auto_modes():
    n = 5000
    x = tone(n, 50.0, 1.0, phase=0.0)
    edges = rising_crossings(50.0, 0.0, 1.0, 0.0, n)[:]
    edges = [e for e in edges if e > 0]
    # hold off 1.5 periods after each firing: every second edge
    held = EdgeTrigger("rising", 0.0, 0.1, holdoff_samples=300).feed(np.arange(n), x)
    assert [e.seq for e in held] == edges[::2]
    # single: once, then nothing until armed again, then the next edge
    single = EdgeTrigger("rising", 0.0, 0.1, mode="single")
    assert [e.seq for e in single.feed(np.arange(1000), x[:1000])] == edges[:1]
    assert single.feed(np.arange(1000, 2000), x[1000:2000]) == [] and not single.armed
    single.arm()
    nxt = [e for e in edges if e > 2000][0]
    assert [e.seq for e in single.feed(np.arange(2000, n), x[2000:])] == [nxt]
    # auto on a flat trace: free-runs every auto_timeout samples
    auto = EdgeTrigger("rising", 0.5, 0.1, mode="auto", auto_timeout_samples=700)
    ev = auto.feed(np.arange(3000), np.zeros(3000))
    assert [(e.seq, e.auto) for e in ev] == [(700, True), (1400, True), (2100, True), (2800, True)]
    # auto with edges closer than the timeout: the edges, no free run
    auto2 = EdgeTrigger("rising", 0.0, 0.1, mode="auto", auto_timeout_samples=700)
    ev2 = auto2.feed(np.arange(n), x)
    assert [e.seq for e in ev2] == edges and not any(e.auto for e in ev2)
    with pytest.raises(ConfigError, match="trigger mode: 'repeat'"):
        EdgeTrigger(mode="repeat")
    with pytest.raises(ConfigError, match="hysteresis"):
        EdgeTrigger(hysteresis=-1.0)


def test_sample_buffer_and_view():
    buf = SampleBuffer(max_samples=1000)
    s = np.arange(0, 600)
    buf.put("frame", s, {"i_a": s * 0.5})
    buf.put("frame", np.arange(550, 1200), {"i_a": np.arange(550, 1200) * 0.5})  # overlap
    seq, v = buf.trace("frame:i_a")
    assert seq[0] == 200 and seq[-1] == 1199 and contiguous(seq)
    assert np.array_equal(v, seq * 0.5)
    vs, vf = buf.view("frame", TS, 0.03, 0.05)
    assert vs[0] == 300 and vs[-1] == 500 and np.array_equal(vf["i_a"], vs * 0.5)
    assert in_view(np.arange(10), TS, 2e-4, 4e-4).tolist() == [2, 3, 4]
    with pytest.raises(KeyError):
        buf.trace("frame:i_z")


def test_raw_export_round_trips_csv_and_bag(tmp_path):
    from fluxdrive.io.scope_export import raw_csv, read_raw_bag, read_raw_csv, write_raw_bag

    rng = np.random.default_rng(11)
    seq = np.arange(1234, 1234 + 300)
    streams = {
        "frame": (seq, {"i_a": rng.normal(size=300), "vdc": 48.0 + rng.normal(size=300)}),
        "state": (seq[::2], {"i_q": rng.normal(size=150)}),
    }
    head, vals = read_raw_csv(raw_csv(streams, TS))
    assert head == ["t_s", "seq", "frame:i_a", "frame:vdc", "state:i_q"]
    assert np.array_equal(vals[:, 1], seq)
    assert np.array_equal(vals[:, 2], streams["frame"][1]["i_a"])  # bit for bit
    assert np.array_equal(vals[::2, 4], streams["state"][1]["i_q"])
    assert np.isnan(vals[1::2, 4]).all()
    mcap_file = write_raw_bag(tmp_path / "export", streams, TS, {"t0_s": 0.1234, "t1_s": 0.1533})
    # the project's bag reader
    back = read_raw_bag(tmp_path / "export")
    for name, (s, f) in streams.items():
        assert np.array_equal(back[name][0], s)
        for k, v in f.items():
            assert np.array_equal(back[name][1][k], v)
    # an independent reader: mcap with its ROS 2 decoder
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(mcap_file, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        rows = [
            (list(m.data), m.layout.dim[0].label)
            for _s, _c, _m, m in reader.iter_decoded_messages(topics=["/scope/raw/frame"])
        ]
    assert len(rows) == 300 and rows[0][1] == "seq,i_a,vdc"
    assert [r[0][0] for r in rows] == seq.tolist()
    assert [r[0][1] for r in rows] == streams["frame"][1]["i_a"].tolist()
