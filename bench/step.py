"""Time of one CA-TC step (``catc.cam.ContextAwareMap.step`` with the safety apps) on one core.

Scene: a straight six-lane road (three lanes each way, 3.6 m wide) with the HV in the
middle lane at 25 m/s.  N remote vehicles are spread evenly over ±300 m around it (the
DSRC safety range), two thirds going the HV's way and one third oncoming, each with its
own speed (18–32 m/s), a slow speed oscillation (±1.5 m/s, 0.3 rad/s) and small heading
wobble, so every predictor has something to learn.  Every RV sends a BSM at 10 Hz and
each message is lost with probability 50 % (``catc.channel``, seeded): each tick about
half the RVs have no fresh BSM and are predicted, with ``hgp`` by default — the issue's
"half of them without a fresh BSM and predicted with hgp".  TemporaryIDs are CRC-32s of
names, as the RVE sends them.  The peer rows are the same run with ``hgp-objects``, the
HGP as one ``HgpPredictor`` object per RV instead of the rows of one ``HgpTable`` (the same
numbers, bit for bit: tests/test_hgp_table.py; "p99 vs" is the table's p99 over it), and
with ``ca`` (constant acceleration): what tracking costs without a learned predictor.

Warm-up ticks (``--warmup``, default 80: the HGP windows of 30 received samples fill at
PER 50 % after ~6 s) are run and not timed; then ``--ticks`` steps are timed one by one
with ``time.perf_counter``.  The BSMs of every tick are built before timing.

    python bench/step.py [--json] [--rvs 50,200,500] [--ticks 100] [--warmup 80]
                         [--predictors hgp,hgp-objects,ca] [--per 0.5] [--profile N]

``--per 0`` is the OBU load bench's case (``bench/obu_load.py --per 0``): every RV fresh
at every tick, every window full and regular.

Targets (issue 30; issue 17's were 25 and 50 ms): p99 at most 20 ms per step at 500 RVs
with hgp and 40 ms at 1,000, one core, PER 50 %.  The process collects garbage as
``obu run`` does (:mod:`hil.gcpolicy`): after each step, not inside it; those passes are
timed apart and printed under the table.
"""

from __future__ import annotations

import os

# One core, like the OBU: this must run before numpy loads its BLAS.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from catc.apps import SafetyApps  # noqa: E402
from catc.bsm import BSM  # noqa: E402
from catc.cam import CamConfig, ContextAwareMap  # noqa: E402
from catc.channel import bernoulli_received  # noqa: E402
from catc.geo import EnuFrame  # noqa: E402
from catc.replay import temp_id  # noqa: E402
from hil.gcpolicy import GcPolicy  # noqa: E402

ORIGIN = (46.89, 16.84, 0.0)
LANE = 3.6
PER = 0.5
DT = 0.1
TARGETS = ((500, 20.0), (1000, 40.0))  # (RVs, p99 ms), at PER 50 %
#: The HGP with one HgpPredictor object per RV (CamConfig.batched=False): the "before"
#: of the HGP table (issue 30), for --predictors hgp,hgp-objects,ca.
OBJECTS = "hgp-objects"


