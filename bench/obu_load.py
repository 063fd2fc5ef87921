"""OBU under load: the ``obu run`` process fed over UDP on 127.0.0.1 with N RVs at 10 Hz.

This process plays the RVE (``rve.run.replay`` on a synthetic ring road of N vehicles and a
host, real time, the channel model at the given PER) and starts ``obu run`` as a separate
process with the given predictor.  From the OBU's own counters (printed when it stops): frames
received at its socket against frames sent (``socket_loss``), step time p50/p99/max over
every tick, deadline misses (steps over the 100 ms tick), and the OBU process's CPU use
(user + system time from /proc over wall time).  The OBU writes no capture here
(``--capture`` adds it, as a HIL run would).  On the RVE side (this process): its CPU use
(``time.process_time`` over wall time; it includes the pacer's last-2-ms spin) and how late
each RV frame left against its deadline (p99 and max, as ``bench/rve_pacing.py``).  And
what every other process on the machine used meanwhile (``other_cpu_percent``, from
/proc/stat, in % of one core): the OBU and the RVE run at the same time as separate
processes, so a busy machine shows up as longer ticks, a late RVE and, at worst, a backlog
at the OBU's socket (stale verdicts, socket loss).

IEEE 1609.2 (``--verify``): ``on`` makes a test PKI with a pseudonym per RV
(``hil.pki.init`` in a temporary directory), the RVE signs every RV BSM (``rve run --sign``:
the full certificate in a vehicle's first BSM, once a second and after a new neighbour, the
HashedId8 digest otherwise) and the OBU runs with ``--verify enforce --trust DIR
--verify-policy all`` (every frame verified on arrival); the row then shows the OBU's ``verify_ok``
and every other ``verify_<reason>`` counter and the RVE's signatures/s.  ``on-demand`` is
the same with ``--verify-policy on-demand`` (issue 30): its row also shows the frames
verified (at once + from the queue), deferred, skipped (dropped from the verification queue
unverified) and stepped unverified.  ``off`` is plain UPER, no 1609.2 at all (the rows
before security existed); ``signed`` sends the signed frames to an OBU that does not verify
(the cost of the envelope alone).  A list (``--verify off,on``, or ``both``) runs every mode
for each cell, one after the other in the same run, and prints each mode's tick p99 and OBU
CPU as a ratio to the ``off`` row of its cell.  ``--verify`` alone means ``on``.
CPU % and signatures/s are over the run: the RVE's preparation before its clock starts
(``sign_ahead_lead_s``, its CPU ``sign_ahead_prepare_cpu_s``) is left out; the signing
workers' CPU is over everything, the time they signed before the clock included.

``--sign-workers 0,2`` (signed modes): one row per value of ``rve run --sign-workers``
(0: the RVE signs in its sending loop; N: N worker processes sign ahead of the schedule,
:mod:`rve.signahead`); ``RVE CPU %`` is then the sending process's and its workers'
(``main+workers``), and the row gives the batches the loop had to wait for.
``--sign-lookahead S`` is ``rve run --sign-lookahead``: with S at least ``--seconds``, the
workers sign the whole run before the RVE's clock starts, and only the sending loop runs
beside the OBU (an RVE is a test instrument: its signing need not share the OBU's cores
while the OBU is measured).

    python bench/obu_load.py [--json] [--rvs 100,250,500] [--per 0,50] [--predictors hgp,ca]
                             [--seconds 15] [--capture | --keep DIR]
                             [--verify [off,on,on-demand,signed|both]] [--sign-workers 0,2]
                             [--sign-lookahead S]

Target (issue 6): 500 RVs with hgp at PER 50 %: no socket loss and tick p99 <= 50 ms.
With --verify the same target holds for the verifying OBU.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np

from catc.channel import ChannelConfig
from catc.replay import plan
from hil.pki import init as pki_init
from hil.transport.udp import free_ports, wait_bound
from rve.run import DEFAULTS, replay
from rve_pacing import ring_table


def machine_busy_seconds() -> float:
    """CPU-seconds all cores have spent busy since boot (/proc/stat: all but idle, iowait)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children_cpu_seconds() -> float:
    """CPU-seconds of this process's children that have ended and been waited for."""
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


