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

One RV and many
---------------
The projection's formulas are written once, as element-wise helpers on floats or arrays
(``_path.py``), and reached two ways:

* one RV, on Python floats: :meth:`HostPath.project`, :func:`classify`,
  :func:`classify_pair`, :func:`relative_position` (``_path.py``, ``_zones.py``);
* many, the CAM's every tick: :func:`classify_many` and :func:`classify_paths`
  (``_rows.py``), on arrays, or row by row on floats for a few rows.

They differ in one thing: arctan2 and hypot of the arc.  One RV takes ``math.atan2`` and
``math.hypot``, many take numpy's (on arrays of all the rows, also for a few rows).  The
two need not agree in the last bit (numpy's SIMD loops against libm: on this project's
AVX-512 VM they differ on 1.5 % of arctan2 and 0.2 % of hypot arguments), and the
thresholds make a last bit visible at a lane boundary, so each way keeps the functions
it always had: the CAM's zones are what they were, and so are those of the one-RV
callers (:func:`catc.evaluate.lane_agreement`'s straight-line projection, the tests, any
user projecting a point).  Both ways take the history polyline from the same
:func:`project_history <catc.classify._path.project_history>`.

Everything here is pure computation: no I/O, no clocks.
"""

from catc.classify._path import HostPath, PathPoint, hv_radius_m, relative_position
from catc.classify._rows import ZoneArrays, classify_many, classify_paths
from catc.classify._trail import trail_offset
from catc.classify._zones import (
    DIRECTION_CODES,
    LATERAL_CODES,
    ClassifyConfig,
    Direction,
    Lateral,
    Longitudinal,
    Zone,
    classify,
    classify_direction,
    classify_lateral,
    classify_longitudinal,
    classify_pair,
    direction_codes,
    heading_difference_deg,
    lateral_codes,
)

__all__ = [
    "DIRECTION_CODES",
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
