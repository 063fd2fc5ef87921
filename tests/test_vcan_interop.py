"""Interoperability on real SocketCAN (vcan) with implementations that are not ours.

On the other end of the bus stand the Linux kernel's own ISO-TP (``can-isotp.ko``, through
can-utils ``isotprecv`` and a ``CAN_ISOTP`` socket) and can-utils ``candump`` /
``canplayer``, against the ``rve run`` and ``obu run`` processes, whose ISO-TP is
can-isotp's Python stack:

* ``rve run`` → the kernel's ISO-TP receivers (``isotprecv``, which send the Flow Control)
  get exactly the schedule's undropped MessageFrames, classic CAN and CAN FD; ``candump -L``
  records the same CAN frames as the RVE's own ``rve.frames.log``;
* the kernel's ISO-TP sender → ``obu run``: real BSMs of deployed OBUs arrive intact;
* ``canplayer`` replays the RVE's candump log of a run into a fresh ``obu run``, whose
  score equals the original run's.

All of them need vcan: where the running kernel has none, ``make test-vcan`` (and
``make test``) runs them in a VM (``tools/vcanvm.py``).  Every wait is bounded.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from captures.canlog import read_can_log
from catc.channel import ChannelConfig
from catc.j2735 import decode_frame
from catc.j2735.sniff import extract_frames
from catc.replay import plan
from hil.capture import read_rx
from hil.datasets import load_table
from hil.transport.can import HOST_IDS, RV_IDS
from rve.framing import wire_frame
from tests.conftest import shared_path
from tests.test_obu import READY, wait_ready
from tests.test_rve_can import BURST, PER, SEED, _dataset, _expected
from tests.test_transport import vcan_interface

pytestmark = pytest.mark.socketcan
#: Dataset seconds replayed: in the VM (software emulation) Python runs ~20x slower.
DURATION = 1.0
PY = sys.executable
# The kernel's ISO-TP socket options (linux/can/isotp.h).
SOL_CAN_ISOTP = 100 + 6  # SOL_CAN_BASE + CAN_ISOTP
CAN_ISOTP_OPTS, CAN_ISOTP_LL_OPTS = 1, 5
CAN_ISOTP_WAIT_TX_DONE = 0x400
CANFD_BRS = 0x01


@pytest.fixture
def vcan():
    with vcan_interface() as name:
        yield name


def _need(*tools: str) -> None:
    missing = [t for t in tools if shutil.which(t) is None]
    if missing:
        pytest.fail(f"can-utils missing ({', '.join(missing)}): make debs installs it")


def _can(iface: str, fd: bool) -> list[str]:
    return ["--transport", "can", "--can-interface", "socketcan", "--can-channel", iface,
            *(["--can-fd"] if fd else [])]


#: The kernel's CAN receive lists: a line per receive filter, its device first.
CAN_PROC = Path("/proc/net/can")


def _filters(iface: str) -> int:
    """How many receive filters sockets have on ``iface`` (a CAN socket bound to it has at
    least one: ``/proc/net/can/rcvlist_*``), or -1 where the kernel lists none of them."""
    lists = sorted(CAN_PROC.glob("rcvlist_*"))
    if not lists:
        return -1
    n = 0
    for path in lists:
        with contextlib.suppress(OSError):
            n += sum(1 for line in path.read_text().splitlines()
                     if len(line.split()) >= 6 and line.split()[0] == iface)
    return n


def _has_socket(pid: int) -> bool:
    with contextlib.suppress(OSError):
        return any(os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:")
                   for fd in os.listdir(f"/proc/{pid}/fd"))
    return False


def _wait_bound(proc: subprocess.Popen, iface: str, before: int, timeout: float = 60.0):
    """Until ``proc``, started when ``iface`` had ``before`` receive filters, has bound its
    socket: a new filter on ``iface`` (where the kernel lists them; else a socket among its
    file descriptors).  Bounded: a tool that exits or never binds fails the test."""
    deadline = time.monotonic() + timeout
    while not (_filters(iface) > before if before >= 0 else _has_socket(proc.pid)):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, f"{proc.args} did not bind to {iface}"
        time.sleep(0.01)


def _lines(path: Path) -> int:
    return path.read_text().count("\n") if path.exists() else 0


def _wait_lines(want: dict[Path, int], timeout: float = 30.0) -> None:
    """Until each file has at least its count of whole lines, or ``timeout`` s (then the
    test's own assertions say what is missing)."""
    deadline = time.monotonic() + timeout
    while any(_lines(f) < n for f, n in want.items()) and time.monotonic() < deadline:
        time.sleep(0.05)


@contextlib.contextmanager
def _tool(cmd: list[str], out: Path, iface: str):
    """A can-utils program on ``iface`` writing line-buffered to ``out``, once its socket
    is bound; stopped with SIGINT."""
    before = _filters(iface)
    with open(out, "w") as f:
        proc = subprocess.Popen(["stdbuf", "-oL", *cmd], stdout=f, stderr=subprocess.PIPE,
                                text=True)  # stdbuf execs the tool: the same pid
    try:
        _wait_bound(proc, iface, before)
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _ll_opts(fd: bool) -> list[str]:
    return ["-L", f"72:64:{CANFD_BRS}"] if fd else []


def _pdus(path: Path) -> list[bytes]:
    """isotprecv's output: one PDU per line, space-separated hex octets."""
    return [bytes.fromhex(line) for line in path.read_text().splitlines() if line.strip()]


def _candump(path: Path) -> list[tuple[int, bytes, bool]]:
    """(id, data, is_fd) of every frame in a candump -L log, in order."""
    import can

    return [(m.arbitration_id, bytes(m.data), m.is_fd)
            for m in can.CanutilsLogReader(str(path))]


def _rve(iface: str, fd: bool, capture: Path, *extra: str, timeout: float = 300) -> dict:
    out = subprocess.run([PY, "-m", "rve.cli", "run", *_can(iface, fd), "--no-progress",
                          "--capture", str(capture), *extra],
                         capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_kernel_isotp_receives_exactly_the_rves_schedule_and_candump_agrees(vcan, fd,
                                                                             tmp_path):
    _need("candump", "isotprecv")
    the_plan, want_rv, want_host = _expected(DURATION)
    ev = the_plan.events[~the_plan.events["dropped"]]
    want = {"rv": sorted(wire_frame(e, the_plan, False) for e in ev if not e["host"]),
            "host": sorted(wire_frame(e, the_plan, False) for e in ev if e["host"])}
    rv_out, host_out, dump = tmp_path / "rv.txt", tmp_path / "host.txt", tmp_path / "dump.log"
    with (_tool(["candump", "-L", vcan], dump, vcan),
          _tool(["isotprecv", "-l", *_ll_opts(fd), "-s", f"{RV_IDS[1]:03X}",
                 "-d", f"{RV_IDS[0]:03X}", vcan], rv_out, vcan),
          _tool(["isotprecv", "-l", *_ll_opts(fd), "-s", f"{HOST_IDS[1]:03X}",
                 "-d", f"{HOST_IDS[0]:03X}", vcan], host_out, vcan)):
        summary = _rve(vcan, fd, tmp_path / "cap", "--dataset", _dataset(), "--per",
                       str(PER * 100), "--burst", str(BURST), "--seed", str(SEED),
                       "--duration", str(DURATION), "--asap")
        # until the tools have written what reached them: every PDU, every frame the
        # RVE logged (its data frames and the Flow Controls it received)
        _wait_lines({rv_out: len(want["rv"]), host_out: len(want["host"]),
                     dump: _lines(tmp_path / "cap" / "rve.frames.log")})
    got = {"rv": _pdus(rv_out), "host": _pdus(host_out)}
    # The kernel reassembled exactly the schedule's undropped frames, octet for octet.
    assert sorted(got["rv"]) == want["rv"] and sorted(got["host"]) == want["host"]
    assert sorted((decode_frame(d).temp_id, decode_frame(d).msg_cnt)
                  for d in got["rv"]) == want_rv
    assert len(got["host"]) == want_host and summary["sent"] == len(want_rv)
    # candump saw what the RVE logged: every data frame it sent, every Flow Control the
    # kernel answered, in the same order.
    ours = _candump(tmp_path / "cap" / "rve.frames.log")
    theirs = _candump(dump)
    assert [(i, d) for i, d, _ in theirs] == [(i, d) for i, d, _ in ours]
    data_frames = [x for x in theirs if x[0] in (RV_IDS[0], HOST_IDS[0])]
    assert data_frames and all(f == fd for _, _, f in data_frames)
    # ... and our decoder (``captures decode``) reassembles candump's log into the same
    # frames, in bus order.
    found = read_can_log(dump, "candump")
    assert not found.isotp_errors
    by_id = {f"{RV_IDS[0]:03X}": "rv", f"{HOST_IDS[0]:03X}": "host"}
    for channel in ("rv", "host"):
        assert [f.frame for f in found.frames if by_id[f.meta["can_id"]] == channel] == \
            got[channel]


def _isotp_socket(iface: str, ids: tuple[int, int], fd: bool) -> socket.socket:
    """The kernel's ISO-TP sender on the address ``ids`` = (data id, Flow Control id);
    ``send`` returns once the transfer is on the bus (CAN_ISOTP_WAIT_TX_DONE), so that the
    two addresses' transfers keep the order they are sent in."""
    s = socket.socket(socket.AF_CAN, socket.SOCK_DGRAM, socket.CAN_ISOTP)
    s.setsockopt(SOL_CAN_ISOTP, CAN_ISOTP_OPTS,
                 struct.pack("=IIBBBB", CAN_ISOTP_WAIT_TX_DONE, 0, 0, 0xCC, 0xCC, 0))
    if fd:
        s.setsockopt(SOL_CAN_ISOTP, CAN_ISOTP_LL_OPTS, struct.pack("=BBB", 72, 64, CANFD_BRS))
    s.bind((iface, ids[1], ids[0]))  # (interface, rx id, tx id)
    s.settimeout(10)
    return s


def _start_obu(iface: str, fd: bool, capture: Path, *extra: str) -> subprocess.Popen:
    proc = subprocess.Popen([PY, "-m", "obu.cli", "run", *_can(iface, fd), "--predictor",
                             "ca", "--capture", str(capture), "--no-progress", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.early_stderr = wait_ready(proc, timeout=120)  # its bus is open
    assert proc.poll() is None, (proc.early_stderr, proc.communicate())
    assert READY.decode() in proc.early_stderr, f"obu run did not start: {proc.early_stderr}"
    return proc


def _stop(proc: subprocess.Popen, idle_exit: bool = False) -> tuple[str, str]:
    """Stop ``obu run``: SIGTERM, or with ``idle_exit`` let it end by itself (it does once
    the bus has been quiet for its --idle-exit), SIGTERM only after 60 s."""
    if idle_exit:
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=60)
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = getattr(proc, "early_stderr", "") + err  # _start_obu read up to the ready line
    assert proc.returncode == 0, err
    return out, err


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_kernel_isotp_sends_real_bsms_to_the_obu(vcan, fd, tmp_path):
    """A replay's frames (RVs, then the host, at each 10 Hz sample), then the 227 BSMs of a
    deployed OBU's log (up to 200 octets: multi-frame on CAN FD too), all from the kernel's
    ISO-TP into ``obu run``."""
    the_plan = plan(load_table(_dataset(), None), ChannelConfig(), SEED, None, DURATION)
    replay = [(bool(e["host"]), wire_frame(e, the_plan, False)) for e in the_plan.events]
    deployed = [x.frame for x in extract_frames(
        shared_path("jpo-ode-bsm-vectors", "rxMsg_BSM.bin").read_bytes())
        if x.frame[:2] == b"\x00\x14"]  # the log's BSMs (messageId 20)
    assert len(deployed) == 227 and max(map(len, deployed)) > 62
    obu = _start_obu(vcan, fd, tmp_path)
    n_rv = sum(not h for h, _ in replay)
    try:
        with (_isotp_socket(vcan, RV_IDS, fd) as rv, _isotp_socket(vcan, HOST_IDS, fd) as hv):
            for host, frame in replay:
                (hv if host else rv).send(frame)
            deadline = time.monotonic() + 60
            while _rx_count(tmp_path) < n_rv:  # the replay's RV frames, taken at host ticks
                assert time.monotonic() < deadline, "the OBU did not take every frame"
                time.sleep(0.2)
            # then the deployed BSMs, once the OBU has worked off the replay: their
            # multi-frame transfers wait for its flow control, which the kernel's sender
            # gives 1 s (N_Bs), and under QEMU's software emulation the OBU's event loop
            # took longer than that to work off a burst of 100 ticks
            for frame in deployed:
                rv.send(frame)
        # (no host frame follows: counted, not ticked; the counters file is rewritten
        # every second)
        while _counter(tmp_path, "frames_rv") < n_rv + len(deployed) \
                and time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        _stop(obu)
    rx = read_rx(tmp_path)
    assert [bytes.fromhex(r["hex"]) for r in rx if r["channel"] == "rv"][:n_rv] == \
        [f for h, f in replay if not h]
    c = json.loads((tmp_path / "obu.counters.json").read_text())
    assert c["frames_host"] == c["ticks"] == len(replay) - n_rv
    assert c["frames_rv"] == n_rv + len(deployed) and c.get("decode_errors", 0) == 0
    assert c["transport_bytes"] == sum(len(f) for _, f in replay) + sum(map(len, deployed))
    assert c.get("transport_errors", 0) == 0


def _counter(capture: Path, name: str) -> int:
    with contextlib.suppress(OSError, ValueError):
        return json.loads((capture / "obu.counters.json").read_text()).get(name, 0)
    return 0


def _rx_count(capture: Path) -> int:
    return len(read_rx(capture))  # a running OBU's gzip stream reads up to its last tick


def _stretch(src: Path, dst: Path, factor: float) -> None:
    """The candump -L log ``src`` with its time offsets multiplied by ``factor``."""
    out, t0 = [], None
    for line in src.read_text().splitlines():
        stamp, rest = line.split(" ", 1)
        t = float(stamp.strip("()"))
        t0 = t if t0 is None else t0
        out.append(f"({t0 + (t - t0) * factor:.6f}) {rest}")
    dst.write_text("\n".join(out) + "\n")


def test_canplayer_replays_a_capture_into_the_obu_with_the_same_score(vcan, tmp_path):
    _need("canplayer")
    from captures.score import score

    live, replayed = tmp_path / "live", tmp_path / "replayed"
    obu = _start_obu(vcan, True, live, "--idle-exit", "2")
    _rve(vcan, True, live, "--per", "50", "--seed", "4", "--duration", "8", "--speed", "2")
    _stop(obu, idle_exit=True)
    replayed.mkdir()
    for name in ("rve.config.json", "rve.truth.jsonl", "rve.schedule.jsonl"):
        shutil.copy(live / name, replayed / name)
    obu = _start_obu(vcan, True, replayed, "--idle-exit", "2")
    # canplayer keeps the log's timing but not the live run's flow control (the RVE waited
    # for the OBU's): under the VM's emulated CPU an OBU that falls behind a replay at the
    # live pace loses PDUs from its socket, so the replay runs at half that pace (the
    # ticks come from the frames, not their arrival times)
    slow = tmp_path / "half-pace.log"
    _stretch(live / "rve.frames.log", slow, 2.0)
    try:
        play = subprocess.run(["canplayer", "-I", str(slow), f"{vcan}={vcan}"],
                              capture_output=True, text=True, timeout=300)
        assert play.returncode == 0, play.stderr
    finally:
        _stop(obu, idle_exit=True)
    # The live run lost nothing (a loaded machine can delay the OBU's Flow Control past
    # the RVE's N_Bs timeout: that would show here, not as a score difference) ...
    for d in (live, replayed):
        c = json.loads((d / "obu.counters.json").read_text())
        assert c.get("transport_errors", 0) == 0 and c.get("decode_errors", 0) == 0, (d, c)
    # ... the OBU got the same frames, in the same order, into the same ticks ...
    rx = [[(r["channel"], r.get("hex"), r.get("tick"), r.get("status"))
           for r in read_rx(d)] for d in (live, replayed)]
    ticks = [[(t["t"], t["warnings"]) for t in map(json.loads, (d / "obu.ticks.jsonl").open())]
             for d in (live, replayed)]
    diff = [(x, y) for x, y in zip(*ticks, strict=False) if x != y][:5]
    assert len(rx[0]) == len(rx[1]) and rx[0] == rx[1], \
        f"rx {len(rx[0])} vs {len(rx[1])}; first ticks that differ: {diff}"
    assert ticks[0] == ticks[1], f"{len(ticks[0])} vs {len(ticks[1])} ticks; {diff}"
    # ... so every score is the same.
    a, b = score(live), score(replayed)
    assert a["received"] == a["sent"] > 0
    for key in ("pte95_m", "fcw_accuracy", "fcw", "sent", "received", "pte95_per_rv",
                "warnings"):
        assert a[key] == b[key], key
