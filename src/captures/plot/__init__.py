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
from collections import defaultdict
from pathlib import Path

import numpy as np

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

#: Lateral codes of catc.classify.LATERAL_CODES, as people say them.
LATERAL_TEXT = ("far left", "left", "same lane", "right", "far right")
#: Direction codes of catc.classify.DIRECTION_CODES (only the unusual ones are shown).
DIRECTION_TEXT = ("", "oncoming", "crossing")
#: Past and future of the true tracks drawn in the bird's-eye view (s).
PAST_S, FUTURE_S = 5.0, 2.0
#: A vehicle's outline when the capture does not say (m): a mid-size car.
CAR_LENGTH, CAR_WIDTH = 4.8, 1.9
#: A --at time may be this far (s) from the nearest OBU tick.
SNAP_S = 0.15


# --- drawing helpers --------------------------------------------------------------------------

def _fwd_right(heading_deg: np.ndarray | float):
    h = np.radians(heading_deg)
    return (np.sin(h), np.cos(h)), (np.cos(h), -np.sin(h))


def _car(x: float, y: float, heading: float, length: float = CAR_LENGTH,
         width: float = CAR_WIDTH) -> np.ndarray:
    """A car outline (pointed nose) centred at (x, y), pointing along ``heading``."""
    (fx, fy), (rx, ry) = _fwd_right(heading)
    lo, wi = length / 2.0, width / 2.0
    local = ((-lo, -wi), (lo - 1.0, -wi), (lo, 0.0), (lo - 1.0, wi), (-lo, wi))
    return np.array([(x + u * fx + v * rx, y + u * fy + v * ry) for u, v in local])


def _centreline(run: Run, i: int, reach: float):
    """The HV path through tick ``i``: arc length s, x, y, heading (arrays), from the true
    past behind (the arc run backwards where it is short) to the arc ahead."""
    from catc.classify import hv_radius_m

    t = float(run.tick_t[i])
    hx, hy = run.tick_host[i]
    hv = run.truth.get(run.host_id)
    state = hv.at(t) if hv is not None else None
    heading, speed, yaw = (state[2], state[3], state[4]) if state else (0.0, 0.0, 0.0)
    if state is None and i + 1 < len(run.tick_t):  # no truth: the HV's own motion
        dx, dy = run.tick_host[i + 1] - run.tick_host[i]
        heading = math.degrees(math.atan2(dx, dy))
    radius = hv_radius_m(speed, yaw)
    k = 0.0 if math.isinf(radius) else 1.0 / radius

    def arc(s: np.ndarray):
        (fx, fy), (rx, ry) = _fwd_right(heading)
        if k == 0.0:
            u, v = s, np.zeros_like(s)
        else:
            u, v = np.sin(k * s) / k, (1.0 - np.cos(k * s)) / k
        return hx + u * fx + v * rx, hy + u * fy + v * ry, heading + np.degrees(k * s)

    s_ahead = np.linspace(0.0, reach, 40)
    ax_, ay_, ah_ = arc(s_ahead)
    # behind: the HV's true path, newest first, points at least 1 m apart
    bx, by = [hx], [hy]
    if hv is not None:
        past = np.flatnonzero(hv.t < t - 1e-6)[::-1]
        walked = 0.0
        for j in past:
            d = math.hypot(hv.x[j] - bx[-1], hv.y[j] - by[-1])
            if d < 1.0:
                continue
            walked += d
            bx.append(float(hv.x[j]))
            by.append(float(hv.y[j]))
            if walked > reach:
                break
    bx_a, by_a = np.array(bx[::-1]), np.array(by[::-1])  # oldest first
    if len(bx_a) >= 3:
        seg = np.hypot(np.diff(bx_a), np.diff(by_a))
        s_b = -np.concatenate((np.cumsum(seg[::-1])[::-1], [0.0]))
        h_b = np.degrees(np.arctan2(np.gradient(bx_a), np.gradient(by_a)))
        h_b = heading + ((h_b - heading + 180.0) % 360.0 - 180.0)
        walked_back = -s_b[0]
    else:
        s_b, bx_a, by_a, h_b, walked_back = np.zeros(1), bx_a[:1], by_a[:1], \
            np.array([heading]), 0.0
    if walked_back < reach:  # extend straight back along the oldest heading
        s_ext = np.linspace(-reach, -walked_back, 10)[:-1]
        (fx, fy), _ = _fwd_right(h_b[0])
        ex = bx_a[0] + (s_ext + walked_back) * fx
        ey = by_a[0] + (s_ext + walked_back) * fy
        s_b = np.concatenate((s_ext, s_b))
        bx_a, by_a = np.concatenate((ex, bx_a)), np.concatenate((ey, by_a))
        h_b = np.concatenate((np.full(len(s_ext), h_b[0]), h_b))
    return (np.concatenate((s_b[:-1], s_ahead)), np.concatenate((bx_a[:-1], ax_)),
            np.concatenate((by_a[:-1], ay_)), np.concatenate((h_b[:-1], ah_)))


