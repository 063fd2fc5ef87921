"""``captures train-bank``: build the HGP kernel bank from real trips (paper: Algorithm 1, H2)."""

from __future__ import annotations

import argparse
import hashlib
import math
import shlex
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from captures.progress import Progress
from catc import __version__
from catc.predict.bank import KernelBank
from catc.predict.training import TrainConfig, cluster, persistency, train
from hil.datasets import DatasetError, load_files

HELP = """\
Walk the trips of the --dataset specs with the paper's Algorithm 1 (TW samples, PTE_th),
collect every (speed, heading) model pair it needed, cluster them to --cluster pairs
(k-means on log hyperparameters) and write the bank as JSON.  Reports the bank size
before clustering, model persistency (MP) against cluster size, and the new-kernel rate
on --holdout trips that were not used for training (the paper's H2 figures).

The default bank shipped with the package is made by `make bank`."""

CLUSTER_SIZES = (1, 2, 4, 8, 16, 32, 64)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train-bank", help="train the HGP kernel bank (Algorithm 1)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", action="append", required=True, metavar="SPEC",
                   help="training trips: PATH or KIND:PATH; repeat for more")
    p.add_argument("--holdout", action="append", default=[], metavar="SPEC",
                   help="trips not used for training, for the new-kernel rate")
    p.add_argument("--out", type=Path, required=True, help="bank JSON to write")
    p.add_argument("--tw", type=int, default=30, help="training window, samples (default 30)")
    p.add_argument("--pte-th", type=float, default=0.5, help="PTE threshold, m (default 0.5)")
    p.add_argument("--horizon", type=float, default=1.0,
                   help="forecast horizon whose PTE is checked, s (default 1.0)")
    p.add_argument("--cluster", type=int, default=16, help="bank size after clustering (16)")
    p.add_argument("--h2-tracks", type=int, default=12,
                   help="tracks (spread over the data) used for MP vs cluster size (12)")
    p.set_defaults(func=run)


def _digest(loaded: list[tuple[Path, list]]) -> dict[str, str]:
    """SHA-256 of every file the trips came from, so a bank names exactly what it came from."""
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f, _ in loaded}


def run(args: argparse.Namespace) -> int:
    try:
        train_files = [item for spec in args.dataset for item in load_files(spec)]
        holdout_files = [item for spec in args.holdout for item in load_files(spec)]
    except DatasetError as err:
        print(f"captures train-bank: {err}", file=sys.stderr)
        return 2
    if args.tw < 3 or args.pte_th <= 0 or args.horizon <= 0 or args.cluster < 1:
        print("captures train-bank: need --tw >= 3 and positive --pte-th, --horizon, --cluster",
              file=sys.stderr)
        return 2
    tables = [t for _, ts in train_files for t in ts]
    holdout = [t for _, ts in holdout_files for t in ts]
    cfg = TrainConfig(tw=args.tw, pte_th=args.pte_th, horizon_s=args.horizon)
    tracks = [tr for t in tables for tr in t.tracks.values()]
    print(f"training on {len(tables)} trips, {len(tracks)} tracks, "
          f"{sum(len(tr) for tr in tracks) / 600:.0f} vehicle-minutes", file=sys.stderr)
    t0 = time.monotonic()
    with Progress("train-bank") as progress:
        result = train(tracks, cfg, progress=progress)
    seconds = time.monotonic() - t0
    bank = cluster(result.bank, args.cluster)
    print(f"bank before clustering: {len(result.bank)} pairs "
          f"({result.steps} steps, {result.switches} switches, {result.reused} answered by an "
          f"existing pair), MP mean {np.mean(result.mp_s):.2f} s; {seconds:.0f} s")

    step = max(1, len(tracks) // max(args.h2_tracks, 1))
    sample = tracks[::step][: args.h2_tracks]
    mp_rows = []
    for size in CLUSTER_SIZES:
        p = persistency(sample, cluster(result.bank, size), cfg)
        mp_rows.append({"cluster_size": size, **p})
        print(f"  C_size {size:>3}: MP {p['mp_mean_s']:6.2f} s, new-kernel rate "
              f"{p['new_kernel_rate']:.3f} of switches ({p['new_kernels_per_min']:.1f}/min)")
    held = None
    if holdout:
        hold_tracks = [tr for t in holdout for tr in t.tracks.values()]
        held = persistency(hold_tracks, bank, cfg)
        print(f"holdout ({len(hold_tracks)} tracks): MP {held['mp_mean_s']:.2f} s, new-kernel "
              f"rate {held['new_kernel_rate']:.3f} of switches "
              f"({held['new_kernels_per_min']:.1f}/min)")
    meta = {
        "command": "captures train-bank " + " ".join(shlex.quote(a) for a in sys.argv[2:]),
        "catc_version": __version__,
        "trained_on": _digest(train_files),
        "holdout": _digest(holdout_files),
        "params": {"tw": cfg.tw, "pte_th": cfg.pte_th, "horizon_s": cfg.horizon_s,
                   "cluster": args.cluster,
                   "hgp": {k: (None if isinstance(v, float) and math.isinf(v) else v)
                           for k, v in asdict(cfg.hgp).items()}},
        "stats": {"pairs_before_clustering": len(result.bank), "steps": result.steps,
                  "switches": result.switches, "reused": result.reused,
                  "mp_mean_s": float(np.mean(result.mp_s)), "train_seconds": round(seconds, 1),
                  "mp_vs_cluster_size": mp_rows, "holdout": held},
    }
    args.out.write_text(KernelBank(bank.speed, bank.heading, meta).to_json())
    print(f"wrote {args.out} ({len(bank)} pairs)")
    return 0

