"""CAN throughput benchmark: SAMPLE_FD frames through a python-can bus, decoded.

One sender thread builds ``can.Message`` objects from pre-encoded SAMPLE_FD payloads
and sends them (always with a timeout: the ``virtual`` interface blocks forever when a
bounded receive queue is full); a ``can.Notifier`` delivers them to a listener that
decodes them in batches with the numpy fast path and tracks the sequence counter.
The listener implements ``on_error`` (a Notifier thread otherwise dies silently).

Also measures decode-only throughput of cantools vs the numpy codec. No ROS imports.
"""

from __future__ import annotations

import itertools
import sys
import threading
import time
from typing import Any

import can
import numpy as np

from fluxdrive.can.protocol import (
    ID_SAMPLE_FD,
    FluxdriveProtocol,
    SeqTracker,
    get_protocol,
    pack_payloads,
)
from fluxdrive.drive.plant import FR_DA, FR_EN, FR_ENC, FR_IA, FR_N, FR_SEQ, FR_VAB, FR_VDC

__all__ = ["bench_can_cli", "make_test_frames", "measure_decode_rates", "run_can_benchmark"]

_channel_counter = itertools.count()


def make_test_frames(n: int, seed: int = 0) -> np.ndarray:
    """Deterministic in-range engine frames (N, 14): a rotating current/voltage vector
    with noise, 72 V bus, SVPWM-like duties, a counting encoder, seq = 0..N-1."""
    rng = np.random.default_rng(seed)
    k = np.arange(n, dtype=np.float64)
    th = 2 * np.pi * 50.0 * k * 1e-4
    f = np.zeros((n, FR_N))
    for j, ph in enumerate((0.0, -2 * np.pi / 3, 2 * np.pi / 3)):
        f[:, FR_IA + j] = 9.0 * np.cos(th + ph) + rng.normal(0, 0.05, n)
        f[:, FR_DA + j] = 0.5 + 0.4 * np.cos(th + ph)
    for j in range(3):  # line voltages from the duties: v_ab = Vdc (d_a - d_b), ...
        f[:, FR_VAB + j] = 72.0 * (f[:, FR_DA + j] - f[:, FR_DA + (j + 1) % 3])
    f[:, FR_VDC] = 72.0 + rng.normal(0, 0.1, n)
    f[:, FR_ENC] = np.floor(k * 0.3)
    f[:, FR_EN] = 1.0
    f[:, FR_SEQ] = k
    return f


