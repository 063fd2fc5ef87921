"""``rve run`` as a separate process sending to a test receiver over real UDP sockets on
127.0.0.1: the frames that arrive are exactly the ones the schedule says were not dropped,
the capture is complete, and bad input gets one line and exit status 2."""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from catc.errors import DecodeError
from catc.j2735 import decode_frame
from tests.conftest import shared_path
from tests.test_capture import read_pcapng

RVE = [sys.executable, "-m", "rve.cli", "run"]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class UdpSink:
    """Receives on two loopback ports in a thread; keeps every datagram."""

    def __init__(self) -> None:
        self.socks = []
        for _ in range(2):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
            s.bind(("127.0.0.1", 0))
            self.socks.append(s)
        self.ports = [s.getsockname()[1] for s in self.socks]
        self.frames: list[list[bytes]] = [[], []]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select(self.socks, [], [], 0.05)
            for s in ready:
                self.frames[self.socks.index(s)].append(s.recv(4096))

    def close(self, linger: float = 0.3) -> None:
        time.sleep(linger)
        self._stop.set()
        self._thread.join(5)
        for s in self.socks:
            s.close()


def _openacc() -> str:
    return "openacc:" + str(shared_path("openacc-zalazone", "short_setting_dynamic_part22.csv"))


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([*RVE, *args], capture_output=True, text=True, timeout=timeout,
                          check=False)


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.parametrize(("per", "burst", "rate"), [(50.0, 1.0, 10.0), (30.0, 4.0, 5.0)])
def test_udp_frames_received_match_the_schedule_exactly(tmp_path, per, burst, rate):
    sink = UdpSink()
    try:
        out = _run("--dataset", _openacc(), "--duration", "4", "--per", str(per),
                   "--burst", str(burst), "--rate", str(rate), "--seed", "3", "--speed", "8",
                   "--to", f"127.0.0.1:{sink.ports[0]}", "--host-to",
                   f"127.0.0.1:{sink.ports[1]}", "--capture", str(tmp_path), "--no-progress")
    finally:
        sink.close()
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    sched = _lines(tmp_path / "rve.schedule.jsonl")
    rv = [r for r in sched if r["channel"] == "rv"]
    host = [r for r in sched if r["channel"] == "host"]
    sent = [r for r in rv if not r["dropped"]]
    assert summary["sent"] == len(sent) and summary["dropped"] == len(rv) - len(sent)
    assert 0 < len(sent) < len(rv)
    # how late the RV frames left, in the summary: the schedule's own largest lateness
    assert summary["late_ms_max"] == pytest.approx(max(r["late_ms"] for r in sent), abs=1e-3)
    assert summary["late_over_1s"] == sum(r["late_ms"] > 1000.0 for r in sent)
    # every frame that arrived is a scheduled, undropped message, and every one arrived
    got = sorted((f"{b.temp_id:08X}", b.msg_cnt, b.sec_mark)
                 for b in map(decode_frame, sink.frames[0]))
    want = sorted((r["id"], r["seq"] % 128, round(r["t"] * 1000) % 60000) for r in sent)
    assert got == want
    assert len(sink.frames[1]) == len(host) == summary["host_frames"]
    # the capture: config, truth for every vehicle sample, every frame in the pcapng
    config = json.loads((tmp_path / "rve.config.json").read_text())
    assert config["seed"] == 3 and config["channel"]["per"] == pytest.approx(per / 100)
    truth = _lines(tmp_path / "rve.truth.jsonl")
    assert {r["vehicle"] for r in truth} == set(config["vehicles"])
    _, packets = read_pcapng((tmp_path / "rve.frames.pcapng").read_bytes())
    assert len(packets) == len(sent) + len(host)
    assert sorted(p[28:] for _, p in packets) == sorted(sink.frames[0] + sink.frames[1])


def test_latency_and_jitter_reorder_but_lose_nothing(tmp_path):
    sink = UdpSink()
    try:
        out = _run("--dataset", _openacc(), "--duration", "3", "--latency", "20",
                   "--jitter", "250", "--speed", "4", "--to", f"127.0.0.1:{sink.ports[0]}",
                   "--host-to", f"127.0.0.1:{sink.ports[1]}", "--capture", str(tmp_path),
                   "--no-progress")
    finally:
        sink.close()
    assert out.returncode == 0, out.stderr
    sched = [r for r in _lines(tmp_path / "rve.schedule.jsonl") if r["channel"] == "rv"]
    assert all(0.02 <= r["delay"] <= 0.27 for r in sched)
    assert len(sink.frames[0]) == len(sched)
    arrived = [(decode_frame(f).temp_id, decode_frame(f).sec_mark) for f in sink.frames[0]]
    by_vehicle: dict[int, list[int]] = {}
    for tid, sm in arrived:
        by_vehicle.setdefault(tid, []).append(sm)
    assert any(v != sorted(v) for v in by_vehicle.values())  # some were overtaken


