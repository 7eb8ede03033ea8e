"""Property-based fuzz (hypothesis, derandomized: the same inputs every run) of the entry points
beyond the config loaders (tests/test_config_fuzz.py): every command's options, the checks
that follow the parse (ROS names, `param set` values, output paths), and the operator's
servers' requests (the Foxglove gate, the scope).

The properties:
- a command's parser (its real `main`, stopped right after `parse_args`) accepts an option
  line or refuses it with one line naming it (exit 2, or ConfigError from a ranged option);
  whatever it accepts holds finite floats and int64 ints;
- a name `check_ros_name` accepts, rclpy accepts too; a value `parse_value` accepts becomes a
  ROS parameter message; a path `check_output` accepts can be written, one it refuses is one
  line;
- the Foxglove gate answers any request head with 101 only for the holder of the token from
  this machine, otherwise one line with a 4xx/503 status, at once, and still lets the operator
  in afterwards; the scope answers any request with a status below 500 and one line when it
  refuses.
Bounded: a few hundred examples, seconds each test on this machine."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from ros_domains import domain

ROOT = Path(__file__).resolve().parents[1]
FUZZ = dict(
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
TOKEN = "fuzz-token-0123"
SKIP_COMMANDS = {"test", "lint"}  # subprocesses of pytest and ruff, not the project's parsers

# hostile option values: non-finite and huge numbers, texts, paths nobody can write
HOSTILE = st.one_of(
    st.sampled_from(
        [
            "nan",
            "inf",
            "-inf",
            "-1",
            "0",
            "1e308",
            "-1e-320",
            "1" * 400,
            "",
            " ",
            "--",
            "-",
            "/sys/kernel/x",
            "/dev/null",
            "a b",
            "{a: 1}",
            "[1,",
            "'",
            "\x00",
            "é",
            "0x10",
        ]
    ),  # fmt: skip
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-(2**70), max_value=2**70).map(str),
    st.text(max_size=12),
)


class _Parsed(Exception):
    def __init__(self, ns: argparse.Namespace) -> None:
        self.ns = ns


class _Captured(Exception):
    def __init__(self, parser: argparse.ArgumentParser) -> None:
        self.parser = parser


def _commands() -> list[str]:
    """Every command, and every `benchmark NAME` (each one a command with its own parser)."""
    from fluxdrive.cli.bench import BENCHES
    from fluxdrive.cli.main import COMMANDS

    cmds = [k for k in COMMANDS if k not in SKIP_COMMANDS and k != "benchmark"]
    return cmds + [f"benchmark {name}" for name in BENCHES]


def _func(cmd: str):
    import importlib

    from fluxdrive.cli.main import COMMANDS

    word, _, sub = cmd.partition(" ")
    mod, fn, _ = COMMANDS[word]
    main = getattr(importlib.import_module(mod), fn)
    return (lambda argv: main([sub, *argv])) if sub else main


@pytest.fixture(scope="module")
def parsers():
    """Every command's parser, taken from its real `main` (parse_args stopped at its start)."""
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive.core.schema import Parser

    orig = Parser.parse_args

    def capture(self, args=None, namespace=None):
        raise _Captured(self)

    Parser.parse_args = capture  # type: ignore[method-assign]
    out = {}
    try:
        for cmd in sorted(_commands()):
            try:
                _func(cmd)([])
            except _Captured as c:
                out[cmd] = c.parser
            except BaseException as exc:  # noqa: BLE001 - a command that parses otherwise
                print(f"{cmd}: no Parser reached ({type(exc).__name__})")
    finally:
        Parser.parse_args = orig  # type: ignore[method-assign]
    return out


