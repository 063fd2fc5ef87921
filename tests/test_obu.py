"""The OBU daemon end to end: ``obu run`` and ``rve run`` as separate processes over UDP on
127.0.0.1 (and over CAN: the virtual bus in one process, udp_multicast between processes
in a namespace the test creates), ``captures score`` on their shared capture, the live run
against the offline simulator, and garbage thrown at a running OBU."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import os
import random
import select
import shutil
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from catc.bsm import BSM
from catc.cam import CamConfig, ContextAwareMap
from catc.channel import ChannelConfig
from catc.j2735 import encode_frame
from catc.replay import plan, simulate
from hil.capture import read_rx, read_tracks
from hil.datasets import load_table
from hil.transport.udp import free_ports, wait_bound
from obu import run as obu_run
from obu.daemon import Obu
from obu.tick import DRAIN_S, QUIET_S, STEP, TAKE, WAIT, TickRule
from rve import run as rve_run
from tests.test_transport import netns  # noqa: F401  (fixture)

PY = sys.executable


#: What ``obu run`` prints on stderr once it receives (its sockets or its bus are open).
READY = b"obu: ready ("


def wait_ready(proc: subprocess.Popen, timeout: float = 60.0) -> str:
    """Read ``proc``'s stderr (unbuffered, from its descriptor) until the OBU's ready line,
    its exit or ``timeout`` s; what was read, which ``finish`` puts back in front."""
    fd, seen = proc.stderr.fileno(), b""
    deadline = time.monotonic() + timeout
    while not any(line.startswith(READY) for line in seen.split(b"\n")[:-1]):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        if not select.select([fd], [], [], min(left, 0.5))[0]:
            continue
        chunk = os.read(fd, 65536)
        if not chunk:  # end of file: the OBU exited
            break
        seen += chunk
    return seen.decode(errors="replace")


def start_obu(cap: Path, ports: list[int], *extra: str, prefix: tuple[str, ...] = ()):
    proc = subprocess.Popen([*prefix, PY, "-m", "obu.cli", "run", "--listen",
                             f"127.0.0.1:{ports[0]}", "--host-listen", f"127.0.0.1:{ports[1]}",
                             "--capture", str(cap), "--idle-exit", "2", "--no-progress",
                             *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # the RVE starts sending once the OBU receives (start-up with --verify and its trust
    # store takes over a second on a busy machine): its ready line, printed once its UDP
    # sockets or its CAN bus are open, in this network namespace or another
    proc.early_stderr = wait_ready(proc)
    assert proc.poll() is None, (proc.early_stderr, proc.communicate())
    assert READY.decode() in proc.early_stderr, f"no ready line: {proc.early_stderr!r}"
    return proc


def rve(ports: list[int], *args: str, prefix: tuple[str, ...] = ()) -> dict:
    out = subprocess.run([*prefix, PY, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}",
                          "--host-to", f"127.0.0.1:{ports[1]}", "--no-progress", *args],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def finish(proc) -> tuple[str, str]:
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = getattr(proc, "early_stderr", "") + err  # start_obu read up to the ready line
    assert proc.returncode == 0, err
    return out, err


def score(cap: Path) -> dict:
    out = subprocess.run([PY, "-m", "captures.cli", "score", str(cap), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_udp_end_to_end_on_the_default_scenario(tmp_path):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "hgp")
    summary = rve(ports, "--per", "50", "--seed", "2", "--speed", "8", "--capture", str(tmp_path))
    out, _ = finish(obu)
    events = [json.loads(line) for line in out.splitlines()]
    fcw = [e for e in events if e["app"] == "fcw" and e["kind"] == "start"]
    assert fcw and 19.9 <= fcw[0]["t"] <= 21.5, fcw  # the leader brakes at 20 s
    s = score(tmp_path)
    assert s["sent"] == summary["sent"] == s["received"]  # loopback loses nothing
    assert s["sent"] + s["dropped"] == sum(1 for line in
                                           (tmp_path / "rve.schedule.jsonl").open()
                                           if '"channel":"rv"' in line)
    assert s["decode_errors"] == {}
    assert s["pte95_m"] < 0.5 and s["fcw_accuracy"] > 0.9
    assert set(s) >= {"pte95_m", "fcw_accuracy", "fcw", "sent", "dropped", "received",
                      "warnings"}
    assert s["warnings"]["fcw"] >= 1
    # the score table is the same numbers for people
    table = subprocess.run([PY, "-m", "captures.cli", "score", str(tmp_path)],
                           capture_output=True, text=True, timeout=120).stdout
    assert f"FCW accuracy {s['fcw_accuracy']}" in table
    assert s["complete"] and s["run"]["coverage"] == 1.0 and s["run"]["gaps"] == 0
    assert s["run"]["obu"] == "clean (idle)" and s["run"]["rve"] == "clean (replayed)"
    assert s["fcw"] == {k: s["apps"]["fcw"][k] for k in ("tp", "tn", "fp", "fn")}
    assert set(s["apps"]) == {"fcw", "eebl", "bsw", "lcw"}
    # the same capture with every FCW warning moved by hand to another real vehicle: each
    # of those ticks is a false positive on it and a false negative on the leader
    moved = tmp_path / "moved"
    shutil.copytree(tmp_path, moved, ignore=shutil.ignore_patterns("moved"))
    ids = json.loads((tmp_path / "rve.config.json").read_text())["vehicles"]
    leader = ids["lead"]
    other = next(v for k, v in ids.items() if k not in ("lead", "host"))
    ticks = [json.loads(line) for line in (tmp_path / "obu.ticks.jsonl").open()]
    on_leader = sum(1 for t in ticks for w in t["warnings"] if w[:2] == ["fcw", leader])
    assert on_leader >= s["fcw"]["tp"] > 0
    with (moved / "obu.ticks.jsonl").open("w") as f:
        for t in ticks:
            t["warnings"] = [[w[0], other, *w[2:]] if w[:2] == ["fcw", leader] else w
                             for w in t["warnings"]]
            f.write(json.dumps(t) + "\n")
    m = score(moved)
    assert m["fcw"]["tp"] == 0
    assert m["fcw"]["fp"] == s["fcw"]["fp"] + s["fcw"]["tp"]  # false alarms stay false
    assert m["fcw"]["fn"] == s["fcw"]["fn"] + s["fcw"]["tp"]
    assert m["fcw_accuracy"] < s["fcw_accuracy"]


def test_live_equals_offline(tmp_path):
    """Same dataset and loss schedule, zero latency: the OBU's per-tick estimates equal
    the offline simulator's (catc driven directly) to 1e-6 m."""
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "hgp")
    rve(ports, "--per", "40", "--burst", "2", "--seed", "9", "--speed", "4",
        "--duration", "25", "--capture", str(tmp_path))
    finish(obu)
    table = load_table("scenario:highway-braking", None)
    the_plan = plan(table, ChannelConfig(per=0.4, burst=2.0), 9, None, 25.0)
    offline = {}
    for snap in simulate(the_plan, ContextAwareMap(CamConfig(predictor="hgp"))):
        for i in range(len(snap)):
            offline[(round(snap.t, 3), f"{int(snap.ids[i]):08X}")] = (snap.x[i], snap.y[i])
    live = {}
    for r in read_tracks(tmp_path):  # obu.tracks.bin, as the JSON rows of before
        live[(round(r["t"], 3), r["id"])] = (r["x"], r["y"])
    assert live.keys() == offline.keys()
    err = max(float(np.hypot(live[k][0] - offline[k][0], live[k][1] - offline[k][1]))
              for k in live)
    assert err <= 1e-6, err


