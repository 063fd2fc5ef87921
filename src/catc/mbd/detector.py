"""The detector: ``observe`` reads one message into an
:class:`~catc.mbd.checks.Observation`, runs the checks of
:data:`~catc.mbd.checks.TABLE` on it and combines their verdicts into the sender's state
and its quarantine (the package docstring has the overview)."""

from __future__ import annotations

import math
import operator
from collections import Counter
from typing import Any

from catc.mbd.checks import BASELINE_CHECKS, TABLE, TRACK_CHECKS, Detection, Observation, pairs
from catc.mbd.config import MbdConfig
from catc.mbd.geometry import dlon, scale
from catc.mbd.quarantine import Quarantine, is_strong
from catc.mbd.state import Msg, Sender, Senders, wrapped_dt

__all__ = ["MisbehaviorDetector"]

_DEFAULT = MbdConfig()
_MESSAGE_CHECKS = tuple((k.name, k.run) for k in TABLE if not k.pair)
_PAIR_CHECKS = tuple((k.name, k.run) for k in TABLE if k.pair)


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
        self._o = Observation(self._senders)

    def __len__(self) -> int:
        """Senders with state (at most ``max_senders``)."""
        return len(self._senders)

    def grid_entries(self) -> int:
        """Ids in the neighbour grid (bounded like the senders)."""
        return self._senders.grid_entries()

    def quarantined(self, temp_id: int, t: float) -> bool:
        """Whether ``temp_id`` is in quarantine at ``t`` (its track must raise no warning).

        Rule: from the detection that puts it there, for ``quarantine_s``, renewed by every
        new detection (and, after a strong finding, by every message): quarantine after
        ``quarantine_k`` failed messages within ``quarantine_window_s``, or at once on a
        sudden appearance inside the safety range, an intersection or a Sybil finding."""
        return self._quarantine.quarantined(temp_id, t)

    def observe(self, bsm, t: float, host_lat: float | None, host_lon: float | None, *,
                host_heading: float | None = None) -> list[Detection]:
        """The checks ``bsm`` (a :class:`catc.bsm.BSM`) fails, received at ``t`` (s, the
        caller's clock) with the host at ``host_lat``/``host_lon`` (None: unknown, and the
        host-relative checks are skipped; pass None too when the host's own position is
        stale).  Empty for a plausible message.  A check whose fields are unavailable is
        skipped.  ``host_heading`` (deg) orients the host's footprint; without it the host
        is taken as aligned with the sender.

        The message checks of :data:`~catc.mbd.checks.TABLE` run in its order, then, when
        the message follows its sender's track and has a heading and a size, its pair
        checks against each neighbour (:func:`~catc.mbd.checks.pairs`) in turn.  Then the
        verdicts are combined: the message becomes its sender's reference unless it
        contradicts its own track (:data:`~catc.mbd.checks.TRACK_CHECKS`; a new baseline
        on :data:`~catc.mbd.checks.BASELINE_CHECKS`), and the quarantine rule applies
        (:mod:`catc.mbd.quarantine`)."""
        o = self._read(bsm, t, host_lat, host_lon, host_heading)
        if o is None:
            return []
        c, tid, t = self.config, o.tid, o.t
        found: list[Detection] = []
        for name, run in _MESSAGE_CHECKS:
            r = run(o, c)
            if r is not None:
                found.append(Detection(name, tid, t, r[0], r[1]))
        if o.follows and o.heading is not None and o.length is not None:
            o.sybil = {}
            for p in pairs(o, c):
                for name, run in _PAIR_CHECKS:
                    r = run(o, p, c)
                    if r is not None:
                        found.append(Detection(name, tid, t, r[0], r[1], p.tid))
            o.st.sybil = o.sybil

        st = o.st
        st.heard_t = t
        if o.anchor_i is not None and not (found and any(d.check in TRACK_CHECKS
                                                         for d in found)):
            reset = bool(found) and any(d.check in BASELINE_CHECKS for d in found)
            self._senders.accept(st, Msg(o.ts, t, o.sm, o.lat, o.lon, o.speed, o.heading,
                                         o.length, o.width), o.anchor_i, reset)
        if found:
            for d in found:
                self.counters[d.check] += 1
            if self._quarantine.punish(st, t, any(is_strong(d, c) for d in found)):
                self.counters["quarantines"] += 1
        elif st.strong:  # a clean message renews only a strong finding's quarantine
            self._quarantine.passed(st, t)
        return found

    def _read(self, bsm, t: float, host_lat: float | None, host_lon: float | None,
              host_heading: float | None) -> Observation | None:
        """The message as the checks see it (None: no usable time, position or id):
        its fields, the host from it, and its timing (:meth:`_timing`).  Every number
        goes through :func:`_num`, whose float case is written out here (most of them
        are floats, and this runs for every message); the one Observation is refilled
        (a new one per message would cost some 5 % of ``observe``)."""
        t = t if type(t) is float and t - t == 0.0 else _num(t)
        lat, lon = bsm.lat, bsm.lon
        lat = lat if type(lat) is float and lat - lat == 0.0 else _num(lat)
        lon = lon if type(lon) is float and lon - lon == 0.0 else _num(lon)
        if t is None or lat is None or lon is None or not -90.0 <= lat <= 90.0 \
                or not -180.0 <= lon <= 180.0:
            return None
        try:
            tid = int(bsm.temp_id)
        except (TypeError, ValueError):
            return None
        senders = self._senders
        if senders.t0 is None:
            senders.t0 = t
        speed, heading, length, width = bsm.speed, bsm.heading, bsm.length, bsm.width
        speed = speed if type(speed) is float and speed - speed == 0.0 else _num(speed)
        if speed is not None and speed < 0.0:
            speed = None
        heading = heading if type(heading) is float and heading - heading == 0.0 \
            else _num(heading)
        if heading is not None:
            heading %= 360.0
        length = length if type(length) is float and length - length == 0.0 else _num(length)
        width = width if type(width) is float and width - width == 0.0 else _num(width)
        if length is None or width is None or length <= 0.0 or width <= 0.0:
            length = width = None
        sm = bsm.sec_mark
        sm = sm if type(sm) is int and 0 <= sm < 61_000 else _sec_mark(sm)
        kx, ky = scale(lat)
        st = senders.get(tid, t)
        o = self._o
        o.bsm = bsm
        o.tid = tid
        o.t = t
        o.lat = lat
        o.lon = lon
        o.speed = speed
        o.heading = heading
        o.length = length
        o.width = width
        o.sm = sm
        o.kx = kx
        o.ky = ky
        o.st = st
        o.acc = st.acc
        o.host_d = None
        hlat = host_lat if type(host_lat) is float and host_lat - host_lat == 0.0 \
            else _num(host_lat)
        hlon = host_lon if type(host_lon) is float and host_lon - host_lon == 0.0 \
            else _num(host_lon)
        if hlat is not None and hlon is not None and -90.0 <= hlat <= 90.0:
            hx = lon - hlon  # the host from the sender; dlon(lon, hlon), its common case
            o.hx = hx = -(hx if -180.0 <= hx <= 180.0 else dlon(lon, hlon)) * kx
            o.hy = hy = (hlat - lat) * ky
            o.host_d = math.hypot(hx, hy)
            o.host_heading = host_heading if type(host_heading) is float \
                and host_heading - host_heading == 0.0 else _num(host_heading)
        self._timing(o, st)
        return o

    def _timing(self, o: Observation, st: Sender) -> None:
        """The message against the sender's last accepted one: its interval ``dt``, its
        time ``ts`` on the sender's clock, ``ahead``, whether it ``follows``, and the
        anchor.  ``o.anchor_i`` is None when the message cannot become the sender's
        reference, whatever the checks say: late (reordered or duplicated on the way;
        not a finding: only the checks that need no history run, as after a receive
        clock jump), or with an implausible timestamp (the frequency check's finding)."""
        o.dt = o.ahead = o.rdist = None
        o.ts = t = o.t
        o.follows = False
        acc = st.acc
        if acc is None:
            o.anchor_i = 0
            return
        o.anchor_i = None
        c = self.config
        dt_rx = t - acc.t
        if not abs(dt_rx) < 1e9:  # a receive clock that jumped by decades
            return
        sm = o.sm
        if sm is not None and acc.sm is not None:
            dt = wrapped_dt(sm, acc.sm, dt_rx)
            ts = acc.ts + dt
            ahead = st.min_off - (t - ts)
            if not ahead > c.max_clock_skew_s and dt <= 0.0 and (
                    -c.reorder_window_s <= dt < 0.0
                    or (dt == 0.0 and o.lat == acc.lat and o.lon == acc.lon)):
                return  # late
            o.ahead = ahead
            if ahead > c.max_clock_skew_s or dt <= 0.0:
                o.dt = dt
                return
        else:
            dt = dt_rx  # no secMark: the receive clock (jittery, but all there is)
            ts = acc.ts + dt
            if dt <= 0.0:
                return  # late
        o.dt = dt
        o.ts = ts
        o.follows = True
        # the anchor: the newest accepted message at least anchor_s older
        hist = st.hist
        n = len(hist)
        i = 0
        while i + 1 < n and ts - hist[i + 1].ts >= c.anchor_s:
            i += 1
        o.anchor_i = i
        ref = hist[i]
        dtr = ts - ref.ts
        if dtr > 0.0:
            o.ref = ref
            o.dtr = dtr
            rx = o.lon - ref.lon  # dlon(o.lon, ref.lon), its common case
            o.rx = rx = (rx if -180.0 <= rx <= 180.0 else dlon(o.lon, ref.lon)) * o.kx
            o.ry = ry = (o.lat - ref.lat) * o.ky
            o.rdist = math.hypot(rx, ry)
