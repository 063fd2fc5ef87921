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
import json
import os
import sys
from pathlib import Path

from catc.cam import CamConfig
from catc.datasets import openacc
from catc.evaluate import lane_agreement

DEFAULT_DATA = Path(os.environ.get(
    "CATC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
) / "openacc-zalazone"


def score_file(path: Path, ph_tolerance_m: float) -> dict:
    table = openacc.parse(path.read_text(), path.stem)
    runs = {label: lane_agreement(table, CamConfig(
        predictor="ca", origin=table.origin, trail_lanes=trails,
        ph_tolerance_m=ph_tolerance_m)) for label, trails in (("trail+arc", True), ("arc", False))}
    t, a = runs["trail+arc"], runs["arc"]
    return {"file": path.stem, "ticks": t.ticks,
            "agree_trail_arc": round(t.agree / t.ticks, 3),
            "agree_arc": round(a.agree / a.ticks, 3),
            "agree_straight": round(a.agree_straight / a.ticks, 3),
            "ahead_ongoing_trail_arc": round(t.ahead_ongoing / t.ticks, 4),
            "ahead_ongoing_arc": round(a.ahead_ongoing / a.ticks, 4)}


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
