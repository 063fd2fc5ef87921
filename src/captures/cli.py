"""``captures``: capture-and-score post analysis.

Subcommands live in their own modules (``captures/decode.py``, ...) and register
themselves here.
"""

from __future__ import annotations

import sys

from captures import decode
from catc.cliargs import dispatch, make_parser

DESCRIPTION = """\
Capture-and-score post analysis for the V2X testbench.

  decode   print the BSMs in a file as JSON lines (raw UPER, hex, IEEE 1609.2,
           ODE OBU .bin logs, ODE JSON/XML records)

Scoring, sweeps and plots arrive with the OBU and captures issues."""


def main(argv: list[str] | None = None) -> int:
    parser, sub = make_parser("captures", DESCRIPTION)
    decode.register(sub)
    return dispatch(parser, argv)


if __name__ == "__main__":
    sys.exit(main())
