"""`./fluxdrive can-import LOG --out BAG`: a bench CAN capture -> a rosbag2 (MCAP) bag of
flux_drive_msgs/PhaseFrame on /drive/frame, the topic the graph uses, so a capture taken
with standard tools (candump .log, Vector .asc, .blf) replays through observer variants.

Decoding is :func:`fluxdrive.can.canlog.read_capture` (vectorised SAMPLE_FD codec, or the
classic 4-frame layout); the 16-bit sequence counter is unwrapped into the period index
k, ``header.stamp`` is the capture timestamp of the frame. Message definitions come from
the .msg text (no ROS import), embedded in the bag so readers need no message package.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.can.canlog import CaptureError, read_capture
from fluxdrive.can.protocol import FRAME_FIELDS, SEQ_BITS, unwrap_counter
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.plant import FR_SEQ
from fluxdrive.drive.scenario import load_scenario, scenario_path
from fluxdrive.io.bagio import BagWriter
from fluxdrive.io.messages import FrameWire, Stamp
from fluxdrive.io.topics import FRAME, T_FRAME

__all__ = ["PHASE_FRAME_TOPIC", "import_capture"]

PHASE_FRAME_TOPIC = FRAME


def import_capture(
    log: str | Path,
    out: str | Path,
    *,
    topic: str = PHASE_FRAME_TOPIC,
    frame_id: str = "drive",
    scenario: str | None = None,
    decimation: int | None = None,
) -> dict[str, Any]:
    """Decode ``log`` and write the bag directory ``out`` (must not exist). Returns the
    capture counts plus ``written``.

    A decimated capture (a sample every D PWM periods; FD D = 4 on a real bus, classic
    D = 8) is imported the way the bench bridge hands it to the graph: the 16-bit wire
    counter is unwrapped into the period index k and each frame carries the sample index
    j = k // D as its seq, stamped j D Ts.  D is the capture's own counter step unless
    given.  The bag records D, the sample period and the machine card at the sample rate
    (`scenario`: its card and observer configurations, else the default card), so replay
    runs the observers at D Ts as the live bridge run did."""
    cap = read_capture(log)
    d = int(decimation or cap.step or 1)
    f = np.array(cap.frames, dtype=np.float64)
    i_seq = FRAME_FIELDS.index("seq")
    k = unwrap_counter(f[:, i_seq], SEQ_BITS)
    k = k - (k[0] - f[0, i_seq])  # keep the first wire value
    f[:, FR_SEQ] = np.floor_divide(k.astype(np.int64), d)
    if scenario:
        sc = load_scenario(scenario_path(scenario))
    else:
        sc = None
    card = sc.machine if sc is not None else MachineCard()
    sample_card = dataclasses.replace(card, pwm_hz=card.pwm_hz / d)
    settings: dict[str, Any] = {
        "format": 1,
        "machine": dataclasses.asdict(sample_card),
        "observers": {nm: o.to_dict() for nm, o in sc.observers.items()} if sc else {},
        "scenario": {"name": sc.name if sc else "", "source": str(sc.source) if sc else ""},
        "first_seq": int(f[0, FR_SEQ]),
        "observer_states": {},
        "can_import": {
            "source": str(log),
            "layout": cap.layout,
            "decimation": d,
            "pwm_hz": card.pwm_hz,
            "sample_period_s": d / card.pwm_hz,
            # the samples left out (repeated, replayed, late, jumping) and the gaps
            "sequence": {
                key: int(cap.counts.get(key, 0))
                for key in ("gaps", "lost", "duplicates", "out_of_order", "jumps", "rejected")
            },
            **({"truncated": cap.truncated} if cap.truncated else {}),
        },
    }
    stamp = Stamp(sample_card.ts_s)
    fw = FrameWire(frame_id)  # FRAME_FIELDS are the engine's FR_* columns
    outp = Path(out)
    offset = _bag_time_offset_ns(log, float(cap.timestamps[0]), stamp, f)
    with BagWriter(outp, settings, epoch_offset_ns=offset) as w:
        cid = w.add_connection(topic, T_FRAME)
        for j in range(f.shape[0]):
            t_ns = stamp.ns(int(f[j, FR_SEQ]))
            w.write(cid, t_ns, fw.pack(f[j], *divmod(t_ns, 1_000_000_000)))
    out_counts: dict[str, Any] = dict(cap.counts)
    out_counts.update(
        written=int(f.shape[0]),
        layout=cap.layout,
        decimation=d,
        sample_period_s=d / card.pwm_hz,
        topic=topic,
        bag=str(outp),
    )
    if cap.truncated:
        out_counts["truncated"] = cap.truncated
    if cap.bad_lines:
        out_counts["first_malformed_lines"] = [
            f"{Path(log).name}:{n}: {why}" for n, why in cap.bad_lines[:5]
        ]
    return out_counts


def _bag_time_offset_ns(log: Path | str, t0_s: float, stamp: Stamp, f: np.ndarray) -> int:
    """Bag time = sample stamp + this offset: the capture's own clock, where its timestamps are
    wall-clock epoch times.  A capture on a relative clock (or one whose header time is damaged)
    would put the first samples before 1970: its bag time is the sample time itself.  A bag
    time past what MCAP's unsigned 64-bit nanoseconds hold is refused in one line."""
    seq0, seq_end = int(f[0, FR_SEQ]), int(f[-1, FR_SEQ])
    if not np.isfinite(t0_s) or abs(t0_s) > 1e10:
        raise CaptureError(f"{log}: first timestamp {t0_s!r} s is not a usable capture time")
    offset = max(int(round(t0_s * 1e9)) - stamp.ns(seq0), 0)
    if offset + stamp.ns(seq_end) >= 2**63:
        raise CaptureError(
            f"{log}: the capture's timestamps run past the year 2262 (bag time limit)"
        )
    return offset
