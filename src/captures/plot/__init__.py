"""``captures plot DIR``: pictures of an ``rve run`` + ``obu run`` capture.

* ``birdseye_t{T}.png``: the road around the host vehicle (HV) at one OBU tick, in the
  OBU's ENU frame (metres east / north of ``obu.config.json``'s origin): the CA-TC zones
  as lane bands along the HV's path (lane width ``w_lane`` of
  :class:`catc.classify.ClassifyConfig`; behind the HV its true past path, ahead the arc
  ``R = v / yaw rate`` of its true speed and yaw rate, as the CAM classifies against),
  every vehicle's true track (5 s back, 2 s ahead), the OBU's estimate of every RV it
  tracks (filled: from a BSM of this tick; pale with a dashed edge: predicted, with the
  predicted path since the last BSM dashed; an arrow to the predicted position at the
  horizon when ``obu.tracks.jsonl`` has ``predicted_x``/``predicted_y``), the RVs of the
  truth that are not in the OBU's map (hollow grey, "missing"), the RVs of active
  warnings (edged in the app's colour, with the warning in a banner) and, per RV in view,
  its zone now and at the horizon, where the estimate came from, its age and its PTE.
* ``timeline.png``: the PTE of every RV over time (the join of :mod:`captures.score`, so
  the pooled 95th percentile is its ``pte95_m``), the channel's delivered and dropped
  messages per RV and per second (``rve.schedule.jsonl``), and the warning events per app
  (``obu.events.jsonl``) as spans; FCW spans are shaded on every panel.
* ``run.gif`` (``--gif``) / ``run.mp4`` (``--mp4``, needs ffmpeg): the bird's-eye view of
  the whole run, at most ``--max-frames`` frames.

Times are on the OBU's clock (the ``t`` of ``obu.ticks.jsonl`` and ``obu.events.jsonl``;
for the built-in scenario it is the dataset's time).  The drawing functions take
matplotlib axes or figures and use the Agg canvas only (never pyplot), so other reports
can reuse them: :func:`load_run`, :func:`birdseye`, :func:`timeline`, :func:`animate`,
:func:`auto_times`.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from pathlib import Path

import numpy as np

from captures.plot.birdseye import birdseye
from captures.plot.load import Run, Truth, auto_times, load_run
from captures.plot.style import APP_COLOURS

__all__ = ["Run", "Truth", "animate", "auto_times", "birdseye", "load_run", "register", "run",
           "timeline"]

HELP = """\
Plot a capture directory written by `rve run --capture DIR` and `obu run --capture DIR`:

  birdseye_t{T}.png  the HV, the RVs' true tracks, the OBU's estimates (fresh BSM or
                     predicted), RVs missing from the OBU's map, the CA-TC zones as lane
                     bands and the active warnings, at OBU time T (--at; by default the
                     start of every FCW warning, the middle of the run and the tick of
                     the largest PTE)
  timeline.png       PTE per RV over time (0.5 m line), delivered / dropped messages,
                     warning events per app
  run.gif            with --gif: an animation of the whole run (run.mp4 with --mp4,
                     which needs ffmpeg)

