"""Process faults and the recorder's guarantees: a node killed
mid-run is named by the launcher and handled per its `on_death` policy (stop, restart,
ignore); the plant takes the drive to PWM off when the controller is gone; the bag stays
readable whatever dies -- SIGTERM finalises it with every message received, a SIGKILL of the
recorder with its writer loses at most the open chunk and `./fluxdrive bag recover` rebuilds
a valid bag; a bag target that cannot be written is refused before anything starts; a write
failure mid-run (file-size limit standing in for a full disk) stops the recording cleanly.

Lockstep graphs on a ROS domain of their own (discovery on localhost), the launcher run
in-process so that the test can kill its processes by pid."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")
STATUS_STALE_COMMAND = 16


def graph_dict(
    bag: Path | None,
    *,
    duration_s: float = 60.0,
    processes: dict[str, str],
    observers: tuple[str, ...] = ("flux_measured",),
    policies: dict | None = None,
    plant: dict | None = None,
    recorder: dict | None = None,
    defaults: dict | None = None,
) -> dict:
    """A lockstep graph of the demo scenario: plant, observers (/obs/<name>), controller,
    recorder; `processes` = node name -> process name, `policies` = node name -> on_death
    keys."""
    n_subs = len(observers) + 1 + (bag is not None)
    common = {"scenario": SCENARIO, "input_durability": "transient_local"}
    nodes = [
        {
            "name": "plant",
            "node": "plant",
            "parameters": {
                **common,
                "duration_s": duration_s,
                "wait_frame_subscribers": n_subs,
                "start_delay_s": 0.3,
                "progress_interval_s": 0.1,
                **(plant or {}),
            },
        }
    ]
    for o in observers:
        nodes.append(
            {
                "name": o,
                "namespace": "/obs",
                "node": "observer",
                "parameters": {**common, "observer": o},
            }
        )
    nodes.append({"name": "controller", "node": "controller", "parameters": dict(common)})
    if bag is not None:
        nodes.append(
            {
                "name": "recorder",
                "node": "recorder",
                "parameters": {
                    **common,
                    "bag_dir": str(bag),
                    "observers": list(observers),
                    **(recorder or {}),
                },
            }
        )
    for nd in nodes:
        nd["process"] = processes.get(nd["name"], "drive")
        nd.update((policies or {}).get(nd["name"], {}))
    return {"name": "faults", **(defaults or {}), "nodes": nodes}


LEASE_XML = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="short_lease" is_default_profile="true">
    <rtps>
      <builtin>
        <discovery_config>
          <leaseDuration><sec>{lease_s}</sec></leaseDuration>
          <leaseAnnouncement><sec>0</sec><nanosec>500000000</nanosec></leaseAnnouncement>
        </discovery_config>
      </builtin>
    </rtps>
  </participant>
</profiles>
"""


def short_lease(tmp: Path, lease_s: int) -> dict:
    """graph_dict's `defaults` for every process of the graph to run with a Fast DDS
    participant lease of `lease_s` (announced every 0.5 s) instead of the default 20 s: a
    participant stopped or killed is dropped by the others after that long."""
    xml = tmp / "lease.xml"
    xml.write_text(LEASE_XML.format(lease_s=lease_s))
    return {"env": {"FASTRTPS_DEFAULT_PROFILES_FILE": str(xml)}}


# the lease of the graphs whose test SIGKILLs a reader of the plant's frames: a stopping
# writer waits for every matched reader's acknowledgement (fluxdrive_ros.runner,
# STOP_ACK_TIMEOUT_S = 10 s), and a killed reader stays matched until its participant's
# lease runs out (20 s by default): with 4 s the stop waits at most 4 s for the dead one
KILLED_LEASE_S = 4