def _garbage(rng: random.Random, host: BSM | None) -> bytes:
    kind = rng.randrange(4)
    if kind == 0:
        return rng.randbytes(rng.randrange(1, 300))
    frame = encode_frame(BSM(msg_cnt=1, temp_id=rng.getrandbits(32), sec_mark=1000,
                             lat=46.9, lon=16.8, speed=10.0, heading=0.0))
    if kind == 1:
        return frame[: rng.randrange(1, len(frame))]  # truncated
    if kind == 2:  # valid frame, absurd speed, far away
        return encode_frame(BSM(msg_cnt=1, temp_id=rng.getrandbits(32), sec_mark=1000,
                                lat=-45.0, lon=170.0, speed=150.0, heading=0.0))
    return b"\x00\x14" + rng.randbytes(40)  # a MessageFrame header and noise


def test_garbage_is_counted_and_changes_nothing(tmp_path):
    clean, dirty = tmp_path / "clean", tmp_path / "dirty"
    for cap, noisy in ((clean, False), (dirty, True)):
        ports = free_ports()
        obu = start_obu(cap, ports, "--predictor", "ca")
        stop = threading.Event()

        def spray(port=ports[0], stop=stop):
            rng = random.Random(1)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                while not stop.is_set():
                    s.sendto(_garbage(rng, None), ("127.0.0.1", port))
                    time.sleep(0.002)

        thread = threading.Thread(target=spray, daemon=True)
        if noisy:
            thread.start()
        rve(ports, "--per", "30", "--seed", "4", "--speed", "8", "--duration", "25",
            "--capture", str(cap))
        stop.set()
        if noisy:
            thread.join(5)
        finish(obu)
    counters = json.loads((dirty / "obu.counters.json").read_text())
    assert counters["decode_errors"] > 100
    assert counters["cam_implausible"] > 10  # decodable frames with absurd values
    a, b = score(clean), score(dirty)
    for key in ("pte95_m", "fcw_accuracy", "fcw", "sent", "pte95_per_rv"):
        assert a[key] == b[key], key
    # the decodable garbage was received too, as phantoms: ids that no vehicle sent
    assert b["phantom_received"] > a["phantom_received"] == 0
    assert b["received"] == a["received"]


