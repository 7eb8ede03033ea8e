"""One line for every bad input the probe found on the command line: each case below ends with
one line on stderr naming the option, file or key, a non-zero exit and no traceback -- before
anything starts (no graph, no bag, no ROS call with a name rclpy cannot form).  The layers
that answer: `fluxdrive.core.schema.Parser` (every float option finite, every int option
int64, a bad option one line), `schema.option` (ranges), `fluxdrive.core.paths.check_output`
(an output written to before work starts), `fluxdrive_ros.topics.check_ros_name` (names),
the one YAML reader (`fluxdrive.core.yamlio`: regular files only), the launcher's node-class
check and `param set`'s value check.

`CASES` is also the table in docs/safety.md ("Bad input on the command line"):
`FLUXDRIVE_WRITE_DOCS=1 ./fluxdrive test tests/test_cli_one_line.py -k docs` rewrites it."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from ros_domains import domain

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "safety.md"
BEGIN = "<!-- bad-input:begin (generated from tests/test_cli_one_line.py CASES) -->"
END = "<!-- bad-input:end -->"
HUGE = "1" * 400
UNWRITABLE = "/sys/kernel/fluxdrive-out"  # EACCES for root too (sysfs)

# (id, what the probe did, argv ({tmp}: the test's folder, {ro}: a read-only file system,
# {file}: an existing file, {fifo}: a FIFO), what the one line must contain)
CASES: list[tuple[str, str, list[str], str]] = [
    ("run-nan", "`run --duration nan`", ["run", "demo", "--duration", "nan"], "--duration"),
    ("run-inf", "`run --duration inf`", ["run", "demo", "--duration", "inf"], "--duration"),
    ("run-neg", "`run --duration -1`", ["run", "demo", "--duration", "-1"], "--duration must be"),
    (
        "bench-nan",
        "`bench --sil --duration nan`",
        ["bench", "--sil", "--duration", "nan"],
        "--duration",
    ),
    (
        "bench-real-nan",
        "`bench --duration nan` (a real bench: nan passed its `<= 0` check)",
        ["bench", "--duration", "nan"],
        "--duration",
    ),
    (
        "bench-real-set",
        "`bench --set` with broken YAML for the bridge",
        ["bench", "--set", "bench_bridge.cur_limit_a=[1,"],
        "--set",
    ),
    (
        "benchmark-can-nan",
        "`benchmark can --rate nan` (an int(nan) traceback)",
        ["benchmark", "can", "--rate", "nan"],
        "--rate",
    ),
    (
        "run-out-file",
        "`run --out` on an existing file",
        ["run", "paper_2pct_150load", "--out", "{file}"],
        "is a file, not a folder",
    ),
    (
        "run-out-unwritable",
        "`run --out` on an unwritable path",
        ["run", "paper_2pct_150load", "--out", UNWRITABLE],
        "--out",
    ),
    (
        "run-out-ro",
        "`run --out` on a read-only file system",
        ["run", "paper_2pct_150load", "--out", "{ro}/out"],
        "Read-only file system",
    ),
    (
        "replay-window",
        "`replay --window nan:nan`",
        ["replay", "{tmp}/no_bag", "--window", "nan:nan"],
        "--window",
    ),
    (
        "replay-out",
        "`replay --out` unwritable",
        ["replay", "{tmp}/no_bag", "--out", UNWRITABLE],
        "--out",
    ),
    (
        "param-dump-o",
        "`param dump -o` unwritable",
        ["param", "dump", "/plant", "-o", UNWRITABLE + "/p.yaml"],
        "--output",
    ),
    (
        "launch-set-yaml",
        "`launch --set` with broken YAML",
        ["launch", "sim_lockstep", "--set", "plant.duration_s=[1,"],
        "--set",
    ),
    (
        "launch-set-huge",
        "`launch --set` with a 400-digit integer",
        ["launch", "sim_lockstep", "--set", f"plant.duration_s={HUGE}"],
        "--set",
    ),
    (
        "launch-class",
        "`launch` with node class `no_such_module:Thing`",
        ["launch", "{tmp}/graph.yaml"],
        "no module named 'no_such_module'",
    ),
    (
        "launch-class-attr",
        "`launch` with node class `json:Nope` (the module is there, the class is not)",
        ["launch", "{tmp}/graph_attr.yaml"],
        "module 'json' has no 'Nope'",
    ),
    (
        "log-dir",
        "`launch --log-dir` unwritable (was exit 0 after a traceback)",
        ["launch", "sim_lockstep", "--log-dir", UNWRITABLE],
        "--log-dir",
    ),
    (
        "param-get-name",
        "`param get` with an invalid node name",
        ["param", "get", "bad node!", "x"],
        "NODE",
    ),
    (
        "fault-reset-name",
        "`fault reset` with an invalid service name",
        ["fault", "reset", "/controller/reset fault"],
        "SERVICE",
    ),
    (
        "param-set-yaml",
        "`param set` with broken YAML",
        ["param", "set", "/plant", "load_scale", "[1,"],
        "not valid YAML",
    ),
    (
        "param-set-map",
        "`param set` with a mapping",
        ["param", "set", "/plant", "load_scale", "{{a: 1}}"],
        "got a mapping",
    ),
    (
        "param-set-mixed",
        "`param set` with a mixed list",
        ["param", "set", "/plant", "load_scale", "[1, a]"],
        "one type",
    ),
    (
        "param-set-int64",
        "`param set` with an integer over int64",
        ["param", "set", "/plant", "load_scale", "9223372036854775808"],
        "outside the 64-bit range",
    ),
    (
        "echo-field",
        "`topic echo --field nosuchfield`",
        ["topic", "echo", "/one_line_probe", "--field", "nosuchfield", "--wait", "20"],
        "has no field 'nosuchfield'",
    ),
    (
        "bag-recover-json",
        "`bag recover` on a foreign JSON-encoded MCAP",
        ["bag", "recover", "{tmp}/foreign.mcap", "--out", "{tmp}/rec"],
        "only rosbag2 bags",
    ),
    (
        "hz-window",
        "`topic hz -w -1` (busy-looped)",
        ["topic", "hz", "/x", "-w", "-1"],
        "-w must be",
    ),
    (
        "emulator-wait",
        "`can-emulator --lockstep-wait nan` (spun, deaf to SIGTERM)",
        ["can-emulator", "--lockstep-wait", "nan"],
        "--lockstep-wait must be",
    ),
    (
        "fifo",
        "a scenario path that is a FIFO (hung)",
        ["run", "{fifo}", "--duration", "0.1"],
        "not a regular file",
    ),
    (
        "speed-pu",
        "`speed_pu: 1e308` (overflowed to inf rpm)",
        ["sim", "{tmp}/fast.yaml"],
        "'speed_pu' must stay within",
    ),
    (
        "card-pole-pairs",
        "a machine card with `pole_pairs: 2.5`",
        ["sim", "{tmp}/card_scenario.yaml"],
        "'pole_pairs' must be an integer",
    ),
    (
        "card-pole-pairs-0",
        "a machine card with `pole_pairs: 0`",
        ["sim", "{tmp}/card_zero_scenario.yaml"],
        "'pole_pairs' = 0 is out of range [1, 64]",
    ),
    (
        "card-range",
        "a machine card with a per-unit value out of its range (`flux_h5: 0.9`)",
        ["sim", "{tmp}/card_h5_scenario.yaml"],
        "'flux_h5' = 0.9 is out of range [-0.5, 0.5]",
    ),
    (
        "card-nan",
        "a machine card with `flux_h5: .nan`",
        ["sim", "{tmp}/card_nan_scenario.yaml"],
        "'flux_h5' must be a finite number",
    ),
]
TESTS = {
    "echo-field": "test_field_of_a_live_topic",
    "launch-class-attr": "test_node_class_without_its_class",
}


def fluxdrive(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(domain(57)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    }
    return subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _one_line(r: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in r.stderr + r.stdout, r.stderr
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1, err
    return err


# Every case through the command line's own entry (fluxdrive.cli.main.main, what `python -m
# fluxdrive.cli` calls) in one interpreter: its stderr and exit per case, and any exception
# that escaped it (what would have been a traceback); a case still running after 60 s is
# recorded as hung.  One start-up for all cases instead of one each (2-3 s apiece).
BATCH = r"""
import contextlib, io, json, signal, sys, traceback
from fluxdrive.cli.main import main