class Run:
    """A Launcher running in a background thread; its [launch] and node lines collected."""

    def __init__(self, g: dict, dom: int, tmp: Path):
        from fluxdrive_bringup.launch.launcher import Launcher, parse_graph

        graph = parse_graph(g, "faults.yaml")
        graph.domain_id = dom
        self.lines: list[str] = []
        self.launcher = Launcher(graph, out=self, quiet=False, progress=False, log_dir=tmp / "logs")
        self.code: int | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def write(self, text: str) -> None:
        self.lines.extend(text.splitlines())

    def flush(self) -> None:
        pass

    def _run(self) -> None:
        self.code = self.launcher.run(timeout=150)

    def start(self) -> Run:
        self.thread.start()
        return self

    def text(self) -> str:
        return "\n".join(self.lines)

    def frames(self) -> int:
        p = self.launcher.progress
        return p[0] if p else 0

    def wait_frames(self, k: int, timeout: float = 90.0) -> int:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end and self.thread.is_alive():
            if self.frames() >= k:
                return self.frames()
            time.sleep(0.05)
        pytest.fail(f"the graph did not reach frame {k}:\n{self.text()}")

    def wait_line(self, pattern: str, timeout: float = 60.0, after: int = 0) -> re.Match:
        """The first line (from index `after` on) matching; self.at = its index."""
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            for i, ln in enumerate(list(self.lines)[after:]):
                m = re.search(pattern, ln)
                if m:
                    self.at = after + i
                    return m
            time.sleep(0.05)
        pytest.fail(f"no line matching {pattern!r}:\n{self.text()}")

    def pid(self, process: str) -> int:
        return next(p.popen.pid for p in self.launcher.procs if p.name == process)

    def join(self, timeout: float = 120.0) -> int:
        self.thread.join(timeout)
        assert not self.thread.is_alive(), self.text()
        return self.code


def read_frames(bag: Path) -> tuple[list[int], list[bool], list[int], dict[str, int]]:
    """Frames of a bag with rosbags' AnyReader (definitions from the bag itself): seq,
    pwm_enabled, status_flags; plus the message count per topic.  Cross-checked with the
    independent mcap reader."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    seqs, pwm, flags = [], [], []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/drive/frame"]
        for conn, _, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            seqs.append(int(m.seq))
            pwm.append(bool(m.pwm_enabled))
            flags.append(int(m.status_flags))
        # what the recorder received (the bag writer adds the run's settings message)
        counts = {
            c.topic: c.msgcount for c in reader.connections if c.topic != "/fluxdrive/settings"
        }
    files = sorted(bag.glob("*.mcap"))
    assert len(files) == 1
    with open(files[0], "rb") as fh:
        rd = make_reader(fh, decoder_factories=[DecoderFactory()])
        m_seqs = [msg.seq for _, _, _, msg in rd.iter_decoded_messages(topics=["/drive/frame"])]
    assert m_seqs == seqs
    return seqs, pwm, flags, counts


def fluxdrive(*args: str, timeout: float = 120.0, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    return subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kw,
    )


# ----------------------------------------------------------------------------- item 3
def test_kill_controller_stop_policy(tmp_path):
    """SIGKILL of the controller (a process of its own) mid-run, default on_death: stop.
    The launcher names the process, its node, pid and signal and exits 1; the graph is
    stopped with the recorder last, so the bag (finalised) ends with the plant's last
    period with the PWM off, flagged STATUS_STALE_COMMAND.  Every duty the recorder
    received is in the bag; duties still in flight from the killed controller when it died
    (the recorder lags it on a loaded machine) are gone with its writer, so the bag's duties
    are the recorder's own count, not the kill frame."""
    bag = tmp_path / "bag"
    g = graph_dict(
        bag,
        processes={"controller": "controller", "recorder": "recorder"},
        defaults=short_lease(tmp_path, KILLED_LEASE_S),
    )
    run = Run(g, domain(1), tmp_path).start()
    k_kill = run.wait_frames(3000)
    pid = run.pid("controller")
    os.kill(pid, signal.SIGKILL)
    code = run.join()
    out = run.text()
    print("\n".join(ln for ln in run.lines if ln.startswith("[launch]")))
    assert code == 1, out
    assert (
        f"process 'controller' died (signal SIGKILL, pid {pid}); "
        f"stopping the graph (on_death: stop)"
    ) in out
    m = run.wait_line(r"stopped before the end of the run: PWM off from frame (\d+)")
    k_off = int(m.group(1))
    received = _recorder_counts(run)
    seqs, pwm, flags, counts = read_frames(bag)
    print(
        f"killed at frame >= {k_kill}; plant stopped with PWM off at frame {k_off}; bag "
        f"{len(seqs)} frames, {counts.get('/drive/duty')} duties; recorder got {received}"
    )
    assert seqs == list(range(len(seqs))) and seqs[-1] == k_off
    assert not pwm[-1] and flags[-1] & STATUS_STALE_COMMAND
    assert any(pwm) and not any(f & STATUS_STALE_COMMAND for f in flags[:-1])
    assert counts["/drive/duty"] == received["/drive/duty"] > 0
    assert _duty_seqs(bag) == list(range(counts["/drive/duty"]))  # a prefix, no gap


