"""The road of the bird's-eye view: the HV's path through a tick and the CA-TC zones along
it as lane bands (the paper's section "Context-Aware Target Classification (CA-TC)",
Eqs. (tc_longi) and (tc_lateral), as :mod:`catc.classify` implements them).

Behind the HV the path is its true past; ahead it is the arc ``R = v / yaw rate``
(:func:`catc.classify.hv_radius_m`) of its true speed and yaw rate, as the CAM classifies
against; the lane width is ``w_lane`` of :class:`catc.classify.ClassifyConfig`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from captures.plot.draw import add_artist, add_line, fwd_right
from captures.plot.load import Run
from catc.classify import hv_radius_m

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["DIRECTION_TEXT", "LATERAL_TEXT", "draw_zones", "zone_text"]

#: Lateral codes of catc.classify.LATERAL_CODES, as people say them.
LATERAL_TEXT = ("far left", "left", "same lane", "right", "far right")
#: Direction codes of catc.classify.DIRECTION_CODES (only the unusual ones are shown).
DIRECTION_TEXT = ("", "oncoming", "crossing")


def _centreline(run: Run, i: int, reach: float):
    """The HV path through tick ``i``: arc length s, x, y, heading (arrays), from the true
    past behind (the arc run backwards where it is short) to the arc ahead."""
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
        (fx, fy), (rx, ry) = fwd_right(heading)
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
        (fx, fy), _ = fwd_right(h_b[0])
        ex = bx_a[0] + (s_ext + walked_back) * fx
        ey = by_a[0] + (s_ext + walked_back) * fy
        s_b = np.concatenate((s_ext, s_b))
        bx_a, by_a = np.concatenate((ex, bx_a)), np.concatenate((ey, by_a))
        h_b = np.concatenate((np.full(len(s_ext), h_b[0]), h_b))
    return (np.concatenate((s_b[:-1], s_ahead)), np.concatenate((bx_a[:-1], ax_)),
            np.concatenate((by_a[:-1], ay_)), np.concatenate((h_b[:-1], ah_)))


def _offset_line(x, y, heading, d):
    _, (rx, ry) = fwd_right(heading)
    return x + d * rx, y + d * ry


def _text_angle(heading: float) -> float:
    """Screen angle (deg) of text running along ``heading``, kept upright."""
    a = (90.0 - heading + 180.0) % 360.0 - 180.0
    return a - 180.0 if a > 90.0 else a + 180.0 if a < -90.0 else a


def draw_zones(ax: Axes, run: Run, i: int, window: float, obstacles: npt.ArrayLike
               ) -> None:
    """The zones of tick ``i`` on ``ax``: the five lateral bands of Eq. (tc_lateral)
    (``w_lane`` wide, along the HV's path of :func:`_centreline` over ``1.6 window`` m
    each way), the Ahead / Behind line of Eq. (tc_longi) across the road at the HV, and
    the lane names and the words AHEAD / BEHIND where they are clearest of the
    ``obstacles`` ((n, 2) vehicle positions)."""
    from matplotlib.patches import Polygon

    w = run.w_lane
    s, x, y, h = _centreline(run, i, 1.6 * window)
    edges = (-2.5, -1.5, -0.5, 0.5, 1.5, 2.5)
    fills = ("#ebebeb", "#dfe9f4", "#bcd4ec", "#dfe9f4", "#ebebeb")
    for k in range(5):
        x0, y0 = _offset_line(x, y, h, edges[k] * w)
        x1, y1 = _offset_line(x, y, h, edges[k + 1] * w)
        poly = np.column_stack((np.concatenate((x0, x1[::-1])),
                                np.concatenate((y0, y1[::-1]))))
        add_artist(ax, Polygon(poly, closed=True, facecolor=fills[k], edgecolor="none", zorder=0))
    for e in edges[1:-1]:
        ex, ey = _offset_line(x, y, h, e * w)
        add_line(ax, ex, ey, color="white", lw=1.2, ls=(0, (5, 4)), zorder=0.5)
    # Ahead / Behind: the line across the road at the HV, and the words
    hx, hy = run.tick_host[i]
    h0 = float(np.interp(0.0, s, h))
    cx, cy = _offset_line(np.array([hx, hx]), np.array([hy, hy]), h0,
                          np.array([-2.5 * w, 2.5 * w]))
    add_line(ax, cx, cy, color="#555555", lw=0.8, ls="--", zorder=0.6)
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
        for k, name in enumerate(LATERAL_TEXT):
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


def zone_text(ahead: bool, lateral: int, direction: int) -> str:
    """A zone of :mod:`catc.classify` (``ahead``, lateral and direction codes) in words."""
    text = f"{'ahead' if ahead else 'behind'}, {LATERAL_TEXT[lateral]}"
    return text + (f", {DIRECTION_TEXT[direction]}" if DIRECTION_TEXT[direction] else "")
