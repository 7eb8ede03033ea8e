"""What the CAN exchange costs on a real bus: the bits of every frame field (classic and
FD, with or without worst-case stuffing), a frame's wire time, and the link budget of a
sample period (bus load, the host's turnaround budget, the smallest decimation that fits).
No ROS imports."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fluxdrive.core.schema import param

# ARM_MODE carries the decimation D in one byte
DECIMATION_MAX = 255


@dataclass(frozen=True)
class LinkOptions:
    """The CAN link's decimation as the commands take it (can-emulator, can-import,
    bench --sil, benchmark bench: `--decimation`), ranged once."""

    decimation: int = param(
        4,
        unit="periods",
        doc="PWM periods per sample on the CAN link, either layout (ARM_MODE's byte)",
        range=(1, DECIMATION_MAX),
    )


# --------------------------------------------------------------------------- bus time

_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def frame_bits(
    n_bytes: int, *, fd: bool = False, brs: bool = False, stuffing: str = "none"
) -> tuple[int, int]:
    """Bits one base-format (11-bit ID) data frame occupies on the wire, intermission
    included, as ``(bits at the nominal bit rate, bits at the data bit rate)``
    (ISO 11898-1:2015 frame fields).

    Classic: SOF, ID, RTR, IDE, r0, DLC, data, CRC-15 (34 + 8n stuffable bits), CRC
    delimiter, ACK slot + delimiter, EOF, intermission (13): 47 + 8n bits, i.e. 111 for 8
    bytes; ``stuffing="worst"`` adds the worst-case dynamic stuff bits (34 + 8n - 1) // 4
    (24 for 8 bytes: 135 bits).
    CAN FD: SOF, ID, RRS, IDE, FDF, res, BRS (17, nominal rate), then ESI, DLC, data, the
    stuff count (4), CRC-17 (<= 16 bytes) or CRC-21 with its fixed stuff bits (6 or 7),
    the CRC delimiter (at the data rate when ``brs``), then ACK, EOF and intermission (12,
    nominal rate). ``n_bytes`` is rounded up to the next valid FD length."""
    if stuffing not in ("none", "worst"):
        raise ValueError("stuffing must be 'none' or 'worst'")
    worst = stuffing == "worst"
    if not fd:
        if not 0 <= n_bytes <= 8:
            raise ValueError(f"a classic CAN frame carries 0..8 bytes, not {n_bytes}")
        body = 34 + 8 * n_bytes
        return body + 13 + ((body - 1) // 4 if worst else 0), 0
    n = next((m for m in _FD_LENGTHS if m >= n_bytes), None)
    if n is None:
        raise ValueError(f"a CAN FD frame carries at most 64 bytes, not {n_bytes}")
    arb = 17
    data = 1 + 4 + 8 * n
    crc = 4 + (17 + 6 if n <= 16 else 21 + 7) + 1
    stuff_arb = (arb - 1) // 4 if worst else 0
    stuff_data = ((arb + data - 1) // 4 - stuff_arb) if worst else 0
    nominal = arb + stuff_arb + 12
    fast = data + stuff_data + crc
    if brs:
        return nominal, fast
    return nominal + fast, 0


def bus_time_s(
    n_bytes: int,
    nominal_bitrate: float,
    data_bitrate: float | None = None,
    *,
    fd: bool = False,
    brs: bool = False,
    stuffing: str = "none",
) -> float:
    """Wire time of one frame [s] (see :func:`frame_bits`)."""
    nom, fast = frame_bits(n_bytes, fd=fd, brs=brs, stuffing=stuffing)
    return nom / nominal_bitrate + (fast / (data_bitrate or nominal_bitrate) if fast else 0.0)


def link_budget(
    layout: str,
    *,
    pwm_hz: float = 10_000.0,
    decimation: int = 1,
    nominal_bitrate: float = 1e6,
    data_bitrate: float = 5e6,
    housekeeping_hz: float = 10.0,
) -> dict[str, Any]:
    """What the sample/duty exchange costs on a real bus, per sample period
    ``T = decimation / pwm_hz`` (either layout sends one sample set every ``decimation``
    PWM periods): the sample frame(s) (``"fd"``: one 64-byte SAMPLE_FD with BRS;
    ``"classic"``: SAMPLE_C_CUR/VLT/DUTY/AUX, 4 x 8 bytes) plus the DUTY_CMD answering
    it (8 bytes, classic format, as the bridge sends it), plus STATUS, ARM_MODE and
    HOST_HEARTBEAT at ``housekeeping_hz``. For no stuffing and worst-case stuffing:
    ``bits_*`` (sample set + duty, nominal-rate and data-rate bits), ``bus_time_us_*``,
    ``load_*`` (fraction of the bus time) and ``host_budget_us_*``: what is left of the
    period for the host's turnaround (last sample bit -> start of the duty frame) when
    the duty must be on the wire before the next sample boundary. ``fits`` = worst-case
    load < 1 and a positive worst-case host budget."""
    if layout not in ("fd", "classic"):
        raise ValueError("layout must be 'fd' or 'classic'")
    d = int(decimation)
    if d < 1:
        raise ValueError("decimation must be >= 1")
    period = d / pwm_hz
    out: dict[str, Any] = {
        "layout": layout, "decimation": d, "sample_rate_hz": pwm_hz / d,
        "period_us": period * 1e6, "nominal_bitrate": nominal_bitrate,
        "data_bitrate": data_bitrate if layout == "fd" else None,
    }  # fmt: skip
    for st in ("none", "worst"):
        if layout == "fd":
            s_nom, s_fast = frame_bits(64, fd=True, brs=True, stuffing=st)
            t_s = s_nom / nominal_bitrate + s_fast / data_bitrate
        else:
            s_nom, s_fast = 4 * frame_bits(8, stuffing=st)[0], 0
            t_s = s_nom / nominal_bitrate
        c_nom = frame_bits(8, stuffing=st)[0]
        t_c = c_nom / nominal_bitrate
        hk = housekeeping_hz * (2 * frame_bits(8, stuffing=st)[0] + frame_bits(2, stuffing=st)[0])
        out[f"bits_{st}"] = {"nominal": s_nom + c_nom, "data": s_fast}
        out[f"bus_time_us_{st}"] = (t_s + t_c) * 1e6
        out[f"load_{st}"] = (t_s + t_c) / period + hk / nominal_bitrate
        out[f"host_budget_us_{st}"] = (period - t_s - t_c) * 1e6
    out["fits"] = bool(out["load_worst"] < 1.0 and out["host_budget_us_worst"] > 0.0)
    return out


def smallest_fitting_decimation(
    layout: str, *, max_decimation: int = DECIMATION_MAX, **kw: Any
) -> int:
    """The smallest D for which :func:`link_budget` says the layout fits (``kw``: its bus
    settings: ``pwm_hz``, ``nominal_bitrate``, ``data_bitrate``, ``housekeeping_hz``).
    Raises ``ValueError`` if none up to ``max_decimation`` does."""
    for d in range(1, int(max_decimation) + 1):
        if link_budget(layout, decimation=d, **kw)["fits"]:
            return d
    raise ValueError(f"the {layout} layout fits no decimation up to {max_decimation}")
