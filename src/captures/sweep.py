"""``captures sweep``: PER × rate × predictor × dataset, on the offline simulator or live.

Every cell is :func:`catc.sweep.run_cell`'s measurement: the RVE's channel model
(:mod:`catc.channel`) with no sockets, PTE on every vehicle of every trip, FCW accuracy
through the CA-TC.  It runs as two kinds of task: PTE of a chunk of trips whose vehicles
advance in lockstep (:func:`catc.sweep.lockstep_errors`, so the HGP forecasts stacked as
in the OBU), and the FCW of one trip's scene (:func:`catc.sweep.cam_run`).
Every predictor sees the same loss pattern (the channel is a function
of the seed, the trip, the vehicle and the message index).  Results pool into one row per
(dataset, predictor, PER, rate) with exact percentiles, so the rows do not depend on the
number of workers, the engine (local processes or Dask) or the completion order.

Engines: ``--workers K`` local processes (the default, K = 1 runs in this process), or
``--dask tcp://HOST:PORT`` a Dask distributed scheduler.  The trips are sent to every
worker once; a task is one (chunk of trips or trip, predictor, cell, seed).

``--live`` re-runs chosen cells through the real daemons (``rve run`` → UDP on
127.0.0.1 → ``obu run``, separate processes), scores the capture with ``captures score``
and puts it next to the offline CA-TC run of the same trip, cell, seed and predictor
(:func:`catc.sweep.cam_run`): the report marks their agreement.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from pathlib import Path

import numpy as np

from captures.evaluate import csv_list
from captures.progress import Progress
from captures.sweep_tables import POOLED, summary
from catc.mobility import MobilityTable
from catc.predict import NAMES, available, check
from catc.sweep import (
    Cell,
    CellResult,
    Row,
    cam_run,
    cells,
    fcw_scene,
    lockstep_errors,
    pool,
    truth_fcw,
)
from hil.datasets import DatasetError, load_files
from hil.errors import InputError

#: The paper's PER grid (docs/architecture.md, "Paper parameters").
PAPER_PERS = (0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 95)
#: The rate axis from 10 to 1 Hz in five steps.  The full 10, 9, ..., 1 Hz grid costs ~2x
#: the CPU of the whole PER grid (a GP forecasts after every message below 10 Hz) and adds
#: little between 10 and 5 Hz (docs/log/2026-11-25-report-cost.md); pass
#: --rate 10,9,8,7,6,5,4,3,2,1 for it.
PAPER_RATES = (10, 5, 3, 2, 1)

HELP = """\
Sweep PER × transmission rate × predictor × dataset on the offline simulator (the RVE's
channel models and the OBU's CA-TC, no sockets) and print the PTE95 table in the layout
of the paper's SPMD table, PTE95 and FCW accuracy against rate, and the counts of
PTE > PTE_th.  Rows: {dataset, predictor, per, rate, pte95_m, fcw_accuracy, n_ticks, ...}
with the code version and every parameter.

The default grid is the paper's: every PER (0..95 %) at the highest rate, and every rate
(10..1 Hz) at the lowest PER (--grid cross for every pair).  The predictors are all
that are installed (the neural ones need the nn extra).  Example (the H3 table on the
shared real data, FCW for the four predictors of the paper's FCW figures, ~10 min on 2
cores; FCW for all eleven takes about 40 min: a network's FCW costs 5x the HGP's):

  captures sweep --dataset ../shared/data/openacc-zalazone \\
      --dataset ngsim:../shared/data/ngsim-i80-pairs --workers 2 \\
      --fcw-predictors hold,ca,kf,hgp --json out/sweep.json --plots out/sweep"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="PER x rate x predictor x dataset, tables and plots",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_grid_arguments(p)
    p.add_argument("--json", type=Path, metavar="OUT", help="write the rows as JSON")
    p.add_argument("--plots", type=Path, metavar="DIR", help="write the figures (PNG) here")
    p.set_defaults(func=run)


def add_grid_arguments(p: argparse.ArgumentParser) -> None:
    """The grid and engine flags (shared with ``captures report``)."""
    p.add_argument("--dataset", action="append", metavar="SPEC",
                   help="PATH or KIND:PATH (a file or a folder); repeat for more")
    p.add_argument("--per", type=partial(csv_list, float), default=list(PAPER_PERS),
                   help="packet error rates in %% (default 0,10,...,90,95)")
    p.add_argument("--rate", type=partial(csv_list, float), default=list(PAPER_RATES),
                   help="transmission rates in Hz (default 10,5,3,2,1)")
    p.add_argument("--grid", choices=("paper", "cross"), default="paper",
                   help="paper: every PER at the top rate + every rate at the lowest PER "
                        "(default); cross: every pair")
    p.add_argument("--burst", type=float, default=1.0,
                   help="mean loss burst length in messages (default 1: independent)")
    p.add_argument("--predictors", type=partial(csv_list, str), default=None,
                   help=f"comma-separated, from {','.join(NAMES)} (default: all that are "
                        "installed; the neural ones need the nn extra)")
    p.add_argument("--fcw-predictors", type=partial(csv_list, str), default=None,
                   help="predictors whose FCW accuracy is measured (default: the same as "
                        "--predictors; 'none' for none): FCW runs the whole CA-TC and costs "
                        "~3x the PTE of a kinematic predictor")
    p.add_argument("--seeds", type=int, default=1, help="loss patterns per cell (default 1)")
    p.add_argument("--max-trips", type=int, default=0,
                   help="use only the first N trips of each dataset (0 = all)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="local worker processes (default: the CPU count; 1 = in process)")
    p.add_argument("--dask", metavar="tcp://HOST:PORT",
                   help="run the tasks on this Dask distributed scheduler instead")
    p.add_argument("--live", type=partial(csv_list, str), default=None, metavar="PER@RATE,...",
                   help="also run these cells (e.g. 50@10,90@10) through the real daemons "
                        "over UDP on 127.0.0.1, on the first trip of the first dataset, "
                        "with hgp (else the first of --predictors)")
    p.add_argument("--attack", action="append", metavar="KIND[:KEY=VALUE,...]",
                   help="also run this attack (rve run --attack) live on the first dataset's "
                        "first trip at each --per, against each --defences (repeatable): "
                        "FCW false alarms and misses, rejections, detection recall/precision; "
                        "and against the same run without it (captures defence): TP ticks "
                        "lost, honest vehicles suspected or quarantined")
    p.add_argument("--defences", type=partial(csv_list, str), default=None,
                   help="OBU defences of the attack runs: none, enforce (verify on "
                        "demand), enforce+mbd, enforce-all (verify every frame on "
                        "arrival) (default the first three)")
    p.add_argument("--live-speed", type=float, default=8.0,
                   help="replay speed of the live runs (default 8x)")


class SweepError(InputError):
    """A sweep that cannot start; ``str()`` is one line."""


# --- inputs -------------------------------------------------------------------------------------


def dataset_label(spec: str) -> str:
    """A dataset's name in the rows: its file or folder name (``KIND:`` dropped)."""
    _kind, sep, rest = spec.partition(":")
    path = Path(rest if sep and not Path(spec).exists() else spec)
    return path.stem if path.is_file() else path.name


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_datasets(specs: list[str], max_trips: int = 0
                  ) -> tuple[dict[str, list[MobilityTable]], dict[str, dict]]:
    """Trips per dataset label, and each dataset's provenance (files and their SHA-256).
    Trips without a host (or whose host has no vehicle ahead) are left out and listed."""
    out: dict[str, list[MobilityTable]] = {}
    prov: dict[str, dict] = {}
    for spec in specs:
        label = dataset_label(spec)
        if label in out:
            raise SweepError(f"two datasets named {label!r}; give them different paths")
        if label == POOLED:
            raise SweepError(f"a dataset may not be named {POOLED!r} (the rows over all "
                             "datasets are); give it a different path")
        tables, files, skipped = [], {}, []
        for path, tabs in load_files(spec):
            files[str(path)] = _sha256(path)
            for t in tabs:
                try:
                    fcw_scene(t)
                except ValueError as err:
                    skipped.append(f"{t.name}: {err}")
                    continue
                tables.append(t)
        if max_trips:
            tables = tables[:max_trips]
        if not tables:
            raise SweepError(f"dataset {spec!r}: no trip with a host and a vehicle ahead")
        out[label] = tables
        prov[label] = {"spec": spec, "files": files, "trips": [t.name for t in tables],
                       "skipped": skipped,
                       "vehicles": sum(len(t.tracks) for t in tables),
                       "vehicle_minutes": round(sum(len(tr) for t in tables
                                                    for tr in t.tracks.values()) / 600, 1)}
    return out, prov


def code_version() -> dict[str, str]:
    """The package version, the git commit (when run from a checkout) and the HGP bank."""
    from hil.capture import versions

    v = dict(versions())
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"],
                                capture_output=True, text=True, timeout=5)
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--", "."],
                               capture_output=True, text=True, timeout=5)
        if commit.returncode == 0:
            v["git"] = commit.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass
    bank = here.parent / "catc" / "predict" / "default_bank.json"
    if bank.is_file():
        v["hgp_bank_sha256"] = _sha256(bank)
    return v