def _offset_line(x, y, heading, d):
    _, (rx, ry) = _fwd_right(heading)
    return x + d * rx, y + d * ry


def _text_angle(heading: float) -> float:
    """Screen angle (deg) of text running along ``heading``, kept upright."""
    a = (90.0 - heading + 180.0) % 360.0 - 180.0
    return a - 180.0 if a > 90.0 else a + 180.0 if a < -90.0 else a


def _add(ax, patch):
    """Add a patch without the data-limit update of ``add_patch`` (the view is fixed)."""
    ax.add_artist(patch)
    return patch


def _plot(ax, x, y, **kw):
    """``ax.plot`` without autoscaling (the view is fixed), several times faster."""
    from matplotlib.lines import Line2D

    line = Line2D(np.atleast_1d(x), np.atleast_1d(y), **kw)
    ax.add_artist(line)
    return line


def _zones(ax, run: Run, i: int, window: float, obstacles) -> None:
    from matplotlib.patches import Polygon

    w = run.w_lane
    s, x, y, h = _centreline(run, i, 1.6 * window)
    edges = (-2.5, -1.5, -0.5, 0.5, 1.5, 2.5)
    fills = ("#ebebeb", "#dfe9f4", "#bcd4ec", "#dfe9f4", "#ebebeb")
    names = ("far left", "left", "same lane", "right", "far right")
    for k in range(5):
        x0, y0 = _offset_line(x, y, h, edges[k] * w)
        x1, y1 = _offset_line(x, y, h, edges[k + 1] * w)
        poly = np.column_stack((np.concatenate((x0, x1[::-1])),
                                np.concatenate((y0, y1[::-1]))))
        _add(ax, Polygon(poly, closed=True, facecolor=fills[k], edgecolor="none", zorder=0))
    for e in edges[1:-1]:
        ex, ey = _offset_line(x, y, h, e * w)
        _plot(ax, ex, ey, color="white", lw=1.2, ls=(0, (5, 4)), zorder=0.5)
    # Ahead / Behind: the line across the road at the HV, and the words
    hx, hy = run.tick_host[i]
    h0 = float(np.interp(0.0, s, h))
    cx, cy = _offset_line(np.array([hx, hx]), np.array([hy, hy]), h0,
                          np.array([-2.5 * w, 2.5 * w]))
    _plot(ax, cx, cy, color="#555555", lw=0.8, ls="--", zorder=0.6)
    # the words and the lane names where no vehicle is (obstacles: (n, 2) positions)
    inside = (np.abs(x - hx) <= 0.86 * window) & (np.abs(y - hy) <= 0.86 * window)
    obstacles = np.asarray(obstacles, dtype=float).reshape(-1, 2)

    def clearest(cands: np.ndarray, offsets) -> int:
        best, best_d = int(cands[0]), -1.0
        for j in cands:
            lx, ly = _offset_line(x[j], y[j], h[j], np.asarray(offsets, dtype=float))
            d = np.hypot(lx[:, None] - obstacles[:, 0], ly[:, None] - obstacles[:, 1]).min() \
                if len(obstacles) else np.inf
            d = min(d, 25.0) + 0.01 * abs(s[j])  # clear enough: the farther out the better
            if d > best_d:
                best, best_d = int(j), d
        return best

    lanes = np.arange(-2, 3) * w
    cands = np.flatnonzero(inside & (np.abs(s) >= 10.0))
    if len(cands):
        j = clearest(cands, lanes)
        for k, name in enumerate(names):
            lx, ly = _offset_line(x[j], y[j], h[j], lanes[k])
            ax.text(lx, ly, name, rotation=_text_angle(h[j]), rotation_mode="anchor",
                    ha="center", va="center", fontsize=6, color="#6d7a89", zorder=0.7)
        obstacles = np.vstack((obstacles, np.column_stack(_offset_line(x[j], y[j], h[j],
                                                                       lanes))))
    for sign, word in ((1.0, "AHEAD"), (-1.0, "BEHIND")):
        cands = np.flatnonzero(inside & (sign * s >= 8.0))
        if not len(cands):
            continue
        j = clearest(cands, (0.0,))
        ax.text(x[j], y[j], word, rotation=_text_angle(h[j]), rotation_mode="anchor",
                ha="center", va="center", fontsize=8, color="#8a9bb0", weight="bold",
                zorder=0.7)