class Hung(BaseException):
    pass

def hung(*_a):
    raise Hung()

signal.signal(signal.SIGALRM, hung)
out = {}
for case, argv in json.loads(sys.argv[1]).items():
    err, std = io.StringIO(), io.StringIO()
    code, escaped = None, ""
    signal.alarm(60)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(std):
            code = main(argv)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    except Hung:
        escaped = "hung for 60 s"
    except BaseException:
        escaped = traceback.format_exc()
    finally:
        signal.alarm(0)
    out[case] = {"code": code, "stderr": err.getvalue(), "stdout": std.getvalue(),
                 "escaped": escaped}
print("@batch " + json.dumps(out))
"""


@pytest.fixture(scope="module")
def batch(files):
    """{case: its outcome} of every parametrized case, run in one interpreter."""
    argvs = {c[0]: [a.format(**files) for a in c[2]] for c in CASES if c[0] not in TESTS}
    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(domain(57)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    }
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-c", BATCH, json.dumps(argvs)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("@batch ")), None)
    assert line is not None, r.stderr[-3000:]
    print(f"{len(argvs)} cases in {time.monotonic() - t0:.1f} s")
    return json.loads(line[7:])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The inputs: an existing file, a FIFO, a read-only file system (a tmpfs mounted
    read-only; root only), a foreign MCAP, a graph with a node class that does not exist,
    scenario and machine cards with bad numbers."""
    tmp = tmp_path_factory.mktemp("one_line")
    (tmp / "a_file").write_text("x")
    os.mkfifo(tmp / "scenario.fifo")
    ro = tmp / "ro"
    ro.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)], capture_output=True
    )
    (tmp / "graph.yaml").write_text(
        "name: bad_class\nnodes:\n  - {name: thing, node: 'no_such_module:Thing'}\n"
    )
    (tmp / "graph_attr.yaml").write_text(
        "name: bad_attr\nnodes:\n  - {name: thing, node: 'json:Nope'}\n"
    )
    card = (ROOT / "config" / "machines" / "default_spm.yaml").read_text()
    (tmp / "card.yaml").write_text(_set_key(card, "pole_pairs", "2.5"))
    (tmp / "card_nan.yaml").write_text(_set_key(card, "flux_h5", ".nan"))
    (tmp / "card_zero.yaml").write_text(_set_key(card, "pole_pairs", "0"))
    (tmp / "card_h5.yaml").write_text(_set_key(card, "flux_h5", "0.9"))
    base = (ROOT / "config" / "scenarios" / "tune_60rpm_80load.yaml").read_text()
    base = base.replace("../machines/", f"{ROOT}/config/machines/")
    base = base.replace("../benches/", f"{ROOT}/config/benches/")
    (tmp / "fast.yaml").write_text(
        "\n".join(ln for ln in base.splitlines() if not ln.startswith("speed_rpm:"))
        + "\nspeed_pu: 1e308\n"
    )
    for name in ("card", "card_nan", "card_zero", "card_h5"):
        (tmp / f"{name}_scenario.yaml").write_text(
            base.replace(f"{ROOT}/config/machines/default_spm.yaml", str(tmp / f"{name}.yaml"))
        )
    _foreign_mcap(tmp / "foreign.mcap")
    yield {
        "tmp": str(tmp),
        "file": str(tmp / "a_file"),
        "fifo": str(tmp / "scenario.fifo"),
        "ro": str(ro),
        "mounted": mounted.returncode == 0,
    }
    if mounted.returncode == 0:
        subprocess.run(["umount", str(ro)], check=False)


