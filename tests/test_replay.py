"""Replay lab: bag round trip, reproduction of recorded estimates, user variants
(module:Class and entry point), CLI report, sweeps, bad bags, benchmark."""

from __future__ import annotations

import json
import shutil
import sys

import numpy as np
import pytest
from fluxdrive.cli import main as cli
from fluxdrive.drive.observers import ES_TH
from fluxdrive.drive.plant import TR_THETA_E
from fluxdrive.drive.scenario import CONFIG_DIR, REPO_ROOT, load_scenario
from fluxdrive.drive.sim import run_scenario
from fluxdrive.io.bagio import (
    est_topic,
    observer_states_at,
    read_run_bag,
    typestore,
    write_run_bag,
)
from fluxdrive.replay.lab import (
    bench_replay,
    expand_variants,
    parse_variant,
    replay_bag,
)

EXAMPLE = REPO_ROOT / "examples" / "my_observer"
SAMPLE = REPO_ROOT / "bags" / "samples" / "paper_2pct_150load"


@pytest.fixture(scope="module")
def sample():
    return read_run_bag(SAMPLE)


@pytest.fixture(scope="module")
def run():
    sc = load_scenario(
        CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml",
        overrides={"duration_s": 0.6, "steady_window_s": [0.3, 0.6]},
    )
    return run_scenario(sc, progress=False)


@pytest.fixture(scope="module")
def bags(run, tmp_path_factory):
    d = tmp_path_factory.mktemp("bags")
    full = write_run_bag(run, d / "full")
    k0 = 2500
    cut = write_run_bag(
        run,
        d / "cut",
        start_s=run.t[k0],
        observers=["flux_measured"],
        obs_states=observer_states_at(run, k0),
        duty=False,
    )
    return {"full": full, "cut": cut, "dir": d}


def test_bag_round_trip_is_exact(run, bags):
    b = read_run_bag(bags["full"])
    assert b.problems == []
    assert np.array_equal(b.frames, run.frames)
    assert np.allclose(b.t, run.t, rtol=0, atol=1e-9)
    assert set(b.est) == set(run.names)
    for i, nm in enumerate(run.names):
        assert np.array_equal(b.est[nm], run.est[i])
    assert np.array_equal(b.truth[:, TR_THETA_E], run.truth[:, TR_THETA_E])
    assert b.machine() == run.scenario.machine


@pytest.mark.parametrize("which", ["full", "cut"])
def test_replay_reproduces_recorded_estimates(bags, which):
    b = read_run_bag(bags[which])
    res = replay_bag(b, expand_variants(["@recorded"], b))
    assert res.recorded_diff, "nothing compared"
    for nm, d in res.recorded_diff.items():
        assert d <= 1e-9, (nm, d)
    # a changed parameter is a different observer
    res2 = replay_bag(b, [parse_variant("x=@flux_measured:cutoff_hz=20")])
    assert np.max(np.abs(res2.est[0, :, ES_TH] - b.est["flux_measured"][:, ES_TH])) > 1e-6


def test_variant_spec_parsing():
    v = parse_variant("paper:cutoff_hz=50,voltage_source=commanded")
    assert (v.target, v.params) == ("paper", {"cutoff_hz": 50.0, "voltage_source": "commanded"})
    v = parse_variant("mine=my_observer:ClampedFluxObserver:clamp=0.9")
    assert (v.label, v.target, v.params) == (
        "mine",
        "my_observer:ClampedFluxObserver",
        {"clamp": 0.9},
    )
    assert parse_variant("pkg.mod:Cls").target == "pkg.mod:Cls"


