"""``obu``: the On-Board Unit, the device under test.

``obu run`` is the receiving daemon (:mod:`obu.run`); ``obu frame`` decodes one frame as
its receive path does, for frames copied from a capture tool.
"""

from __future__ import annotations

import os

# One BLAS thread (before numpy loads): the daemons' linear algebra is 31x31 matrices,
# where threads only spin (measured: the OBU used 106-121 % CPU without this).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import binascii
import json
import sys

from catc.errors import DecodeError
from catc.j2735 import decode_frame
from catc.j2735.ieee1609 import looks_like_1609, unwrap
from catc.records import bsm_to_record
from hil.cliargs import dispatch, make_parser

DESCRIPTION = """\
On-Board Unit: receives BSM frames and runs the CA-TC and the safety applications.

  run      receive BSM frames over UDP or CAN, run the CA-TC and the safety apps
  frame    decode one frame given in hex, as the OBU's receive path does"""

FRAME_HELP = """\
Decode one frame given in hex (spaces and colons allowed), as the OBU's receive path
does: an IEEE 1609.2 envelope is removed when present, then the UPER MessageFrame is
decoded.  Prints the whole BSM as one JSON object.  An undecodable frame prints its
reason (truncated, garbage, wrong-message-id, out-of-range, unsupported) and exits 1."""


def _frame(args: argparse.Namespace) -> int:
    text = "".join(args.hex).replace(":", "").replace(" ", "")
    try:
        data = binascii.unhexlify(text)
    except (binascii.Error, ValueError):
        print("obu frame: not a hex string", file=sys.stderr)
        return 2
    try:
        security = None
        if looks_like_1609(data):
            unwrapped = unwrap(data)
            data, security = unwrapped.frame, unwrapped.security
        record = bsm_to_record(decode_frame(data), full=True)
    except DecodeError as err:
        print(f"obu frame: {err}", file=sys.stderr)
        return 1
    record["ieee1609"] = security
    print(json.dumps(record, indent=2))
    return 0


def _run(args: argparse.Namespace) -> int:
    from hil.config import run_daemon
    from obu import run

    return run_daemon(args, "obu", run)


def main(argv: list[str] | None = None) -> int:
    from obu import run

    parser, sub = make_parser("obu", DESCRIPTION)
    r = sub.add_parser("run", help="the OBU daemon: receive, classify, warn",
                       description=run.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    run.add_arguments(r)
    r.set_defaults(func=_run, parser=r)
    p = sub.add_parser("frame", help="decode one hex frame", description=FRAME_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("hex", nargs="+", metavar="HEX")
    p.set_defaults(func=_frame)
    return dispatch(parser, argv)


if __name__ == "__main__":
    sys.exit(main())
