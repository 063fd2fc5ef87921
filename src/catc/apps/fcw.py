"""Cooperative Forward Collision Warning (FCW): the CAMP Linear warning range.

Source: the reference paper, section "Cooperative Forward Collision Warning (FCW)"
(it cites Lee 2005 and Kiefer et al. 2003, "Forward collision warning requirements
project", DOT HS 809 574).  Equations as printed there (both carry the label
``equ:FCW`` in the paper; called (FCW-1) and (FCW-2) here)::

    (FCW-1)  r_w = BOR + (v_HV - v_RV) t_d + 1/2 (a_HV - a_RV) t_d^2

    (FCW-2)  Case 1 (RV stationary):
                 BOR = v_HVp^2 / (-2 a_req)
             Case 2 (RV moving at the beginning and end of the scenario):
                 BOR = (v_HVp - v_RVp)^2 / (-2 (a_req - a_RV))
             Case 3 (RV moving at the beginning but stopping at the end):
                 BOR = v_HVp^2 / (-2 a_req) - v_RVp^2 / (-2 a_RV)

    with v_HVp = v_HV + a_HV t_d  and  v_RVp = v_RV + a_RV t_d.

"A warning is issued if the distance between the HV and the RV is less than the
r_w."  ``t_d`` is the driver and brake-system reaction delay, ``a_req`` the
deceleration the HV driver is assumed to apply after ``t_d`` (the paper: "modeled
in [Kiefer 2003] using real data").  BOR (brake onset range) is the gap needed at
brake onset so that the HV, braking at ``a_req``, just does not reach the RV.

Units: speeds in m/s (>= 0), accelerations in m/s^2 (negative = braking),
ranges in metres, times in seconds.

Choices this module makes where the paper is silent (all documented, all tested):

* **a_req** is the CAMP Required Deceleration Model (Kiefer et al. 1999, DOT HS 808 964,
  validated in Kiefer et al. 2003), a regression on last-second braking in feet and
  seconds::

      a_req = -5.308 + 0.685 a_RV + 2.570 [v_RV > 0] - 0.086 (v_HVp - v_RVp)   (ft/s^2)

  i.e. in SI ``-1.6179 + 0.685 a_RV + 0.7833 [v_RV > 0] - 0.086 (v_HVp - v_RVp)`` m/s^2
  (equivalently -0.165 g + 0.685 a_RV + 0.080 g [moving] - 0.00877 g·s/m · closing).
  Sources found here: the form and coefficients as quoted by the SAVE-IT task 9 report
  (Burgett / CAMP comparison, "in units of ft and s") and the CAMP Linear FCW
  implementation of Y. P. Fallah (2015, a co-author of the reference paper), which
  also uses the closing speed after the delay, ``v_HVp - v_RVp``.  Two domain limits,
  ours: the lead-acceleration input is ``min(a_RV, 0)`` and the closing speed
  ``max(0, v_HVp - v_RVp)`` (the model was fitted on stopped, constant-speed and
  braking leads that the HV closed on); this keeps ``a_req <= -0.835 m/s^2 < 0`` so
  the BOR formulas never divide by zero.  ``FcwConfig(a_req=...)`` replaces the model
  with a constant (the paper's formulas then use that value), which hand-computed
  tests use.
* **Predicted speeds are clamped at 0**: ``v_HVp = max(0, v_HV + a_HV t_d)`` (same
  for the RV).  A braking vehicle stops; it does not reverse within ``t_d``.  The
  delay term of (FCW-1) is used exactly as printed (not clamped).
* **Case selection.**  Case 1 if ``v_RV <= rv_stationary_speed``.  Otherwise case 3
  if the RV stops strictly before the HV would, braking from the predicted speeds
  (RV at ``a_RV``, HV at ``a_req``)::

      a_RV < 0  and  v_RVp / (-a_RV) < v_HVp / (-a_req)
      <=>  a_RV < 0  and  v_RVp * a_req > v_HVp * a_RV      (no division)

  and case 2 otherwise.  At equality (both stop at the same instant T) cases 2 and
  3 give the same BOR, ``T^2 (a_RV - a_req) / 2``, so the boundary is continuous;
  it is assigned to case 2.  (For a closing HV, "RV stops first" is equivalent to
  "the speeds would not equalise while the RV still moves", which is what the
  case-2 formula, the gap at equal speeds, assumes.)
* **Not closing at brake onset.**  The case-2 formula squares ``v_HVp - v_RVp`` and
  would report a positive range for an opening gap; when ``v_HVp <= v_RVp`` in case
  2 the gap never shrinks after brake onset, so ``BOR = 0``.  In case 3 the printed
  difference can be negative when the HV would stop short of the RV's stopping
  point with no gap at all; ``BOR = max(0, ...)``.  The printed value is kept in
  :attr:`FcwRange.bor_printed`.
* **r_w is not clamped**: the delay term is negative when the RV is faster, so
  ``r_w <= 0`` is possible; :func:`should_warn` then never warns (range >= 0).
* **Stationary HV.**  ``v_HV <= min_hv_speed`` (default 0.0, i.e. a stopped HV)
  makes the FCW inactive (:attr:`FcwRange.active` is False, no warning): a warning
  to brake means nothing to a stopped vehicle.  r_w is still computed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from catc.apps.events import AppWarning

__all__ = [
    "FcwConfig",
    "FcwRange",
    "forward_collision",
    "required_deceleration",
    "should_warn",
    "warning_range",
]


@dataclass(frozen=True)
class FcwConfig:
    """Parameters of the CAMP Linear FCW; every default is justified inline."""

    # Driver + brake-system reaction delay t_d (s), (FCW-1).  The paper names t_d but
    # gives no value; 2.05 s is the total delay (driver response + brake system) in the
    # CAMP Linear implementation of Y. P. Fallah (2015), a co-author of the paper.
    t_d: float = 2.05
    # Deceleration the HV driver is assumed to apply after t_d (m/s^2, < 0), (FCW-2).
    # None (default): the CAMP Required Deceleration Model (module docstring, Kiefer et
    # al. 1999/2003); a number: that constant instead.
    a_req: float | None = None
    # RV speed (m/s) at or below which the RV counts as stationary (case 1).  0.0:
    # the paper gives no threshold, and BOR is continuous at v_RV = 0 for a_RV = 0
    # (case 2 reduces to case 1), so no tolerance is needed for the formulas.
    rv_stationary_speed: float = 0.0
    # HV speed (m/s) at or below which the FCW is inactive (no warning).  0.0 = only
    # a stopped HV is excluded; the paper gives no minimum speed.
    min_hv_speed: float = 0.0

    def __post_init__(self) -> None:
        for name in ("t_d", "rv_stationary_speed", "min_hv_speed"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"FcwConfig.{name} must be finite")
        if self.t_d < 0.0:
            raise ValueError(f"FcwConfig.t_d must be >= 0, got {self.t_d}")
        if self.rv_stationary_speed < 0.0 or self.min_hv_speed < 0.0:
            raise ValueError("FcwConfig speed thresholds must be >= 0")
        if self.a_req is not None and not (math.isfinite(self.a_req) and self.a_req < 0.0):
            raise ValueError(f"FcwConfig.a_req must be finite and < 0 (braking), got "
                             f"{self.a_req}")


@dataclass(frozen=True)
class FcwRange:
    """The warning range and the intermediate values that led to it."""

    r_w: float  # warning range (m), (FCW-1); may be <= 0 (never warns then)
    bor: float  # brake onset range used in r_w (m), >= 0
    bor_printed: float  # (FCW-2) of the selected case as printed, before the >= 0 rules
    case: int  # 1, 2 or 3, (FCW-2)
    v_hvp: float  # max(0, v_HV + a_HV t_d)
    v_rvp: float  # max(0, v_RV + a_RV t_d)
    delay_term: float  # (v_HV - v_RV) t_d + 1/2 (a_HV - a_RV) t_d^2
    closing: bool  # v_HVp > v_RVp (closing at brake onset)
    active: bool  # False when v_HV <= min_hv_speed (stationary HV): no warning
    t_d: float
    a_req: float  # the a_req used: the CAMP model's value, or the configured constant


#: The CAMP Required Deceleration Model's coefficients converted from ft/s^2 (x 0.3048).
FT = 0.3048
RDM_INTERCEPT = -5.308 * FT  # m/s^2
RDM_LEAD = 0.685  # dimensionless (a ratio of accelerations)
RDM_MOVING = 2.570 * FT  # m/s^2, when the lead vehicle moves
RDM_CLOSING = 0.086  # 1/s (the same in ft and m)


def required_deceleration(v_rv: float, a_rv: float, closing: float) -> float:
    """The CAMP Required Deceleration Model (module docstring), m/s^2, always < 0.

    ``closing`` is ``v_HVp - v_RVp`` (m/s); ``a_rv`` the RV's acceleration (m/s^2).
    """
    return (RDM_INTERCEPT + RDM_LEAD * min(a_rv, 0.0)
            + (RDM_MOVING if v_rv > 0.0 else 0.0) - RDM_CLOSING * max(closing, 0.0))


def _check(name: str, value: float, *, nonneg: bool) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if nonneg and value < 0.0:
        raise ValueError(f"{name} must be >= 0 (a speed), got {value}")
    return value


def warning_range(
    v_hv: float,
    a_hv: float,
    v_rv: float,
    a_rv: float,
    config: FcwConfig = FcwConfig(),  # frozen dataclass: a safe shared default
) -> FcwRange:
    """CAMP Linear warning range r_w for an HV following an RV (see module docstring).

    ``v_hv``/``v_rv`` in m/s (>= 0), ``a_hv``/``a_rv`` in m/s² (negative = braking).
    Raises :class:`ValueError` for a negative speed or a non-finite input.
    """
    v_hv = _check("v_hv", v_hv, nonneg=True)
    a_hv = _check("a_hv", a_hv, nonneg=False)
    v_rv = _check("v_rv", v_rv, nonneg=True)
    a_rv = _check("a_rv", a_rv, nonneg=False)
    t_d = config.t_d

    # Predicted speeds at the end of the delay, clamped at 0 (no reversing).
    v_hvp = max(0.0, v_hv + a_hv * t_d)
    v_rvp = max(0.0, v_rv + a_rv * t_d)
    closing = v_hvp > v_rvp
    a_req = (config.a_req if config.a_req is not None
             else required_deceleration(v_rv, a_rv, v_hvp - v_rvp))

    if v_rv <= config.rv_stationary_speed:
        case = 1
        bor_printed = v_hvp**2 / (-2.0 * a_req)
        bor = bor_printed
    else:
        # RV stops strictly before the HV: v_RVp/(-a_RV) < v_HVp/(-a_req).  The second
        # clause is implied in exact arithmetic (a closing HV that is not outlasted by
        # the RV must brake harder than it) and only guards rounding, so that case 2
        # never divides by a_req - a_RV >= 0 while closing.
        rv_stops_first = a_rv < 0.0 and (
            v_rvp * a_req > v_hvp * a_rv or (closing and a_rv <= a_req)
        )
        if rv_stops_first:
            case = 3
            bor_printed = v_hvp**2 / (-2.0 * a_req) - v_rvp**2 / (-2.0 * a_rv)
            bor = max(0.0, bor_printed)
        else:
            case = 2
            denom = -2.0 * (a_req - a_rv)
            bor_printed = (v_hvp - v_rvp) ** 2 / denom if denom != 0.0 else math.inf
            bor = bor_printed if closing else 0.0

    delay_term = (v_hv - v_rv) * t_d + 0.5 * (a_hv - a_rv) * t_d**2
    return FcwRange(
        r_w=bor + delay_term,
        bor=bor,
        bor_printed=bor_printed,
        case=case,
        v_hvp=v_hvp,
        v_rvp=v_rvp,
        delay_term=delay_term,
        closing=closing,
        active=v_hv > config.min_hv_speed,
        t_d=t_d,
        a_req=a_req,
    )


def should_warn(range_m: float, fcw_range: FcwRange) -> bool:
    """True when the HV–RV range (m) is below r_w: ``0 <= range_m < r_w``.

    A negative or non-finite range (RV behind, or no valid range) never warns, and
    neither does an inactive FCW (stationary HV).  At exactly r_w: no warning
    ("less than the r_w").
    """
    if not fcw_range.active or not math.isfinite(range_m) or range_m < 0.0:
        return False
    return range_m < fcw_range.r_w


_CENTRE = 2  # catc.classify.LATERAL_CODES
_ONGOING = 0  # catc.classify.DIRECTION_CODES
#: ``_CENTRE_ONGOING[lateral, direction]``: On Centre and Ongoing (one lookup per tick
#: instead of two comparisons and a logical and).
_CENTRE_ONGOING = np.zeros((5, 3), dtype=bool)
_CENTRE_ONGOING[_CENTRE, _ONGOING] = True


def forward_collision(snap, config: FcwConfig = FcwConfig()) -> list[AppWarning]:
    """The FCW condition at this tick, for the in-path target of a :class:`MapSnapshot`.

    The target is the nearest RV classified Ahead, On Centre and Ongoing (CAMP's
    "in-path" lead vehicle; the paper: "the TC will classify the vehicle as Ahead and the
    FCW application will be evaluated").  Range = the bumper-to-bumper gap along the HV
    path, ``s - (L_HV + L_RV)/2`` (BSM positions are vehicle centres), at least 0; the
    RV's speed is its component along the lane, ``v_RV cos(phi_RV - phi_lane)``; its
    acceleration is its last BSM's.  Returns one warning or none.
    """
    z = snap.zone
    cand = (z.ahead & _CENTRE_ONGOING[z.lateral, z.direction]).nonzero()[0]
    if not len(cand):
        return []
    i = int(cand[z.s[cand].argmin()]) if len(cand) > 1 else int(cand[0])
    host = snap.host
    # .item(i): the entry as a Python float, as float(a[i]) gives it
    gap = max(0.0, z.s.item(i) - 0.5 * (host.length + snap.length.item(i)))
    v_rv = max(0.0, snap.speed.item(i) * math.cos(math.radians(z.heading_diff_deg.item(i))))
    r = warning_range(max(host.speed, 0.0), host.accel, v_rv, snap.accel.item(i), config)
    if not should_warn(gap, r):
        return []
    return [AppWarning("fcw", int(snap.ids[i]), gap, r.r_w)]