MODES = ("off", "on", "on-demand", "signed")


class WebClients:
    """``k`` live-view clients of ``obu run --web`` on their own thread: WebSocket
    connections that read every state pushed, as the page does (``/ws``), without drawing
    it (ten Chromium tabs drawing 500 RVs would compete with the OBU for the 2 cores)."""

    def __init__(self, k: int, port: int) -> None:
        self.k, self.port = k, port
        self.received = 0
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_until_complete,
                                       args=(self._main(),), daemon=True)

    async def _client(self, session) -> None:
        import aiohttp

        for _ in range(50):  # the OBU's server comes up within a second or so
            try:
                async with session.ws_connect(f"http://127.0.0.1:{self.port}/ws") as ws:
                    async for msg in ws:
                        if msg.type == aiohttp.WSMsgType.TEXT:
                            json.loads(msg.data)
                            self.received += 1
                    return
            except aiohttp.ClientError:
                await asyncio.sleep(0.1)

    async def _main(self) -> None:
        import aiohttp

        async with aiohttp.ClientSession() as session:
            tasks = [asyncio.create_task(self._client(session)) for _ in range(self.k)]
            await asyncio.wait(tasks)

    def __enter__(self) -> WebClients:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.thread.join(timeout=30)


def measure(n: int, per: float, predictor: str, seconds: float, capture: bool,
            verify: str = "off", web_clients: int | None = None,
            keep: Path | None = None, sign_workers: int | None = None,
            verify_workers: int | None = None, sign_lookahead: float | None = None) -> dict:
    ports = free_ports()
    web_port = None
    if web_clients is not None:
        import socket

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            web_port = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "obu.cli", "run", "--listen", f"127.0.0.1:{ports[0]}",
               "--host-listen", f"127.0.0.1:{ports[1]}", "--predictor", predictor,
               "--idle-exit", "2", "--no-progress", "--warnings", os.devnull]
        if keep is not None:
            cmd += ["--capture", str(keep / f"rvs{n}-per{per:g}-{predictor}-{verify}"),
                    "--overwrite"]  # a cell run again replaces its capture
        elif capture:
            cmd += ["--capture", str(Path(tmp) / "capture")]
        if web_port is not None:
            cmd += ["--web", str(web_port)]
        pki_dir = None
        if verify != "off":  # a pseudonym per RV (the ring has N RVs and the host)
            pki_dir = Path(tmp) / "pki"
            pki_init(pki_dir, n, 1.0, seed=f"obu-load-{n}", foreign=False)
        if verify in ("on", "on-demand"):  # on: every frame verified on arrival
            cmd += ["--verify", "enforce", "--trust", str(pki_dir), "--verify-policy",
                    "all" if verify == "on" else "on-demand"]
            if verify == "on-demand" and verify_workers is not None:
                cmd += ["--verify-workers", str(verify_workers)]
        obu = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True)
        try:
            if not wait_bound(ports, alive=lambda: obu.poll() is None):
                raise RuntimeError(f"obu did not start: {obu.communicate()[1][-500:]}")
            args = argparse.Namespace(**DEFAULTS)
            args.to, args.host_to = ("127.0.0.1", ports[0]), ("127.0.0.1", ports[1])
            args.progress = False
            args.sign = str(pki_dir) if pki_dir is not None else None
            if sign_workers is not None:
                args.sign_workers = sign_workers
            if sign_lookahead is not None:
                args.sign_lookahead = sign_lookahead
            the_plan = plan(ring_table(n, seconds), ChannelConfig(per=per / 100.0), 1)
            late: list[float] = []
            cpu0, wall0 = cpu_seconds(obu.pid), time.monotonic()
            rve_cpu0, busy0 = time.process_time(), machine_busy_seconds()
            workers0 = children_cpu_seconds()  # the signing workers, reaped by replay()
            clients = WebClients(web_clients or 0, web_port) if web_port else None
            if clients is not None:
                clients.__enter__()
            counts = asyncio.run(replay(args, the_plan, late))
            rve_cpu1, busy1 = time.process_time(), machine_busy_seconds()
            workers_cpu = children_cpu_seconds() - workers0
            cpu1, wall1 = cpu_seconds(obu.pid), time.monotonic()
            _, err = obu.communicate(timeout=120)
            if clients is not None:
                clients.__exit__(None, None, None)
        finally:
            if obu.poll() is None:
                obu.kill()
    lines = [ln for ln in err.splitlines() if ln.startswith('{"obu"')]
    if not lines:
        raise RuntimeError(f"obu gave no counters: {err[-500:]}")
    c = json.loads(lines[-1])["obu"]
    sent = counts["sent"] + counts["host"]
    got = c.get("transport_frames", 0)
    wall = wall1 - wall0
    # the RVE's signing before its clock started (--sign-lookahead): not the run's
    lead, prep = counts.get("sign_ahead_lead_s", 0.0), counts.get("sign_ahead_prepare_cpu_s", 0.0)
    run_wall = wall - lead
    late_ms = np.array(late) * 1e3 if late else np.zeros(1)
    return {"rvs": n, "per": per, "predictor": predictor, "verify": verify,
            "verify_workers": verify_workers,
            "web_clients": web_clients,
            "web_states_received": clients.received if web_port else None,
            "socket_loss": sent - got, "frames_sent": sent,
            "tick_ms_p50": c.get("tick_ms_p50"), "tick_ms_p99": c.get("tick_ms_p99"),
            "tick_ms_max": c.get("tick_ms_max"), "deadline_misses": c.get("deadline_misses", 0),
            "ticks": c.get("ticks", 0),
            # arrival to decision: the RV messages', and the host frames' (a tick's own)
            "lag_ms_p99": c.get("lag_ms_p99"), "host_lag_ms_p99": c.get("host_lag_ms_p99"),
            "cpu_percent": round(100.0 * (cpu1 - cpu0) / run_wall, 1),
            "verify_counters": {k: v for k, v in sorted(c.items())
                                if k.startswith("verify_")},
            "ondemand_counters": {k: v for k, v in sorted(c.items())
                                  if k.startswith("ondemand_")},
            "signed": counts.get("signed", 0),
            "signed_with_certificate": counts.get("with_certificate", 0),
            "signed_per_s": round(counts.get("signed", 0) / run_wall, 1),
            "rve_cpu_percent": round(100.0 * (rve_cpu1 - rve_cpu0 - prep) / run_wall, 1),
            "sign_ahead_lead_s": lead,
            "sign_workers": (args.sign_workers if pki_dir is not None else None),
            "sign_lookahead_s": (args.sign_lookahead if pki_dir is not None else None),
            "rve_workers_cpu_percent": round(100.0 * workers_cpu / wall, 1),
            **{k: counts[k] for k in ("sign_ahead_batches", "sign_ahead_waits",
                                      "sign_ahead_wait_ms_max") if k in counts},
            "rve_late_ms_p99": round(float(np.percentile(late_ms, 99)), 3),
            "rve_late_ms_max": round(float(late_ms.max()), 3),
            # everything else the machine ran meanwhile, in % of one core (contention)
            # (clamped at 0: the counters tick in 1/CLK_TCK s, so a quiet machine reads ±1 tick)
            "other_cpu_percent": max(0.0, round(100.0 * ((busy1 - busy0) - (cpu1 - cpu0)
                                                         - (rve_cpu1 - rve_cpu0)
                                                         - workers_cpu) / wall, 1))}


