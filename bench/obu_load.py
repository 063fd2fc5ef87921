"""OBU under load: the ``obu run`` process fed over UDP on 127.0.0.1 with N RVs at 10 Hz.

This process plays the RVE (``rve.run.replay`` on a synthetic ring road of N vehicles and a
host, real time, the channel model at the given PER) and starts ``obu run`` as a separate
process with the given predictor.  From the OBU's own counters (printed when it stops): frames
received at its socket against frames sent (``socket_loss``), step time p50/p99/max over
every tick, deadline misses (steps over the 100 ms tick), and the OBU process's CPU use
(user + system time from /proc over wall time).  The OBU writes no capture here
(``--capture`` adds it, as a HIL run would).

    python bench/obu_load.py [--json] [--rvs 100,250,500] [--per 0,50] [--predictors hgp,ca]
                             [--seconds 15] [--capture]

Target (issue 6): 500 RVs with hgp at PER 50 %: no socket loss and tick p99 <= 50 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from catc.channel import ChannelConfig
from catc.replay import plan
from hil.transport.udp import free_ports
from rve.run import DEFAULTS, replay
from rve_pacing import ring_table


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(n: int, per: float, predictor: str, seconds: float, capture: bool) -> dict:
    ports = free_ports()
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "obu.cli", "run", "--listen", f"127.0.0.1:{ports[0]}",
               "--host-listen", f"127.0.0.1:{ports[1]}", "--predictor", predictor,
               "--idle-exit", "2", "--no-progress", "--warnings", os.devnull]
        if capture:
            cmd += ["--capture", tmp]
        obu = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True)
        try:
            time.sleep(1.0)
            args = argparse.Namespace(**DEFAULTS)
            args.to, args.host_to = ("127.0.0.1", ports[0]), ("127.0.0.1", ports[1])
            args.progress = False
            the_plan = plan(ring_table(n, seconds), ChannelConfig(per=per / 100.0), 1)
            cpu0, wall0 = cpu_seconds(obu.pid), time.monotonic()
            counts = asyncio.run(replay(args, the_plan))
            cpu1, wall1 = cpu_seconds(obu.pid), time.monotonic()
            _, err = obu.communicate(timeout=120)
        finally:
            if obu.poll() is None:
                obu.kill()
    lines = [ln for ln in err.splitlines() if ln.startswith('{"obu"')]
    if not lines:
        raise RuntimeError(f"obu gave no counters: {err[-500:]}")
    c = json.loads(lines[-1])["obu"]
    sent = counts["sent"] + counts["host"]
    got = c.get("transport_frames", 0)
    return {"rvs": n, "per": per, "predictor": predictor,
            "socket_loss": sent - got, "frames_sent": sent,
            "tick_ms_p50": c.get("tick_ms_p50"), "tick_ms_p99": c.get("tick_ms_p99"),
            "tick_ms_max": c.get("tick_ms_max"), "deadline_misses": c.get("deadline_misses", 0),
            "ticks": c.get("ticks", 0),
            "cpu_percent": round(100.0 * (cpu1 - cpu0) / (wall1 - wall0), 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--rvs", default="100,250,500")
    ap.add_argument("--per", default="0,50", help="PER values in %% (default 0,50)")
    ap.add_argument("--predictors", default="hgp,ca")
    ap.add_argument("--seconds", type=float, default=15.0, help="replay length per cell")
    ap.add_argument("--capture", action="store_true", help="the OBU also writes its capture")
    args = ap.parse_args(argv)
    rows = []
    for n in (int(v) for v in args.rvs.split(",")):
        for per in (float(v) for v in args.per.split(",")):
            for p in args.predictors.split(","):
                rows.append(measure(n, per, p, args.seconds, args.capture))
                if not args.json:
                    print(f"  done {n} RVs PER {per:g} % {p}", file=sys.stderr)
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print("OBU under load: UDP on 127.0.0.1, 10 Hz per RV, one OBU process"
          + (" writing its capture" if args.capture else ""))
    print(f"{'RVs':>5} {'PER %':>6} {'predictor':>9} {'socket loss':>12} {'tick p50':>9} "
          f"{'tick p99':>9} {'tick max':>9} {'misses':>7} {'CPU %':>6}")
    for r in rows:
        print(f"{r['rvs']:>5} {r['per']:>6g} {r['predictor']:>9} "
              f"{r['socket_loss']:>5}/{r['frames_sent']:<6} {r['tick_ms_p50']:>9.1f} "
              f"{r['tick_ms_p99']:>9.1f} {r['tick_ms_max']:>9.1f} {r['deadline_misses']:>7} "
              f"{r['cpu_percent']:>6.1f}")
    target = [r for r in rows if r["rvs"] == 500 and r["per"] == 50 and r["predictor"] == "hgp"]
    if target:
        t = target[0]
        ok = t["socket_loss"] == 0 and t["tick_ms_p99"] <= 50.0
        print(f"target: 500 RVs, hgp, PER 50 %: no socket loss and tick p99 <= 50 ms: "
              f"{'met' if ok else 'NOT met'} (loss {t['socket_loss']}, "
              f"p99 {t['tick_ms_p99']:.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
