"""Misbehavior detection on honest traffic: every finding and quarantine is a false positive.

No vehicle misbehaves in a replayed dataset, so whatever ``catc.mbd`` finds there is a
false positive, and a quarantine costs the host real warnings.  For each dataset (default:
the dense NGSIM I-80 scene, ``scene:ngsim:../shared/data/ngsim-i80-pairs``, 45 RVs, and
``scenario:highway-braking``) this replays the RVE's plan (``catc.replay.plan``, PER 0 by
default, seed 0) into a :class:`catc.mbd.MisbehaviorDetector` exactly as ``obu run --mbd``
feeds it (``obu.frames.Frames.misbehaves``):

* every RV frame, through UPER encode and decode, is observed on arrival with the host's
  clock and position of the newest host frame (the plan's order: RV frames before the
  host frame of the same instant; before the first host frame nothing is checked);
* a sender in quarantine has that frame dropped, its queued frames too, and its track
  removed from the map (:meth:`catc.cam.ContextAwareMap.drop`);
* the host frame steps a :class:`catc.cam.ContextAwareMap` (predictor ``ca``, every safety
  app) with the frames due (:func:`catc.replay.split_due`).

It prints the findings by check and by vehicle (the JSON has each vehicle's first finding,
its time, distance and place from the host), the reports (findings past the reporting
threshold, :attr:`catc.mbd.MisbehaviorDetector.reports`), each quarantined vehicle (its
first finding, how far from the host, how long it stayed in quarantine, frames dropped),
and the warnings the quarantines cost: the same map fed every frame (no MBD) against the map
with MBD, warning ticks (tick x vehicle) and warning events per app.  ``--set KEY=VALUE``
changes an :class:`catc.mbd.MbdConfig` threshold, to tune the detector against these
numbers.  An offline pass over both datasets takes ~15 s.

``--live`` runs the same through the daemons instead (``obu run --verify off --mbd
--predictor ca`` and ``rve run --speed S``, UDP on 127.0.0.1, ~20 s per dataset at
``--speed 4``) and reads the capture: ``obu.mbd.jsonl`` (findings), ``obu.mbr.jsonl``
(reports), ``obu.rx.jsonl`` (frames with status ``quarantined``) and
``obu.counters.json`` (``mbd_quarantined``).
The two should agree up to the UDP arrival order and the live host-freshness window
(0.5 s of wall clock).

``--hosts K`` replaces each scene's one host by K drawn at random (``--seed``) from every
vehicle of its files, and prints their totals: what it finds on honest traffic should
not rest on one host (24 hosts, seed 7: docs/log/2026-11-28-mbd-in-path.md).

    python bench/mbd_honest.py [--json] [--dataset SPEC ...] [--per P] [--seed N]
        [--set KEY=VALUE ...] [--no-apps] [--live [--speed X]] [--hosts K]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("CATC_SHARED_DATA", REPO.parent / "shared" / "data"))
DEFAULT_DATASETS = (f"scene:ngsim:{SHARED / 'ngsim-i80-pairs'}", "scenario:highway-braking")
#: As obu.frames.Frames.HOST_FRESH_S: an older host frame is no position for the checks.
HOST_FRESH_S = 0.5


def mbd_config(settings: list[str]):
    """:class:`catc.mbd.MbdConfig` with ``KEY=VALUE`` overrides (values of the field's type)."""
    from catc.mbd import MbdConfig

    base = MbdConfig()
    kinds = {f.name: type(getattr(base, f.name)) for f in dataclasses.fields(base)}
    changes = {}
    for s in settings:
        key, sep, value = s.partition("=")
        if not sep or key not in kinds:
            raise SystemExit(f"mbd_honest: --set {s!r}: expected KEY=VALUE with KEY one of "
                             f"{', '.join(kinds)}")
        kind = kinds[key]
        changes[key] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return dataclasses.replace(base, **changes)


def _missing(spec: str) -> str | None:
    """Why ``spec``'s data is absent (a path under ../shared/data), or None."""
    path = spec.split("?", 1)[0].rsplit(":", 1)[-1]
    if spec.startswith("scenario:") or Path(path).exists():
        return None
    return f"{path} not present (set CATC_SHARED_DATA)"


def host_specs(spec: str, k: int, seed: int) -> list[str]:
    """``spec`` (a ``scene:INNER[?host=ID]``) with ``k`` hosts drawn at random (seeded)
    from every vehicle of INNER's files: so that what is measured on honest traffic does
    not rest on one host."""
    import random

    from hil.datasets import load_files

    inner = spec.split("?", 1)[0][len("scene:"):]
    ids = sorted({v for _, tabs in load_files(inner) for t in tabs for v in t.tracks
                  if "#" not in v}, key=lambda v: (len(v), v))
    return [f"scene:{inner}?host={h}" for h in random.Random(seed).sample(ids, min(k, len(ids)))]


def _hosts_summary(results: list[dict]) -> dict:
    """Totals over the hosts of ``--hosts``: frames, findings by check, reports, honest
    vehicles quarantined and at how many hosts."""
    checks: Counter = Counter()
    for r in results:
        checks.update(r["findings_by_check"])
    return {"hosts": len(results), "rv_frames": sum(r["rv_frames"] for r in results),
            "findings_by_check": dict(checks.most_common()),
            "reports": sum(r["reports"] for r in results),
            "quarantined_vehicles": sum(r["quarantined_vehicles"] for r in results),
            "hosts_with_a_quarantine": [r["host"] for r in results if r["quarantined_vehicles"]]}


def _scene_info(table) -> dict:
    """The run's host, RVs, duration and RVs within 300 m of the host (mean, max)."""
    from catc.datasets.scene import RADIUS_M, neighbours

    host = table.tracks[table.default_host]
    near = neighbours(table, table.default_host, RADIUS_M)
    return {"host": table.default_host, "rvs": len(table.tracks) - 1,
            "duration_s": round(float(host.t[-1] - host.t[0]), 3),
            "rvs_within_radius": {"mean": round(float(near.mean()), 2),
                                  "max": int(near.max())}}


def _quarantine_rows(times: dict[str, list[float]], first: dict[str, dict]) -> dict:
    """Per quarantined vehicle: its first finding and how long its frames were dropped."""
    out = {}
    for vid in sorted(times, key=lambda v: times[v][0]):
        ts = times[vid]
        f = first.get(vid, {})
        out[vid] = {"first_finding": f.get("check"), "at_s": f.get("at_s"),
                    "distance_m": f.get("distance_m"), "frames": len(ts),
                    "from_s": round(ts[0], 2), "to_s": round(ts[-1], 2),
                    "quarantined_s": round(ts[-1] - ts[0] + 0.1, 1)}
    return out


def offline(spec: str, config, per: float, seed: int, apps: bool) -> dict:
    """One dataset through the detector (and the map) as ``obu run --mbd`` runs it."""
    from hil.datasets import load_table

    t_start = time.perf_counter()
    out = measure(load_table(spec, None), config, per, seed, apps)
    return {"spec": spec, **out, "elapsed_s": round(time.perf_counter() - t_start, 2)}


def measure(table, config, per: float = 0.0, seed: int = 0, apps: bool = True) -> dict:
    """:func:`offline` on a table (its ``default_host`` the host)."""
    from catc.apps import SafetyApps
    from catc.cam import CamConfig, ContextAwareMap, SecMarkClock
    from catc.channel import ChannelConfig
    from catc.j2735 import decode_frame, encode_frame
    from catc.mbd import MisbehaviorDetector
    from catc.replay import plan, simulate, split_due, temp_id

    the_plan = plan(table, ChannelConfig(per=per / 100.0), seed)
    names = {temp_id(v): v for v in the_plan.vehicles}
    mbd = MisbehaviorDetector(config)

    def new_cam():
        return ContextAwareMap(CamConfig(predictor="ca", origin=table.origin), SafetyApps())

    cam = new_cam() if apps else None
    clock = SecMarkClock()
    last_host = None  # (bsm, its plan time, its time on the host's clock)
    t0 = None  # the first host frame's clock time
    pending = []
    findings: Counter = Counter()
    reported: Counter = Counter()
    by_vehicle: dict[str, Counter] = defaultdict(Counter)
    first: dict[str, dict] = {}
    q_times: dict[str, list[float]] = defaultdict(list)
    rv_frames = no_host = 0
    warn_ticks, warn_events = set(), Counter()
    for ev in the_plan.events:
        if ev["dropped"]:
            continue
        m = decode_frame(encode_frame(the_plan.bsm(ev)))
        if ev["host"]:
            now = clock(m.sec_mark)
            t0 = now if t0 is None else t0
            last_host = (m, float(ev["time"]), now)
            if cam is not None:
                due, pending = split_due(now, pending, cam.config.max_future_s)
                cam.apps.muted = mbd.muted(now)  # as obu.daemon.Obu.tick
                snap = cam.step(now, m, due)
                warn_ticks |= {(round(now - t0, 1), w.app, names.get(w.rv_id, w.rv_id))
                               for w in snap.warnings}
                warn_events.update(e.app for e in snap.events if e.kind == "start")
            continue
        rv_frames += 1
        if last_host is None:
            no_host += 1
            pending.append(m)
            continue
        hb, h_time, t = last_host
        fresh = float(ev["time"]) - h_time <= HOST_FRESH_S
        found = mbd.observe(m, t, hb.lat if fresh else None, hb.lon if fresh else None,
                            host_heading=hb.heading if fresh else None,
                            host_speed=hb.speed if fresh else None,
                            host_yaw_rate=hb.yaw_rate if fresh else None)
        vid = names.get(m.temp_id, f"{m.temp_id:08X}")
        reported.update(d.check for d in mbd.reports)
        for d in found:
            findings[d.check] += 1
            by_vehicle[vid][d.check] += 1
            first.setdefault(vid, {"check": d.check, "at_s": round(t - t0, 2),
                                   "distance_m": d.evidence.get("distance_m"),
                                   "along_m": d.evidence.get("along_m"),
                                   "across_m": d.evidence.get("across_m")})
        if mbd.quarantined(m.temp_id, t):
            q_times[vid].append(t - t0)
            pending = [p for p in pending if p.temp_id != m.temp_id]
            if cam is not None:
                cam.drop(m.temp_id)
            continue
        pending.append(m)
    out = {
        "table": table.name, **_scene_info(table), "per": per, "seed": seed,
        "rv_frames": rv_frames, "unchecked_before_host": no_host,
        "findings": sum(findings.values()), "findings_by_check": dict(findings.most_common()),
        "findings_by_vehicle": {v: dict(c) for v, c in sorted(by_vehicle.items())},
        "first_findings": first,
        "reports": sum(reported.values()), "reports_by_check": dict(reported.most_common()),
        "quarantined_frames": sum(len(v) for v in q_times.values()),
        "quarantined_vehicles": len(q_times),
        "quarantines": _quarantine_rows(q_times, first),
    }
    if cam is not None:
        out["warnings"] = _warnings_lost(the_plan, new_cam(), names, warn_ticks, warn_events,
                                         simulate)
    return out


def _warnings_lost(the_plan, cam, names, with_mbd: set, events_mbd: Counter,
                   simulate) -> dict:
    """The same plan through a map without MBD, against the run with it: per app, warning
    ticks (tick x vehicle) and warning events of each, and the ticks MBD lost, by vehicle."""
    base, events_base, t0 = set(), Counter(), None
    for snap in simulate(the_plan, cam):
        t0 = snap.t if t0 is None else t0
        base |= {(round(snap.t - t0, 1), w.app, names.get(w.rv_id, w.rv_id))
                 for w in snap.warnings}
        events_base.update(e.app for e in snap.events if e.kind == "start")
    out = {}
    for app in ("fcw", "eebl", "bsw", "lcw"):
        b = {k for k in base if k[1] == app}
        w = {k for k in with_mbd if k[1] == app}
        lost = Counter(k[2] for k in b - w)
        out[app] = {"ticks_without_mbd": len(b), "ticks_with_mbd": len(w),
                    "ticks_lost": len(b - w), "ticks_gained": len(w - b),
                    "events_without_mbd": events_base[app], "events_with_mbd": events_mbd[app],
                    "lost_by_vehicle": dict(lost.most_common())}
    return out


def live(spec: str, per: float, seed: int, speed: float) -> dict:
    """One dataset through ``rve run`` and ``obu run --verify off --mbd`` on loopback."""
    import socket

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO / "src"), *filter(None, [os.environ.get("PYTHONPATH")])])}
    bindir = Path(sys.executable).parent
    with tempfile.TemporaryDirectory(prefix="mbd_honest_") as tmp:
        cap = Path(tmp) / "cap"
        ports = []
        for _ in range(2):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.bind(("127.0.0.1", 0))
                ports.append(s.getsockname()[1])
        rv, host = (f"127.0.0.1:{p}" for p in ports)
        t_start = time.perf_counter()
        obu = subprocess.Popen(
            [str(bindir / "obu"), "run", "--listen", rv, "--host-listen", host,
             "--predictor", "ca", "--capture", str(cap), "--verify", "off", "--mbd",
             "--idle-exit", "3", "--no-progress"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            line = obu.stderr.readline()
            if "ready" not in line:
                raise SystemExit(f"mbd_honest: obu run did not start: {line.strip()}")
            subprocess.run(
                [str(bindir / "rve"), "run", "--dataset", spec, "--to", rv, "--host-to", host,
                 "--per", str(per), "--seed", str(seed), "--speed", str(speed),
                 "--capture", str(cap), "--no-progress"],
                env=env, check=True, stdout=subprocess.DEVNULL)
            obu.wait(timeout=60)
        finally:
            if obu.poll() is None:
                obu.terminate()
                obu.wait()
        names = {tid: v for v, tid in json.loads((cap / "rve.config.json").read_text())
                 ["vehicles"].items()}
        counters = json.loads((cap / "obu.counters.json").read_text())
        counters = counters.get("obu", counters)
        findings: Counter = Counter()
        by_vehicle: dict[str, Counter] = defaultdict(Counter)
        for line in (cap / "obu.mbd.jsonl").read_text().splitlines():
            r = json.loads(line)
            findings[r["check"]] += 1
            by_vehicle[names.get(r["suspect"], r["suspect"])][r["check"]] += 1
        reported = Counter(json.loads(line)["check"] for line in
                           (cap / "obu.mbr.jsonl").read_text().splitlines())
        q: Counter = Counter()
        from hil.capture import read_rx

        for r in read_rx(cap):  # a quarantine, not a dropped copy (rx "why")
            if r.get("status") == "quarantined" and r.get("why", "quarantine") == "quarantine":
                q[names.get(r["id"], r["id"])] += 1
        return {"spec": spec, "speed": speed, "per": per, "seed": seed,
                "rv_frames": counters.get("frames_rv"),
                "findings": sum(findings.values()),
                "findings_by_check": dict(findings.most_common()),
                "findings_by_vehicle": {v: dict(c) for v, c in sorted(by_vehicle.items())},
                "reports": sum(reported.values()),
                "reports_by_check": dict(reported.most_common()),
                "quarantined_frames": sum(q.values()),
                "mbd_quarantined": counters.get("mbd_quarantined", 0),
                "quarantined_vehicles": len(q), "quarantined_frames_by_vehicle": dict(q),
                "elapsed_s": round(time.perf_counter() - t_start, 2)}


def _print(r: dict) -> None:
    size = (f"host {r['host']}, {r['rvs']} RVs, {r['duration_s']:g} s"
            if "host" in r else f"live at --speed {r['speed']:g}")
    near = r.get("rvs_within_radius")
    near = f"; RVs within 300 m mean {near['mean']:g}, max {near['max']}" if near else ""
    print(f"\n{r['spec']}  ({size}{near}; PER {r['per']:g} %, seed {r['seed']}; "
          f"{r['elapsed_s']:g} s)")
    print(f"  RV frames {r['rv_frames']}, findings {r['findings']}, reports {r['reports']}, "
          f"frames dropped in quarantine {r['quarantined_frames']}, vehicles quarantined "
          f"{r['quarantined_vehicles']}")
    for check, n in r["findings_by_check"].items():
        who = ", ".join(f"{v} {c[check]}" for v, c in r["findings_by_vehicle"].items()
                        if check in c)
        print(f"  {check:<22} {n:>5}   {who}")
    if r.get("quarantines"):
        print(f"  {'quarantined':<12} {'first finding':<20} {'at s':>6} {'dist m':>7} "
              f"{'for s':>6} {'frames':>6}")
        for vid, q in r["quarantines"].items():
            dist = "-" if q["distance_m"] is None else f"{q['distance_m']:.1f}"
            print(f"  {vid:<12} {q['first_finding'] or '-':<20} {q['at_s']:>6} {dist:>7} "
                  f"{q['quarantined_s']:>6} {q['frames']:>6}")
    elif r.get("quarantined_frames_by_vehicle"):
        print("  quarantined frames: " + ", ".join(
            f"{v} {n}" for v, n in r["quarantined_frames_by_vehicle"].items()))
    if "warnings" in r:
        print(f"  {'warnings':<8} {'ticks no MBD':>12} {'with MBD':>9} {'lost':>5} "
              f"{'events no MBD':>14} {'with MBD':>9}  lost ticks by vehicle")
        for app, w in r["warnings"].items():
            lost = ", ".join(f"{v} {n}" for v, n in w["lost_by_vehicle"].items())
            print(f"  {app:<8} {w['ticks_without_mbd']:>12} {w['ticks_with_mbd']:>9} "
                  f"{w['ticks_lost']:>5} {w['events_without_mbd']:>14} "
                  f"{w['events_with_mbd']:>9}  {lost}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--dataset", action="append", metavar="SPEC",
                    help="dataset spec, repeatable (default: the NGSIM I-80 scene and "
                         "scenario:highway-braking)")
    ap.add_argument("--per", type=float, default=0.0, help="packet error rate, %% (default 0)")
    ap.add_argument("--seed", type=int, default=0, help="loss pattern seed (default 0)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an MbdConfig threshold (repeatable), e.g. sa_safety_range_m=30")
    ap.add_argument("--no-apps", action="store_true",
                    help="skip the map and the warnings lost (about half the time)")
    ap.add_argument("--live", action="store_true",
                    help="through rve run and obu run --mbd on loopback instead")
    ap.add_argument("--speed", type=float, default=4.0, help="--live replay speed (default 4)")
    ap.add_argument("--hosts", type=int, default=0, metavar="K",
                    help="for each scene: K hosts drawn at random (--seed) from its files' "
                         "vehicles instead, and their totals (offline; implies --no-apps)")
    args = ap.parse_args(argv)
    if args.live and args.set:
        ap.error("--set is offline only (obu run has no MbdConfig flags)")

    if args.live and args.hosts:
        ap.error("--hosts is offline only")
    config = mbd_config(args.set)
    results, skipped, hosts = [], {}, {}
    for spec in args.dataset or DEFAULT_DATASETS:
        why = _missing(spec)
        if why:
            skipped[spec] = why
            continue
        if args.hosts and spec.startswith("scene:"):
            rows = [offline(s, config, args.per, args.seed, False)
                    for s in host_specs(spec, args.hosts, args.seed)]
            hosts[spec.split("?", 1)[0]] = _hosts_summary(rows)
            results += rows
            continue
        results.append(live(spec, args.per, args.seed, args.speed) if args.live
                       else offline(spec, config, args.per, args.seed, not args.no_apps))
    out = {"mode": "live" if args.live else "offline", "datasets": results, "skipped": skipped,
           "hosts": hosts,
           "mbd_config_changes": dict(s.split("=", 1) for s in args.set),
           "mbd_config": dataclasses.asdict(config), "python": platform.python_version()}
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    changes = ", ".join(args.set) or "defaults"
    print(f"catc.mbd on honest traffic ({out['mode']}; MbdConfig {changes}): every finding "
          "is a false positive")
    for r in results:
        _print(r)
    for spec, s in hosts.items():
        print(f"\n{spec}: {s['hosts']} hosts drawn with seed {args.seed}, {s['rv_frames']} RV "
              f"frames: findings {s['findings_by_check']}, reports {s['reports']}, honest "
              f"vehicles quarantined {s['quarantined_vehicles']} (at hosts "
              f"{', '.join(s['hosts_with_a_quarantine']) or 'none'})")
    for spec, why in skipped.items():
        print(f"\n{spec}: skipped ({why})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
