"""``captures decode FILE``: the BSMs in any file that holds frames, as JSON lines."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from catc.bsm import BSM
from catc.errors import DecodeError
from catc.j2735 import decode_bsm, decode_frame
from catc.j2735.sniff import as_text, extract_frames
from catc.records import bsm_to_record
from hil.capture import gunzip

from .canlog import can_log_kind, read_can_log

HELP = """\
Print every BSM in FILE as one JSON object per line, with the keys
msgCnt, id, secMark, lat, lon, elev, speed, heading, accel_long, accel_lat,
accel_vert, yaw_rate, width, length (SI units and degrees; null = unavailable).

FILE may hold raw UPER (a MessageFrame or a bare BasicSafetyMessage), hex text
(one frame per line), IEEE 1609.2-wrapped frames, an ODE/WYDOT OBU .bin log,
ODE JSON/XML records that carry the frame in hex, a pcapng capture of UDP, or a
CAN capture (candump -L log or Vector ASC: the ISO-TP transfers on every 11-bit
identifier are reassembled), or the OBU's obu.rx.jsonl.gz (gzip is read through).  The
kind is detected from the content.  A frame that does not decode, or a broken ISO-TP
transfer, is reported on stderr with its reason and skipped; the exit status is then 1.
A file that ends in a torn tail (its writer was killed, or the disk filled: a pcapng
block, a JSON line or a gzip stream cut off) gives every frame before it, and one line
on stderr says where the whole part ends (file and byte offset); the exit status is
then 1 too."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("decode", help="print the BSMs in a file as JSON lines",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", type=Path, metavar="FILE")
    p.add_argument("--full", action="store_true",
                   help="add every other field: accuracy, brakes, path history and prediction, "
                        "and the container it came in")
    p.set_defaults(func=run)


def is_message_frame(data: bytes) -> bool:
    """Whether ``data`` looks like a UPER MessageFrame rather than a bare BSM.

    True for a BSM frame (it starts 00 14) and for any frame whose first octet is 0
    (messageId < 256) and whose length determinant accounts for the data exactly, so
    that a non-BSM frame is reported as such.  A bare BasicSafetyMessage starting
    with those octets is possible in principle but does not occur in deployed logs.
    """
    if data[:2] == b"\x00\x14":
        return True
    if len(data) < 3 or data[0] != 0:
        return False
    n = data[2]
    if n < 0x80:
        return len(data) == 3 + n
    return len(data) >= 4 and len(data) == 4 + (((n & 0x3F) << 8) | data[3])


def decode_any(frame: bytes) -> BSM:
    """A MessageFrame, or else a bare BasicSafetyMessage."""
    return decode_frame(frame) if is_message_frame(frame) else decode_bsm(frame)


def run(args: argparse.Namespace) -> int:
    try:
        data = args.file.read_bytes()
    except OSError as err:
        print(f"captures decode: cannot read {args.file}: {err.strerror}", file=sys.stderr)
        return 2
    failures = 0
    torn: list[tuple[int, str]] = []
    gz_cut = None
    if data[:2] == b"\x1f\x8b":  # gzip (the OBU's obu.rx.jsonl.gz)
        data, gz_cut = gunzip(data)
    try:
        text = as_text(data[:4096])
        kind = can_log_kind(text) if text is not None else None
        if kind is not None:
            found = read_can_log(args.file, kind)
            items = found.frames
            for reason, n in sorted(found.isotp_errors.items()):
                failures += n
                print(f"captures decode: {args.file}: {n} broken ISO-TP transfer(s): {reason}",
                      file=sys.stderr)
        else:
            items = extract_frames(data, torn)
    except DecodeError as err:
        print(f"captures decode: {args.file}: {err}", file=sys.stderr)
        return 2
    if gz_cut is not None:  # offsets of the compressed file, not of its content
        torn = [gz_cut]
    if torn:
        failures += 1
        offset, why = torn[0]
        print(f"captures decode: {args.file}: torn at byte {offset} ({why}; killed, or the "
              f"disk full?): decoded the {len(items)} frames before it", file=sys.stderr)
    out = sys.stdout
    for index, item in enumerate(items):
        try:
            bsm = decode_any(item.frame)
        except DecodeError as err:
            failures += 1
            print(f"captures decode: {args.file} frame {index} ({item.container}): {err}",
                  file=sys.stderr)
            continue
        record = bsm_to_record(bsm, full=args.full)
        if args.full:
            record["container"] = item.container
        out.write(json.dumps(record) + "\n")
    if not items:
        print(f"captures decode: {args.file}: holds no frames (decoded values only?)",
              file=sys.stderr)
    return 1 if failures else 0
