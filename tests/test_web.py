"""The live view (obu.web) in a real browser: Debian's headless Chromium driven by
Playwright (``make debs`` installs chromium; no browser download), against a live
``obu run --web`` fed by ``rve run`` on the default scenario, and ``captures view`` over
the capture.  Screenshots go to ``out/test-artifacts/``.  The page's Content-Security-Policy
forbids ``eval``: ``wait_for_function`` gets functions (``"() => ..."``), not expressions,
which Playwright would ``eval`` in the page."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from hil.transport.udp import free_ports
from tests.test_obu import finish, start_obu

PY = sys.executable
CHROMIUM = "/usr/bin/chromium"
ARTIFACTS = Path(__file__).resolve().parents[1] / "out" / "test-artifacts"

sync_api = pytest.importorskip("playwright.sync_api", reason="playwright (test extra)")
if not Path(CHROMIUM).exists():
    pytest.skip("Debian's chromium is not installed (make debs installs it)",
                allow_module_level=True)


def _port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as err:
        return err.code, err.read()


def _wait_http(url: str, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            _get(url)
            return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"{url} did not answer")


@contextlib.contextmanager
def _serve(make, host: str = "127.0.0.1", background=()):
    """The application ``make()`` returns (called on the server's loop), served on ``host``
    from a thread of this process with the coroutine functions ``background`` running
    beside it on the same loop: its port."""
    from obu.web import start

    port, ready = _port(), threading.Event()
    loop = asyncio.new_event_loop()

    def main() -> None:
        asyncio.set_event_loop(loop)
        runner = loop.run_until_complete(start(make(), host, port))
        tasks = [loop.create_task(b()) for b in background]
        ready.set()
        loop.run_forever()
        for task in tasks:
            task.cancel()
        loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
        loop.run_until_complete(runner.cleanup())
        loop.close()

    thread = threading.Thread(target=main, daemon=True)
    thread.start()
    assert ready.wait(10), "the server did not start"
    try:
        yield port
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(70)


@contextlib.contextmanager
def _serve_replay(ticks: list[dict], tracks: list[dict], events: list[dict] = (),
                  counters: dict | None = None):
    """The page in replay mode over hand-made ticks and tracks (``obu.web.Replay``), served
    from a thread of this process: its base URL."""
    from obu.web import Replay, make_app

    with _serve(lambda: make_app(replay=Replay(ticks, tracks, list(events), None,
                                                counters or {}))) as port:
        yield f"http://127.0.0.1:{port}"


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as p:
        # rebind.test: a name that resolves to this machine, as an attacker's would once
        # rebound (DNS rebinding)
        b = p.chromium.launch(executable_path=CHROMIUM, args=[
            "--no-sandbox", "--host-resolver-rules=MAP rebind.test 127.0.0.1"])
        yield b
        b.close()


def _same_tick_counts(page, state_url: str, tries: int = 200) -> tuple[int, int, float]:
    """(RVs drawn, RVs in /api/state, t) at a tick where the page and the API agree on
    the time."""
    for _ in range(tries):
        s = json.loads(_get(state_url)[1])
        # both attributes in one call: the page may draw the next tick in between
        t_page, n_page = page.evaluate(
            "() => { const m = document.getElementById('map'); "
            "return [m.dataset.t, +(m.dataset.rvs || 0)]; }")
        if s.get("t") is not None and t_page and float(t_page) == s["t"]:
            return n_page, len(s["rvs"]), s["t"]
        time.sleep(0.02)
    raise AssertionError("the page never showed the tick /api/state returned")


@pytest.mark.slow
def test_live_view_in_chromium(browser, tmp_path):
    ports = free_ports()
    web = _port()
    base = f"http://127.0.0.1:{web}"
    obu = start_obu(tmp_path, ports, "--predictor", "hgp", "--web", str(web))
    _wait_http(base + "/")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(base + "/")
    rve = subprocess.Popen([PY, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}",
                            "--host-to", f"127.0.0.1:{ports[1]}", "--no-progress", "--speed",
                            "2", "--duration", "26", "--capture", str(tmp_path)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        page.wait_for_function("() => +document.getElementById('map').dataset.rvs > 0",
                               timeout=20_000)
        drawn, listed, _ = _same_tick_counts(page, base + "/api/state")
        assert drawn == listed > 0
        # the leader brakes at 20 s of data: the FCW banner
        page.wait_for_selector("#banner:not(.hidden)", timeout=30_000)
        banner = page.inner_text("#banner")
        deadline = time.monotonic() + 20
        while "FCW" not in banner and time.monotonic() < deadline:
            time.sleep(0.05)
            banner = page.inner_text("#banner")
        assert "FCW" in banner and "range" in banner, banner
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "live-view.png"))
        # north-up toggle and zoom do not lose the RVs
        page.click("#hostframe")
        page.mouse.wheel(0, -300)
        drawn, listed, _ = _same_tick_counts(page, base + "/api/state")
        assert drawn == listed
        # bad input: unknown path, malformed query; a WebSocket that goes away mid-stream
        assert _get(base + "/nope")[0] == 404
        assert _get(base + "/api/state?tick=x")[0] == 400
        other = browser.new_page()
        other.goto(base + "/")
        other.wait_for_function("() => +document.getElementById('map').dataset.rvs > 0")
        other.close()
        assert obu.poll() is None
    finally:
        page.close()
        _, err = rve.communicate(timeout=120)
        assert rve.returncode == 0, err
    finish(obu)
    counters = json.loads((tmp_path / "obu.counters.json").read_text())
    assert counters["ticks"] > 200


@pytest.mark.slow
def test_captures_view_in_chromium(browser, tmp_path):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca")
    out = subprocess.run([PY, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}",
                          "--host-to", f"127.0.0.1:{ports[1]}", "--no-progress", "--speed",
                          "8", "--duration", "25", "--per", "30", "--capture", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    finish(obu)
    web = _port()
    base = f"http://127.0.0.1:{web}"
    view = subprocess.Popen([PY, "-m", "captures.cli", "view", str(tmp_path), "--web",
                             str(web)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        _wait_http(base + "/")
        index = json.loads(_get(base + "/api/ticks")[1])
        assert index["ticks"] > 100 and index["events"]
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.goto(base + "/")
        page.wait_for_selector("#replay:not(.hidden)")
        # the slider to tick 150: the page draws what /api/state?tick=150 lists
        page.eval_on_selector("#slider", "s => { s.value = 150; s.dispatchEvent("
                                         "new Event('input')); }")
        page.wait_for_function("() => document.getElementById('tickno').textContent"
                               ".startsWith('tick 150 ')")
        s = json.loads(_get(base + "/api/state?tick=150")[1])
        page.wait_for_function(f"() => +document.getElementById('map').dataset.t == {s['t']}")
        assert int(page.get_attribute("#map", "data-rvs")) == len(s["rvs"]) > 0
        assert s["truth"]  # the RVE's ground truth, joined
        # a warning in the list jumps to its moment
        first = index["events"][0]
        page.click("#warnlist li >> nth=0")
        page.wait_for_function(
            f"() => Math.abs(+document.getElementById('map').dataset.t - {first['t']}) < 0.11")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "captures-view.png"))
        page.click("#play")
        t0 = float(page.get_attribute("#map", "data-t"))
        page.wait_for_function(f"() => +document.getElementById('map').dataset.t > {t0}")
        # bad input
        assert _get(base + "/api/state?tick=999999")[0] == 400
        assert _get(base + "/api/state?tick=abc")[0] == 400
        assert _get(base + "/missing")[0] == 404
        page.close()
    finally:
        view.terminate()
        view.communicate(timeout=30)
    bad = subprocess.run([PY, "-m", "captures.cli", "view", str(tmp_path / "nothing")],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1, bad.stderr


#: The zone colours of app.js (COLORS) by zone [ahead, lateral lane code, direction].
_ZONES = {"centre": ([True, 2, 0], (0xD6, 0x27, 0x28)),
          "left": ([True, 1, 0], (0x1F, 0x77, 0xB4)),
          "right": ([True, 3, 0], (0x2C, 0xA0, 0x2C)),
          "oncoming": ([True, 2, 1], (0x94, 0x67, 0xBD))}
#: A known tick: the host at (40, 20) m heading 30 degrees, four fresh RVs, none near the
#: diagonal x = y, so that each one's swapped position (y, x) is far from every vehicle.
_HOST = (40.0, 20.0, 30.0)
_RVS = [("0000000A", 60.0, 30.0, "centre"), ("0000000B", 25.0, 5.0, "left"),
        ("0000000C", 35.0, 50.0, "right"), ("0000000D", 55.0, 15.0, "oncoming")]


def _pixels(page, points: list[tuple[float, float]], half: int = 2) -> list[list[tuple]]:
    """The canvas' RGB pixels (getImageData) of a (2 half + 1)-square around each point."""
    return page.evaluate(
        """([points, half]) => {
             const m = document.getElementById('map'), ctx = m.getContext('2d');
             return points.map(([x, y]) => {
               const d = ctx.getImageData(Math.floor(x) - half, Math.floor(y) - half,
                                          2 * half + 1, 2 * half + 1).data;
               const out = [];
               for (let i = 0; i < d.length; i += 4) out.push([d[i], d[i + 1], d[i + 2]]);
               return out;
             });
           }""", [points, half])


def _to_pixel(view: dict, x: float, y: float) -> tuple[float, float]:
    """World ENU (m) to canvas px, computed here from the page's transform parameters
    (scale k in px/m, origin ox/oy, rotation a, the host at hx/hy): east right and north
    up, turned by a (the host's heading in the host frame)."""
    dx, dy = x - view["hx"], y - view["hy"]
    c, s = math.cos(view["a"]), math.sin(view["a"])
    return view["ox"] + view["k"] * (dx * c - dy * s), view["oy"] - view["k"] * (dx * s + dy * c)


def test_live_view_draws_each_rv_at_its_pixel(browser):
    """Each RV of a known tick is drawn in its zone's colour at the pixel its position maps
    to (read back from the canvas), and not at its swapped position (y, x); in the host
    frame (turned by the host's heading) and north-up."""
    hx, hy, heading = _HOST
    ticks = [{"t": 12.3, "sec_mark": 12300, "host": [hx, hy], "host_heading": heading,
              "host_speed": 10.0, "warnings": [], "tracked": len(_RVS)}]
    tracks = [{"t": 12.3, "id": rid, "x": x, "y": y, "heading": heading, "speed": 10.0,
               "zone": _ZONES[zone][0], "predicted_zone": _ZONES[zone][0], "fresh": True,
               "age": 0.0, "source": "bsm", "predicted_x": x, "predicted_y": y}
              for rid, x, y, zone in _RVS]
    for _, x, y, _ in _RVS:  # the swapped points are at least 10 m from every vehicle
        assert min(math.hypot(y - vx, x - vy) for vx, vy in
                   [(hx, hy), *((r[1], r[2]) for r in _RVS)]) > 10
    with _serve_replay(ticks, tracks) as base:
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        try:
            page.goto(base + "/")
            page.wait_for_function("() => document.getElementById('map').dataset.t == '12.3'")
            assert page.get_attribute("#map", "data-rvs") == str(len(_RVS))
            for north_up in (False, True):
                if north_up:
                    page.click("#hostframe")
                view = page.evaluate("() => { const v = liveView.view(); return {k: v.k, "
                                     "ox: v.ox, oy: v.oy, a: v.a, hx: v.hx, hy: v.hy}; }")
                size = page.evaluate("() => [document.getElementById('map').width, "
                                     "document.getElementById('map').height]")
                assert math.isclose(view["a"], 0 if north_up else math.radians(heading))
                at = [_to_pixel(view, x, y) for _, x, y, _ in _RVS]
                swapped = [_to_pixel(view, y, x) for _, x, y, _ in _RVS]
                for px, py in at + swapped:
                    assert 10 < px < size[0] - 10 and 10 < py < size[1] - 10, (px, py, size)
                for (rid, _, _, zone), here, there in zip(
                        _RVS, _pixels(page, at), _pixels(page, swapped), strict=True):
                    rgb = _ZONES[zone][1]

                    def near(p, rgb=rgb):
                        return max(abs(a - b) for a, b in zip(p, rgb, strict=True)) <= 3

                    assert all(near(p) for p in here), (rid, zone, north_up, here)
                    assert not any(near(p) for p in there), (rid, zone, north_up, there)
        finally:
            page.close()


def test_an_unverified_track_is_drawn_apart(browser):
    """Verify on demand: a track whose latest message is unverified (the tick's
    ``unverified``) is drawn hollow and dashed in amber, never filled in its zone's
    colour, and counted in the panel; a verified one beside it is filled."""
    hx, hy, heading = _HOST
    ticks = [{"t": 12.3, "sec_mark": 12300, "host": [hx, hy], "host_heading": heading,
              "host_speed": 10.0, "warnings": [], "tracked": 2, "unverified": ["0000000B"]}]
    rvs = _RVS[:2]
    tracks = [{"t": 12.3, "id": rid, "x": x, "y": y, "heading": heading, "speed": 10.0,
               "zone": _ZONES[zone][0], "predicted_zone": _ZONES[zone][0], "fresh": True,
               "age": 0.0, "source": "bsm", "predicted_x": x, "predicted_y": y}
              for rid, x, y, zone in rvs]
    with _serve_replay(ticks, tracks) as base:
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        try:
            page.goto(base + "/")
            page.wait_for_function("() => document.getElementById('map').dataset.t == '12.3'")
            assert page.get_attribute("#map", "data-unverified") == "1"
            view = page.evaluate("() => { const v = liveView.view(); return {k: v.k, "
                                 "ox: v.ox, oy: v.oy, a: v.a, hx: v.hx, hy: v.hy}; }")
            centres = _pixels(page, [_to_pixel(view, x, y) for _, x, y, _ in rvs], half=1)
            for (rid, _, _, zone), px in zip(rvs, centres, strict=True):
                filled = [max(abs(a - b) for a, b in zip(p, _ZONES[zone][1], strict=True))
                          <= 3 for p in px]
                assert all(filled) if rid == "0000000A" else not any(filled), (rid, px)
            assert "unverified tracks\t1" in page.inner_text("#panel")
        finally:
            page.close()


# --- who may look: text not HTML, Host, Origin, the cap, clients that do not read -----------

#: Strings a crafted capture could hold: each sets window.__pwned if the page runs it.
_XSS = ['<img src=x onerror="window.__pwned=1">', "<script>window.__pwned=2</script>",
        '<svg onload="window.__pwned=3"></svg>']


def test_a_capture_s_strings_are_shown_as_text_not_run(browser):
    """``captures view`` of a capture whose fields hold HTML: the page shows the text as it
    is and runs none of it."""
    ticks = [{"t": 12.3, "sec_mark": 12300, "host": [0.0, 0.0], "host_heading": 0.0,
              "host_speed": 10.0, "warnings": [["fcw", _XSS[1], 20.0, None]],
              "tracked": _XSS[0], "step_ms": _XSS[1]}]
    events = [{"kind": "start", "app": _XSS[2], "rv": _XSS[0], "t": 12.3}]
    with _serve_replay(ticks, [], events, {"decode_errors": _XSS[2],
                                           "verify_rejected": _XSS[0]}) as base:
        page = browser.new_page()
        try:
            page.goto(base + "/")
            page.wait_for_function("() => document.getElementById('map').dataset.t == '12.3'")
            page.wait_for_load_state("networkidle")  # an <img src=x> would have failed
            time.sleep(0.3)
            assert page.evaluate("window.__pwned") is None
            assert page.query_selector_all("#panel img, #panel script, #panel svg, "
                                           "#warnlist img, #warnlist svg") == []
            panel = page.inner_text("#panel")
            for text in _XSS:
                assert text in panel, (text, panel)
            assert _XSS[1] in page.inner_text("#banner")
        finally:
            page.close()
        with urllib.request.urlopen(base + "/", timeout=5) as r:
            csp = r.headers["Content-Security-Policy"]
        assert "script-src 'self'" in csp and "unsafe-inline" not in csp.partition(
            "style-src")[0]  # no inline script: a defence beside the text


def _request(port: int, path: str, host: str | None = "127.0.0.1:{port}",
             headers: str = "", method_line: str = "") -> tuple[int, socket.socket, bytes]:
    """A request by hand (any Host header, or none): its status, the socket and the head
    of the answer; the answer's body is left unread."""
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    head = method_line or f"GET {path} HTTP/1.1\r\n"
    if host is not None:
        head += f"Host: {host.format(port=port)}\r\n"
    s.sendall((head + headers + "\r\n").encode())
    got = b""
    while b"\r\n\r\n" not in got:
        chunk = s.recv(1)  # a byte at a time: what follows the head stays unread
        if not chunk:
            break
        got += chunk
    return (int(got.split(b" ", 2)[1]) if got else 0), s, got


def _status(port: int, path: str = "/", **kw) -> int:
    status, s, _ = _request(port, path, **kw)
    s.close()
    return status


_UPGRADE = ("Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n")


def _ws(port: int, origin: str | None = None, host: str | None = "127.0.0.1:{port}"):
    """A WebSocket handshake by hand: (status, socket)."""
    extra = _UPGRADE + (f"Origin: {origin.format(port=port)}\r\n" if origin else "")
    status, s, _ = _request(port, "/ws", host=host, headers=extra)
    return status, s


def _frame(payload: bytes) -> bytes:
    """A masked text frame (what a client sends)."""
    mask = b"\x01\x02\x03\x04"
    return (bytes([0x81, 0x80 | len(payload)]) + mask
            + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))