def _metres(v: float) -> str:
    return "< 1 cm" if v < 0.01 else f"{v:.2f} m"


def _zone_text(ahead: bool, lateral: int, direction: int) -> str:
    text = f"{'ahead' if ahead else 'behind'}, {LATERAL_TEXT[lateral]}"
    return text + (f", {DIRECTION_TEXT[direction]}" if DIRECTION_TEXT[direction] else "")


def _legend(ax, horizon_s: float | None) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [
        Patch(facecolor="black", label="HV (host vehicle)"),
        Patch(facecolor="#2ca02c", edgecolor="black", label="OBU estimate: BSM this tick"),
        Patch(facecolor="#2ca02c", alpha=0.35, edgecolor="black", ls="--",
              label="OBU estimate: predicted (gap)"),
        Line2D([], [], color="#2ca02c", ls="--", lw=1.5, marker="s", mfc="white", ms=4,
               markevery=[0], label="predicted since the last BSM (\u25a1)"),
        Line2D([], [], marker="o", ls="", color="black", ms=3, label="true position"),
        Line2D([], [], color="#2ca02c", lw=0.8, label=f"true track (-{PAST_S:g} s)"),
        Line2D([], [], color="#2ca02c", lw=0.8, ls=":",
               label=f"true track (+{FUTURE_S:g} s)"),
        Patch(facecolor="none", edgecolor="#888888", ls="--",
              label="in the truth, missing from the map"),
        Patch(facecolor="#eeeeee", edgecolor=APP_COLOURS["fcw"], lw=2.5,
              label="RV of an active warning"),
    ]
    if horizon_s is not None:
        handles.insert(4, Line2D([], [], color="#2ca02c", ls="--", lw=1.0, marker=">",
                                 markevery=[1], ms=4,
                                 label=f"OBU's predicted position in {horizon_s:g} s"))
    ax.legend(handles=handles, loc="lower left", bbox_to_anchor=(1.02, 0.0), fontsize=7,
              frameon=False, borderaxespad=0.0)


# --- the three pictures -----------------------------------------------------------------------