def test_kill_controller_ignore_policy_plant_watchdog(tmp_path):
    """on_death: ignore for the controller: the graph runs on without it; the lockstep
    plant's watchdog (duty_timeout_s) takes the drive to PWM off -- each further timeout one
    more period with the PWM off, flagged stale -- until the graph is stopped (exit 0: the
    death was allowed)."""
    bag = tmp_path / "bag"
    g = graph_dict(
        bag,
        processes={"controller": "controller", "recorder": "recorder"},
        policies={"controller": {"on_death": "ignore"}},
        plant={"duty_timeout_s": 0.3},
        defaults=short_lease(tmp_path, KILLED_LEASE_S),
    )
    run = Run(g, domain(2), tmp_path).start()
    run.wait_frames(3000)
    pid = run.pid("controller")
    os.kill(pid, signal.SIGKILL)
    m = run.wait_line(r"watchdog: no duty command (\d+) for 0.3 s of wall time")
    j = int(m.group(1))
    run.wait_line(rf"died \(signal SIGKILL, pid {pid}\); on_death: ignore, the graph runs on")
    t_end = time.monotonic() + 30
    while run.frames() < j + 4 and time.monotonic() < t_end:  # a few watchdog periods
        time.sleep(0.1)
    run.launcher.stop()
    code = run.join()
    print("\n".join(ln for ln in run.lines if ln.startswith("[launch]")))
    assert code == 0, run.text()
    seqs, pwm, flags, _ = read_frames(bag)
    stale = [k for k, f in zip(seqs, flags, strict=True) if f & STATUS_STALE_COMMAND]
    print(f"controller killed; no duty {j}: frames {j + 2}..{seqs[-1]} PWM off, flagged stale")
    assert seqs == list(range(len(seqs)))
    assert stale == list(range(j + 2, len(seqs))) and len(stale) >= 3
    assert not any(pwm[j + 2 :]) and pwm[j + 1]


def test_restart_policy_controller(tmp_path):
    """The controller (a process of its own, on_death: restart) is SIGKILLed mid-run: the
    launcher restarts it (counted); the lockstep plant's watchdog runs the periods without
    a controller with the PWM off until the restarted controller -- a fresh sensorless
    start-up at the live frame (its readers skip the writers' history) -- answers; then
    lockstep resumes and the drive runs again; every frame is recorded; stopped by the
    test, exit 0."""
    bag = tmp_path / "bag"
    g = graph_dict(
        bag,
        plant={"duty_timeout_s": 0.5},
        processes={"controller": "controller", "recorder": "recorder"},
        policies={
            "controller": {"on_death": "restart", "max_restarts": 2, "restart_backoff_s": 0.2}
        },
        defaults=short_lease(tmp_path, 4),
    )
    run = Run(g, domain(3), tmp_path).start()
    k_kill = run.wait_frames(1000)
    pid = run.pid("controller")
    os.kill(pid, signal.SIGKILL)
    m = run.wait_line(r"watchdog: no duty command (\d+) for 0.5 s")
    j = int(m.group(1))
    # the restarted controller is a new DDS participant: the plant, there before, matches
    # its duty writer within 0.5-2 s -- or, in about a third of the runs here, only once the
    # dead participant's lease has run out (Fast DDS 2.14): 4 s here, not the default 20 s
    t0 = time.monotonic()
    run.wait_line(r"duty commands back \(seq \d+\); lockstep resumes", timeout=45)
    t_ctl = time.monotonic() - t0
    k_back = run.wait_frames(run.frames() + 3000)
    run.launcher.stop()
    code = run.join()
    print("\n".join(ln for ln in run.lines if ln.startswith("[launch]")))
    out = run.text()
    assert code == 0, out
    assert run.launcher.restarts == {"controller": 1}
    assert (
        f"process 'controller' died (signal SIGKILL, pid {pid}); restarting in 0.2 s "
        f"(restart 1 of 2)"
    ) in out
    assert re.search(r"process 'controller' restarted \(pid \d+, restart 1 of 2\)", out)

    seqs, pwm, flags, counts = read_frames(bag)
    n = len(seqs)
    stale = [k for k, f in zip(seqs, flags, strict=True) if f & STATUS_STALE_COMMAND]
    k_res = next(k for k in range(j + 2, n) if not flags[k] & STATUS_STALE_COMMAND)
    print(
        f"killed at frame >= {k_kill}; {n} frames; controller back {t_ctl:.1f} s after "
        f"the watchdog tripped: frames {j + 2}..{k_res - 1} PWM off (watchdog), lockstep "
        f"from {k_res}, PWM on in {sum(pwm[k_res:])} of the {n - k_res} frames after"
    )
    assert seqs == list(range(n)) and n >= k_back > k_res
    assert stale[: k_res - j - 2] == list(range(j + 2, k_res)) and not any(pwm[j + 2 : k_res])
    assert set(stale[k_res - j - 2 :]) <= {n - 1}  # + the final PWM-off frame, if recorded
    assert sum(pwm[k_res:]) > 2000  # the restarted controller drives again
    assert counts["/drive/duty"] >= j  # (the recorder, too, hears the new writer late)
    assert counts["/obs/flux_measured/estimate"] >= n - 3