def test_a_tick_takes_every_frame_received_before_its_host_frame(tmp_path, monkeypatch):
    """Which tick a frame joins depends on the order of the frames, not on how fast the
    OBU reads them: 10 RV frames sent before a host frame are all stepped at that host
    frame even when each takes 3 ms to handle (a loaded 2-core machine verifying
    signatures), three times the collect rule's 1 ms quiet gap.  The event loop reads one
    datagram per socket per pass, so the host frame is read while most RV frames still
    wait in the socket buffer; the old rule stepped without them."""
    handle = Obu.frame

    def slow_frame(self, channel, data, rx_unix):
        if channel == "rv":
            time.sleep(0.003)
        return handle(self, channel, data, rx_unix)

    monkeypatch.setattr(Obu, "frame", slow_frame)
    ports = free_ports()
    ns = dict(obu_run.DEFAULTS, listen=("127.0.0.1", ports[0]),
              host_listen=("127.0.0.1", ports[1]), predictor="ca", capture=str(tmp_path),
              idle_exit=0.5, progress=False)

    def bsm(temp_id: int) -> bytes:
        return encode_frame(BSM(msg_cnt=1, temp_id=temp_id, sec_mark=1000, lat=42.28,
                                lon=-83.74 + temp_id * 1e-4, elev=200.0, speed=10.0,
                                heading=90.0))

    async def main():
        serving = asyncio.create_task(obu_run.serve(argparse.Namespace(**ns)))
        assert await asyncio.to_thread(wait_bound, ports)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # no await between
            for k in range(10):
                s.sendto(bsm(0x100 + k), ("127.0.0.1", ports[0]))
            s.sendto(bsm(0x1), ("127.0.0.1", ports[1]))
        return await asyncio.wait_for(serving, 30)

    with contextlib.redirect_stdout(open(tmp_path / "warnings.jsonl", "w")):
        counters = asyncio.run(main())
    assert counters["ticks"] == 1 and counters["frames_rv"] == 10
    rx = read_rx(tmp_path)
    assert [r["status"] for r in rx if r["channel"] == "rv"] == ["ok"] * 10