def _argv_strategy(parser: argparse.ArgumentParser):
    """An option line for `parser`: its subcommand (if any), positionals and some options,
    each with a hostile value."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if subs:
        choices = subs[0].choices
        return st.sampled_from(sorted(choices)).flatmap(
            lambda name: _argv_strategy(choices[name]).map(lambda rest: [name, *rest])
        )
    opts = [a for a in parser._actions if a.option_strings and a.dest != "help"]
    pos = [a for a in parser._actions if not a.option_strings]

    def build(pos_vals, picks):
        argv = list(pos_vals)
        for action, value in picks:
            flag = action.option_strings[-1]
            argv += [flag] if action.nargs == 0 else [flag, value]
        return argv

    picks = st.lists(st.tuples(st.sampled_from(opts), HOSTILE), max_size=4) if opts else st.just([])
    return st.builds(build, st.lists(HOSTILE, min_size=len(pos), max_size=len(pos)), picks)


def _check_parse(cmd: str, argv: list[str]) -> str:
    """Run the command's main with `argv`, stopped right after parsing; the outcome."""
    from fluxdrive.core.errors import ConfigError
    from fluxdrive.core.schema import Parser

    orig = Parser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        raise _Parsed(orig(self, args, namespace))

    err = io.StringIO()
    Parser.parse_args = parse_then_stop  # type: ignore[method-assign]
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            _func(cmd)(list(argv))
    except _Parsed as p:
        for k, v in vars(p.ns).items():
            if isinstance(v, float):
                assert math.isfinite(v), (cmd, argv, k, v)
            if isinstance(v, int) and not isinstance(v, bool):
                assert -(2**63) <= v < 2**63, (cmd, argv, k, v)
        return "parsed"
    except SystemExit as e:
        text = err.getvalue().strip()
        assert e.code == 2 and len(text.splitlines()) == 1, (cmd, argv, e.code, text)
        assert "Traceback" not in text
        return "refused"
    except ConfigError as e:
        assert len(str(e).splitlines()) == 1 and str(e).startswith("-"), (cmd, argv, str(e))
        return "refused"
    finally:
        Parser.parse_args = orig  # type: ignore[method-assign]
    raise AssertionError(f"{cmd} {argv}: returned without parsing")


def test_fuzz_every_command_option(parsers):
    """Every command's options, hostile values: parsed (finite, int64) or one line."""
    want = {"run", "launch", "param", "topic", "bench", "replay", "scope", "foxglove"}
    want |= {"benchmark can", "benchmark graph", "benchmark engine"}
    assert want <= set(parsers), sorted(parsers)
    seen: dict[str, int] = {}
    t0 = time.monotonic()

    @settings(max_examples=400, **FUZZ)
    @given(data=st.data())
    def prop(data):
        cmd = data.draw(st.sampled_from(sorted(parsers)))
        argv = data.draw(_argv_strategy(parsers[cmd]))
        outcome = _check_parse(cmd, argv)
        seen[outcome] = seen.get(outcome, 0) + 1

    prop()
    print(f"{len(parsers)} commands: {seen} in {time.monotonic() - t0:.1f} s")
    assert seen.get("refused") and seen.get("parsed"), seen


# ----------------------------------------------------------------- after the parse
NAMEISH = st.one_of(
    st.text(alphabet="/_aZ09 ~{}.-!", max_size=16), st.from_regex(r"/?[a-z_]\w{0,6}(/\w{1,5}){0,2}")
)


def test_fuzz_ros_names_agree_with_rclpy():
    pytest.importorskip("rclpy")
    from fluxdrive.core.errors import ConfigError
    from fluxdrive_ros.topics import check_ros_name
    from rclpy.validate_full_topic_name import validate_full_topic_name

    counts = {"accepted": 0, "refused": 0}

    @settings(max_examples=300, **FUZZ)
    @given(name=NAMEISH)
    def prop(name):
        try:
            full = check_ros_name(name, "NAME")
        except ConfigError as exc:
            assert len(str(exc).splitlines()) == 1 and str(exc).startswith("NAME ")
            counts["refused"] += 1
            return
        validate_full_topic_name(full, is_service=True)  # raises if rclpy disagrees
        counts["accepted"] += 1

    prop()
    print(counts)
    assert all(counts.values()), counts


def test_fuzz_param_values_become_parameter_messages():
    pytest.importorskip("rclpy")
    from fluxdrive.core.errors import ConfigError
    from fluxdrive_bringup.inspect.commands import parse_value
    from rclpy.parameter import Parameter

    yamlish = st.one_of(
        st.text(max_size=20),
        st.recursive(
            st.one_of(
                st.booleans(),
                st.integers(min_value=-(2**70), max_value=2**70),
                st.floats(),
                st.text(max_size=5),
                st.none(),
            ),
            lambda c: st.one_of(st.lists(c, max_size=4), st.dictionaries(st.text(max_size=3), c)),
            max_leaves=8,
        ).map(lambda v: json.dumps(v, allow_nan=False) if _jsonable(v) else str(v)),
    )
    counts = {"accepted": 0, "refused": 0}

    @settings(max_examples=400, **FUZZ)
    @given(text=yamlish)
    def prop(text):
        try:
            v = parse_value(text, None)
        except ConfigError as exc:
            assert len(str(exc).splitlines()) == 1 and str(exc).startswith("value ")
            counts["refused"] += 1
            return
        Parameter("x", value=v).to_parameter_msg()  # rclpy can form it
        counts["accepted"] += 1

    prop()
    print(counts)
    assert all(counts.values()), counts


def _jsonable(v) -> bool:
    try:
        json.dumps(v, allow_nan=False)
    except ValueError:
        return False
    return True


