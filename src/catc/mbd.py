"""Misbehavior detection (MBD) on BSMs that passed IEEE 1609.2 verification.

A valid signature says who sent a message, not that it is true: an insider with a valid
pseudonym certificate can broadcast a ghost vehicle, a shifted position or a speed that
contradicts its own positions.  :class:`MisbehaviorDetector` runs plausibility checks on
every received BSM and keeps the sender's recent history, so that the OBU can drop
implausible messages and quarantine their senders (their tracks raise no warning).

The checks are the legacy checks of F2MD (J. Kamel et al., "Simulation Framework for
Misbehavior Detection in Vehicular Networks", IEEE TVT 69(6), 2020), read from its source:
``LegacyChecks.cc`` and ``F2MDParameters.h`` of IRT-SystemX/veins-f2md
(``src/veins/modules/application/f2md/``, commit 1d529e5), ``MDMLib.cc`` there for the
kinematic envelope and the rectangle overlap, and ``F2MDVeinsApp.cc`` for the vehicle limits;
the older ``josephkamel/F2MD`` tree (``f2mdVeinsApp/``) has the same checks with ``#define``
constants.  Each threshold below cites its F2MD constant; where it had to change for a
10 Hz BSM on a real radio, the comment says why.  F2MD's names map to ours as:

========================================  ============================================
F2MD (``LegacyChecks.cc``)                 ``Detection.check``
========================================  ============================================
RangePlausibilityCheck                    ``range``
PositionConsistancyCheck                  ``position-consistency``
SpeedConsistancyCheck, SpeedPlausibility  ``speed-consistency``
PositionSpeedConsistancyCheck             ``position-speed``
SuddenAppearenceCheck                     ``sudden-appearance``
BeaconFrequencyCheck (+ secMark clock)    ``frequency``
PositionHeadingConsistancyCheck           ``heading``
(none; VeReMi extension's grid Sybil)     ``sybil``
IntersectionCheck, MultipleIntersection   ``intersection``
========================================  ============================================

F2MD's PositionPlausibilityCheck (distance from the road map) needs a map and is not done;
its Kalman checks belong to its newer "Kalman" versions, not the legacy set.  SAE J3287
(misbehavior reports; it reuses the observation structure of ETSI TS 103 759, whose
observation names include Beacon-IntervalTooSmall, Position-ChangeTooLarge,
Speed-ValueTooLarge-VehicleType, Speed-ChangeTooLarge, LongAcc-ValueTooLarge) is what a
report built from a :class:`Detection` would carry; ``evidence`` holds the numbers.

Conventions: positions are WGS-84 degrees as in :class:`catc.bsm.BSM`; distances come from
a local metric scale (:func:`local_offset_m`, checked against :mod:`catc.geo`'s geodesics
in the tests: catc.geo's pyproj calls cost ~11 us each, more than the whole budget of one
message here).  Headings are degrees clockwise from north.  Times: the sender's own clock
is its secMark (ms within the UTC minute, wrapped at 60000); ``t`` is the caller's
receive clock.  Pure: no I/O, no clock of its own.  docs/mbd.md has each check's formula,
threshold and source, the quarantine rule and the measured cost.
"""

from __future__ import annotations

import math
import operator
from collections import Counter, OrderedDict
from dataclasses import dataclass, field, fields
from typing import Any

__all__ = ["CHECKS", "Detection", "MbdConfig", "MisbehaviorDetector", "local_offset_m"]

#: The check names a :class:`Detection` carries.
CHECKS = ("range", "position-consistency", "speed-consistency", "position-speed",
          "sudden-appearance", "frequency", "heading", "sybil", "intersection")

#: Checks whose failure means the message contradicts its own track: such a message does
#: not become the sender's reference (one bad message must not poison the next good one).
#: Failures of the others (the message's position is self-consistent) still update it.
_TRACK_CHECKS = frozenset({"position-consistency", "speed-consistency", "frequency"})

# WGS-84
_A = 6_378_137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)
_RAD = math.pi / 180.0
_SCORE_CAP = 1e6


def _scale(lat: float) -> tuple[float, float]:
    """Metres per degree of longitude and of latitude at ``lat`` (WGS-84 radii of
    curvature: prime vertical N and meridian M)."""
    s = math.sin(lat * _RAD)
    w = 1.0 - _E2 * s * s
    n = _A / math.sqrt(w)
    return n * math.cos(lat * _RAD) * _RAD, n * (1.0 - _E2) / w * _RAD


def _dlon(a: float, b: float) -> float:
    """``a - b`` in degrees of longitude, across the antimeridian the short way."""
    d = a - b
    if d > 180.0:
        d -= 360.0
    elif d < -180.0:
        d += 360.0
    return d


def local_offset_m(lat1: float, lon1: float, lat2: float, lon2: float) -> tuple[float, float]:
    """East and north (m) of point 2 from point 1, on the WGS-84 ellipsoid's local scale at
    their mean latitude: within 1e-6 of the geodesic distance up to 2 km (the tests check
    it against :func:`catc.geo.distance_m` and :func:`catc.geo.bearing_deg`)."""
    kx, ky = _scale(0.5 * (lat1 + lat2))
    return _dlon(lon2, lon1) * kx, (lat2 - lat1) * ky


def _num(x: Any) -> float | None:
    """A finite float, or None (unavailable, NaN, infinite or not a number)."""
    if type(x) is float:  # the common case, fast
        return x if x - x == 0.0 else None
    if x is None or isinstance(x, bool):
        return None
    try:
        v = float(x)
    except (TypeError, ValueError, OverflowError):
        return None
    return v if math.isfinite(v) else None