def _set_key(text: str, key: str, value: str) -> str:
    """The card's YAML with `key` set to `value` (added when absent)."""
    lines = [ln for ln in text.splitlines() if not ln.strip().startswith(f"{key}:")]
    return "\n".join([*lines, f"{key}: {value}", ""])


def _foreign_mcap(path: Path) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("thing", "jsonschema", b'{"type": "object"}')
        cid = w.register_channel("/thing", "json", sid)
        for i in range(5):
            w.add_message(cid, log_time=i, publish_time=i, data=b'{"a": %d}' % i)
        w.finish()


@pytest.mark.parametrize(
    ("case", "argv", "want"),
    [(c[0], c[2], c[3]) for c in CASES if c[0] not in TESTS],
    ids=[c[0] for c in CASES if c[0] not in TESTS],
)
def test_bad_input_is_one_line(case, argv, want, files, batch):
    if case == "run-out-ro" and not files["mounted"]:
        pytest.fail("could not mount a read-only tmpfs for the read-only case (needs root)")
    r = batch[case]
    assert not r["escaped"], r["escaped"]  # a traceback, or a hang
    err = r["stderr"].strip()
    assert "Traceback" not in err + r["stdout"], err
    assert len(err.splitlines()) == 1, err
    assert r["code"] not in (0, None), (r["code"], err)
    assert want in err, err
    print(f"{case}: exit {r['code']}: {err}")
    if case in ("run-out-file", "run-out-ro", "fifo", "run-nan"):
        assert "[launch]" not in r["stdout"] and "[run] graph" not in r["stdout"]  # nothing ran
    if case == "bag-recover-json":
        assert not Path(files["tmp"], "rec").exists()  # no half bag left behind