def verify_modes(spec: str) -> list[str]:
    """The --verify modes in order: "both" is off,on; each of off, on, signed."""
    modes = ["off", "on"] if spec == "both" else [m.strip() for m in spec.split(",")]
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        raise argparse.ArgumentTypeError(f"--verify: {', '.join(bad) or spec!r} is not one of "
                                         f"{', '.join(MODES)} or both")
    return list(dict.fromkeys(modes))


def add_ratios(rows: list[dict]) -> None:
    """Each row with verify on or signed gets its tick p99 and OBU CPU as ratios to the
    ``off`` row of the same cell (when there is one)."""
    off = {(r["rvs"], r["per"], r["predictor"]): r for r in rows if r["verify"] == "off"}
    for r in rows:
        base = off.get((r["rvs"], r["per"], r["predictor"]))
        if r["verify"] == "off" or base is None:
            continue
        r["vs_off"] = {
            "tick_p99_ratio": (round(r["tick_ms_p99"] / base["tick_ms_p99"], 2)
                               if base["tick_ms_p99"] else None),
            "cpu_ratio": (round(r["cpu_percent"] / base["cpu_percent"], 2)
                          if base["cpu_percent"] else None),
            "rve_cpu_ratio": (round(r["rve_cpu_percent"] / base["rve_cpu_percent"], 2)
                              if base["rve_cpu_percent"] else None)}


