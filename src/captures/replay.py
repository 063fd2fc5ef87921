"""``captures replay``: run the CA-TC offline over real or simulated trips and list what it
raised: the safety applications' warning events as JSON lines, and a summary per trip.

No sockets: every trip's vehicles become BSM streams (:mod:`catc.replay`), a seeded
Bernoulli channel drops messages, and :meth:`catc.cam.ContextAwareMap.step` runs at each
of the host vehicle's 10 Hz samples, exactly as the OBU would on the same messages.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter

import numpy as np

from captures.progress import Progress
from catc.apps import APPS, AppsConfig, SafetyApps
from catc.cam import CamConfig, ContextAwareMap
from catc.channel import bernoulli_received
from catc.predict import NAMES, check
from catc.replay import run_offline, temp_id
from hil.datasets import DatasetError, load

HELP = """\
Replay trips through the Context-Aware Target Classification and the safety applications
(FCW, EEBL, BSW, LCW) with no sockets.  Prints one JSON object per warning event on stdout
(app, kind start/end, trip, rv id, time) and a summary per trip on stderr.  Examples:

  captures replay --dataset nyc:../shared/data/cv-pilot-samples/nycdot-fcw-event.json
  captures replay --dataset ../shared/data/openacc-zalazone/short_setting_dynamic_part1.csv \\
      --per 50 --predictor hgp"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="run the CA-TC and apps offline, print warning events",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", action="append", required=True, metavar="SPEC",
                   help="PATH or KIND:PATH (a file or a folder); repeat for more")
    p.add_argument("--host", metavar="ID",
                   help="host vehicle id (default: each trip's default host)")
    p.add_argument("--predictor", default="hgp", help=f"one of {','.join(NAMES)} (default hgp)")
    p.add_argument("--per", type=float, default=0.0,
                   help="packet error rate in %% for the RVs' BSMs (default 0)")
    p.add_argument("--seed", type=int, default=0, help="loss pattern seed (default 0)")
    p.add_argument("--apps", default=",".join(APPS),
                   help=f"comma-separated applications (default {','.join(APPS)})")
    p.set_defaults(func=run)


def _error(message: str) -> int:
    print(f"captures replay: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    try:
        check(args.predictor)
    except ValueError as err:
        return _error(str(err))
    if not 0.0 <= args.per <= 100.0:
        return _error("--per takes a percentage from 0 to 100")
    try:
        apps_config = AppsConfig(enabled=tuple(a for a in args.apps.split(",") if a))
    except ValueError as err:
        return _error(str(err))
    try:
        tables = [t for spec in args.dataset for t in load(spec)]
    except DatasetError as err:
        return _error(str(err))
    total = sum(len(t.tracks[args.host or t.default_host]) for t in tables
                if (args.host or t.default_host) in t.tracks)
    progress = Progress("replay")
    done = 0
    for table in tables:
        host = args.host or table.default_host
        if host not in table.tracks:
            return _error(f"trip {table.name}: no host vehicle {host!r}; vehicles: "
                          f"{', '.join(table.tracks)}")
        received = None
        if args.per > 0:
            n = max(len(tr) for tr in table.tracks.values())
            pattern = {vid: bernoulli_received(args.seed, f"{table.name}/{vid}", n,
                                               args.per / 100.0)
                       for vid in table.tracks}
            received = lambda vid, i, pattern=pattern: bool(pattern[vid][i])  # noqa: E731
        cam = ContextAwareMap(CamConfig(predictor=args.predictor, origin=table.origin),
                              SafetyApps(apps_config))
        names = {temp_id(v): v for v in table.tracks}
        ticks = 0
        warn_ticks: Counter[str] = Counter()
        tracked = []
        snap = None
        for snap in run_offline(table, cam, host, received):
            ticks += 1
            tracked.append(len(snap))
            warn_ticks.update({w.app for w in snap.warnings})
            for e in snap.events:
                print(json.dumps({"app": e.app, "kind": e.kind, "trip": table.name,
                                  "rv": names.get(e.rv_id, f"{e.rv_id:08X}"),
                                  "t": e.t_start if e.kind == "start" else e.t_end,
                                  "t_start": e.t_start}), flush=True)
            done += 1
            progress(done, total)
        counters = snap.counters if snap is not None else {}
        rejected = {k: v for k, v in counters.items()
                    if k in ("incomplete", "implausible", "late", "future", "duplicate",
                             "out_of_order", "jump") and v}
        progress.write(f"{table.name}: host {host}, {ticks} ticks, "
                       f"{np.mean(tracked or [0]):.1f} RVs tracked on average; warning ticks "
                       + (", ".join(f"{a} {warn_ticks[a]}" for a in apps_config.enabled))
                       + "; " + f"{counters.get('accepted', 0)} BSMs applied"
                       + (f", rejected {rejected}" if rejected else ""))
    return 0
