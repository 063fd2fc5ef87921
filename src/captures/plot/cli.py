"""The ``captures plot`` command: its flags, and the pictures it writes (:func:`stills`,
then :func:`captures.plot.movie.animate` with ``--gif`` / ``--mp4``), their paths printed
one per line; a bad flag or capture is one line on stderr and exit status 2."""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from pathlib import Path

from captures.plot.birdseye import birdseye
from captures.plot.load import Run, auto_times, load_run
from captures.plot.movie import animate
from captures.plot.timeline import timeline
from hil.capture.schema import OBU_EVENTS, OBU_TICKS

__all__ = ["HELP", "SNAP_S", "register", "run", "stills"]

HELP = f"""\
Plot a capture directory written by `rve run --capture DIR` and `obu run --capture DIR`:

  birdseye_t{{T}}.png  the HV, the RVs' true tracks, the OBU's estimates (fresh BSM or
                     predicted), RVs missing from the OBU's map, the CA-TC zones as lane
                     bands and the active warnings, at OBU time T (--at; by default the
                     start of every FCW warning, the middle of the run and the tick of
                     the largest PTE)
  timeline.png       PTE per RV over time (0.5 m line), delivered / dropped messages,
                     warning events per app
  run.gif            with --gif: an animation of the whole run (run.mp4 with --mp4,
                     which needs ffmpeg)

Times T are seconds on the OBU's clock (the `t` of {OBU_TICKS} / {OBU_EVENTS}).
The paths written are printed one per line."""

#: A --at time may be this far (s) from the nearest OBU tick.
SNAP_S = 0.15


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``captures plot`` to the subcommands ``sub``."""
    p = sub.add_parser("plot", help="bird's-eye views, timeline and animation of a capture",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", type=Path, metavar="DIR", help="the shared capture directory")
    p.add_argument("--out", type=Path, metavar="OUTDIR", help="where to write (default "
                   "DIR/plots)")
    p.add_argument("--at", metavar="T1,T2,...", help="bird's-eye views at these OBU times "
                   "(s); default: FCW starts, the middle, the largest PTE")
    p.add_argument("--gif", action="store_true", help="also write run.gif")
    p.add_argument("--mp4", action="store_true", help="also write run.mp4 (needs ffmpeg)")
    p.add_argument("--fps", type=float, help="animation frames per second (default: real "
                   "time)")
    p.add_argument("--window", type=float, default=60.0, metavar="M",
                   help="half-width of the bird's-eye view, m (default 60)")
    p.add_argument("--max-frames", type=int, default=300, metavar="N",
                   help="most frames of the animation (default 300)")
    p.set_defaults(func=run)


def _times(text: str | None, run_: Run) -> list[float]:
    if text is None:
        return auto_times(run_)
    out = []
    for part in text.split(","):
        try:
            t = float(part)
        except ValueError:
            raise ValueError(f"--at: not a time in seconds: {part.strip()!r}") from None
        i = run_.tick_index(t)
        if not math.isfinite(t) or abs(run_.tick_t[i] - t) > SNAP_S:
            raise ValueError(f"--at {part.strip()}: no OBU tick there (ticks run from "
                             f"{run_.tick_t[0]:.1f} to {run_.tick_t[-1]:.1f} s)")
        out.append(float(run_.tick_t[i]))
    return out


def _check_flags(args: argparse.Namespace) -> None:
    if not (args.window > 0 and math.isfinite(args.window)):
        raise ValueError(f"--window must be > 0, got {args.window}")
    if args.max_frames < 2:
        raise ValueError(f"--max-frames must be >= 2, got {args.max_frames}")
    if args.fps is not None and not (args.fps > 0 and math.isfinite(args.fps)):
        raise ValueError(f"--fps must be > 0, got {args.fps}")
    if args.mp4 and shutil.which("ffmpeg") is None:
        raise ValueError("--mp4 needs ffmpeg on PATH (--gif needs nothing more)")


def stills(the_run: Run, times: list[float], out: Path, window: float = 60.0) -> list[Path]:
    """``birdseye_t{T}.png`` for each time and ``timeline.png`` in ``out``; their paths."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for t in times:
        fig = Figure(figsize=(11.5, 7.6))
        FigureCanvasAgg(fig)
        ax = fig.add_axes((0.06, 0.07, 0.58, 0.86))
        birdseye(ax, the_run, t, window=window)
        path = out / f"birdseye_t{t:.1f}.png"
        fig.savefig(path, dpi=110)
        written.append(path)
    fig = Figure(figsize=(12, 9.5), layout="constrained")
    FigureCanvasAgg(fig)
    timeline(fig, the_run)
    written.append(out / "timeline.png")
    fig.savefig(written[-1], dpi=110)
    return written


def run(args: argparse.Namespace) -> int:
    """``captures plot`` with the parsed ``args``; the exit status.  A capture file that
    cannot be read, or an ``--out`` that cannot be written, is an OSError that
    :func:`hil.cliargs.dispatch` prints in one line (``FILE: reason``, status 1)."""
    try:
        _check_flags(args)
        the_run = load_run(args.dir)
        times = _times(args.at, the_run)
    except (ValueError, KeyError, TypeError) as err:  # CaptureError too
        msg = str(err) if not isinstance(err, KeyError) else f"a capture file lacks {err}"
        print(f"captures plot: {msg}", file=sys.stderr)
        return 2
    out = args.out if args.out is not None else Path(args.dir) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    written = stills(the_run, times, out, window=args.window)
    for flag, name, writer in ((args.gif, "run.gif", "pillow"), (args.mp4, "run.mp4",
                                                                  "ffmpeg")):
        if flag:
            animate(the_run, out / name, fps=args.fps, max_frames=args.max_frames,
                    window=args.window, writer=writer)
            written.append(out / name)
    for path in written:
        print(path)
    return 0
