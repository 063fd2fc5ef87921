"""Target classification (TC): the zone of a remote vehicle (RV) relative to the host (HV).

This implements the "Target Classification" subsection of the reference paper
(Context-Aware Target Classification with Hybrid Gaussian Process prediction, section
"Context-Aware Target Classification (CA-TC)"), which follows Lee 2005 and Kim 2016:

* Eq. (tc_longi), longitudinal::

      RV_class = Ahead   if Xrel >= 0
                 Behind  if Xrel <  0

* Eq. (tc_lateral), lateral, with ``ld`` the lateral distance (positive to the LEFT in
  the paper) and ``w_lane`` the lane width::

      Far Left   ld in ( 1.5 w_lane,  inf)
      Left       ld in ( 0.5 w_lane,  1.5 w_lane]
      On Centre  ld in [-0.5 w_lane,  0.5 w_lane]
      Right      ld in [-1.5 w_lane, -0.5 w_lane)
      Far Right  ld in (-inf,        -1.5 w_lane)

* Eq. (tc_heading), direction, comparing the lane heading ``phi_lane`` with the RV
  heading ``phi_RV``::

      Ongoing         |phi_RV - phi_lane| <= dphi_ongoing
      Oncoming        |phi_RV - phi_lane| >= dphi_oncoming
      not classified  otherwise

Conventions
-----------
ENU metres (x east, y north) in the run's local frame; headings in degrees clockwise
from north (J2735, as in :mod:`catc.geo`); yaw rate in deg/s positive clockwise
(J2735 YawRate, as in :mod:`catc.predict.base`).

Path coordinates ``(s, d)`` are measured along the HV's path, not as a straight-line
projection ("the CAM leverages vehicles' path history, road geometry ... HV path
prediction"):

* ``s`` (the paper's ``Xrel``) is the signed arc length from the HV to the point of its
  path closest to the RV; positive ahead.
* ``d`` is the signed offset of the RV from that point, **positive to the RIGHT** of the
  direction of travel (the J2735 / NED-style sense: clockwise headings, y to the right).
  The paper's ``ld`` is positive to the left, so ``ld = -d``.  Eq. (tc_lateral) is
  symmetric in ``|ld|`` (closed at +-0.5 w_lane, Left/Right closed at +-1.5 w_lane), so
  only the side changes sign.

The path ahead of the HV is a circular arc of signed radius ``R = v / omega`` (constant
speed and yaw rate; positive ``R`` = turning right, centre on the right; ``inf`` =
straight).  The path behind is the HV's path-history polyline when one is given, else
the same arc run backwards.  ``phi_lane`` in Eq. (tc_heading) is taken as the heading of
the HV path at the RV's closest point (the arc tangent there, or the history segment's
direction), so a vehicle in the same lane around a bend stays Ongoing.

Everything here is pure computation: no I/O, no clocks.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import chain, pairwise

import numpy as np
import numpy.typing as npt

from catc.geo import enu_heading_deg, heading_diff_deg

__all__ = [
    "LATERAL_CODES",
    "ClassifyConfig",
    "Direction",
    "HostPath",
    "Lateral",
    "Longitudinal",
    "PathPoint",
    "Zone",
    "ZoneArrays",
    "classify",
    "classify_direction",
    "classify_lateral",
    "classify_longitudinal",
    "classify_many",
    "classify_pair",
    "classify_paths",
    "direction_codes",
    "heading_difference_deg",
    "hv_radius_m",
    "lateral_codes",
    "relative_position",
    "trail_offset",
]

Point = tuple[float, float]


class Longitudinal(enum.Enum):
    """Eq. (tc_longi): the sign of the longitudinal offset along the HV path."""

    AHEAD = "ahead"
    BEHIND = "behind"


class Lateral(enum.Enum):
    """Eq. (tc_lateral): the lane the RV is in, relative to the HV's lane."""

    FAR_LEFT = "far_left"
    LEFT = "left"
    ON_CENTRE = "on_centre"
    RIGHT = "right"
    FAR_RIGHT = "far_right"