Times T are seconds on the OBU's clock (the `t` of obu.ticks.jsonl / obu.events.jsonl).
The paths written are printed one per line."""

#: A --at time may be this far (s) from the nearest OBU tick.
SNAP_S = 0.15


def timeline(fig, run: Run) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Draw the PTE, message and warning timelines on ``fig``; returns the PTE samples
    drawn, per RV id: ``(t, pte)``."""
    from matplotlib.patches import Patch

    axes = fig.subplots(4, 1, sharex=True, gridspec_kw={"height_ratios": (3.2, 2.2, 1.2,
                                                                           1.3)})
    a_pte, a_raster, a_count, a_warn = axes
    tr = run.tracks
    t0, t1 = float(run.tick_t[0]), float(run.tick_t[-1])
    ids = run.rv_ids() + sorted(set(tr["id"]) - set(run.truth))

    # PTE
    drawn: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for tid in ids:
        rows = np.flatnonzero((tr["id"] == tid) & np.isfinite(tr["pte"]))
        if not len(rows):
            continue
        drawn[tid] = (tr["t"][rows], tr["pte"][rows])
        a_pte.plot(tr["t"][rows], tr["pte"][rows], lw=0.9,
                   color=run.colours.get(tid, "#555555"), label=run.name(tid))
    a_pte.axhline(0.5, color="black", ls="--", lw=1.0)
    a_pte.text(t0, 0.5, " 0.5 m", va="bottom", ha="left", fontsize=7)
    samples = run.pte_samples()
    p95 = f"{np.percentile(samples, 95):.3f} m" if len(samples) else "n/a"
    top = max(1.0, 1.1 * float(np.percentile(samples, 99.9))) if len(samples) else 1.0
    a_pte.set_ylim(0.0, top)
    clipped = len(samples) and samples.max() > top
    a_pte.set_title(f"{run.dataset}   PER {100 * run.per:g} % at {run.rate_hz:g} Hz   "
                    f"predictor {run.predictor}   PTE95 {p95} over {len(samples)} samples",
                    fontsize=10)
    a_pte.set_ylabel("PTE [m]" + (f"\n(max {samples.max():.1f} m\nis off the top)"
                                  if clipped else ""), fontsize=8)
    if drawn:
        a_pte.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7,
                     frameon=False, ncol=1 + len(drawn) // 14, title="RV", title_fontsize=7)

    # raster of messages per RV
    rv_row = {tid: k for k, tid in enumerate(ids)}
    k = np.array([rv_row.get(s, -1) for s in run.sched_id], dtype=int)
    ok = k >= 0
    for dropped, colour, label in ((False, "#7fb77e", "delivered"),
                                   (True, "#d62728", "dropped by the channel")):
        m = ok & (run.sched_dropped == dropped)
        a_raster.scatter(run.sched_t[m], k[m], marker="|", s=14, lw=0.7, color=colour,
                         label=label, rasterized=True)
    a_raster.set_yticks(range(len(ids)), [run.name(i) for i in ids], fontsize=6)
    a_raster.set_ylim(len(ids) - 0.5, -0.5)
    a_raster.set_ylabel("RV messages", fontsize=8)
    a_raster.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7,
                    frameon=False, markerscale=2)

    # counts per second
    if len(run.sched_t):
        edges = np.arange(math.floor(run.sched_t.min()), math.ceil(run.sched_t.max()) + 1.0)
        if len(edges) < 2:
            edges = np.array([edges[0], edges[0] + 1.0])
        sent, _ = np.histogram(run.sched_t[~run.sched_dropped], edges)
        lost, _ = np.histogram(run.sched_t[run.sched_dropped], edges)
        a_count.bar(edges[:-1], sent, width=1.0, align="edge", color="#7fb77e",
                    label="delivered")
        a_count.bar(edges[:-1], lost, width=1.0, align="edge", bottom=sent,
                    color="#d62728", label="dropped")
        rate = run.sched_dropped.mean()
        a_count.set_title(f"dropped {run.sched_dropped.sum()} of {len(run.sched_t)} "
                          f"({100 * rate:.1f} %)", fontsize=8, loc="right")
    a_count.set_ylabel("messages/s", fontsize=8)
    a_count.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, frameon=False)

    # warning spans
    apps = [a for a in ("fcw", "eebl", "bsw", "lcw") if any(s[0] == a for s in run.spans)]
    apps += sorted({s[0] for s in run.spans} - set(apps))
    for row, app in enumerate(apps):
        colour = APP_COLOURS.get(app, "#555555")
        mine = [s for s in run.spans if s[0] == app]
        a_warn.broken_barh([(s[2], max(s[3] - s[2], 0.1)) for s in mine], (row - 0.35, 0.7),
                           color=colour, alpha=0.85)
        last_end = -math.inf
        for s in mine:
            if s[2] >= last_end:  # names that do not run into each other
                a_warn.text(s[2], row - 0.4, run.name(s[1]), fontsize=6, va="bottom",
                            ha="left", color=colour)
                last_end = s[2] + 0.012 * (t1 - t0) * max(4, len(run.name(s[1])))
    a_warn.set_yticks(range(len(apps)), [a.upper() for a in apps], fontsize=8)
    a_warn.set_ylim(len(apps) - 0.4 if apps else 0.6, -0.9)
    a_warn.set_ylabel("warnings", fontsize=8)
    a_warn.set_xlabel("t [s] (OBU clock)", fontsize=8)
    for s in run.spans:
        if s[0] == "fcw":
            for a in axes:
                a.axvspan(s[2], max(s[3], s[2] + 0.1), color=APP_COLOURS["fcw"], alpha=0.08,
                          lw=0)
    a_warn.legend(handles=[Patch(color=APP_COLOURS["fcw"], alpha=0.2,
                                 label="FCW active\n(all panels)")],
                  loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, frameon=False)
    for a in axes:
        a.tick_params(labelsize=7)
        a.grid(axis="x", color="#dddddd", lw=0.5)
    a_warn.set_xlim(t0 - 0.5, t1 + 0.5)
    return drawn


def _frames(run: Run, max_frames: int) -> np.ndarray:
    step = max(1, math.ceil(len(run.tick_t) / max_frames))
    return np.arange(0, len(run.tick_t), step)