def test_sigterm_stops_flushes_and_keeps_the_capture(tmp_path):
    sink = UdpSink()
    proc = subprocess.Popen([*RVE, "--dataset", _openacc(), "--to",
                             f"127.0.0.1:{sink.ports[0]}", "--host-to",
                             f"127.0.0.1:{sink.ports[1]}", "--capture", str(tmp_path),
                             "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        # stop it mid-run, once it has sent something (bounded wait: a slow start on a
        # loaded machine must not make the test flaky)
        schedule = tmp_path / "rve.schedule.jsonl"
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and (
                not schedule.is_file() or schedule.read_text().count("\n") <= 60):
            time.sleep(0.1)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        sink.close()
    assert proc.returncode == 0, err
    assert json.loads(out.strip().splitlines()[-1])["interrupted"] is True
    sched = _lines(tmp_path / "rve.schedule.jsonl")  # every line complete JSON
    assert len(sched) > 50
    assert len(sink.frames[0]) == sum(1 for r in sched if r["channel"] == "rv"
                                      and not r["dropped"])


def test_kill_9_keeps_all_but_the_last_tick(tmp_path):
    sink = UdpSink()
    proc = subprocess.Popen([*RVE, "--dataset", _openacc(), "--to",
                             f"127.0.0.1:{sink.ports[0]}", "--host-to",
                             f"127.0.0.1:{sink.ports[1]}", "--capture", str(tmp_path),
                             "--no-progress"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        time.sleep(2.5)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        sink.close()
    lines = (tmp_path / "rve.schedule.jsonl").read_text().splitlines()
    assert len(lines) > 50
    parsed = [json.loads(line) for line in lines]  # no torn line: flushed per tick
    sent = sum(1 for r in parsed if r["channel"] == "rv" and not r["dropped"])
    # frames of at most the last tick (one frame per vehicle) may be unrecorded
    assert 0 <= len(sink.frames[0]) - sent <= 10


@pytest.mark.parametrize(("args", "needle"), [
    (["--dataset", "/no/such/file.csv"], "no such file"),
    (["--dataset", "scenario:nope"], "unknown scenario"),
    (["--dataset", "gpx:/no/such.gpx"], "unknown kind 'gpx'"),
    (["--per", "150"], "percentage"),
    (["--to", "localhost"], "HOST:PORT"),
    (["--to", "no-such-host.invalid:4500"], "no-such-host.invalid"),
    (["--transport", "can", "--can-interface", "socketcan", "--can-channel", "nocan0"],
     "nocan0"),
    (["--rate", "20"], "rate"),
    (["--host", "NOBODY"], "NOBODY"),
])
def test_bad_input_is_one_line_and_exit_2(args, needle):
    out = _run("--dataset", _openacc(), "--duration", "1", "--asap", "--no-progress", *args)
    assert out.returncode == 2, (out.stdout, out.stderr)
    err = out.stderr.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def test_config_file_and_flags_override(tmp_path):
    sink = UdpSink()
    cfg = tmp_path / "rve.toml"
    cfg.write_text(f'[rve]\ndataset = "{_openacc()}"\nper = 100\nduration = 2\n'
                   f'to = "127.0.0.1:{sink.ports[0]}"\nhost-to = "127.0.0.1:{sink.ports[1]}"\n'
                   "asap = true\nprogress = false\n")
    try:
        out = _run("--config", str(cfg), "--per", "0")
    finally:
        sink.close()
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["dropped"] == 0 and summary["sent"] == len(sink.frames[0]) > 0
    bad = tmp_path / "bad.toml"
    bad.write_text("per = [\n")
    out = _run("--config", str(bad))
    assert out.returncode == 2 and "not valid TOML" in out.stderr
    bad.write_text("pre = 5\n")
    out = _run("--config", str(bad))
    assert out.returncode == 2 and "unknown setting" in out.stderr


def test_progress_on_a_pipe_is_one_line_per_redraw():
    """Without a terminal the tqdm bar is plain lines (no carriage returns), the last one
    at 100 % with the run's counters."""
    sink = UdpSink()
    try:
        out = _run("--dataset", _openacc(), "--duration", "2", "--asap", "--to",
                   f"127.0.0.1:{sink.ports[0]}", "--host-to", f"127.0.0.1:{sink.ports[1]}")
    finally:
        sink.close()
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    lines = out.stderr.splitlines()
    assert "\r" not in out.stderr and lines
    assert all(line.startswith("rve: ") for line in lines)
    assert lines[-1].startswith("rve: 100%")
    assert f"sent {summary['sent']}, dropped {summary['dropped']}, late p99" in lines[-1]


def test_frames_decode_as_real_j2735():
    sink = UdpSink()
    try:
        out = _run("--dataset", _openacc(), "--duration", "1", "--asap", "--ieee1609",
                   "--to", f"127.0.0.1:{sink.ports[0]}", "--host-to",
                   f"127.0.0.1:{sink.ports[1]}", "--no-progress")
    finally:
        sink.close()
    assert out.returncode == 0, out.stderr
    from catc.j2735.ieee1609 import unwrap

    assert sink.frames[0]
    for f in sink.frames[0]:
        with pytest.raises(DecodeError):
            decode_frame(f)  # wrapped: not a bare MessageFrame
        assert decode_frame(unwrap(f).frame).lat is not None


def test_captures_decode_reads_the_rves_own_pcapng(tmp_path):
    sink = UdpSink()
    try:
        out = _run("--dataset", _openacc(), "--duration", "1", "--asap", "--per", "30",
                   "--ieee1609", "--to", f"127.0.0.1:{sink.ports[0]}", "--host-to",
                   f"127.0.0.1:{sink.ports[1]}", "--capture", str(tmp_path), "--no-progress")
    finally:
        sink.close()
    assert out.returncode == 0, out.stderr
    dec = subprocess.run([sys.executable, "-m", "captures.cli", "decode",
                          str(tmp_path / "rve.frames.pcapng")], capture_output=True,
                         text=True, timeout=60, check=False)
    assert dec.returncode == 0, dec.stderr
    records = [json.loads(line) for line in dec.stdout.splitlines()]
    assert len(records) == len(sink.frames[0]) + len(sink.frames[1])
    from catc.j2735.ieee1609 import unwrap

    want = sorted((f"{b.temp_id:08X}", b.msg_cnt) for b in
                  (decode_frame(unwrap(f).frame) for f in sink.frames[0] + sink.frames[1]))
    assert sorted((r["id"], r["msgCnt"]) for r in records) == want


def test_default_scenario_and_a_synthetic_idm_host(tmp_path):
    sink = UdpSink()
    try:
        default = _run("--duration", "2", "--asap", "--no-progress", "--to",
                       f"127.0.0.1:{sink.ports[0]}", "--host-to", f"127.0.0.1:{sink.ports[1]}")
        idm = _run("--dataset", _openacc(), "--idm-host", "SMART_TARGET", "--duration", "2",
                   "--asap", "--no-progress", "--to", f"127.0.0.1:{sink.ports[0]}",
                   "--host-to", f"127.0.0.1:{sink.ports[1]}", "--capture", str(tmp_path))
    finally:
        sink.close()
    assert default.returncode == 0, default.stderr
    assert json.loads(default.stdout.splitlines()[-1])["host"] == "host"
    assert idm.returncode == 0, idm.stderr
    summary = json.loads(idm.stdout.splitlines()[-1])
    assert summary["host"] == "idm-host" and summary["host_frames"] == 21
    truth = _lines(tmp_path / "rve.truth.jsonl")
    assert any(r["vehicle"] == "idm-host" and r["host"] for r in truth)


def test_a_bad_dataset_row_is_named(tmp_path):
    src = shared_path("openacc-zalazone", "short_setting_dynamic_part22.csv").read_text()
    lines = src.splitlines()
    lines[9], lines[10] = lines[10], lines[9]  # two rows out of order
    bad = tmp_path / "swapped.csv"
    bad.write_text("\n".join(lines) + "\n")
    out = _run("--dataset", str(bad), "--asap", "--no-progress")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"rve run: dataset {bad}: openacc: line 10: Time "
        f"{lines[9].split(',')[0]} after {lines[8].split(',')[0]} breaks the strictly "
        "increasing 10 Hz grid"]


def test_frames_sent_over_a_second_late_are_counted():
    """A replay that cannot keep its schedule says so (rve.end.json, the summary): the
    latest RV frame's lateness and the frames over 1 s late; the host's do not count."""
    from rve.run import _account

    counts = {"sent": 0, "dropped": 0, "host": 0, "late_ms_max": 0.0, "late_over_1s": 0}
    for host, late in ((False, 0.004), (False, 1.5), (True, 3.0), (False, 0.9)):
        _account({"host": host}, b"x", (0.0, late), counts, None)
    assert counts["late_ms_max"] == 1500.0 and counts["late_over_1s"] == 1
    assert counts["sent"] == 3 and counts["host"] == 1
