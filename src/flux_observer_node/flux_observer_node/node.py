"""flux_observer_node: one rotor-position observer variant as a ROS node.

A thin wrapper around fluxdrive.drive.observers.observer_step: every PhaseFrame in, one
RotorEstimate out (same seq and stamp).  Several instances run side by side, each in its
own name (/obs/<name>), one driving the controller and the others in shadow; all publish
on /obs/<name>/estimate.

Parameters: `variant` (read-only) and every field of fluxdrive.drive.observers.ObserverConfig,
declared with description, unit and range.  The model parameters r_hat_ohm, l_hat_h and
lambda_hat_vs default to the machine card's values.  Live changes (cutoff_hz,
pll_bandwidth_hz, voltage_source, deadtime_comp_s, ...) are validated as a whole through
ObserverConfig.with_overrides and rebuild the kernel's parameter row in place; the
observer's state is kept.  The change takes effect from the next frame processed (the
successful result says which).

`decimation` (read-only): the frames come every D-th PWM period (a decimated CAN link, split
mode); the observer steps at the sample time D * the card's Ts and stamps its estimates so.

With `scenario` set, the defaults come from that scenario's `observers.<observer>` entry
(`observer` defaults to the node's name) and its machine card; without it, from
`machine` (a machine card YAML) and the variant's defaults.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, replace

import numpy as np
from fluxdrive.core import schema
from fluxdrive.core.machine import load_machine
from fluxdrive.core.schema import param
from fluxdrive.drive.observers import (
    ES_N,
    ES_VALID,
    OP_TS,
    OS_BAD,
    OS_GAPS,
    OS_LOST,
    OS_N,
    OS_STALE,
    ObserverConfig,
    block_out_of_range,
    build_observer,
    frame_limits,
    frame_out_of_range,
    observer_config,
    observer_reset,
    observer_run,
    observer_step,
)
from fluxdrive.drive.plant import FR_IA, FR_N
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario, scenario_path
from fluxdrive.drive.warm import direct
from fluxdrive_ros.intra import BlockReader, RawPublisher, RawSubscription, bus
from fluxdrive_ros.params import P, declare, on_set
from fluxdrive_ros.runner import FluxNode, main_node
from fluxdrive_ros.wire import EstimateWire, FrameWire, Stamp

import flux_drive_msgs.msg as fm
from fluxdrive_ros import diagnostics as diag
from fluxdrive_ros import params, qos, topics

# a user variant's declared parameters: its model only (plus `plugin_kwargs`)
_PLUGIN_SKIP = tuple(
    f for f in schema.specs(ObserverConfig) if f not in ("r_hat_ohm", "l_hat_h", "lambda_hat_vs")
)


@dataclass
class ObserverPlugin:
    """A user variant's constructor keywords."""

    plugin_kwargs: str = param(
        "{}",
        unit="",
        doc="a user variant's constructor keywords, a JSON object (default: the "
        "scenario observer's `extra`)",
        live=False,
    )


def _plugin_kwargs_param(extra: dict) -> P:
    return params.config_params(ObserverPlugin(json.dumps(extra, sort_keys=True)))[0]


def _parse_kwargs(text: str) -> dict:
    try:
        value = json.loads(text or "{}")
    except json.JSONDecodeError as exc:
        raise ValueError(f"plugin_kwargs: not JSON ({exc.msg}): {text!r}") from None
    if not isinstance(value, dict):
        raise ValueError(f"plugin_kwargs: must be a JSON object, got {text!r}")
    return value


def config_params(cfg: ObserverConfig, card) -> list[P]:
    """The live parameters of every ObserverConfig field from its schema (the variant is
    declared on its own; a user variant takes only its model, R^, L^, lambda^)."""
    skip = _PLUGIN_SKIP if cfg.is_plugin else ("variant",)
    return params.config_params(cfg, card, skip=skip)


@dataclass
class ObserverInput:
    """Where the node's defaults come from."""

    scenario: str = param(
        "",
        unit="",
        doc="scenario YAML (path or a name under config/scenarios): the machine "
        "card and this observer's defaults",
        live=False,
    )
    observer: str = param(
        "observer",
        unit="",
        doc="entry of the scenario's observers this node runs (default: the node "
        "name); also the estimate's variant field",
        live=False,
    )
    machine: str = param(
        str(CONFIG_DIR / "machines" / "default_spm.yaml"),
        unit="",
        doc="machine card YAML when no scenario is given",
        live=False,
    )