# --- tasks and engines --------------------------------------------------------------------------

_TABLES: dict[str, MobilityTable] = {}


def _init_worker(tables: dict[str, MobilityTable]) -> None:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # torch, for the neural predictors
    _TABLES.clear()
    _TABLES.update(tables)


def _truth_task(tables: dict[str, MobilityTable] | None, trip: str):
    table = (tables or _TABLES)[trip]
    return trip, truth_fcw(fcw_scene(table))


def _pte_task(tables: dict[str, MobilityTable] | None, chunk: str, trips: tuple[str, ...],
              predictor: str, cell: Cell, seed: int) -> tuple[str, CellResult, float]:
    """PTE of a group of trips in lockstep (:func:`catc.sweep.lockstep_errors`)."""
    t0 = time.process_time()
    tabs = [(tables or _TABLES)[k] for k in trips]
    errors, sent, dropped = lockstep_errors(
        [(f"{t.name}/{v}", tr) for t in tabs for v, tr in t.tracks.items()], predictor, cell,
        seed)
    pte = np.concatenate(errors) if errors else np.zeros(0, np.float32)
    zero = dict.fromkeys(("tp", "tn", "fp", "fn"), 0)
    return chunk, CellResult(chunk, predictor, cell, seed, pte, zero, sent, dropped, 0, 0), \
        time.process_time() - t0


