"""RVE pacing: how late each frame leaves against its deadline, at 10 Hz per vehicle over UDP.

The RVE's replay loop (``rve.run.replay``: plan, absolute-deadline pacer, UPER encoding,
``hil.transport`` UDP sender, no capture) runs in this process on a synthetic table of N
vehicles on a ring road (every vehicle a BSM every 100 ms, all due at the same instants:
the worst case for a pacer, N frames per deadline).  A separate process receives on
127.0.0.1 and counts the datagrams, so the sends are real.  Send jitter = send time minus
the frame's deadline, per frame, over ``--seconds`` of replay after 1 s of warm-up.  The
peer row is the same loop without pacing (``--asap``): what encoding and sending N frames
costs back to back, the floor of any pacing.

    python bench/rve_pacing.py [--json] [--vehicles 50,250,500] [--seconds 10]

Target (issue 5): p99 at most 2 ms at 250 vehicles (2,500 BSM/s).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import platform
import socket
import subprocess
import sys
import time

import numpy as np

from catc.channel import ChannelConfig
from catc.geo import EnuFrame
from catc.mobility import DT, MobilityTable, Track
from catc.replay import plan
from rve.run import DEFAULTS, replay

ORIGIN = (46.89, 16.84, 0.0)

SINK = r"""
import socket, sys, time
socks = []
for port in (int(sys.argv[1]), int(sys.argv[2])):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    s.bind(("127.0.0.1", port)); s.settimeout(0.05); socks.append(s)
print("ready", flush=True)
n = 0; last = time.monotonic(); deadline = time.monotonic() + float(sys.argv[3])
while time.monotonic() < deadline and time.monotonic() - last < 3.0:
    for s in socks:
        try:
            while True:
                s.recv(4096); n += 1; last = time.monotonic(); s.settimeout(0.0)
        except (BlockingIOError, TimeoutError, socket.timeout):
            s.settimeout(0.05)
print(n, flush=True)
"""


def ring_table(n: int, seconds: float) -> MobilityTable:
    """N vehicles + a host on a 2 km ring, 10 Hz, 20-30 m/s."""
    frame = EnuFrame(*ORIGIN)
    t = np.arange(int(seconds / DT) + 1) * DT
    r = 2000.0 / (2 * math.pi)
    tracks = {}
    rng = np.random.default_rng(0)
    for k in range(n + 1):
        v = 20.0 + 10.0 * rng.random()
        a = 2 * math.pi * k / (n + 1) + v * t / r
        x, y = r * np.cos(a), r * np.sin(a)
        lat, lon, _ = frame.to_geodetic(x, y, 0.0)
        heading = (np.degrees(np.arctan2(-np.sin(a), np.cos(a)))) % 360.0
        vid = "host" if k == 0 else f"rv{k}"
        tracks[vid] = Track(vid, t, x, y, np.asarray(lat), np.asarray(lon), np.zeros_like(t),
                            np.full_like(t, v), heading, np.zeros_like(t),
                            np.full_like(t, -math.degrees(v / r)), 4.5, 1.8)
    return MobilityTable("ring", "synthetic", ORIGIN, tracks, default_host="host")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure(n: int, seconds: float, asap: bool) -> dict:
    ports = free_port(), free_port()
    sink = subprocess.Popen([sys.executable, "-c", SINK, str(ports[0]), str(ports[1]),
                             str(seconds + 30)], stdout=subprocess.PIPE, text=True)
    try:
        assert sink.stdout is not None and sink.stdout.readline().strip() == "ready"
        args = argparse.Namespace(**DEFAULTS)
        args.to, args.host_to = ("127.0.0.1", ports[0]), ("127.0.0.1", ports[1])
        args.asap, args.progress, args.speed = asap, False, 1.0
        the_plan = plan(ring_table(n, seconds + 1.0), ChannelConfig())
        late: list[float] = []
        t0 = time.perf_counter()
        counts = asyncio.run(replay(args, the_plan, late))
        wall = time.perf_counter() - t0
        received = int(sink.communicate(timeout=60)[0].strip())
    finally:
        if sink.poll() is None:
            sink.kill()
    ms = np.array(late[n * 10:]) * 1e3 if not asap else np.array([0.0])  # skip 1 s warm-up
    frames = counts["sent"] + counts["host"]
    return {"vehicles": n, "mode": "asap" if asap else "paced", "frames": frames,
            "received": received, "wall_s": round(wall, 3),
            "frames_per_s": round(frames / wall, 1),
            "jitter_ms_p50": round(float(np.percentile(ms, 50)), 4),
            "jitter_ms_p99": round(float(np.percentile(ms, 99)), 4),
            "jitter_ms_max": round(float(ms.max()), 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--vehicles", default="50,250,500", help="counts (default 50,250,500)")
    ap.add_argument("--seconds", type=float, default=10.0, help="replay length per run")
    args = ap.parse_args(argv)
    sizes = [int(v) for v in args.vehicles.split(",")]
    rows = []
    for n in sizes:
        rows.append(measure(n, args.seconds, asap=False))
        rows.append(measure(n, min(args.seconds, 3.0), asap=True))
        if not args.json:
            print(f"  done {n} vehicles", file=sys.stderr)
    paced = {r["vehicles"]: r for r in rows if r["mode"] == "paced"}
    result = {key: {str(n): paced[n][f"jitter_ms_{key.split('_')[-1]}"] for n in sizes}
              for key in ("jitter_ms_p50", "jitter_ms_p99", "jitter_ms_max")}
    result.update(rows=rows, python=platform.python_version(), cpus=os.cpu_count())
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print("RVE send jitter (send time - deadline), UDP on 127.0.0.1, 10 Hz per vehicle")
    print(f"{'vehicles':>8} {'mode':>6} {'frames/s':>9} {'p50 ms':>8} {'p99 ms':>8} "
          f"{'max ms':>8} {'received':>9}")
    for r in rows:
        print(f"{r['vehicles']:>8} {r['mode']:>6} {r['frames_per_s']:>9.0f} "
              f"{r['jitter_ms_p50']:>8.3f} {r['jitter_ms_p99']:>8.3f} {r['jitter_ms_max']:>8.3f} "
              f"{r['received']:>5}/{r['frames']:<5}")
    if 250 in paced:
        ok = paced[250]["jitter_ms_p99"] <= 2.0
        print(f"target: p99 <= 2 ms at 250 vehicles: {'met' if ok else 'NOT met'} "
              f"({paced[250]['jitter_ms_p99']:.3f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