def test_the_wrapper_gives_the_same_one_line(files):
    """One case end to end through `python -m fluxdrive.cli` (the ./fluxdrive wrapper's
    command): the same line on stderr, exit 2."""
    r = fluxdrive("run", "demo", "--duration", "nan")
    line = _one_line(r)
    assert r.returncode == 2 and "--duration" in line, line


def test_field_of_a_live_topic(files):
    """`topic echo --field nosuchfield` on a live topic: refused with the type's fields
    before the first message is printed (was a KeyError traceback per message)."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Header

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain(57))
    node = rclpy.create_node("one_line_probe", context=ctx)
    pub = node.create_publisher(Header, "/one_line_probe", 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            pub.publish(Header(frame_id="x"))
            with contextlib.suppress(Exception):
                ex.spin_once(timeout_sec=0.05)

    t = threading.Thread(target=spin, daemon=True)
    t.start()
    try:
        case = next(c for c in CASES if c[0] == "echo-field")
        r = fluxdrive(*case[2])
        line = _one_line(r)
        assert r.returncode != 0 and case[3] in line, line
        assert "stamp" in line and "frame_id" in line, line  # the fields there are
        ok = fluxdrive("topic", "echo", "/one_line_probe", "--field", "frame_id", "-n", "1")
        assert ok.returncode == 0 and "x" in ok.stdout, ok.stderr
    finally:
        stop.set()
        t.join(5)
        ctx.try_shutdown()


def test_node_class_without_its_class(files):
    """A node class whose module imports but lacks the class: the process that would host it
    says so in one line (was a traceback), the launcher names it and stops, exit 1."""
    pytest.importorskip("rclpy")
    case = next(c for c in CASES if c[0] == "launch-class-attr")
    r = fluxdrive(*[a.format(**files) for a in case[2]])
    out = r.stdout + r.stderr
    assert "Traceback" not in out, out
    assert r.returncode != 0, out
    lines = [ln for ln in out.splitlines() if case[3] in ln]
    assert lines and lines[0].startswith("[thing] cannot start node 'thing': node class"), out


def docs_table() -> str:
    rows = ["| bad input | now | test |", "|---|---|---|"]
    for case, what, _argv, want in CASES:
        test = TESTS.get(case, f"test_bad_input_is_one_line[{case}]")
        rows.append(
            f"| {what} | one line containing `{want}`, non-zero exit, nothing started | "
            f"`tests/test_cli_one_line.py::{test}` |"
        )
    return "\n".join(rows)


def test_docs_table_is_current():
    text = DOC.read_text()
    new = f"{BEGIN}\n{docs_table()}\n{END}"
    start, end = text.find(BEGIN), text.find(END)
    assert start >= 0 and end > start, f"docs/safety.md lacks the {BEGIN} ... {END} block"
    current = text[start : end + len(END)]
    if current != new and os.environ.get("FLUXDRIVE_WRITE_DOCS") == "1":
        DOC.write_text(text[:start] + new + text[end + len(END) :])
        return
    assert current == new, (
        "docs/safety.md's bad-input table is out of date: "
        "FLUXDRIVE_WRITE_DOCS=1 ./fluxdrive test tests/test_cli_one_line.py -k docs"
    )


def test_log_file_on_a_full_disk_does_not_stop_the_output(tmp_path):
    """A log folder that fills up while a graph runs (a 4 KiB tmpfs here): the launcher says
    so in one line and keeps reading the process's output (a reader that died of the
    ENOSPC left the process blocked on a full pipe)."""
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive_bringup.launch.launcher import Graph, Launcher, Proc

    logs = tmp_path / "logs"
    logs.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4k", "tmpfs", str(logs)]).returncode:
        pytest.fail("could not mount a 4 KiB tmpfs (needs root)")
    try:
        out = io.StringIO()
        launcher = Launcher(Graph(name="t", nodes=[]), quiet=True, log_dir=logs)
        launcher.out = out
        # 200 000 lines of 80 bytes: 16 MB, far more than a pipe and the disk hold
        code = "import sys\nfor i in range(200000): print('x' * 79)\nprint('last line')"
        p = Proc("chatty", [], [sys.executable, "-c", code])
        p.popen = subprocess.Popen(p.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        launcher._pump(p)
        assert p.popen.wait(timeout=60) == 0  # it wrote everything: nobody stopped reading
        assert p.tail[-1] == "last line"
        said = [ln for ln in out.getvalue().splitlines() if "log file of chatty" in ln]
        assert said == ["[launch] log file of chatty stopped: No space left on device"], said
    finally:
        subprocess.run(["umount", str(logs)], check=False)