class _Loop:
    """A fake event loop for the tick rule: a fake clock, the OBU's queue, and a socket
    buffer of which each pass (a WAIT) reads one datagram."""

    def __init__(self, rule: TickRule, socket_buffer: list[str], handle_s: float) -> None:
        self.rule, self.buffer, self.handle_s = rule, list(socket_buffer), handle_s
        self.now, self.queue, self.taken = 0.0, [], []
        self.next_host = False  # a believed host frame ended the collection

    def collect(self) -> list[str]:
        """Collect a tick's frames from a host frame at the current time; what it took."""
        self.rule.host_frame(self.now)
        action = WAIT
        while action is not STEP:
            if action is TAKE:
                frame = self.queue.pop(0)
                if frame == "host":  # this fake's host gate believes every host frame
                    self.next_host = True
                    action = self.rule.next_host()
                    continue
                self.now += self.handle_s  # handling one RV frame takes this long
                self.rule.rv_frame(self.now)
                self.taken.append(frame)
            else:
                self.now += 1e-5
                if self.buffer:
                    self.queue.append(self.buffer.pop(0))
            head = "host" if self.queue and self.queue[0] == "host" else \
                ("rv" if self.queue else None)
            action = self.rule.next(self.now, head, head is None and bool(self.buffer))
        return self.taken


def test_the_tick_rule_takes_every_frame_that_reached_the_receiver_first():
    """The socket-level test below without sockets: 10 RV frames in the socket buffer
    when the host frame is read, 3 ms each to handle (three times the quiet gap): all
    are taken before the step; the next host frame stops the collection."""
    loop = _Loop(TickRule(collect_ms=5.0), ["rv"] * 10 + ["host", "rv"], handle_s=0.003)
    assert loop.collect() == ["rv"] * 10
    assert loop.next_host and loop.queue == [] and loop.buffer == ["rv"]
    assert loop.now < DRAIN_S


def test_the_tick_rule_drains_for_at_most_drain_s():
    """A flood delays a tick by DRAIN_S at most, never stops it."""
    loop = _Loop(TickRule(collect_ms=5.0), ["rv"] * 10_000, handle_s=0.001)
    taken = loop.collect()
    assert DRAIN_S <= loop.now < DRAIN_S + 0.002 and 40 < len(taken) < 60


def test_the_tick_rule_waits_for_the_rv_channel_to_go_quiet():
    rule = TickRule(collect_ms=5.0)
    rule.rv_frame(0.9995)
    rule.host_frame(1.0)
    assert rule.next(1.0, None, False) is WAIT  # an RV frame 0.5 ms ago: not quiet
    assert rule.next(1.0004, None, False) is WAIT  # 0.9 ms since: not yet
    rule.rv_frame(1.001)
    assert rule.next(1.0015, "rv", False) is TAKE  # a frame in the queue: take it
    assert rule.next(1.0015, None, True) is WAIT  # one in the socket buffer: read it
    assert rule.next(1.0015 + QUIET_S + 1e-6, None, False) is STEP  # quiet
    with pytest.raises(RuntimeError):  # the step ends the collection
        rule.next(1.1, None, False)


def test_the_tick_rule_stops_at_collect_ms_and_at_the_next_host_frame():
    rule = TickRule(collect_ms=5.0)
    rule.host_frame(2.0)
    for k in range(5):  # an RV frame every 0.9 ms: never quiet
        rule.rv_frame(2.0 + 0.0009 * k)
        assert rule.next(2.0 + 0.0009 * k, None, False) is WAIT
    assert rule.next(2.005, None, False) is STEP  # --collect-ms is over
    rule.host_frame(2.1)
    assert rule.next(2.1, "host", True) is TAKE  # a host frame: is it believed?
    assert rule.next_host() is STEP  # it is: the next tick, whatever waits
    rule.host_frame(2.2)
    assert rule.next(2.2 + DRAIN_S - 1e-6, None, True) is WAIT  # still draining
    assert rule.next(2.2 + DRAIN_S, None, True) is STEP
    slow = TickRule(collect_ms=80.0)  # --collect-ms longer than DRAIN_S: the limit
    slow.host_frame(0.0)
    assert slow.next(0.079, None, True) is WAIT and slow.next(0.08, None, True) is STEP
    assert TickRule(collect_ms=-3.0).collect_s == 0.0