def scene(n: int, ticks: int, seed: int = 0) -> list[tuple[float, BSM, list[BSM]]]:
    """(now, host BSM, received RV BSMs) for every tick; see the module docstring."""
    rng = np.random.default_rng(seed)
    frame = EnuFrame(*ORIGIN)
    t = np.arange(ticks) * DT
    # HV: middle lane of the northbound side (x = 0), 25 m/s.
    hv_y = 25.0 * t
    # RVs: evenly over ±300 m, lanes -1, 0, +1 (northbound) or +3, +4, +5 (southbound).
    s0 = np.linspace(-300.0, 300.0, n) + rng.uniform(-2.0, 2.0, n)
    onc = (np.arange(n) % 3) == 2
    lane = np.where(onc, rng.integers(3, 6, n), rng.integers(-1, 2, n))
    v0 = rng.uniform(18.0, 32.0, n)
    ph = rng.uniform(0, 2 * math.pi, n)
    sign = np.where(onc, -1.0, 1.0)
    # speed, heading wobble and position (integrated in closed form)
    speed = v0[None, :] + 1.5 * np.sin(0.3 * t[:, None] + ph[None, :])
    along = v0[None, :] * t[:, None] - 5.0 * (np.cos(0.3 * t[:, None] + ph) - np.cos(ph))
    wob = 0.3 * np.sin(0.5 * t[:, None] + ph[None, :])  # lateral wobble (m)
    x = lane[None, :] * LANE + wob
    y = s0[None, :] + sign[None, :] * along
    heading = np.where(onc, 180.0, 0.0)[None, :] + np.degrees(
        np.arctan2(0.15 * np.cos(0.5 * t[:, None] + ph), speed))
    accel = 0.45 * np.cos(0.3 * t[:, None] + ph[None, :])
    yaw = np.degrees(-0.075 * np.sin(0.5 * t[:, None] + ph) / speed)
    lat, lon, _ = frame.to_geodetic(x, y, 0.0)
    hv_lat, hv_lon, _ = frame.to_geodetic(np.zeros(ticks), hv_y, 0.0)
    received = np.array([bernoulli_received(seed, i, ticks, PER) for i in range(n)]).T
    # TemporaryIDs as the RVE makes them (CRC-32 of a name): spread over 32 bits.  Ids
    # 1..N would put vehicles 0.6 m apart one bit apart, and the CAM would drop ~15 % of
    # their messages as bit-flipped copies (the shadow check) and create tracks late.
    ids = [temp_id(f"rv{i}") for i in range(n)]
    out = []
    for k in range(ticks):
        sm = round(t[k] * 1000.0) % 60_000
        host = BSM(msg_cnt=k % 128, temp_id=0xFFFFFFFF, sec_mark=sm, lat=float(hv_lat[k]),
                   lon=float(hv_lon[k]), speed=25.0, heading=0.0, accel_long=0.0,
                   length=4.8, width=1.9)
        msgs = [BSM(msg_cnt=k % 128, temp_id=ids[i], sec_mark=sm, lat=float(lat[k, i]),
                    lon=float(lon[k, i]), speed=float(speed[k, i]),
                    heading=float(heading[k, i] % 360.0), accel_long=float(accel[k, i]),
                    yaw_rate=float(yaw[k, i]), length=4.8, width=1.9)
                for i in np.flatnonzero(received[k])]
        out.append((float(t[k]), host, msgs))
    return out


def run(n: int, predictor: str, ticks: int, warmup: int,
        profile: int = 0) -> dict:
    data = scene(n, warmup + ticks)
    # The garbage collection of `obu run` (hil.gcpolicy): what exists now is frozen (the
    # scene's BSMs are the input, not the OBU's state: a daemon holds a tick's worth),
    # and collections run after the steps, not timed as a step (reported).
    policy = GcPolicy()
    objects = predictor == OBJECTS  # the HGP as one object per RV, not a table's rows
    cam = ContextAwareMap(CamConfig(predictor="hgp" if objects else predictor, origin=ORIGIN,
                                    batched=not objects), SafetyApps())
    for now, host, msgs in data[:warmup]:
        cam.step(now, host, msgs)
        policy.after_tick()
    policy.reset_counters()  # count the timed steps' collections only
    times, fresh, tracked = [], [], []
    prof = cProfile.Profile() if profile else None
    for now, host, msgs in data[warmup:]:
        if prof:
            prof.enable()
        t0 = time.perf_counter()
        snap = cam.step(now, host, msgs)
        times.append(time.perf_counter() - t0)
        policy.after_tick()
        if prof:
            prof.disable()
        fresh.append(float(np.mean(snap.fresh)) if len(snap) else 0.0)
        tracked.append(len(snap))
    if prof:
        print(f"\n--- profile: {n} RVs, {predictor} ---", file=sys.stderr)
        pstats.Stats(prof, stream=sys.stderr).sort_stats("tottime").print_stats(profile)
    policy.restore()
    ms = np.array(times) * 1e3
    return {"rvs": n, "predictor": predictor, "ticks": ticks,
            "step_ms_median": round(float(np.median(ms)), 3),
            "step_ms_p99": round(float(np.percentile(ms, 99)), 3),
            "step_ms_max": round(float(ms.max()), 3),
            "tracked_mean": round(float(np.mean(tracked)), 1),
            **policy.counters(),
            "fresh_fraction": round(float(np.mean(fresh)), 3)}