def input_params(name: str) -> list[P]:
    """Where the node's defaults come from: a scenario's observer entry, else a card."""
    return params.config_params(ObserverInput(observer=name))


@dataclass
class ObserverCommon:
    """frame_id, the decimation, frames per kernel call."""

    frame_id: str = param(
        "",
        unit="",
        doc="header.frame_id of published estimates",
        live=False,
    )
    decimation: int = param(
        1,
        unit="-",
        doc="PWM periods per frame (a decimated CAN link, split mode): the "
        "observer steps at decimation x the machine card's PWM period",
        range=(1, 64),
        live=False,
    )
    block_frames: int = param(
        1,
        unit="frames",
        doc="frames per kernel call: 1 = each frame as it comes; N > 1 collects N"
        " frames (or what came within 50 ms of wall time) and runs them in "
        "one call, the estimates then go out together -- for shadow "
        "observers, whose estimates nothing waits for; the driving observer "
        "keeps 1",
        range=(1, 4096),
        live=False,
    )


def common_params(decimation: int) -> list[P]:
    """Input topic and durability, frame_id, the decimation, diagnostics."""
    return [
        *params.frame_input_params(),
        *params.config_params(ObserverCommon(decimation=int(decimation))),
        diag.PARAM,
    ]


# block_frames > 1: frames collected for longer than this (wall time) are processed anyway,
# so a paced or slow graph's shadow estimates are at most this late
BLOCK_WAIT_S = 0.05


class FrameBlock:
    """A block of PhaseFrames as FR_* rows, unpacked once for every shadow observer of the
    process.  The bus collects each shadow's frames for it on its own, but they are the same
    messages (one plant's), so the first shadow to run a block unpacks it and the others find
    it here (the last block only: the shadows run one after the other) -- as does the check
    against a card's sensor ranges (`out_of_range`, by the limits).  Equal messages give
    equal rows: the block is found again by comparing the messages, each one by identity
    first.  `rows` and `seqs` are shared: read them only."""

    _last: FrameBlock | None = None  # the block unpacked last in this process

    def __init__(self, datas: list[bytes], fw: FrameWire):
        self.datas = list(datas)  # its own list: the caller's may change
        n = len(datas)
        self.rows = np.zeros((n, FR_N))
        seqs = fw.unpack_block(self.datas, self.rows)
        if seqs is None:  # frames of several layouts: one by one
            seqs = [fw.unpack(data, self.rows[i]) for i, data in enumerate(self.datas)]
        self.seqs = np.asarray(seqs, dtype=np.int64)
        self.last_seq = int(max(seqs))
        self._oor: dict[bytes, bool] = {}

    @classmethod
    def of(cls, datas: list[bytes], fw: FrameWire) -> FrameBlock:
        blk = cls._last
        if blk is None or blk.datas != datas:
            blk = cls._last = cls(datas, fw)
        return blk

    def out_of_range(self, limits: np.ndarray) -> bool:
        """block_out_of_range of the rows against these limits (a card's)."""
        key = limits.tobytes()
        oor = self._oor.get(key)
        if oor is None:
            oor = self._oor[key] = bool(block_out_of_range(self.rows, limits))
        return oor