def animate(run: Run, path: Path | str, fps: float | None = None, max_frames: int = 300,
            window: float = 60.0, writer: str = "pillow", dpi: int = 80,
            workers: int | None = None) -> int:
    """Write the bird's-eye view of the whole run to ``path``: a GIF (``writer="pillow"``)
    or, through :class:`matplotlib.animation.FFMpegWriter`, an MP4 (``"ffmpeg"``).  Every
    k-th tick, so there are at most ``max_frames`` frames; ``fps`` defaults to real time.
    Returns the number of frames.

    Speed: the axes are not cleared between frames (only the last frame's artists are
    removed), the legend is rendered once and pasted as an image, there are no tick labels
    and no per-RV details, the GIF's frames are quantised by Pillow's fast octree to 128
    colours (the adaptive quantiser of matplotlib's PillowWriter takes longer than drawing
    a frame), and a GIF's frames are drawn by ``workers`` forked processes (default: up to
    two, one per CPU)."""
    frames = _frames(run, max_frames)
    if fps is None:
        dt = float(np.median(np.diff(run.tick_t))) if len(run.tick_t) > 1 else 0.1
        step = int(frames[1] - frames[0]) if len(frames) > 1 else 1
        fps = max(1.0, 1.0 / (dt * step))
    if writer == "ffmpeg":
        from matplotlib.animation import FFMpegWriter

        movie = FFMpegWriter(fps=fps)
        fig, ax = _movie_figure(dpi)
        movie.setup(fig, str(path), dpi=dpi)
        try:
            for _ in _draw_frames(fig, ax, run, frames, window):
                movie.grab_frame()
        finally:
            movie.finish()
        return len(frames)
    if writer != "pillow":
        raise ValueError(f"writer must be pillow or ffmpeg, got {writer!r}")
    if workers is None:
        import os

        workers = min(2, os.cpu_count() or 1)
    images = _gif_frames_parallel(run, frames, window, dpi, workers) \
        if workers > 1 and len(frames) >= 16 else None
    if images is None:
        images = _gif_frames((run, frames, window, dpi))
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=round(1000.0 / fps), loop=0)
    return len(frames)


def _movie_figure(dpi: int):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 5.6), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.08, 0.07, 0.6, 0.86))
    ax.set_autoscale_on(False)
    return fig, ax


def _draw_frames(fig, ax, run: Run, frames, window: float):
    """Draw the frames one after the other on ``ax``, yielding after each."""
    drawn: list = []
    for k, i in enumerate(frames):
        for artist in drawn:  # the previous frame's, not the axes (cheaper than clear)
            artist.remove()
        before = set(ax.get_children())
        birdseye(ax, run, float(run.tick_t[i]), window=window, details=False, legend=k == 0)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel(f"{2 * window:g} m x {2 * window:g} m around the HV, north up",
                      fontsize=8)
        ax.set_ylabel("")
        if k == 0:
            _freeze_legend(fig, ax)
        drawn = [a for a in ax.get_children() if a not in before
                 and a not in (ax.title, ax.xaxis, ax.yaxis, ax.patch)]
        yield i


def _gif_frames(job) -> list:
    """The GIF frames (Pillow "P" images) of ``job = (run, frames, window, dpi)``."""
    from PIL import Image

    run, frames, window, dpi = job
    fig, ax = _movie_figure(dpi)
    images = []
    for _ in _draw_frames(fig, ax, run, frames, window):
        fig.canvas.draw()
        rgba = Image.frombuffer("RGBA", fig.canvas.get_width_height(),
                                fig.canvas.buffer_rgba(), "raw", "RGBA", 0, 1)
        images.append(rgba.convert("RGB").quantize(
            128, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE))
    return images


def _gif_frames_parallel(run: Run, frames, window: float, dpi: int, workers: int):
    """:func:`_gif_frames` in ``workers`` forked processes, one contiguous part of the
    frames each (the same frames as one process draws); None where processes cannot be
    forked or this one runs threads (then the caller draws alone)."""
    import multiprocessing
    import threading
    from concurrent.futures import ProcessPoolExecutor

    if threading.active_count() > 1:  # forking a threaded process can deadlock the child
        return None
    try:
        context = multiprocessing.get_context("fork")
    except ValueError:
        return None
    parts = [p for p in np.array_split(frames, workers) if len(p)]
    try:
        with ProcessPoolExecutor(len(parts), mp_context=context) as pool:
            chunks = list(pool.map(_gif_frames, [(run, p, window, dpi) for p in parts]))
    except (OSError, RuntimeError):  # no fork here (sandbox, limits): draw in-process
        return None
    return [image for chunk in chunks for image in chunk]


def _freeze_legend(fig, ax) -> None:
    """Replace the legend (the same in every frame) by a picture of it: one image blit
    instead of laying out and rendering its text every frame."""
    legend = ax.get_legend()
    if legend is None:
        return
    fig.canvas.draw()
    box = legend.get_window_extent()
    pixels = np.asarray(fig.canvas.buffer_rgba())
    height = pixels.shape[0]
    x0, x1 = max(0, int(box.x0) - 2), min(pixels.shape[1], math.ceil(box.x1) + 2)
    y0, y1 = max(0, int(box.y0) - 2), min(height, math.ceil(box.y1) + 2)
    picture = pixels[height - y1:height - y0, x0:x1].copy()
    legend.remove()
    fig.figimage(picture, xo=x0, yo=y0, origin="upper", zorder=10)


# --- the command ------------------------------------------------------------------------------

def register(sub: argparse._SubParsersAction) -> None:
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
    try:
        _check_flags(args)
        the_run = load_run(args.dir)
        times = _times(args.at, the_run)
        out = args.out if args.out is not None else Path(args.dir) / "plots"
        out.mkdir(parents=True, exist_ok=True)
    except (ValueError, KeyError, TypeError, OSError) as err:  # CaptureError too
        msg = str(err) if not isinstance(err, KeyError) else f"a capture file lacks {err}"
        print(f"captures plot: {msg}", file=sys.stderr)
        return 2
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
