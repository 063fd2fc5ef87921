"""HGP forecast cost in the OBU workload, before and after the fast path; PTE95 of the
selection-reuse settings.

The workload (cost): N remote vehicles (default 200) drive synthetic speed and heading
sinusoids; each 10 Hz tick every RV's BSM arrives with probability 1 − PER (the seeded
channel of ``catc.channel``) and every RV is asked ``predict(now)`` and ``predict(now + 2)``,
as the OBU does.  A forecast is made at most once per received BSM (``HgpPredictor``
caches it), so the cost that matters is the time per forecast.  The first 50 ticks fill the
windows and are not timed.  Variants, each on fresh predictors and the same data:

* ``before``: the forecast as it was computed before this work (kept in the code as
  ``HgpPredictor._make_forecast_reference``: window from the observation deque, bank
  selection at every forecast by batched ``np.linalg.solve``, SciPy posteriors).
* ``k=1``: the fast path with the old behaviour (``reselect_every=1``, no gap rule): the
  same forecasts to 1e-9 (tests/test_hgp.py).
* ``default``: the fast path with the shipped ``HgpConfig`` (selection reused between
  reselections, see docs/log/2026-11-22-hgp-model-persistency.md for the PTE95 this costs).
* ``batch``: ``default`` with ``forecast_many(rvs, now + 2)`` once per tick before the
  predictions (the stacked batch API); its per-forecast figures are per tick (tick time
  over forecasts made that tick, including every RV's two predictions).

Timing: each variant runs ``--repeat`` times; the forecasts are the same every time, so
each forecast's (or tick's) time is the best of the repeats, then the median, the 95th
percentile and the mean ("amortized") over forecasts are reported in µs.  Times include the
two ``predict`` calls of the RV that forecast (in ``batch``: of all RVs).  ``ms/tick@500``
scales the mean cost to 500 RVs (forecasts per tick × 500 / N × mean).

PTE95 (``--pte``): ``catc.evaluate`` on the shared OpenACC and NGSIM data, exactly what
``captures evaluate --per 0,50,80,90,95 --predictors hgp`` computes, for each
(``reselect_every``, ``reselect_gap_s``) in the sweep; relative changes against k = 1.

    python bench/hgp_forecast.py [--json] [--repeat N] [--rvs N] [--ticks N]
    python bench/hgp_forecast.py --pte [--json]
"""

from __future__ import annotations

import os

# One core, like the OBU: a multi-threaded BLAS only adds overhead on 31 × 31 systems.  This
# must run before numpy loads its BLAS; an explicit setting in the environment wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402

from catc.channel import bernoulli_received  # noqa: E402
from catc.predict.base import Observation  # noqa: E402
from catc.predict.hgp import HgpConfig, HgpPredictor, forecast_many  # noqa: E402

WARMUP = 50
DATA = Path(os.environ.get("CATC_SHARED_DATA",
                           Path(__file__).resolve().parents[2] / "shared" / "data"))
PTE_DATASETS = {"OpenACC": str(DATA / "openacc-zalazone"),
                "NGSIM": "ngsim:" + str(DATA / "ngsim-i80-pairs")}
PTE_PERS = (0, 50, 80, 90, 95)
#: (reselect_every, reselect_gap_s) for --pte; (1, inf) is the reference.
PTE_SWEEP = ((1, math.inf), (5, math.inf), (10, math.inf), (30, math.inf),
             (5, 0.25), (10, 0.25), (30, 0.25), (5, 0.35), (10, 0.35), (30, 0.35))
TARGET_US = 60.0
BUDGET_MS = 20.0


class ReferencePredictor(HgpPredictor):
    """The forecast computation from before the fast path (same predict and read)."""

    def _make_forecast(self, horizon: float):
        self.stats["selections"] += 1  # it selects at every forecast
        return self._make_forecast_reference(horizon)


