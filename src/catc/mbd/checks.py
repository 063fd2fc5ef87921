"""The plausibility checks: one function per check, listed in :data:`TABLE`.

F2MD has one method per check (``LegacyChecks.cc``); so do we.  A check is a function

* ``check(o, c) -> (score, evidence) | None`` on one message (:class:`Observation` ``o``,
  :class:`~catc.mbd.config.MbdConfig` ``c``), or, for a check of a message against a
  neighbour, ``check(o, p, c)`` with the neighbour :class:`Pair` ``p``;
* None when the message passes, or when the check does not apply (a field it needs is
  unavailable, or the message has no earlier one to compare with): it is skipped, not
  flagged;
* else the failure: ``score`` how far beyond the threshold (>= 1, :func:`ratio`), and
  ``evidence`` the numbers that failed.

To add a check: write its function here and add a :class:`Check` to :data:`TABLE` (and its
name to :data:`CHECKS` when it is a new one).  :class:`~catc.mbd.MisbehaviorDetector`
runs the message checks in the table's order, then the pair checks for each neighbour in
turn, and makes every failure a :class:`Detection` named after its entry; which failures
quarantine at once is :func:`catc.mbd.quarantine.is_strong`.  docs/mbd.md has each check's
formula, threshold and source.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

from catc.mbd.config import MbdConfig
from catc.mbd.geometry import RAD, blocks, dlon, max_min_dist, overlap
from catc.mbd.state import Senders

__all__ = ["BASELINE_CHECKS", "CHECKS", "ID_CONFLICT", "TABLE", "TRACK_CHECKS", "Check",
           "Detection", "Observation", "Pair", "in_path", "pairs", "ratio"]

#: The check names a :class:`Detection` carries (the checks of :data:`TABLE`) ...
CHECKS = ("range", "position-consistency", "speed-consistency", "position-speed",
          "sudden-appearance", "frequency", "heading", "sybil", "intersection")
#: ... and the finding of the identity binding (:mod:`catc.mbd.identity`): a message
#: under an id another signer holds.
ID_CONFLICT = "id-conflict"

#: Checks whose failure means the message contradicts its own track: such a message does
#: not become the sender's reference (one bad message must not poison the next good one).
#: Failures of the others (the message's position is self-consistent) still update it.
TRACK_CHECKS = frozenset({"position-consistency", "speed-consistency", "frequency"})

#: Checks whose failure makes the message, when it is accepted, the start of a new
#: baseline (position-speed: a GNSS step is reported once, a lasting lie again whenever it
#: outgrows the tolerances).
BASELINE_CHECKS = frozenset({"position-speed"})

_SCORE_CAP = 1e6

#: What a failed check returns: ``(score, evidence)``.
Finding = tuple[float, dict]


@dataclass(frozen=True)
class Detection:
    """One failed check of one message."""

    #: One of :data:`CHECKS`, or :data:`ID_CONFLICT`.
    check: str
    #: The TemporaryID the message claims.
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
    #: Whom the evidence attaches to: the HashedId8 of the certificate that signed the
    #: message (None: unsigned, the id ``suspect`` itself).
    signer: bytes | None = None


class Observation:
    """One received message as the checks see it.  The detector refills its one
    Observation for every message; the checks read it (and the Sybil check counts in
    ``sybil``).

    * Its signer: ``key``, whom the evidence attaches to (the signer's HashedId8, or
      ``tid`` when unsigned), ``conflict``, the other signer holding ``tid`` (None: none;
      when set, the fields below are not filled: the message goes no further), and
      ``twin``, another id the signer sends under at the same time (None: none).
    * The message: ``bsm`` itself, ``tid``, ``t`` (receive time, s), ``sm`` (secMark),
      ``lat``, ``lon``, ``speed``, ``heading`` (deg, in [0, 360)), ``length``, ``width``
      (None when unavailable), and ``kx``/``ky``, metres per degree at its latitude.
    * Its sender: ``st`` (:class:`~catc.mbd.state.Sender`), its last accepted message
      ``acc`` (None: this is its first) and all the ``senders``; ``discredited(tid)``,
      whether the sender of id ``tid`` is in quarantine (no witness: a fabricated
      vehicle's place is no intersection for anybody, nor a shadow, nor a previous
      pseudonym).
    * The host: ``host_d`` (m; None: no host position) and, when known, its offset from
      the sender ``hx``, ``hy`` (m east, north), ``host_heading`` (deg or None) and
      ``host_k``, the curvature of its path (1/m, + turning right; 0: straight or unknown).
    * Against ``acc``: ``ahead``, how far the sender's clock runs ahead of its lowest
      latency (None without secMarks), the interval ``dt`` on that clock (None: none
      usable), the message's time ``ts`` on it, and ``follows``: it comes after ``acc``,
      plausibly in time (the track checks compare the two).
    * Against the anchor, the newest accepted message at least ``anchor_s`` older:
      ``rdist`` (m; None: no anchor older than the message) and, when known, ``ref``
      itself, ``dtr`` (s), ``rx``, ``ry`` (m); ``anchor_i``, its index in the sender's
      history (None: whatever the checks say, the message will not be the sender's
      reference: late, or an implausible timestamp).
    * While the pair checks run: ``sybil``, the Sybil check's counts by the other id, and
      the sender's footprint: heading ``h`` (rad), ``sin_h``, ``cos_h`` and diagonal
      ``diag`` (m)."""

    __slots__ = ("acc", "ahead", "anchor_i", "bsm", "conflict", "cos_h", "diag", "discredited",
                 "dt", "dtr", "follows", "h", "heading", "host_d", "host_heading", "host_k",
                 "hx", "hy", "key", "kx", "ky", "lat", "length", "lon", "rdist", "ref", "rx",
                 "ry", "senders", "sin_h", "sm", "speed", "st", "sybil", "t", "tid", "ts",
                 "twin", "width")

    def __init__(self, senders: Senders) -> None:
        self.senders = senders


class Pair:
    """A neighbour of the message's sender, for the pair checks: its id ``tid``, its last
    accepted message ``m``, where it is at this message's time (``x``, ``y`` east/north m
    from the sender, moved on by its speed over ``dt`` s; ``d`` m away) and its heading
    ``h`` (rad).  Valid during the call only (:func:`pairs` reuses it)."""

    __slots__ = ("d", "dt", "h", "m", "tid", "x", "y")


def ratio(num: float, den: float) -> float:
    """``num / den`` for a score (>= 1 when failed), finite."""
    if den <= num / _SCORE_CAP:
        return _SCORE_CAP
    return min(num / den, _SCORE_CAP)


# -- against the host ----------------------------------------------------------------------


def range_plausibility(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD RangePlausibilityCheck: the sender farther from the host than a radio reaches."""
    d = o.host_d
    if d is None or not d >= c.max_range_m:
        return None
    return ratio(d, c.max_range_m), {"distance_m": d, "limit_m": c.max_range_m}


