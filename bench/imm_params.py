"""IMM parameters chosen by trips: PTE95 of ``ImmPredictor`` settings next to the KF on the
HGP bank's training trips (the four OpenACC dynamic runs and the NGSIM pairs), or on the
held-out OpenACC handling runs (``--holdout``), at PER 30 and 90 %, seed 0.

    python bench/imm_params.py [--json] [--holdout] [--workers 2]
                               [--grid '[{"q_cv": 8, "q_ct": 8}, "kf"]']

The shipped PSDs (``catc.predict.imm.Q_CV``, ``Q_CT``) are the setting with the lowest
mean ratio to the KF's PTE95 over the four training cells (docs/log/2026-11-25-imm.md).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from catc.channel import bernoulli_received
from catc.evaluate import replay_track
from catc.predict import make_predictor
from catc.predict.imm import ImmPredictor
from hil.datasets import load

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
OA = DATA / "openacc-zalazone"
TRAIN = [str(OA / f) for f in ("short_setting_dynamic_part1.csv",
                               "short_setting_dynamic_part22.csv",
                               "long_setting_dynamic_part16.csv", "mixed_dynamic_part7.csv")]
TRAIN.append("ngsim:" + str(DATA / "ngsim-i80-pairs"))
HOLDOUT = [str(OA / "short_setting_handling_part36.csv"), str(OA / "no_ACC_handling_part40.csv")]
GRID = [{"q_cv": 0.5, "q_ct": 0.5}, {"q_cv": 2.0, "q_ct": 2.0}, {"q_cv": 8.0, "q_ct": 8.0}, "kf"]
PERS = (0.3, 0.9)


def _errors(job):
    spec, setting, per = job
    p = make_predictor("kf") if setting == "kf" else ImmPredictor(**setting)
    errs = [replay_track(tr, p, bernoulli_received(0, f"{t.name}/{tr.vehicle_id}", len(tr), per))
            for t in load(spec) for tr in t.tracks.values()]
    e = np.concatenate(errs)
    return spec, json.dumps(setting), per, e[~np.isnan(e)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--holdout", action="store_true")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--grid", type=json.loads, default=GRID)
    args = ap.parse_args()
    if not OA.is_dir():
        print(f"no shared data at {DATA}", file=sys.stderr)
        return 2
    specs = HOLDOUT if args.holdout else TRAIN
    jobs = [(s, g, per) for s in specs for g in args.grid for per in PERS]
    pooled: dict[tuple[str, float, str], list[np.ndarray]] = {}
    with ProcessPoolExecutor(args.workers) as pool:
        for spec, setting, per, e in pool.map(_errors, jobs):
            ds = "ngsim" if spec.startswith("ngsim:") else "openacc"
            pooled.setdefault((setting, per, ds), []).append(e)
    rows = [{"setting": json.loads(k[0]), "per": k[1] * 100, "dataset": k[2],
             "pte95_m": float(np.percentile(np.concatenate(v), 95))}
            for k, v in sorted(pooled.items())]
    kf = {(r["per"], r["dataset"]): r["pte95_m"] for r in rows if r["setting"] == "kf"}
    for r in rows:
        ref = kf.get((r["per"], r["dataset"]))
        r["ratio_to_kf"] = r["pte95_m"] / ref if ref else None
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    cells = sorted({(r["dataset"], r["per"]) for r in rows})
    print(f"{'setting':<34}" + "".join(f"{d[:7]} {p:g}%".rjust(14) for d, p in cells)
          + "   mean ratio to kf")
    for s in dict.fromkeys(json.dumps(r["setting"]) for r in rows):
        mine = {(r["dataset"], r["per"]): r for r in rows if json.dumps(r["setting"]) == s}
        ratios = [mine[c]["ratio_to_kf"] for c in cells if mine[c]["ratio_to_kf"]]
        print(f"{s:<34}" + "".join(f"{mine[c]['pte95_m']:>14.3f}" for c in cells)
              + f"   {np.mean(ratios):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
