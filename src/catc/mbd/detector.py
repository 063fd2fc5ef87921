"""The detector: ``observe`` binds one message's id to its signer
(:mod:`catc.mbd.identity`), reads it into an :class:`~catc.mbd.checks.Observation`, drops
it if it is a copy or older than its sender's last (a replay), runs the checks of
:data:`~catc.mbd.checks.TABLE` on it and combines their verdicts into the sender's state
and its signer's quarantine (the package docstring has the overview)."""

from __future__ import annotations

import math
import operator
from collections import Counter
from collections.abc import Hashable
from typing import Any

from catc.mbd.checks import (
    BASELINE_CHECKS,
    ID_CONFLICT,
    TABLE,
    TRACK_CHECKS,
    Detection,
    Observation,
    in_path,
    pairs,
)
from catc.mbd.config import MbdConfig
from catc.mbd.geometry import dlon, scale
from catc.mbd.identity import Identities
from catc.mbd.quarantine import Quarantine
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


def _curvature(speed: Any, yaw_rate: Any) -> float:
    """The curvature (1/m, + turning right) of a path at ``speed`` (m/s) and ``yaw_rate``
    (deg/s, + clockwise): 0 when either is unknown or the vehicle all but stands still,
    and at most that of a 10 m turning circle."""
    v, w = _num(speed), _num(yaw_rate)
    if v is None or w is None or v < 1.0:
        return 0.0
    return max(-0.1, min(0.1, math.radians(w) / v))


def _hex(key: Hashable) -> str:
    return key.hex() if isinstance(key, bytes) else f"{key:08X}"


