"""OBU memory under a flood of garbage: ``obu run`` (separate process, hgp, capture on) fed
in real time by the RVE on a synthetic ring road (``bench/rve_pacing.ring_table``: N RVs and
a host at 10 Hz, PER 50 %), while a third process floods its RV port with ``rve flood``'s
mix (random octets, oversize datagrams, bit-flipped and truncated copies of the ring's
host and RV frames) at ``--rate`` datagrams/s.  The OBU's resident memory (VmRSS from
/proc) is sampled every second; the table prints it each minute, and the verdict compares
the last half of the run with the first minutes after warm-up: a plateau grows by less
than ``--plateau-mb`` per minute over the second half.

    python bench/obu_flood.py [--json] [--minutes 10] [--rate 2000] [--rvs 20]
    python bench/obu_flood.py --rate 0       # the control: the same run, no flood

Target (issue 18): a 10-minute flood at 2,000 datagrams/s reaches a plateau.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np

from catc.channel import ChannelConfig
from catc.j2735 import encode_frame
from catc.replay import plan
from hil.transport.udp import free_ports, wait_bound
from rve.run import DEFAULTS, replay
from rve_pacing import ring_table


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS")


def _ring_plan(n: int, seconds: float):
    return plan(ring_table(n, seconds), ChannelConfig(per=0.5), 1)


def flooder(port: int, n: int, seconds: float, rate: float) -> None:
    """The flood process: copies of the ring's frames (the same plan the RVE replays)."""
    from rve.flood import _mix, flood

    the_plan = _ring_plan(n, seconds)
    ev = the_plan.events
    t0 = float(ev["t"][ev["host"]][0])
    times, frames = [], []
    for e in ev:
        if not e["dropped"]:
            frames.append(encode_frame(the_plan.bsm(e)))
            times.append(float(e["time"]) - t0)
    args = argparse.Namespace(to=("127.0.0.1", port), rate=rate, duration=seconds, speed=1.0,
                              mix=_mix("random=1,oversize=0.1,copy=1"), flood_seed=1, lag=1.0)
    print(json.dumps(flood(args, times, frames)), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=2000.0)
    ap.add_argument("--rvs", type=int, default=20)
    ap.add_argument("--plateau-mb", type=float, default=1.0,
                    help="growth per minute over the second half that still counts as a "
                         "plateau (default 1 MB/min)")
    ap.add_argument("--flooder", nargs=3, type=float, help=argparse.SUPPRESS)  # port n secs
    args = ap.parse_args()
    seconds = args.minutes * 60.0
    if args.flooder:
        port, n, secs = args.flooder
        flooder(int(port), int(n), secs, args.rate)
        return 0
    ports = free_ports()
    samples: list[tuple[float, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        obu = subprocess.Popen(
            [sys.executable, "-m", "obu.cli", "run", "--listen", f"127.0.0.1:{ports[0]}",
             "--host-listen", f"127.0.0.1:{ports[1]}", "--predictor", "hgp", "--idle-exit",
             "3", "--no-progress", "--warnings", os.devnull, "--capture", f"{tmp}/cap"],
            stdout=subprocess.DEVNULL, stderr=open(f"{tmp}/obu.err", "w"),  # noqa: SIM115
            text=True)  # a file, not a pipe: ten minutes of log lines would fill a pipe
        fl = None
        try:
            wait_bound(ports, alive=lambda: obu.poll() is None)
            if args.rate > 0:  # --rate 0: the same run without the flood (the control)
                fl = subprocess.Popen([sys.executable, __file__, "--rate", str(args.rate),
                                       "--flooder", str(ports[0]), str(args.rvs),
                                       str(seconds)], stdout=subprocess.PIPE, text=True)
            start = time.monotonic()
            done = threading.Event()

            def sample() -> None:
                k = 0
                while not done.is_set():
                    try:
                        samples.append((time.monotonic() - start, rss_mb(obu.pid)))
                    except (OSError, RuntimeError):
                        return
                    k += 1
                    done.wait(max(0.0, start + k - time.monotonic()))

            th = threading.Thread(target=sample, daemon=True)
            th.start()
            rve = argparse.Namespace(**DEFAULTS)
            rve.to, rve.host_to = ("127.0.0.1", ports[0]), ("127.0.0.1", ports[1])
            rve.progress = False
            asyncio.run(replay(rve, _ring_plan(args.rvs, seconds), []))
            sent = (json.loads(fl.communicate(timeout=120)[0].strip().splitlines()[-1])
                    if fl is not None else {"sent": {}, "datagrams": 0})
            done.set()
            th.join()
            obu.wait(timeout=120)
        finally:
            for p in (obu, fl):
                if p is not None and p.poll() is None:
                    p.kill()
        counters = json.loads((Path(tmp) / "cap" / "obu.counters.json").read_text())
    t = np.array([s[0] for s in samples])
    mb = np.array([s[1] for s in samples])
    half = t >= t[-1] / 2
    slope = float(np.polyfit(t[half] / 60.0, mb[half], 1)[0]) if half.sum() > 2 else 0.0
    per_minute = [{"minute": m, "rss_mb": round(float(mb[np.argmin(abs(t - 60.0 * m))]), 1)}
                  for m in range(int(args.minutes) + 1) if t[-1] >= 60.0 * m - 1]
    result = {"minutes": args.minutes, "rate": args.rate, "rvs": args.rvs, "flood": sent,
              "rss_mb": per_minute, "rss_max_mb": round(float(mb.max()), 1),
              "growth_second_half_mb_per_min": round(slope, 3),
              "plateau": slope < args.plateau_mb,
              "counters": {k: v for k, v in counters.items()
                           if k.startswith(("cam_", "decode_", "transport_", "frames"))
                           or k in ("pending", "ticks", "tick_ms_p99")}}
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print(f"OBU RSS under a flood of {args.rate:g} datagrams/s for {args.minutes:g} min "
          f"({sent['datagrams']} sent: {sent['sent']}), {args.rvs} RVs + host at PER 50 %")
    print("minute  RSS MB")
    for row in per_minute:
        print(f"{row['minute']:>6}  {row['rss_mb']:>6.1f}")
    print(f"max {result['rss_max_mb']} MB; growth over the second half "
          f"{slope:+.3f} MB/min: {'plateau' if result['plateau'] else 'NOT a plateau'}")
    c = result["counters"]
    print(f"decode errors {c.get('decode_errors', 0)}, oversized "
          f"{c.get('transport_oversized', 0)}, self {c.get('cam_self', 0)}, shadow "
          f"{c.get('cam_shadow', 0)}, tentative evicted {c.get('cam_tentative_evicted', 0)}, "
          f"confirmed {c.get('cam_confirmed', 0)}, tick p99 {c.get('tick_ms_p99')} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