def _live(**kw):
    from obu.web import Hub, make_app

    hub = Hub()
    return hub, (lambda: make_app(hub, **kw))


def test_only_requests_that_name_this_server_are_answered(browser):
    """DNS rebinding: a page of a name that resolves here (rebind.test) is refused (421),
    page and WebSocket; the loopback names and the port are answered."""
    _, make = _live()
    with _serve(make) as port:
        for host in ("127.0.0.1:{port}", "localhost:{port}", "[::1]:{port}",
                     "LOCALHOST.:{port}", "[0:0:0:0:0:0:0:1]:{port}"):
            assert _status(port, host=host) == 200, host
            assert _status(port, "/api/state", host=host) == 200, host
        for host in ("rebind.test:{port}", "127.0.0.1", "127.0.0.1:1", "localhost:{port}0",
                     "10.0.0.1:{port}", "127.0.0.1:{port}/x", "user@127.0.0.1:{port}", "",
                     "127.0.0.1:{port}.rebind.test"):
            assert _status(port, host=host) == 421, host
            assert _status(port, "/api/state", host=host) == 421, host
        assert _status(port, host=None, method_line="GET / HTTP/1.0\r\n") == 421
        assert _ws(port, host="rebind.test:{port}")[0] == 421
        page = browser.new_page()
        try:
            answer = page.goto(f"http://rebind.test:{port}/")
            assert answer.status == 421
            assert page.evaluate("fetch('/api/state').then(r => r.status)") == 421
            answer = page.goto(f"http://localhost:{port}/")
            assert answer.status == 200
        finally:
            page.close()
    _, make = _live()
    with _serve(make, host="0.0.0.0") as port:  # all interfaces: any address, no other name
        me = socket.gethostname()
        for host in ("127.0.0.1:{port}", "10.1.2.3:{port}", "localhost:{port}",
                     f"{me}:{{port}}"):
            assert _status(port, host=host) == 200, host
        assert _status(port, host="rebind.test:{port}") == 421


