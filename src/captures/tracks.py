"""``captures tracks DIR``: the OBU's tracks (``obu.tracks.bin``) as people read them.

The tracks are written compactly (:mod:`hil.capture.tracks`); this prints them as the JSON
lines the OBU wrote before 2026-11-27 (one object per tracked RV and tick, the fields of
:func:`hil.capture.schema.track_rows`), or as CSV, segments in order.  A torn tail (the
OBU killed mid-write) ends the output, and one stderr line says where it was.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from hil.capture import Torn, block_rows, iter_blocks, schema, segment_files, torn_line

HELP = """\
Print the OBU's tracks of a capture directory (obu.tracks.bin, and its segments under
obu run --capture-max-mb) as JSON lines, one object per tracked RV and tick with the keys
t, sec_mark, id, x, y, speed, heading, source, age, fresh, lane, zone, s, d, predicted_x,
predicted_y, predicted_zone (as obu.tracks.jsonl had them), or with --csv as a table
(zone and predicted_zone split into three columns each).  --id keeps one RV (8 hex
digits).  In Python: hil.capture.read_columns(FILE) gives numpy columns
(pandas.DataFrame(...) of them is a table)."""

_ZONES = ("ahead", "lateral", "direction")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tracks", help="the OBU's compact tracks as JSON lines or CSV",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", type=Path, metavar="DIR", help="capture directory (obu run --capture)")
    p.add_argument("--csv", action="store_true", help="CSV instead of JSON lines")
    p.add_argument("--id", metavar="HEX", help="only this RV's rows")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    files = segment_files(args.dir, schema.OBU_TRACKS)
    if not files:
        print(f"captures tracks: {args.dir}: no {schema.OBU_TRACKS} (not an obu run --capture)",
              file=sys.stderr)
        return 2
    want = args.id.upper() if args.id else None
    torn: list[Torn] = []
    writer = None
    out = sys.stdout
    try:
        for _, path in files:
            if path.suffix == ".jsonl":  # a capture of before 2026-11-27: already JSON lines
                rows = (json.loads(line) for line in path.open() if line.strip())
            else:
                rows = (r for b in iter_blocks(path, lambda *t: torn.append(t))
                        for r in block_rows(b))
            for r in rows:
                if want is not None and r["id"] != want:
                    continue
                if not args.csv:
                    out.write(json.dumps(r, separators=(",", ":")) + "\n")
                    continue
                flat = {k: v for k, v in r.items() if k not in ("zone", "predicted_zone")}
                flat.update({z: v for z, v in zip(_ZONES, r["zone"], strict=True)})
                flat.update({f"p_{z}": v for z, v in zip(_ZONES, r["predicted_zone"],
                                                         strict=True)})
                if writer is None:
                    writer = csv.DictWriter(out, fieldnames=list(flat))
                    writer.writeheader()
                writer.writerow(flat)
    except ValueError as err:
        print(f"captures tracks: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # | head
        return 0
    line = torn_line(torn, "captures tracks")
    if line:
        print(line, file=sys.stderr)
        return 1
    return 0
