"""Who may open the operator's servers (`./fluxdrive scope`, `./fluxdrive foxglove`).

One set of rules for both (docs/safety.md, "The operator's servers"):

- **Host**: the request's `Host` header names this machine's loopback (`127.0.0.1`,
  `localhost`, `::1`), the address the server is bound to, or a name given with
  `--allow-host`; anything else (`Host: evil.example`: a DNS-rebinding page) is refused.
- **Origin**: a browser names the page that opens a connection or posts a request; a page
  served from this machine's loopback (the scope's own page) or an origin given with
  `--allow-origin` may, any other (`http://evil.example`, `null`) is refused.  A request
  without an Origin (a program, not a page) passes this check.
- **Token**: the per-launch random token, in the URL (`?token=...`) or the `X-Fluxdrive-Token`
  header, compared in constant time.  Whoever holds it is the operator: may view, set
  parameters, reset faults, arm.  Without it nothing but the scope page's scripts and styles.
- **Connection cap**: at most `max_clients` open connections; the next is answered
  `503` at once (never left hanging in its handshake).

Every refusal is one HTTP answer with one line of text and one line in the server's log:
`<server>: refused <client>: <status> <reason>`.

`FoxgloveGate` applies the rules in front of the Foxglove SDK's server (which has no hook for
them): it owns the public port, checks each WebSocket handshake and pipes an accepted one to
the SDK's server on a loopback port that speaks only TLS with a certificate made per launch
and trusted by the gate alone, so a browser page that finds that port cannot complete a
handshake with it.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import secrets
import ssl
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qs, urlsplit

TOKEN_HEADER = "X-Fluxdrive-Token"
LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})
WILDCARD_HOSTS = frozenset({"", "0.0.0.0", "::"})
HANDSHAKE_TIMEOUT_S = 10.0  # a client that sends no complete request head by then is closed
MAX_HEAD_BYTES = 16384  # a request head longer than this is refused
TOKEN_RE = re.compile(r"[A-Za-z0-9_-]{8,128}")
HOST_RE = re.compile(r"[A-Za-z0-9.:_-]{1,253}")


def new_token() -> str:
    return secrets.token_urlsafe(18)


def add_access_options(ap: Any) -> None:
    """The access options both servers take (argparse)."""
    from fluxdrive.core.schema import option
    from fluxdrive.io.graphfile import ServeOptions

    ap.add_argument(
        "--token",
        help="access token, 8 to 128 characters of A-Z a-z 0-9 _ - (default: a fresh random "
        "one per launch; a given one is visible to other users in the process list)",
    )
    ap.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="ORIGIN",
        help="a web page origin (scheme://host[:port]) that may connect besides this machine's "
        "own; repeatable",
    )
    ap.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a host name clients may address the server by besides 127.0.0.1, localhost, "
        "::1 and --host; repeatable",
    )
    option(ap, "--max-clients", ServeOptions)


def access_from_args(args: Any, name: str) -> Access:
    """The Access of a server from its parsed options (ConfigError naming the option)."""
    from fluxdrive.core.machine import ConfigError

    token = args.token if args.token is not None else new_token()
    if not TOKEN_RE.fullmatch(token):
        raise ConfigError("--token must be 8 to 128 characters of A-Z a-z 0-9 _ -")
    for o in args.allow_origin:
        parts = urlsplit(o)
        if parts.scheme not in ("http", "https") or not parts.netloc or parts.path not in ("", "/"):
            raise ConfigError(f"--allow-origin must be scheme://host[:port], got {o!r}")
    for h in args.allow_host:
        if not HOST_RE.fullmatch(h):
            raise ConfigError(f"--allow-host must be a host name or address, got {h!r}")
    return Access(
        name,
        token,
        bind_host=args.host,
        allow_hosts=tuple(args.allow_host),
        allow_origins=tuple(args.allow_origin),
        max_clients=args.max_clients,
    )


def host_name(value: str) -> str:
    """The host of a `Host` header or an origin's netloc, lower case, without port or
    brackets ('' when it cannot be read)."""
    v = value.strip().lower()
    if v.startswith("["):  # [::1]:8765
        return v[1:].split("]", 1)[0]
    if v.count(":") > 1:  # a bare IPv6 address
        return v
    return v.rsplit(":", 1)[0] if ":" in v else v


@dataclass
class Access:
    """The rules of one server: its name (log lines), token, extra hosts and origins, cap."""

    name: str
    token: str
    bind_host: str = "127.0.0.1"
    allow_hosts: tuple[str, ...] = ()
    allow_origins: tuple[str, ...] = ()
    max_clients: int = 100
    log: Callable[[str], None] = print
    _hosts: frozenset[str] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        hosts = set(LOOPBACK_HOSTS) | {h.lower() for h in self.allow_hosts}
        if self.bind_host.lower() not in WILDCARD_HOSTS:
            hosts.add(host_name(self.bind_host))
        self._hosts = frozenset(hosts)
        self.allow_origins = tuple(o.rstrip("/").lower() for o in self.allow_origins)

    def where(self, headers: Mapping[str, str]) -> tuple[int, str] | None:
        """Host and Origin checked: None when they pass, else (HTTP status, reason)."""
        host = headers.get("Host")
        if not host:
            return 400, "no Host header"
        if host_name(host) not in self._hosts:
            return 403, (
                f"Host {host[:100]!r} is not this server (allowed: {sorted(self._hosts)}; "
                f"add a name with --allow-host)"
            )
        origin = headers.get("Origin")
        if origin is None:
            return None
        o = origin.strip().rstrip("/").lower()
        parts = urlsplit(o) if o != "null" else None
        if parts is not None and parts.scheme in ("http", "https"):
            if host_name(parts.netloc) in self._hosts or o in self.allow_origins:
                return None
        return 403, (
            f"Origin {origin[:100]!r} is not allowed (a page of another site; "
            f"allow a viewer's origin with --allow-origin)"
        )

    def has_token(self, target: str, headers: Mapping[str, str]) -> bool:
        given = parse_qs(urlsplit(target).query).get("token", [""])[0]
        given = given or headers.get(TOKEN_HEADER, "")
        return secrets.compare_digest(given.encode(), self.token.encode())

    def check(self, target: str, headers: Mapping[str, str]) -> tuple[int, str] | None:
        """Host, Origin and token: None when all pass, else (HTTP status, reason)."""
        bad = self.where(headers)
        if bad is None and not self.has_token(target, headers):
            bad = (403, "missing or wrong token (use the URL the server printed)")
        return bad

    def refused(self, client: str, status: int, reason: str) -> str:
        """The one log line of a refusal; returns the line for the client."""
        self.log(f"{self.name}: refused {client}: {status} {reason}")
        return f"{self.name}: refused: {reason}\n"


def http_answer(status: int, text: str) -> bytes:
    phrase = {400: "Bad Request", 403: "Forbidden", 431: "Request Header Fields Too Large"}
    phrase[503] = "Service Unavailable"
    body = text.encode()
    return (
        f"HTTP/1.1 {status} {phrase.get(status, 'Error')}\r\n"
        f"Content-Type: text/plain; charset=utf-8\r\nContent-Length: {len(body)}\r\n"
        f"Connection: close\r\n\r\n"
    ).encode() + body


def parse_head(head: bytes) -> tuple[str, str, dict[str, str]]:
    """(method, target, headers) of an HTTP request head; ValueError when it is not one."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/"):
        raise ValueError("not an HTTP request")
    headers: dict[str, str] = {}
    for ln in lines[1:]:
        if not ln:
            continue
        k, sep, v = ln.partition(":")
        if not sep or not k.strip():
            raise ValueError("malformed header line")
        key = "-".join(w.capitalize() for w in k.strip().split("-"))
        if key in headers and key in ("Host", "Origin"):
            raise ValueError(f"{key} given twice")
        headers[key] = v.strip()
    return parts[0], parts[1], headers