class Direction(enum.Enum):
    """Eq. (tc_heading): travel direction relative to the lane.

    ``NOT_CLASSIFIED`` is the paper's own "else, not classified" case: heading
    differences strictly between ``delta_phi_ongoing`` and ``delta_phi_oncoming``
    (with the default 45/135 deg thresholds this is crossing or turning traffic).
    """

    ONGOING = "ongoing"
    ONCOMING = "oncoming"
    NOT_CLASSIFIED = "not_classified"


@dataclass(frozen=True, slots=True)
class ClassifyConfig:
    """Thresholds of Eqs. (tc_lateral) and (tc_heading)."""

    #: Lane width w_lane in metres.  The paper gives no value; 3.6 m is the project's
    #: DESIGN.md default ("lane width 3.6 m (assumed)"), a typical (US 12 ft) lane.
    w_lane: float = 3.6
    #: Delta phi_ongoing in degrees.  Not given in the paper: our choice.  45 deg splits
    #: the circle into quadrants, so "ongoing" is within half a right angle of the lane.
    delta_phi_ongoing: float = 45.0
    #: Delta phi_oncoming in degrees.  Not given in the paper: our choice, symmetric with
    #: delta_phi_ongoing (within 45 deg of the opposite direction).
    delta_phi_oncoming: float = 135.0

    def __post_init__(self) -> None:
        if not (self.w_lane > 0.0 and math.isfinite(self.w_lane)):
            raise ValueError(f"w_lane must be positive and finite, got {self.w_lane}")
        if not (0.0 <= self.delta_phi_ongoing <= self.delta_phi_oncoming <= 180.0):
            raise ValueError(
                "need 0 <= delta_phi_ongoing <= delta_phi_oncoming <= 180, got "
                f"{self.delta_phi_ongoing}, {self.delta_phi_oncoming}"
            )


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
class Zone:
    """The classification of one RV position; ``s``/``d`` as in :class:`PathPoint`.

    ``heading_diff_deg`` is ``|phi_RV - phi_lane|`` wrapped to ``[0, 180]``.
    """

    longitudinal: Longitudinal
    lateral: Lateral
    direction: Direction
    s: float
    d: float
    heading_diff_deg: float


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
        sh, ch = math.sin(h), math.cos(h)
        dx, dy = rv_xy[0] - self.x, rv_xy[1] - self.y
        # forward = (sin h, cos h); right = (cos h, -sin h) (forward turned 90 deg cw).
        return dx * sh + dy * ch, dx * ch - dy * sh

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
        """
        k = self.curvature
        if k == 0.0:
            return PathPoint(u, v, self.heading_deg % 360.0)
        alpha = math.atan2(k * u, 1.0 - k * v)
        s = math.copysign(abs(alpha) / abs(k), 1.0 if u >= 0.0 else -1.0)
        d = (2.0 * v - k * (u * u + v * v)) / (1.0 + math.hypot(k * u, 1.0 - k * v))
        return PathPoint(s, d, (self.heading_deg + math.degrees(k * s)) % 360.0)

    def _on_history(self, rv_xy: Point) -> PathPoint | None:
        """Project onto the history polyline (behind the HV); None if it has no length.

        Arc length runs back from the HV (so ``s <= 0``), the offset is perpendicular to
        the closest segment, positive to the right of the direction of travel (which is
        from older to newer points).  Beyond the oldest point the last segment is extended.
        The arithmetic is :func:`_project_history_many` on one point.
        """
        out = _project_history_many(self, np.array([rv_xy[0]]), np.array([rv_xy[1]]))
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


def classify_longitudinal(s: float) -> Longitudinal:
    """Eq. (tc_longi): Ahead if ``Xrel >= 0`` else Behind (``Xrel`` = ``s``)."""
    return Longitudinal.AHEAD if s >= 0.0 else Longitudinal.BEHIND


def classify_lateral(d: float, w_lane: float) -> Lateral:
    """Eq. (tc_lateral) with ``ld = -d`` (``d`` positive right, the paper's ``ld`` left).

    On Centre for ``|d| <= 0.5 w``; Left/Right for ``0.5 w < |d| <= 1.5 w``; Far beyond.
    """
    ld = -d
    if ld > 1.5 * w_lane:
        return Lateral.FAR_LEFT
    if ld > 0.5 * w_lane:
        return Lateral.LEFT
    if ld >= -0.5 * w_lane:
        return Lateral.ON_CENTRE
    if ld >= -1.5 * w_lane:
        return Lateral.RIGHT
    return Lateral.FAR_RIGHT


def heading_difference_deg(rv_heading_deg: float, lane_heading_deg: float) -> float:
    """``|phi_RV - phi_lane|`` as the smallest angle, in ``[0, 180]`` (359 vs 1 -> 2)."""
    return abs(float(heading_diff_deg(rv_heading_deg, lane_heading_deg)))


def classify_direction(diff_deg: float, config: ClassifyConfig) -> Direction:
    """Eq. (tc_heading) on ``diff_deg = |phi_RV - phi_lane|`` in ``[0, 180]``."""
    if diff_deg <= config.delta_phi_ongoing:
        return Direction.ONGOING
    if diff_deg >= config.delta_phi_oncoming:
        return Direction.ONCOMING
    return Direction.NOT_CLASSIFIED


_DEFAULT = ClassifyConfig()


def classify(
    host: HostPath,
    rv_xy: Point,
    rv_heading_deg: float,
    config: ClassifyConfig = _DEFAULT,
) -> Zone:
    """Classify one RV position: Eqs. (tc_longi), (tc_lateral), (tc_heading) on path coords."""
    p = host.project(rv_xy)
    diff = heading_difference_deg(rv_heading_deg, p.heading_deg)
    return Zone(
        longitudinal=classify_longitudinal(p.s),
        lateral=classify_lateral(p.d, config.w_lane),
        direction=classify_direction(diff, config),
        s=p.s,
        d=p.d,
        heading_diff_deg=diff,
    )


def classify_pair(
    host: HostPath,
    current_xy: Point,
    current_heading_deg: float,
    predicted_xy: Point,
    predicted_heading_deg: float,
    config: ClassifyConfig = _DEFAULT,
    predicted_host: HostPath | None = None,
) -> tuple[Zone, Zone]:
    """Zones of an RV's current and predicted positions (the CA-TC's current + forecast).

    The paper's example: "the local map is showing RV1 as behind, but the CAM is
    predicting RV1 will be behind right", so RV1 is also handed to LCW and BSW.  The
    predicted position is classified against ``predicted_host`` (the HV's own predicted
    path at that time) when given, else against the current ``host``.
    """
    now = classify(host, current_xy, current_heading_deg, config)
    target_host = predicted_host if predicted_host is not None else host
    later = classify(target_host, predicted_xy, predicted_heading_deg, config)
    return now, later


# --- vectorised form: every RV of a tick at once ----------------------------------------------

Array = npt.NDArray[np.float64]

#: Lateral classes by code in :class:`ZoneArrays` (``lateral`` index into this tuple).
LATERAL_CODES = (Lateral.FAR_LEFT, Lateral.LEFT, Lateral.ON_CENTRE, Lateral.RIGHT,
                 Lateral.FAR_RIGHT)
#: Direction classes by code.
DIRECTION_CODES = (Direction.ONGOING, Direction.ONCOMING, Direction.NOT_CLASSIFIED)


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


def _project_arc_many(k: float, heading_deg: float | Array, lane_k0: float | Array,
                      u: Array, v: Array) -> tuple[Array, Array, Array]:
    """:meth:`HostPath._on_arc` for arrays (same formulas, same branch at k = 0).

    ``heading_deg`` is the HV heading and ``lane_k0`` its ``heading_deg % 360.0``: scalars,
    or one per row when the rows belong to several paths of curvature ``k``.
    """
    if k == 0.0:
        return u.copy(), v.copy(), np.full(u.shape, lane_k0)
    ku, kv = k * u, 1.0 - k * v  # each used twice below, as the scalar formulas use them
    alpha = np.arctan2(ku, kv)
    s = np.where(u >= 0.0, 1.0, -1.0) * np.abs(alpha) / abs(k)
    d = (2.0 * v - k * (u * u + v * v)) / (1.0 + np.hypot(ku, kv))
    return s, d, (heading_deg + np.degrees(k * s)) % 360.0


def _project_history_many(host: HostPath, px: Array, py: Array
                          ) -> tuple[Array, Array, Array] | None:
    """:meth:`HostPath._on_history` for arrays: the first closest segment wins, as there."""
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


#: Up to this many rows (RV positions) :func:`classify_many` and :func:`classify_paths` go
#: row by row on Python floats (:func:`_classify_small`): the few RVs of a tick cost a
#: fraction of numpy's ~50 calls, each of which costs a microsecond or two whatever the
#: size.  Above it, the numpy path.
_SMALL_ROWS = 16


def _first_true(conditions: Sequence[npt.NDArray[np.bool_]], default: int
                ) -> npt.NDArray[np.int8]:
    """``np.select(conditions, range(len(conditions)), default)`` as int8: the index of the
    first true condition, else ``default``.  Applied last condition first, each overriding
    the ones after it, so the first true one wins exactly as in ``np.select`` (which costs
    several times as much)."""
    out = np.full(np.shape(conditions[0]), default, dtype=np.int8)
    for code in range(len(conditions) - 1, -1, -1):
        out = np.where(conditions[code], np.int8(code), out)
    return out


def lateral_codes(d: Array, w_lane: float) -> npt.NDArray[np.int8]:
    """Eq. (tc_lateral) on offsets ``d`` (positive right): codes into :data:`LATERAL_CODES`."""
    ld = -np.asarray(d, dtype=float)
    return _first_true([ld > 1.5 * w_lane, ld > 0.5 * w_lane, ld >= -0.5 * w_lane,
                        ld >= -1.5 * w_lane], 4)


def direction_codes(diff_deg: Array, config: ClassifyConfig = _DEFAULT
                    ) -> npt.NDArray[np.int8]:
    """Eq. (tc_heading) on ``|phi_RV - phi_lane|`` in ``[0, 180]``: codes into
    :data:`DIRECTION_CODES` (:func:`classify_direction` for arrays)."""
    diff_deg = np.asarray(diff_deg, dtype=float)
    return _first_true([diff_deg <= config.delta_phi_ongoing,
                        diff_deg >= config.delta_phi_oncoming], 2)


def classify_many(host: HostPath, x: npt.ArrayLike, y: npt.ArrayLike,
                  heading_deg: npt.ArrayLike, config: ClassifyConfig = _DEFAULT) -> ZoneArrays:
    """:func:`classify` of every RV position in ``x, y`` (ENU m) with ``heading_deg``.

    Same projection and thresholds as the scalar path (the tests check them against each
    other entry by entry); vectorised because the OBU classifies hundreds of RVs per tick.
    """
    return _classify_rows((host,), None, x, y, heading_deg, config)[0]


def classify_paths(hosts: Sequence[HostPath], counts: Sequence[int], x: npt.ArrayLike,
                   y: npt.ArrayLike, heading_deg: npt.ArrayLike,
                   config: ClassifyConfig = _DEFAULT) -> list[ZoneArrays]:
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
    ``bounds`` None: one host, arrays of any shape the arithmetic broadcasts."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    rv_heading = np.asarray(heading_deg, dtype=float)
    if x.ndim == 1 and len(x) <= _SMALL_ROWS and x.shape == y.shape == rv_heading.shape:
        return _classify_small(hosts, bounds or [(0, len(x))], x, y, rv_heading, config)
    if len(hosts) == 1:
        hx, hy, sh, ch, hh, lane_k0 = _path_row(hosts[0])
    else:  # the path's values on each of its rows
        rows = np.repeat(np.array([_path_row(h) for h in hosts]),
                         [hi - lo for lo, hi in bounds], axis=0)
        hx, hy, sh, ch, hh, lane_k0 = rows.T
    dx, dy = x - hx, y - hy
    u, v = dx * sh + dy * ch, dx * ch - dy * sh
    s, d, lane = _project_arc_many(hosts[0].curvature, hh, lane_k0, u, v)
    behind = u < 0.0
    for host, (lo, hi) in zip(hosts, bounds or [(0, None)], strict=True):
        rows_behind = behind if hi is None else behind[lo:hi]
        if not (host.history and rows_behind.any()):
            continue
        idx = np.flatnonzero(rows_behind) + lo
        hist = _project_history_many(host, x[idx], y[idx])
        if hist is not None:
            hs, hd, hl = hist
            use = hs < 0.0
            sel = idx[use]
            s[sel], d[sel], lane[sel] = hs[use], hd[use], hl[use]
    diff = np.abs(np.asarray(heading_diff_deg(rv_heading, lane), dtype=float))
    fields = (s >= 0.0, lateral_codes(d, config.w_lane), direction_codes(diff, config),
              s, d, lane, diff)
    if bounds is None:
        return [ZoneArrays(*fields)]
    return [ZoneArrays(*(f[lo:hi] for f in fields)) for lo, hi in bounds]


def _classify_small(hosts: Sequence[HostPath], bounds: list[tuple[int, int]], x: Array,
                    y: Array, rv_heading: Array, config: ClassifyConfig) -> list[ZoneArrays]:
    """:func:`_classify_rows` of a few rows (1-d arrays), row by row on Python floats.

    The results are the numpy path's bit for bit: ``+ - * /``, ``abs``, comparisons, ``%``
    (fmod corrected to the divisor's sign, in CPython as in numpy's remainder) and
    ``math.degrees`` (a product with the constant 180/pi, as ``np.degrees``) are the IEEE
    operations numpy applies to each entry, here in the same order; arctan2 and hypot,
    whose numpy and math versions need not agree, are numpy's on arrays of the rows, as
    there; Eqs. (tc_lateral) and (tc_heading) are the scalar classifiers, which make the
    numpy path's comparisons.  tests/test_cam_exact.py runs both paths on the same rows.
    """
    k = hosts[0].curvature
    xs, ys = x.tolist(), y.tolist()
    rows = []  # (u, v, HV heading, HV heading mod 360) of each row
    ku: list[float] = []  # k u and 1 - k v, the arguments of arctan2 and hypot
    kv: list[float] = []
    behind: list[list[int]] = []  # per path, its rows with u < 0
    for host, (lo, hi) in zip(hosts, bounds, strict=True):
        hx, hy, sh, ch, h, h0 = _path_row(host)
        behind.append([])
        for i in range(lo, hi):
            dx, dy = xs[i] - hx, ys[i] - hy
            u, v = dx * sh + dy * ch, dx * ch - dy * sh
            rows.append((u, v, h, h0))
            ku.append(k * u)
            kv.append(1.0 - k * v)
            if u < 0.0:
                behind[-1].append(i)
    s: list[float] = []
    d: list[float] = []
    lane: list[float] = []
    if k == 0.0:  # _project_arc_many, row by row
        for u, v, _, h0 in rows:
            s.append(u)
            d.append(v)
            lane.append(h0)
    else:
        ku_a, kv_a = np.array(ku), np.array(kv)
        for (u, v, h, _), a, hp in zip(rows, np.arctan2(ku_a, kv_a).tolist(),
                                       np.hypot(ku_a, kv_a).tolist(), strict=True):
            si = (1.0 if u >= 0.0 else -1.0) * abs(a) / abs(k)
            s.append(si)
            d.append((2.0 * v - k * (u * u + v * v)) / (1.0 + hp))
            lane.append((h + math.degrees(k * si)) % 360.0)
    for host, idx in zip(hosts, behind, strict=True):
        if not (host.history and idx):
            continue
        hist = _project_history_many(host, x[idx], y[idx])
        if hist is not None:
            for i, hs, hd, hl in zip(idx, *(a.tolist() for a in hist), strict=True):
                if hs < 0.0:
                    s[i], d[i], lane[i] = hs, hd, hl
    diff: list[float] = []  # |heading_diff_deg|: wrapped to [-180, 180) as geo._wrap180
    lateral_l: list[int] = []
    direction_l: list[int] = []
    for h, di, ln in zip(rv_heading.tolist(), d, lane, strict=True):
        w = (h - ln + 180.0) % 360.0
        df = abs((0.0 if w >= 360.0 else w) - 180.0)
        diff.append(df)
        lateral_l.append(LATERAL_CODES.index(classify_lateral(di, config.w_lane)))
        direction_l.append(DIRECTION_CODES.index(classify_direction(df, config)))
    # Flat arrays (numpy converts a flat list fastest), field after field, sliced per path.
    n = len(rows)
    values = np.array(s + d + lane + diff, dtype=np.float64)
    codes = np.array(lateral_l + direction_l, dtype=np.int8)
    ahead = values[:n] >= 0.0
    return [ZoneArrays(ahead[lo:hi], codes[lo:hi], codes[n + lo:n + hi], values[lo:hi],
                       values[n + lo:n + hi], values[2 * n + lo:2 * n + hi],
                       values[3 * n + lo:3 * n + hi]) for lo, hi in bounds]


def trail_offset(trail: Sequence[Point], p: Point) -> tuple[float, float, float] | None:
    """Where ``p`` lies relative to a vehicle's trail: ``(s, d, heading_deg)`` or None.

    ``trail`` is the vehicle's path history, most recent first, starting at its current
    position (ENU m).  ``s`` is the arc length from ``p``'s closest point on the trail
    forward to the vehicle, ``d`` the offset of ``p`` from the trail, positive to the
    right of the direction of travel, ``heading_deg`` the trail's direction of travel at
    that closest point (the lane heading there).  None when ``p``'s closest point is the trail's
    head approached from ahead (``p`` is ahead of the vehicle), its oldest point
    approached from beyond (the trail does not reach back to ``p``), or the trail has
    no length.  Used for lane estimation: an HV on the trail of an RV ahead drives
    where that RV drove (the CAM's "path history ... for lane estimation").
    """
    px, py = p
    best: tuple[float, float, float, float, float] | None = None  # (dist2, s, d, fx, fy)
    walked = 0.0
    last = len(trail) - 2
    sqrt = math.sqrt
    for i, ((nx, ny), (ox, oy)) in enumerate(pairwise(trail)):  # newer, older
        bx, by = ox - nx, oy - ny
        seg2 = bx * bx + by * by
        if seg2 == 0.0:
            continue
        seg = sqrt(seg2)
        t = ((px - nx) * bx + (py - ny) * by) / seg2
        off_head, off_tail = (i == 0 and t < 0.0), (i == last and t > 1.0)
        if t < 0.0:  # t = min(max(t, 0.0), 1.0), NaN and -0.0 included
            t = 0.0
        elif t > 1.0:
            t = 1.0
        ex, ey = px - (nx + t * bx), py - (ny + t * by)
        dist2 = ex * ex + ey * ey
        if best is None or dist2 < best[0]:
            if off_head or off_tail:
                best = (dist2, math.nan, math.nan, 0.0, 0.0)
            else:
                fx, fy = -bx / seg, -by / seg  # direction of travel
                side = ex * fy - ey * fx
                best = (dist2, walked + t * seg, math.copysign(sqrt(dist2), side), fx, fy)
        walked += seg
    if best is None or math.isnan(best[1]):
        return None
    return best[1], best[2], math.degrees(math.atan2(best[3], best[4])) % 360.0