@contextlib.contextmanager
def _attacker_site():
    """Another site's page, served on another loopback port: its URL."""
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    class Page(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = b"<!doctype html><title>another site</title>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_args) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Page)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


def test_websockets_from_another_origin_are_refused(browser):
    """A page of another origin (here: another port) cannot open the live view's
    WebSocket (403); the page's own origin, its loopback names and a program that sends
    no Origin can."""
    hub, make = _live()
    with _serve(make) as port, _serve_replay([], []) as other:
        for origin in (None, "http://127.0.0.1:{port}", "http://localhost:{port}",
                       "http://[::1]:{port}"):
            status, s = _ws(port, origin)
            s.close()
            assert status == 101, origin
        for origin in ("http://rebind.test:{port}", "http://127.0.0.1:1", "null",
                       "https://127.0.0.1:{port}", other, "http://127.0.0.1:{port}.evil",
                       "file://", "http://127.0.0.1:{port}/path"):
            status, s = _ws(port, origin)
            s.close()
            assert status == 403, origin
        page = browser.new_page()
        js = (f"() => new Promise(done => {{ const w = new WebSocket("
              f"'ws://127.0.0.1:{port}/ws'); w.onopen = () => done('open'); "
              "w.onclose = () => done('closed'); setTimeout(() => done('hung'), 5000); })")
        try:  # another site's page on this machine (Chromium itself blocks a public
            # site from loopback, not one on the same machine or network)
            with _attacker_site() as site:
                page.goto(site)
                assert page.evaluate(js) == "closed"
            page.goto(f"http://127.0.0.1:{port}/")
            assert page.evaluate(js) == "open"
        finally:
            page.close()
        assert hub.counters["refused_origin"] >= 9


def test_at_most_32_websockets_are_served(browser):
    hub, make = _live()
    with _serve(make) as port:
        socks = []
        try:
            for _ in range(32):
                status, s = _ws(port)
                socks.append(s)
                assert status == 101
            status, s = _ws(port)
            s.close()
            assert status == 503
            socks.pop().close()  # one goes away: its place is free again
            deadline = time.monotonic() + 10
            while True:
                status, s = _ws(port)
                socks.append(s)
                if status == 101 or time.monotonic() > deadline:
                    break
                time.sleep(0.1)
            assert status == 101
            assert _status(port, "/api/state") == 200  # the page itself is still served
        finally:
            for s in socks:
                s.close()
    from obu.web import MAX_CLIENTS

    assert MAX_CLIENTS == 32 and hub.counters["refused_full"] >= 1


def _tcp_state(s: socket.socket) -> int:
    """The kernel's TCP state of ``s`` (1: established; 7: closed, 8: closed by the peer)."""
    return s.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 8)[0]


