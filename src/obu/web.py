"""The live view: a web page of the OBU's map, served by ``obu run --web HOST:PORT`` from the
OBU process itself, and by ``captures view DIR`` over a finished capture.

One aiohttp application on the daemon's asyncio loop (aiohttp: a maintained asyncio HTTP
and WebSocket server, so the page shares the loop instead of a thread or a process):

* ``GET /``: the page (plain HTML, CSS and JavaScript shipped as package data in
  ``obu/web/``; no build step, nothing loaded from the internet).
* ``GET /api/state``: the current tick (live) or, with ``?tick=N`` (replay), tick N, as
  JSON: what the page shows.  ``GET /api/ticks`` (replay): the number of ticks, their
  times and the warning events, for the slider and the warning list.
* ``GET /ws``: a WebSocket that pushes each tick's state.  Each browser has one slot that
  holds the newest state; a browser that is slow misses states, it never makes a queue
  grow, and a browser that goes away is forgotten.  Nothing a browser sends is read: the
  page cannot change what the OBU does.

Unknown paths give 404, a malformed query 400.

Who may look (issue 28):

* **Host** (DNS rebinding): every request, page or WebSocket, must name this server in
  its ``Host`` header, else 421: the host it was started on (an address or a name) with
  the port it listens on; for a loopback address also ``localhost``, ``127.0.0.1`` and
  ``[::1]``; for all interfaces (``0.0.0.0``, ``::``) any IP address, ``localhost`` and the
  machine's host name.  A page of another site whose name an attacker points at this
  address sends that name, and is refused.  To be reached by another name, serve on that
  name (``--web NAME:PORT``).  A request without ``Host`` is refused too.
* **Origin**: a WebSocket whose ``Origin`` is not this server's own (``http://`` and a
  name and port the Host rule takes) is refused with 403: another site's page cannot
  read the live states.  A handshake without ``Origin`` is taken: browsers always send
  one, so it comes from a program (a test, ``curl``), which the Host rule has let in
  and which could read ``/api/state`` anyway.
* **At most** :data:`MAX_CLIENTS` WebSockets at once; one more is refused with 503.
* **A browser that does not read is cut off**: it is sent the next state only once less
  than :data:`BACKLOG_BYTES` wait for it (in the loop's buffer and the kernel's send
  queue, ``TIOCOUTQ``), so what a browser holds of the server's memory is bounded; one
  whose backlog stays above that for :data:`STALL_S` seconds (or whose send blocks that
  long) is aborted (a reset: a close would wait for it to read), counted
  (``web_cut_off``) and logged on stderr, at most a line a second.  Sending to the OBU
  does not keep such a client alive: what it sends is read and dropped.
* The page's responses carry a Content-Security-Policy (scripts from this server only, no
  inline script) and ``nosniff``; the page writes every string of a state or a capture
  as text (``textContent``), never as HTML.

Plain HTTP only, no proxy in front (the Host and Origin rules would refuse its names).

The state of a tick (:func:`tick_state`): ``t``, the host (x, y, heading, speed, path
radius, predicted pose), every tracked RV (id, x, y, heading, speed, zone now and
predicted, fresh or predicted with the age of its last BSM, predicted position), the
warnings with their range and threshold, and the counters of the panel.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import math
import socket
import struct
import sys
from collections import Counter
from collections.abc import Callable
from importlib import resources
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from aiohttp import WSMsgType, hdrs, web

from hil.capture.schema import hex_id, track_rows, unverified

if TYPE_CHECKING:
    from catc.cam import MapSnapshot

STATIC = {"index.html": "text/html", "app.js": "application/javascript",
          "style.css": "text/css"}
#: Headers of every page response (module docstring).
PAGE_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; script-src 'self'; style-src 'self' "
                               "'unsafe-inline'; img-src 'self' data:; object-src 'none'; "
                               "base-uri 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
}
#: WebSockets served at once; one more is refused with 503.
MAX_CLIENTS = 32
#: A browser gets the next state only when less than this waits for it (bytes).
BACKLOG_BYTES = 256 * 1024
#: A browser whose backlog stays above BACKLOG_BYTES this long (s) is cut off.
STALL_S = 5.0
#: How often a backed-up browser's backlog is looked at again (s).
POLL_S = 0.1
#: The names every loopback address answers to.
LOOPBACK = frozenset({"localhost", "127.0.0.1", "::1"})

try:
    import fcntl
    import termios

    _OUTQ: int | None = termios.TIOCOUTQ  # == SIOCOUTQ: unacknowledged bytes of a socket
except (ImportError, AttributeError):  # not Linux: the loop's buffer only
    _OUTQ = None


def tick_state(snap: MapSnapshot, host_sec_mark: int, panel: dict,
               truth: list[dict] | None = None) -> dict:
    """The JSON-ready state of one tick from a :class:`catc.cam.MapSnapshot`, its track
    rows as the capture has them (:func:`hil.capture.schema.track_rows`) and the panel's
    counters."""
    rows = track_rows(snap, host_sec_mark)
    h = snap.host
    radius = h.radius_m if math.isfinite(h.radius_m) else None
    pp = h.predicted_path
    return {
        "t": round(snap.t, 3), "sec_mark": host_sec_mark,
        "host": {"x": round(h.x, 3), "y": round(h.y, 3), "heading": round(h.heading, 3),
                 "speed": round(h.speed, 3), "radius": radius, "length": h.length,
                 "width": h.width, "pred": [round(pp.x, 3), round(pp.y, 3)]},
        "horizon_s": snap.horizon_s,
        "rvs": [_rv(r) for r in rows],
        "warnings": [[w.app, hex_id(w.rv_id), round(w.range_m, 2),
                      round(w.threshold_m, 2) if w.threshold_m == w.threshold_m else None]
                     for w in snap.warnings],
        "panel": panel, "truth": truth or [],
        **unverified(snap),  # verify on demand: tracks no verified message fed last
    }


def _rv(r: dict) -> dict:
    return {"id": r["id"], "x": round(r["x"], 3), "y": round(r["y"], 3),
            "heading": r["heading"], "speed": r["speed"], "zone": r["zone"],
            "pzone": r["predicted_zone"], "fresh": r["fresh"], "age": r["age"],
            "source": r["source"], "px": round(r["predicted_x"], 3),
            "py": round(r["predicted_y"], 3)}


class Hub:
    """The newest state and the browsers connected to it (see the module docstring)."""

    def __init__(self) -> None:
        self.latest: str | None = None
        self.clients: set[_Client] = set()
        #: Someone asked /api/state: states are built from then on even with no browser
        #: (before, the OBU builds none: no cost when nobody looks).
        self.polled = False
        #: Builds the newest tick's state when nobody has looked yet (a reference to the
        #: tick, no work): the first /api/state or browser gets it, not an empty state.
        self.unbuilt: Callable[[], dict] | None = None
        #: What the guards refused and cut off (module docstring), for the OBU's counters.
        self.counters: Counter[str] = _counters()

    def newest(self) -> str | None:
        """The newest state as JSON, built now if nobody had asked for it yet."""
        if self.latest is None and self.unbuilt is not None:
            self.publish(self.unbuilt())
        return self.latest

    def publish(self, state: dict) -> None:
        self.unbuilt = None
        self.latest = json.dumps(state, separators=(",", ":"))
        for c in self.clients:
            c.slot = self.latest
            c.ready.set()


class _Client:
    def __init__(self) -> None:
        self.slot: str | None = None
        self.ready = asyncio.Event()


def _counters() -> Counter[str]:
    return Counter(dict.fromkeys(("refused_host", "refused_origin", "refused_full",
                                  "cut_off", "backlog_max_bytes"), 0))


def _name(text: str | None) -> tuple[str, int] | None:
    """(host name or canonical IP address, port) of a ``Host`` header or an origin's
    authority (``HOST[:PORT]``, ``[V6]:PORT``; port 80 when absent); None when malformed."""
    if not text:
        return None
    try:
        parts = urlsplit("//" + text)
        host, port = parts.hostname, parts.port
    except ValueError:
        return None
    if not host or parts.path or parts.query or parts.fragment or "@" in parts.netloc:
        return None
    host = host.removesuffix(".")
    with contextlib.suppress(ValueError):
        host = str(ipaddress.ip_address(host))
    return host, 80 if port is None else port


class Names:
    """The names and ports the server answers to (module docstring), known once
    :func:`start` has bound its sockets; before, nothing is answered."""

    def __init__(self) -> None:
        self.hosts: set[str] = set()
        self.ports: set[int] = set()
        self.any_ip = False  # bound to all interfaces: any IP address names it

    def bind(self, host: str, sockets: list[Any]) -> None:
        """Learn the names of ``host`` (as given to :func:`start`) bound as ``sockets``
        (their ``getsockname()``)."""
        given = _name(f"[{host}]" if ":" in host else host)
        if given:
            self.hosts.add(given[0])
        for addr in sockets:
            ip = ipaddress.ip_address(str(addr[0]).partition("%")[0])
            self.ports.add(int(addr[1]))
            self.hosts.add(str(ip))
            if ip.is_loopback:
                self.hosts |= LOOPBACK
            if ip.is_unspecified:
                self.any_ip = True
                me = socket.gethostname().lower()
                self.hosts |= LOOPBACK | {me, me.partition(".")[0]}

    def allows(self, named: tuple[str, int] | None) -> bool:
        if named is None or named[1] not in self.ports:
            return False
        if named[0] in self.hosts:
            return True
        if self.any_ip:
            try:
                ipaddress.ip_address(named[0])
                return True
            except ValueError:
                pass
        return False

    def allows_origin(self, origin: str) -> bool:
        """An ``Origin`` header of a page of this server (``http://NAME:PORT``)."""
        scheme, _, rest = origin.partition("://")
        return scheme.lower() == "http" and self.allows(_name(rest))


NAMES = web.AppKey("names", Names)
COUNTERS = web.AppKey("counters", Counter)


def _backlog(transport: asyncio.BaseTransport | None) -> int:
    """Bytes written to a client that it has not yet acknowledged: the loop's buffer and
    the kernel's send queue."""
    if transport is None:
        return 0
    n = transport.get_write_buffer_size()  # type: ignore[attr-defined]
    sock = transport.get_extra_info("socket")
    if _OUTQ is not None and sock is not None:
        with contextlib.suppress(OSError, ValueError):  # closed meanwhile
            n += struct.unpack("i", fcntl.ioctl(sock.fileno(), _OUTQ, b"\0" * 4))[0]
    return n


class _CutOffLog:
    """One stderr line per cut-off client, at most one a second (a flood of clients that
    do not read must not flood the log); every one is counted."""

    def __init__(self) -> None:
        self.last = -math.inf

    def __call__(self, counters: Counter[str], transport: asyncio.BaseTransport | None,
                 peer: Any, stalled: float) -> None:
        backlog = _backlog(transport)
        if transport is not None:
            transport.abort()  # a reset: a close would wait for it to read
        counters["cut_off"] += 1
        now = asyncio.get_running_loop().time()
        if now - self.last >= 1.0:
            self.last = now
            print(f"obu: live view: cut off a browser at {peer} that read nothing for "
                  f"{stalled:.1f} s ({backlog} bytes waiting; {counters['cut_off']} cut off "
                  "so far)", file=sys.stderr, flush=True)


def make_app(hub: Hub | None = None, replay: Replay | None = None, *,
             max_clients: int = MAX_CLIENTS, backlog_bytes: int = BACKLOG_BYTES,
             stall_s: float = STALL_S) -> web.Application:
    """The application: live over ``hub``, or a finished capture's ``replay``; the limits
    of the module docstring."""
    names = Names()
    counters = hub.counters if hub is not None else _counters()
    cut_off = _CutOffLog()
    open_sockets = [0]  # WebSockets being served

    @web.middleware
    async def only_our_names(request: web.Request, handler: Callable) -> web.StreamResponse:
        host = request.headers.get(hdrs.HOST)
        if not names.allows(_name(host)):
            counters["refused_host"] += 1
            raise web.HTTPMisdirectedRequest(
                text=f"Host {host!r} is not a name of this server (DNS rebinding?)")
        return await handler(request)

    app = web.Application(middlewares=[only_our_names])
    app[NAMES] = names
    app[COUNTERS] = counters
    pkg = resources.files("obu").joinpath("web")

    def static(name: str) -> Callable:
        async def handler(_request: web.Request) -> web.Response:
            text = pkg.joinpath(name).read_text(encoding="utf-8")
            if name == "index.html":
                text = text.replace("__MODE__", "replay" if replay else "live")
            return web.Response(text=text, content_type=STATIC[name], headers=PAGE_HEADERS)
        return handler

    async def state(request: web.Request) -> web.Response:
        if replay is not None:
            raw = request.query.get("tick", "0")
            try:
                i = int(raw)
            except ValueError:
                raise web.HTTPBadRequest(text=f"tick must be an integer, got {raw!r}") \
                    from None
            if not 0 <= i < len(replay):
                raise web.HTTPBadRequest(text=f"tick {i} outside 0..{len(replay) - 1}")
            return web.json_response(text=json.dumps(replay.state(i)))
        if set(request.query) - {"_"}:
            raise web.HTTPBadRequest(text="the live state takes no query")
        if hub is not None:
            hub.polled = True
        latest = hub.newest() if hub is not None else None
        if latest is None:  # no tick yet
            return web.json_response({"t": None, "rvs": [], "warnings": []})
        return web.json_response(text=latest)

    async def ticks(_request: web.Request) -> web.Response:
        if replay is None:
            raise web.HTTPNotFound(text="live view: no tick list")
        return web.json_response(replay.index())

    async def ws(request: web.Request) -> web.WebSocketResponse:
        origin = request.headers.get(hdrs.ORIGIN)
        if origin is not None and not names.allows_origin(origin):
            counters["refused_origin"] += 1
            raise web.HTTPForbidden(text=f"a WebSocket from {origin!r}: not this page")
        if open_sockets[0] >= max_clients:
            counters["refused_full"] += 1
            raise web.HTTPServiceUnavailable(
                text=f"the live view serves {max_clients} WebSockets at most")
        open_sockets[0] += 1
        try:
            return await _serve(request)
        finally:
            open_sockets[0] -= 1

    async def _serve(request: web.Request) -> web.WebSocketResponse:
        sock = web.WebSocketResponse(heartbeat=10.0)
        await sock.prepare(request)
        if hub is None:
            await sock.close()
            return sock
        transport = request.transport
        client = _Client()
        hub.clients.add(client)
        if hub.newest() is not None:
            client.slot = hub.latest
            client.ready.set()

        async def drain() -> None:  # read (and ignore) what the browser sends: closes
            async for msg in sock:
                if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break

        reader = asyncio.create_task(drain())
        loop = asyncio.get_running_loop()
        since = None  # when the backlog went above backlog_bytes
        try:
            while not sock.closed and not reader.done():
                backlog = _backlog(transport)
                counters["backlog_max_bytes"] = max(counters["backlog_max_bytes"], backlog)
                if backlog > backlog_bytes:  # keep the newest state; look again soon
                    since = loop.time() if since is None else since
                    if loop.time() - since > stall_s:
                        cut_off(counters, transport, request.remote, loop.time() - since)
                        break
                    await asyncio.wait({reader}, timeout=POLL_S)
                    continue
                since = None
                if client.slot is None:
                    client.ready.clear()
                    waiter = asyncio.create_task(client.ready.wait())
                    await asyncio.wait({waiter, reader}, return_when=asyncio.FIRST_COMPLETED)
                    waiter.cancel()
                    continue
                text, client.slot = client.slot, None
                try:
                    await asyncio.wait_for(sock.send_str(text), stall_s)
                except TimeoutError:
                    cut_off(counters, transport, request.remote, stall_s)
                    break
        except (ConnectionResetError, RuntimeError):
            pass
        finally:
            hub.clients.discard(client)
            reader.cancel()
            if transport is not None and transport.get_write_buffer_size() > 0:
                transport.abort()  # nobody reads it: a close would wait for ever
        return sock

    app.router.add_get("/", static("index.html"))
    app.router.add_get("/app.js", static("app.js"))
    app.router.add_get("/style.css", static("style.css"))
    app.router.add_get("/api/state", state)
    app.router.add_get("/api/ticks", ticks)
    app.router.add_get("/ws", ws)
    return app


async def start(app: web.Application, host: str, port: int) -> web.AppRunner:
    """Serve ``app`` on ``host:port`` on the running loop; the runner, for cleanup.  From
    here on the app answers to the names of ``host`` (:class:`Names`)."""
    runner = web.AppRunner(app, access_log=None, handle_signals=False)
    await runner.setup()
    await web.TCPSite(runner, host, port).start()
    app[NAMES].bind(host, runner.addresses)
    return runner


class Replay:
    """A finished capture as tick states (``captures view``): the OBU's ticks, tracks and
    events, joined with the RVE's ground truth when the capture has it."""

    def __init__(self, ticks: list[dict], tracks: list[dict], events: list[dict],
                 truth: dict | None, counters: dict) -> None:
        self.ticks = ticks
        self.events = events
        self.by_t: dict[float, list[dict]] = {}
        for r in tracks:
            self.by_t.setdefault(round(r["t"], 3), []).append(r)
        self.truth = truth  # id -> (t array, x array, y array), on the OBU's clock
        self.counters = counters

    def __len__(self) -> int:
        return len(self.ticks)

    def index(self) -> dict:
        return {"ticks": len(self.ticks), "t": [tk["t"] for tk in self.ticks],
                "events": [e for e in self.events if e.get("kind") == "start"]}

    def state(self, i: int) -> dict:
        import numpy as np

        tk = self.ticks[i]
        t = round(tk["t"], 3)
        rows = self.by_t.get(t, [])
        truth = []
        if self.truth:
            for tid, (tt, xx, yy) in self.truth.items():
                if tt[0] - 1e-6 <= t <= tt[-1] + 1e-6:
                    truth.append({"id": tid, "x": round(float(np.interp(t, tt, xx)), 3),
                                  "y": round(float(np.interp(t, tt, yy)), 3)})
        hx, hy = tk["host"]
        return {
            "t": t, "sec_mark": tk.get("sec_mark"), "tick": i,
            "host": {"x": hx, "y": hy, "heading": tk.get("host_heading", 0.0),
                     "speed": tk.get("host_speed", 0.0), "radius": None, "length": 4.8,
                     "width": 1.9, "pred": None},
            "horizon_s": 2.0,
            "rvs": [_rv(r) for r in rows],
            "warnings": [[w[0], w[1], w[2], w[3]] for w in tk.get("warnings", [])],
            "panel": {"tracked": tk.get("tracked", len(rows)), "tick_ms": tk.get("step_ms"),
                      "decode_errors": self.counters.get("decode_errors", 0),
                      "rejected": self.counters.get("verify_rejected", 0)},
            "truth": truth,
            "unverified": list(tk.get("unverified", ())),
        }