# Foxglove's WebSocket protocol under its two names: the SDK's server speaks only the new one;
# clients of before its rename (Lichtblick <= 1.21, @foxglove/ws-protocol's default) offer
# only the old.  The protocol is the same (the SDK says so); only the handshake's
# Sec-WebSocket-Protocol differs, so the gate renames it on the way in and back out.
SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
_PROTOCOL_LINE = re.compile(rb"(?im)^(sec-websocket-protocol:)([^\r\n]*)\r\n")


def legacy_subprotocol_request(head: bytes) -> tuple[bytes, bool]:
    """A handshake offering the old name and not the new: the same request offering the
    new name, and True (its answer is renamed back by `legacy_subprotocol_answer`)."""
    m = _PROTOCOL_LINE.search(head)
    if m is None:
        return head, False
    offered = [p.strip() for p in m.group(2).decode("latin-1").split(",")]
    if SUBPROTOCOL in offered or LEGACY_SUBPROTOCOL not in offered:
        return head, False
    line = m.group(1) + b" " + SUBPROTOCOL.encode() + b"\r\n"
    return head[: m.start()] + line + head[m.end() :], True


def legacy_subprotocol_answer(head: bytes) -> bytes:
    """The server's handshake answer with the protocol it chose named the old way."""
    return _PROTOCOL_LINE.sub(
        lambda m: (
            m.group(1) + b" " + LEGACY_SUBPROTOCOL.encode() + b"\r\n"
            if m.group(2).strip() == SUBPROTOCOL.encode()
            else m.group(0)
        ),
        head,
        count=1,
    )