def _fcw_task(tables: dict[str, MobilityTable] | None, trip: str, predictor: str, cell: Cell,
              seed: int, truth) -> tuple[str, CellResult, float]:
    """FCW of one trip's scene through the CA-TC (:func:`catc.sweep.cam_run`)."""
    t0 = time.process_time()
    r = cam_run(fcw_scene((tables or _TABLES)[trip]), predictor, cell, seed, truth, wire=False,
                pte=False)
    r.sent, r.dropped = 0, 0  # PTE and the counts come from _pte_task
    return trip, r, time.process_time() - t0


def chunks(keys: list[str], tables: dict[str, MobilityTable], size: int = 250_000
           ) -> list[tuple[str, ...]]:
    """Trips grouped, in order, into chunks of about ``size`` vehicle-samples: big enough
    for the stacked forecasts (an LSTM forecast costs 1 ms alone, 0.23 ms in a batch of
    32: the shared OpenACC runs as one chunk of 63 vehicles instead of two took 27 % less
    CPU with ``lstm`` at PER 50 %), small enough to spread over workers (the grid has
    many cells and predictors per chunk)."""
    out: list[list[str]] = [[]]
    n = 0
    for k in keys:
        m = sum(len(tr) for tr in tables[k].tracks.values())
        if out[-1] and n + m > size:
            out.append([])
            n = 0
        out[-1].append(k)
        n += m
    return [tuple(c) for c in out if c]


class Engine:
    """Runs tasks ``fn(tables, *args)`` and yields their results as they complete."""

    def __init__(self, tables: dict[str, MobilityTable], workers: int = 1,
                 dask: str | None = None) -> None:
        self.tables, self.workers, self.dask = tables, max(1, workers), dask
        self._pool = self._client = self._scattered = None

    def __enter__(self) -> Engine:
        if self.dask:
            try:
                from distributed import Client
            except ImportError:
                raise SweepError("--dask needs the distributed package: pip install "
                                 "'catc-hil[dask]'") from None
            try:
                self._client = Client(self.dask, timeout="10s")
            except (OSError, TimeoutError) as err:
                raise SweepError(f"cannot reach the Dask scheduler {self.dask}: {err}") from None
            for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
                self._client.run(os.environ.setdefault, var, "1")
            self._scattered = self._client.scatter(self.tables, broadcast=True, hash=False)
        elif self.workers > 1:
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(self.workers, initializer=_init_worker,
                                             initargs=(self.tables,))
        else:
            _init_worker(self.tables)
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
        if self._client is not None:
            self._client.close()

    def map(self, tasks: list[tuple[Callable, tuple]]) -> Iterator[tuple[int, object]]:
        """Run ``fn(tables, *args)`` for each ``(fn, args)``; yield ``(index, result)`` as
        they complete."""
        if self._client is not None:
            from distributed import as_completed

            # every task gets the scattered dict: Dask resolves it on the worker
            futures = {self._client.submit(fn, self._scattered, *a, pure=False): i
                       for i, (fn, a) in enumerate(tasks)}
            for fut in as_completed(futures):
                yield futures[fut], fut.result()
        elif self._pool is not None:
            from concurrent.futures import as_completed

            futures = {self._pool.submit(fn, None, *a): i for i, (fn, a) in enumerate(tasks)}
            for fut in as_completed(futures):
                yield futures[fut], fut.result()
        else:
            for i, (fn, a) in enumerate(tasks):
                yield i, fn(None, *a)


