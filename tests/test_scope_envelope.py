"""The scope tap's decimation: min/max envelopes per bucket keep every extreme (a one-sample
spike shows), bucket indices follow the sample numbers, and the batch decoder reads the
graph's CDR exactly as the per-message codec does."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")
scope_tap = pytest.importorskip("fluxdrive_bringup.view.scope_tap")


def test_envelope_keeps_a_one_sample_spike():
    n, b = 10_000, 20
    seq = np.arange(n)
    x = np.sin(2 * math.pi * 50.0 * seq * 1e-4)
    x[4321] = 7.5  # one-sample spike
    x[777] = -3.0
    k, mn, mx = scope_tap.envelope(seq, x[:, None], b)
    assert len(k) == n // b and (k == np.arange(n // b)).all()
    assert mx.max() == 7.5 and k[mx[:, 0].argmax()] == 4321 // b
    assert mn.min() == -3.0 and k[mn[:, 0].argmin()] == 777 // b
    # elsewhere the band is the sine's range over the bucket
    j = 100
    seg = x[j * b : (j + 1) * b]
    assert mn[j, 0] == seg.min() and mx[j, 0] == seg.max()


def test_envelope_unsorted_partial_and_nan():
    seq = np.array([45, 41, 40, 60, 61, 44])
    v = np.array(
        [[1.0, np.nan], [5.0, np.nan], [-2.0, np.nan], [3.0, 1.0], [4.0, 2.0], [0.0, np.nan]]
    )
    k, mn, mx = scope_tap.envelope(seq, v, 20)
    assert k.tolist() == [2, 3]
    assert mn[:, 0].tolist() == [-2.0, 3.0] and mx[:, 0].tolist() == [5.0, 4.0]
    assert math.isnan(mn[0, 1]) and mx[1, 1] == 2.0  # all-NaN bucket stays NaN


def test_batch_decode_matches_the_codec():
    from fluxdrive_ros.cdr import Codec, Decoder

    from fluxdrive_ros import topics

    c = Codec(topics.T_ESTIMATE, {"header.frame_id": "", "variant": "flux_measured"})
    c2 = Codec(topics.T_ESTIMATE, {"header.frame_id": "x", "variant": "paper"})
    rng = np.random.default_rng(3)
    msgs, rows = [], []
    for i in range(50):
        vals = (i // 10, i * 1000, i, 7, *rng.normal(size=7).tolist(), bool(i % 2))
        msgs.append((c if i % 3 else c2).pack(*vals))
        rows.append(vals)
    paths = ["seq", "theta_e", "flux_ab[1]", "valid"]
    out = scope_tap.decode_batch(Decoder(topics.T_ESTIMATE), msgs, paths)
    assert list(out) == paths
    for p in paths:
        assert np.array_equal(out[p], np.array([r[c.index(p)] for r in rows], dtype=float)), p


def test_batch_decode_reads_padded_dds_payloads():
    """Over DDS a message may arrive with trailing padding to a multiple of 4 bytes."""
    from fluxdrive_ros.cdr import Codec, Decoder

    from fluxdrive_ros import topics

    c = Codec(topics.T_DUTY, {"header.frame_id": ""})
    pad = (-c.size) % 4 or 4
    msgs = [c.pack(0, k, k, 7, 0.1 * k, 0.2, 0.3, True) + b"\0" * pad for k in range(20)]
    out = scope_tap.decode_batch(Decoder(topics.T_DUTY), msgs, ["seq", "duty[0]"])
    assert out["seq"].tolist() == list(range(20))
    assert np.allclose(out["duty[0]"], 0.1 * np.arange(20))


def test_order_spectrum_reads_the_orders_of_a_known_signal():
    """θ̃ = 0.5° + 2° sin(6θ) and λ̂α = 10 mV·s cos θ + 0.3 mV·s cos(5θ + 1) over whole and
    part electrical periods, the speed wandering a little: the spectrum gives exactly those
    amplitudes (orders against the angle, the engine's definition)."""
    n = 9000
    rng = np.random.default_rng(11)
    speed = 1.0 + 0.05 * np.sin(np.linspace(0, 3, n)) + 0.001 * rng.standard_normal(n)
    theta = np.cumsum(speed) * (2 * math.pi * 3.37 / n)  # 3.37 electrical periods
    wrapped = np.mod(theta, 2 * math.pi)
    err = np.radians(0.5 + 2.0 * np.sin(6 * theta))
    flux_a = 10e-3 * np.cos(theta) + 0.3e-3 * np.cos(5 * theta + 1.0)
    sp = scope_tap.order_spectrum(wrapped, err, flux_a, np.ones(n))
    assert sp["orders"] == list(range(1, 21)) and sp["periods"] == pytest.approx(3, abs=0.01)
    assert sp["err"][5] == pytest.approx(2.0, rel=1e-3)
    assert max(sp["err"][:5] + sp["err"][6:]) < 0.01
    assert sp["flux_alpha"][0] == pytest.approx(10.0, rel=1e-3)
    assert sp["flux_alpha"][4] == pytest.approx(0.3, rel=1e-2)
    # without truth (the observer's own angle): no θ̃ spectrum, λ̂α still
    sp2 = scope_tap.order_spectrum(wrapped, err * np.nan, flux_a, np.zeros(n))
    assert "err" not in sp2 and sp2["flux_alpha"][0] == pytest.approx(10.0, rel=1e-3)


def test_envelope_message_round_trip_with_arrays():
    """The tap's wire format carries the spectrum samples untouched, and the page JSON
    has the spectra computed from them."""
    n = 4000
    theta = np.mod(np.linspace(0, 4 * math.pi, n, endpoint=False), 2 * math.pi)
    spec = np.stack([theta, np.radians(np.sin(6 * theta)), 1e-2 * np.cos(theta), np.ones(n)])
    doc = {
        "v": 1,
        "seq": 1234,
        "ts_s": 1e-4,
        "streams": {
            "state": {
                "k": np.array([3.0, 4.0]),
                "n": ["i_d", "mode"],
                "dec": [3, 0],
                "lo": np.array([[0.12345, 3.0], [0.2, 3.0]]),
                "hi": np.array([[0.5, 3.0], [0.25, 3.0]]),
            }
        },
        "locus": {},
        "arrays": {"spec/x": spec},
    }
    head, arrays = scope_tap.unpack_envelopes(scope_tap.pack_envelopes(doc))
    assert np.array_equal(arrays["spec/x"], spec) and head["seq"] == 1234
    import json

    text, head2 = scope_tap.page_json(scope_tap.pack_envelopes(doc))
    page = json.loads(text)
    assert page["streams"]["state"]["lo"][0] == [0.123, 3.0]  # rounded per field
    assert page["spectrum"]["x"]["err"][5] == pytest.approx(1.0, rel=1e-6)
    assert page["spectrum"]["x"]["flux_alpha"][0] == pytest.approx(10.0, rel=1e-6)


def test_triggers_mode_fault_and_threshold():
    """The trigger finds the first sample of its condition within a period."""
    from types import SimpleNamespace

    tap = SimpleNamespace(
        pv={"trigger": "mode", "trigger_field": "state:i_q", "trigger_level": 2.0},
        last_mode=2,
        marker_raw=[],
        candidates=[],
    )
    seq = np.arange(100, 110)
    mode = np.array([2, 2, 3, 3, 3, 3, 4, 4, 4, 4], float)
    i_q = np.array([0, 1, -2.5, 1, 3, 0, 0, 0, 0, 0], float)
    cols = {"state": (seq, {"mode": mode, "i_q": i_q})}
    scope_tap.ScopeTapNode._triggers(tap, cols)
    assert tap.candidates == [(102, "mode 2 to 3"), (106, "mode 3 to 4")]
    assert tap.last_mode == 4
    tap.pv["trigger"], tap.last_mode = "fault", 2
    scope_tap.ScopeTapNode._triggers(tap, cols)
    assert tap.candidates == [(106, "mode 3 to 4")]
    tap.pv["trigger"] = "threshold"
    scope_tap.ScopeTapNode._triggers(tap, cols)
    assert tap.candidates == [(102, "state:i_q >= 2")]  # |i_q| >= 2 first at 102


def test_controller_descriptor_range_is_what_the_controller_accepts():
    """The current-loop bandwidth's range follows the card: up to a quarter of the PWM
    frequency, which the engine's check accepts, and nothing above."""
    from fluxdrive.core.machine import ConfigError
    from fluxdrive.core.schema import ranges
    from fluxdrive.drive.control import ControllerConfig
    from fluxdrive.drive.scenario import load_scenario, scenario_path

    sc = load_scenario(scenario_path("paper_2pct_150load"))
    card = sc.machine
    lo, hi = ranges(ControllerConfig, card)["current_bandwidth_hz"]
    assert hi == 0.25 * card.pwm_hz
    import dataclasses

    dataclasses.replace(sc.control, current_bandwidth_hz=hi).check(card)  # accepted
    with pytest.raises(ConfigError, match="quarter of the PWM"):
        dataclasses.replace(sc.control, current_bandwidth_hz=hi * 1.001).check(card)
    # the split mode's reference timeout: at least two of the host's samples
    for d in (1, 4):
        lo, _ = ranges(ControllerConfig, card, d)["reference_timeout_s"]
        assert lo == pytest.approx(2 * d * card.ts_s)
        split = dataclasses.replace(sc.control, mode="split", decimation=d)
        dataclasses.replace(split, reference_timeout_s=lo).check(card)
        with pytest.raises(ConfigError, match="two samples"):
            dataclasses.replace(split, reference_timeout_s=lo * 0.99).check(card)


def test_raw_samples_reach_the_server_instrument_and_gaps_are_named():
    """The tap's raw arrays (raw_streams) cross the wire untouched into the server's
    instrument: its edge trigger fires at the crossing sample, and a view with samples
    that never arrived is refused with their count instead of exported short."""
    scope = pytest.importorskip("fluxdrive_bringup.view.scope")

    def envelope_of(seq: np.ndarray) -> dict:
        i_a = np.sin(2 * math.pi * 250.0 * seq * 1e-4)
        raw = np.stack([seq.astype(float), i_a, np.full(len(seq), 48.0)])
        doc = {"v": 1, "seq": int(seq[-1]), "ts_s": 1e-4, "streams": {}, "locus": {}}
        doc["arrays"], doc["raw_fields"] = {"raw/frame": raw}, {"frame": ["i_a", "vdc"]}
        return scope_tap.page_json(scope_tap.pack_envelopes(doc))[1]

    ins = scope.Instrument()
    ins.set_edge(
        {
            "trace": "frame:i_a",
            "stream": "frame",
            "field": "i_a",
            "edge": "rising",
            "level": 0.5,
            "hysteresis": 0.2,
            "mode": "single",
            "pre_s": 0.001,
            "post_s": 0.001,
            "holdoff_s": 0.0,
            "auto_timeout_s": 0.1,
        }
    )
    ins.on_head(envelope_of(np.arange(0, 400)))
    ins.on_head(envelope_of(np.arange(410, 800)))  # 400..409 never arrived
    assert ins.missing == {"frame": 10}
    st = ins.edge_state()
    # sin(2π·250 Hz·k·ts) = sin(πk/20) reaches 0.5 at k = 20/6 = 3.33: sample 4 fires
    assert [e["seq"] for e in st["events"]] == [4]
    assert st["fired"] == 1 and not st["armed"]  # single
    ev = st["events"][0]  # 1 ms before (from sample 0: no earlier one) to 1 ms after
    assert ev["t"][0] == 0.0 and ev["t"][-1] == pytest.approx(14e-4)
    assert ev["v"][4] == pytest.approx(math.sin(math.pi * 4 / 20), rel=1e-6)
    assert ins.covers("frame", 0.0, 0.079)
    seq, fields = ins.view("frame", 0.0, 0.0399)
    assert seq.tolist() == list(range(0, 400)) and (fields["vdc"] == 48.0).all()
    with pytest.raises(LookupError, match="10 of the view's 800 frame samples never reached"):
        ins.view("frame", 0.0, 0.0799)