class MisbehaviorDetector:
    """Plausibility checks on verified BSMs with bounded per-sender state (module
    docstring; every threshold in :class:`MbdConfig`)."""

    #: Why :meth:`observe` dropped its last message without a finding (None: it did not):
    #: ``copy`` (an exact copy of a message heard from its sender) or ``stale`` (older
    #: than its sender's last beyond the reorder window); or, with the finding, ``id-
    #: conflict`` (another signer holds its id).
    dropped: str | None = None
    #: What :meth:`observe` reported for its last message: nothing while its sender's
    #: evidence is below the reporting threshold (the quarantine rule); once the sender
    #: is in quarantine, its findings in the window not reported before (on entry: the
    #: weak findings that led there) and this message's.  A misbehavior report (SAE J3287,
    #: ETSI TS 103 759) goes to the authority only past such a threshold (F2MD's
    #: AggregationApp), so an honest car's one odd message files none.
    reports: tuple[Detection, ...] = ()

    def __init__(self, config: MbdConfig = _DEFAULT, max_senders: int = 4096) -> None:
        if not isinstance(max_senders, int) or max_senders < 1:
            raise ValueError(f"max_senders must be a positive int, got {max_senders!r}")
        self.config = config
        self.max_senders = max_senders
        #: Detections by check name, ``quarantines`` (signers, or unsigned ids, put in
        #: quarantine), ``reported`` (findings reported, :attr:`reports`), and the
        #: messages dropped as ``copy`` or ``stale``.
        self.counters: Counter = Counter()
        self._senders = Senders(config, max_senders)
        self._quarantine = Quarantine(config, max_senders)
        self._ids = Identities(config, max_senders)
        self._o = Observation(self._senders)
        self._o.discredited = self._discredited
        #: TemporaryID -> until when (s) its warnings are withheld (:meth:`muted`)
        self._unconfirmed: dict[int, float] = {}

    def __len__(self) -> int:
        """Senders with state (at most ``max_senders``)."""
        return len(self._senders)

    def grid_entries(self) -> int:
        """Ids in the neighbour grid (bounded like the senders)."""
        return self._senders.grid_entries()

    def quarantined(self, temp_id: int, t: float, signer: bytes | None = None) -> bool:
        """Whether a message under ``temp_id`` signed by ``signer`` is in quarantine at
        ``t`` (its track must raise no warning): ``signer``'s quarantine; without one, that
        of the signer holding ``temp_id``, or of the unsigned id.

        Rule (:mod:`catc.mbd.quarantine`): from the detection that puts it there, for
        ``quarantine_s``, renewed by every new detection (and, after a strong finding, by
        every message): quarantine after ``quarantine_k`` failed messages within
        ``quarantine_window_s``, or at once on a sudden appearance inside the safety
        range, an intersection, a Sybil finding or an id conflict."""
        return self._quarantine.quarantined(self._key(temp_id, t, signer), t)

    def ids_of(self, temp_id: int, t: float, signer: bytes | None = None) -> frozenset[int]:
        """The ids a quarantine of this message's sender covers (their tracks go with
        it): those its signer holds, or ``temp_id`` alone when unsigned."""
        key = self._key(temp_id, t, signer)
        return self._ids.ids_of(key) | {temp_id} if isinstance(key, bytes) \
            else frozenset((temp_id,))

    def muted(self, t: float) -> frozenset[int]:
        """The ids whose warnings are withheld at ``t``: unconfirmed newcomers.  A first
        message inside the host's safety range and in its path ahead, but behind another
        vehicle (a weak sudden appearance: it may have been in that vehicle's radio shadow,
        or be a ghost hiding there), is tracked, not quarantined; for ``sa_confirm_s`` no
        warning may be raised on it (a ghost that brakes at once, behind a real leader,
        raises none; an honest car first heard there loses its warnings for that long)."""
        u = self._unconfirmed
        if not u:
            return frozenset()
        for tid in [k for k, until in u.items() if not t < until]:
            del u[tid]
        return frozenset(u)

    def _discredited(self, tid: int) -> bool:
        """Whether the sender of ``tid`` is in quarantine now (the message's time)."""
        t = self._o.t
        holder = self._ids.holder(tid, t) if self._ids else None
        return self._quarantine.quarantined(tid if holder is None else holder, t)

    def _key(self, temp_id: int, t: float, signer: bytes | None) -> Hashable:
        if signer is not None:
            return signer
        holder = self._ids.holder(temp_id, t)
        return temp_id if holder is None else holder

    def observe(self, bsm, t: float, host_lat: float | None, host_lon: float | None, *,
                host_heading: float | None = None, host_speed: float | None = None,
                host_yaw_rate: float | None = None,
                signer: bytes | None = None) -> list[Detection]:
        """The checks ``bsm`` (a :class:`catc.bsm.BSM`) fails, received at ``t`` (s, the
        caller's clock) with the host at ``host_lat``/``host_lon`` (None: unknown, and the
        host-relative checks are skipped; pass None too when the host's own position is
        stale).  Empty for a plausible message.  A check whose fields are unavailable is
        skipped.  ``host_heading`` (deg) orients the host's footprint; without it the host
        is taken as aligned with the sender.  ``host_speed`` (m/s) and ``host_yaw_rate``
        (deg/s, positive clockwise as in J2735) bend the host's path ahead, along which a
        sudden appearance is placed (:func:`~catc.mbd.checks.in_path`); without them the
        path is straight.

        ``signer`` is the HashedId8 of the certificate whose signature on the message
        verified (None: unsigned or unverified).  The evidence attaches to it, and it
        holds the message's id (:mod:`catc.mbd.identity`): a message under an id that
        another signer holds, or an unsigned one under a held id, is an id conflict (a
        strong finding against the newcomer; the message goes no further, and
        :attr:`dropped` says so); one under an id whose messages interleave in time with
        another id of the same signer is a Sybil (``other``: that id).  Without signers
        the evidence attaches to the id.

        A message that repeats one already heard from its sender (msgCnt, secMark and
        position), or that is older than its sender's last beyond the reorder window,
        is dropped without a finding (:attr:`dropped`): a replay, which needs no key and
        says nothing of its sender's behaviour.

        The message checks of :data:`~catc.mbd.checks.TABLE` run in its order, then, when
        the message follows its sender's track and has a heading and a size, its pair
        checks against each neighbour (:func:`~catc.mbd.checks.pairs`) in turn.  Then the
        verdicts are combined: the message becomes its sender's reference unless it
        contradicts its own track (:data:`~catc.mbd.checks.TRACK_CHECKS`; a new baseline
        on :data:`~catc.mbd.checks.BASELINE_CHECKS`), and the quarantine rule applies
        (:mod:`catc.mbd.quarantine`)."""
        self.dropped = None
        self.reports = ()
        o = self._read(bsm, t, host_lat, host_lon, host_heading, signer)
        if o is None:
            return []
        o.host_k = _curvature(host_speed, host_yaw_rate)
        c, tid, t, key = self.config, o.tid, o.t, o.key
        if o.conflict is not None:
            return self._conflict(o, signer)
        st = o.st
        copy = (bsm.msg_cnt, o.sm, o.lat, o.lon)
        copies = st.copies
        if copy in copies:
            return self._drop("copy")
        if o.dt is not None and o.dt < -c.reorder_window_s and not o.ahead > c.max_clock_skew_s:
            return self._drop("stale")
        copies[copy] = None
        if len(copies) > c.copies_kept:
            del copies[next(iter(copies))]
        found: list[Detection] = []
        if o.twin is not None:  # its signer sends under another id at the same time
            found.append(Detection("sybil", tid, t, 1.0, {"signer": signer.hex(),
                                                          "same_certificate": True},
                                   o.twin, signer))
        for name, run in _MESSAGE_CHECKS:
            r = run(o, c)
            if r is not None:
                found.append(Detection(name, tid, t, r[0], r[1], None, signer))
        if o.follows and o.heading is not None and o.length is not None:
            o.sybil = {}
            for p in pairs(o, c):
                for name, run in _PAIR_CHECKS:
                    r = run(o, p, c)
                    if r is not None:
                        found.append(Detection(name, tid, t, r[0], r[1], p.tid, signer))
            o.st.sybil = o.sybil

        if o.acc is None:
            self._senders.arrived(t)
        st.heard_t = t
        if o.anchor_i is not None and not (found and any(d.check in TRACK_CHECKS
                                                         for d in found)):
            reset = bool(found) and any(d.check in BASELINE_CHECKS for d in found)
            self._senders.accept(st, Msg(o.ts, t, o.sm, o.lat, o.lon, o.speed, o.heading,
                                         o.length, o.width), o.anchor_i, reset)
        if found:
            for d in found:
                self.counters[d.check] += 1
                if d.check == "sudden-appearance" and d.evidence["behind"] is not None \
                        and in_path(d, c):
                    self._unconfirmed[tid] = t + c.sa_confirm_s
                    self.counters["unconfirmed"] += 1
            entered, self.reports = self._quarantine.punish(key, t, found)
            if entered:
                self.counters["quarantines"] += 1
            if self.reports:
                self.counters["reported"] += len(self.reports)
        else:  # a clean message renews only a strong finding's quarantine
            self._quarantine.passed(key, t)
        return found

    def _drop(self, why: str) -> list[Detection]:
        self.dropped = why
        self.counters[why] += 1
        return []

    def _conflict(self, o: Observation, signer: bytes | None) -> list[Detection]:
        """The message's id is held by another signer: the finding, against its own
        signer (or, unsigned, its id), and the message dropped."""
        d = Detection(ID_CONFLICT, o.tid, o.t, 1.0, {
            "holder": _hex(o.conflict), "signer": None if signer is None else signer.hex()},
            None, signer)
        self.dropped = ID_CONFLICT
        self.counters[ID_CONFLICT] += 1
        entered, self.reports = self._quarantine.punish(o.key, o.t, [d])
        if entered:
            self.counters["quarantines"] += 1
        self.counters["reported"] += len(self.reports)
        return [d]

    def _read(self, bsm, t: float, host_lat: float | None, host_lon: float | None,
              host_heading: float | None, signer: bytes | None) -> Observation | None:
        """The message as the checks see it (None: no usable time, position or id):
        whom the evidence attaches to, or the signer holding its id when that is another
        (``conflict``: then nothing more); its fields, the host from it, and its timing
        (:meth:`_timing`).  Every number
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
        o = self._o
        o.tid = tid
        o.t = t
        o.key = tid if signer is None else signer
        sm = bsm.sec_mark
        sm = sm if type(sm) is int and 0 <= sm < 61_000 else _sec_mark(sm)
        ids = self._ids
        if signer is not None:
            o.conflict, new, o.twin = ids.claim(tid, signer, t, sm)
            if new:  # the id changed hands: its history is not the new holder's
                self._senders.forget(tid)
        else:
            o.conflict = ids.holder(tid, t) if ids else None
            o.twin = None
        if o.conflict is not None:
            return o
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
        kx, ky = scale(lat)
        st = senders.get(tid, t)
        o.bsm = bsm
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