def test_fuzz_output_paths(tmp_path):
    from fluxdrive.core.errors import ConfigError
    from fluxdrive.core.paths import check_output

    (tmp_path / "file").write_text("x")
    (tmp_path / "dir").mkdir()
    part = st.sampled_from(["file", "dir", "new", "..", ".", "a b", "x" * 300, "é"])
    counts = {"accepted": 0, "refused": 0}

    @settings(max_examples=200, **FUZZ)
    @given(parts=st.lists(part, min_size=1, max_size=4), kind=st.sampled_from(["dir", "file"]))
    def prop(parts, kind):
        path = tmp_path.joinpath(*parts)
        try:
            p = check_output(path, "--out", kind=kind)
        except ConfigError as exc:
            assert len(str(exc).splitlines()) == 1 and str(exc).startswith("--out ")
            counts["refused"] += 1
            return
        counts["accepted"] += 1
        target = p if kind == "dir" else p.parent
        target.mkdir(parents=True, exist_ok=True)  # what the command then does
        assert os.access(target, os.W_OK)

    prop()
    print(counts)
    assert all(counts.values()), counts


# ----------------------------------------------------------------- the servers
HEADER_NAMES = ["Host", "Origin", "X-Fluxdrive-Token", "Upgrade", "Connection", "X", "host"]
HEADER_VALUES = st.one_of(
    st.sampled_from(
        [
            "127.0.0.1",
            "localhost:1",
            "evil.example",
            "[::1]:9",
            "null",
            "http://127.0.0.1:9",
            "http://evil.example",
            "websocket",
            "Upgrade",
            TOKEN,
            "",
            "a" * 300,
        ]
    ),  # fmt: skip
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=20),
)
TARGETS = st.one_of(
    st.sampled_from(["/", f"/?token={TOKEN}", "/?token=", "/ws", f"/ws?token={TOKEN}", "*"]),
    st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=126), max_size=30),
)


def test_fuzz_access_rules():
    from fluxdrive_bringup.view.gate import Access, host_name

    a = Access("fuzz", TOKEN, log=lambda _line: None)

    @settings(max_examples=400, **FUZZ)
    @given(
        target=TARGETS,
        headers=st.dictionaries(st.sampled_from(HEADER_NAMES), HEADER_VALUES, max_size=4),
    )
    def prop(target, headers):
        bad = a.check(target, headers)
        if bad is None:  # let in: the holder of the token, addressing this machine
            assert host_name(headers["Host"]) in ("127.0.0.1", "localhost", "::1")
            assert TOKEN in target or headers.get("X-Fluxdrive-Token") == TOKEN
            origin = headers.get("Origin")
            assert origin is None or host_name(origin.split("://", 1)[-1]) in (
                "127.0.0.1",
                "localhost",
                "::1",
            )
        else:
            assert bad[0] in (400, 403) and "\n" not in bad[1]

    prop()


def _exchange(port: int, data: bytes, timeout: float = 10.0) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(data)
        if b"\r\n\r\n" not in data:  # an incomplete head: say that nothing more comes
            s.shutdown(socket.SHUT_WR)
        out = b""
        with contextlib.suppress(TimeoutError, ConnectionError):
            while chunk := s.recv(4096):
                out += chunk
                if b"\r\n\r\n" in out and not out.startswith(b"HTTP/1.1 101"):
                    break
                if out.startswith(b"HTTP/1.1 101") and b"serverInfo" in out:
                    break
    return out