def test_a_websocket_client_that_sends_but_never_reads_is_cut_off(capsys):
    """A client that does the handshake by hand, then sends a frame every 0.2 s and never
    reads, against a server publishing 64 kB states at 50 Hz: it is reset within seconds,
    counted and logged once, while what waits for it never exceeds the bound; a client
    that reads meanwhile is served throughout."""
    import aiohttp

    from obu import web as obu_web

    hub, make = _live()
    pad = "x" * 65536
    state_bytes = len(json.dumps({"t": 10 ** 6, "pad": pad}, separators=(",", ":")))
    got = {"messages": 0, "closed": False}
    port_box: list[int] = []

    async def publish() -> None:
        i = 0
        while True:
            hub.publish({"t": i, "pad": pad})
            i += 1
            await asyncio.sleep(0.02)

    async def reader() -> None:  # a browser: reads everything (and answers pings)
        while not port_box:
            await asyncio.sleep(0.01)
        async with aiohttp.ClientSession() as session, \
                session.ws_connect(f"http://127.0.0.1:{port_box[0]}/ws") as ws:
            async for _ in ws:
                got["messages"] += 1
        got["closed"] = True

    with _serve(make, background=(publish, reader)) as port:
        port_box.append(port)
        status, lazy = _ws(port)
        assert status == 101
        t0 = time.monotonic()
        cut_after = None
        try:
            while time.monotonic() - t0 < 15:
                try:
                    lazy.sendall(_frame(b"still here"))  # it talks, it never listens
                except OSError:
                    cut_after = time.monotonic() - t0
                    break
                if _tcp_state(lazy) != 1:
                    cut_after = time.monotonic() - t0
                    break
                time.sleep(0.2)
            assert cut_after is not None, "a client that never reads was never cut off"
            assert cut_after < 12, cut_after
            served = got["messages"]
            time.sleep(1.0)
            assert got["messages"] > served > 50 and not got["closed"]  # still served
        finally:
            lazy.close()
    assert cut_after > obu_web.STALL_S  # not before the stall bound
    assert hub.counters["cut_off"] == 1
    # never more than the bound and one state waited for a client
    assert 0 < hub.counters["backlog_max_bytes"] <= obu_web.BACKLOG_BYTES + state_bytes + 1024
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "cut off" in ln]
    assert len(lines) == 1 and "read nothing" in lines[0], lines