def _cost(table: MobilityTable, predictor: str, fcw: bool) -> float:
    """A rough relative cost (CPU seconds per 10,000 samples, measured), to start the
    longest tasks first and to weigh the progress bar."""
    gp = {"hgp": 1.5, "hgp-d": 4.0, "ae": 1.1, "ae-d": 1.1, "lstm": 1.6,
          "lstm-d": 1.6}.get(predictor, 0.0)
    if fcw:  # the CA-TC on the host's ticks
        return len(table.tracks[table.default_host]) * (4.0 + gp) / 1e4
    return sum(len(tr) for tr in table.tracks.values()) * (0.15 + gp) / 1e4


def sweep(datasets: dict[str, list[MobilityTable]], predictors: list[str],
          grid: list[Cell], seeds: Iterable[int], *, fcw_predictors: Iterable[str] = (),
          workers: int = 1, dask: str | None = None,
          progress: Callable[[float, float], None] | None = None,
          cpu: dict[str, float] | None = None) -> list[Row]:
    """Every (dataset, predictor, cell) row over all trips and seeds (module docstring),
    then, with more than one dataset, the :data:`~captures.sweep_tables.POOLED` rows
    over all of them.
    ``progress(done, total)`` in units of estimated cost; ``cpu`` (when given) collects
    the CPU seconds spent per predictor and metric."""
    seeds = list(seeds)
    fcw_set = [p for p in predictors if p in set(fcw_predictors)]
    trips = {f"{label}/{t.name}": (label, t) for label, tabs in datasets.items() for t in tabs}
    tables = {k: t for k, (_, t) in trips.items()}
    groups = {}
    for label in datasets:
        keys = [k for k, (lab, _) in trips.items() if lab == label]
        for n, c in enumerate(chunks(keys, tables)):
            groups[f"{label}#{n}"] = (label, c)
    work = [(_pte_task, (g, c, p, cell, s), label,
             sum(_cost(tables[k], p, False) for k in c))
            for g, (label, c) in groups.items() for p in predictors for cell in grid
            for s in seeds]
    by: dict[tuple[str, str, Cell], list[CellResult]] = defaultdict(list)
    with Engine(tables, workers, dask) as engine:
        truth = dict(r for _, r in engine.map([(_truth_task, (k,)) for k in trips])) \
            if fcw_set else {}
        work += [(_fcw_task, (k, p, cell, s, truth[k]), trips[k][0],
                  _cost(tables[k], p, True))
                 for k in trips for p in fcw_set for cell in grid for s in seeds]
        work.sort(key=lambda w: -w[3])
        total, done = sum(w[3] for w in work), 0.0
        for i, (_, r, seconds) in engine.map([(w[0], w[1]) for w in work]):
            fn, _, label, cost = work[i]
            by[label, r.predictor, r.cell].append(r)
            if cpu is not None:
                what = f"{r.predictor}/{'fcw' if fn is _fcw_task else 'pte'}"
                cpu[what] = cpu.get(what, 0.0) + seconds
            done += cost
            if progress is not None:
                progress(done, total)
    rows = [pool(label, by[label, p, c], trips=len(datasets[label])) for label in datasets
            for p in predictors for c in grid]
    if len(datasets) > 1:  # every tick of every dataset in one percentile
        rows += [pool(POOLED, [r for label in datasets for r in by[label, p, c]],
                      trips=sum(len(t) for t in datasets.values()))
                 for p in predictors for c in grid]
    for row in rows:
        if row.predictor not in fcw_set:
            row.fcw_accuracy = None
    return rows


# --- the command ----------------------------------------------------------------------------------


def parse_live(items: list[str] | None) -> list[Cell]:
    out = []
    for item in items or []:
        per, _, rate = item.partition("@")
        try:
            out.append(Cell(float(per) / 100.0, float(rate or 10.0)))
        except ValueError:
            raise SweepError(f"--live takes PER@RATE items like 50@10, got {item!r}") from None
    return out