def test_can_end_to_end_on_the_virtual_bus(tmp_path):
    channel = f"obu-{uuid.uuid4().hex}"
    ns = dict(obu_run.DEFAULTS, transport="can", can_interface="virtual", can_channel=channel,
              can_fd=True, predictor="ca", capture=str(tmp_path), idle_exit=1.0,
              progress=False)
    obu_args = argparse.Namespace(**ns)
    r = dict(rve_run.DEFAULTS, transport="can", can_interface="virtual", can_channel=channel,
             can_fd=True, per=50.0, seed=3, duration=25.0, speed=8.0, capture=str(tmp_path),
             progress=False)
    rve_args = argparse.Namespace(**r)
    table = load_table(rve_args.dataset, None)
    the_plan = plan(table, ChannelConfig(per=0.5), 3, None, 25.0)

    err = io.StringIO()

    async def main():
        serving = asyncio.create_task(obu_run.serve(obu_args))
        deadline = time.monotonic() + 30
        while READY.decode() not in err.getvalue():  # its bus is open: the RVE may send
            assert not serving.done() and time.monotonic() < deadline, err.getvalue()
            await asyncio.sleep(0.01)
        counts = await rve_run.replay(rve_args, the_plan)
        return counts, await asyncio.wait_for(serving, 60)

    with contextlib.redirect_stdout(open(tmp_path / "warnings.jsonl", "w")), \
            contextlib.redirect_stderr(err):
        counts, obu_counters = asyncio.run(main())
    assert obu_counters["frames_rv"] == counts["sent"]
    assert obu_counters["ticks"] == counts["host"]
    s = score(tmp_path)
    assert s["received"] == s["sent"] and s["warnings"].get("fcw", 0) >= 1


def test_can_end_to_end_between_processes_over_udp_multicast(netns, tmp_path):  # noqa: F811
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    prefix = ("ip", "netns", "exec", netns)
    can = ("--transport", "can", "--can-interface", "udp_multicast", "--can-channel",
           "239.74.163.2", "--can-fd")
    obu = start_obu(tmp_path, [4500, 4501], "--predictor", "ca", *can, prefix=prefix)
    summary = rve([4500, 4501], "--per", "50", "--seed", "6", "--speed", "8",
                  "--duration", "25", "--capture", str(tmp_path), *can, prefix=prefix)
    finish(obu)
    s = score(tmp_path)
    assert s["received"] == s["sent"] == summary["sent"]
    assert s["warnings"].get("fcw", 0) >= 1