def test_fuzz_foxglove_gate_requests():
    foxglove = pytest.importorskip("foxglove")
    ws_client = pytest.importorskip("websockets.sync.client")
    from fluxdrive_bringup.view.gate import Access, FoxgloveGate
    from fluxdrive_ros.security import loopback_tls_pair

    cert, key = loopback_tls_pair()
    server = foxglove.start_server(host="127.0.0.1", port=0, tls_cert=cert, tls_key=key)
    gate = FoxgloveGate(Access("foxglove", TOKEN, log=lambda _line: None), server.port, cert)
    gate.start("127.0.0.1", 0)
    counts: dict[str, int] = {}
    try:
        base = {
            "Host": f"127.0.0.1:{gate.port}",
            "Upgrade": "websocket",
            "Connection": "Upgrade",
            "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
            "Sec-WebSocket-Version": "13",
            "Sec-WebSocket-Protocol": "foxglove.sdk.v1",
        }

        @settings(max_examples=150, **FUZZ)
        @example(method="GET", target=f"/?token={TOKEN}", drop=set(), extra=[], tail=b"\r\n")
        @given(
            method=st.sampled_from(["GET", "GET", "POST", "get", "", "GET /"]),
            target=TARGETS,
            drop=st.sets(st.sampled_from(sorted(base)), max_size=2),
            extra=st.lists(st.tuples(st.sampled_from(HEADER_NAMES), HEADER_VALUES), max_size=3),
            tail=st.sampled_from([b"\r\n", b"\r\n", b"", b"\n", b"\r\n" + b"x" * 20000]),
        )
        def prop(method, target, drop, extra, tail):
            headers = [(k, v) for k, v in base.items() if k not in drop] + extra
            lines = [f"{method} {target} HTTP/1.1"] + [f"{k}: {v}" for k, v in headers]
            data = ("\r\n".join(lines) + "\r\n").encode() + tail
            t0 = time.monotonic()
            out = _exchange(gate.port, data)
            status = out.split(b" ", 2)[1].decode() if out.startswith(b"HTTP/1.1 ") else "none"
            counts[status] = counts.get(status, 0) + 1
            assert time.monotonic() - t0 < 15.0
            if status == "101":  # only the holder of the token, from this machine
                assert TOKEN.encode() in data
            else:  # the SDK's own answer (e.g. 400) or the gate's one line
                assert status.startswith("4") or status == "503", (data[:300], out[:200])
                if b"foxglove: refused" in out:
                    body = out.split(b"\r\n\r\n", 1)[1]
                    assert body.count(b"\n") == 1, body

        prop()
        # the operator still gets in
        url = f"ws://127.0.0.1:{gate.port}/?token={TOKEN}"
        with ws_client.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=20) as ws:
            assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
    finally:
        gate.stop()
        server.stop()
    print(counts)
    assert counts.get("403") and counts.get("101"), counts


def _http(base: str, method: str, path: str, headers: dict, body: bytes | None):
    req = urllib.request.Request(base + path, data=body, headers=headers, method=method)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


@pytest.mark.timeout(300)
def test_fuzz_scope_requests():
    pytest.importorskip("aiohttp")
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive_ros.topics import ROS_NAME_RE

    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(domain(58)),
        PYTHONUNBUFFERED="1",
    )
    argv = [sys.executable, "-m", "fluxdrive.cli", "scope", "--port", "0", "--token", TOKEN]
    proc = subprocess.Popen(
        [*argv, "--attach-wait", "3600"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    counts: dict[int, int] = {}
    try:
        line = ""
        t_end = time.monotonic() + 60
        while "scope: http" not in line and time.monotonic() < t_end:
            line = proc.stdout.readline() if proc.stdout else ""
            if not line and proc.poll() is not None:
                break
        assert "scope: http" in line, line
        base = line.split("scope: ", 1)[1].split("/?")[0]
        # names no ROS graph could have: each request is answered at once (a valid name
        # would wait for its node's services)
        bad_name = st.text(max_size=12).filter(lambda t: not ROS_NAME_RE.fullmatch(t))
        body = st.one_of(
            st.binary(max_size=40),
            st.builds(
                lambda n, k, v: json.dumps({"node": n, "name": k, "value": v}).encode(),
                bad_name,
                st.text(max_size=8),
                st.one_of(st.text(max_size=8), st.floats().map(repr)),
            ),
            st.just(b"[]"),
            st.just(b'{"trigger": 1e999}'),
        )

        @settings(max_examples=200, **FUZZ)
        @given(
            method=st.sampled_from(["GET", "POST", "POST", "PUT"]),
            path=st.one_of(
                st.sampled_from(
                    [
                        "/",
                        "/api/param",
                        "/api/status",
                        "/api/nodes",
                        "/api/capture",
                        "/api/capture.mcap",
                        "/static/index.html",
                        "/static/../../etc/passwd",
                        "/static/scope.js",
                        "/ws",
                        "/nope",
                        "/api/trigger",
                        "/api/reset",
                    ]
                ),  # fmt: skip
                bad_name.map(lambda n: "/api/reset?service=" + urllib.request.quote(n)),
            ),
            token=st.sampled_from([TOKEN, TOKEN, TOKEN, "", "wrong-token"]),
            origin=st.sampled_from(
                [None, None, None, "http://evil.example", "http://127.0.0.1:1", "null"]
            ),
            body=body,
        )
        def prop(method, path, token, origin, body):
            if path == "/api/nodes" and token == TOKEN and origin in (None, "http://127.0.0.1:1"):
                return  # a real graph walk (seconds): not a bad request
            headers = {"X-Fluxdrive-Token": token}
            if origin:
                headers["Origin"] = origin
            status, text = _http(base, method, path, headers, body if method != "GET" else None)
            counts[status] = counts.get(status, 0) + 1
            assert status < 500, (method, path, status, text[:200])
            if status in (400, 403, 503):
                assert text.strip().count(b"\n") == 0, text[:300]

        prop()
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    print(counts)
    assert "Traceback" not in out, out[-3000:]
    assert counts.get(403) and counts.get(200), counts