def test_kill_driving_observer_controller_goes_pwm_off(tmp_path):
    """The driving observer (a process of its own, on_death: ignore) is killed: the
    controller waits for its estimate, trips 'stale input' after position_wall_timeout_s
    (latched, PWM off) and from then on answers every frame with the PWM off, so the
    lockstep run goes on with the bridge disabled (stopped by the test)."""
    bag = tmp_path / "bag"
    g = graph_dict(
        bag,
        processes={"flux_measured": "obs_fm", "recorder": "recorder"},
        policies={"flux_measured": {"on_death": "ignore"}},
        defaults=short_lease(tmp_path, KILLED_LEASE_S),
    )
    run = Run(g, domain(8), tmp_path).start()
    k_kill = run.wait_frames(2000)
    os.kill(run.pid("obs_fm"), signal.SIGKILL)
    m = run.wait_line(r"\[controller\]: (.*stale input.*)")
    run.wait_frames(run.frames() + 2000)
    run.launcher.stop()
    code = run.join()
    out = run.text()
    assert code == 0, out
    print(m.group(1))
    from rosbags.highlevel import AnyReader

    en = []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/drive/duty"]
        for conn, _, raw in reader.messages(connections=conns):
            d = reader.deserialize(raw, conn.msgtype)
            en.append((int(d.seq), bool(d.enable)))
    seqs, pwm, _, _ = read_frames(bag)
    n = len(seqs)
    first_off = next(k for k, e in en if k > 100 and not e)
    print(
        f"observer killed at frame >= {k_kill}; duties enabled until {first_off - 1}, "
        f"PWM off from duty {first_off} on ({n} frames)"
    )
    assert seqs == list(range(n)) and [k for k, _ in en] == list(range(len(en)))
    assert len(en) >= n - 3 and n > first_off + 2000
    assert first_off >= k_kill - 200 and not any(e for k, e in en if k >= first_off)
    assert not any(pwm[first_off + 2 :]) and any(pwm[:first_off])


LAYOUT_PROCESSES = {
    # composed: one process, the recorder closing last in it
    "composed": {},
    # separate: every node a process of its own
    "separate": {
        "plant": "plant",
        "flux_measured": "obs",
        "controller": "controller",
        "recorder": "recorder",
    },
}


def _graph_pids(stop_dir: Path) -> list[int]:
    """Live processes (not zombies) started for the graph: their environment names its
    stop directory (the launcher's processes and whatever they started, the bag writer)."""
    key = f"FLUXDRIVE_STOP_DIR={stop_dir}".encode()
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if key in (d / "environ").read_bytes().split(b"\0") and (
                (d / "stat").read_text().split()[2] != "Z"
            ):
                out.append(int(d.name))
        except OSError:
            continue
    return out