def _sec_mark(x: Any) -> int | None:
    """A J2735 DSecond that means a time (0..60999 ms; 60000.. is a leap second), or None."""
    if x is None or isinstance(x, bool):
        return None
    try:
        v = operator.index(x)
    except TypeError:
        return None
    return v if 0 <= v < 61_000 else None


def _wrapped_dt(sm: int, sm0: int, dt_rx: float) -> float:
    """Seconds from secMark ``sm0`` to ``sm``: the reading (mod 60 s) nearest ``dt_rx``."""
    d = ((sm - sm0) % 60_000) / 1000.0
    return d + 60.0 * round((dt_rx - d) / 60.0)


def _ratio(num: float, den: float) -> float:
    """``num / den`` for a score (>= 1 when failed), finite."""
    if den <= num / _SCORE_CAP:
        return _SCORE_CAP
    return min(num / den, _SCORE_CAP)


def _max_min_dist(cur: float, old: float, dt: float, accel: float, decel: float,
                  vmax: float) -> tuple[float, float]:
    """Least and greatest distance (m) a vehicle covers in ``dt`` s going from speed
    ``old`` to ``cur`` with accelerations within ``accel``/``decel`` and speed within
    ``vmax``: F2MD ``MDMLib::calculateMaxMinDist`` (accelerate then brake for the
    greatest, brake then accelerate for the least).  Two changes: the switch time is kept
    in [0, dt] (an infeasible speed change is the speed check's finding), and the capped
    branch decelerates from ``vmax``, not from the uncapped peak speed (F2MD's version
    overstates the greatest distance there)."""
    cur = max(cur, 0.0)
    old = max(old, 0.0)
    t1 = min(max((cur - old + dt * decel) / (accel + decel), 0.0), dt)
    t2 = dt - t1
    peak = accel * t1 + old
    if peak > vmax:
        n1 = min(max((vmax - old) / accel, 0.0), dt)
        n2 = min(max((vmax - cur) / decel, 0.0), dt - n1)
        top = max(old, min(vmax, peak))
        greatest = (old * n1 + 0.5 * accel * n1 * n1 + top * n2 - 0.5 * decel * n2 * n2
                    + top * (dt - n1 - n2))
    else:
        greatest = old * t1 + 0.5 * accel * t1 * t1 + peak * t2 - 0.5 * decel * t2 * t2
    low = old - decel * t2
    if low < 0.0:
        n1 = cur / accel
        n2 = old / decel
        least = old * n2 - 0.5 * decel * n2 * n2 + 0.5 * accel * n1 * n1
    else:
        least = old * t2 - 0.5 * decel * t2 * t2 + low * t1 + 0.5 * accel * t1 * t1
    return least, greatest


def _corners(x: float, y: float, h: float, length: float, width: float
             ) -> list[tuple[float, float]]:
    """Corners of a vehicle's footprint (centre ``x, y`` east/north m, heading ``h``
    radians clockwise from north, ``length`` along it), counter-clockwise."""
    ax, ay = math.sin(h) * 0.5 * length, math.cos(h) * 0.5 * length  # forward
    bx, by = math.cos(h) * 0.5 * width, -math.sin(h) * 0.5 * width  # right
    return [(x + ax + bx, y + ay + by), (x + ax - bx, y + ay - by),
            (x - ax - bx, y - ay - by), (x - ax + bx, y - ay + by)]


def _area(poly: list[tuple[float, float]]) -> float:
    s = 0.0
    for i in range(len(poly)):
        x1, y1 = poly[i - 1]
        x2, y2 = poly[i]
        s += x1 * y2 - x2 * y1
    return abs(s) * 0.5


def _clip(subject: list[tuple[float, float]], clip: list[tuple[float, float]]
          ) -> list[tuple[float, float]]:
    """Sutherland-Hodgman: ``subject`` clipped by the convex polygon ``clip``."""
    out = subject
    orient = 1.0 if _signed_area(clip) > 0 else -1.0
    for i in range(len(clip)):
        if not out:
            break
        (cx1, cy1), (cx2, cy2) = clip[i - 1], clip[i]
        ex, ey = cx2 - cx1, cy2 - cy1
        inp, out = out, []
        for j in range(len(inp)):
            px, py = inp[j - 1]
            qx, qy = inp[j]
            sp = orient * (ex * (py - cy1) - ey * (px - cx1))
            sq = orient * (ex * (qy - cy1) - ey * (qx - cx1))
            if sq >= 0.0:
                if sp < 0.0:
                    r = sp / (sp - sq)
                    out.append((px + r * (qx - px), py + r * (qy - py)))
                out.append((qx, qy))
            elif sp >= 0.0:
                r = sp / (sp - sq)
                out.append((px + r * (qx - px), py + r * (qy - py)))
    return out


def _signed_area(poly: list[tuple[float, float]]) -> float:
    s = 0.0
    for i in range(len(poly)):
        x1, y1 = poly[i - 1]
        x2, y2 = poly[i]
        s += x1 * y2 - x2 * y1
    return 0.5 * s


def _iou(a: tuple[float, float, float, float, float],
         b: tuple[float, float, float, float, float]) -> float:
    """Intersection over union of two footprints ``(x, y, heading rad, length, width)``:
    F2MD ``MDMLib::RectRectFactor`` (intersection area / (area1 + area2 - intersection))."""
    pa, pb = _corners(*a), _corners(*b)
    inter = _area(_clip(pa, pb))
    union = a[3] * a[4] + b[3] * b[4] - inter
    return inter / union if union > 0.0 else 0.0


