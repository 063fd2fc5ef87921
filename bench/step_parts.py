"""Pieces of a CA-TC step, one core, each beside the code it replaced (issue 17, part 3).

Taken from ``bench/step.py``'s scene (500 RVs, PER 50 %) after its warm-up:

* ``forecast reads``: every forecast read of one tick (the RVs' now and now + 2 s answers
  that come from a GP forecast), by ``forecast.read`` one by one (what the snapshot did)
  and by ``forecast.read_many`` (what it does);
* ``KF step``: the Kalman filter's update arithmetic (``kalman._kf_step``) in Python and
  compiled (``kalman.compiled_kf_step``), on the states of that tick's KF branches;
* ``forecast finish``: ``hgp.stacked.finish_stack`` (switching, integration, position variance)
  on the biggest forecast batch of a tick; no "before" row: the numpy code it replaced is
  kept only as ``tests/test_hgp.py``'s reference (970 µs on e2495df,
  docs/log/2026-11-26-hgp-python-second-pass.md).

Best of ``--repeat`` runs each, µs per call of the whole piece and per item.

    python bench/step_parts.py [--json] [--rvs 500] [--repeat 7]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import step  # noqa: E402
from catc.apps import SafetyApps  # noqa: E402
from catc.cam import CamConfig, ContextAwareMap  # noqa: E402
from catc.predict.forecast import read, read_many  # noqa: E402
from catc.predict.hgp import stacked  # noqa: E402
from catc.predict.kalman import KalmanPredictor, _kf_step, compiled_kf_step  # noqa: E402


def best(fn, repeat: int) -> float:
    """Best wall time of ``fn()`` over ``repeat`` runs, µs."""
    fn()
    out = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t0)
    return out * 1e6


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--rvs", type=int, default=500)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args(argv)
    data = step.scene(args.rvs, 90)
    cam = ContextAwareMap(CamConfig(predictor="hgp", origin=step.ORIGIN), SafetyApps())
    for now, host, msgs in data[:89]:
        cam.step(now, host, msgs)
    batches = []  # the last tick's forecast batches, as finish_stack got them
    finish = stacked.finish_stack

    def keep(states, mean, var, start, grid):
        batches.append((states, mean.copy(), var.copy(), start.copy(), grid))
        return finish(states, mean, var, start, grid)

    stacked.finish_stack = keep
    now, host, msgs = data[89]
    cam.step(now, host, msgs)
    stacked.finish_stack = finish
    later = now + cam.config.horizon_s
    preds = [tr.predictor for tr in cam._table.tracks.values()]
    reads = [a for p in preds for a in p.plan_pair(now, later) if a.__class__ is tuple]
    kfs = [k for p in preds for k in p._branches.kin if isinstance(k, KalmanPredictor)]
    args_kf = [(0.2, k.q, k._r, k._p, k._east, k._north, k._east, k._north) for k in kfs]
    compiled = compiled_kf_step()
    big = max(batches, key=lambda b: len(b[0]))
    rows = [
        ("forecast reads", "read, one by one", len(reads),
         best(lambda: [read(f, t) for f, t in reads], args.repeat)),
        ("forecast reads", "read_many", len(reads),
         best(lambda: read_many(reads), args.repeat)),
        ("KF step", "Python", len(args_kf),
         best(lambda: [_kf_step(*a) for a in args_kf], args.repeat)),
        ("KF step", "compiled", len(args_kf),
         best(lambda: [compiled(*a) for a in args_kf], args.repeat)),
        ("forecast finish", "compiled passes", len(big[0]),
         best(lambda: finish(big[0], big[1].copy(), big[2].copy(), big[3], big[4]),
              args.repeat)),
    ]
    out = [{"piece": p, "way": w, "items": n, "us": round(us, 1),
            "us_per_item": round(us / max(n, 1), 3)} for p, w, n, us in rows]
    if args.json:
        print(json.dumps({"rvs": args.rvs, "rows": out}, indent=1))
        return 0
    print(f"pieces of one CA-TC step, {args.rvs} RVs, PER 50 %, one core (best of "
          f"{args.repeat})")
    print(f"{'piece':16s} {'way':18s} {'items':>6s} {'us':>9s} {'us/item':>8s}")
    for r in out:
        print(f"{r['piece']:16s} {r['way']:18s} {r['items']:>6d} {r['us']:>9.1f} "
              f"{r['us_per_item']:>8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
