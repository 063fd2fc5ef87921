"""The host on the vehicle side against the private host channel, side by side.

Each dataset runs through the daemons twice at each PER, with the same seed and channel:
once with the host as a ready-made BSM on the private channel, once with ``rve run
--host-bus`` playing the car (its CAN bus through the RAV4 profile's DBC as a serial
slcan adapter on a pty, its GNSS as NMEA over UDP) and ``obu run --host-source vehicle``
reading it.  It prints, per run, coverage, PTE95, FCW accuracy and the FCW events, and
the vehicle path's ratio to the channel's PTE95.  Defaults: the built-in
``scenario:highway-braking`` (GNSS noise 0 and rve's default 0.5 m) and the real
comma2k19 minute (its own fixes), PER 0 and 50 %, 4x speed.

    python bench/vehicle_path.py [--json] [--dataset SPEC ...] [--per P ...] [--speed X]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from captures.live import run_daemons, vehicle_flags
from captures.score import score

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
DEFAULTS = ["scenario:highway-braking", "scenario:highway-braking@noise",
            f"comma2k19:{SHARED / 'comma2k19-example'}"]


def one(root: Path, spec: str, per: float, speed: float, vehicle: bool) -> dict:
    """One run; its score and FCW events."""
    dataset, _, variant = spec.partition("@")
    comma = dataset.startswith("comma2k19:")
    name = f"{'vehicle' if vehicle else 'channel'}-{per:g}-{abs(hash(spec)) % 10_000}"
    out = root / name
    rve = ["--dataset", dataset, "--per", f"{per:g}", "--speed", f"{speed:g}", "--seed", "1"]
    obu = ["--predictor", "hgp"]
    if vehicle:
        r, o = vehicle_flags(out, speed, gnss_delay=0.2 if comma else 0.1)
        rve += r + ([] if comma or variant == "noise" else ["--gnss-noise", "0"])
        obu += o
    warnings = run_daemons(out, rve, obu)
    s = score(out)
    fcw = [(e["kind"], e["rv"], round(e["t"], 1)) for e in map(json.loads,
                                                               warnings.splitlines())
           if e["app"] == "fcw"]
    return {"coverage": s["run"]["coverage"], "pte95_m": s["pte95_m"],
            "fcw_accuracy": s["fcw_accuracy"], "fcw": s["fcw"], "fcw_events": fcw}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", action="append", help="a dataset spec (repeatable; "
                    "SPEC@noise: rve's default GNSS noise instead of none)")
    ap.add_argument("--per", action="append", type=float, help="PER, %% (repeatable)")
    ap.add_argument("--speed", type=float, default=4.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    datasets = args.dataset or DEFAULTS
    pers = args.per or [0.0, 50.0]
    rows = []
    with tempfile.TemporaryDirectory(prefix="catc-vehicle-path-") as tmp:
        for spec in datasets:
            for per in pers:
                ch = one(Path(tmp), spec, per, args.speed, vehicle=False)
                car = one(Path(tmp), spec, per, args.speed, vehicle=True)
                ratio = (car["pte95_m"] / ch["pte95_m"]) if ch["pte95_m"] else None
                rows.append({"dataset": spec, "per": per, "channel": ch, "vehicle": car,
                             "pte95_ratio": ratio})
                print(f"{spec} PER {per:g}: done", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'dataset':<34}{'PER':>5}  {'path':<8}{'cover':>7}{'PTE95 m':>9}{'ratio':>7}"
          f"{'FCW acc':>9}  FCW events (kind@t)")
    for r in rows:
        for path in ("channel", "vehicle"):
            x = r[path]
            ratio = "" if path == "channel" or r["pte95_ratio"] is None \
                else f"{r['pte95_ratio']:.3f}"
            events = " ".join(f"{k}@{t:g}" for k, _, t in x["fcw_events"]) or "-"
            label = r["dataset"].split("/")[-1][:33]
            print(f"{label:<34}{r['per']:>5g}  {path:<8}{x['coverage']:>7.3f}"
                  f"{x['pte95_m']:>9.4f}{ratio:>7}{x['fcw_accuracy']:>9.4f}  {events}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
