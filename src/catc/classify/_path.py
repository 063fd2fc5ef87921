"""The HV's path and HV path coordinates ``(s, d)``: the projection every classification uses.

Reference paper, section "Context-Aware Target Classification (CA-TC)": the CAM
leverages "vehicles' path history, road geometry ... HV path prediction".  The path ahead
of the HV is a circular arc of signed radius ``R = v / omega`` (:func:`hv_radius_m`), the
path behind is its path-history polyline (:func:`project_history`); conventions in
:mod:`catc.classify`.

The projection's formulas are element-wise helpers (:func:`tangent_frame`,
:func:`arc_length`, :func:`arc_offset`, :func:`arc_heading`) that take Python floats or
numpy arrays alike and apply the same IEEE operations in the same order to each entry:
:class:`HostPath` calls them on floats, :func:`catc.classify.classify_many` on arrays or
row by row (``catc/classify/_rows.py``), so the formulas are written once.
"""

from __future__ import annotations

import math
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import chain

import numpy as np
import numpy.typing as npt

from catc.geo import enu_heading_deg

Point = tuple[float, float]
Array = npt.NDArray[np.float64]
#: A float or a float array: what the element-wise helpers take and give.
F = typing.TypeVar("F", float, Array)


def hv_radius_m(speed_mps: float, yaw_rate_deg_s: float) -> float:
    """Signed radius of curvature ``R = v / omega`` of the HV's predicted path, metres.

    ``yaw_rate_deg_s`` is positive clockwise (J2735), so positive ``R`` is a right turn.
    A zero yaw rate, or a (near) standstill with no meaningful path, gives ``inf``
    (straight).
    """
    omega = math.radians(yaw_rate_deg_s)
    if omega == 0.0 or abs(speed_mps) < 1e-3 or not math.isfinite(omega):
        return math.inf
    return speed_mps / omega


# --- the projection's formulas, element-wise on floats or arrays ------------------------------

def tangent_frame(dx: F, dy: F, sin_h: float | F, cos_h: float | F) -> tuple[F, F]:
    """An ENU offset ``(dx, dy)`` from the HV in its straight frame: ``(u forward, v right)``
    for an HV heading ``h`` given by its sine and cosine.

    forward = (sin h, cos h); right = (cos h, -sin h) (forward turned 90 deg cw).
    """
    return dx * sin_h + dy * cos_h, dx * cos_h - dy * sin_h


def arc_length(sign: F, alpha: F, k: float) -> F:
    """``s = sign |alpha| / |k|``: the arc length to the turning angle ``alpha`` on the arc
    of curvature ``k``, with the sign (``sign`` is +-1) of ``u`` (:meth:`HostPath._on_arc`)."""
    return sign * abs(alpha) / abs(k)


def arc_offset(k: float, u: F, v: F, hyp: F) -> F:
    """``d = (2 v - k (u^2 + v^2)) / (1 + hypot(k u, 1 - k v))``, ``hyp`` being that hypot:
    the signed offset from the arc of curvature ``k`` (:meth:`HostPath._on_arc`)."""
    return (2.0 * v - k * (u * u + v * v)) / (1.0 + hyp)


def arc_heading(heading_deg: float | F, k: float, s: F,
                degrees: typing.Callable[[F], F]) -> F:
    """The path heading ``s`` metres along the arc: ``(heading + degrees(k s)) mod 360``.

    ``degrees`` is ``math.degrees`` on floats, ``np.degrees`` on arrays: both multiply by
    the constant ``180 / pi``.
    """
    return (heading_deg + degrees(k * s)) % 360.0


@dataclass(frozen=True, slots=True)
class PathPoint:
    """An RV position in HV path coordinates.

    ``s``: signed arc length along the HV path (m, positive ahead); ``d``: signed offset
    from the path (m, positive to the right); ``heading_deg``: heading of the HV path at
    the closest point (the paper's phi_lane there).
    """

    s: float
    d: float
    heading_deg: float