def _positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"MbdConfig.{name} must be a finite number > 0, got {value!r}")


@dataclass(frozen=True)
class MbdConfig:
    """Every threshold, with its source.  F2MD = IRT-SystemX/veins-f2md, commit 1d529e5,
    ``src/veins/modules/application/f2md/``; "P.h" is its ``F2MDParameters.h``."""

    # -- range -------------------------------------------------------------------------
    #: Farthest plausible sender (m).  F2MD P.h MAX_PLAUSIBLE_RANGE = 420 (the old tree:
    #: 417): the edge of reception of its simulated DSRC at Veins' transmit power.  Ours is
    #: the RVE's radio (catc.channel: 20 dBm, -82 dBm sensitivity, free-space exponent 2,
    #: Nakagami m 1.5), which still receives 1 % of BSMs at 1 km and 1e-5 at 1.5 km; real
    #: DSRC / C-V2X line-of-sight ranges are reported up to ~1 km.  Without the distance
    #: model the RVE delivers every vehicle (the default scenario's farthest is 750 m).
    max_range_m: float = 1500.0
    # -- vehicle limits (F2MDVeinsApp.cc: MAX_PLAUSIBLE_* = the SUMO vType's maxSpeed /
    # accel / decel + 0.01, floors P.h MIN_MAX_SPEED 40, MIN_MAX_ACCEL 3, MIN_MAX_DECEL 4.5;
    # SUMO's passenger car: 55.56 m/s, 2.6 and 4.5 m/s²).  A remote vehicle's type is not
    # known here, so the limits are those of any car: --------------------------------------
    #: m/s: 252 km/h, above production cars' speeds on unlimited roads (SUMO's 200 km/h
    #: passenger limit is below them).
    max_speed_mps: float = 70.0
    #: m/s² (≈1 g, the tyre-road friction limit on dry asphalt; fast cars reach it).
    max_accel_mps2: float = 10.0
    #: m/s² (≈1 g; the default scenario's leader brakes at 7, above SUMO's decel 4.5, and
    #: SUMO's passenger emergencyDecel is 9).
    max_decel_mps2: float = 10.0
    #: m/s added to the speed-change bound: two J2735 speed LSBs (0.02 m/s), so that the
    #: encoding's rounding over a short interval is not read as acceleration.  F2MD: none.
    speed_tolerance_mps: float = 0.04
    # -- position consistency and position-speed ------------------------------------------
    #: P.h MAX_TIME_DELTA = 3.1 s: position-speed is checked over at most this interval.
    max_time_delta_s: float = 3.1
    #: P.h MAX_MGT_RNG_UP = 2.1 m: tolerance above the greatest distance (position-speed);
    #: also the tolerance of position-consistency (F2MD's legacy check has none: its
    #: simulated positions are noise-free; real GNSS is not).
    max_mgt_rng_up_m: float = 2.1
    #: P.h MAX_MGT_RNG_DOWN = 6.2 m: tolerance below the least distance, plus F2MD's
    #: speed-dependent term 0.3571 v - 0.01694 v² (LegacyChecks.cc; fitted to its urban
    #: speeds, it turns negative above 37 m/s).  We keep at least ``max_mgt_rng_up_m``.
    max_mgt_rng_down_m: float = 6.2
    #: F2MD compares a BSM with the sender's previous one, 1 s earlier (its beacons are
    #: 1 Hz).  At 10 Hz the tolerances above are larger than a 0.1 s interval can reveal,
    #: so position-speed and heading use the newest earlier message at least this old.
    anchor_s: float = 1.0
    # -- heading ---------------------------------------------------------------------------
    #: Largest angle between the heading and the direction of travel (deg).  F2MD P.h
    #: MAX_HEADING_CHANGE = 90 (a heading pointing backwards).  Over ~1 s of travel the
    #: largest honest angle in the real data here is 48 deg (OpenACC: raw GNSS jumping a
    #: few metres sideways at 10 m/s; 99.99 % are below 23); 90 would pass a heading at
    #: right angles to the path, so: 60.
    max_heading_change_deg: float = 60.0
    #: P.h POS_HEADING_TIME = 1.1 s: heading is compared over at most this interval.
    pos_heading_time_s: float = 1.1
    #: Below this speed (m/s) or displacement (m) heading is not checked: F2MD's 1 and 1
    #: (PositionHeadingConsistancyCheck).
    heading_min_speed_mps: float = 1.0
    heading_min_distance_m: float = 1.0
    # -- sudden appearance -----------------------------------------------------------------
    #: P.h MAX_SA_RANGE = 210 m (half its 420 m range): a first message closer than this.
    sa_range_m: float = 210.0
    #: Inside this range (m) a sudden appearance is strong evidence (quarantine at once):
    #: about 2 s of travel at highway speed, where a ghost can trigger a forward collision
    #: warning (catc.apps.fcw).  Ours, not F2MD's.
    sa_safety_range_m: float = 50.0
    #: P.h MAX_SA_TIME = 2.1 s: no sudden appearance in the detector's first seconds (every
    #: sender is new then) ...
    sa_warmup_s: float = 2.1
    #: ... nor before this many typical message intervals have passed (so that at 1 Hz and
    #: high loss a vehicle in range has been heard: 0.5^10 = 1e-3).  Ours.
    sa_warmup_intervals: float = 10.0
    #: A new id that continues the path of an id last heard up to this long ago (s) is a
    #: pseudonym change, not an appearance (J2735 TemporaryIDs change with the pseudonym
    #: certificate, possibly after a silent period of a few seconds).  Ours.
    sa_link_time_s: float = 5.0
    #: ... and last heard at least this long (s) before the new id's first message: half
    #: a 10 Hz interval (an id still sending alongside is a neighbour).  Ours.
    sa_link_min_gap_s: float = 0.05
    #: ... "continues": within ``sa_link_accel_mps2 dt² / 2 + max_mgt_rng_up_m`` of where
    #: the old id's last speed and heading would have taken it (0.3 g of unannounced
    #: acceleration or braking during the silence).  Ours.
    sa_link_accel_mps2: float = 3.0
    # -- beacon frequency and timing ----------------------------------------------------
    #: Shortest plausible interval (s) between two BSMs of a sender: F2MD P.h
    #: MAX_BEACON_FREQUENCY = 0.9 s for its 1 s beacons, i.e. 0.9 of the nominal interval;
    #: SAE J2945/1's nominal BSM interval is 100 ms, so 0.09 s.  Measured on secMark.
    min_interval_s: float = 0.09
    #: A message up to this much older (s, secMark) than the sender's last one is a late
    #: (reordered) frame, skipped without a finding; older is a replay.  Ours.
    reorder_window_s: float = 0.5
    #: A sender's secMark may run ahead of the receive clock by at most this much (s) over
    #: its lowest latency so far: more is a forged or replayed timestamp.  Ours.
    max_clock_skew_s: float = 1.0
    # -- intersection ----------------------------------------------------------------------
    #: F2MD IntersectionCheck: footprints overlap when intersection over union, times
    #: (MAX_DELTA_INTER - dt) / MAX_DELTA_INTER, exceeds 0.5.
    intersection_threshold: float = 0.5
    #: P.h MAX_DELTA_INTER = 2.0 s (the old tree: 0.4).  The other vehicle's last position
    #: is also moved forward by its speed over dt (ours; F2MD compares it where it was).
    max_delta_inter_s: float = 2.0
    #: F2MD's IntersectionCheck with the host uses dt = 0.11 s.
    host_delta_s: float = 0.11
    #: Host footprint (m): SUMO's passenger car, as every vehicle of the scenarios.
    host_length_m: float = 5.0
    host_width_m: float = 1.8
    # -- Sybil (ours: F2MD has no legacy Sybil check; its grid Sybil attack puts ghosts
    # SybilDistanceX = 5 m and SybilDistanceY = 2 m from the sender, P.h) ---------------------
    #: Two ids moving together, closer than distinct vehicles could: same heading within
    #: ``sybil_heading_deg`` and speed within ``sybil_speed_mps``, both above
    #: ``sybil_min_speed_mps`` (in a queue close and slow is normal) ...
    sybil_min_speed_mps: float = 5.0
    sybil_heading_deg: float = 10.0
    sybil_speed_mps: float = 1.0
    #: ... side by side closer than half their widths plus this (m; adjacent lanes are
    #: 3 m or more apart) ...
    sybil_lateral_clearance_m: float = 0.5
    #: ... and a bumper-to-bumper gap below ``sybil_min_gap_m + sybil_headway_s * speed``
    #: (the shortest honest gap in the real data here is about a 0.33 s time gap, OpenACC
    #: by hand at 16 m/s: 4.9 m, above the 2.6 m this gives there) ...
    sybil_min_gap_m: float = 1.0
    sybil_headway_s: float = 0.1
    #: ... in this many consecutive messages of the younger id.
    sybil_messages: int = 5
    # -- quarantine (ours) -----------------------------------------------------------------
    #: A sender is quarantined when ``quarantine_k`` of its messages fail within
    #: ``quarantine_window_s``, or at once on a strong finding (sudden appearance inside
    #: the safety range, intersection, Sybil); a single GNSS glitch is one failed message.
    quarantine_k: int = 3
    quarantine_window_s: float = 2.0
    #: How long (s) from the last detection a quarantine lasts; renewed by new detections.
    quarantine_s: float = 10.0
    #: A sender quarantined on a strong finding (a fabricated vehicle) stays quarantined
    #: while it keeps transmitting: each of its messages renews the quarantine.
    sticky_strong: bool = True
    #: Size (m) of the grid cells that find neighbours for intersection and Sybil.
    grid_cell_m: float = 50.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "sticky_strong":
                continue
            _positive(f.name, v)
        if not self.intersection_threshold < 1.0:
            raise ValueError("MbdConfig.intersection_threshold must be below 1 "
                             f"(an overlap ratio), got {self.intersection_threshold}")
        if not isinstance(self.quarantine_k, int) or not isinstance(self.sybil_messages, int):
            raise ValueError("MbdConfig.quarantine_k and sybil_messages are counts (int)")