@pytest.mark.parametrize(("args", "needle"), [
    (["--listen", "nohost.invalid:4500"], "nohost.invalid"),
    (["--predictor", "nope"], "invalid choice"),
    (["--transport", "can", "--can-interface", "socketcan", "--can-channel", "nocan0"],
     "nocan0"),
])
def test_obu_bad_input_is_one_line_and_exit_2(args, needle):
    out = subprocess.run([PY, "-m", "obu.cli", "run", "--duration", "1", *args],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines


def test_obu_sigterm_flushes_and_kill_9_keeps_all_but_the_last_tick(tmp_path):
    import os
    import signal

    for sig, cap in ((signal.SIGTERM, tmp_path / "term"), (signal.SIGKILL, tmp_path / "kill")):
        ports = free_ports()
        obu = start_obu(cap, ports, "--predictor", "ca")
        sender = subprocess.Popen([PY, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}",
                                   "--host-to", f"127.0.0.1:{ports[1]}", "--no-progress"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        ticks_file = cap / "obu.ticks.jsonl"
        try:
            deadline = time.monotonic() + 60  # some ticks in, then the signal
            while time.monotonic() < deadline and obu.poll() is None and not (
                    ticks_file.exists() and sum(1 for _ in ticks_file.open()) >= 20):
                time.sleep(0.05)
            os.kill(obu.pid, sig)
            obu.wait(20)
        finally:
            sender.kill()
            sender.wait(10)
            if obu.poll() is None:
                obu.kill()
        ticks = [json.loads(line) for line in ticks_file.open()]
        tracks = read_tracks(cap)
        assert len(ticks) > 10
        # every tick but possibly the last has all its track rows
        per_tick = {t["t"]: t["tracked"] for t in ticks[:-1]}
        for t, n in per_tick.items():
            assert sum(1 for r in tracks if r["t"] == t) == n
        if sig == signal.SIGTERM:
            assert obu.returncode == 0
            assert json.loads((cap / "obu.counters.json").read_text())["ticks"] == len(ticks)
            end = json.loads((cap / "obu.end.json").read_text())
            assert (end["exit"], end["reason"], end["ticks"]) == ("signal", "SIGTERM",
                                                                   len(ticks))
            config = json.loads((cap / "obu.config.json").read_text())
            assert end["run_id"] == config["run_id"] and len(end["run_id"]) == 32
        else:
            assert not (cap / "obu.end.json").exists()  # killed: nothing could say so


def test_an_obu_killed_at_40_percent_scores_as_an_incomplete_run(tmp_path):
    """Issue 27: kill -9 of the OBU at 40 % of the run left a capture that scored "FCW
    accuracy 1.0" on its 202 ticks with no word of the rest.  Now the score joins the
    ticks with the replay's host frames: coverage about 40 %, the OBU's missing end
    record, the coverage beside every figure, and exit 3 unless --partial."""
    import os
    import signal

    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca")
    sender = subprocess.Popen([PY, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}",
                               "--host-to", f"127.0.0.1:{ports[1]}", "--no-progress",
                               "--speed", "4", "--capture", str(tmp_path)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ticks = tmp_path / "obu.ticks.jsonl"
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and obu.poll() is None:
            if ticks.exists() and sum(1 for _ in ticks.open()) >= 200:  # of 500
                break
            time.sleep(0.05)
        os.kill(obu.pid, signal.SIGKILL)
        obu.wait(20)
        _, err = sender.communicate(timeout=120)
        assert sender.returncode == 0, err
    finally:
        for p in (sender, obu):
            if p.poll() is None:
                p.kill()
                p.wait(10)
    s = subprocess.run([PY, "-m", "captures.cli", "score", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert s.returncode == 3, s.stderr
    assert "incomplete run" in s.stderr and len(s.stderr.strip().splitlines()) == 1
    assert s.stdout.startswith("INCOMPLETE RUN")
    for line in s.stdout.splitlines():
        if line.startswith(("PTE95 ", "FCW accuracy")):
            assert "[coverage " in line, line
    j = subprocess.run([PY, "-m", "captures.cli", "score", str(tmp_path), "--json",
                        "--partial"], capture_output=True, text=True, timeout=120)
    assert j.returncode == 0, j.stderr
    r = json.loads(j.stdout)
    run = r["run"]
    assert r["complete"] is False and 490 <= run["expected_ticks"] <= 510
    assert 0.35 <= run["coverage"] <= 0.6, run
    assert run["gaps"] >= 1 and run["longest_gap_s"] >= 15.0
    assert run["obu"].startswith("no end record") and run["rve"] == "clean (replayed)"


def test_a_capture_directory_holding_a_run_is_refused_unless_overwritten(tmp_path):
    """Issue 27: a second run into the same directory appended to the first, and the score
    counted 1,000 ticks without a word.  Each daemon refuses a directory with its own
    files in one line, or replaces them with --overwrite; the other's files stay."""
    ports = free_ports()
    args = [PY, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}", "--host-to",
            f"127.0.0.1:{ports[1]}", "--no-progress", "--asap", "--duration", "1",
            "--capture", str(tmp_path)]
    first = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    (tmp_path / "obu.config.json").write_text("{}")  # an OBU's file: not the RVE's
    lines = (tmp_path / "rve.schedule.jsonl").read_text()
    again = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert again.returncode == 2
    assert again.stderr.strip().count("\n") == 0 and "already holds an RVE run" in again.stderr
    assert (tmp_path / "rve.schedule.jsonl").read_text() == lines
    over = subprocess.run([*args, "--overwrite"], capture_output=True, text=True, timeout=120)
    assert over.returncode == 0, over.stderr
    n = len(lines.splitlines())  # replaced, not appended
    assert len((tmp_path / "rve.schedule.jsonl").read_text().splitlines()) == n
    assert (tmp_path / "obu.config.json").read_text() == "{}"
    obu = subprocess.run([PY, "-m", "obu.cli", "run", "--listen", f"127.0.0.1:{ports[0]}",
                          "--host-listen", f"127.0.0.1:{ports[1]}", "--capture",
                          str(tmp_path), "--duration", "0.5", "--no-progress"],
                         capture_output=True, text=True, timeout=60)
    assert obu.returncode == 2 and "already holds an OBU run" in obu.stderr
    assert obu.stderr.strip().count("\n") == 0


def test_captures_decode_reads_the_obus_rx_capture(tmp_path):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca")
    rve(ports, "--asap", "--duration", "2", "--ieee1609", "--capture", str(tmp_path))
    finish(obu)
    rx = read_rx(tmp_path)
    out = subprocess.run([PY, "-m", "captures.cli", "decode", str(tmp_path / "obu.rx.jsonl.gz")],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    decoded = [json.loads(line) for line in out.stdout.splitlines()]
    assert len(decoded) == len(rx) > 0
    assert [(d["id"], d["msgCnt"]) for d in decoded] == [(r["id"], r["msgCnt"]) for r in rx]


def test_score_reads_a_torn_last_line_but_not_a_torn_middle(tmp_path):
    from hil.capture import CaptureError
    from hil.capture import read_lines as _lines

    path = tmp_path / "x.jsonl"
    path.write_text('{"a":1}\n{"b":2}\n{"c":')  # killed mid-line
    assert _lines(path) == [{"a": 1}, {"b": 2}]
    path.write_text('{"a":1}\n{"b":\n{"c":3}\n')
    with pytest.raises(CaptureError, match=":2: not a JSON line"):
        _lines(path)


def test_the_first_look_at_the_live_state_gets_the_newest_tick(tmp_path):
    """Issue 27: the first ``GET /api/state`` after the OBU started answered an empty
    state, because no state is built until someone looks.  Now the first look builds the
    newest tick's."""
    import socket
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        web = s.getsockname()[1]
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca", "--web", str(web))
    try:
        sent = rve(ports, "--asap", "--duration", "3", "--capture", str(tmp_path))
        # the RVE is done when its last host frame is sent; the OBU may still be stepping
        # it: wait (bounded) until every host frame is a tick in the capture
        ticks = tmp_path / "obu.ticks.jsonl"
        deadline = time.monotonic() + 10
        while len(ticks.read_text().splitlines()) < sent["host_frames"]:
            assert time.monotonic() < deadline, "the OBU did not step every host frame"
            time.sleep(0.05)
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/api/state", timeout=10) as r:
            state = json.loads(r.read())
        assert obu.poll() is None  # still running (--idle-exit 2): a live answer
    finally:
        finish(obu)
    last = json.loads((tmp_path / "obu.ticks.jsonl").read_text().splitlines()[-1])
    assert state["t"] == last["t"] and len(state["rvs"]) == last["tracked"] > 0
