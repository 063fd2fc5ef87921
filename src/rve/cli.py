"""``rve``: the Remote Vehicle Emulator.

``rve run`` is the replay daemon (:mod:`rve.run`); ``rve encode`` the encoder it uses, on
its own.
"""

from __future__ import annotations

import os

# One BLAS thread (before numpy loads): the daemons' linear algebra is 31x31 matrices,
# where threads only spin (measured: the OBU used 106-121 % CPU without this).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import sys

from catc.errors import EncodeError
from catc.j2735 import encode_frame
from catc.j2735.ieee1609 import wrap_unsecured
from catc.records import KEYS, bsm_from_record
from hil.cliargs import dispatch, make_parser

DESCRIPTION = """\
Remote Vehicle Emulator: replays mobility logs as SAE J2735 BSM frames.

  run      replay a mobility log as BSM frames in real time over UDP or CAN, with
           scheduled dropouts, and record ground truth
  encode   turn BSM records (JSON lines) into UPER MessageFrames
  scenario generate a built-in traffic scenario with Eclipse SUMO (FCD XML)
  pki      make a test IEEE 1609.2 PKI (root CA, AA, pseudonym certificates) for --sign"""

PKI_HELP = """\
pki init DIR: create a test IEEE 1609.2 PKI in DIR (a new directory): a self-signed root
CA, an authorization CA (AA) signed by it, and one pseudonym certificate per remote
vehicle signed by the AA (explicit certificates, ECDSA NIST P-256, psid 0x20 in
appPermissions, valid from an hour ago for --days), each as LABEL.oer (COER) with its
private key LABEL.key.pem (PKCS#8, mode 0600), and pki.json listing them with their
HashedId8s.  DIR/foreign is a second PKI that nobody trusts (for attacks).  Every file is
new: a file or a symbolic link already in DIR's way is an error, and so is a DIR that is a
symbolic link or group- or world-writable.  A --seed is written nowhere (every key
derives from it): give it again to make the same PKI again.

  rve run --sign DIR ...        signs every RV's BSM with these pseudonyms
  obu run --verify enforce --trust DIR ...   trusts DIR's root and knows its AA"""


def _pki_init(args: argparse.Namespace) -> int:
    from hil.pki import PkiError, init

    try:
        manifest = init(args.dir, args.vehicles, args.days, seed=args.seed)
    except PkiError as err:
        print(f"rve pki init: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"rve pki init: cannot write {args.dir}: {err.strerror}", file=sys.stderr)
        return 2
    print(json.dumps({"dir": str(args.dir), "root": manifest["certificates"]["root"],
                      "aa": manifest["certificates"]["aa"],
                      "pseudonyms": len(manifest["pseudonyms"])}))
    return 0

ENCODE_HELP = f"""\
Read one BSM record per line (JSON with the keys {", ".join(KEYS)};
SI units and degrees, null or a missing key = unavailable, "id" = 8 hex digits)
and write the UPER MessageFrame of each: one hex line each, or with --binary the
raw frames back to back.  This is the inverse of `captures decode`."""


def _encode(args: argparse.Namespace) -> int:
    out = sys.stdout.buffer
    where = "" if args.input is sys.stdin else f"{args.input.name}: "
    try:
        for lineno, line in enumerate(args.input, 1):
            if not line.strip():
                continue
            try:
                frame = encode_frame(bsm_from_record(json.loads(line)))
            except (ValueError, EncodeError) as err:  # JSONDecodeError is a ValueError
                print(f"rve encode: {where}line {lineno}: {err}", file=sys.stderr)
                return 1
            if args.ieee1609:
                frame = wrap_unsecured(frame)
            out.write(frame if args.binary else frame.hex().upper().encode() + b"\n")
    except UnicodeDecodeError as err:  # reading the input: the loop's own are caught above
        print(f"rve encode: {where or 'standard input: '}not UTF-8 text (byte "
              f"{err.object[err.start]:#04x})", file=sys.stderr)
        return 1
    out.flush()
    return 0


def _run(args: argparse.Namespace) -> int:
    from hil.config import run_daemon
    from rve import run

    return run_daemon(args, "rve", run)


def main(argv: list[str] | None = None) -> int:
    from rve import flood, run, scenario

    parser, sub = make_parser("rve", DESCRIPTION)
    r = sub.add_parser("run", help="replay a mobility log as BSMs over UDP or CAN",
                       description=run.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    run.add_arguments(r)
    r.set_defaults(func=_run, parser=r)
    p = sub.add_parser("encode", help="BSM records (JSON lines) to UPER frames",
                       description=ENCODE_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", nargs="?", type=argparse.FileType("r"), default=sys.stdin,
                   metavar="FILE", help="JSON lines (default: standard input)")
    p.add_argument("--binary", action="store_true", help="write raw frames instead of hex lines")
    p.add_argument("--ieee1609", action="store_true",
                   help="wrap each frame in an unsecured IEEE 1609.2 envelope")
    p.set_defaults(func=_encode)
    f = sub.add_parser("flood", help="garbage at an OBU's RV port (corrupted copies of "
                                     "the RVE's frames, random and oversize datagrams)",
                       description=flood.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    flood.add_arguments(f)
    f.set_defaults(func=flood.command)
    s = sub.add_parser("scenario", help="generate a built-in traffic scenario with SUMO",
                       description=scenario.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    scenario.add_arguments(s)
    s.set_defaults(func=scenario.command)
    k = sub.add_parser("pki", help="make a test IEEE 1609.2 PKI for rve run --sign",
                       description=PKI_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ksub = k.add_subparsers(dest="pki_command", metavar="COMMAND", required=True)
    ki = ksub.add_parser("init", help="create a root CA, an AA and pseudonym certificates",
                         description=PKI_HELP,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    ki.add_argument("dir", metavar="DIR")
    ki.add_argument("--vehicles", type=int, default=64,
                    help="pseudonym certificates, one per remote vehicle (default 64)")
    ki.add_argument("--days", type=float, default=30.0,
                    help="validity period of every certificate in days (default 30)")
    ki.add_argument("--seed", help="derive the keys from this string (reproducible PKI; "
                                   "for tests only: whoever knows it has every key; it is "
                                   "not stored)")
    ki.set_defaults(func=_pki_init)
    return dispatch(parser, argv)


if __name__ == "__main__":
    sys.exit(main())