def main(argv: list[str] | None = None) -> int:
    global PER
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--rvs", default="50,200,500", help="RV counts (default 50,200,500)")
    ap.add_argument("--ticks", type=int, default=100, help="timed steps per run")
    ap.add_argument("--warmup", type=int, default=80, help="untimed steps first")
    ap.add_argument("--predictors", default="hgp,hgp-objects,ca",
                    help="first is the target's; hgp-objects: the HGP as one object per RV "
                         "(default hgp,hgp-objects,ca)")
    ap.add_argument("--per", type=float, default=PER,
                    help="packet error rate of the scene, 0..1 (default 0.5)")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="cProfile the timed steps, print the top N functions to stderr")
    args = ap.parse_args(argv)
    if not 0.0 <= args.per < 1.0:
        ap.error(f"--per must be in [0, 1), got {args.per}")
    PER = args.per
    try:
        sizes = [int(v) for v in args.rvs.split(",")]
    except ValueError:
        ap.error(f"--rvs: not a list of integers: {args.rvs!r}")
    predictors = args.predictors.split(",")
    rows = []
    for n in sizes:
        for p in predictors:
            rows.append(run(n, p, args.ticks, args.warmup, args.profile))
            if not args.json:
                print(f"  done {n} RVs {p}", file=sys.stderr)
    main_p = predictors[0]
    by = {(r["rvs"], r["predictor"]): r for r in rows}
    result = {
        "predictor": main_p,
        "step_ms_median": {str(n): by[(n, main_p)]["step_ms_median"] for n in sizes},
        "step_ms_p99": {str(n): by[(n, main_p)]["step_ms_p99"] for n in sizes},
        "rows": rows,
        "per": PER,
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    peer = predictors[1] if len(predictors) > 1 else None
    print(f"CA-TC step time, one core, PER {PER:.0%} (≈ {PER:.0%} of the RVs predicted "
          "each tick)")
    print(f"{'RVs':>5} {'predictor':>11} {'median ms':>10} {'p99 ms':>8} {'max ms':>8} "
          f"{'fresh':>6}" + (f" {'p99 vs ' + peer:>12}" if peer else ""))
    for r in rows:
        ratio = ""
        if peer:
            base = by[(r["rvs"], peer)]["step_ms_p99"]
            ratio = f" {r['step_ms_p99'] / base:>11.1f}x"
        print(f"{r['rvs']:>5} {r['predictor']:>11} {r['step_ms_median']:>10.2f} "
              f"{r['step_ms_p99']:>8.2f} {r['step_ms_max']:>8.2f} {r['fresh_fraction']:>6.2f}"
              + ratio)
    for rvs, limit in TARGETS if PER == 0.5 else ():
        target = by.get((rvs, main_p))
        if target:
            verdict = "met" if target["step_ms_p99"] <= limit else "NOT met"
            print(f"target: p99 <= {limit:g} ms at {rvs} RVs with {main_p}: {verdict} "
                  f"({target['step_ms_p99']:.1f} ms, {target['step_ms_p99'] / limit:.2f}x)")
    # hil.gcpolicy: every collection runs after a tick, outside the step; shown here
    print("garbage collections after ticks (not in the step times): "
          + ", ".join(f"{r['rvs']} {r['predictor']}: young {r['gc_young_ms_mean']:.2f} ms "
                      f"mean, {r['gc_young_ms_max']:.2f} max"
                      + (f", {r['gc_full']} full of max {r['gc_full_ms_max']:.1f} ms"
                         if r["gc_full"] else "") for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
