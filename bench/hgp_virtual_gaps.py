"""Branch scores from virtual gaps, measured (issue 17, part 2; not adopted).

The HGP's branch scores (``HgpConfig.branches``) learn from one squared position error per
gap, at the BSM that ends it.  On NGSIM the per-RV choice in the short-gap class is noisy
(CA is best, yet KF or the GP answer a third of those gaps).  This script tries the
obvious remedy: at every BSM also score every branch on *virtual* gaps, from the states it
had at the BSMs 0.2-0.35 s earlier (their forecasts, the KF's state, CA's last BSM), so
that each class gets several scores per BSM instead of one per real gap.

Rows, PTE95 over all trips, seed 0, forecasts made at every BSM (as ``obu run`` makes
them): ``eager`` the shipped HGP, ``virtual`` the same with virtual-gap scores for gaps
up to 0.35 s, and ``ca``.

    python bench/hgp_virtual_gaps.py [--json] [--per 0.1,0.3,0.5] [--workers 2]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import copy
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from catc.channel import bernoulli_received
from catc.evaluate import observations
from catc.predict import make_predictor
from catc.predict.forecast import read_xy
from catc.predict.hgp import HgpPredictor
from hgp_ablation import DATASETS
from hil.datasets import load

SHORT_S = 0.35  # the short-gap class (HgpConfig.branch_edges[0])


class EagerHgp(HgpPredictor):
    """The HGP with a forecast made at every BSM; ``virtual``: also score the branches on
    the virtual gaps from the last three BSMs but one to this one, when up to SHORT_S."""

    def __init__(self, virtual: bool = False) -> None:
        super().__init__()
        self.virtual = virtual
        self.past: list = []  # (t, forecast, copies of the branches) of recent BSMs

    def reset(self) -> None:
        super().reset()
        self.past = []

    def update(self, obs) -> None:
        if self._obs and obs.t <= self._obs[-1].t:
            return
        if self.virtual and self._branches.kin:
            for tj, f, branches in self.past[:-1]:  # the last one is the real gap's
                lag = obs.t - tj
                if lag > SHORT_S + 1e-6:
                    continue
                gx, gy = read_xy(f, lag)
                errs = [(gx - obs.x) ** 2 + (gy - obs.y) ** 2]
                for k in branches:
                    px, py = k.position(obs.t)
                    errs.append((px - obs.x) ** 2 + (py - obs.y) ** 2)
                self._branches.add(0, errs)  # the short-gap class
        super().update(obs)
        if len(self._obs) >= self.config.min_points:
            self._forecast = self._make_forecast(3.0)
            self.past = [*self.past[-2:], (obs.t, self._forecast,
                                           [copy.copy(k) for k in self._branches.kin])]


def pte95(job: tuple[str, float, str]) -> tuple[str, float, str, float]:
    dataset, per, row = job
    errors = []
    for t in load(DATASETS[dataset]):
        for tr in t.tracks.values():
            received = bernoulli_received(0, f"{t.name}/{tr.vehicle_id}", len(tr), per)
            p = make_predictor("ca") if row == "ca" else EagerHgp(row == "virtual")
            started = False
            for i, o in enumerate(observations(tr)):
                if received[i]:
                    p.update(o)
                    started = True
                if started:
                    q = p.predict(o.t)
                    errors.append(math.hypot(q.x - o.x, q.y - o.y))
    return dataset, per, row, float(np.percentile(errors, 95))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--per", default="0.1,0.3,0.5")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    pers = [float(v) for v in args.per.split(",")]
    jobs = [(d, p, r) for d in DATASETS for p in pers for r in ("eager", "virtual", "ca")]
    with ProcessPoolExecutor(args.workers) as ex:
        out = {(d, p, r): v for d, p, r, v in ex.map(pte95, jobs)}
    if args.json:
        print(json.dumps([{"dataset": d, "per": p, "row": r, "pte95_m": v}
                          for (d, p, r), v in out.items()], indent=1))
        return 0
    cols = [(d, p) for d in DATASETS for p in pers]
    print("PTE95 [m]" + "".join(f"{d} {p:.0%}".rjust(14) for d, p in cols))
    for r in ("eager", "virtual", "ca"):
        print(f"{r:9s}" + "".join(f"{out[d, p, r]:14.5f}" for d, p in cols))
    return 0


if __name__ == "__main__":
    sys.exit(main())