def observation(i: int, t: float) -> Observation:
    """RV ``i``'s BSM at time ``t`` (the workload of the task: smooth speed and heading)."""
    return Observation(t, 20.0 * t, i * 1.0, 20.0 + 2.0 * math.sin(0.3 * t + i),
                       (90.0 + 10.0 * math.sin(0.1 * t + i)) % 360.0,
                       0.6 * math.cos(0.3 * t + i), 1.0 * math.cos(0.1 * t + i))


def run(factory, rvs: int, ticks: int, per: float, batch: bool) -> dict:
    """One pass of the workload: per-forecast (or, batched, per-tick) times in µs."""
    preds = [factory() for _ in range(rvs)]
    received = [bernoulli_received(0, i, ticks, per) for i in range(rvs)]
    times: list[float] = []  # per forecast, or per tick and forecast when batched
    weights: list[int] = []
    for k in range(ticks):
        t = k * 0.1
        for i, p in enumerate(preds):
            if received[i][k]:
                p.update(observation(i, t))
        if k < WARMUP:
            continue
        if batch:
            before = sum(p.stats["forecasts"] for p in preds)
            t0 = time.perf_counter()
            forecast_many(preds, t + 2.0)
            for p in preds:
                try:
                    p.predict(t)
                    p.predict(t + 2.0)
                except LookupError:
                    pass
            dt = time.perf_counter() - t0
            made = sum(p.stats["forecasts"] for p in preds) - before
            if made:
                times.append(dt * 1e6 / made)
                weights.append(made)
            continue
        for p in preds:
            before = p.stats["forecasts"]
            t0 = time.perf_counter()
            try:
                p.predict(t)
                p.predict(t + 2.0)
            except LookupError:
                pass
            dt = time.perf_counter() - t0
            made = p.stats["forecasts"] - before
            if made:
                times.append(dt * 1e6 / made)
                weights.append(made)
    forecasts = sum(p.stats["forecasts"] for p in preds)
    return {"times": times, "weights": weights,
            "selections_per_forecast": sum(p.stats["selections"] for p in preds)
            / max(forecasts, 1)}


def measure(factory, rvs: int, ticks: int, per: float, repeat: int, batch: bool) -> dict:
    """Best-of-``repeat`` statistics of :func:`run`."""
    runs = [run(factory, rvs, ticks, per, batch) for _ in range(repeat)]
    if len({len(r["times"]) for r in runs}) != 1:
        raise RuntimeError("the workload is not deterministic across repeats")
    best = np.min([r["times"] for r in runs], axis=0)
    weights = np.array(runs[0]["weights"])
    made = int(weights.sum())
    per_tick = made / (ticks - WARMUP)
    mean = float((best * weights).sum() / made)
    return {"forecasts_per_tick": per_tick,
            "median_us": float(np.median(best)), "p95_us": float(np.percentile(best, 95)),
            "mean_us": mean, "est_ms_per_tick_500": per_tick * 500 / rvs * mean / 1e3,
            "selections_per_forecast": runs[0]["selections_per_forecast"]}


def cost(args) -> dict:
    default = HgpConfig()
    old = replace(default, reselect_every=1, reselect_gap_s=math.inf)
    variants = {
        "before": (partial(ReferencePredictor, config=old), False),
        "k=1": (partial(HgpPredictor, config=old), False),
        "default": (partial(HgpPredictor, config=default), False),
        "batch": (partial(HgpPredictor, config=default), True),
    }
    res: dict = {"rvs": args.rvs, "ticks": args.ticks, "repeat": args.repeat,
                 "default_config": {"reselect_every": default.reselect_every,
                                    "reselect_gap_s": default.reselect_gap_s},
                 "per": {}}
    for per in (0.0, 0.5):
        rows = {}
        for name, (factory, batch) in variants.items():
            rows[name] = measure(factory, args.rvs, args.ticks, per, args.repeat, batch)
            print(f"  PER {per:.0%} {name}: {rows[name]['mean_us']:.1f} us/forecast",
                  file=sys.stderr)
        for name in variants:
            rows[name]["speedup_vs_before"] = rows["before"]["mean_us"] / rows[name]["mean_us"]
        res["per"][f"{100 * per:g}"] = rows
    return res


