"""``captures``: capture-and-score post analysis.

Subcommands live in their own modules (``captures/decode.py``, ...) and register
themselves here.
"""

from __future__ import annotations

import os
import sys

# One BLAS thread: the GP works on 30x30 matrices, where threads only add overhead
# (measured: 40x slower at TW 100 with two threads on a loaded machine).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from captures import (
    decode,
    defence,
    evaluate,
    plot,
    replay,
    report,
    score,
    sweep,
    tracks,
    train_bank,
    train_nn,
    view,
)
from hil.cliargs import dispatch, make_parser

DESCRIPTION = """\
Capture-and-score post analysis for the V2X testbench.

  decode       print the BSMs in a file as JSON lines (raw UPER, hex, IEEE 1609.2,
               ODE OBU .bin logs, ODE JSON/XML records)
  defence      what an attack cost against its clean twin: lost warnings, honest vehicles
               suspected or quarantined, detection with victims as false positives
  evaluate     PTE95 of each predictor on real trips under seeded packet loss
  plot         bird's-eye views, PTE / messages / warnings timeline and GIF of a capture
  replay       run the CA-TC and the safety apps offline, print their warning events
  report       the paper's experiments on real data as one HTML/Markdown report
  score        PTE, FCW accuracy and counts of an `rve run` + `obu run` capture
  sweep        PER x rate x predictor x dataset: the paper's tables, on real data
  tracks       the OBU's compact tracks (obu.tracks.bin) as JSON lines or CSV
  train-bank   train the HGP kernel bank on real trips (Algorithm 1)
  train-nn     train the neural baselines (AE, LSTM; direct and indirect) on real trips
  view         the OBU live view's page over a finished capture (play, slider, warnings)"""


def main(argv: list[str] | None = None) -> int:
    parser, sub = make_parser("captures", DESCRIPTION)
    decode.register(sub)
    defence.register(sub)
    evaluate.register(sub)
    plot.register(sub)
    replay.register(sub)
    report.register(sub)
    score.register(sub)
    sweep.register(sub)
    tracks.register(sub)
    train_bank.register(sub)
    train_nn.register(sub)
    view.register(sub)
    return dispatch(parser, argv)


if __name__ == "__main__":
    sys.exit(main())
