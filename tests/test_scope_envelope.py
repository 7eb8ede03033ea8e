"""The scope tap's decimation: min/max envelopes per bucket keep every extreme (a one-sample
spike shows), bucket indices follow the sample numbers, and the batch decoder reads the
graph's CDR exactly as the per-message codec does."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")
scope_tap = pytest.importorskip("fluxdrive_bringup.scope_tap")


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
    want = np.array([[r[c.index(p)] for p in paths] for r in rows], dtype=float)
    assert np.array_equal(out, want)


def test_batch_decode_reads_padded_dds_payloads():
    """Over DDS a message may arrive with trailing padding to a multiple of 4 bytes."""
    from fluxdrive_ros.cdr import Codec, Decoder

    from fluxdrive_ros import topics

    c = Codec(topics.T_DUTY, {"header.frame_id": ""})
    pad = (-c.size) % 4 or 4
    msgs = [c.pack(0, k, k, 7, 0.1 * k, 0.2, 0.3, True) + b"\0" * pad for k in range(20)]
    out = scope_tap.decode_batch(Decoder(topics.T_DUTY), msgs, ["seq", "duty[0]"])
    assert out[:, 0].tolist() == list(range(20))
    assert np.allclose(out[:, 1], 0.1 * np.arange(20))