@dataclass(frozen=True)
class Detection:
    """One failed check of one message."""

    #: One of :data:`CHECKS`.
    check: str
    #: The TemporaryID of the sender.
    suspect: int
    #: The receive time (s, the caller's clock).
    t: float
    #: How far beyond the threshold: >= 1 means failed (value / limit, or limit / value
    #: for lower bounds), capped at 1e6.
    score: float
    #: The numbers that failed, e.g. ``{"distance_m": ..., "limit_m": ...}``.
    evidence: dict = field(default_factory=dict)
    #: The second id for sybil / intersection (None: the host).
    other: int | None = None


class _Msg:
    """An accepted message, as the checks need it."""

    __slots__ = ("heading", "lat", "length", "lon", "sm", "speed", "t", "ts", "width")

    def __init__(self, ts: float, t: float, sm: int | None, lat: float, lon: float,
                 speed: float | None, heading: float | None, length: float | None,
                 width: float | None) -> None:
        self.ts, self.t, self.sm = ts, t, sm
        self.lat, self.lon, self.speed, self.heading = lat, lon, speed, heading
        self.length, self.width = length, width


class _Sender:
    """What the detector keeps of one TemporaryID."""

    __slots__ = ("acc", "cell", "first_t", "heard_t", "hist", "min_off", "strikes", "strong",
                 "sybil", "tid")

    def __init__(self, tid: int, t: float) -> None:
        self.tid = tid
        self.first_t = t  # first heard (receive clock)
        self.heard_t = t  # last heard, accepted or not
        self.acc: _Msg | None = None  # the last accepted message
        self.hist: list[_Msg] = []  # accepted messages back to the anchor
        self.min_off = math.inf  # lowest (receive time - sender time) so far
        self.strikes: list[float] = []  # receive times of failed messages in the window
        self.strong = False  # quarantined on a strong finding
        self.sybil: dict[int, int] = {}  # other id -> consecutive co-moving messages
        self.cell: tuple[int, int] | None = None


