"""Transport throughput: MessageFrames per second through ``hil.transport``, saturated.

The sender sends ``--frames`` frames (default 5,000) back to back, sizes drawn uniformly
from 40 to 200 octets (a BSM without and with a long path history; seeded), every 25th
on the host channel, yielding to the event loop after each frame as the RVE does; the
rate is frames received divided by the time from the first send to the last complete
frame at the receiver (``time.monotonic``, one clock for both processes).  Each frame
is one ISO-TP transfer on CAN, never interleaved with another, with one Flow Control
round trip when it needs more than one CAN frame; "CAN frames/frame" counts the CAN
frames on the bus per MessageFrame, Flow Control included.

Rows:

* ``udp``: loopback 127.0.0.1, sender and receiver in this process;
* ``can virtual``: python-can's in-process bus, classic CAN and CAN FD, one process;
* ``can udp_multicast``: classic and FD between two processes (``--peer``) inside a
  network namespace this script creates and deletes (lo + an IPv4 multicast route); the
  rows are skipped with the reason when ``ip netns add`` is not permitted (not root) or
  python-can's ``msgpack`` is missing;
* ``can socketcan``: classic and FD on a vcan interface this script creates and deletes,
  one process.  Where the running kernel has no vcan they run inside the QEMU VM of
  ``tools/vcanvm.py`` (``--vm-frames`` frames, default 1,000), next to a ``virtual`` FD row
  in the same VM: under software emulation (TCG) Python runs about 20× slower, so compare
  the VM's rows with each other, not with the host's.  The column "where" says which.

    python bench/transport.py [--json] [--frames N] [--vm-frames N]

Target: 2,500 frames/s (250 RVs at 10 Hz) on CAN FD.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform
import random
import select
import subprocess
import sys
import time

from hil.transport import open_receiver, open_sender

TARGET = 2500.0
GROUP = "239.74.163.2"


def workload(n: int, seed: int = 5) -> list[tuple[str, bytes]]:
    rng = random.Random(seed)
    return [("host" if i % 25 == 24 else "rv", rng.randbytes(rng.randint(40, 200)))
            for i in range(n)]


async def _send_all(tx, frames: list[tuple[str, bytes]]) -> None:
    for channel, data in frames:
        await (tx.send(data) if channel == "rv" else tx.send_host(data))
        await asyncio.sleep(0)


async def _receive(rx, n: int, idle_s: float = 3.0) -> tuple[int, float]:
    """(frames received, monotonic time of the last); stops after ``idle_s`` of silence."""
    got, last = 0, time.monotonic()
    with contextlib.suppress(TimeoutError):
        while got < n:
            async with asyncio.timeout(idle_s):
                await rx.recv()
            got, last = got + 1, time.monotonic()
    return got, last


def _row(transport: str, bus: str, fd: bool | None, n: int, got: int, seconds: float,
         stats: dict[str, int]) -> dict:
    row = {"transport": transport, "bus": bus, "fd": fd, "frames": n, "received": got,
           "seconds": round(seconds, 4), "frames_per_s": round(got / seconds, 1)}
    if "can_frames" in stats:
        row["can_frames_per_frame"] = round(stats["can_frames"] / max(stats["frames"], 1), 2)
    return row


async def in_process(kind: str, n: int, fd: bool | None, interface: str = "virtual",
                     channel: str | None = None) -> dict:
    frames = workload(n)
    if kind == "udp":
        rx = await open_receiver("udp", listen=("127.0.0.1", 0), host_listen=("127.0.0.1", 0))
        tx = await open_sender("udp", to=rx.addresses["rv"], host_to=rx.addresses["host"])
        bus = "loopback 127.0.0.1"
    else:
        channel = channel or f"bench-{os.getpid()}-{fd}"
        rx = await open_receiver("can", interface=interface, channel=channel, fd=bool(fd))
        tx = await open_sender("can", interface=interface, channel=channel, fd=bool(fd))
        bus = f"{interface} {'vcan ' if interface == 'socketcan' else ''}(1 process)"
    try:
        receiving = asyncio.create_task(_receive(rx, n))
        t0 = time.monotonic()
        await _send_all(tx, frames)
        got, last = await receiving
    finally:
        await tx.aclose()
        await rx.aclose()
    return _row(kind, bus, fd, n, got, last - t0, tx.stats)


async def peer(role: str, n: int, fd: bool) -> dict:
    """One process of the udp_multicast rows (run inside the namespace)."""
    if role == "recv":
        async with await open_receiver("can", interface="udp_multicast", channel=GROUP,
                                       fd=fd) as rx:
            print("ready", flush=True)
            got, last = await _receive(rx, n)
            return {"received": got, "last": last, "stats": rx.stats}
    async with await open_sender("can", interface="udp_multicast", channel=GROUP,
                                 fd=fd) as tx:
        t0 = time.monotonic()
        await _send_all(tx, workload(n))
        return {"t0": t0, "stats": tx.stats}


def _ip(*args: str) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return subprocess.CompletedProcess(args, 1, "", str(exc))


def multicast_rows(n: int) -> tuple[list[dict], str | None]:
    """The two udp_multicast rows, or no rows and the reason they were skipped."""
    try:
        import msgpack  # noqa: F401
    except ImportError:
        return [], "python-can's udp_multicast needs msgpack (pip install msgpack)"
    name = f"catc-bench-{os.getpid()}"
    made = _ip("netns", "add", name)
    if made.returncode != 0:
        return [], f"cannot create a network namespace: {made.stderr.strip()}"
    rows = []
    try:
        for args in (("link", "set", "lo", "up"), ("route", "add", "224.0.0.0/4", "dev", "lo")):
            done = _ip("-n", name, *args)
            if done.returncode != 0:
                return [], f"ip -n {name} {' '.join(args)}: {done.stderr.strip()}"
        for fd in (False, True):
            rows.append(_two_processes(name, n, fd))
    finally:
        _ip("netns", "del", name)
    return rows, None


def _two_processes(netns: str, n: int, fd: bool) -> dict:
    cmd = ["ip", "netns", "exec", netns, sys.executable, os.path.abspath(__file__),
           "--frames", str(n)] + (["--fd"] if fd else [])
    receiver = subprocess.Popen([*cmd, "--peer", "recv"], stdout=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([receiver.stdout], [], [], 20)
        if not ready or receiver.stdout.readline().strip() != "ready":
            raise RuntimeError("udp_multicast receiver did not start")
        sender = subprocess.run([*cmd, "--peer", "send"], capture_output=True, text=True,
                                timeout=300)
        if sender.returncode != 0:
            raise RuntimeError(f"udp_multicast sender failed: {sender.stderr.strip()}")
        out, _ = receiver.communicate(timeout=60)
    finally:
        if receiver.poll() is None:
            receiver.kill()
            receiver.wait(timeout=5)
    rx = json.loads(out.strip().splitlines()[-1])
    tx = json.loads(sender.stdout.strip().splitlines()[-1])
    return _row("can", "udp_multicast (2 processes)", fd, n, rx["received"],
                rx["last"] - tx["t0"], tx["stats"])


def _vcan_rows(n: int) -> list[dict]:
    """socketcan rows on a vcan interface of this kernel (created and deleted)."""
    name = f"catcbench{os.getpid() % 100000}"
    made = _ip("link", "add", "dev", name, "type", "vcan")
    if made.returncode != 0:
        raise RuntimeError(f"cannot create a vcan interface: {made.stderr.strip()}")
    try:
        up = _ip("link", "set", "dev", name, "mtu", "72", "up")
        if up.returncode != 0:
            raise RuntimeError(f"cannot bring {name} up: {up.stderr.strip()}")
        return [asyncio.run(in_process("can", n, fd, "socketcan", name)) for fd in (False, True)]
    finally:
        _ip("link", "del", "dev", name)


def socketcan_rows(n: int, vm_frames: int) -> tuple[list[dict], str | None]:
    """socketcan rows here, else in the vcan VM; or no rows and the reason."""
    try:
        return [dict(r, where="host") for r in _vcan_rows(n)], None
    except RuntimeError as exc:
        reason = str(exc)
    vm = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tools", "vcanvm.py")
    out = subprocess.run([sys.executable, vm, "run", "--", sys.executable,
                          os.path.abspath(__file__), "--in-vm", "--frames", str(vm_frames)],
                         capture_output=True, text=True, timeout=1800)
    lines = [x for x in out.stdout.splitlines() if x.startswith("[{")]
    if out.returncode != 0 or not lines:
        why = (out.stderr.strip().splitlines() or ["no output"])[-1]
        return [], f"no vcan here ({reason}) and the VM failed: {why}"
    accel = "KVM" if "(KVM)" in out.stderr else "TCG"
    return [dict(r, where=f"VM ({accel})") for r in json.loads(lines[-1])], None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--frames", type=int, default=5000, help="frames per row (default 5000)")
    ap.add_argument("--peer", choices=("send", "recv"), help=argparse.SUPPRESS)
    ap.add_argument("--vm-frames", type=int, default=1000,
                    help="frames per row inside the vcan VM (default 1000)")
    ap.add_argument("--fd", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--in-vm", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.peer:
        print(json.dumps(asyncio.run(peer(args.peer, args.frames, args.fd))), flush=True)
        return 0
    if args.in_vm:  # the VM's rows: socketcan, and virtual FD to compare them with
        rows = [*_vcan_rows(args.frames), asyncio.run(in_process("can", args.frames, True))]
        print(json.dumps(rows), flush=True)
        return 0
    rows = [dict(asyncio.run(in_process("udp", args.frames, None)), where="host"),
            dict(asyncio.run(in_process("can", args.frames, False)), where="host"),
            dict(asyncio.run(in_process("can", args.frames, True)), where="host")]
    more, skipped = multicast_rows(args.frames)
    rows += [dict(r, where="host") for r in more]
    vcan, vcan_skipped = socketcan_rows(args.frames, args.vm_frames)
    rows += vcan
    result = {"rows": rows, "skipped": skipped, "socketcan_skipped": vcan_skipped,
              "target_frames_per_s": TARGET,
              "python": platform.python_version(), "machine": platform.machine(),
              "cpus": os.cpu_count()}
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print(f"hil.transport throughput, {args.frames} frames of 40-200 octets, saturated")
    print(f"{'transport':>9} {'bus':<28} {'CAN':>7} {'where':>9} {'frames/s':>9} "
          f"{'received':>9} {'CAN frames/frame':>16}")
    for r in rows:
        can_kind = "" if r["fd"] is None else ("FD" if r["fd"] else "classic")
        per = r.get("can_frames_per_frame", "")
        print(f"{r['transport']:>9} {r['bus']:<28} {can_kind:>7} {r['where']:>9} "
              f"{r['frames_per_s']:>9.0f} {r['received']:>4}/{r['frames']:<4} {per:>16}")
    if skipped:
        print(f"udp_multicast rows skipped: {skipped}")
    if vcan_skipped:
        print(f"socketcan rows skipped: {vcan_skipped}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
