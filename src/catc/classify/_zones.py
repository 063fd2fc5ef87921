"""The zones of Eqs. (tc_longi), (tc_lateral) and (tc_heading), and one RV's classification.

Reference paper, section "Context-Aware Target Classification (CA-TC)", subsection
"Target Classification" (after Lee 2005 and Kim 2016); the equations are quoted in
:mod:`catc.classify`.  Here: the classes, the thresholds (:class:`ClassifyConfig`), the
threshold tests on one value (floats) and on many (arrays of codes into
:data:`LATERAL_CODES` / :data:`DIRECTION_CODES`), and :func:`classify` /
:func:`classify_pair`, the zones of one RV on the HV path coordinates of
:meth:`HostPath.project`.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from catc.classify._path import Array, HostPath, Point
from catc.geo import heading_diff_deg


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


#: Lateral classes by code in :class:`ZoneArrays` (``lateral`` index into this tuple).
LATERAL_CODES = (Lateral.FAR_LEFT, Lateral.LEFT, Lateral.ON_CENTRE, Lateral.RIGHT,
                 Lateral.FAR_RIGHT)
#: Direction classes by code.
DIRECTION_CODES = (Direction.ONGOING, Direction.ONCOMING, Direction.NOT_CLASSIFIED)


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


#: The thresholds every function takes by default.
DEFAULT = ClassifyConfig()


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


# --- the threshold tests on one value ---------------------------------------------------------

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


# --- the same tests on arrays, as codes -------------------------------------------------------

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


def direction_codes(diff_deg: Array, config: ClassifyConfig = DEFAULT
                    ) -> npt.NDArray[np.int8]:
    """Eq. (tc_heading) on ``|phi_RV - phi_lane|`` in ``[0, 180]``: codes into
    :data:`DIRECTION_CODES` (:func:`classify_direction` for arrays)."""
    diff_deg = np.asarray(diff_deg, dtype=float)
    return _first_true([diff_deg <= config.delta_phi_ongoing,
                        diff_deg >= config.delta_phi_oncoming], 2)


# --- one RV -----------------------------------------------------------------------------------

def classify(
    host: HostPath,
    rv_xy: Point,
    rv_heading_deg: float,
    config: ClassifyConfig = DEFAULT,
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
    config: ClassifyConfig = DEFAULT,
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