@pytest.mark.parametrize("layout", ["composed", "separate"])
def test_launcher_killed_graph_says_its_last_word(tmp_path, layout):
    """SIGKILL of the launcher mid-run: its processes (in sessions of their own) get SIGTERM
    from the kernel (parent-death signal) all at once; the plant takes the drive to PWM off
    and publishes that frame, the recorder waits until every process has said what it
    published (their counts files, the launcher being gone), takes it all and finalises the
    bag: the last frame recorded has the PWM off, every frame the plant published is in the
    bag or the shortfall is in its metadata, and no process of the graph is left."""
    import json

    import yaml

    bag = tmp_path / "bag"
    gpath = tmp_path / "graph.yaml"
    gpath.write_text(yaml.safe_dump(graph_dict(bag, processes=LAYOUT_PROCESSES[layout])))
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, TMPDIR=str(tmp))  # the launcher's stop directory goes there
    dom = domain(9) if layout == "composed" else domain(62)
    proc = subprocess.Popen(
        [sys.executable, "-m", "fluxdrive.cli", "launch", str(gpath), "--domain-id", str(dom)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()
    mcap = bag / "bag.mcap"
    t_end = time.monotonic() + 120
    while not (mcap.exists() and mcap.stat().st_size > 2_000_000):  # mid-run, a few chunks in
        assert proc.poll() is None and time.monotonic() < t_end, "".join(lines)
        time.sleep(0.1)
    stop_dir = next(tmp.glob("fluxdrive-stop-*"))
    pids = [int(x) for x in re.findall(r"started \(pid (\d+)\)", "".join(lines))]
    assert len(pids) == len(set(LAYOUT_PROCESSES[layout].values()) or {"drive"}), "".join(lines)
    proc.kill()
    proc.wait()
    t_end = time.monotonic() + 60
    while _graph_pids(stop_dir) and time.monotonic() < t_end:
        time.sleep(0.1)
    assert not _graph_pids(stop_dir), f"graph processes outlived the launcher: {pids}"
    seqs, pwm, _, _ = read_frames(bag)
    plant_proc = "plant" if layout == "separate" else "drive"
    published = json.loads((stop_dir / f"{plant_proc}.published.json").read_text())
    n_pub = published["/drive/frame"]
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    note = json.loads((info.get("custom_data") or {}).get("fluxdrive_missing") or "{}")
    print(
        f"{layout}: launcher SIGKILLed; its processes {pids} ended; the plant published "
        f"{n_pub} frames, the bag holds {len(seqs)} (last PWM {'on' if pwm[-1] else 'off'}); "
        f"metadata: {note or 'no shortfall'}"
    )
    assert seqs == list(range(len(seqs))) and len(seqs) > 1000
    if len(seqs) == n_pub:
        assert not pwm[-1] and any(pwm), "the last recorded frame must have the PWM off"
    else:  # the shortfall stated
        assert note["topics"]["/drive/frame"] == {"recorded": len(seqs), "published": n_pub}


def test_on_death_policy_errors_name_file_and_key():
    """Malformed on_death settings are refused with the file, the node and the key."""
    from fluxdrive.core.machine import ConfigError
    from fluxdrive_bringup.launch.launcher import parse_graph

    def bad(pol: dict, node: str = "controller", top: dict | None = None) -> str:
        g = graph_dict(
            Path("/tmp/x"), processes={"controller": "ctl"}, policies={node: pol}, defaults=top
        )
        with pytest.raises(ConfigError) as ei:
            parse_graph(g, "g.yaml")
        return str(ei.value)

    assert bad({"on_death": "explode"}) == (
        "g.yaml: nodes[2] (controller): on_death must be one of "
        "['stop', 'restart', 'ignore'], got 'explode'"
    )
    assert bad({"max_restarts": -1}) == (
        "g.yaml: nodes[2] (controller): max_restarts must be an integer in [0, 1000], got -1"
    )
    assert bad({"restart_backoff_s": "soon"}) == (
        "g.yaml: nodes[2] (controller): restart_backoff_s must be a number in "
        "[0.0, 3600.0], got 'soon'"
    )
    assert bad({}, top={"on_death": "retry"}) == (
        "g.yaml: on_death must be one of ['stop', 'restart', 'ignore'], got 'retry'"
    )
    assert "'on_death: restart' is not supported for a recorder" in bad(
        {"on_death": "restart"}, node="recorder"
    )
    assert "the nodes of process 'drive' disagree on on_death" in bad(
        {"on_death": "ignore"}, node="plant"
    )
    g = parse_graph(
        graph_dict(
            None,
            processes={"plant": "plant"},
            defaults={"on_death": "ignore"},
            policies={"plant": {"on_death": "stop"}},
        ),
        "g.yaml",
    )
    assert g.to_dict()["on_death"] == "ignore"
    assert {pn: g.policy(m)[0] for pn, m in g.processes().items()} == {
        "plant": "stop",
        "drive": "ignore",
    }


# ----------------------------------------------------------------------------- item 4
def _duty_seqs(bag: Path) -> list[int]:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/drive/duty"]
        return [
            int(reader.deserialize(raw, c.msgtype).seq)
            for c, _, raw in reader.messages(connections=conns)
        ]


def _recorder_counts(run: Run) -> dict[str, int]:
    m = run.wait_line(r"\[recorder\] .*finalised: \d+ messages \((.*)\)")
    return {t: int(c) for t, c in (x.rsplit(" ", 1) for x in m.group(1).split(", "))}


def test_sigterm_recorder_finalises_every_message(tmp_path):
    """SIGTERM to the recorder (a process of its own) mid-run: it stops between callbacks,
    hands everything it received to its writer and finalises the bag -- the bag holds
    exactly the per-topic counts the recorder reports, frames 0..N-1 without a gap; the
    recorder ends with 0, so the graph runs on to its end (exit 0)."""
    bag = tmp_path / "bag"
    g = graph_dict(bag, duration_s=1.0, processes={"recorder": "recorder"})
    g["nodes"][0]["required"] = True
    run = Run(g, domain(4), tmp_path).start()
    run.wait_frames(3000)
    os.kill(run.pid("recorder"), signal.SIGTERM)
    counts = _recorder_counts(run)
    code = run.join()
    assert code == 0, run.text()
    seqs, _, _, in_bag = read_frames(bag)
    print(f"recorder stopped by SIGTERM after {len(seqs)} frames; reported {counts}")
    # a topic recorded but never published (the scope's parameter markers) holds no message,
    # and rosbags lists no connection for it
    assert {t: c for t, c in in_bag.items() if c} == {t: c for t, c in counts.items() if c}
    # the recorder lags the plant on a loaded machine: it has fewer frames than the plant's
    # 3000 at the signal, but it stopped before the run's end
    assert seqs == list(range(len(seqs))) and 0 < len(seqs) < 10000
    assert "done: 10000 frames" in run.text()  # the drive ran on to its end


def _bag_bytes(bag: Path) -> int:
    """The bag's messages as an MCAP chunk holds them: data plus record head, every topic
    (the run's settings message aside)."""
    from fluxdrive.io.mcapfile import MESSAGE_HEAD_BYTES
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic != "/fluxdrive/settings"]
        return sum(len(raw) + MESSAGE_HEAD_BYTES for _, _, raw in reader.messages(conns))


def _sigkill_loss_bound(per_frame: float) -> float:
    """Bytes a SIGKILL of the recorder with its writer can lose (fluxdrive.io.bagwriter):
    the recorder's backlog and the feeder's batch taken off it (max_backlog_mb each), the
    pipe, the writer's read not yet in the bag, its open chunk; the backlog and the chunk
    are checked after a message is added, so each may be over by one frame's messages."""
    from fluxdrive.cli.bagwriter import PIPE_BYTES
    from fluxdrive.io.bagwriter import READ_BYTES
    from fluxdrive.io.mcapfile import CHUNK_BYTES
    from fluxdrive_bringup.record.recorder import RecorderWriting

    backlog = int(RecorderWriting().max_backlog_mb * 1e6)
    return 2 * backlog + PIPE_BYTES + READ_BYTES + CHUNK_BYTES + 3 * per_frame


def test_sigkill_recorder_and_writer_then_bag_recover(tmp_path):
    """SIGKILL of the recorder's whole process group mid-run of a lockstep graph (composed
    layout: the recorder, its bag writer and the drive nodes die at once -- nothing can
    finalise, nothing publishes after the kill).  The launcher names the process and the
    unfinalised bag and exits 1; `./fluxdrive bag recover` rebuilds a valid bag (rosbags
    and mcap open it) whose frames run from 0 without a gap.  Bounded in bytes by the writer's
    design (fluxdrive.io.bagwriter): what was published but is not in the recovered bag --
    the frames lost against the plant's last progress report (published at least that many;
    at most one report interval, 0.05 s of wall time, more), times the bag's bytes per frame
    -- is at most the recorder's backlog twice (its buffer and the feeder's batch), the pipe,
    one read of the writer and its open chunk, plus the report's slack."""
    bag = tmp_path / "bag"
    g = graph_dict(bag, processes={}, plant={"progress_interval_s": 0.05})
    run = Run(g, domain(5), tmp_path).start()
    run.wait_frames(8000)
    # kill once complete chunks are on disk (how many frames that takes depends on how fast
    # this machine runs the graph and the writer): at least 1 MB, so the cut below leaves some
    mcap_file = bag / "bag.mcap"
    t_end = time.monotonic() + 60.0
    while time.monotonic() < t_end and run.thread.is_alive():
        if mcap_file.exists() and mcap_file.stat().st_size >= 1_000_000:
            break
        time.sleep(0.02)
    else:
        pytest.fail(f"no 1 MB of complete chunks in {mcap_file} within 60 s:\n{run.text()}")
    pid = run.pid("drive")
    os.killpg(pid, signal.SIGKILL)
    code = run.join()
    out = run.text()
    print("\n".join(ln for ln in run.lines if ln.startswith("[launch]")))
    assert code == 1, out
    assert (
        f"process 'drive' (/plant, /obs/flux_measured, /controller, /recorder) died "
        f"(signal SIGKILL, pid {pid}); stopping the graph (on_death: stop)"
    ) in out
    assert (
        f"bag {bag} was not finalised (process 'drive' (/plant, /obs/flux_measured, "
        f"/controller, /recorder) ended with code -9); recover it with: ./fluxdrive bag "
        f"recover {bag}"
    ) in out
    k_last, _, wall = run.launcher.progress
    published_max = k_last + int(k_last / wall * 0.05) + 1
    assert not (bag / "metadata.yaml").exists() and (bag / "recording.json").exists()

    out_dir = tmp_path / "recovered"
    r = fluxdrive("bag", "recover", str(bag), "--out", str(out_dir))
    print(r.stdout)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "recovered " in r.stdout and "no gaps" in r.stdout
    seqs, _, _, counts = read_frames(out_dir)
    n = len(seqs)
    assert seqs == list(range(n)) and n > 0
    per_frame = _bag_bytes(out_dir) / n  # every topic's share of one frame, record heads too
    lost_bytes = (published_max - n) * per_frame
    slack = (published_max - k_last) * per_frame
    bound = _sigkill_loss_bound(per_frame)
    print(
        f"killed after {k_last}..{published_max} published frames; recovered {n} "
        f"({per_frame:.0f} bytes a frame): lost at most {published_max - n} frames = "
        f"{lost_bytes / 1e6:.2f} MB; the design's bound {bound / 1e6:.2f} MB + the report's "
        f"slack {slack / 1e6:.3f} MB"
    )
    assert lost_bytes <= bound + slack
    assert counts["/drive/duty"] >= n - 10 and counts["/obs/flux_measured/estimate"] >= n - 10

    from fluxdrive.io.bagio import read_run_bag  # the run's metadata came back too

    assert read_run_bag(out_dir).meta["scenario"]["name"] == "paper_2pct_150load"

    # a file cut inside its last chunk (killed while writing it): that chunk is dropped
    import shutil

    from fluxdrive.io.bagrecover import recover

    cut = tmp_path / "cut"
    cut.mkdir()
    shutil.copy(bag / "recording.json", cut)
    data = (bag / "bag.mcap").read_bytes()
    (cut / "cut.mcap").write_bytes(data[: len(data) - 200_000])
    rc = recover(cut, tmp_path / "cut-recovered")
    print(f"cut 200 kB before the end: {rc.chunks} complete chunks; {rc.stop_reason}")
    assert "the file ends inside a record" in rc.stop_reason and rc.chunks >= 1
    seqs_cut, _, _, _ = read_frames(tmp_path / "cut-recovered")
    assert seqs_cut == list(range(len(seqs_cut))) and 0 < len(seqs_cut) < n


def test_bag_target_refused_before_start(tmp_path):
    """An unwritable bags/ (its parent is a regular file: fails for root too) and a
    min_free_mb above the free space are refused in one line before any process starts."""
    from fluxdrive.core.machine import ConfigError
    from fluxdrive_bringup.launch.launcher import Launcher, parse_graph

    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    g = graph_dict(blocker / "bags" / "run1", processes={})
    gpath = tmp_path / "graph.yaml"
    import yaml

    gpath.write_text(yaml.safe_dump(g))
    r = fluxdrive("launch", str(gpath), "--domain-id", str(domain(6)), timeout=60)
    err = r.stderr.strip()
    print(err)
    assert r.returncode == 2 and "\n" not in err and "Traceback" not in err
    assert err.startswith(
        f"fluxdrive launch: configuration error: {gpath}: recorder /recorder: "
        f"cannot record to {blocker}/bags/run1: {blocker}/bags is not a "
        f"writable directory ("
    )
    assert "started (pid" not in r.stdout

    import shutil

    free_mb = shutil.disk_usage(tmp_path).free / 1e6
    g = graph_dict(tmp_path / "bag", processes={}, recorder={"min_free_mb": free_mb * 10})
    launcher = Launcher(parse_graph(g, "g.yaml"), quiet=True)
    with pytest.raises(
        ConfigError,
        match=r"g.yaml: recorder /recorder: cannot record to "
        r".*/bag: \d+ MB free on its file system, the recorder's min_free_mb "
        r"is \d+ MB",
    ):
        launcher.start()
    assert launcher.procs == []  # nothing was started


def test_write_failure_midrun_stops_recording_cleanly(tmp_path):
    """A bag write that fails mid-run (the recorder runs under a 3 MB file-size limit,
    RLIMIT_FSIZE: writes beyond it fail with EFBIG like ENOSPC on a full disk): the writer
    stops with one line, the recorder logs why and what to do and exits 1, the launcher
    stops the rest of the graph cleanly (on_death: stop) and names the bag; `bag recover`
    gets every complete chunk, frames from 0 without a gap."""
    bag = tmp_path / "bag"
    limit = 3_000_000
    g = graph_dict(bag, processes={"recorder": "recorder"})
    rec = g["nodes"].pop()
    args = ["--ros-args", "-r", "__node:=recorder"]
    for k, v in rec["parameters"].items():
        args += ["-p", f"{k}:={v if not isinstance(v, list) else '[' + ','.join(v) + ']'}"]
    code_ = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, "
        f"({limit}, {limit})); from fluxdrive_bringup.record.recorder import main; "
        "sys.exit(main(sys.argv))"
    )
    g["nodes"].append({"name": "recorder", "cmd": [sys.executable, "-c", code_, *args]})
    run = Run(g, domain(7), tmp_path).start()
    m = run.wait_line(r"\[recorder\] \[ERROR\] \[recorder\]: recording stopped: (.*)")
    code = run.join()
    out = run.text()
    print(m.group(0))
    print("\n".join(ln for ln in run.lines if ln.startswith("[launch]")))
    assert code == 1
    assert re.search(
        r"recording stopped: cannot write .*bag\.mcap: File too large \(after "
        r"\d+ messages\); the complete chunks can be recovered with \./fluxdrive "
        r"bag recover .*bag",
        out,
    )
    assert re.search(r"process 'recorder' died \(exit code 1, pid \d+\); stopping the graph", out)
    assert "Traceback" not in out
    assert f"bag {bag} was not finalised" in out
    assert (bag / "bag.mcap").stat().st_size <= limit

    from fluxdrive.io.bagrecover import recover

    rec_ = recover(bag, tmp_path / "recovered")
    seqs, _, _, _ = read_frames(tmp_path / "recovered")
    print(
        f"recovered {len(seqs)} frames, {rec_.messages} messages, {rec_.chunks} chunks "
        f"of {limit} bytes allowed"
    )
    assert seqs == list(range(len(seqs))) and len(seqs) > 1000