def pte(args) -> dict:
    from catc.evaluate import evaluate
    from hil.datasets import load

    out: dict = {}
    for name, spec in PTE_DATASETS.items():
        tables = load(spec)
        factories = {f"k={k} gap={g:g}": partial(
            HgpPredictor, config=HgpConfig(reselect_every=k, reselect_gap_s=g))
            for k, g in PTE_SWEEP}
        print(f"  {name}: {len(factories)} settings x {len(PTE_PERS)} PERs", file=sys.stderr)
        scores = evaluate(tables, factories, [p / 100 for p in PTE_PERS])
        out[name] = {s.predictor: {} for s in scores}
        for s in scores:
            out[name][s.predictor][f"{100 * s.per:g}"] = s.pte95_m
    return out


def print_cost(res: dict) -> None:
    print(f"HGP forecast cost, {res['rvs']} RVs, {res['ticks'] - WARMUP} timed ticks, best of "
          f"{res['repeat']} per forecast; default: reselect_every="
          f"{res['default_config']['reselect_every']}, reselect_gap_s="
          f"{res['default_config']['reselect_gap_s']:g}")
    for per, rows in res["per"].items():
        print(f"\nPER {per} %  ({rows['before']['forecasts_per_tick']:.0f} forecasts per tick)")
        print(f"{'variant':<10}{'median us':>11}{'p95 us':>9}{'mean us':>9}{'x before':>10}"
              f"{'sel/fc':>8}{'ms/tick@500':>13}")
        for name, r in rows.items():
            print(f"{name:<10}{r['median_us']:>11.1f}{r['p95_us']:>9.1f}{r['mean_us']:>9.1f}"
                  f"{r['speedup_vs_before']:>10.1f}{r['selections_per_forecast']:>8.2f}"
                  f"{r['est_ms_per_tick_500']:>13.1f}")
    r50 = res["per"]["50"]
    for name in ("default", "batch"):
        mean = r50[name]["mean_us"]
        print(f"target <= {TARGET_US:.0f} us/forecast at PER 50 %, {name}: {mean:.1f} us "
              f"({'met' if mean <= TARGET_US else 'MISSED'}); tick budget {BUDGET_MS:.0f} ms at "
              f"500 RVs: {r50[name]['est_ms_per_tick_500']:.1f} ms")


def print_pte(res: dict) -> None:
    for name, rows in res.items():
        base = rows[f"k=1 gap={math.inf:g}"]
        print(f"\n{name}: PTE95 [m] (change against k=1)")
        print(f"{'setting':<16}" + "".join(f"{f'PER {p}%':>17}" for p in PTE_PERS))
        for setting, vals in rows.items():
            cells = []
            for p in PTE_PERS:
                v, b = vals[f"{p:g}"], base[f"{p:g}"]
                rel = f"({100 * (v / b - 1):+.1f}%)" if b > 0 else ""
                cells.append(f"{v:>8.3f}{rel:>9}")
            print(f"{setting:<16}" + "".join(cells))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--repeat", type=int, default=3, help="runs per variant (best kept)")
    ap.add_argument("--rvs", type=int, default=200, help="remote vehicles")
    ap.add_argument("--ticks", type=int, default=300, help="10 Hz ticks (first 50 untimed)")
    ap.add_argument("--pte", action="store_true",
                    help="PTE95 of the reselection settings on the shared data instead")
    args = ap.parse_args(argv)
    if args.ticks <= WARMUP:
        ap.error(f"--ticks must exceed the {WARMUP} warm-up ticks")
    res = pte(args) if args.pte else cost(args)
    res["platform"] = {"python": platform.python_version(), "numpy": np.__version__,
                       "scipy": scipy.__version__, "machine": platform.machine(),
                       "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS")}
    if args.json:
        print(json.dumps(res, indent=2))
    elif args.pte:
        print_pte({k: v for k, v in res.items() if k != "platform"})
    else:
        print_cost(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