class FoxgloveGate:
    """The public port of `./fluxdrive foxglove`: each connection's WebSocket handshake
    checked by `access`, an accepted one piped to the SDK's TLS server on `upstream_port`."""

    def __init__(self, access: Access, upstream_port: int, upstream_cert: bytes) -> None:
        self.access = access
        self.upstream_port = upstream_port
        self.ssl = ssl.create_default_context(cadata=upstream_cert.decode())
        self.ssl.check_hostname = False  # the certificate is pinned: ours, made this launch
        self.active = 0
        self.accepted = 0
        self.refusals = 0
        self.loop: asyncio.AbstractEventLoop | None = None
        self.server: asyncio.Server | None = None
        self.port = 0
        self.thread: threading.Thread | None = None

    def start(self, host: str, port: int, timeout_s: float = 10.0) -> None:
        """Bind `host:port` and serve from a thread of its own; OSError when it cannot bind."""
        ready = threading.Event()
        error: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            self.loop = loop
            try:
                self.server = loop.run_until_complete(
                    asyncio.start_server(self._handle, host, port, limit=MAX_HEAD_BYTES)
                )
                self.port = self.server.sockets[0].getsockname()[1]
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                error.append(exc)
                ready.set()
                loop.close()
                return
            ready.set()
            loop.run_forever()
            loop.close()

        self.thread = threading.Thread(target=run, name="foxglove-gate", daemon=True)
        self.thread.start()
        ready.wait(timeout_s)
        if error:
            raise error[0]

    def stop(self) -> None:
        loop, server = self.loop, self.server
        if loop is None or server is None or loop.is_closed():
            return

        async def close() -> None:
            server.close()
            me = asyncio.current_task()
            for task in asyncio.all_tasks():  # the open connections' pipes
                if task is not me:
                    task.cancel()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 2.0)
            loop.stop()

        with contextlib.suppress(RuntimeError):
            asyncio.run_coroutine_threadsafe(close(), loop)
        if self.thread is not None:
            self.thread.join(timeout=5.0)

    async def _refuse(self, writer: asyncio.StreamWriter, client: str, status: int, why: str):
        self.refusals += 1
        line = self.access.refused(client, status, why)
        with contextlib.suppress(Exception):
            writer.write(http_answer(status, line))
            await writer.drain()
        writer.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        client = f"{peer[0]}:{peer[1]}" if peer else "?"
        full = self.active >= self.access.max_clients
        self.active += 1
        try:
            try:
                head = await asyncio.wait_for(
                    reader.readuntil(b"\r\n\r\n"), 1.0 if full else HANDSHAKE_TIMEOUT_S
                )
            except ConnectionError:
                writer.close()
                return
            except (TimeoutError, asyncio.IncompleteReadError) as exc:
                if full:  # the answer goes out whether or not the request head came
                    await self._refuse(writer, client, 503, self._full_text())
                elif isinstance(exc, TimeoutError):
                    why = f"no complete request head within {HANDSHAKE_TIMEOUT_S:g} s"
                    await self._refuse(writer, client, 400, why)
                elif exc.partial:
                    await self._refuse(writer, client, 400, "incomplete request head")
                else:
                    writer.close()  # connected and closed without a word
                return
            except asyncio.LimitOverrunError:
                await self._refuse(writer, client, 431, "request head too long")
                return
            if full:
                await self._refuse(writer, client, 503, self._full_text())
                return
            try:
                _method, target, headers = parse_head(head)
            except ValueError as exc:
                await self._refuse(writer, client, 400, str(exc))
                return
            bad = self.access.check(target, headers)
            if bad is not None:
                await self._refuse(writer, client, *bad)
                return
            await self._pipe(reader, writer, head, client)
        finally:
            self.active -= 1

    def _full_text(self) -> str:
        return f"connection limit reached ({self.access.max_clients} clients; --max-clients)"

    async def _pipe(self, reader, writer, head: bytes, client: str) -> None:
        head, legacy = legacy_subprotocol_request(head)
        try:
            up_r, up_w = await asyncio.open_connection(
                "127.0.0.1", self.upstream_port, ssl=self.ssl, server_hostname="127.0.0.1"
            )
        except (OSError, ssl.SSLError) as exc:
            await self._refuse(writer, client, 503, f"the bridge's server is not answering ({exc})")
            return
        up_w.write(head)

        async def copy(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            try:
                while data := await src.read(65536):
                    dst.write(data)
                    await dst.drain()
            except (ConnectionError, ssl.SSLError, OSError):
                pass
            finally:
                with contextlib.suppress(Exception):
                    dst.close()

        to_server = asyncio.create_task(copy(reader, up_w))
        try:
            # the answer's head alone (the frames after it stay for the copy below)
            first = await up_r.readuntil(b"\r\n\r\n")
        except (ConnectionError, ssl.SSLError, OSError, asyncio.IncompleteReadError):
            first = b""
        except asyncio.LimitOverrunError:  # not an HTTP answer we can read: pass it on
            first = await up_r.read(65536)
        if legacy and first:
            first = legacy_subprotocol_answer(first)
        if not first:  # the SDK dropped the handshake without a word: say it in one line
            to_server.cancel()
            with contextlib.suppress(Exception):
                up_w.close()
            why = (
                "not a WebSocket handshake the server takes (Upgrade, Connection, Sec-WebSocket-*)"
            )
            await self._refuse(writer, client, 400, why)
            return
        self.accepted += 1
        writer.write(first)
        with contextlib.suppress(ConnectionError, OSError):
            await writer.drain()
        await asyncio.gather(to_server, copy(up_r, writer))
