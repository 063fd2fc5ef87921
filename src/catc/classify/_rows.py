"""The zones of many RV positions at once: :func:`classify` of every row, for the CAM's ticks.

Reference paper, section "Context-Aware Target Classification (CA-TC)", subsection
"Target Classification": Eqs. (tc_longi), (tc_lateral) and (tc_heading) on the HV path
coordinates of :meth:`HostPath.project`, for every RV of a tick (the OBU classifies
hundreds per tick, the current positions and the predicted ones).

There is one path, :func:`_classify_rows`: the projection's steps (tangent frame, arc,
history polyline), then the heading difference and the thresholds.  Up to
:data:`SMALL_ROWS` rows each step runs row by row on Python floats, through the same
element-wise helpers as on arrays (``catc/classify/_path.py``): the few RVs of a tick
cost a fraction of numpy's ~50 calls, each of which costs a microsecond or two whatever
the size.  The results are the arrays' bit for bit: ``+ - * /``, ``abs``, comparisons,
``%`` (fmod corrected to the divisor's sign, in CPython as in numpy's remainder) and
``math.degrees`` (a product with the constant 180/pi, as ``np.degrees``) are the IEEE
operations numpy applies to each entry, here in the same order; arctan2 and hypot, whose
numpy and math versions need not agree, are numpy's on arrays of the rows in both cases;
Eqs. (tc_lateral) and (tc_heading) are the scalar classifiers, which make the same
comparisons as :func:`lateral_codes` / :func:`direction_codes`.  tests/test_cam_exact.py
runs both on the same rows.  The helpers cost a Python call per row and formula: against
the formulas written out in the loop, about 0.7 % of the instructions of a CAM step with
one RV and 1.5 % with eight (``ca`` predictor, callgrind), the price of writing them once.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from catc.classify._path import (
    Array,
    HostPath,
    arc_heading,
    arc_length,
    arc_offset,
    project_history,
    tangent_frame,
)
from catc.classify._zones import (
    DEFAULT,
    DIRECTION_CODES,
    LATERAL_CODES,
    ClassifyConfig,
    Longitudinal,
    Zone,
    classify_direction,
    classify_lateral,
    direction_codes,
    lateral_codes,
)
from catc.geo import heading_diff_deg

#: Up to this many rows (RV positions) :func:`classify_many` and :func:`classify_paths` go
#: row by row on Python floats; above it, on numpy arrays (module docstring).
SMALL_ROWS = 16


@dataclass(frozen=True, slots=True, eq=False)
class ZoneArrays:
    """:func:`classify` of many RVs: one entry per RV.

    ``ahead`` is Eq. (tc_longi) as a bool; ``lateral`` and ``direction`` are codes into
    :data:`LATERAL_CODES` and :data:`DIRECTION_CODES`; ``s``, ``d``, ``lane_heading_deg``
    and ``heading_diff_deg`` as in :class:`Zone` / :class:`PathPoint`.
    """

    ahead: npt.NDArray[np.bool_]
    lateral: npt.NDArray[np.int8]
    direction: npt.NDArray[np.int8]
    s: Array
    d: Array
    lane_heading_deg: Array
    heading_diff_deg: Array

    def zone(self, i: int) -> Zone:
        """Entry ``i`` as a :class:`Zone`."""
        return Zone(Longitudinal.AHEAD if self.ahead[i] else Longitudinal.BEHIND,
                    LATERAL_CODES[self.lateral[i]], DIRECTION_CODES[self.direction[i]],
                    float(self.s[i]), float(self.d[i]), float(self.heading_diff_deg[i]))


def classify_many(host: HostPath, x: npt.ArrayLike, y: npt.ArrayLike,
                  heading_deg: npt.ArrayLike, config: ClassifyConfig = DEFAULT) -> ZoneArrays:
    """:func:`classify` of every RV position in ``x, y`` (ENU m) with ``heading_deg``.

    Same projection formulas and thresholds as the scalar path, with numpy's arctan2 and
    hypot (:mod:`catc.classify`); vectorised because the OBU classifies hundreds of RVs per
    tick.
    """
    return _classify_rows((host,), None, x, y, heading_deg, config)[0]


def classify_paths(hosts: Sequence[HostPath], counts: Sequence[int], x: npt.ArrayLike,
                   y: npt.ArrayLike, heading_deg: npt.ArrayLike,
                   config: ClassifyConfig = DEFAULT) -> list[ZoneArrays]:
    """:func:`classify_many` of several paths' RVs: the first ``counts[0]`` rows of ``x, y,
    heading_deg`` against ``hosts[0]``, the next ``counts[1]`` against ``hosts[1]``, ...

    The CAM classifies the current positions against the HV path and the predicted ones
    against the HV's predicted path, which has the same curvature.  Paths of one curvature
    are done in one pass over all the rows, each row with its own path's values: with a
    few RVs a tick's cost is per call, not per row.  Every row goes through the same
    operations as in a pass of its own, so the results are those of :func:`classify_many`
    of each path bit for bit (paths of different curvatures are done one by one).
    """
    bounds = []
    lo = 0
    for n in counts:
        bounds.append((lo, lo + n))
        lo += n
    if len({h.curvature for h in hosts}) > 1:
        return [classify_many(h, x[lo:hi], y[lo:hi], heading_deg[lo:hi], config)
                for h, (lo, hi) in zip(hosts, bounds, strict=True)]
    return _classify_rows(hosts, bounds, x, y, heading_deg, config)


def _path_row(host: HostPath) -> tuple[float, float, float, float, float, float]:
    """What the projection needs of a path: x, y, sin and cos of the heading, heading and
    heading mod 360 (the arc's lane heading at curvature 0)."""
    h = math.radians(host.heading_deg)
    return (host.x, host.y, math.sin(h), math.cos(h), host.heading_deg,
            host.heading_deg % 360.0)


def _classify_rows(hosts: Sequence[HostPath], bounds: list[tuple[int, int]] | None,
                   x: npt.ArrayLike, y: npt.ArrayLike, heading_deg: npt.ArrayLike,
                   config: ClassifyConfig) -> list[ZoneArrays]:
    """Rows ``lo:hi`` of each ``bounds[j]`` against ``hosts[j]`` (paths of one curvature);
    ``bounds`` None: one host, arrays of any shape the arithmetic broadcasts.  A few rows
    (1-d) go row by row on Python floats (module docstring)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    rv_heading = np.asarray(heading_deg, dtype=float)
    few = x.ndim == 1 and len(x) <= SMALL_ROWS and x.shape == y.shape == rv_heading.shape
    if few:
        bounds = bounds or [(0, len(x))]
    s, d, lane = _project_rows(hosts, bounds, x, y, few)
    if not few:
        diff = np.abs(np.asarray(heading_diff_deg(rv_heading, lane), dtype=float))
        fields = (s >= 0.0, lateral_codes(d, config.w_lane), direction_codes(diff, config),
                  s, d, lane, diff)
        if bounds is None:
            return [ZoneArrays(*fields)]
        return [ZoneArrays(*(f[lo:hi] for f in fields)) for lo, hi in bounds]
    diff: list[float] = []
    lateral: list[int] = []
    direction: list[int] = []
    for h, di, ln in zip(rv_heading.tolist(), d, lane, strict=True):
        # |heading_diff_deg(h, ln)|: wrapped to [-180, 180) as geo._wrap180 does it
        w = (h - ln + 180.0) % 360.0
        df = abs((0.0 if w >= 360.0 else w) - 180.0)
        diff.append(df)
        lateral.append(LATERAL_CODES.index(classify_lateral(di, config.w_lane)))
        direction.append(DIRECTION_CODES.index(classify_direction(df, config)))
    # Flat arrays (numpy converts a flat list fastest), field after field, sliced per path.
    n = len(s)
    values = np.array(s + d + lane + diff, dtype=np.float64)
    codes = np.array(lateral + direction, dtype=np.int8)
    ahead = values[:n] >= 0.0
    return [ZoneArrays(ahead[lo:hi], codes[lo:hi], codes[n + lo:n + hi], values[lo:hi],
                       values[n + lo:n + hi], values[2 * n + lo:2 * n + hi],
                       values[3 * n + lo:3 * n + hi]) for lo, hi in bounds]


def _project_rows(hosts: Sequence[HostPath], bounds: list[tuple[int, int]] | None,
                  x: Array, y: Array, few: bool) -> tuple:
    """:meth:`HostPath.project` of every row against its path: ``(s, d, lane heading)``,
    lists of floats when ``few`` (row by row), else arrays.

    Its steps on all the rows at once: the tangent frame, the arc ahead (numpy's arctan2
    and hypot, on arrays of all the rows either way), and for the rows behind a path with
    a history, that polyline wherever it gives ``s < 0``.
    """
    k = hosts[0].curvature
    # 1. (u, v) in the tangent frame of each row's path, the path's heading (and mod 360),
    # the rows behind (u < 0); row by row also k u and 1 - k v (arctan2's, hypot's)
    if few:
        xs, ys = x.tolist(), y.tolist()
        rows: list[tuple[float, float, float, float]] = []  # u, v, heading, heading mod 360
        ku: list[float] = []
        kv: list[float] = []
        behind: list = []
        for host, (lo, hi) in zip(hosts, bounds, strict=True):
            hx, hy, sh, ch, h, h0 = _path_row(host)
            behind.append([])
            for i in range(lo, hi):
                ui, vi = tangent_frame(xs[i] - hx, ys[i] - hy, sh, ch)
                rows.append((ui, vi, h, h0))
                ku.append(k * ui)
                kv.append(1.0 - k * vi)
                if ui < 0.0:
                    behind[-1].append(i)
    else:
        if len(hosts) == 1:
            hx, hy, sh, ch, heading, heading0 = _path_row(hosts[0])
        else:  # the path's values on each of its rows
            per_row = np.repeat(np.array([_path_row(h) for h in hosts]),
                                [hi - lo for lo, hi in bounds], axis=0)
            hx, hy, sh, ch, heading, heading0 = per_row.T
        u, v = tangent_frame(x - hx, y - hy, sh, ch)
        behind = u < 0.0
    # 2. The arc ahead (HostPath._on_arc), with numpy's arctan2 and hypot
    if k == 0.0:
        s, d, lane = ([r[0] for r in rows], [r[1] for r in rows], [r[3] for r in rows]) \
            if few else (u.copy(), v.copy(), np.full(u.shape, heading0))
    elif few:
        s, d, lane = [], [], []
        ku_a, kv_a = np.array(ku), np.array(kv)
        for (ui, vi, h, _), a, hp in zip(rows, np.arctan2(ku_a, kv_a).tolist(),
                                         np.hypot(ku_a, kv_a).tolist(), strict=True):
            si = arc_length(1.0 if ui >= 0.0 else -1.0, a, k)
            s.append(si)
            d.append(arc_offset(k, ui, vi, hp))
            lane.append(arc_heading(h, k, si, math.degrees))
    else:
        ku, kv = k * u, 1.0 - k * v
        s = arc_length(np.where(u >= 0.0, 1.0, -1.0), np.arctan2(ku, kv), k)
        d = arc_offset(k, u, v, np.hypot(ku, kv))
        lane = arc_heading(heading, k, s, np.degrees)
    # 3. The history behind (HostPath._on_history), where it gives s < 0
    for j, host in enumerate(hosts):
        if not host.history:
            continue
        if few:
            idx = behind[j]
            if not idx:
                continue
        else:
            lo, hi = bounds[j] if bounds else (0, None)
            rows_behind = behind if hi is None else behind[lo:hi]
            if not rows_behind.any():
                continue
            idx = np.flatnonzero(rows_behind) + lo
        hist = project_history(host, x[idx], y[idx])
        if hist is None:
            continue
        if few:
            for i, hs, hd, hl in zip(idx, *(a.tolist() for a in hist), strict=True):
                if hs < 0.0:
                    s[i], d[i], lane[i] = hs, hd, hl
        else:
            hs, hd, hl = hist
            use = hs < 0.0
            sel = idx[use]
            s[sel], d[sel], lane[sel] = hs[use], hd[use], hl[use]
    return s, d, lane