def _ondemand_cell(r: dict) -> str:
    """Verified (at once + from the queue, also late), deferred, skipped, stepped
    unverified: the frames of an on-demand row."""
    c = r.get("ondemand_counters") or {}
    if not c:
        return "-"
    vw = "" if r.get("verify_workers") is None else f"w{r['verify_workers']} "
    return (f"{vw}{c.get('ondemand_at_once', 0)}+{c.get('ondemand_deferred_ok', 0)}/"
            f"{c.get('ondemand_deferred', 0)}/{c.get('ondemand_skipped', 0)}/"
            f"{c.get('ondemand_unverified_stepped', 0)}")


def _verify_cell(r: dict) -> str:
    counters = r["verify_counters"]
    if not counters:
        return "-"
    ok = counters.get("verify_ok", 0)
    others = " ".join(f"{k.removeprefix('verify_')}={v}" for k, v in counters.items()
                      if k != "verify_ok")
    return f"ok={ok}" + (f" {others}" if others else "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--rvs", default="100,250,500")
    ap.add_argument("--per", default="0,50", help="PER values in %% (default 0,50)")
    ap.add_argument("--predictors", default="hgp,ca")
    ap.add_argument("--seconds", type=float, default=15.0, help="replay length per cell")
    ap.add_argument("--capture", action="store_true", help="the OBU also writes its capture")
    ap.add_argument("--keep", type=Path, metavar="DIR",
                    help="the OBU writes its capture into DIR/rvsN-perP-PREDICTOR-VERIFY and "
                         "it is kept (obu.ticks.jsonl has every tick's step time)")
    ap.add_argument("--verify", nargs="?", const="on", default="off", type=verify_modes,
                    metavar="MODES",
                    help="IEEE 1609.2: on (the RVE signs, the OBU runs --verify enforce "
                         "--verify-policy all: every frame on arrival), on-demand (--verify "
                         "enforce --verify-policy on-demand), off (plain UPER), signed "
                         "(signed, the OBU does not verify), a list such as off,on,on-demand, "
                         "or both (= off,on); --verify alone is on; default off")
    ap.add_argument("--web-clients", metavar="K,...",
                    help="the OBU serves its live view (obu run --web) and K clients read "
                         "every state it pushes, one row per K (e.g. 0,10: the same cell "
                         "with none and with ten connected, in one run)")
    ap.add_argument("--verify-workers", metavar="N,...",
                    help="obu run --verify-workers for the on-demand mode, one row per value "
                         "(default: obu run's own, 1)")
    ap.add_argument("--sign-workers", metavar="N,...",
                    help="rve run --sign-workers for the signed modes, one row per value "
                         "(default: rve run's own)")
    ap.add_argument("--sign-lookahead", type=float, metavar="S",
                    help="rve run --sign-lookahead for the signed modes; at least --seconds: "
                         "the whole run is signed before the RVE's clock starts")
    args = ap.parse_args(argv)
    workers = ([int(v) for v in args.sign_workers.split(",")] if args.sign_workers
               else [None])
    webs = ([int(v) for v in args.web_clients.split(",")] if args.web_clients else [None])
    vworkers = ([int(v) for v in args.verify_workers.split(",")] if args.verify_workers
                else [None])
    rows = []
    for n in (int(v) for v in args.rvs.split(",")):
        for per in (float(v) for v in args.per.split(",")):
            for p in args.predictors.split(","):
                for mode in args.verify:
                    for w in (workers if mode != "off" else [None]):
                        for vw in (vworkers if mode == "on-demand" else [None]):
                            for k in webs:
                                rows.append(measure(n, per, p, args.seconds, args.capture,
                                                    mode, k, args.keep, w, vw,
                                                    args.sign_lookahead))
                    if not args.json:
                        print(f"  done {n} RVs PER {per:g} % {p} verify {mode}",
                              file=sys.stderr)
    add_ratios(rows)
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print("OBU under load: UDP on 127.0.0.1, 10 Hz per RV, one OBU process"
          + (" writing its capture" if args.capture else "")
          + f", {os.cpu_count()} CPUs (other CPU %: what the rest of the machine ran meanwhile)")
    print(f"{'RVs':>5} {'PER %':>6} {'predictor':>9} {'verify':>9} {'wk':>2} "
          f"{'socket loss':>13} "
          f"{'tick p50':>9} {'tick p99':>9} {'tick max':>9} {'misses':>7} {'CPU %':>6} "
          f"{'p99 x':>6} {'CPU x':>6} {'RVE CPU %':>11} {'RVE late p99/max ms':>19} "
          f"{'signed/s':>8} {'waits':>5} {'other CPU %':>11}  {'on demand':>27}  verdicts")
    for r in rows:
        ratios = r.get("vs_off", {})
        tick_x, cpu_x = ratios.get("tick_p99_ratio"), ratios.get("cpu_ratio")
        wk = "-" if r["sign_workers"] is None else r["sign_workers"]
        rve_cpu = f"{r['rve_cpu_percent']:.0f}+{r['rve_workers_cpu_percent']:.0f}"
        print(f"{r['rvs']:>5} {r['per']:>6g} {r['predictor']:>9} {r['verify']:>9} {wk:>2} "
              f"{r['socket_loss']:>6}/{r['frames_sent']:<6} {r['tick_ms_p50']:>9.1f} "
              f"{r['tick_ms_p99']:>9.1f} {r['tick_ms_max']:>9.1f} {r['deadline_misses']:>7} "
              f"{r['cpu_percent']:>6.1f} "
              f"{f'{tick_x:.2f}' if tick_x is not None else '-':>6} "
              f"{f'{cpu_x:.2f}' if cpu_x is not None else '-':>6} "
              f"{rve_cpu:>11} "
              f"{r['rve_late_ms_p99']:>9.2f}/{r['rve_late_ms_max']:<9.2f} "
              f"{r['signed_per_s']:>8.0f} {r.get('sign_ahead_waits', '-'):>5} "
              f"{r['other_cpu_percent']:>11.1f}  {_ondemand_cell(r):>27}  {_verify_cell(r)}")
    for r in rows:
        if r["web_clients"] is not None:
            print(f"  web clients {r['web_clients']:>2} ({r['rvs']} RVs PER {r['per']:g} % "
                  f"{r['predictor']}): tick p99 {r['tick_ms_p99']:.1f} ms, states read "
                  f"{r['web_states_received']}")
    if any(r["verify"] == "on-demand" for r in rows):
        print("on demand: frames verified at once + from the queue / deferred / skipped "
              "(dropped from the queue unverified) / stepped unverified")
    if any("vs_off" in r for r in rows):
        print("p99 x, CPU x: the row's tick p99 and OBU CPU over those of the verify-off row "
              "of the same cell")
    for t in [r for r in rows if r["rvs"] == 500 and r["per"] == 50 and r["predictor"] == "hgp"]:
        ok = t["socket_loss"] == 0 and t["tick_ms_p99"] <= 50.0
        print(f"target: 500 RVs, hgp, PER 50 %, verify {t['verify']}: no socket loss and tick "
              f"p99 <= 50 ms: {'met' if ok else 'NOT met'} (loss {t['socket_loss']}, "
              f"p99 {t['tick_ms_p99']:.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
