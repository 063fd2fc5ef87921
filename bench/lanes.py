"""Lane estimation on the real OpenACC platoons: the CA-TC's lateral class of the vehicle
ahead against where the host actually drives next.

For every platoon file in ``../shared/data/openacc-zalazone`` (or ``--data``), every
vehicle is the host once with the vehicle in front of it as the RV, all BSMs received.
At each tick (host moving at ≥ 1 m/s) the truth is the RV's offset from the host's own
path over the next 10 s (:func:`catc.evaluate.hindsight_offset`), classified with the
paper's lateral bands (w_lane 3.6 m).  Three estimates are compared in one run:

* ``trail+arc``: the CAM's default (RVs ahead measured along their own trails);
* ``arc``: the paper's HV path prediction only (``CamConfig(trail_lanes=False)``);
* ``straight``: a straight-line projection on the host's heading.

Also the share of ticks the RV is Ahead and Ongoing.

    python bench/lanes.py [--json] [--data DIR] [--ph-tolerance M]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from pathlib import Path

import numpy as np

from catc.cam import CamConfig, ContextAwareMap
from catc.classify import HostPath, lateral_codes
from catc.datasets import openacc
from catc.evaluate import hindsight_offset
from catc.replay import run_offline, temp_id

DEFAULT_DATA = Path(os.environ.get(
    "CATC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
) / "openacc-zalazone"
W_LANE = 3.6


def score_file(path: Path, ph_tolerance_m: float) -> dict:
    table = openacc.parse(path.read_text(), path.stem)
    ids = [v for v in table.tracks if "#" not in v]
    runs = {}
    for label, trails in (("trail+arc", True), ("arc", False)):
        agree = n = ahead_ongoing = 0
        straight = 0
        for lead, host in itertools.pairwise(ids):
            h = table.tracks[host]
            cam = ContextAwareMap(CamConfig(predictor="ca", origin=table.origin,
                                            trail_lanes=trails,
                                            ph_tolerance_m=ph_tolerance_m))
            for k, snap in enumerate(run_offline(table, cam, host_id=host)):
                if snap.host.speed < 1.0:
                    continue
                try:
                    i = snap.index(temp_id(lead))
                except KeyError:
                    continue
                d = hindsight_offset(h.x[k:k + 100], h.y[k:k + 100], snap.x[i], snap.y[i])
                if d is None:
                    continue
                truth = lateral_codes(np.array([d]), W_LANE)[0]
                n += 1
                agree += snap.zone.lateral[i] == truth
                ahead_ongoing += bool(snap.zone.ahead[i]) and snap.zone.direction[i] == 0
                if label == "arc":
                    sd = HostPath(snap.host.x, snap.host.y, snap.host.heading).to_path_frame(
                        (snap.x[i], snap.y[i]))[1]
                    straight += lateral_codes(np.array([sd]), W_LANE)[0] == truth
        runs[label] = (agree / n, ahead_ongoing / n, n)
        if label == "arc":
            runs["straight"] = (straight / n, float("nan"), n)
    return {"file": path.stem, "ticks": runs["trail+arc"][2],
            "agree_trail_arc": round(runs["trail+arc"][0], 3),
            "agree_arc": round(runs["arc"][0], 3),
            "agree_straight": round(runs["straight"][0], 3),
            "ahead_ongoing_trail_arc": round(runs["trail+arc"][1], 4),
            "ahead_ongoing_arc": round(runs["arc"][1], 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="OpenACC folder")
    ap.add_argument("--ph-tolerance", type=float, default=CamConfig().ph_tolerance_m,
                    help="the CAM's path-history tolerance in m (default: CamConfig's)")
    args = ap.parse_args(argv)
    files = sorted(args.data.glob("*.csv"))
    if not files:
        print(f"bench/lanes.py: no OpenACC files in {args.data}", file=sys.stderr)
        return 2
    rows = []
    for f in files:
        rows.append(score_file(f, args.ph_tolerance))
        if not args.json:
            print(f"  done {f.name}", file=sys.stderr)
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print("lateral class of the vehicle ahead = where the host then drives (share of ticks)")
    print(f"{'file':<32} {'ticks':>6} {'trail+arc':>10} {'arc':>6} {'straight':>9} "
          f"{'ahead+ongoing':>14}")
    for r in rows:
        print(f"{r['file']:<32} {r['ticks']:>6} {r['agree_trail_arc']:>10.3f} "
              f"{r['agree_arc']:>6.3f} {r['agree_straight']:>9.3f} "
              f"{r['ahead_ongoing_trail_arc']:>14.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
