"""The detector: per-sender state, the neighbour grid, the quarantine, and ``observe``,
which runs the checks on one message (the package docstring has the overview)."""

from __future__ import annotations

import math
import operator
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from catc.mbd.config import MbdConfig
from catc.mbd.geometry import RAD, dlon, iou, max_min_dist, scale
from catc.mbd.quarantine import Quarantine
from catc.mbd.state import Msg, Sender, Senders, wrapped_dt

__all__ = ["CHECKS", "Detection", "MisbehaviorDetector"]

#: The check names a :class:`Detection` carries.
CHECKS = ("range", "position-consistency", "speed-consistency", "position-speed",
          "sudden-appearance", "frequency", "heading", "sybil", "intersection")

#: Checks whose failure means the message contradicts its own track: such a message does
#: not become the sender's reference (one bad message must not poison the next good one).
#: Failures of the others (the message's position is self-consistent) still update it.
_TRACK_CHECKS = frozenset({"position-consistency", "speed-consistency", "frequency"})
_SCORE_CAP = 1e6
_DEFAULT = MbdConfig()


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


def _ratio(num: float, den: float) -> float:
    """``num / den`` for a score (>= 1 when failed), finite."""
    if den <= num / _SCORE_CAP:
        return _SCORE_CAP
    return min(num / den, _SCORE_CAP)



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


