"""The local map's tracks: admission of each BSM, the track record, and eviction.

Reference paper, section "Context-Aware Target Classification (CA-TC)": "a local map of
the latest record of every remote vehicle" and "a tracking module that ... filters
outliers".  :class:`TrackTable` holds every RV's track (its predictor, concise path
history and latest BSM) and applies the rules of :mod:`catc.cam`, steps 1-3: timing,
admission (``self``, ``shadow``, ``jump``, ``inconsistent``, ... each counted),
confirmation of new tracks, the table-full policy and eviction of silent RVs.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from catc.bsm import BSM
from catc.cam._clock import message_time
from catc.cam._config import CamConfig
from catc.cam._snapshot import HostEstimate
from catc.geo import EnuFrame
from catc.pathhistory import ConcisePathHistory, from_bsm_path_history
from catc.predict.base import Observation, Predictor

#: J2735 eventHardBraking is bit 7 of VehicleEventFlags (named bit 0 = the MSB).
EVENT_HARD_BRAKING = 7
#: AntiLockBrakeStatus "engaged" (catc.bsm.ControlStatus.ENGAGED).
_ABS_ENGAGED = 3
#: Counter names, in the order reports list them.
COUNTERS = (
    "received", "accepted", "incomplete", "implausible", "late", "future", "duplicate",
    "out_of_order", "jump", "inconsistent", "self", "shadow", "reacquired", "table_full",
    "displaced", "evicted_stale", "tracks_created", "confirmed", "tentative_evicted",
    "tentative_full", "ph_crumbs_used", "ticks",
)

#: Positions kept per vehicle for the shadow check: 10 s at 10 Hz.
_RECENT = 100

#: A gap (s) between accepted BSMs beyond which the new BSM's Part II path history is
#: used to fill the RV's history (more than one 100 ms period: a message was lost).
_PH_GAP_S = 0.15


def hard_braking(bsm: BSM, decel_threshold: float) -> bool:
    """The BSM says it brakes hard: eventHardBraking set, ABS engaged, or a longitudinal
    deceleration of at least ``decel_threshold`` (m/s², positive)."""
    if bsm.events is not None and bsm.events.size > EVENT_HARD_BRAKING \
            and bsm.events.bit(EVENT_HARD_BRAKING):
        return True
    if int(bsm.brakes.abs) == _ABS_ENGAGED:
        return True
    return bsm.accel_long is not None and bsm.accel_long <= -decel_threshold


#: Hard braking by deceleration: 0.4 g, SAE J2945/1's hard-braking event threshold.
HARD_BRAKING_DECEL = 0.4 * 9.80665


@dataclass(slots=True)
class Track:
    """One RV in the local map."""

    temp_id: int
    predictor: Predictor
    history: ConcisePathHistory
    bsm: BSM  # the latest accepted message
    t: float  # its generation time
    x: float
    y: float
    first_t: float
    accepted: int = 1
    #: The consecutive jump rejections, if they agree with each other:
    #: (t, x, y, speed, heading, n).
    alt: tuple[float, float, float, float, float, int] | None = None
    #: Accepted messages it needs before it is classified (1 once confirmed).
    need: int = 1
    #: (t, x, y) of its accepted messages of the last ``stale_after_s`` (the shadow
    #: check compares a bit-flipped copy with where the vehicle was at the copy's time).
    recent: deque = field(default_factory=lambda: deque(maxlen=_RECENT))
    fresh_at: float = math.nan  # the step time that last applied a message
    #: What snapshots report of ``bsm``: (accel, length, width, hard braking); set with it.
    bsm_values: tuple[float, float, float, bool] = (0.0, 0.0, 0.0, False)
    est_x: float = math.nan  # last estimate, for the table-full policy
    est_y: float = math.nan
    #: Its latest accepted message was verified (or verification was not deferred).
    verified: bool = True


class TrackTable:
    """Every RV's :class:`Track`, by TemporaryID, and the rules that admit a BSM to it.

    ``counters`` is the CAM's dict of :data:`COUNTERS`, which the rules count into;
    ``new_predictor`` makes the tracking predictor of a new track, ``new_history`` its
    concise path history (default a :class:`~catc.pathhistory.ConcisePathHistory`).  The
    HV's own ids and
    recent positions are kept too (:meth:`note_host_id`, :meth:`note_host_position`): a
    BSM of ours heard back, or a bit-flipped copy of it, is no remote vehicle.
    """

    def __init__(self, config: CamConfig, counters: dict[str, int],
                 new_predictor: Callable[[], Predictor],
                 new_history: Callable[[], ConcisePathHistory] | None = None) -> None:
        self.config = config
        self.counters = counters
        self._new_predictor = new_predictor
        self._new_history = new_history or (
            lambda: ConcisePathHistory(tolerance_m=config.ph_tolerance_m))
        self.tracks: dict[int, Track] = {}
        self.tentative: dict[int, None] = {}  # ids of tentative tracks, least recently heard first
        self.host_ids: dict[int, float] = {}  # the HV's temporary ids -> last seen
        self.host_recent: deque = deque(maxlen=_RECENT)  # the HV's (t, x, y)

    def __len__(self) -> int:
        """Confirmed tracks."""
        return len(self.tracks) - len(self.tentative)

    def confirmed(self) -> list[Track]:
        """The confirmed tracks, in the table's order."""
        return [tr for tr in self.tracks.values() if tr.need <= 1]

    # -- the HV ------------------------------------------------------------------------------
    def note_host_id(self, now: float, temp_id: int) -> None:
        """The HV sends as ``temp_id`` at ``now``; ids unused for ``stale_after_s`` go."""
        self.host_ids[temp_id] = now
        if len(self.host_ids) > 1:  # pseudonym changes: forget ids unused for long
            for tid in [k for k, v in self.host_ids.items()
                        if now - v > self.config.stale_after_s]:
                del self.host_ids[tid]

    def note_host_position(self, now: float, x: float, y: float) -> None:
        """The HV is at ``(x, y)`` at ``now`` (for the shadow check)."""
        self.host_recent.append((now, x, y))

    # -- admission ---------------------------------------------------------------------------
    def timed(self, now: float, messages: Sequence[BSM]) -> list[tuple[float, BSM]]:
        """Messages with what tracking needs, timed and sorted oldest first (steps 1 and 2:
        ``incomplete``, ``implausible``, ``late``, ``future``)."""
        c = self.config
        cnt = self.counters
        out: list[tuple[float, BSM]] = []
        for m in messages:
            cnt["received"] += 1
            if (m.lat is None or m.lon is None or m.sec_mark is None or m.speed is None
                    or m.heading is None or m.sec_mark >= 60_000):
                cnt["incomplete"] += 1
                continue
            if m.speed > c.max_speed:
                cnt["implausible"] += 1
                continue
            t = message_time(now, m.sec_mark)
            if now - t > c.stale_after_s:
                cnt["late"] += 1
                continue
            if t - now > c.max_future_s:
                cnt["future"] += 1
                continue
            out.append((t, m))
        if len(out) > 1:
            out.sort(key=lambda tm: (tm[0], tm[1].temp_id, tm[1].msg_cnt))
        return out

    def apply(self, now: float, t: float, m: BSM, x: float, y: float, host: HostEstimate,
              frame: EnuFrame, verified: bool = True) -> None:
        """Admit the BSM ``m`` generated at ``t`` at ENU ``(x, y)`` of ``frame`` to its track,
        or start one, or count why not (steps 2 and 3).  ``verified``: its signature was
        verified (False: deferred), kept as the track's :attr:`Track.verified`."""
        c = self.config
        cnt = self.counters
        tr = self.tracks.get(m.temp_id)
        if tr is None:
            if m.temp_id in self.host_ids:
                cnt["self"] += 1
                return
            if self._shadows(m.temp_id, t, x, y):
                cnt["shadow"] += 1
                return
            near = math.hypot(x - host.x, y - host.y) <= c.near_range_m
            need = c.confirm_near if near else c.confirm_after
            if need > 1 and self._tentative_full(t):
                cnt["tentative_full"] += 1
                return
            if not self._make_room(x, y, host):
                cnt["table_full"] += 1
                return
            self._new_track(now, t, m, x, y, frame, need, verified)
            return
        if t == tr.t:
            cnt["duplicate"] += 1
            return
        if t < tr.t:
            cnt["out_of_order"] += 1
            return
        if m.msg_cnt == tr.bsm.msg_cnt:
            # a corrupted copy of the last message (its time changed): a sender's msgCnt
            # moves on with every new message and repeats after 128 (12.8 s at 10 Hz,
            # longer than a track lives without messages)
            cnt["duplicate"] += 1
            return
        speed, heading = m.speed or 0.0, m.heading or 0.0
        why = self._inconsistency(tr.t, tr.x, tr.y, tr.bsm.speed or 0.0,
                                  tr.bsm.heading or 0.0, t, x, y, speed, heading)
        if why is not None:
            alt = tr.alt
            if alt is not None and t > alt[0] and self._inconsistency(
                    alt[0], alt[1], alt[2], alt[3], alt[4], t, x, y, speed, heading) is None:
                tr.alt = (t, x, y, speed, heading, alt[5] + 1)
            else:
                tr.alt = (t, x, y, speed, heading, 1)
            if tr.alt[5] < c.reacquire_after:
                cnt[why] += 1
                return
            cnt["reacquired"] += 1
            confirmed = tr.need <= 1
            self.forget(m.temp_id)
            self._new_track(now, t, m, x, y, frame, 1 if confirmed else c.confirm_after,
                            verified)
            return
        tr.alt = None
        if m.path_history is not None and t - tr.t > _PH_GAP_S:
            self._fill_history(tr.history, m, t, tr.t, frame)
        tr.bsm, tr.t, tr.x, tr.y = m, t, x, y
        tr.bsm_values = self._bsm_values(m)
        tr.verified = verified
        tr.accepted += 1
        tr.fresh_at = now
        tr.predictor.update(_observation(t, x, y, m))
        tr.history.add(t, x, y)
        tr.recent.append((t, x, y))
        cnt["accepted"] += 1
        if tr.need > 1:
            del self.tentative[m.temp_id]
            if tr.accepted >= tr.need:
                tr.need = 1
                cnt["confirmed"] += 1
            else:  # heard again: the most recent, evicted last
                self.tentative[m.temp_id] = None

    def _tentative_full(self, t: float) -> bool:
        """The tentative tracks are ``max_tentative`` and the least recently heard was
        heard within ``tentative_grace_s`` of ``t``: a newcomer at ``t`` must wait (module
        docstring of :mod:`catc.cam`, step 3)."""
        c = self.config
        if len(self.tentative) < c.max_tentative:
            return False
        oldest = self.tracks[next(iter(self.tentative))]
        return t - oldest.t < c.tentative_grace_s

    def _fill_history(self, hist: ConcisePathHistory, m: BSM, t: float, after: float,
                      frame: EnuFrame) -> None:
        """Add the BSM's own Part II path-history crumbs generated in ``(after, t)``:
        the sender's path through a gap of lost messages, or before we first heard it."""
        assert m.path_history is not None
        crumbs = from_bsm_path_history(m.path_history, frame, m.lat, m.lon, t)
        used = 0
        for tc, xc, yc in reversed(crumbs):
            if after < tc < t:
                hist.add(tc, xc, yc)
                used += 1
        self.counters["ph_crumbs_used"] += used

    def _inconsistency(self, t0: float, x0: float, y0: float, v0: float, h0: float,
                       t: float, x: float, y: float, v: float, h: float) -> str | None:
        """Why a message at (t, x, y, speed v, heading h) cannot follow one at (t0, x0,
        y0, v0, h0) of the same vehicle (``jump``: position, ``inconsistent``: speed or
        heading), or None when it can (module docstring, step 2)."""
        c = self.config
        dt = t - t0
        if math.hypot(x - x0, y - y0) > (max(v0, v) + c.max_accel * dt) * dt + \
                c.gnss_tolerance_m:
            return "jump"
        slack = 0.5 * c.max_accel * dt * dt + c.gnss_tolerance_m
        r = math.radians(h0)
        if math.hypot(x - x0 - v0 * dt * math.sin(r), y - y0 - v0 * dt * math.cos(r)) > slack:
            return "jump"  # not where the last speed and heading lead
        if abs(v - v0) > c.max_accel * dt + c.speed_tolerance:
            return "inconsistent"
        slow = min(v, v0)
        if slow >= 3.0:
            turn = abs((h - h0 + 180.0) % 360.0 - 180.0)
            if turn > math.degrees(c.max_accel / slow * dt) + c.heading_tolerance_deg:
                return "inconsistent"
        return None

    def _shadows(self, temp_id: int, t: float, x: float, y: float) -> bool:
        """``temp_id`` is one bit away from a tracked RV's id (or the HV's) and the message
        is within ``shadow_range_m`` of where that vehicle was at the message's time ``t``
        (its nearest recorded position within 0.2 s): a bit-flipped copy of its BSM, old
        or new."""
        r2 = self.config.shadow_range_m ** 2
        for bit in range(32):
            other = temp_id ^ (1 << bit)
            tr = self.tracks.get(other)
            recent = tr.recent if tr is not None else \
                self.host_recent if other in self.host_ids else None
            if not recent:
                continue
            for tp, xp, yp in reversed(recent):
                if tp <= t + 0.2:
                    if t - tp <= 0.2 and (xp - x) ** 2 + (yp - y) ** 2 <= r2:
                        return True
                    if tp < t - 0.2:
                        break
        return False

    def forget(self, temp_id: int) -> bool:
        """Remove the track of ``temp_id``; False when there was none."""
        self.tentative.pop(temp_id, None)
        tr = self.tracks.pop(temp_id, None)
        if tr is None:
            return False
        for part in (tr.predictor, tr.history):  # rows of tables (CamConfig.batched)
            release = getattr(part, "release", None)
            if release is not None:
                release()
        return True

    def _new_track(self, now: float, t: float, m: BSM, x: float, y: float, frame: EnuFrame,
                   need: int = 1, verified: bool = True) -> None:
        pred = self._new_predictor()
        pred.update(_observation(t, x, y, m))
        hist = self._new_history()
        if m.path_history is not None:
            self._fill_history(hist, m, t, -math.inf, frame)
        hist.add(t, x, y)
        self.tracks[m.temp_id] = Track(m.temp_id, pred, hist, m, t, x, y, t, fresh_at=now,
                                         est_x=x, est_y=y, bsm_values=self._bsm_values(m),
                                         need=need, verified=verified)
        self.tracks[m.temp_id].recent.append((t, x, y))
        self.counters["accepted"] += 1
        self.counters["tracks_created"] += 1
        if need > 1:
            if len(self.tentative) >= self.config.max_tentative:
                self.forget(next(iter(self.tentative)))
                self.counters["tentative_evicted"] += 1
            self.tentative[m.temp_id] = None

    def _bsm_values(self, m: BSM) -> tuple[float, float, float, bool]:
        """:attr:`Track.bsm_values` of a track whose latest BSM is ``m``."""
        c = self.config
        return (m.accel_long or 0.0, m.length or c.default_length_m,
                m.width or c.default_width_m, hard_braking(m, HARD_BRAKING_DECEL))

    def _make_room(self, x: float, y: float, host: HostEstimate) -> bool:
        """True when a new track fits (evicting the farthest RV if the newcomer is nearer)."""
        if len(self) < self.config.max_tracks:
            return True
        far_id, far_d2 = None, -1.0
        for tid, tr in self.tracks.items():
            if tr.need > 1:
                continue
            d2 = (tr.est_x - host.x) ** 2 + (tr.est_y - host.y) ** 2
            if d2 > far_d2 or (d2 == far_d2 and far_id is not None and tid > far_id):
                far_id, far_d2 = tid, d2
        if far_id is None or (x - host.x) ** 2 + (y - host.y) ** 2 >= far_d2:
            return False
        self.forget(far_id)
        self.counters["displaced"] += 1
        return True

    def evict_stale(self, now: float) -> None:
        """Evict the RVs silent for more than ``stale_after_s`` (``evicted_stale``)."""
        limit = self.config.stale_after_s
        stale = [tid for tid, tr in self.tracks.items() if now - tr.t > limit]
        for tid in stale:
            self.forget(tid)
        self.counters["evicted_stale"] += len(stale)


def _observation(t: float, x: float, y: float, m: BSM) -> Observation:
    return Observation(t, x, y, m.speed or 0.0, m.heading or 0.0, m.accel_long or 0.0,
                       m.yaw_rate)