def test_user_variant_module_class_and_entry_point(sample, tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))
    # an installed distribution with the example's entry point (what `pip install -e
    # examples/my_observer` creates), found by importlib.metadata on sys.path
    dist = tmp_path / "my_observer-0.1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-observer\nVersion: 0.1.0\n")
    ep = "[fluxdrive.observers]\nclamped_flux = my_observer:ClampedFluxObserver\n"
    assert (
        'clamped_flux = "my_observer:ClampedFluxObserver"'
        in (EXAMPLE / "pyproject.toml").read_text()
    )
    (dist / "entry_points.txt").write_text(ep)
    monkeypatch.syspath_prepend(str(tmp_path))
    b = sample  # the worked example of docs/replay.md, over a shipped bag
    res = replay_bag(
        b,
        [
            parse_variant("mc=my_observer:ClampedFluxObserver"),
            parse_variant("clamped_flux"),
            parse_variant("tight=clamped_flux:clamp=0.95,speed_lpf_hz=5"),
        ],
    )
    assert np.array_equal(res.est[0], res.est[1])
    assert not np.array_equal(res.est[1], res.est[2])
    from fluxdrive.analysis.metrics import compute

    m = compute(res)
    # the shipped bags come from the paper scenarios on the non-ideal bench (voltage capture,
    # model errors, saturation): given the machine card's R, L, lambda the example's plain
    # clamped integrator tracks within 10 deg; given the bag's observer model (the default:
    # what the recorded observers ran with, R^ off by the bench's model error) the R^ error
    # integrates into a larger lag -- a pure integrator has no way to forget it
    on_card = compute(replay_bag(b, [parse_variant("clamped_flux")], card_model=True))
    rms_card = on_card["observers"]["clamped_flux"]["theta_err_rms_deg"]
    assert rms_card < 10.0
    assert m["observers"]["clamped_flux"]["theta_err_rms_deg"] > rms_card
    assert len((EXAMPLE / "my_observer" / "__init__.py").read_text().splitlines()) < 50


def test_cli_report_plots_and_augmented_bag(bags, tmp_path, capsys):
    out = tmp_path / "out"
    rc = cli.main(
        [
            "replay",
            str(bags["full"]),
            str(bags["cut"]),
            "-v",
            "@flux_measured",
            "-v",
            "paper:voltage_source=commanded",
            "--out",
            str(out),
            "--write-bag",
            str(tmp_path / "aug"),
        ]
    )
    assert rc == 0
    txt = capsys.readouterr().out
    assert "max |replayed - recorded| = 0" in txt
    m = json.loads((out / "metrics.json").read_text())
    assert set(m) == {"full", "cut"}
    assert "paper_voltage_source_commanded" in m["full"]["observers"]
    md = (out / "report.md").read_text()
    assert "| flux_measured |" in md and "| 0.00e+00 |" in md
    for png in ("theta_error", "theta_harmonics", "flux_locus", "speed"):
        assert (out / "full" / f"{png}.png").stat().st_size > 1000
        assert f"full/{png}.png" in md
    aug = read_run_bag(tmp_path / "aug" / "full")
    assert "paper_voltage_source_commanded" in aug.est and "emf_commanded" in aug.est
    assert np.array_equal(aug.est["flux_measured_replay"], aug.est["flux_measured"])


def test_no_truth_uses_encoder(run, tmp_path):
    p = write_run_bag(run, tmp_path / "notruth", truth=False, ctrl=False, duty=False)
    b = read_run_bag(p)
    res = replay_bag(b, [parse_variant("paper_robust")], card_model=True)
    assert res.truth_source == "encoder"
    from fluxdrive.analysis.metrics import compute

    assert compute(res)["observers"]["paper_robust"]["theta_err_rms_deg"] < 5.0
    # with the bag's observer model (the default) the encoder reference gives the truth's
    # figure to within the encoder's resolution (one count, in electrical degrees)
    card = run.scenario.machine
    count_deg = 360.0 * card.pole_pairs / (4.0 * card.encoder_lines)
    variant = [parse_variant("paper_robust")]
    on_encoder = compute(replay_bag(b, variant))["observers"]["paper_robust"]
    with_truth = write_run_bag(run, tmp_path / "truth", ctrl=False, duty=False)
    on_truth = compute(replay_bag(read_run_bag(with_truth), variant))["observers"]["paper_robust"]
    assert on_encoder["theta_err_rms_deg"] == pytest.approx(
        on_truth["theta_err_rms_deg"], abs=count_deg
    )


