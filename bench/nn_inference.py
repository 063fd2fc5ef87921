"""Inference cost of the neural baselines next to the HGP's: per forecast and per OBU tick.

Per forecast: ``--rvs`` remote vehicles of ``bench/step.py``'s scene (a six-lane road,
speeds 18-32 m/s with oscillations, PER 50 %) are fed their first 6 s of received BSMs;
then the forecast each one needs after its last BSM (3 s ahead at 0.1 s steps, what the
OBU asks for its 2 s prediction horizon) is made

* alone (one predictor per call: what a predictor costs on its own), and
* stacked, all RVs in one call (``catc.predict.prepare_at``: what the OBU's CA-TC and the
  sweep do at every tick; per forecast = call time / RVs).

Each is timed ``--repeat`` times on the same windows; the best time of each forecast (or
call) is kept, then the median over forecasts is printed.  ``hgp-d`` and the closed-form
kinematic models (``ca``) have no stacked form; theirs is the cost of ``predict``.

Per OBU tick: ``bench/step.py``'s run (``ContextAwareMap.step`` with the safety apps, one
core) at ``--tick-rvs`` RVs (default 200), median and p99 ms, and the ratio to ``hgp``.

    python bench/nn_inference.py [--json] [--rvs 100] [--tick-rvs 200] [--repeat 5]
                                 [--predictors ae,ae-d,lstm,lstm-d,hgp,hgp-d,ca]

Peer: the HGP (``hgp``) in the same run; the OBU's tick budget is the 100 ms BSM period.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from catc.geo import EnuFrame  # noqa: E402
from catc.predict import STACKED, available, make_predictor, prepare_at  # noqa: E402
from catc.predict.base import Observation  # noqa: E402
from step import ORIGIN, scene  # noqa: E402
from step import run as tick_run  # noqa: E402

FEED_TICKS = 60


def fed(name: str, data, frame: EnuFrame, n: int) -> tuple[list, float]:
    """One predictor per RV, fed the RV's received BSMs of the first FEED_TICKS ticks."""
    preds = {i + 1: make_predictor(name) for i in range(n)}
    now = 0.0
    for now, _host, msgs in data[:FEED_TICKS]:
        for m in msgs:
            x, y, _ = frame.to_enu(m.lat, m.lon, 0.0)
            preds[m.temp_id].update(Observation(now, float(x), float(y), m.speed, m.heading,
                                                m.accel_long or 0.0, m.yaw_rate or 0.0))
    return list(preds.values()), now


def per_forecast(name: str, n: int, repeat: int) -> dict:
    data = scene(n, FEED_TICKS)
    frame = EnuFrame(*ORIGIN)
    preds, now = fed(name, data, frame, n)
    t = now + 3.0  # every RV forecasts 3 s on from its last BSM or more
    alone = np.full(n, math.inf)
    stacked = math.inf
    for _ in range(repeat):
        for i, p in enumerate(preds):
            if hasattr(p, "_forecast"):
                p._forecast = None
            t0 = time.perf_counter()
            if name in STACKED:
                prepare_at([(p, t)])
            else:
                p.predict(t)
            alone[i] = min(alone[i], time.perf_counter() - t0)
        if name in STACKED:
            for p in preds:
                p._forecast = None
            t0 = time.perf_counter()
            made = prepare_at([(p, t) for p in preds])
            stacked = min(stacked, time.perf_counter() - t0)
            assert made == n, (name, made)
    return {"predictor": name, "rvs": n,
            "alone_us": round(float(np.median(alone)) * 1e6, 1),
            "stacked_us": None if math.isinf(stacked) else round(stacked / n * 1e6, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--rvs", type=int, default=100, help="RVs for the per-forecast cost")
    ap.add_argument("--tick-rvs", type=int, default=200, help="RVs of the OBU tick")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--ticks", type=int, default=60, help="timed OBU ticks")
    ap.add_argument("--predictors", default="ae,ae-d,lstm,lstm-d,hgp,hgp-d,ca")
    args = ap.parse_args(argv)
    names = args.predictors.split(",")
    missing = [n for n in names if n not in available()]
    if missing:
        print(f"nn_inference: not available here: {', '.join(missing)} (the neural ones need "
              "pip install 'catc-hil[nn]')", file=sys.stderr)
        return 2
    rows = []
    for name in names:
        row = per_forecast(name, args.rvs, args.repeat)
        tick = tick_run(args.tick_rvs, name, args.ticks, 80)
        row.update({"tick_rvs": args.tick_rvs, "tick_ms_median": tick["step_ms_median"],
                    "tick_ms_p99": tick["step_ms_p99"]})
        rows.append(row)
        if not args.json:
            print(f"  done {name}", file=sys.stderr)
    by = {r["predictor"]: r for r in rows}
    peer = by.get("hgp")
    for r in rows:
        r["tick_vs_hgp"] = round(r["tick_ms_median"] / peer["tick_ms_median"], 2) \
            if peer else None
        r["alone_vs_hgp"] = round(r["alone_us"] / peer["alone_us"], 2) if peer else None
    if args.json:
        print(json.dumps({"rows": rows, "python": platform.python_version(),
                          "machine": platform.machine()}, indent=1))
        return 0
    print(f"Forecast cost (3 s ahead, {args.rvs} RVs, best of {args.repeat}, median) and "
          f"OBU tick at {args.tick_rvs} RVs, PER 50 %, one core")
    print(f"{'predictor':>9} {'alone µs':>9} {'vs hgp':>7} {'stacked µs':>11} "
          f"{'tick ms med':>12} {'tick p99':>9} {'vs hgp':>7}")
    for r in rows:
        stacked = "-" if r["stacked_us"] is None else f"{r['stacked_us']:.1f}"
        print(f"{r['predictor']:>9} {r['alone_us']:>9.1f} {r['alone_vs_hgp'] or 0:>6.2f}x "
              f"{stacked:>11} {r['tick_ms_median']:>12.2f} {r['tick_ms_p99']:>9.2f} "
              f"{r['tick_vs_hgp'] or 0:>6.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