@dataclass(frozen=True, slots=True)
class HostPath:
    """The HV's path: current pose, predicted arc ahead and optional history behind.

    ``radius_m`` is the signed radius of curvature (positive = turning right, ``inf`` =
    straight; see :func:`hv_radius_m`).  ``history`` is the HV's path-history polyline in
    ENU metres, **most recent first**; the current position is prepended automatically
    when it is not already the first point.
    """

    x: float
    y: float
    heading_deg: float
    radius_m: float = math.inf
    history: tuple[Point, ...] = ()

    def __post_init__(self) -> None:
        if self.radius_m == 0.0 or math.isnan(self.radius_m):
            raise ValueError(f"radius_m must be non-zero (inf for straight), got {self.radius_m}")
        # tuple((float(px), float(py)) for px, py in history), iterated in C: the HV path
        # is built every tick with a history of up to two dozen points.
        history = tuple(self.history)  # the same tuple when it is one
        if not {2}.issuperset(map(len, history)):
            raise ValueError("every history point must be a pair (x, y)")
        coords = map(float, chain.from_iterable(history))
        object.__setattr__(self, "history", tuple(zip(coords, coords, strict=True)))

    @classmethod
    def from_motion(
        cls,
        x: float,
        y: float,
        heading_deg: float,
        speed_mps: float,
        yaw_rate_deg_s: float,
        history: Sequence[Point] = (),
    ) -> HostPath:
        """A host path from the HV state: ``R = v / omega`` (see :func:`hv_radius_m`)."""
        return cls(x, y, heading_deg, hv_radius_m(speed_mps, yaw_rate_deg_s), tuple(history))

    @property
    def curvature(self) -> float:
        """Signed curvature ``1 / R`` in 1/m (0 when straight, positive turning right)."""
        return 0.0 if math.isinf(self.radius_m) else 1.0 / self.radius_m

    def _local(self, rv_xy: Point) -> Point:
        """RV position in the HV's straight frame: (u forward, v right), metres."""
        h = math.radians(self.heading_deg)
        return tangent_frame(rv_xy[0] - self.x, rv_xy[1] - self.y, math.sin(h), math.cos(h))

    def _on_arc(self, u: float, v: float) -> PathPoint:
        """Project (u, v) onto the constant-curvature path through the HV.

        With curvature k the path is ``u = sin(k s) / k, v = (1 - cos(k s)) / k``; its
        centre is at ``(0, 1/k)``.  The closest point on the circle has turning angle
        ``alpha = atan2(k u, 1 - k v)``, so ``s = alpha / k``, and the signed radial offset
        is ``d = R - sign(R) * rho`` (rho = distance to the centre), written in a form that
        is exact as k -> 0: ``d = (2 v - k (u^2 + v^2)) / (1 + hypot(k u, 1 - k v))``.
        For k = 0 this is ``s = u, d = v``.  The sign of ``s`` follows the sign of ``u``
        (the paper's Xrel >= 0 test in the HV's tangent frame); arc lengths are limited to
        half a turn (``|s| <= pi |R|``).

        On Python floats with ``math.atan2`` and ``math.hypot`` (:mod:`catc.classify`
        says why the row path uses numpy's); ``s`` takes its sign with ``copysign``, which
        is :func:`arc_length` but for the sign bit of a NaN.
        """
        k = self.curvature
        if k == 0.0:
            return PathPoint(u, v, self.heading_deg % 360.0)
        ku, kv = k * u, 1.0 - k * v
        s = math.copysign(abs(math.atan2(ku, kv)) / abs(k), 1.0 if u >= 0.0 else -1.0)
        return PathPoint(s, arc_offset(k, u, v, math.hypot(ku, kv)),
                         arc_heading(self.heading_deg, k, s, math.degrees))

    def _on_history(self, rv_xy: Point) -> PathPoint | None:
        """Project onto the history polyline (behind the HV); None if it has no length.

        The arithmetic is :func:`project_history` on one point.
        """
        out = project_history(self, np.array([rv_xy[0]]), np.array([rv_xy[1]]))
        if out is None:
            return None
        s, d, heading = out
        return PathPoint(float(s[0]), float(d[0]), float(heading[0]))

    def project(self, rv_xy: Point) -> PathPoint:
        """The RV position in path coordinates (s, d) with the path heading there.

        Ahead (``u >= 0`` in the HV tangent frame): the predicted arc.  Behind: the history
        polyline if given, else the arc continued backwards.  An RV whose closest history
        point is the HV itself (beside it) keeps its tangent-frame coordinates.
        """
        u, v = self._local(rv_xy)
        if u >= 0.0 or not self.history:
            return self._on_arc(u, v)
        on_history = self._on_history(rv_xy)
        if on_history is None or on_history.s >= 0.0:
            return self._on_arc(u, v)
        return on_history

    def to_path_frame(self, rv_xy: Point) -> tuple[float, float]:
        """``(s, d)``: arc length along the HV path (m, + ahead), offset (m, + right)."""
        p = self.project(rv_xy)
        return p.s, p.d