def birdseye(ax, run: Run, t: float, window: float = 60.0, details: bool = True,
             legend: bool = True) -> int:
    """Draw the bird's-eye view of the tick nearest ``t`` on ``ax`` (see the module
    docstring); ``window`` is the half-width of the view (m).  ``details`` writes the list
    of RVs in view, ``legend`` the key, both to the right of the axes.  Returns the tick
    index drawn."""
    from matplotlib.patches import Polygon

    i = run.tick_index(t)
    tt = float(run.tick_t[i])
    hx, hy = run.tick_host[i]
    tr = run.tracks
    rows = np.arange(run.tick_rows[i], run.tick_rows[i + 1])
    in_map = {tr["id"][r]: r for r in rows}
    warn: dict[str, list] = defaultdict(list)
    for w in run.tick_warnings[i]:
        warn[w[1]].append(w)

    ax.set_xlim(hx - window, hx + window)
    ax.set_ylim(hy - window, hy + window)
    ax.set_aspect("equal", adjustable="box")
    ax.set_facecolor("#f7f7f2")
    obstacles = [(tr["x"][r], tr["y"][r]) for r in rows]
    for truth in run.truth.values():
        state = truth.at(tt)
        if state is not None:
            obstacles.append(state[:2])
    _zones(ax, run, i, window, obstacles)

    def visible(px, py, margin=0.0):
        return abs(px - hx) <= window + margin and abs(py - hy) <= window + margin

    # true tracks (5 s back, 2 s ahead) and true positions now: one collection each
    from matplotlib.collections import LineCollection

    lines = []
    past_xy, future_xy, colours = [], [], []
    for tid, truth in run.truth.items():
        state = truth.at(tt)
        if state is None:
            continue
        r = in_map.get(tid)
        if not visible(state[0], state[1], 5.0) and (r is None
                                                     or not visible(tr["x"][r], tr["y"][r])):
            continue
        colours.append("black" if tid == run.host_id else run.colours.get(tid, "#555555"))
        past = (truth.t >= tt - PAST_S) & (truth.t <= tt)
        future = (truth.t >= tt) & (truth.t <= tt + FUTURE_S)
        past_xy.append(np.column_stack((truth.x[past], truth.y[past])))
        future_xy.append(np.column_stack((truth.x[future], truth.y[future])))
        if tid != run.host_id:
            lines.append((tid, state))
    ax.add_collection(LineCollection(past_xy, colors=colours, linewidths=0.8, zorder=2),
                      autolim=False)
    ax.add_collection(LineCollection(future_xy, colors=colours, linewidths=0.8,
                                     linestyles=":", zorder=2), autolim=False)
    if lines:
        _plot(ax, [s[1][0] for s in lines], [s[1][1] for s in lines], marker="o", ls="",
              color="black", ms=2.5, zorder=6)

    # the HV
    hv = run.truth.get(run.host_id)
    hstate = hv.at(tt) if hv is not None else None
    h_heading = hstate[2] if hstate else 0.0
    _add(ax, Polygon(_car(hx, hy, h_heading), closed=True, facecolor="black",
                     edgecolor="black", zorder=5))
    (fx, fy), _ = _fwd_right(h_heading)
    ax.annotate("HV", (hx, hy), xytext=(-16 * fx, -16 * fy), textcoords="offset points",
                ha="center", va="center", fontsize=7, weight="bold", zorder=9,
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none",
                      "alpha": 0.7})

    # the OBU's estimates and the missing RVs
    listed = []
    outside = 0
    for tid, r in in_map.items():
        x, y = tr["x"][r], tr["y"][r]
        if not visible(x, y, 1.0):
            outside += 1
            continue
        colour = run.colours.get(tid, "#555555")
        fresh = bool(tr["fresh"][r])
        warned = tid in warn
        edge = APP_COLOURS.get(warn[tid][0][0], "red") if warned else "black"
        _add(ax, Polygon(_car(x, y, tr["heading"][r]), closed=True, facecolor=colour,
                         alpha=1.0 if fresh else 0.45, edgecolor=edge,
                         lw=2.5 if warned else 0.8, ls="-" if fresh else "--", zorder=7))
        g = tr["gap_start"][r]
        if not fresh:  # the predicted path since the last BSM, which is marked
            own = np.flatnonzero(tr["id"][max(g, 0):r + 1] == tid) + max(g, 0)
            if len(own) > 1:
                _plot(ax, tr["x"][own], tr["y"][own], color=colour, ls="--", lw=1.5, zorder=4)
                if g >= 0:
                    _plot(ax, tr["x"][g], tr["y"][g], marker="s", ls="", mfc="white",
                          mec=colour, ms=4, zorder=4)
        px, py = tr["pred_x"][r], tr["pred_y"][r]
        if np.isfinite(px) and np.isfinite(py):
            ax.annotate("", (px, py), (x, y), zorder=4, arrowprops={
                "arrowstyle": "->", "color": colour, "lw": 1.0, "ls": "--"})
        if warned:
            _plot(ax, [hx, x], [hy, y], color=edge, lw=1.0, alpha=0.7, zorder=3)
        tag = ("! " + "/".join(w[0].upper() for w in warn[tid]) + " " if warned else "") \
            + run.name(tid)
        ax.annotate(tag, (x, y), xytext=(0, 7), textcoords="offset points", ha="center",
                    va="bottom", fontsize=7, color=edge if warned else "black",
                    weight="bold" if warned else "normal", zorder=9,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none",
                          "alpha": 0.7})
        listed.append((float(tr["s"][r]), tid, r))
    missing = []
    for tid, state in lines:
        if tid in in_map or not visible(state[0], state[1], 1.0):
            continue
        _add(ax, Polygon(_car(state[0], state[1], state[2]), closed=True,
                         facecolor="none", edgecolor="#888888", ls="--", lw=1.0, zorder=7))
        ax.annotate(f"{run.name(tid)} missing", (state[0], state[1]), xytext=(0, -7),
                    textcoords="offset points", ha="center", va="top", fontsize=7,
                    color="#666666", style="italic", zorder=9)
        missing.append(tid)

    # title, warnings banner, details
    ax.set_title(f"t = {tt:.1f} s   {run.dataset}   PER {100 * run.per:g} % at "
                 f"{run.rate_hz:g} Hz   predictor {run.predictor}", fontsize=10)
    ax.set_xlabel("east [m]", fontsize=8)
    ax.set_ylabel("north [m]", fontsize=8)
    ax.tick_params(labelsize=7)
    if run.tick_warnings[i]:
        text = "\n".join(
            f"{w[0].upper()}  {run.name(w[1])}  range {w[2]:.1f} m"
            + (f" (threshold {w[3]:.1f} m)" if w[3] is not None else "")
            + (f", {w[4]}" if len(w) > 4 and w[4] else "")
            for w in run.tick_warnings[i])
        ax.text(0.01, 0.99, text, transform=ax.transAxes, ha="left", va="top", fontsize=8,
                color="white", weight="bold", zorder=10,
                bbox={"boxstyle": "round,pad=0.3", "fc": APP_COLOURS.get(
                    run.tick_warnings[i][0][0], "red"), "ec": "none", "alpha": 0.9})
    ax.text(0.99, 0.01, f"HV {run.tick_host_speed[i] * 3.6:.0f} km/h   tracked "
            f"{len(in_map)} ({outside} outside the view)   missing in view {len(missing)}",
            transform=ax.transAxes, ha="right", va="bottom", fontsize=7, zorder=10,
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "none", "alpha": 0.8})
    if details:
        # warned RVs first, then from the farthest ahead to the farthest behind
        listed.sort(key=lambda e: (e[1] not in warn, -e[0]))
        _details(ax, run, listed, missing, warn)
    if legend:
        _legend(ax, run.horizon_s if np.isfinite(tr["pred_x"]).any() else None)
    return i