class ObserverNode(FluxNode):
    PLUGIN_SETTINGS = ObserverPlugin  # what a user variant declares besides its model

    def __init__(self, name: str = "observer", namespace: str | None = None, **kw):
        super().__init__(name, namespace, **kw)
        first = declare(self, input_params(name))
        obs_name = first["observer"]
        card, base, decimation = self._load(first)
        self.card = card
        base = base.resolved(card)  # frequencies left unset: from the card (card rules)
        # a user variant takes only its model (R^, L^, lambda^) and its constructor keywords
        # (`plugin_kwargs`, JSON); the kernel's filter and PLL settings do not apply to it
        self.specs = config_params(base, card)
        pv = declare(self, self.specs)
        if base.is_plugin:
            kw_text = declare(self, [_plugin_kwargs_param(base.extra)])["plugin_kwargs"]
            base = replace(base, extra=_parse_kwargs(kw_text))
        common = declare(self, common_params(decimation))
        self.sample_s = card.ts_s * int(common["decimation"])
        self.cfg = base.with_overrides(**pv)
        # a user variant runs its Python class per frame; a built-in one the kernel
        self.plugin = None
        if self.cfg.is_plugin:
            if int(common["decimation"]) != 1:
                raise ValueError(
                    f"{self.cfg.variant}: a user variant steps at the card's PWM period; "
                    f"decimation {common['decimation']} (split mode) needs a built-in variant"
                )
            self.plugin = build_observer(self.cfg, card, obs_name)
        self.params = None if self.plugin else self._params(self.cfg)
        self.state = np.zeros(OS_N)
        observer_reset(self.state)
        self.frame = np.zeros(FR_N)
        self.row = np.zeros(ES_N)
        self.stamp = Stamp(self.sample_s)
        self.fw = FrameWire()
        self.ew = EstimateWire(obs_name, common["frame_id"], graph_id=self.graph.id)
        self.exit_on_done = common["exit_on_done"]
        self._init_blocks(int(common["block_frames"]))
        self.last_seq = -1
        self.done_seq: int | None = None
        self.limits = frame_limits(card)
        self._kernels()
        self.counts = diag.Counters(
            "frames",
            "good",
            "bad_samples",
            "out_of_range",
            "repeated_or_backwards",
            "missing",
            "invalid_estimates",
            "lost_interval_frames",
        )
        self._lost_seen = 0.0
        self._lost_frame = -2  # seq of the last coasted lost-interval frame
        self._good_reported = 0
        self._frames_reported = 0
        self._logged = 0
        self._wire(common)
        on_set(self, self.specs, self._apply, lambda: self.last_seq + 1, card.ts_s)
        self.diag = diag.Diagnostics(self, common["diagnostics_period_s"])
        self.diag.add("input", self._diag_input)
        self.get_logger().info(
            f"{obs_name}: variant {self.cfg.variant}, {self.cfg.voltage_source} voltages, "
            f"publishing {self.pub.topic_name}"
        )

    def _wire(self, common: dict) -> None:
        """The estimate publisher, the frame subscription (rows from a plant in this process,
        or blocks for a shadow), the end of the run."""
        self.pub = RawPublisher(
            self, fm.RotorEstimate, "~/" + topics.ESTIMATE, qos.SAMPLES, stamp=self.stamp
        )
        frame_topic = topics.in_drive(self, common["frame_topic"])
        self.sub = RawSubscription(
            self,
            fm.PhaseFrame,
            frame_topic,
            self._on_frame if self.block > 1 else self._step,
            qos.reader(common["input_durability"]),
            block=self._block_reader(frame_topic),
            row_callback=self._step_row if self.block <= 1 else None,
        )
        self.create_subscription(
            fm.RunDone,
            topics.drive_topic(self, topics.DONE),
            self.graph.typed(topics.DONE, self._on_done),
            qos.LATCHED,
        )

    def _kernels(self) -> None:
        """The kernels of a frame (`_step`), without numba's dispatch: always these arrays."""
        self._out_of_range = direct(frame_out_of_range, self.frame, self.limits)
        self._observer_step = (
            observer_step
            if self.params is None
            else direct(observer_step, self.state, self.params, self.frame, self.row)
        )

    def _load(self, first: dict):
        """(card, the observer's config, decimation) of the scenario or the machine card,
        the variant as declared (an unknown or unloadable one: one line)."""
        base, decimation = None, 1
        if first["scenario"]:
            sc = load_scenario(scenario_path(first["scenario"]))
            card = sc.machine
            base = sc.observers.get(first["observer"])
            decimation = int(sc.control.decimation)
        else:
            card = load_machine(first["machine"])
        if base is None:
            base = observer_config("paper")
        spec = schema.specs(ObserverConfig)["variant"]
        variant = declare(self, [P.of(spec, base.variant)])["variant"]
        if variant != base.variant:
            base = observer_config(variant)
        return card, base, decimation

    def _params(self, cfg) -> np.ndarray:
        """The kernel's parameter row at this node's sample time."""
        op = cfg.to_params(self.card)
        op[OP_TS] = self.sample_s
        return op

    def _apply(self, changes: dict) -> str:
        if self.plugin is not None:
            raise ValueError(
                f"{self.cfg.variant} is a user variant: its parameters are fixed at start "
                f"(scenario or parameter file); rebuilding it would lose its state"
            )
        cfg = self.cfg.with_overrides(**changes)  # raises ConfigError with the reason
        assert self.params is not None  # a built-in variant's kernel row
        self.params[:] = self._params(cfg)
        self.cfg = cfg
        return f"applied from frame {self.last_seq + 1}"

    def _init_blocks(self, block_frames: int) -> None:
        """Shadows in blocks (block_frames > 1): frames wait here, then one observer_run."""
        self.block = block_frames if self.plugin is None else 1
        self.pending: list[bytes] = []
        self.blk_est = np.zeros((self.block, ES_N))
        if self.block > 1:
            self.create_timer(BLOCK_WAIT_S, self._flush)

    def _block_reader(self, topic: str):
        """How the frames of a publisher in this process come in blocks (block_frames > 1):
        the shadows of one graph with the same block size share a reader, so the bus
        collects each frame once for them all (fluxdrive_ros.intra.SharedBlockReader)."""
        if self.block <= 1:
            return None
        b = bus()
        if b is None:
            return BlockReader(self._on_frames, self.block)
        key = (self.resolve_topic_name(topic), int(self.graph.id), self.block)
        return b.shared_reader(key, self._on_frames, self.block)

    def _on_frame(self, data: bytes) -> None:
        if self.block > 1:
            self.pending.append(data)
            if len(self.pending) >= self.block or self.done_seq is not None:
                self._flush()
            return
        self._step(data)

    def _on_frames(self, parts: list[tuple[object, list[bytes]]]) -> None:
        """Frames from the plant in this process, collected by the bus (fluxdrive_ros.intra):
        run in blocks of at most `block_frames`."""
        datas = parts[0][1] if len(parts) == 1 else [d for _, part in parts for d in part]
        if self.pending:
            datas = self.pending + datas
        b = self.block
        for i in range(0, len(datas), b):
            self.pending = datas[i : i + b]
            self._flush()

    def _flush(self) -> None:
        """Process the collected frames in one observer_run -- the kernel loop replay uses,
        over observer_step, so the estimates are the per-frame ones bit for bit.  A block
        with a bad, out-of-range, repeated or missing frame or a lost interval is run
        again frame by frame from the state before it (the same checks, counts and log
        lines as without blocks)."""
        pend = self.pending
        if not pend:
            return
        self.pending = []
        n = len(pend)
        blk = FrameBlock.of(pend, self.fw)  # unpacked once for every shadow of the process
        est = self.blk_est[:n]
        st = self.state
        saved = st.copy()
        before = (st[OS_BAD], st[OS_STALE], st[OS_GAPS], st[OS_LOST])
        clean = not blk.out_of_range(self.limits)
        if clean:
            est.fill(0.0)
            observer_run(st, self.params, blk.rows, est)
            clean = (st[OS_BAD], st[OS_STALE], st[OS_GAPS], st[OS_LOST]) == before
        if not clean:
            st[:] = saved
            for data in pend:
                self._step(data)
            return
        # the block's estimates in one pass, to a reader of this process (the recorder) as
        # one block; the same messages as one by one
        seqs = blk.seqs
        self.pub.publish_block(self.ew.pack_block(est, seqs, self.stamp.ns_block(seqs)))
        c = self.counts.values
        c["frames"] += n
        c["good"] += n
        c["invalid_estimates"] += int(np.count_nonzero(est[:, ES_VALID] == 0.0))
        self.row[:] = est[n - 1]
        self.last_seq = max(self.last_seq, blk.last_seq)
        if self.done_seq is not None and self.last_seq >= self.done_seq:
            self.finished = True

    def _step(self, data: bytes) -> None:
        self._step_frame(self.frame, self.fw.unpack(data, self.frame))

    def _step_row(self, msg: tuple) -> None:
        """A frame of the plant in this process, as its row (fluxdrive_ros.intra; shared
        with the controller: read only)."""
        self._step_frame(msg[0], msg[1])

    def _step_frame(self, fr: np.ndarray, seq: int) -> None:
        st, c, row = self.state, self.counts.values, self.row
        before = (st.item(OS_BAD), st.item(OS_STALE), st.item(OS_GAPS))
        oor = self._out_of_range(fr, self.limits)
        if oor:  # beyond the sensors' full scale: a bad sample like a NaN
            if fr is not self.frame:  # another reader's row too: marked in our copy
                self.frame[:] = fr
                fr = self.frame
            fr[FR_IA] = np.nan
        row.fill(0.0)
        if self.plugin is not None:  # the user's class handles bad input its own way
            row[:] = self.plugin.step(fr.copy())
        else:
            self._observer_step(st, self.params, fr, row)
        self.pub.publish_row(self.ew.rc, row, seq)
        c["frames"] += 1
        if row.item(ES_VALID) == 0.0:
            c["invalid_estimates"] += 1
        if (st.item(OS_BAD), st.item(OS_STALE), st.item(OS_GAPS)) != before:
            self._count_bad(seq, oor, before)
        elif st.item(OS_LOST) != self._lost_seen:  # a lost interval (watchdog PWM off): coasted
            self._lost(seq)
        else:
            c["good"] += 1
        if seq > self.last_seq:
            self.last_seq = seq
        if self.done_seq is not None and seq >= self.done_seq:
            self.finished = True

    def _lost(self, seq: int) -> None:
        """A frame of a lost interval (the power stage's watchdog switched the PWM off;
        commanded voltages would be wrong): coasted -- one line when an interval begins."""
        c = self.counts.values
        first = self._lost_frame != seq - 1
        self._lost_seen = self.state[OS_LOST]
        self._lost_frame = seq
        c["lost_interval_frames"] = int(self._lost_seen)
        if first and self._logged < 10:
            self._logged += 1
            self.get_logger().warning(
                f"frame {seq}: PWM off by the power stage's watchdog (a lost interval): the "
                f"commanded voltage is not what the terminals saw -- coasting at w^ with the "
                f"flux state kept in phase, estimates flagged invalid until PWM is back"
            )

    def _count_bad(self, seq: int, oor: bool, before: tuple) -> None:
        st, c = self.state, self.counts.values
        c["bad_samples"] = int(st[OS_BAD])
        c["out_of_range"] += int(oor)
        c["repeated_or_backwards"] = int(st[OS_STALE])
        c["missing"] = int(st[OS_GAPS])
        if self._logged < 10:
            self._logged += 1
            what = (
                "out of range (beyond the sensors' full scale)"
                if oor
                else "not finite"
                if st[OS_BAD] != before[0]
                else f"repeated/backwards after {self.last_seq}"
                if st[OS_STALE] != before[1]
                else f"{int(st[OS_GAPS] - before[2])} frame(s) missing before it"
            )
            self.get_logger().warning(
                f"frame {seq}: {what}; estimate held and flagged invalid"
                + ("" if self._logged < 10 else " (further cases: /diagnostics only)")
            )

    def _diag_input(self) -> tuple[int, str, dict]:
        c = self.counts
        grew = c.grew("bad_samples", "repeated_or_backwards", "missing")
        lost = c.grew("lost_interval_frames")
        frames_new = c["frames"] - self._frames_reported
        good_new = c["good"] - self._good_reported
        self._frames_reported, self._good_reported = c["frames"], c["good"]
        values = {
            **c.report(),
            "last_seq": self.last_seq,
            "estimate_valid": bool(self.row[ES_VALID]),
        }
        if lost and not grew:
            return (
                diag.WARN,
                (
                    "lost interval (the power stage's watchdog switched the PWM "
                    "off): coasting, estimates flagged invalid"
                ),
                values,
            )
        if frames_new and not good_new:
            return (
                diag.ERROR,
                (f"no usable frame among the last {frames_new}: estimate held, flagged invalid"),
                values,
            )
        if grew:
            return (
                diag.WARN,
                "bad input since the last report ("
                + ", ".join(f"{k} {c[k]}" for k in grew)
                + "); estimates flagged invalid",
                values,
            )
        return (
            diag.OK,
            "input ok" + ("" if values["estimate_valid"] else " (estimate not valid yet)"),
            values,
        )

    def _on_done(self, msg) -> None:
        if not self.exit_on_done:
            return
        self.done_seq = int(msg.seq)
        self._flush()
        if self.last_seq >= self.done_seq:
            self.finished = True

    def close(self) -> None:
        if self.pending and self.context.ok():  # stopped: what came is processed and sent
            self._flush()
        if self.done_seq is not None:
            self.pub.wait_for_all_acked(_dur(10.0))


def _dur(s: float):
    from rclpy.duration import Duration

    return Duration(seconds=s)


def main(argv: list[str] | None = None) -> int:
    return main_node("flux_observer_node.node:ObserverNode", "observer", argv)


if __name__ == "__main__":
    sys.exit(main())
