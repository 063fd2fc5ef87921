"""Two HGP variants, trip by trip and by leave-one-trip-out: is a choice between them one
that every trip supports, or one that a few files make?

For every dataset and PER: the pooled PTE95 of variant A, of variant B and of a peer
predictor (default ``ca``); how many trips B makes better and worse (each trip's own
PTE95); and the leave-one-trip-out score: each trip is scored with whichever variant has
the lower pooled PTE95 over all the *other* trips of its dataset, and those errors are
pooled.  When that score equals B's everywhere, choosing B was not a choice made for one
file.  The variants are ``bench/hgp_ablation.py``'s (the same seeded loss on every vehicle
of every trip: ``hgp_ablation.trip_errors``).

    python bench/hgp_cv.py [--json] [--a br-m0.5] [--b hgp[,VARIANT...]] [--peer ca]
                           [--per 10,30,50,80,90,95] [--workers 2]

Several B variants (a comma list) are each compared with the same A, computed once.

Behind docs/log/2026-11-26-hgp-blend-and-margin.md.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hgp_ablation import DATA, DATASETS, VARIANTS, trip_errors


def errors(job: tuple[str, float, str]) -> tuple[str, float, str, dict[str, np.ndarray]]:
    dataset, per, name = job
    return dataset, per, name, trip_errors(dataset, name, per)


def p95(parts) -> float:
    return float(np.percentile(np.concatenate(list(parts)), 95))


def compare(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict:
    """Pooled PTE95 of a and b, trips b makes better / worse, and the leave-one-out score."""
    better = sum(p95([b[t]]) < p95([a[t]]) for t in a)
    worse = sum(p95([b[t]]) > p95([a[t]]) for t in a)
    chosen = []
    for t in a:
        others = [u for u in a if u != t]
        pick = b if p95(b[u] for u in others) < p95(a[u] for u in others) else a
        chosen.append(pick[t])
    return {"a": p95(a.values()), "b": p95(b.values()), "better": better, "worse": worse,
            "trips": len(a), "loo": p95(chosen)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--a", default="br-m0.5", help="variant A (default br-m0.5: margin 0.5)")
    ap.add_argument("--b", default="hgp",
                    help="variant B, or a comma list of them (default hgp: as shipped)")
    ap.add_argument("--peer", default="ca", help="a predictor shown beside (default ca)")
    ap.add_argument("--per", default="10,30,50,80,90,95", help="PER list in %%")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    bs = args.b.split(",")
    unknown = [v for v in (args.a, *bs) if v not in VARIANTS]
    if unknown:
        print(f"hgp_cv: unknown variant {unknown[0]!r}; one of {', '.join(VARIANTS)}",
              file=sys.stderr)
        return 2
    if not (DATA / "openacc-zalazone").is_dir():
        print(f"hgp_cv: no shared data at {DATA}", file=sys.stderr)
        return 2
    pers = [float(p) / 100 for p in args.per.split(",")]
    names = (args.a, *bs, args.peer)
    jobs = [(d, p, n) for d in DATASETS for p in pers for n in names]
    got: dict[tuple[str, float, str], dict[str, np.ndarray]] = {}
    with ProcessPoolExecutor(args.workers) as pool:
        for k, (d, p, n, out) in enumerate(pool.map(errors, jobs), 1):
            got[d, p, n] = out
            if not args.json:
                print(f"  {k}/{len(jobs)}: {d} PER {p * 100:g} % {n}", file=sys.stderr)
    rows = []
    for b in bs:
        for d in DATASETS:
            for p in pers:
                row = compare(got[d, p, args.a], got[d, p, b])
                rows.append({"dataset": d, "per": p * 100, "a": args.a, "b": b,
                             "pte95_a": row["a"], "pte95_b": row["b"],
                             "pte95_loo": row["loo"], "trips_better": row["better"],
                             "trips_worse": row["worse"], "trips": row["trips"],
                             "peer": args.peer,
                             "pte95_peer": p95(got[d, p, args.peer].values())})
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"PTE95 [m]; A = {args.a}; LOO: each trip scored with the variant the other "
          "trips prefer")
    for r in rows:
        if r["dataset"] == next(iter(DATASETS)) and r["per"] == pers[0] * 100:
            print(f"\nB = {r['b']}")
            print(f"{'dataset':9} {'PER %':>5} {'A':>9} {'B':>9} {'LOO':>9} "
                  f"{'B better/worse':>16} {args.peer:>9}")
        print(f"{r['dataset']:9} {r['per']:5.0f} {r['pte95_a']:9.5f} {r['pte95_b']:9.5f} "
              f"{r['pte95_loo']:9.5f} {r['trips_better']:>7}/{r['trips_worse']:<3} of "
              f"{r['trips']:<3} {r['pte95_peer']:9.5f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