def project_history(host: HostPath, px: Array, py: Array) -> tuple[Array, Array, Array] | None:
    """Points ``(px, py)`` projected onto the HV's history polyline (behind the HV):
    ``(s, d, heading_deg)`` arrays, or None when the polyline has no length.

    Arc length runs back from the HV (so ``s <= 0``), the offset is perpendicular to the
    closest segment, positive to the right of the direction of travel (which is from
    older to newer points), the heading is that direction.  Beyond the oldest point the
    last segment is extended.  The first closest segment wins.
    """
    pts = [(host.x, host.y)]
    for p in host.history:
        if p != pts[-1]:
            pts.append(p)
    if len(pts) < 2:
        return None
    P = np.asarray(pts)
    n_xy, o_xy = P[:-1], P[1:]  # newer, older end of each segment
    b = o_xy - n_xy  # backwards along the path
    seg = np.hypot(b[:, 0], b[:, 1])
    walked = np.concatenate(([0.0], np.cumsum(seg)[:-1]))
    ex0 = px[:, None] - n_xy[None, :, 0]
    ey0 = py[:, None] - n_xy[None, :, 1]
    t = (ex0 * b[None, :, 0] + ey0 * b[None, :, 1]) / (seg * seg)[None, :]
    t = np.maximum(t, 0.0)
    t[:, :-1] = np.minimum(t[:, :-1], 1.0)  # the oldest segment extends beyond its end
    ex = ex0 - t * b[None, :, 0]
    ey = ey0 - t * b[None, :, 1]
    dist2 = ex * ex + ey * ey
    j = np.argmin(dist2, axis=1)
    rows = np.arange(len(px))
    fx, fy = -b[j, 0] / seg[j], -b[j, 1] / seg[j]  # direction of travel
    exj, eyj = ex[rows, j], ey[rows, j]
    side = exj * fy - eyj * fx
    d = np.where(side != 0.0, np.copysign(np.sqrt(dist2[rows, j]), side), 0.0)
    s = -(walked[j] + t[rows, j] * seg[j])
    return s, d, np.asarray(enu_heading_deg(fx, fy), dtype=float)


def relative_position(
    hv_xy: Point,
    hv_heading_deg: float,
    rv_xy: Point,
    radius_m: float = math.inf,
    history: Sequence[Point] = (),
) -> tuple[float, float]:
    """``(longitudinal_m, lateral_m)`` of the RV along the HV path; lateral positive right.

    With the defaults (straight, no history) it is the ENU offset rotated into the HV
    frame.  See :class:`HostPath` for the curved and path-history cases.
    """
    host = HostPath(hv_xy[0], hv_xy[1], hv_heading_deg, radius_m, tuple(history))
    return host.to_path_frame(rv_xy)