def _details(ax, run: Run, listed: list, missing: list[str], warn: dict) -> None:
    """One block per RV of ``listed`` ((s, id, row) in order): zone now and predicted,
    source, age, PTE; as many as fit above the legend."""
    tr = run.tracks
    y = 0.0  # points below the top of the axes
    room = ax.get_position().height * ax.figure.get_figheight() * 72.0 - 150.0

    def text(dx: float, dy: float, s: str, **kw) -> None:
        ax.annotate(s, (1.0, 1.0), xycoords="axes fraction", xytext=(dx, dy),
                    textcoords="offset points", ha="left", va="top", **kw)

    shown = 0
    for _, tid, r in listed:
        fresh = bool(tr["fresh"][r])
        zone = _zone_text(tr["ahead"][r], tr["lateral"][r], tr["direction"][r])
        later = _zone_text(tr["p_ahead"][r], tr["p_lateral"][r], tr["p_direction"][r])
        source = "fresh BSM" if fresh else \
            f"predicted ({tr['source'][r]}), {tr['age'][r]:.1f} s since its BSM"
        pte = tr["pte"][r]
        lines = [f"{zone}", source + (f", PTE {_metres(pte)}" if np.isfinite(pte) else "")]
        if later != zone:
            lines.append(f"in {run.horizon_s:g} s: {later}")
        if -y + 17 + 8.6 * len(lines) > room:
            break
        shown += 1
        head = run.name(tid)
        colour = "black"
        if tid in warn:
            head = " ".join(w[0].upper() for w in warn[tid]) + "  " + head
            colour = APP_COLOURS.get(warn[tid][0][0], "red")
        text(10, y + 1, "\u25a0", fontsize=9, color=run.colours.get(tid, "#555555"))
        text(22, y, head, fontsize=8, weight="bold", color=colour)
        text(22, y - 11, "\n".join(lines), fontsize=7, color="#333333", linespacing=1.2)
        y -= 11 + 8.6 * len(lines) + 6
    if len(listed) > shown:
        text(10, y, f"... and {len(listed) - shown} more in view", fontsize=7)
        y -= 12
    if missing:
        text(10, y, "missing from the map:\n" + ", ".join(run.name(m) for m in missing),
             fontsize=7, color="#666666", style="italic")


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
