"""``captures evaluate``: PTE95 of each predictor on real trips under a seeded Bernoulli loss.

The quick offline evaluation (no sockets): every track of every trip is one remote
vehicle, its 10 Hz BSMs are dropped with probability PER (the same pattern for every
predictor), and PTE is scored at every tick (see :mod:`catc.evaluate`).
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

from captures.progress import Progress
from catc.evaluate import Score, evaluate
from catc.predict import NAMES, available, check, make_predictor
from hil.datasets import DatasetError, load

HELP = """\
Replay every vehicle of the given trips through a seeded Bernoulli channel at each PER and
report PTE95 (m) per predictor: the 95th percentile of the 2-D position error at every
10 Hz tick (docs/architecture.md, "Metrics").  Example:

  captures evaluate --dataset ../shared/data/openacc-zalazone \\
      --dataset ngsim:../shared/data/ngsim-i80-pairs --per 0,50,80,90,95"""


def csv_list(kind, text: str) -> list:
    try:
        return [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list: {text!r}") from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="PTE95 per predictor under seeded packet loss",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", action="append", required=True, metavar="SPEC",
                   help="PATH or KIND:PATH (a file or a folder); repeat for more")
    p.add_argument("--per", type=partial(csv_list, float), default=[0, 50, 80, 90, 95],
                   help="packet error rates in %% (default 0,50,80,90,95)")
    p.add_argument("--predictors", type=partial(csv_list, str), default=None,
                   help=f"comma-separated, from {','.join(NAMES)} (default: all that are "
                        "installed; the neural ones need the nn extra)")
    p.add_argument("--seeds", type=int, default=1, help="loss patterns per PER (default 1)")
    p.add_argument("--max-trips", type=int, default=0,
                   help="use only the first N trips of each dataset (0 = all)")
    p.add_argument("--json", type=Path, metavar="OUT", help="also write the rows as JSON")
    p.set_defaults(func=run)


def table(scores: list[Score]) -> str:
    pers = sorted({s.per for s in scores})
    names = list(dict.fromkeys(s.predictor for s in scores))
    by = {(s.predictor, s.per): s for s in scores}
    lines = ["PTE95 [m]  " + "".join(f"{f'PER {100 * p:g}%':>11}" for p in pers)]
    for n in names:
        lines.append(f"{n:<11}" + "".join(f"{by[n, p].pte95_m:>11.3f}" for p in pers))
    if "hgp" in names:
        for n in names:
            if n != "hgp":
                lines.append(f"{n + '/hgp':<11}" + "".join(
                    f"{by[n, p].pte95_m / by['hgp', p].pte95_m:>11.2f}"
                    if by["hgp", p].pte95_m > 0 else f"{'-':>11}" for p in pers))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.predictors is None:
        args.predictors = list(available())
    try:
        for n in args.predictors:
            check(n)
    except ValueError as err:
        print(f"captures evaluate: {err}", file=sys.stderr)
        return 2
    if any(not 0 <= p <= 100 for p in args.per):
        print("captures evaluate: --per takes percentages from 0 to 100", file=sys.stderr)
        return 2
    try:
        tables = []
        for spec in args.dataset:
            loaded = load(spec)
            tables += loaded[: args.max_trips] if args.max_trips else loaded
    except DatasetError as err:
        print(f"captures evaluate: {err}", file=sys.stderr)
        return 2
    factories = {n: partial(make_predictor, n) for n in args.predictors}
    n_tracks = sum(len(t.tracks) for t in tables)
    print(f"{len(tables)} trips, {n_tracks} vehicles, "
          f"{sum(len(tr) for t in tables for tr in t.tracks.values()) / 600:.0f} vehicle-minutes",
          file=sys.stderr)
    with Progress("evaluate") as progress:
        scores = evaluate(tables, factories, [p / 100 for p in args.per], range(args.seeds),
                          progress=progress)
    print(table(scores))
    if args.json:
        rows = [{"predictor": s.predictor, "per": s.per * 100, "pte95_m": s.pte95_m,
                 "pte_mean_m": s.pte_mean_m, "n_ticks": s.n_ticks,
                 "exceedances": {str(k): v for k, v in s.exceedances.items()},
                 "datasets": args.dataset, "seeds": args.seeds} for s in scores]
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