def host_intersection(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD IntersectionCheck with the host (dt = ``host_delta_s``): the footprints
    overlap.  Without the host's heading its footprint is aligned with the sender's."""
    d, length, width = o.host_d, o.length, o.width
    if d is None or o.heading is None or length is None:
        return None
    reach = 0.5 * (math.hypot(length, width) + math.hypot(c.host_length_m, c.host_width_m))
    if not d < reach:
        return None
    hh = o.host_heading
    h = o.heading * RAD
    inter = overlap((0.0, 0.0, h, length, width),
                (o.hx, o.hy, h if hh is None else hh * RAD, c.host_length_m, c.host_width_m))
    inter *= (c.max_delta_inter_s - c.host_delta_s) / c.max_delta_inter_s
    if not inter > c.intersection_threshold:
        return None
    return ratio(inter, c.intersection_threshold), {
        "overlap": inter, "limit": c.intersection_threshold, "with": "host"}


def speed_plausibility(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD SpeedPlausibilityCheck: a speed no car reaches (reported as
    speed-consistency)."""
    speed = o.speed
    if speed is None or not speed >= c.max_speed_mps:
        return None
    return ratio(speed, c.max_speed_mps), {"speed_mps": speed, "limit_mps": c.max_speed_mps}


def sudden_appearance(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD SuddenAppearenceCheck: a sender's first message close to the host that does
    not continue another id's path (a pseudonym change), once every vehicle in range has
    been heard (:meth:`~catc.mbd.state.Senders.unheard_s`: 0.5 s at 10 Hz without loss,
    not F2MD's blind 2.1 s)."""
    d = o.host_d
    if o.acc is not None or d is None or not d < c.sa_range_m:
        return None
    senders = o.senders
    if not o.t - senders.t0 >= senders.unheard_s(c) or _continues(o, c):
        return None
    along, across = _in_host_frame(o)
    return ratio(c.sa_range_m, d), {"distance_m": d, "limit_m": c.sa_range_m,
                                    "safety_range_m": c.sa_safety_range_m,
                                    "along_m": along, "across_m": across,
                                    "behind": _behind(o, c) if d < c.sa_safety_range_m
                                    else None}


def _in_host_frame(o: Observation) -> tuple[float | None, float | None]:
    """The sender from the host along the host's path (m, + ahead) and across it (m, +
    right): in the host's heading frame, less the offset of its arc (``host_k``, 1/m)
    at that distance; (None, None) without the host's heading."""
    hh = o.host_heading
    if hh is None:
        return None, None
    h = hh * RAD
    x, y = -o.hx, -o.hy  # the sender from the host, east and north
    s, c_ = math.sin(h), math.cos(h)
    along = x * s + y * c_
    return along, x * c_ - y * s - 0.5 * o.host_k * along * along


def in_path(d: Detection, c: MbdConfig) -> bool:
    """Whether a sudden appearance ``d`` is in the host's path ahead (where a ghost
    can trigger a forward collision warning), or its place is unknown (no host heading:
    taken as in the path)."""
    along, across = d.evidence.get("along_m"), d.evidence.get("across_m")
    return along is None or (along > 0.0 and abs(across) <= c.sa_path_halfwidth_m)


def _behind(o: Observation, c: MbdConfig) -> int | None:
    """The id of a vehicle heard lately, and for ``sa_shadow_heard_s`` at least (ids that
    appear together shield none of each other), whose footprint crosses the line of
    sight from the host to the message's sender (None: a clear line).  Vehicles shadow the radio
    (M. Boban et al., "Impact of Vehicles as Obstacles in Vehicular Ad Hoc Networks",
    IEEE JSAC 29(1), 2011: some 10 dB past one car), so a vehicle first heard behind
    another may have been there all along; in the clear it could not have."""
    get = o.senders.by_id.get
    hx, hy = o.hx, o.hy
    for otid in o.senders.ids_near(o.lat, o.lon):
        other = get(otid)
        if other is None or other is o.st or other.acc is None \
                or not o.t - other.first_t >= c.sa_shadow_heard_s or o.discredited(otid):
            continue
        m = other.acc
        dt = o.senders.pair_dt(other, o.t, o.sm)
        if not -c.max_delta_inter_s < dt < c.max_delta_inter_s:
            continue
        ox, oy = dlon(m.lon, o.lon) * o.kx, (m.lat - o.lat) * o.ky
        width = c.host_width_m if m.width is None else m.width
        if m.heading is None:
            box = (ox, oy, 0.0, width, width)
        else:
            h = m.heading * RAD
            if m.speed is not None:
                ox += m.speed * dt * math.sin(h)
                oy += m.speed * dt * math.cos(h)
            box = (ox, oy, h, c.host_length_m if m.length is None else m.length, width)
        if blocks(0.0, 0.0, hx, hy, box):
            return other.tid
    return None


def _continues(o: Observation, c: MbdConfig) -> bool:
    """Whether the message's new id continues the path of a sender heard within
    ``sa_link_time_s``, plus twice the time the measured loss may hide a vehicle (a
    pseudonym change; :class:`~catc.mbd.config.MbdConfig`)."""
    v = (c.max_speed_mps if o.speed is None else min(o.speed, c.max_speed_mps)) + 5.0
    link_s = c.sa_link_time_s + 2.0 * o.senders.unheard_s(c)
    reach = min(8, 1 + int(v * link_s // c.grid_cell_m))
    lat, lon, kx, ky = o.lat, o.lon, o.kx, o.ky
    get = o.senders.by_id.get
    for otid in o.senders.ids_near(lat, lon, reach):
        other = get(otid)
        if other is None or other.acc is None or other.tid == o.tid \
                or o.discredited(otid):
            continue
        m = other.acc
        dt = o.senders.pair_dt(other, o.t, o.sm)
        # a vehicle does not send under two ids in the same interval: an id heard with
        # this very message's time is a neighbour, not our previous pseudonym
        if not c.sa_link_min_gap_s <= dt <= link_s:
            continue
        ox, oy = dlon(m.lon, lon) * kx, (m.lat - lat) * ky
        if m.speed is not None and m.heading is not None:
            h = m.heading * RAD
            ox += m.speed * dt * math.sin(h)
            oy += m.speed * dt * math.cos(h)
        if math.hypot(ox, oy) <= 0.5 * c.sa_link_accel_mps2 * dt * dt + c.max_mgt_rng_up_m:
            return True
    return False


# -- against the sender's own track -------------------------------------------------------


def beacon_frequency(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD BeaconFrequencyCheck, on secMark: messages closer in time than
    ``min_interval_s`` (two messages with one secMark included); and the sender's clock
    running ahead of the receive clock (a forged timestamp).  A message older than the
    sender's last beyond the reorder window never gets here: it is a replay, whoever
    sent it, and the detector drops it without a finding."""
    ahead = o.ahead
    if ahead is None:
        return None
    if ahead > c.max_clock_skew_s:
        return ratio(ahead, c.max_clock_skew_s), {"ahead_s": ahead,
                                                  "limit_s": c.max_clock_skew_s}
    dt = o.dt
    if not dt < c.min_interval_s:
        return None
    return ratio(c.min_interval_s, dt), {"interval_s": dt, "limit_s": c.min_interval_s}


def position_consistency(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD PositionConsistancyCheck: farther from the last message than ``max_speed_mps``
    covers in the interval, plus the GNSS tolerance ``max_mgt_rng_up_m``."""
    if not o.follows:
        return None
    acc, dt = o.acc, o.dt
    dx = o.lon - acc.lon  # dlon(o.lon, acc.lon), its common case inline
    dx = (dx if -180.0 <= dx <= 180.0 else dlon(o.lon, acc.lon)) * o.kx
    dy = (o.lat - acc.lat) * o.ky
    dist = math.hypot(dx, dy)
    limit = c.max_speed_mps * dt + c.max_mgt_rng_up_m
    if not dist >= limit:
        return None
    return ratio(dist, limit), {"distance_m": dist, "limit_m": limit, "interval_s": dt}


def speed_consistency(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD SpeedConsistancyCheck: a speed change beyond ``max_accel_mps2`` or
    ``max_decel_mps2`` over the interval (plus ``speed_tolerance_mps``)."""
    speed = o.speed
    if not o.follows or speed is None or o.acc.speed is None:
        return None
    dt = o.dt
    dv = speed - o.acc.speed
    bound = c.max_accel_mps2 if dv > 0.0 else c.max_decel_mps2
    limit = bound * dt + c.speed_tolerance_mps
    if not abs(dv) >= limit:
        return None
    return ratio(abs(dv), limit), {"accel_mps2": dv / dt, "limit_mps2": bound,
                                   "interval_s": dt}


def position_speed(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD PositionSpeedConsistancyCheck, against the anchor ~1 s back: the distance
    covered outside the kinematic envelope of the two reported speeds
    (:func:`~catc.mbd.geometry.max_min_dist`) widened by the tolerances."""
    dist, speed = o.rdist, o.speed
    if dist is None or speed is None:
        return None
    dt, old = o.dtr, o.ref.speed
    if not dt < c.max_time_delta_s or old is None:
        return None
    least, greatest = max_min_dist(speed, old, dt, c.max_accel_mps2, c.max_decel_mps2,
                                   c.max_speed_mps)
    vmin = min(speed, old)
    addon = c.max_mgt_rng_down_m + 0.3571 * vmin - 0.01694 * vmin * vmin
    addon = max(addon, c.max_mgt_rng_up_m)
    low, high = least - addon, greatest + c.max_mgt_rng_up_m
    if dist < low:
        score = ratio(low, dist)
    elif dist > high:
        score = ratio(dist, high)
    else:
        return None
    return score, {"distance_m": dist, "min_m": low, "max_m": high, "interval_s": dt,
                   "speeds_mps": (old, speed)}


def position_heading(o: Observation, c: MbdConfig) -> Finding | None:
    """F2MD PositionHeadingConsistancyCheck, against the anchor: the heading more than
    ``max_heading_change_deg`` off the direction of travel (not checked slow, over a short
    displacement, or in reverse gear)."""
    dist, speed, hdg = o.rdist, o.speed, o.heading
    if dist is None or not o.dtr < c.pos_heading_time_s or hdg is None or speed is None \
            or not speed >= c.heading_min_speed_mps or not dist >= c.heading_min_distance_m \
            or o.bsm.transmission == 3:  # REVERSE_GEARS
        return None
    dtr = o.dtr
    path = math.degrees(math.atan2(o.rx, o.ry)) % 360.0
    diff = abs((hdg - path + 180.0) % 360.0 - 180.0)
    if not diff > c.max_heading_change_deg:
        return None
    return ratio(diff, c.max_heading_change_deg), {
        "heading_deg": hdg, "path_deg": path, "difference_deg": diff,
        "limit_deg": c.max_heading_change_deg, "interval_s": dtr}


# -- against the neighbours (the younger id of a pair is the suspect) ----------------------


def pairs(o: Observation, c: MbdConfig) -> Iterator[Pair]:
    """The neighbours the pair checks judge ``o`` against (``o`` has a heading and a
    size).  A pair is checked on the younger id's messages only, and only while the older
    one is still heard (an id that fell silent before this one appeared is a pseudonym
    change, not a twin); neighbours too far apart for any pair check to fail are left
    out."""
    lat, lon, kx, ky, t, st = o.lat, o.lon, o.kx, o.ky, o.t, o.st
    # no finding beyond this (m) plus the other's half length + width and its travel
    # (Sybil: along + lateral < half both lengths and widths + the gap and clearance)
    reach = 0.5 * (o.length + o.width) + c.sybil_lateral_clearance_m + c.sybil_min_gap_m \
        + c.sybil_headway_s * (o.speed or 0.0)
    first_t = st.first_t
    pair_dt = o.senders.pair_dt
    p = None
    get = o.senders.by_id.get
    for otid in o.senders.ids_near(lat, lon):
        other = get(otid)
        if other is None or other is st or other.acc is None or other.first_t > first_t \
                or other.heard_t < first_t:
            continue
        m = other.acc
        if m.heading is None or m.length is None:
            continue
        ox = m.lon - lon  # dlon(m.lon, lon), its common case inline (every neighbour)
        ox = (ox if -180.0 <= ox <= 180.0 else dlon(m.lon, lon)) * kx
        oy = (m.lat - lat) * ky
        ov = m.speed or 0.0
        if ox * ox + oy * oy > (reach + 0.5 * (m.length + m.width)
                                + ov * (abs(t - m.t) + c.max_clock_skew_s)) ** 2:
            continue  # too far apart even after the other's travel since
        dt = pair_dt(other, t, o.sm)
        if not -c.max_delta_inter_s < dt < c.max_delta_inter_s:
            continue
        oh = m.heading * RAD
        if m.speed is not None:  # where the other is now
            ox += m.speed * dt * math.sin(oh)
            oy += m.speed * dt * math.cos(oh)
        if p is None:  # the first one: the sender's footprint, for all of them
            p = Pair()
            o.h = h = o.heading * RAD
            o.sin_h = math.sin(h)
            o.cos_h = math.cos(h)
            o.diag = math.hypot(o.length, o.width)
        p.tid = other.tid
        p.m = m
        p.x = ox
        p.y = oy
        p.h = oh
        p.dt = dt
        p.d = math.hypot(ox, oy)
        yield p


def intersection(o: Observation, p: Pair, c: MbdConfig) -> Finding | None:
    """F2MD IntersectionCheck / MultipleIntersectionCheck: the footprints overlap (F2MD's
    IoU at the smaller footprint's size, :func:`~catc.mbd.geometry.overlap`), the ratio
    weighted by how close in time (``max_delta_inter_s``).  A neighbour in quarantine is
    no witness: an honest car driving through the place of a stopped ghost overlaps it,
    and that is no evidence against the car."""
    m = p.m
    if not p.d < 0.5 * (o.diag + math.hypot(m.length, m.width)) or o.discredited(p.tid):
        return None
    inter = overlap((0.0, 0.0, o.h, o.length, o.width),
                (p.x, p.y, p.h, m.length, m.width))
    inter *= (c.max_delta_inter_s - abs(p.dt)) / c.max_delta_inter_s
    if not inter > c.intersection_threshold:
        return None
    return ratio(inter, c.intersection_threshold), {
        "overlap": inter, "limit": c.intersection_threshold, "interval_s": p.dt}


def sybil(o: Observation, p: Pair, c: MbdConfig) -> Finding | None:
    """Ours (F2MD has no legacy Sybil check): two ids moving together, closer than two
    vehicles could, in ``sybil_messages`` consecutive messages of the younger one (counted
    in ``o.sybil``)."""
    m, speed, hdg = p.m, o.speed, o.heading
    if speed is None or not speed >= c.sybil_min_speed_mps or m.speed is None \
            or not m.speed >= c.sybil_min_speed_mps \
            or not abs(speed - m.speed) <= c.sybil_speed_mps \
            or not abs((hdg - m.heading + 180.0) % 360.0 - 180.0) <= c.sybil_heading_deg:
        return None
    sin_h, cos_h = o.sin_h, o.cos_h
    along = abs(p.x * sin_h + p.y * cos_h)
    lateral = abs(p.x * cos_h - p.y * sin_h)
    lat_limit = 0.5 * (o.width + m.width) + c.sybil_lateral_clearance_m
    gap = along - 0.5 * (o.length + m.length)
    gap_limit = c.sybil_min_gap_m + c.sybil_headway_s * speed
    if not (lateral < lat_limit and gap < gap_limit):
        return None
    n = o.sybil[p.tid] = o.st.sybil.get(p.tid, 0) + 1
    if n < c.sybil_messages:
        return None
    score = min(ratio(lat_limit, lateral), ratio(gap_limit, max(gap, 0.0)))
    return max(score, 1.0), {"lateral_m": lateral, "lateral_limit_m": lat_limit,
                             "gap_m": gap, "gap_limit_m": gap_limit, "messages": n}


# -- the table -------------------------------------------------------------------------------


class Check(NamedTuple):
    """One entry of :data:`TABLE`."""

    #: The ``Detection.check`` of its failures (one of :data:`CHECKS`).
    name: str
    #: The function: ``run(o, c)``, or ``run(o, p, c)`` for a pair check.
    run: Callable[..., Finding | None]
    #: Run once per neighbour (:func:`pairs`), after the message checks.
    pair: bool = False


#: Every check, in the order its detections are listed.
TABLE: tuple[Check, ...] = (
    Check("range", range_plausibility),
    Check("intersection", host_intersection),
    Check("speed-consistency", speed_plausibility),
    Check("sudden-appearance", sudden_appearance),
    Check("frequency", beacon_frequency),
    Check("position-consistency", position_consistency),
    Check("speed-consistency", speed_consistency),
    Check("position-speed", position_speed),
    Check("heading", position_heading),
    Check("intersection", intersection, pair=True),
    Check("sybil", sybil, pair=True),
)
