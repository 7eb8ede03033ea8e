"""fluxdrive CAN wire protocol, interpreted from ``config/can/fluxdrive.dbc`` (the single
source of truth). No ROS imports.

- :mod:`~fluxdrive.can.protocol.codec`: the messages, the engine frame's columns on the bus, a
  cantools codec plus a vectorised numpy fast path, the classic layout's reassembly;
- :mod:`~fluxdrive.can.protocol.sequence`: sequence counters (gaps, duplicates, which samples
  are new, unwrapping);
- :mod:`~fluxdrive.can.protocol.budget`: the bits and bus time of every frame and the link
  budget of a sample period.

Every protocol constant (message ids ``ID_*``, ``PROTOCOL_VERSION``, ``ARM_KEY``, the value
tables' ``FAULT_*``, ``PRM_*``, ``PA_*``, ``MODE_*``, ``ST_*``) is generated from the DBC into
:mod:`fluxdrive.core.protocol_constants` by :mod:`~fluxdrive.can.protocol.generate` (and into
the firmware's ``fd_protocol.h``); the ids are re-exported here.

Messages (11-bit IDs, lower ID wins arbitration, all signals little-endian):

====== ================ ===== ==========================================================
ID     name             DLC   content
====== ================ ===== ==========================================================
0x010  FAULT            8     MCU->PC fault code, latched/active, detail, seq, count
0x020  ARM_MODE         8     PC->MCU arm (+ key 0xA5), reset_fault, mode, layout, D
0x040  DUTY_CMD         8     PC->MCU seq answered, 3 duties (15 bit, 4e-5), enable
0x080  SAMPLE_FD        64    MCU->PC one every D PWM periods (CAN FD, BRS; D=1 default)
0x100  SAMPLE_C_CUR     8     classic layout part 1/4: seq, i_a, i_b, i_c
0x101  SAMPLE_C_VLT     8     classic layout part 2/4: seq, v_ab, v_bc, v_ca (4 mV)
0x102  SAMPLE_C_DUTY    8     classic layout part 3/4: seq, duties applied
0x103  SAMPLE_C_AUX     8     classic layout part 4/4: seq, vdc, encoder (24 bit), flags
0x700  STATUS           8     MCU->PC heartbeat 10 Hz
0x701  HOST_HEARTBEAT   2     PC->MCU heartbeat 10 Hz
====== ================ ===== ==========================================================

The package re-exports every public name of its modules, so ``from fluxdrive.can.protocol
import X`` works whichever module X lives in.
"""

from __future__ import annotations

from fluxdrive.can.protocol.budget import (
    DECIMATION_MAX,
    LinkOptions,
    bus_time_s,
    frame_bits,
    link_budget,
    smallest_fitting_decimation,
)
from fluxdrive.can.protocol.codec import (
    CLASSIC_SAMPLE_IDS,
    DBC_ENV_VAR,
    FRAME_FIELDS,
    FRAME_FLAG_ADC_CLIP,
    FRAME_INDEX,
    ClassicReassembler,
    DecodeResult,
    FluxdriveProtocol,
    NumpyCodec,
    ValidationReport,
    decimate_for_classic,
    decimate_frames,
    default_dbc_path,
    fd_payloads_to_frames,
    frame_to_classic_payloads,
    frame_to_fd_payload,
    frames_to_fd_payloads,
    get_protocol,
    load_database,
    pack_payloads,
)
from fluxdrive.can.protocol.sequence import (
    SEQ_BITS,
    SeqFilter,
    SeqStats,
    SeqTracker,
    count_seq_gaps,
    unwrap_counter,
)
from fluxdrive.core.protocol_constants import (
    ARM_KEY,
    ID_ARM_MODE,
    ID_DRIVE_PARAM,
    ID_DRIVE_PARAM_ACK,
    ID_DUTY_CMD,
    ID_FAULT,
    ID_HOST_HEARTBEAT,
    ID_HOST_REF,
    ID_SAMPLE_C_AUX,
    ID_SAMPLE_C_CUR,
    ID_SAMPLE_C_DUTY,
    ID_SAMPLE_C_VLT,
    ID_SAMPLE_FD,
    ID_STATUS,
    PROTOCOL_VERSION,
)

__all__ = [
    "ARM_KEY",
    "CLASSIC_SAMPLE_IDS",
    "DBC_ENV_VAR",
    "FRAME_FIELDS",
    "FRAME_FLAG_ADC_CLIP",
    "FRAME_INDEX",
    "ID_ARM_MODE",
    "ID_DRIVE_PARAM",
    "ID_DRIVE_PARAM_ACK",
    "ID_DUTY_CMD",
    "ID_FAULT",
    "ID_HOST_HEARTBEAT",
    "ID_HOST_REF",
    "ID_SAMPLE_C_AUX",
    "ID_SAMPLE_C_CUR",
    "ID_SAMPLE_C_DUTY",
    "ID_SAMPLE_C_VLT",
    "ID_SAMPLE_FD",
    "ID_STATUS",
    "PROTOCOL_VERSION",
    "SEQ_BITS",
    "ClassicReassembler",
    "DecodeResult",
    "FluxdriveProtocol",
    "NumpyCodec",
    "SeqFilter",
    "SeqStats",
    "SeqTracker",
    "ValidationReport",
    "bus_time_s",
    "count_seq_gaps",
    "decimate_for_classic",
    "decimate_frames",
    "default_dbc_path",
    "fd_payloads_to_frames",
    "frame_to_classic_payloads",
    "frame_to_fd_payload",
    "frames_to_fd_payloads",
    "frame_bits",
    "get_protocol",
    "link_budget",
    "LinkOptions",
    "DECIMATION_MAX",
    "load_database",
    "smallest_fitting_decimation",
    "pack_payloads",
    "unwrap_counter",
]