def measure_decode_rates(
    n_numpy: int = 100_000, n_cantools: int = 20_000, protocol: FluxdriveProtocol | None = None
) -> dict[str, float]:
    """Decode-only (and numpy encode) throughput of SAMPLE_FD payloads [frames/s]."""
    proto = protocol or get_protocol()
    pay = proto.frames_to_fd_payloads(make_test_frames(n_numpy, seed=1))
    msg = proto.sample_fd
    rows = [r.tobytes() for r in pay[:n_cantools]]
    t0 = time.perf_counter()
    for r in rows:
        msg.decode(r, decode_choices=False)
    t_ct = time.perf_counter() - t0
    t0 = time.perf_counter()
    proto.fd_payloads_to_frames(pay)
    t_np = time.perf_counter() - t0
    t0 = time.perf_counter()
    frames, _ = proto.decode_fd(pay)
    t_npc = time.perf_counter() - t0
    t0 = time.perf_counter()
    proto.frames_to_fd_payloads(frames)
    t_enc = time.perf_counter() - t0
    t0 = time.perf_counter()
    packed, _ = pack_payloads(rows * (n_numpy // max(len(rows), 1)), proto.fd_codec.length)
    t_pack = time.perf_counter() - t0
    ct = len(rows) / t_ct
    npr = n_numpy / t_np
    return {
        "cantools_decode_frames_per_s": ct,
        "numpy_decode_frames_per_s": npr,
        "numpy_checked_decode_frames_per_s": n_numpy / t_npc,
        "numpy_encode_frames_per_s": n_numpy / t_enc,
        "pack_bytes_frames_per_s": packed.shape[0] / t_pack,
        "numpy_speedup": npr / ct,
    }


class _DecodingListener(can.Listener):
    """Collects SAMPLE_FD payloads and decodes them in batches (numpy path)."""

    def __init__(self, proto: FluxdriveProtocol, batch: int) -> None:
        self.proto = proto
        self.batch = batch
        self.buf: list[bytes] = []
        self.received = 0
        self.decoded = 0
        self.malformed = 0
        self.other = 0
        self.seq = SeqTracker()
        self.errors: list[BaseException] = []
        self.checksum = 0.0
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id != ID_SAMPLE_FD:
            self.other += 1
            return
        self.buf.append(bytes(msg.data))
        self.received += 1
        if len(self.buf) >= self.batch:
            self.flush()

    def flush(self) -> None:
        with self.lock:
            if not self.buf:
                return
            rows, self.buf = self.buf, []
            frames, res = self.proto.decode_fd(rows)
            ok = res.report.valid
            self.decoded += int(ok.sum())
            self.malformed += int((~ok).sum())
            self.seq.update_many(frames[ok, FR_SEQ].astype(np.int64))
            self.checksum += float(np.sum(frames[ok, FR_IA]))

    def on_error(self, exc: Exception) -> None:
        self.errors.append(exc)


def run_can_benchmark(
    n_frames: int = 100_000,
    *,
    rate_hz: float | None = None,
    interface: str = "virtual",
    channel: str | None = None,
    rx_queue_size: int = 8192,
    send_timeout: float = 0.05,
    batch: int = 1024,
    decode_rates: bool = True,
    progress: bool = True,
    protocol: FluxdriveProtocol | None = None,
) -> dict[str, Any]:
    """Push ``n_frames`` SAMPLE_FD frames through a python-can bus and decode them.

    ``rate_hz`` None sends as fast as possible (throughput); a number paces the sender
    to that average rate (sustained test, e.g. 10_000 for a 10 kHz PWM). Returns
    ``frames_per_s`` (decoded frames / wall time), ``dropped`` (sent minus decoded,
    including send timeouts), ``decoded`` and details; with ``decode_rates`` also the
    decode-only rates of cantools and the numpy codec. Progress goes to stderr."""
    proto = protocol or get_protocol()
    payloads = proto.frames_to_fd_payloads(make_test_frames(n_frames))
    rows = [r.tobytes() for r in payloads]
    ch = channel or f"fluxdrive-bench-{next(_channel_counter)}-{time.monotonic_ns()}"
    kw: dict[str, Any] = {"interface": interface, "channel": ch, "fd": True}
    rx_kw = dict(kw, rx_queue_size=rx_queue_size) if interface == "virtual" else kw
    bus_rx = can.Bus(**rx_kw)
    bus_tx = can.Bus(**kw)
    listener = _DecodingListener(proto, batch)
    notifier = can.Notifier(bus_rx, [listener], timeout=0.05)
    sender = _Sender(bus_tx, rows, rate_hz, send_timeout)
    t0 = time.perf_counter()
    threading.Thread(target=sender.run, name="can-bench-sender", daemon=True).start()
    try:
        _follow(sender, listener, n_frames, t0, progress)
        listener.flush()
        elapsed = time.perf_counter() - t0
    finally:
        notifier.stop()
        bus_tx.shutdown()
        bus_rx.shutdown()
    listener.flush()
    decoded = listener.decoded
    result: dict[str, Any] = {
        "frames_per_s": decoded / elapsed if elapsed > 0 else 0.0,
        "dropped": n_frames - decoded,
        "decoded": decoded,
        "n_frames": n_frames,
        "rate_hz": rate_hz,
        "elapsed_s": elapsed,
        "send_timeouts": sender.timeouts,
        "send_errors": sender.errors,
        "malformed": listener.malformed,
        "seq_gaps": listener.seq.stats.gaps,
        "seq_lost": listener.seq.stats.lost,
        "listener_errors": [repr(e) for e in listener.errors[:5]],
        "interface": interface,
    }
    if rate_hz is not None:
        result["sustained"] = bool(
            result["dropped"] == 0 and result["frames_per_s"] >= 0.98 * rate_hz
        )
    if decode_rates:
        result["decode_only"] = measure_decode_rates(protocol=proto)
    if progress:
        print(
            f"[bench can] done: {decoded} decoded, {result['dropped']} dropped, "
            f"{result['frames_per_s']:,.0f} frames/s",
            file=sys.stderr,
            flush=True,
        )
    return result


class _Sender:
    """Sends the payloads as SAMPLE_FD frames, paced to ``rate_hz`` on average (None: as
    fast as the bus takes them), each with a timeout (the virtual bus blocks forever on a
    full receive queue); counts what went out, timed out or failed."""

    def __init__(
        self, bus: can.BusABC, rows: list[bytes], rate_hz: float | None, timeout_s: float
    ) -> None:
        self.bus, self.rows, self.rate_hz, self.timeout_s = bus, rows, rate_hz, timeout_s
        self.sent = self.timeouts = self.errors = 0
        self.done = threading.Event()

    def run(self) -> None:
        t_start = time.perf_counter()
        for i, data in enumerate(self.rows):
            if self.rate_hz is not None and i % 16 == 0:
                lag = i / self.rate_hz - (time.perf_counter() - t_start)
                if lag > 0:
                    time.sleep(lag)
            msg = can.Message(
                arbitration_id=ID_SAMPLE_FD,
                is_extended_id=False,
                is_fd=True,
                bitrate_switch=True,
                data=data,
            )
            try:
                self.bus.send(msg, timeout=self.timeout_s)
                self.sent += 1
            except can.CanOperationError:
                self.timeouts += 1
            except can.CanError:
                self.errors += 1
        self.done.set()


def _follow(
    sender: _Sender, listener: _DecodingListener, n_frames: int, t0: float, progress: bool
) -> None:
    """Wait for the sender (progress to stderr each second), then until the receive side
    has everything the sender got out (at most 5 s)."""
    last_print = t0
    while True:
        finished = sender.done.wait(0.2)
        now = time.perf_counter()
        if progress and (now - last_print >= 1.0 or finished):
            last_print = now
            print(
                f"[bench can] sent {sender.sent}/{n_frames} "
                f"received {listener.received} decoded {listener.decoded} "
                f"({listener.received / max(now - t0, 1e-9):,.0f} frames/s)",
                file=sys.stderr,
                flush=True,
            )
        if finished:
            break
    deadline = time.perf_counter() + 5.0
    while listener.received < sender.sent and time.perf_counter() < deadline:
        time.sleep(0.005)


def bench_can_cli(argv: list[str]) -> dict[str, Any]:
    """`./fluxdrive benchmark can [--frames N] [--rate HZ] [--seconds S]`.

    Two runs over python-can's virtual bus with the numpy batch decoder: a sustained run
    paced at ``--rate`` (default 10 kHz, the PWM rate, for ``--seconds``, default 3 s)
    and a flat-out run of ``--frames`` frames (default 100 000). ``frames_per_s`` is the
    flat-out decoded rate, ``dropped`` the frames lost over both runs; the sustained
    figures are under ``sustained_*``."""
    from fluxdrive.core.schema import Parser

    ap = Parser(prog="fluxdrive benchmark can")
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--rate", type=float, default=10_000.0)
    ap.add_argument("--seconds", type=float, default=3.0)
    a = ap.parse_args(argv)
    n_sus = int(a.rate * a.seconds)
    print(f"[bench can] sustained: {n_sus} SAMPLE_FD frames at {a.rate:.0f} Hz", file=sys.stderr)
    sus = run_can_benchmark(n_sus, rate_hz=a.rate, decode_rates=False)
    print(f"[bench can] flat out: {a.frames} frames", file=sys.stderr)
    top = run_can_benchmark(a.frames, rate_hz=None, decode_rates=True)
    out: dict[str, Any] = {
        "frames_per_s": round(top["frames_per_s"]),
        "dropped": int(top["dropped"] + sus["dropped"]),
        "sustained_rate_hz": a.rate,
        "sustained_frames_per_s": round(sus["frames_per_s"]),
        "sustained_dropped": int(sus["dropped"]),
        "sustained": bool(sus.get("sustained")),
        "flat_out_dropped": int(top["dropped"]),
        "seq_gaps": int(top["seq_gaps"] + sus["seq_gaps"]),
        "interface": top["interface"],
    }
    out.update({k: round(v, 1) for k, v in top.get("decode_only", {}).items()})
    return out


if __name__ == "__main__":  # pragma: no cover
    import json

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 100_000
    rate = float(sys.argv[2]) if len(sys.argv) > 2 else None
    print(json.dumps(run_can_benchmark(n, rate_hz=rate)))
