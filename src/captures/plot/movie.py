"""The animation of ``captures plot`` (``run.gif`` with ``--gif``, ``run.mp4`` with
``--mp4``, which needs ffmpeg): the bird's-eye view of the whole run, at most
``--max-frames`` frames, a GIF's frames drawn by forked processes.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from captures.plot.birdseye import birdseye
from captures.plot.load import Run

__all__ = ["animate"]


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