class MisbehaviorDetector:
    """Plausibility checks on verified BSMs with bounded per-sender state (module
    docstring; every threshold in :class:`MbdConfig`)."""

    def __init__(self, config: MbdConfig = MbdConfig(), max_senders: int = 4096) -> None:
        if not isinstance(max_senders, int) or max_senders < 1:
            raise ValueError(f"max_senders must be a positive int, got {max_senders!r}")
        self.config = config
        self.max_senders = max_senders
        #: Detections by check name, and ``quarantines`` (senders put in quarantine).
        self.counters: Counter = Counter()
        self._senders: OrderedDict[int, _Sender] = OrderedDict()
        self._quarantine: OrderedDict[int, float] = OrderedDict()  # id -> until (s)
        self._grid: dict[tuple[int, int], set[int]] = {}
        self._cell_lat = self._cell_lon = 0.0  # grid cell size in degrees, set on first use
        self._t0: float | None = None  # first message seen
        self._interval = 0.0  # running mean of accepted message intervals (s)

    def __len__(self) -> int:
        """Senders with state (at most ``max_senders``)."""
        return len(self._senders)

    def grid_entries(self) -> int:
        """Ids in the neighbour grid (bounded like the senders)."""
        return sum(len(s) for s in self._grid.values())

    # -- quarantine --------------------------------------------------------------------

    def quarantined(self, temp_id: int, t: float) -> bool:
        """Whether ``temp_id`` is in quarantine at ``t`` (its track must raise no warning).

        Rule: from the detection that puts it there, for ``quarantine_s``, renewed by every
        new detection (and, after a strong finding, by every message): quarantine after
        ``quarantine_k`` failed messages within ``quarantine_window_s``, or at once on a
        sudden appearance inside the safety range, an intersection or a Sybil finding."""
        until = self._quarantine.get(temp_id)
        return until is not None and t < until

    def _punish(self, st: _Sender, t: float, found: list[Detection], strong: bool) -> None:
        c = self.config
        until = self._quarantine.get(st.tid)
        active = until is not None and t < until
        strikes = [s for s in st.strikes if t - s < c.quarantine_window_s]
        strikes.append(t)
        st.strikes = strikes[-c.quarantine_k:]
        if strong or len(strikes) >= c.quarantine_k or active:
            if not active:
                self.counters["quarantines"] += 1
            st.strong = st.strong or strong
            self._set_quarantine(st.tid, t + c.quarantine_s)

    def _set_quarantine(self, tid: int, until: float) -> None:
        q = self._quarantine
        q[tid] = until
        q.move_to_end(tid)
        while len(q) > self.max_senders:
            q.popitem(last=False)

    # -- state -------------------------------------------------------------------------

    def _sender(self, tid: int, t: float) -> _Sender:
        senders = self._senders
        st = senders.get(tid)
        if st is not None:
            senders.move_to_end(tid)
            return st
        st = senders[tid] = _Sender(tid, t)
        while len(senders) > self.max_senders:
            _, old = senders.popitem(last=False)
            self._ungrid(old)
        return st

    def _ungrid(self, st: _Sender) -> None:
        if st.cell is not None:
            cell = self._grid.get(st.cell)
            if cell is not None:
                cell.discard(st.tid)
                if not cell:
                    del self._grid[st.cell]
            st.cell = None

    def _cell(self, lat: float, lon: float) -> tuple[int, int]:
        if not self._cell_lat:
            kx, ky = _scale(lat)
            self._cell_lat = self.config.grid_cell_m / ky
            self._cell_lon = self.config.grid_cell_m / max(kx, 1.0)
        return int(lat // self._cell_lat), int(lon // self._cell_lon)

    def _neighbours(self, lat: float, lon: float, reach: int = 1):
        i, j = self._cell(lat, lon)
        grid = self._grid
        senders = self._senders
        for di in range(-reach, reach + 1):
            for dj in range(-reach, reach + 1):
                cell = grid.get((i + di, j + dj))
                if cell:
                    for tid in cell:
                        o = senders.get(tid)
                        if o is not None and o.acc is not None:
                            yield o

    def _accept(self, st: _Sender, m: _Msg, anchor_i: int, reset: bool) -> None:
        if st.acc is not None and m.sm is not None and st.acc.sm is not None:
            dt = m.ts - st.acc.ts
            if 0.0 < dt <= self.config.max_time_delta_s:
                self._interval = dt if not self._interval else \
                    0.98 * self._interval + 0.02 * dt
        st.acc = m
        if reset:
            st.hist = [m]
        else:
            if anchor_i:
                del st.hist[:anchor_i]
            st.hist.append(m)
            if len(st.hist) > 64:  # a flood of messages inside anchor_s
                del st.hist[:-64]
        off = m.t - m.ts
        if off < st.min_off:
            st.min_off = off
        cell = self._cell(m.lat, m.lon)
        if cell != st.cell:
            self._ungrid(st)
            self._grid.setdefault(cell, set()).add(st.tid)
            st.cell = cell

    # -- the checks ----------------------------------------------------------------------

    def observe(self, bsm, t: float, host_lat: float | None, host_lon: float | None, *,
                host_heading: float | None = None) -> list[Detection]:
        """The checks ``bsm`` (a :class:`catc.bsm.BSM`) fails, received at ``t`` (s, the
        caller's clock) with the host at ``host_lat``/``host_lon`` (None: unknown, and the
        host-relative checks are skipped; pass None too when the host's own position is
        stale).  Empty for a plausible message.  A check whose fields are unavailable is
        skipped.  ``host_heading`` (deg) orients the host's footprint; without it the host
        is taken as aligned with the sender."""
        c = self.config
        t = _num(t)
        lat, lon = _num(bsm.lat), _num(bsm.lon)
        if t is None or lat is None or lon is None or not -90.0 <= lat <= 90.0 \
                or not -180.0 <= lon <= 180.0:
            return []
        try:
            tid = int(bsm.temp_id)
        except (TypeError, ValueError):
            return []
        if self._t0 is None:
            self._t0 = t
        speed = _num(bsm.speed)
        if speed is not None and speed < 0.0:
            speed = None
        heading = _num(bsm.heading)
        if heading is not None:
            heading %= 360.0
        length, width = _num(bsm.length), _num(bsm.width)
        if length is None or width is None or length <= 0.0 or width <= 0.0:
            length = width = None
        sm = _sec_mark(bsm.sec_mark)
        kx, ky = _scale(lat)
        found: list[Detection] = []
        strong = False

        def add(check: str, score: float, evidence: dict, other: int | None = None) -> None:
            found.append(Detection(check, tid, t, score, evidence, other))

        # -- against the host: range, intersection with the host ------------------------
        hlat, hlon = _num(host_lat), _num(host_lon)
        host_d = None
        if hlat is not None and hlon is not None and -90.0 <= hlat <= 90.0:
            hx, hy = -_dlon(lon, hlon) * kx, (hlat - lat) * ky  # host from the sender
            host_d = math.hypot(hx, hy)
            if host_d >= c.max_range_m:  # RangePlausibilityCheck
                add("range", _ratio(host_d, c.max_range_m),
                    {"distance_m": host_d, "limit_m": c.max_range_m})
            if heading is not None and length is not None:
                reach = 0.5 * (math.hypot(length, width) + math.hypot(c.host_length_m,
                                                                        c.host_width_m))
                if host_d < reach:
                    hh = _num(host_heading)
                    h = heading * _RAD
                    inter = _iou((0.0, 0.0, h, length, width),
                                 (hx, hy, h if hh is None else hh * _RAD, c.host_length_m,
                                  c.host_width_m))
                    inter *= (c.max_delta_inter_s - c.host_delta_s) / c.max_delta_inter_s
                    if inter > c.intersection_threshold:
                        add("intersection", _ratio(inter, c.intersection_threshold),
                            {"overlap": inter, "limit": c.intersection_threshold,
                             "with": "host"})
                        strong = True
        # -- SpeedPlausibilityCheck ------------------------------------------------------
        if speed is not None and speed >= c.max_speed_mps:
            add("speed-consistency", _ratio(speed, c.max_speed_mps),
                {"speed_mps": speed, "limit_mps": c.max_speed_mps})

        st = self._sender(tid, t)
        acc = st.acc
        ts = t  # the sender's clock, continued from its last accepted message
        late = False
        timing_ok = True
        anchor_i = 0
        reset = False
        if acc is None:
            # -- SuddenAppearenceCheck: a first message close to the host ------------------
            warmup = max(c.sa_warmup_s, c.sa_warmup_intervals * self._interval)
            if host_d is not None and host_d < c.sa_range_m and t - self._t0 >= warmup \
                    and not self._continues(tid, t, sm, lat, lon, kx, ky, speed):
                inside = host_d < c.sa_safety_range_m
                add("sudden-appearance", _ratio(c.sa_range_m, host_d),
                    {"distance_m": host_d, "limit_m": c.sa_range_m,
                     "safety_range_m": c.sa_safety_range_m})
                strong = strong or inside
        else:
            dt_rx = t - acc.t
            if not abs(dt_rx) < 1e9:  # a receive clock that jumped by decades
                return self._finish(st, tid, t, found, strong, None, 0, False)
            if sm is not None and acc.sm is not None:
                dt = _wrapped_dt(sm, acc.sm, dt_rx)
                ts = acc.ts + dt
                ahead = st.min_off - (t - ts)
                if ahead > c.max_clock_skew_s:
                    add("frequency", _ratio(ahead, c.max_clock_skew_s),
                        {"ahead_s": ahead, "limit_s": c.max_clock_skew_s})
                    timing_ok = False
                elif dt <= 0.0:
                    if -c.reorder_window_s <= dt < 0.0 or (
                            dt == 0.0 and lat == acc.lat and lon == acc.lon):
                        late = True  # reordered or duplicated on the way: not a finding
                    else:
                        add("frequency", _ratio(c.min_interval_s, dt),
                            {"interval_s": dt, "limit_s": c.min_interval_s})
                        timing_ok = False
                elif dt < c.min_interval_s:  # BeaconFrequencyCheck
                    add("frequency", _ratio(c.min_interval_s, dt),
                        {"interval_s": dt, "limit_s": c.min_interval_s})
            else:
                dt = dt_rx  # no secMark: the receive clock (jittery, but all there is)
                ts = acc.ts + dt
                if dt <= 0.0:
                    late = True
            if late:
                return self._finish(st, tid, t, found, strong, None, 0, False)
            if timing_ok and dt > 0.0:
                dx, dy = _dlon(lon, acc.lon) * kx, (lat - acc.lat) * ky
                dist = math.hypot(dx, dy)
                # -- PositionConsistancyCheck ----------------------------------------------
                limit = c.max_speed_mps * dt + c.max_mgt_rng_up_m
                if dist >= limit:
                    add("position-consistency", _ratio(dist, limit),
                        {"distance_m": dist, "limit_m": limit, "interval_s": dt})
                # -- SpeedConsistancyCheck -------------------------------------------------
                if speed is not None and acc.speed is not None:
                    dv = speed - acc.speed
                    bound = c.max_accel_mps2 if dv > 0.0 else c.max_decel_mps2
                    limit = bound * dt + c.speed_tolerance_mps
                    if abs(dv) >= limit:
                        add("speed-consistency", _ratio(abs(dv), limit),
                            {"accel_mps2": dv / dt, "limit_mps2": bound, "interval_s": dt})
                # -- against the anchor, ~1 s back: position-speed and heading -------------
                hist = st.hist
                n = len(hist)
                while anchor_i + 1 < n and ts - hist[anchor_i + 1].ts >= c.anchor_s:
                    anchor_i += 1
                ref = hist[anchor_i]
                dtr = ts - ref.ts
                if dtr > 0.0:
                    rx, ry = _dlon(lon, ref.lon) * kx, (lat - ref.lat) * ky
                    rdist = math.hypot(rx, ry)
                    if 0.0 < dtr < c.max_time_delta_s and speed is not None \
                            and ref.speed is not None:
                        reset = self._position_speed(add, rdist, dtr, speed, ref.speed)
                    if 0.0 < dtr < c.pos_heading_time_s and heading is not None \
                            and speed is not None and speed >= c.heading_min_speed_mps \
                            and rdist >= c.heading_min_distance_m \
                            and bsm.transmission != 3:  # REVERSE_GEARS
                        path = math.degrees(math.atan2(rx, ry)) % 360.0
                        diff = abs((heading - path + 180.0) % 360.0 - 180.0)
                        if diff > c.max_heading_change_deg:
                            add("heading", _ratio(diff, c.max_heading_change_deg),
                                {"heading_deg": heading, "path_deg": path,
                                 "difference_deg": diff, "limit_deg": c.max_heading_change_deg,
                                 "interval_s": dtr})
        # -- pairs: intersection and Sybil (the younger id of the pair is the suspect) -----
        if timing_ok and acc is not None and heading is not None and length is not None:
            strong = self._pairs(st, add, t, sm, lat, lon, kx, ky, speed, heading, length,
                                 width) or strong
        msg = None
        if not any(d.check in _TRACK_CHECKS for d in found):
            msg = _Msg(ts, t, sm, lat, lon, speed, heading, length, width)
        return self._finish(st, tid, t, found, strong, msg, anchor_i, reset)

    def _finish(self, st: _Sender, tid: int, t: float, found: list[Detection], strong: bool,
                msg: _Msg | None, anchor_i: int, reset: bool) -> list[Detection]:
        st.heard_t = t
        if msg is not None:
            self._accept(st, msg, anchor_i, reset)
        if found:
            for d in found:
                self.counters[d.check] += 1
            self._punish(st, t, found, strong)
        elif st.strong and self.config.sticky_strong:
            until = self._quarantine.get(tid)
            if until is not None and t < until:
                self._set_quarantine(tid, t + self.config.quarantine_s)
        return found

    def _position_speed(self, add, dist: float, dt: float, speed: float, old: float) -> bool:
        """F2MD PositionSpeedConsistancyCheck: the distance covered in ``dt`` within the
        kinematic envelope of the two reported speeds.  True when it fails (the message
        then starts a new baseline: a GNSS step is reported once, a lasting lie again
        whenever it outgrows the tolerances)."""
        c = self.config
        least, greatest = _max_min_dist(speed, old, dt, c.max_accel_mps2, c.max_decel_mps2,
                                        c.max_speed_mps)
        vmin = min(speed, old)
        addon = c.max_mgt_rng_down_m + 0.3571 * vmin - 0.01694 * vmin * vmin
        addon = max(addon, c.max_mgt_rng_up_m)
        low, high = least - addon, greatest + c.max_mgt_rng_up_m
        if dist < low:
            add("position-speed", _ratio(low, dist),
                {"distance_m": dist, "min_m": low, "max_m": high, "interval_s": dt,
                 "speeds_mps": (old, speed)})
            return True
        if dist > high:
            add("position-speed", _ratio(dist, high),
                {"distance_m": dist, "min_m": low, "max_m": high, "interval_s": dt,
                 "speeds_mps": (old, speed)})
            return True
        return False

    def _pair_dt(self, o: _Sender, t: float, sm: int | None) -> float:
        """Time (s) from the other's last accepted message to this one: on secMark (one
        UTC minute for all senders) when it agrees with the receive clock, else that."""
        m = o.acc
        dt_rx = t - m.t
        if not abs(dt_rx) < 1e9:
            return math.inf
        if sm is not None and m.sm is not None:
            d = _wrapped_dt(sm, m.sm, dt_rx)
            if abs(d - dt_rx) <= self.config.max_clock_skew_s:
                return d
        return dt_rx

    def _continues(self, tid: int, t: float, sm: int | None, lat: float, lon: float,
                   kx: float, ky: float, speed: float | None) -> bool:
        """Whether a new id continues the path of a sender heard within ``sa_link_time_s``
        (a pseudonym change; :class:`MbdConfig`)."""
        c = self.config
        v = (c.max_speed_mps if speed is None else min(speed, c.max_speed_mps)) + 5.0
        reach = min(8, 1 + int(v * c.sa_link_time_s // c.grid_cell_m))
        for o in self._neighbours(lat, lon, reach):
            if o.tid == tid:
                continue
            m = o.acc
            dt = self._pair_dt(o, t, sm)
            # a vehicle does not send under two ids in the same interval: an id heard with
            # this very message's time is a neighbour, not our previous pseudonym
            if not c.sa_link_min_gap_s <= dt <= c.sa_link_time_s:
                continue
            ox, oy = _dlon(m.lon, lon) * kx, (m.lat - lat) * ky
            if m.speed is not None and m.heading is not None:
                h = m.heading * _RAD
                ox += m.speed * dt * math.sin(h)
                oy += m.speed * dt * math.cos(h)
            if math.hypot(ox, oy) <= 0.5 * c.sa_link_accel_mps2 * dt * dt + c.max_mgt_rng_up_m:
                return True
        return False

    def _pairs(self, st: _Sender, add, t: float, sm: int | None, lat: float, lon: float,
               kx: float, ky: float, speed: float | None, heading: float, length: float,
               width: float) -> bool:
        """MultipleIntersectionCheck and the Sybil check against the neighbours; True on a
        finding.  A pair is checked on the younger id's messages only, and only while the
        older one is still heard (an id that fell silent before this one appeared is a
        pseudonym change, not a twin)."""
        c = self.config
        h = heading * _RAD
        sin_h, cos_h = math.sin(h), math.cos(h)
        me = (0.0, 0.0, h, length, width)
        diag = math.hypot(length, width)
        counts: dict[int, int] = {}
        hit = False
        sybil_speed = speed is not None and speed >= c.sybil_min_speed_mps
        # no finding beyond this (m) plus the other's half length + width and its travel
        # (Sybil: along + lateral < half both lengths and widths + the gap and clearance)
        reach = 0.5 * (length + width) + c.sybil_lateral_clearance_m + c.sybil_min_gap_m \
            + c.sybil_headway_s * (speed or 0.0)
        first_t = st.first_t
        i, j = self._cell(lat, lon)
        grid, senders = self._grid, self._senders
        others = []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                cell = grid.get((i + di, j + dj))
                if cell:
                    others.extend(cell)
        for otid in others:
            o = senders.get(otid)
            if o is None or o is st or o.acc is None or o.first_t > first_t \
                    or o.heard_t < first_t:
                continue
            m = o.acc
            if m.heading is None or m.length is None:
                continue
            ox, oy = _dlon(m.lon, lon) * kx, (m.lat - lat) * ky
            ov = m.speed or 0.0
            if ox * ox + oy * oy > (reach + 0.5 * (m.length + m.width)
                                    + ov * (abs(t - m.t) + c.max_clock_skew_s)) ** 2:
                continue  # too far apart even after the other's travel since
            dt = self._pair_dt(o, t, sm)
            if not -c.max_delta_inter_s < dt < c.max_delta_inter_s:
                continue
            oh = m.heading * _RAD
            if m.speed is not None:  # where the other is now
                ox += m.speed * dt * math.sin(oh)
                oy += m.speed * dt * math.cos(oh)
            d = math.hypot(ox, oy)
            # -- IntersectionCheck ---------------------------------------------------------
            if d < 0.5 * (diag + math.hypot(m.length, m.width)):
                inter = _iou(me, (ox, oy, oh, m.length, m.width))
                inter *= (c.max_delta_inter_s - abs(dt)) / c.max_delta_inter_s
                if inter > c.intersection_threshold:
                    add("intersection", _ratio(inter, c.intersection_threshold),
                        {"overlap": inter, "limit": c.intersection_threshold,
                         "interval_s": dt}, o.tid)
                    hit = True
            # -- Sybil: moving together, closer than two vehicles could ---------------------
            if sybil_speed and m.speed is not None and m.speed >= c.sybil_min_speed_mps \
                    and abs(speed - m.speed) <= c.sybil_speed_mps \
                    and abs((heading - m.heading + 180.0) % 360.0 - 180.0) \
                    <= c.sybil_heading_deg:
                along = abs(ox * sin_h + oy * cos_h)
                lateral = abs(ox * cos_h - oy * sin_h)
                lat_limit = 0.5 * (width + m.width) + c.sybil_lateral_clearance_m
                gap = along - 0.5 * (length + m.length)
                gap_limit = c.sybil_min_gap_m + c.sybil_headway_s * speed
                if lateral < lat_limit and gap < gap_limit:
                    n = counts[o.tid] = st.sybil.get(o.tid, 0) + 1
                    if n >= c.sybil_messages:
                        score = min(_ratio(lat_limit, lateral),
                                    _ratio(gap_limit, max(gap, 0.0)))
                        add("sybil", max(score, 1.0),
                            {"lateral_m": lateral, "lateral_limit_m": lat_limit,
                             "gap_m": gap, "gap_limit_m": gap_limit, "messages": n},
                            o.tid)
                        hit = True
        st.sybil = counts
        return hit