def test_graph_processes_get_the_shipped_dds_profile_unless_one_is_named(tmp_path, monkeypatch):
    """Every graph process runs with config/dds/fastdds_profiles.xml (writers' heartbeat
    0.1 s, so a stop does not wait up to Fast DDS's 3 s for its readers' last
    acknowledgement); a profile in the environment or the graph's env wins."""
    import xml.etree.ElementTree as ET

    from fluxdrive_bringup.launch.launcher import (
        DDS_PROFILE_VARS,
        DDS_PROFILES,
        Launcher,
        parse_graph,
    )

    for var in DDS_PROFILE_VARS:
        monkeypatch.delenv(var, raising=False)
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    hb = ET.parse(DDS_PROFILES).getroot().find("p:data_writer/p:times/p:heartbeatPeriod", ns)
    period_s = int(hb.find("p:sec", ns).text) + int(hb.find("p:nanosec", ns).text) * 1e-9
    assert period_s == pytest.approx(0.1)

    def env_of(defaults=None) -> dict[str, str]:
        g = parse_graph(graph_dict(None, processes={}, defaults=defaults), "profile.yaml")
        return Launcher(g, out=None, quiet=True, progress=False, log_dir=tmp_path).env()

    assert env_of()["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(DDS_PROFILES)
    assert env_of(short_lease(tmp_path, 2))["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("lease.xml")
    monkeypatch.setenv("FASTDDS_DEFAULT_PROFILES_FILE", "/elsewhere/mine.xml")
    assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in env_of()