class MisbehaviorDetector:
    """Plausibility checks on verified BSMs with bounded per-sender state (module
    docstring; every threshold in :class:`MbdConfig`)."""

    def __init__(self, config: MbdConfig = _DEFAULT, max_senders: int = 4096) -> None:
        if not isinstance(max_senders, int) or max_senders < 1:
            raise ValueError(f"max_senders must be a positive int, got {max_senders!r}")
        self.config = config
        self.max_senders = max_senders
        #: Detections by check name, and ``quarantines`` (senders put in quarantine).
        self.counters: Counter = Counter()
        self._senders = Senders(config, max_senders)
        self._quarantine = Quarantine(config, max_senders)

    def __len__(self) -> int:
        """Senders with state (at most ``max_senders``)."""
        return len(self._senders)

    def grid_entries(self) -> int:
        """Ids in the neighbour grid (bounded like the senders)."""
        return self._senders.grid_entries()

    # -- quarantine --------------------------------------------------------------------

    def quarantined(self, temp_id: int, t: float) -> bool:
        """Whether ``temp_id`` is in quarantine at ``t`` (its track must raise no warning).

        Rule: from the detection that puts it there, for ``quarantine_s``, renewed by every
        new detection (and, after a strong finding, by every message): quarantine after
        ``quarantine_k`` failed messages within ``quarantine_window_s``, or at once on a
        sudden appearance inside the safety range, an intersection or a Sybil finding."""
        return self._quarantine.quarantined(temp_id, t)

    def _punish(self, st: Sender, t: float, found: list[Detection], strong: bool) -> None:
        if self._quarantine.punish(st, t, strong):
            self.counters["quarantines"] += 1

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
        senders = self._senders
        if senders.t0 is None:
            senders.t0 = t
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
        kx, ky = scale(lat)
        found: list[Detection] = []
        strong = False

        def add(check: str, score: float, evidence: dict, other: int | None = None) -> None:
            found.append(Detection(check, tid, t, score, evidence, other))

        # -- against the host: range, intersection with the host ------------------------
        hlat, hlon = _num(host_lat), _num(host_lon)
        host_d = None
        if hlat is not None and hlon is not None and -90.0 <= hlat <= 90.0:
            hx, hy = -dlon(lon, hlon) * kx, (hlat - lat) * ky  # host from the sender
            host_d = math.hypot(hx, hy)
            if host_d >= c.max_range_m:  # RangePlausibilityCheck
                add("range", _ratio(host_d, c.max_range_m),
                    {"distance_m": host_d, "limit_m": c.max_range_m})
            if heading is not None and length is not None:
                reach = 0.5 * (math.hypot(length, width) + math.hypot(c.host_length_m,
                                                                        c.host_width_m))
                if host_d < reach:
                    hh = _num(host_heading)
                    h = heading * RAD
                    inter = iou((0.0, 0.0, h, length, width),
                                 (hx, hy, h if hh is None else hh * RAD, c.host_length_m,
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

        st = senders.get(tid, t)
        acc = st.acc
        ts = t  # the sender's clock, continued from its last accepted message
        late = False
        timing_ok = True
        anchor_i = 0
        reset = False
        if acc is None:
            # -- SuddenAppearenceCheck: a first message close to the host ------------------
            warmup = max(c.sa_warmup_s, c.sa_warmup_intervals * senders.interval)
            if host_d is not None and host_d < c.sa_range_m and t - senders.t0 >= warmup \
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
                dt = wrapped_dt(sm, acc.sm, dt_rx)
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
                dx, dy = dlon(lon, acc.lon) * kx, (lat - acc.lat) * ky
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
                    rx, ry = dlon(lon, ref.lon) * kx, (lat - ref.lat) * ky
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
            msg = Msg(ts, t, sm, lat, lon, speed, heading, length, width)
        return self._finish(st, tid, t, found, strong, msg, anchor_i, reset)

    def _finish(self, st: Sender, tid: int, t: float, found: list[Detection], strong: bool,
                msg: Msg | None, anchor_i: int, reset: bool) -> list[Detection]:
        st.heard_t = t
        if msg is not None:
            self._senders.accept(st, msg, anchor_i, reset)
        if found:
            for d in found:
                self.counters[d.check] += 1
            self._punish(st, t, found, strong)
        elif st.strong:
            self._quarantine.passed(st, t)
        return found

    def _position_speed(self, add, dist: float, dt: float, speed: float, old: float) -> bool:
        """F2MD PositionSpeedConsistancyCheck: the distance covered in ``dt`` within the
        kinematic envelope of the two reported speeds.  True when it fails (the message
        then starts a new baseline: a GNSS step is reported once, a lasting lie again
        whenever it outgrows the tolerances)."""
        c = self.config
        least, greatest = max_min_dist(speed, old, dt, c.max_accel_mps2, c.max_decel_mps2,
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

    def _continues(self, tid: int, t: float, sm: int | None, lat: float, lon: float,
                   kx: float, ky: float, speed: float | None) -> bool:
        """Whether a new id continues the path of a sender heard within ``sa_link_time_s``
        (a pseudonym change; :class:`MbdConfig`)."""
        c = self.config
        v = (c.max_speed_mps if speed is None else min(speed, c.max_speed_mps)) + 5.0
        reach = min(8, 1 + int(v * c.sa_link_time_s // c.grid_cell_m))
        get = self._senders.by_id.get
        for otid in self._senders.ids_near(lat, lon, reach):
            o = get(otid)
            if o is None or o.acc is None or o.tid == tid:
                continue
            m = o.acc
            dt = self._senders.pair_dt(o, t, sm)
            # a vehicle does not send under two ids in the same interval: an id heard with
            # this very message's time is a neighbour, not our previous pseudonym
            if not c.sa_link_min_gap_s <= dt <= c.sa_link_time_s:
                continue
            ox, oy = dlon(m.lon, lon) * kx, (m.lat - lat) * ky
            if m.speed is not None and m.heading is not None:
                h = m.heading * RAD
                ox += m.speed * dt * math.sin(h)
                oy += m.speed * dt * math.cos(h)
            if math.hypot(ox, oy) <= 0.5 * c.sa_link_accel_mps2 * dt * dt + c.max_mgt_rng_up_m:
                return True
        return False

    def _pairs(self, st: Sender, add, t: float, sm: int | None, lat: float, lon: float,
               kx: float, ky: float, speed: float | None, heading: float, length: float,
               width: float) -> bool:
        """MultipleIntersectionCheck and the Sybil check against the neighbours; True on a
        finding.  A pair is checked on the younger id's messages only, and only while the
        older one is still heard (an id that fell silent before this one appeared is a
        pseudonym change, not a twin)."""
        c = self.config
        h = heading * RAD
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
        get = self._senders.by_id.get
        for otid in self._senders.ids_near(lat, lon):
            o = get(otid)
            if o is None or o is st or o.acc is None or o.first_t > first_t \
                    or o.heard_t < first_t:
                continue
            m = o.acc
            if m.heading is None or m.length is None:
                continue
            ox, oy = dlon(m.lon, lon) * kx, (m.lat - lat) * ky
            ov = m.speed or 0.0
            if ox * ox + oy * oy > (reach + 0.5 * (m.length + m.width)
                                    + ov * (abs(t - m.t) + c.max_clock_skew_s)) ** 2:
                continue  # too far apart even after the other's travel since
            dt = self._senders.pair_dt(o, t, sm)
            if not -c.max_delta_inter_s < dt < c.max_delta_inter_s:
                continue
            oh = m.heading * RAD
            if m.speed is not None:  # where the other is now
                ox += m.speed * dt * math.sin(oh)
                oy += m.speed * dt * math.cos(oh)
            d = math.hypot(ox, oy)
            # -- IntersectionCheck ---------------------------------------------------------
            if d < 0.5 * (diag + math.hypot(m.length, m.width)):
                inter = iou(me, (ox, oy, oh, m.length, m.width))
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
