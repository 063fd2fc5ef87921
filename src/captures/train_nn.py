"""``captures train-nn``: train the paper's neural baselines (AE and LSTM, direct and
indirect) on real trips; the shipped weights are made by ``make nn``."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import sys
import time
from dataclasses import asdict
from functools import partial
from pathlib import Path

from captures.evaluate import csv_list
from captures.progress import Progress
from catc import __version__
from hil.datasets import DatasetError, load_files
from hil.errors import InputError, load_json

HELP = """\
Train the neural baselines of the paper (predictors ae, ae-d, lstm, lstm-d) on the trips
of the --dataset specs, split by trip into training and validation (--val-fraction),
with the channel's losses drawn into every example (PER 0-95 %, rates 10-1 Hz), Adam on
MSE and early stopping on the validation loss.  Writes DIR/NAME.pt per model (float16
weights with everything needed to rebuild it, and how it was made) and DIR/train-nn.json.
Needs the nn extra: pip install 'catc-hil[nn]'.

The weights shipped with the package are made by `make nn` (about an hour on 2 cores);
use them from elsewhere with CATC_NN_DIR=DIR."""


def register(sub: argparse._SubParsersAction) -> None:
    from catc.predict.nn import NN_NAMES
    from catc.predict.nn_train import TrainConfig

    d = TrainConfig()
    p = sub.add_parser("train-nn", help="train the neural baselines (AE, LSTM)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", action="append", required=True, metavar="SPEC",
                   help="training trips: PATH or KIND:PATH; repeat for more")
    p.add_argument("--holdout", action="append", default=[], metavar="SPEC",
                   help="trips kept out of training and validation (recorded in the meta)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument("--models", type=partial(csv_list, str), default=list(NN_NAMES),
                   help=f"which to train (default {','.join(NN_NAMES)})")
    p.add_argument("--epochs", type=int, default=d.epochs,
                   help=f"most epochs (default {d.epochs})")
    p.add_argument("--steps", type=int, default=0,
                   help="stop after this many optimiser steps (default: no limit)")
    p.add_argument("--examples", type=int, default=d.examples,
                   help=f"training examples drawn per epoch (default {d.examples})")
    p.add_argument("--val-examples", type=int, default=d.val_examples,
                   help=f"validation examples (default {d.val_examples})")
    p.add_argument("--batch", type=int, default=d.batch, help=f"batch size ({d.batch})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate ({d.lr:g})")
    p.add_argument("--patience", type=int, default=d.patience,
                   help=f"epochs without a better validation loss before stopping "
                        f"({d.patience})")
    p.add_argument("--max-trips", type=int, default=0,
                   help="use only the first N trips of each dataset (0 = all)")
    p.add_argument("--val-fraction", type=float, default=0.15,
                   help="share of the trips used for validation (default 0.15)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                   help="torch threads (default: the CPU count)")
    p.set_defaults(func=run)


def _digest(loaded) -> dict[str, str]:
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f, _ in loaded}


def run(args: argparse.Namespace) -> int:
    from catc.predict.nn import NN_NAMES, MissingExtra, NnConfig

    def fail(msg: str) -> int:
        print(f"captures train-nn: {msg}", file=sys.stderr)
        return 2

    unknown = [m for m in args.models if m not in NN_NAMES]
    if unknown:
        return fail(f"unknown model {unknown[0]!r}; known: {', '.join(NN_NAMES)}")
    if min(args.epochs, args.examples, args.val_examples, args.batch, args.patience) < 1 \
            or args.steps < 0 or not 0.0 < args.val_fraction < 1.0 or args.lr <= 0:
        return fail("need positive --epochs, --examples, --val-examples, --batch, --patience "
                    "and --lr, --steps >= 0 and 0 < --val-fraction < 1")
    try:
        from catc.predict.nn import torch_module
        from catc.predict.nn_train import TrainConfig, split, train

        torch = torch_module()
    except MissingExtra as err:
        return fail(str(err))
    try:
        loaded = []
        for spec in args.dataset:
            files = load_files(spec)
            if args.max_trips:
                kept, n = [], 0
                for path, tabs in files:
                    if n < args.max_trips:
                        kept.append((path, tabs[:args.max_trips - n]))
                        n += len(kept[-1][1])
                files = kept
            loaded += files
        held = [item for spec in args.holdout for item in load_files(spec)]
    except DatasetError as err:
        return fail(str(err))
    tables = [t for _, ts in loaded for t in ts]
    held_names = {t.name for _, ts in held for t in ts}
    tables = [t for t in tables if t.name not in held_names]
    try:
        train_tables, val_tables = split(tables, args.val_fraction, args.seed)
    except ValueError as err:
        return fail(str(err))
    torch.set_num_threads(max(1, args.threads))
    tc = TrainConfig(epochs=args.epochs, steps=args.steps, examples=args.examples,
                     val_examples=args.val_examples, batch=args.batch, lr=args.lr,
                     patience=args.patience, seed=args.seed)
    tr_tracks = [tr for t in train_tables for tr in t.tracks.values()]
    va_tracks = [tr for t in val_tables for tr in t.tracks.values()]
    print(f"train-nn: {len(train_tables)} training trips ({len(tr_tracks)} vehicles, "
          f"{sum(len(t) for t in tr_tracks) / 600:.0f} vehicle-minutes), {len(val_tables)} "
          f"validation trips ({len(va_tracks)} vehicles); torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads", file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    from catc.predict.nn import save

    summary = {}
    command = "captures train-nn " + " ".join(shlex.quote(a) for a in sys.argv[2:])
    for name in args.models:
        config = NnConfig.for_name(name)
        t0 = time.monotonic()
        try:
            with Progress(name) as progress:
                result = train(config, tr_tracks, va_tracks, tc, progress=progress,
                               log=progress.write)
        except ValueError as err:
            return fail(f"{name}: {err}")
        net = result.network
        net.meta.update({
            "command": command, "catc_version": __version__, "torch": str(torch.__version__),
            "trained_on": _digest(loaded), "holdout": _digest(held),
            "train_trips": len(train_tables),
            "validation_trips": sorted(t.name for t in val_tables),
            "train_config": asdict(tc), "best_epoch": result.best_epoch,
            "steps": result.steps, "train_seconds": round(result.seconds, 1),
            "history": result.history})
        path = args.out / f"{name}.pt"
        save(net, path)
        summary[name] = {k: net.meta[k] for k in (
            "val_loss", "val_position_error_m", "val_position_error_m_cs", "best_epoch",
            "steps", "train_seconds")}
        summary[name]["bytes"] = path.stat().st_size
        err, cs = net.meta["val_position_error_m"], net.meta["val_position_error_m_cs"]
        print(f"{name}: best epoch {result.best_epoch}, validation loss "
              f"{net.meta['val_loss']:.4f}; position error mean/p95 at " + ", ".join(
                  f"{h} {e['mean']:.3f}/{e['p95']:.3f} m (cs {cs[h]['mean']:.3f}/"
                  f"{cs[h]['p95']:.3f})" for h, e in err.items()) +
              f"; {time.monotonic() - t0:.0f} s; wrote {path}")
    index = args.out / "train-nn.json"  # one entry per model; others trained earlier stay
    try:
        earlier = load_json(index) if index.is_file() else {}
    except InputError as err:  # not JSON: it is rewritten with this run's models
        print(f"captures train-nn: {err}; rewritten", file=sys.stderr)
        earlier = {}
    if not isinstance(earlier, dict):
        earlier = {}
    index.write_text(json.dumps({**earlier, **summary}, indent=1))
    return 0
