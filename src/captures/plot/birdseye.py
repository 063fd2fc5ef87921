"""The bird's-eye view of ``captures plot`` (``birdseye_t{T}.png``, and each frame of the
animation): the road around the host vehicle (HV) at one OBU tick, in the OBU's ENU frame
(metres east / north of the origin the OBU's config records), with

* the CA-TC zones as lane bands along the HV's path (:mod:`captures.plot.zones`),
* every vehicle's true track (5 s back, 2 s ahead),
* the OBU's estimate of every RV it tracks (filled: from a BSM of this tick; pale with a
  dashed edge: predicted, with the predicted path since the last BSM dashed; an arrow to
  the predicted position at the horizon when the capture's track rows have the predicted
  positions, :func:`hil.capture.schema.track_rows`),
* the RVs of the truth that are not in the OBU's map (hollow grey, "missing"),
* the RVs of active warnings (edged in the app's colour, with the warning in a banner),
* and, per RV in view, its zone now and at the horizon, where the estimate came from, its
  age and its PTE.
"""

from __future__ import annotations

from collections import defaultdict
from typing import TYPE_CHECKING

import numpy as np

from captures.plot.draw import add_artist, add_line, car, fwd_right
from captures.plot.load import Run
from captures.plot.style import APP_COLOURS
from captures.plot.zones import draw_zones, zone_text

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["FUTURE_S", "PAST_S", "birdseye"]

#: Past and future of the true tracks drawn in the bird's-eye view (s).
PAST_S, FUTURE_S = 5.0, 2.0


def _metres(v: float) -> str:
    return "< 1 cm" if v < 0.01 else f"{v:.2f} m"


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


def birdseye(ax: Axes, run: Run, t: float, window: float = 60.0, details: bool = True,
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
    draw_zones(ax, run, i, window, obstacles)

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
        add_line(ax, [s[1][0] for s in lines], [s[1][1] for s in lines], marker="o", ls="",
              color="black", ms=2.5, zorder=6)

    # the HV
    hv = run.truth.get(run.host_id)
    hstate = hv.at(tt) if hv is not None else None
    h_heading = hstate[2] if hstate else 0.0
    add_artist(ax, Polygon(car(hx, hy, h_heading), closed=True, facecolor="black",
                     edgecolor="black", zorder=5))
    (fx, fy), _ = fwd_right(h_heading)
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
        add_artist(ax, Polygon(car(x, y, tr["heading"][r]), closed=True, facecolor=colour,
                         alpha=1.0 if fresh else 0.45, edgecolor=edge,
                         lw=2.5 if warned else 0.8, ls="-" if fresh else "--", zorder=7))
        g = tr["gap_start"][r]
        if not fresh:  # the predicted path since the last BSM, which is marked
            own = np.flatnonzero(tr["id"][max(g, 0):r + 1] == tid) + max(g, 0)
            if len(own) > 1:
                add_line(ax, tr["x"][own], tr["y"][own], color=colour, ls="--", lw=1.5, zorder=4)
                if g >= 0:
                    add_line(ax, tr["x"][g], tr["y"][g], marker="s", ls="", mfc="white",
                          mec=colour, ms=4, zorder=4)
        px, py = tr["pred_x"][r], tr["pred_y"][r]
        if np.isfinite(px) and np.isfinite(py):
            ax.annotate("", (px, py), (x, y), zorder=4, arrowprops={
                "arrowstyle": "->", "color": colour, "lw": 1.0, "ls": "--"})
        if warned:
            add_line(ax, [hx, x], [hy, y], color=edge, lw=1.0, alpha=0.7, zorder=3)
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
        add_artist(ax, Polygon(car(state[0], state[1], state[2]), closed=True,
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
        zone = zone_text(tr["ahead"][r], tr["lateral"][r], tr["direction"][r])
        later = zone_text(tr["p_ahead"][r], tr["p_lateral"][r], tr["p_direction"][r])
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
