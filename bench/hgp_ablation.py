"""HGP formulation choices, measured: PTE95 of HGP variants next to the kinematic baselines.

Each variant changes one thing from the shipped configuration (``HgpConfig()`` and the
shipped kernel bank).  Every variant and baseline sees the same seeded Bernoulli loss on
every vehicle of every trip (``catc.evaluate``).  This is the script behind the
formulation notes in ``src/catc/predict/hgp/`` and docs/reference/predictors.md.

    python bench/hgp_ablation.py [--json] [--per 90,95] [--workers 2] [--variants a,b]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from catc.channel import bernoulli_received
from catc.evaluate import replay_track
from catc.predict import gp, make_predictor
from catc.predict.bank import KernelBank
from catc.predict.hgp import HgpConfig, HgpPredictor
from catc.predict.training import series
from hil.datasets import load

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DATASETS = {"openacc": str(DATA / "openacc-zalazone"),
            "ngsim": "ngsim:" + str(DATA / "ngsim-i80-pairs")}
BASE = HgpConfig()

#: name -> (description, HgpConfig overrides, bank: "default" or "loo")
VARIANTS: dict[str, tuple[str, dict, str]] = {
    "hgp": ("shipped configuration", {}, "default"),
    "paper": ("no slopes, select on values only (the paper's HGP)",
              {"slopes": False, "select_with_slopes": False}, "default"),
    "no-select-slopes": ("slopes in the forecast, selection on values only",
                         {"select_with_slopes": False}, "default"),
    "loo-bank": ("bank = k-means of LOO fits on 300 random windows, not Algorithm 1", {},
                 "loo"),
    "online": ("online models on (backtest 1 s, PTE_th 0.5 m)", {"online": True}, "default"),
    "no-damping": ("E[cos h] without exp(-σh²/2)", {"heading_damping": False}, "default"),
    "no-switching": ("no plausibility switching (negative speed still stops)",
                     {"accel_max": 1e9, "yaw_rate_max": 1e9, "lat_accel_max": 1e9,
                      "speed_std_max": 1e9, "heading_std_max": 1e9}, "default"),
    "left-rule": ("the paper's left Riemann recursion", {"integration": "left"}, "default"),
    "window-10s": ("window also capped at 10 s", {"window_s": 10.0}, "default"),
    "window-30s": ("window also capped at 30 s", {"window_s": 30.0}, "default"),
    "accel-sd-0.14": ("BSM acceleration σ 0.14 m/s² (shipped 0.07)", {"noise_accel": 0.02},
                      "default"),
    "accel-sd-0.28": ("BSM acceleration σ 0.28 m/s²", {"noise_accel": 0.08}, "default"),
    "yaw-sd-0.18": ("BSM yaw rate σ 0.18 deg/s (shipped 0.31)", {"noise_yaw": 1e-5},
                    "default"),
    "yaw-sd-0.57": ("BSM yaw rate σ 0.57 deg/s", {"noise_yaw": 1e-4}, "default"),
    "ca-speed": ("diagnostic: CA speed forecast, GP heading", {"speed_model": "ca"},
                 "default"),
    "ctrv-heading": ("diagnostic: GP speed, constant-yaw-rate heading",
                     {"heading_model": "ctrv"}, "default"),
    "br-ca-kf": ("branches CA and KF beside the GP, scored at each gap's end",
                 {"branches": ("ca", "kf")}, "default"),
    "br-ca-kf-ctrv": ("branches CA, KF and CTRV", {"branches": ("ca", "kf", "ctrv")},
                      "default"),
    "br-ca-kf-imm": ("branches CA, KF and IMM", {"branches": ("ca", "kf", "imm")},
                     "default"),
    "blend-all": ("branches CA and KF blended with the GP, inverse-score weights",
                  {"branch_blend": float("inf")}, "default"),
    "blend-2": ("blend of the branches scoring at most 2x the best",
                {"branch_blend": 2.0}, "default"),
    "blend-1.25": ("blend of the branches scoring at most 1.25x the best",
                   {"branch_blend": 1.25}, "default"),
    "blend-all-p2": ("blend of every branch, weights 1/score^2",
                     {"branch_blend": float("inf"), "blend_power": 2.0}, "default"),
    "blend-4-p2": ("blend of the branches scoring at most 4x the best, weights 1/score^2",
                   {"branch_blend": 4.0, "blend_power": 2.0}, "default"),
    "blend-all-p0.5": ("blend of every branch, weights 1/sqrt(score)",
                       {"branch_blend": float("inf"), "blend_power": 0.5}, "default"),
    "m-1-1-.5": ("margin 1 for gaps up to 1.05 s, 0.5 for longer ones",
                 {"branch_margin": (1.0, 1.0, 0.5, 0.5)}, "default"),
    "m-1-.75-.5": ("margins 1, 0.75, 0.5, 0.5 by gap class",
                   {"branch_margin": (1.0, 0.75, 0.5, 0.5)}, "default"),
    "br-d0.5": ("branches CA and KF, score decay 0.5",
                {"branches": ("ca", "kf"), "branch_decay": 0.5}, "default"),
    "br-d0.9": ("branches CA and KF, score decay 0.9",
                {"branches": ("ca", "kf"), "branch_decay": 0.9}, "default"),
    "br-d0.95": ("branches CA and KF, score decay 0.95",
                 {"branches": ("ca", "kf"), "branch_decay": 0.95}, "default"),
    "br-m0.5": ("branches CA and KF, a kinematic branch only at half the GP's score",
                {"branches": ("ca", "kf"), "branch_margin": 0.5}, "default"),
    **{f"fit-{m:g}": (f"a gap keeps the selection when the GP's forecast over it landed "
                      f"within {m:g} m", {"reselect_fit_m": m}, "default")
       for m in (0.02, 0.05, 0.1, 0.25, 0.5, 1.0)},
}
BASELINES = ("ca", "kf", "ctrv", "imm")


def loo_bank(tables, count: int = 300, seed: int = 0) -> KernelBank:
    """k-means(16) of LOO fits on random 3 s windows: a bank without Algorithm 1."""
    from catc.predict.training import cluster

    rng = np.random.default_rng(seed)
    tracks = [tr for t in tables for tr in t.tracks.values() if len(tr) >= 40]
    speed, heading = [], []
    for _ in range(count):
        tr = tracks[rng.integers(len(tracks))]
        c = int(rng.integers(29, len(tr)))
        t, s, h, *_ = series(tr)
        w = slice(c - 29, c + 1)
        tau = t[w] - t[c]
        speed.append(gp.fit(tau, s[w] - s[c], BASE.noise_speed, np.array([2.0, 1.0, 0.1]),
                            BASE.speed_bounds).theta)
        heading.append(gp.fit(tau, h[w] - h[c], BASE.noise_heading,
                              np.array([2.0, 0.1, 0.01]), BASE.heading_bounds).theta)
    return cluster(KernelBank(np.array(speed), np.array(heading)), 16)


def trip_errors(dataset: str, name: str, per: float) -> dict[str, np.ndarray]:
    """Every position error of variant or predictor ``name`` at ``per`` on ``dataset``,
    per trip (the same seeded loss for every name)."""
    tables = load(DATASETS[dataset])
    if name in VARIANTS:
        _, overrides, bank = VARIANTS[name]
        loo = (loo_bank([t for spec in DATASETS.values() for t in load(spec)])
               if bank == "loo" else None)
        predictor = HgpPredictor(bank=loo, config=replace(BASE, **overrides))
    else:
        predictor = make_predictor(name)
    out = {}
    for t in tables:
        e = np.concatenate([replay_track(tr, predictor, bernoulli_received(
            0, f"{t.name}/{tr.vehicle_id}", len(tr), per)) for tr in t.tracks.values()])
        out[t.name] = e[~np.isnan(e)]
    return out


def pte95(job: tuple[str, str, float]) -> tuple[str, str, float, float]:
    dataset, name, per = job
    errors = trip_errors(dataset, name, per)
    return dataset, name, per, float(np.percentile(np.concatenate(list(errors.values())), 95))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--per", default="90,95", help="PER list in %% (default 90,95)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="comma-separated variant names (default all)")
    ap.add_argument("--no-baselines", action="store_true", help="variants only")
    args = ap.parse_args()
    if not (DATA / "openacc-zalazone").is_dir():
        print(f"no shared data at {DATA}", file=sys.stderr)
        return 2
    pers = [float(p) / 100 for p in args.per.split(",")]
    names = [*([] if args.no_baselines else BASELINES), *args.variants.split(",")]
    jobs = [(d, n, p) for d in DATASETS for n in names for p in pers]
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(pte95, jobs))
    table = {(d, n, p): v for d, n, p, v in results}
    if args.json:
        print(json.dumps([{"dataset": d, "variant": n, "per": p * 100, "pte95_m": v}
                          for d, n, p, v in results], indent=1))
        return 0
    cols = [(d, p) for d in DATASETS for p in pers]
    print(f"{'PTE95 [m]':<18}" + "".join(f"{d[:7]} {p * 100:g}%".rjust(14) for d, p in cols)
          + "   change")
    for n in names:
        print(f"{n:<18}" + "".join(f"{table[d, n, p]:>14.3f}" for d, p in cols)
              + ("   " + VARIANTS[n][0] if n in VARIANTS else "   baseline"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