def check_args(args: argparse.Namespace, prog: str) -> tuple[list[Cell], list[str]]:
    """The grid and the FCW predictors, or SweepError for bad flags."""
    if not args.dataset:
        raise SweepError("give at least one --dataset SPEC")
    if getattr(args, "attack", None):
        from captures.live import DEFENCES
        from catc.attacks import parse

        try:
            for text in args.attack:
                parse(text)
        except ValueError as err:
            raise SweepError(str(err)) from None
        bad = [d for d in args.defences or [] if d not in DEFENCES]
        if bad:
            raise SweepError(f"--defences: unknown {bad[0]!r}; choose from "
                             f"{', '.join(DEFENCES)}")
    if args.predictors is None:
        args.predictors = list(available())
    for n in args.predictors + [p for p in (args.fcw_predictors or []) if p != "none"]:
        try:
            check(n)
        except ValueError as err:
            raise SweepError(str(err)) from None
    if args.seeds < 1 or args.workers < 1:
        raise SweepError("--seeds and --workers must be at least 1")
    try:
        grid = cells([p / 100.0 for p in args.per], args.rate, grid=args.grid, burst=args.burst)
        for c in grid:
            c.channel()
    except ValueError as err:
        raise SweepError(str(err)) from None
    fcw = args.predictors if args.fcw_predictors is None else \
        [p for p in args.fcw_predictors if p != "none"]
    return grid, fcw


def run_sweep(args: argparse.Namespace, prog: str = "sweep") -> dict:
    """Load, run the grid (and the live cells), return the result document."""
    grid, fcw = check_args(args, prog)
    live_cells = parse_live(args.live)
    try:
        datasets, prov = load_datasets(args.dataset, args.max_trips)
    except DatasetError as err:
        raise SweepError(str(err)) from None
    n_trips = sum(len(v) for v in datasets.values())
    print(f"{prog}: {len(datasets)} datasets, {n_trips} trips, {len(grid)} cells x "
          f"{len(args.predictors)} predictors x {args.seeds} seeds "
          f"({'dask ' + args.dask if args.dask else f'{args.workers} workers'})",
          file=sys.stderr)
    t0 = time.monotonic()
    cpu: dict[str, float] = {}
    with Progress(prog) as progress:
        rows = sweep(datasets, args.predictors, grid, range(args.seeds), fcw_predictors=fcw,
                     workers=args.workers, dask=args.dask, progress=progress, cpu=cpu)
    elapsed = time.monotonic() - t0
    params = {"per": args.per, "rate": args.rate, "grid": args.grid, "burst": args.burst,
              "predictors": args.predictors, "fcw_predictors": fcw, "seeds": args.seeds,
              "max_trips": args.max_trips, "datasets": args.dataset}
    version = code_version()
    doc = {"format": "catc-sweep/1", "version": version, "params": params,
           "datasets": prov, "elapsed_s": round(elapsed, 1),
           "cpu_s": {k: round(v, 1) for k, v in cpu.items()},
           "engine": {"dask": args.dask} if args.dask else {"workers": args.workers},
           "rows": [dict(r.as_dict(), version=version.get("git", version["catc-hil"]))
                    for r in rows]}
    if live_cells:
        from captures.live import live_checks

        first = next(iter(datasets.values()))[0]
        who = "hgp" if "hgp" in args.predictors else args.predictors[0]
        doc["live"] = live_checks(args.dataset[0], first, who, live_cells,
                                  seed=0, speed=args.live_speed, progress=sys.stderr,
                                  keep=getattr(args, "live_dir", None))
    if getattr(args, "attack", None):
        from captures.live import attack_checks

        first = next(iter(datasets.values()))[0]
        who = "hgp" if "hgp" in args.predictors else args.predictors[0]
        doc["attacks"] = attack_checks(args.dataset[0], first, who, args.attack, args.per,
                                       defences=args.defences, speed=args.live_speed,
                                       progress=sys.stderr)
    return doc


def run(args: argparse.Namespace) -> int:
    try:
        doc = run_sweep(args)
    except SweepError as err:
        print(f"captures sweep: {err}", file=sys.stderr)
        return 2
    print(summary(doc["rows"]))
    if doc.get("attacks"):
        from captures.live import attack_table

        print(attack_table(doc["attacks"]))
    print(f"{len(doc['rows'])} rows in {doc['elapsed_s']:.0f} s", file=sys.stderr)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))
        print(f"wrote {args.json}", file=sys.stderr)
    if args.plots:
        from captures.figures import sweep_figures

        for path in sweep_figures(doc, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0