def test_sweep_parallel_with_progress_and_plot(bags, tmp_path, capsys):
    out = tmp_path / "sw"
    rc = cli.main(
        [
            "replay",
            str(bags["full"]),
            "-v",
            "paper",
            "--sweep",
            "cutoff_hz=20:200:3",
            "-j",
            "2",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    cap = capsys.readouterr()
    assert "[sweep] 3/3" in cap.err
    rows = json.loads((out / "sweep.json").read_text())["rows"]
    assert [r["cutoff_hz"] for r in rows] == [20.0, 110.0, 200.0]
    assert len({r["theta_err_rms_deg"] for r in rows}) == 3
    assert (out / "sweep.png").stat().st_size > 1000


def _bad(capsys, path) -> str:
    rc = cli.main(["replay", str(path), "--no-plots", "--out", str(path) + "-out"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def _writer(path, topics):
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for tp, ty, msgs in topics:
            c = w.add_connection(tp, ty, typestore=store)
            for k, m in enumerate(msgs):
                w.write(
                    c, 1000 * (k + 1), m if isinstance(m, bytes) else store.serialize_cdr(m, ty)
                )
    return path


def test_bad_bags_one_line_errors(tmp_path, capsys, run):
    assert "no such bag" in _bad(capsys, tmp_path / "nothere")
    (tmp_path / "junk").mkdir()
    assert "no metadata.yaml" in _bad(capsys, tmp_path / "junk")
    assert "empty" in _bad(capsys, _writer(tmp_path / "empty", []))
    store = typestore()
    s = store.types["std_msgs/msg/String"](data="hi")
    err = _bad(capsys, _writer(tmp_path / "foreign", [("/chatter", "std_msgs/msg/String", [s])]))
    assert "foreign message types" in err and "std_msgs/msg/String" in err
    from fluxdrive.io.messages import TruthWire

    tr = [TruthWire().pack(run.truth[k], k, 0, 1000 * k) for k in range(3)]
    err = _bad(
        capsys,
        _writer(tmp_path / "noframe", [("/drive/truth", "flux_drive_msgs/msg/PlantTruth", tr)]),
    )
    assert "no /drive/frame" in err
    # storage file replaced by garbage
    g = shutil.copytree(SAMPLE, tmp_path / "garbage")
    for f in g.glob("*.mcap*"):
        f.write_bytes(b"\x00" * 100)
    assert "cannot open bag" in _bad(capsys, g)


def test_truncated_bag_replays_what_it_holds(bags, tmp_path, capsys):
    t = shutil.copytree(bags["full"], tmp_path / "trunc")
    (f,) = t.glob("*.mcap")
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    b = read_run_bag(t)
    assert 0 < b.n < 6000
    assert any("truncated" in p for p in b.problems)
    assert any("/drive/frame:" in p and "missing" in p for p in b.problems)
    rc = cli.main(["replay", str(t), "--no-plots", "--out", str(tmp_path / "o")])
    assert rc == 0
    err = capsys.readouterr().err
    assert "partial bag" in err and "missing" in err and "Traceback" not in err
    # frames with gaps (lost messages): replayed back to back, counted
    from fluxdrive.io.bagio import read_run_bag as rr

    full = rr(bags["full"])
    assert full.problems == []


def test_sample_bags_shipped_small_and_documented():
    d = REPO_ROOT / "bags" / "samples"
    readme = (d / "README.md").read_text()
    for nm in ("paper_2pct_150load", "paper_6pct_stepload"):
        size = sum(p.stat().st_size for p in (d / nm).iterdir())
        assert size < 6e6, (nm, size)  # zstd chunks inside the MCAP (every tool opens it)
        assert nm in readme
        b = read_run_bag(d / nm)
        assert b.problems == [] and b.n >= 10000
        assert est_topic("flux_measured")[len("/obs/") : -len("/estimate")] in b.est
    assert "seed" in readme and "make_sample_bags.py" in readme


def test_sample_bag_replay_reproduces_live_estimates(sample):
    b = sample
    res = replay_bag(b, expand_variants(["@recorded"], b))
    assert max(res.recorded_diff.values()) <= 1e-9


def test_benchmark_replay(capsys):
    out = bench_replay(["--samples", "300000", "--variant", "paper", "--variant", "emf"])
    assert set(out["samples_per_s"]) == {"paper", "emf"}
    assert "[bench]" in capsys.readouterr().err


def test_live_replay_is_lazy_about_ros():
    import subprocess

    code = (
        "import sys, fluxdrive.replay.lab, fluxdrive.io.bagio; "
        "sys.exit(1 if 'rclpy' in sys.modules else 0)"
    )
    assert (
        subprocess.call([sys.executable, "-c", code], env={"PYTHONPATH": str(REPO_ROOT / "python")})
        == 0
    )


def test_duplicate_frames_of_two_graphs_are_reported(run, tmp_path):
    """A bag holding the frames of two runs interleaved (two graphs on one ROS domain, a
    restarted source): read_run_bag names the duplicates instead of replaying silently."""
    from fluxdrive.io.messages import FrameWire

    fw = FrameWire()
    one = [fw.pack(run.frames[k], 0, 1000 * k) for k in range(200)]
    mixed = [m for pair in zip(one, one, strict=True) for m in pair]
    b = read_run_bag(
        _writer(tmp_path / "dup", [("/drive/frame", "flux_drive_msgs/msg/PhaseFrame", mixed)])
    )
    assert b.n == 200
    dup = [p for p in b.problems if "duplicate frames" in p]
    assert len(dup) == 1 and dup[0].startswith(
        "200 duplicate frames (a seq recorded more than once; 200 times the seq did not"
    ), dup


def test_every_shipped_bag_deserializes_with_todays_types():
    """Every message of every shipped bag deserializes with today's message types through
    rclpy (the graph's own CDR), and says the same seq as the engine's reader."""
    pytest.importorskip("rclpy")
    from mcap.reader import make_reader
    from rclpy.serialization import deserialize_message

    msg_class = pytest.importorskip("fluxdrive_ros.topics").msg_class
    bags = sorted(p.parent for p in (REPO_ROOT / "bags" / "samples").glob("*/metadata.yaml"))
    assert len(bags) >= 2
    classes: dict[str, type] = {}
    for bag in bags:
        counts: dict[str, int] = {}
        (path,) = bag.glob("*.mcap")
        with open(path, "rb") as fh:
            # file order: a count per topic needs no time order (which costs a heap merge)
            for schema, channel, message in make_reader(fh).iter_messages(log_time_order=False):
                if schema.name not in classes:
                    classes[schema.name] = msg_class(schema.name)
                msg = deserialize_message(message.data, classes[schema.name])
                counts[channel.topic] = counts.get(channel.topic, 0) + 1
                if channel.topic == "/drive/frame":
                    assert msg.seq >= 0
        engine = read_run_bag(bag)
        assert counts["/drive/frame"] == engine.n, bag.name
        assert counts == engine.counts, bag.name


def test_replayed_variant_takes_the_bags_observer_model(sample, capsys, tmp_path):
    """A new variant replayed over a bench bag starts from the observer model (R^, L^,
    lambda^) the bag records, so a replayed `paper` is the recorded literal observer: the
    same θ̃ in the window (it starts fresh, the recorded one ran from t = 0); with the card's
    model instead (--card-model) it is a different observer."""
    from fluxdrive.analysis.metrics import compute
    from fluxdrive.io.bagio import recorded_observer_model

    model, source = recorded_observer_model(sample.meta)
    assert "observer_model" in source
    rec = sample.meta["observers"]["paper_measured"]
    assert model == {k: rec[k] for k in ("r_hat_ohm", "l_hat_h", "lambda_hat_vs")}
    card = sample.machine()
    assert model["r_hat_ohm"] != pytest.approx(card.resistance_ohm)  # the bench's R^ error
    variants = [parse_variant("paper"), parse_variant("@paper_measured")]
    res = replay_bag(sample, variants)
    assert res.model == model
    rms = {k: v["theta_err_rms_deg"] for k, v in compute(res)["observers"].items()}
    card_res = replay_bag(sample, [parse_variant("paper")], card_model=True)
    rms_card = compute(card_res)["observers"]["paper"]["theta_err_rms_deg"]
    print(
        f"θ̃ RMS: replayed paper {rms['paper']:.3f}°, recorded {rms['paper_measured']:.3f}°, "
        f"card model {rms_card:.3f}°"
    )
    assert rms["paper"] == pytest.approx(rms["paper_measured"], abs=0.02)
    assert abs(rms_card - rms["paper_measured"]) > 5 * abs(rms["paper"] - rms["paper_measured"])
    assert (
        cli.main(
            [
                "replay",
                str(SAMPLE),
                "-v",
                "paper",
                "--no-plots",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    assert "observer model" in capsys.readouterr().out


def _tuned_bag(src, dst, row: int, change: dict) -> int:
    """`src` rewritten as if flux_measured had been changed live at frame row `row`: its
    node's ParameterMarker (source "node") and its estimates from there on.  Returns the
    marker's seq."""
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.io.bagio import BagWriter, read_raw
    from fluxdrive.io.messages import EstimateWire
    from fluxdrive.io.topics import MARKER, SETTINGS, T_MARKER
    from fluxdrive.replay.lab import build_observer, run_with_changes

    b = read_run_bag(src)
    obs = build_observer(parse_variant("@flux_measured"), b, b.machine())
    est = run_with_changes(obs, np.ascontiguousarray(b.frames), [(row, change)])
    seqs = b.frames[:, FR_SEQ].astype(int)
    ew, store, i = EstimateWire("flux_measured"), typestore(), 0
    ((name, value),) = change.items()
    t = store.types
    stamp = t["builtin_interfaces/msg/Time"](*divmod(round(b.t[row] * 1e9), 10**9))
    marker = t[T_MARKER](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=""),
        seq=int(seqs[row]), graph_id=0, node="/obs/flux_measured", name=name,
        value=json.dumps(value), successful=True, reason="", source="node",
    )  # fmt: skip
    with BagWriter(dst, b.meta, epoch_offset_ns=0) as w:
        for topic, mtype, t_ns, raw in read_raw(src):
            if topic == SETTINGS:
                continue  # the writer writes its own
            if topic == est_topic("flux_measured"):
                st = divmod(round(b.t[i] * 1e9), 10**9)
                if i < row:  # the rows are aligned: before the change, the same bytes
                    assert ew.pack(b.est["flux_measured"][i], int(seqs[i]), *st) == bytes(raw)
                raw = ew.pack(est[i], int(seqs[i]), *st)
                if i == row:
                    cdr = store.serialize_cdr(marker, T_MARKER)
                    w.write(w.add_connection(MARKER, T_MARKER), t_ns, cdr)
                i += 1
            w.write(w.add_connection(topic, mtype), t_ns, bytes(raw))
    return int(seqs[row])


def test_sweep_applies_the_bags_markers_and_says_so(bags, tmp_path, capsys):
    """A sweep over a bag with a live change replays it: the value that keeps the recorded
    settings gives max |replayed - recorded| = 0 (the marker applied at its sample, the cut
    bag's recorded state restored); sweeping the changed setting itself replaces it, and
    the sweep says which."""
    from fluxdrive.drive.observers import ObserverConfig

    tuned = tmp_path / "tuned"
    _tuned_bag(bags["cut"], tuned, 1200, {"cutoff_hz": 40.0})
    b = read_run_bag(tuned)
    assert [(m["name"], m["value"]) for m in b.markers] == [("cutoff_hz", "40.0")]
    rec = b.meta["observers"]["flux_measured"]
    pll = ObserverConfig(**rec).resolved(b.machine()).pll_bandwidth_hz
    out = tmp_path / "sw"
    argv = ["replay", str(tuned), "-v", "@flux_measured", "-j", "1", "--out", str(out)]
    assert cli.main([*argv, "--sweep", f"pll_bandwidth_hz={pll!r},{2 * pll!r}"]) == 0
    text = capsys.readouterr().out
    print(text)
    assert "applied in every run at the sample they took effect: 1\n" in text
    assert f"pll_bandwidth_hz={pll:g} keeps the recorded settings: max |replayed" in text
    assert "max |replayed - recorded| = 0\n" in text
    rows = json.loads((out / "sweep.json").read_text())["rows"]
    assert [r["markers_applied"] for r in rows] == [1, 1]
    assert rows[0]["recorded_max_abs_diff"] == 0.0 and rows[1]["recorded_max_abs_diff"] is None
    # without the marker the same settings are not the recorded run
    plain = replay_bag(b, [parse_variant("@flux_measured")])
    b.markers = []
    assert replay_bag(b, [parse_variant("@flux_measured")]).recorded_diff["flux_measured"] > 1e-6
    assert plain.recorded_diff["flux_measured"] == 0.0
    # sweeping the changed setting: the swept value holds for the whole run
    assert cli.main([*argv, "--sweep", "cutoff_hz=40,60"]) == 0
    text = capsys.readouterr().out
    assert "effect: 0; 1 change(s) of cutoff_hz replaced by the swept value" in text
