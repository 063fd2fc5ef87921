"""The Context-Aware Map (CAM) and its one entry point, :meth:`ContextAwareMap.step`.

Reference paper, section "Context-Aware Target Classification (CA-TC)": a local map of
the latest record of every remote vehicle (RV), the path history of the host vehicle (HV)
and of every RV, a tracking module that predicts RVs whose BSMs were lost and filters
outliers, the HV path prediction, lane estimation, and the target classification of
section "Target Classification" on the current *and* the predicted positions.  The
safety applications (:mod:`catc.apps`) run on the resulting :class:`MapSnapshot`.

``step(now, host, messages)`` is called once per HV tick (10 Hz) by the live OBU and by
the offline simulator alike.  It is pure: the result depends only on the arguments and on
the previous calls, never on a clock, so a replay gives the same snapshots bit for bit.

What one step does, in order:

1. **Timing.**  Each BSM's generation time is recovered from its ``secMark`` against
   ``now`` (:func:`message_time`: the age is ``secMark(now) - secMark`` modulo one minute,
   so the minute rollover is handled).  Messages are applied oldest first; ties by id
   and msgCnt, so the arrival order within a tick does not matter.
2. **Admission** (each rejection is counted under its reason in :attr:`counters`):
   ``incomplete`` (no position, time, speed or heading), ``implausible`` (speed above
   ``max_speed``), ``late`` (older than ``stale_after_s``), ``future`` (generated more
   than ``max_future_s`` after ``now``), ``duplicate`` (same time or msgCnt as the RV's
   last accepted message: a repeat, a replay or a corrupted copy of it), ``out_of_order``
   (older than the RV's last accepted message: a reordered or replayed one), ``jump``
   (the position moved farther than physics allows since the last accepted message:
   ``(max(v_last, v_new) + max_accel·dt)·dt + gnss_tolerance_m``, and no farther than
   ``½·max_accel·dt² + gnss_tolerance_m`` from where the last message's speed and heading lead),
   ``inconsistent`` (speed or heading changed more than physics allows:
   ``|Δv| > max_accel·dt + speed_tolerance``; above 3 m/s ``|Δh| > max_accel/v·dt +
   heading_tolerance_deg``).  When ``reacquire_after`` consecutive ``jump`` or
   ``inconsistent`` rejections are consistent with each other by the same rules, the track
   is restarted from them (``reacquired``): a track whose *old* data were the outlier must
   not be locked out for ever, while random garbage (not self-consistent) never takes a
   track over.  Before any of these, for ids without a track: ``self`` (the HV's own
   temporary id, now or within ``stale_after_s``: our own BSM heard back, or a corrupted
   copy of it, is never a remote vehicle) and ``shadow`` (an id one bit away from a
   tracked RV's or the HV's, within ``shadow_range_m`` of it: a bit-flipped copy, not a
   new vehicle).
3. **Local map**: an accepted message updates its RV's record and predictor and its path
   history.  When it carries Part II pathHistory and follows a gap (a lost message) or
   starts a track, its crumbs from within the gap go into the RV's history first: the
   sender's own record of where it drove while we did not hear it.  A new RV gets a
   track; the table holds at most ``max_tracks``.  When it is full, the RV farthest from
   the HV is evicted if the newcomer is nearer (``displaced``), else the newcomer is
   dropped (``table_full``): nearby vehicles are the ones the safety applications need.
   RVs silent for more than ``stale_after_s`` are evicted (``evicted_stale``).
   **Confirmation** (issue 18): a new track is *tentative* (tracked, but not classified,
   not in the snapshot, no warning) until ``confirm_after`` of its messages have been
   accepted, each consistent with the one before by the rules above, or
   ``confirm_near`` when it first appeared within ``near_range_m`` of the HV (a sudden
   appearance); ``confirmed`` counts them.  At most ``max_tentative`` tentative tracks
   are kept (the one heard from least recently goes: ``tentative_evicted``; a real
   vehicle, heard every 0.1-0.2 s, outlives one-off ids), and they do not count against
   ``max_tracks``: garbage that happens to decode can neither raise a warning nor fill
   the table.
4. **HV**: its own predictor (``host_predictor``, CTRV as in SAE J2945/1) and path
   history are updated with ``host`` (no loss on the HV channel).  The HV path ahead is
   the arc of radius ``R = v / yaw rate`` (:func:`catc.classify.hv_radius_m`), behind it
   the concise path history.
5. **Tracking**: every RV is estimated at ``now`` with its predictor (an RV with a fresh
   BSM gets that BSM's state, moved forward by any latency) and at ``now + horizon_s``
   (the predicted position).
6. **Classification** of the current positions against the HV path now, and of the
   predicted positions against the HV's own predicted pose and path at ``now +
   horizon_s``.  **Lane estimation**: for an RV ahead (within ``trail_range_m``, not
   Oncoming) whose trail (its estimated position, then its concise path history)
   reaches back past the HV, the longitudinal and lateral offsets are measured along
   that trail instead (:func:`catc.classify.trail_offset`: the HV's offset from the RV's
   trail, negated), and the lane heading of Eq. (tc_heading) is the trail's direction
   where the HV is: where the RV drove is where the lane goes, which a constant-radius
   arc does not know on a curve that changes.  On the real OpenACC
   platoons this agrees with the HV's own later path far more often (see
   tests/test_cam_data.py).  Lane offsets are ``round(d / w_lane)``.
7. The applications, when given, turn the snapshot into per-tick warnings and events.

Units and frames as in :mod:`catc.bsm` and :mod:`catc.classify`: ENU metres in the run's
frame (``origin``, or the HV's first position), headings in degrees clockwise from north,
lateral offsets positive to the right.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from itertools import chain

import numpy as np
import numpy.typing as npt

from catc.bsm import BSM, MINUTE_MS
from catc.bsm import sec_mark as bsm_sec_mark
from catc.classify import (
    DIRECTION_CODES,
    LATERAL_CODES,
    ClassifyConfig,
    HostPath,
    ZoneArrays,
    classify_direction,
    classify_lateral,
    classify_paths,
    hv_radius_m,
    trail_offset,
)
from catc.geo import EnuFrame
from catc.pathhistory import ConcisePathHistory, from_bsm_path_history
from catc.predict import make_predictor, predict_columns, prepare
from catc.predict.base import Observation, Predictor

__all__ = [
    "CamConfig",
    "ContextAwareMap",
    "HostEstimate",
    "MapSnapshot",
    "RvView",
    "SecMarkClock",
    "message_time",
]

Array = npt.NDArray[np.float64]

#: J2735 eventHardBraking is bit 7 of VehicleEventFlags (named bit 0 = the MSB).
EVENT_HARD_BRAKING = 7
#: AntiLockBrakeStatus "engaged" (catc.bsm.ControlStatus.ENGAGED).
_ABS_ENGAGED = 3
#: Counter names, in the order reports list them.
COUNTERS = (
    "received", "accepted", "incomplete", "implausible", "late", "future", "duplicate",
    "out_of_order", "jump", "inconsistent", "self", "shadow", "reacquired", "table_full",
    "displaced", "evicted_stale", "tracks_created", "confirmed", "tentative_evicted",
    "ph_crumbs_used", "ticks",
)

#: Positions kept per vehicle for the shadow check: 10 s at 10 Hz.
_RECENT = 100

#: A gap (s) between accepted BSMs beyond which the new BSM's Part II path history is
#: used to fill the RV's history (more than one 100 ms period: a message was lost).
_PH_GAP_S = 0.15


@dataclass(frozen=True)
class CamConfig:
    """Every parameter of the CAM; each default says where it comes from."""

    #: The tracking predictor of the RVs (:func:`catc.predict.make_predictor`).
    predictor: str = "hgp"
    #: The HV's own predictor, for its predicted pose at ``horizon_s``.  The HV knows its
    #: state at every tick (no loss), and SAE J2945/1 predicts the HV's path as a constant
    #: radius from its own speed and yaw rate: CTRV.  Kept apart from ``predictor`` so that
    #: comparing RV predictors (``captures sweep``) does not change the HV's path.
    host_predictor: str = "ctrv"
    #: How far ahead (s) the predicted position is classified.  The paper's example
    #: (an RV now Behind, predicted Behind-Right) needs a horizon of the order of a lane
    #: change; 2.0 s is ours, within the 3 s the HGP's training window covers.
    horizon_s: float = 2.0
    #: An RV silent this long (s) is evicted; older messages are ``late``.  10 s is the
    #: HGP forecast horizon (HgpConfig.horizon_s): the paper sweeps to PER 95 % and 1 Hz,
    #: where gaps of several seconds are normal and must be predicted, not forgotten.
    stale_after_s: float = 10.0
    #: Generation times up to this far (s) after ``now`` are accepted (clock offsets
    #: between the HV and RV GNSS time bases); later ones are ``future``.
    max_future_s: float = 0.5
    #: Most RVs tracked at once.  A DSRC channel carries at most ~1,600 BSM/s (issue 6);
    #: 1,000 RVs at 10 Hz is already far beyond it.
    max_tracks: int = 1000
    #: Highest plausible speed (m/s), 252 km/h.
    max_speed: float = 70.0
    #: Largest plausible |acceleration| (m/s²) between messages: ~1.2 g, beyond any
    #: road vehicle's braking.
    max_accel: float = 12.0
    #: Position noise allowed on top of the physics bound (m): a few GNSS sigmas.
    gnss_tolerance_m: float = 3.0
    #: Consecutive ``jump`` rejections after which the track restarts from the new data.
    reacquire_after: int = 3
    #: Speed change (m/s) allowed between messages on top of ``max_accel·dt``: a few
    #: J2735 speed units of GNSS speed noise.
    speed_tolerance: float = 1.0
    #: Heading change (deg) allowed on top of ``max_accel/v·dt`` (the lateral
    #: acceleration bound), checked above 3 m/s where GNSS heading is meaningful.
    heading_tolerance_deg: float = 15.0
    #: Accepted messages a new track needs before it is classified (M of M consecutive
    #: consistent ones; module docstring, step 3).  3 at 10 Hz: 0.2 s.
    confirm_after: int = 3
    #: The same for a track first seen within ``near_range_m`` of the HV (sudden
    #: appearance: F2MD's and J3287's check): 4 at 10 Hz, 0.3 s.
    confirm_near: int = 4
    near_range_m: float = 50.0
    #: Tentative tracks kept at once: as many as the table, so that a full table of
    #: vehicles appearing at once (a bench start, a 1,000-RV scene) can all be confirmed;
    #: a tentative track is evicted when it is the least recently heard of them, so a
    #: flood of one-off ids delays no real vehicle that sends 10 times a second unless it
    #: brings over ``max_tentative`` new ids between two of its messages.
    max_tentative: int = 1000
    #: An unknown id one bit away from a tracked RV's or the HV's id and within this
    #: distance (m) of it is a bit-flipped copy (``shadow``).
    shadow_range_m: float = 10.0
    #: Allowable error (m) of the CAM's concise path histories.  SAE J2945/1's 1 m is
    #: for what a vehicle transmits; for lane estimation a 1 m chord error is over half
    #: the ±1.8 m lane band.  Measured on the OpenACC platoons (bench/lanes.py
    #: --ph-tolerance, agreement with the lane the HV then drives): 1.0 m is 1-7 points
    #: below 0.3 m on every file; 0.1 m is no better than 0.3 m.
    ph_tolerance_m: float = 0.3
    #: Thresholds of the zone equations.
    classify: ClassifyConfig = field(default_factory=ClassifyConfig)
    #: Lane estimation from the trails of RVs ahead (module docstring, step 6): on
    #: (default) or off (HV path only).
    trail_lanes: bool = True
    #: Farthest RV ahead (m) whose trail is used; 300 m is the J2945/1 path-history span.
    trail_range_m: float = 300.0
    #: ENU origin (lat, lon, h); None = the HV's first position.
    origin: tuple[float, float, float] | None = None
    #: Vehicle length (m) when a BSM does not say: a typical passenger car (J2735 size is
    #: optional in practice only for Part I size "unavailable").
    default_length_m: float = 4.8
    #: Vehicle width (m) when a BSM does not say.
    default_width_m: float = 1.9

    def __post_init__(self) -> None:
        positive = ("horizon_s", "stale_after_s", "max_speed", "max_accel",
                    "ph_tolerance_m", "default_length_m", "default_width_m")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"CamConfig.{name} must be positive and finite, got {value}")
        for name in ("max_future_s", "gnss_tolerance_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"CamConfig.{name} must be >= 0 and finite, got {value}")
        if self.stale_after_s > 30.0:
            raise ValueError("CamConfig.stale_after_s must be <= 30 s (secMark spans a minute)")
        if self.max_tracks < 1 or self.reacquire_after < 1:
            raise ValueError("CamConfig.max_tracks and reacquire_after must be >= 1")
        if self.confirm_after < 1 or self.confirm_near < 1 or self.max_tentative < 1:
            raise ValueError("CamConfig.confirm_after, confirm_near and max_tentative must "
                             "be >= 1")
        make_predictor(self.predictor)  # an unknown name fails here, not at the first RV


def message_time(now: float, sec_mark: int) -> float:
    """Generation time of a BSM with ``sec_mark`` (ms within the minute) seen at ``now``.

    The age is ``(secMark(now) - sec_mark) mod 60000`` ms, so a message from second 59.9
    read at second 0.1 of the next minute is 0.2 s old.  secMark cannot tell an age of
    40 s from one of -20 s: ages over 30 s are read as from the future (a clock offset),
    and the result is then after ``now``.  Either reading is rejected by the CAM (late or
    future), since ``stale_after_s`` is at most 30 s.
    """
    age_ms = (bsm_sec_mark(now) - sec_mark) % MINUTE_MS
    if age_ms > MINUTE_MS // 2:
        age_ms -= MINUTE_MS
    return now - age_ms / 1000.0


class SecMarkClock:
    """The HV's time in seconds from its BSMs' secMarks, across minute rollovers.

    The OBU knows no date: its clock is the host vehicle's (DESIGN.md).  The first secMark
    sets the origin (``t = secMark / 1000`` there); a secMark more than 30 s below the
    previous one starts the next minute.  The live OBU and the offline simulator both
    take ``now`` from here, so they step the CAM at identical times; the clock differs
    from the dataset's own time by a whole number of minutes (:attr:`minutes`).
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self.minutes = 0

    def __call__(self, sec_mark: int) -> float:
        if self._last is not None and sec_mark < self._last - 30_000:
            self.minutes += 1
        self._last = sec_mark
        return (self.minutes * 60_000 + sec_mark) / 1000.0


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
class _Track:
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


@dataclass(frozen=True, slots=True)
class HostEstimate:
    """The HV at a tick: pose and motion in the run's ENU frame, and its path."""

    t: float
    x: float
    y: float
    lat: float
    lon: float
    speed: float
    heading: float
    accel: float
    yaw_rate: float
    length: float
    width: float
    radius_m: float  # signed radius of the predicted path (inf = straight)
    path: HostPath  # the path the current positions are classified against
    predicted_path: HostPath  # the HV's predicted pose at t + horizon


@dataclass(frozen=True, slots=True)
class RvView:
    """One RV of a :class:`MapSnapshot`, as plain values (for logs, tests and captures)."""

    temp_id: int
    x: float
    y: float
    speed: float
    heading: float
    accel: float
    var_x: float
    var_y: float
    source: str
    age: float
    fresh: bool
    lane: int
    zone: object  # catc.classify.Zone
    predicted_x: float
    predicted_y: float
    predicted_zone: object  # catc.classify.Zone
    hard_braking: bool
    length: float
    width: float


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """The CAM after one step: the HV, every tracked RV (column arrays, one row per RV in
    the map's order), classifications, warnings and counters.

    Columns: ``ids`` (TemporaryID), ``x, y`` (m), ``speed`` (m/s), ``heading`` (deg),
    ``accel`` (m/s², from the RV's last BSM), ``var_x, var_y`` (m², NaN for models
    without uncertainty), ``source`` (what produced the estimate: ``bsm``, ``gp``, ``ca``,
    ...), ``age`` (s since the last BSM was generated), ``fresh`` (a BSM was applied in
    this step), ``lane`` (lane offset, positive right), ``zone`` / ``predicted_zone``
    (:class:`catc.classify.ZoneArrays`), ``pred_x, pred_y, pred_heading, pred_speed`` (at
    ``t + horizon_s``), ``hard_braking``, ``length, width`` (m).
    """

    t: float
    horizon_s: float
    host: HostEstimate
    ids: npt.NDArray[np.int64]
    x: Array
    y: Array
    speed: Array
    heading: Array
    accel: Array
    var_x: Array
    var_y: Array
    source: tuple[str, ...]
    age: Array
    fresh: npt.NDArray[np.bool_]
    lane: npt.NDArray[np.int64]
    zone: ZoneArrays
    pred_x: Array
    pred_y: Array
    pred_heading: Array
    pred_speed: Array
    predicted_zone: ZoneArrays
    hard_braking: npt.NDArray[np.bool_]
    length: Array
    width: Array
    #: The RV's offsets were measured along its own trail (lane estimation).
    on_trail: npt.NDArray[np.bool_]
    counters: Mapping[str, int]
    #: Per-tick warning conditions: (app, rv_id) pairs whose condition holds now.
    warnings: tuple[tuple[str, int], ...] = ()
    #: Start/end events raised in this step (:class:`catc.apps.events.AppEvent`).
    events: tuple = ()

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, temp_id: int) -> int:
        """Row of RV ``temp_id`` (``KeyError`` when it is not tracked)."""
        hits = np.flatnonzero(self.ids == temp_id)
        if not len(hits):
            raise KeyError(temp_id)
        return int(hits[0])

    def rv(self, i: int) -> RvView:
        """Row ``i`` as an :class:`RvView`."""
        return RvView(int(self.ids[i]), float(self.x[i]), float(self.y[i]),
                      float(self.speed[i]), float(self.heading[i]), float(self.accel[i]),
                      float(self.var_x[i]), float(self.var_y[i]), self.source[i],
                      float(self.age[i]), bool(self.fresh[i]), int(self.lane[i]),
                      self.zone.zone(i), float(self.pred_x[i]), float(self.pred_y[i]),
                      self.predicted_zone.zone(i), bool(self.hard_braking[i]),
                      float(self.length[i]), float(self.width[i]))

    def __iter__(self) -> Iterator[RvView]:
        return (self.rv(i) for i in range(len(self)))


class ContextAwareMap:
    """The CA-TC state: local map, tracks, path histories, HV path; see the module doc.

    ``apps`` is an optional callable ``apps(snapshot) -> (warnings, events)`` (normally a
    :class:`catc.apps.SafetyApps`) run at the end of every step.
    """

    def __init__(self, config: CamConfig | None = None, apps=None,
                 predictor_kwargs: Mapping | None = None) -> None:
        self.config = config or CamConfig()
        self.apps = apps
        self._predictor_kwargs = dict(predictor_kwargs or {})
        self.frame: EnuFrame | None = (EnuFrame(*self.config.origin)
                                       if self.config.origin is not None else None)
        self._tracks: dict[int, _Track] = {}
        self._tentative: dict[int, None] = {}  # ids of tentative tracks, least recently heard first
        self._host_ids: dict[int, float] = {}  # the HV's temporary ids -> last seen
        self._host_recent: deque = deque(maxlen=_RECENT)  # the HV's (t, x, y)
        self._host_predictor = make_predictor(self.config.host_predictor)
        self._host_history = ConcisePathHistory(tolerance_m=self.config.ph_tolerance_m)
        self._host_t = -math.inf
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)

    # -- public ---------------------------------------------------------------------------
    def __len__(self) -> int:
        """Confirmed tracks (the RVs a snapshot has)."""
        return len(self._tracks) - len(self._tentative)

    @property
    def tentative(self) -> int:
        """Tracks not confirmed yet."""
        return len(self._tentative)

    def history(self, temp_id: int) -> list[tuple[float, float]]:
        """Concise path history of an RV, most recent first (ENU m)."""
        return self._tracks[temp_id].history.points()

    def host_history(self) -> list[tuple[float, float]]:
        """Concise path history of the HV, most recent first (ENU m)."""
        return self._host_history.points()

    def step(self, now: float, host: BSM, messages: Sequence[BSM] = ()) -> MapSnapshot:
        """Advance the map to ``now`` (s, the HV's dataset time) with the HV state ``host``
        and the RV messages received since the last step; see the module docstring."""
        if not math.isfinite(now) or now <= self._host_t:
            raise ValueError(f"step times must increase: {now} after {self._host_t}")
        if host.lat is None or host.lon is None:
            raise ValueError("the HV state has no position")
        self.counters["ticks"] += 1
        if self.frame is None:
            self.frame = EnuFrame(host.lat, host.lon, 0.0)
        self._host_ids[host.temp_id] = now
        if len(self._host_ids) > 1:  # pseudonym changes: forget ids unused for long
            for tid in [k for k, v in self._host_ids.items()
                        if now - v > self.config.stale_after_s]:
                del self._host_ids[tid]
        usable = self._admit_fields(now, messages)
        ex, ny = self.frame.en_lists([host.lat] + [m.lat for _, m in usable],
                                     [host.lon] + [m.lon for _, m in usable])
        host_est = self._update_host(now, host, ex[0], ny[0])
        self._host_recent.append((now, ex[0], ny[0]))
        for (t, m), x, y in zip(usable, ex[1:], ny[1:], strict=True):
            self._apply(now, t, m, x, y, host_est)
        self._evict_stale(now)
        snap = self._snapshot(now, host_est)
        if self.apps is not None:
            warnings, events = self.apps(snap)
            if warnings or events:  # else the copy would equal snap, built with () for both
                snap = _with_apps(snap, tuple(warnings), tuple(events))
        return snap

    # -- admission ------------------------------------------------------------------------
    def _admit_fields(self, now: float, messages: Sequence[BSM]) -> list[tuple[float, BSM]]:
        """Messages with what tracking needs, timed and sorted oldest first."""
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

    def _apply(self, now: float, t: float, m: BSM, x: float, y: float,
               host: HostEstimate) -> None:
        c = self.config
        cnt = self.counters
        tr = self._tracks.get(m.temp_id)
        if tr is None:
            if m.temp_id in self._host_ids:
                cnt["self"] += 1
                return
            if self._shadows(m.temp_id, t, x, y):
                cnt["shadow"] += 1
                return
            near = math.hypot(x - host.x, y - host.y) <= c.near_range_m
            if not self._make_room(x, y, host):
                cnt["table_full"] += 1
                return
            self._new_track(now, t, m, x, y, c.confirm_near if near else c.confirm_after)
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
            self._forget(m.temp_id)
            self._new_track(now, t, m, x, y, 1 if confirmed else c.confirm_after)
            return
        tr.alt = None
        if m.path_history is not None and t - tr.t > _PH_GAP_S:
            self._fill_history(tr.history, m, t, tr.t)
        tr.bsm, tr.t, tr.x, tr.y = m, t, x, y
        tr.bsm_values = self._bsm_values(m)
        tr.accepted += 1
        tr.fresh_at = now
        tr.predictor.update(_observation(t, x, y, m))
        tr.history.add(t, x, y)
        tr.recent.append((t, x, y))
        cnt["accepted"] += 1
        if tr.need > 1:
            del self._tentative[m.temp_id]
            if tr.accepted >= tr.need:
                tr.need = 1
                cnt["confirmed"] += 1
            else:  # heard again: the most recent, evicted last
                self._tentative[m.temp_id] = None

    def _fill_history(self, hist: ConcisePathHistory, m: BSM, t: float,
                      after: float) -> None:
        """Add the BSM's own Part II path-history crumbs generated in ``(after, t)``:
        the sender's path through a gap of lost messages, or before we first heard it."""
        assert self.frame is not None and m.path_history is not None
        crumbs = from_bsm_path_history(m.path_history, self.frame, m.lat, m.lon, t)
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
            tr = self._tracks.get(other)
            recent = tr.recent if tr is not None else \
                self._host_recent if other in self._host_ids else None
            if not recent:
                continue
            for tp, xp, yp in reversed(recent):
                if tp <= t + 0.2:
                    if t - tp <= 0.2 and (xp - x) ** 2 + (yp - y) ** 2 <= r2:
                        return True
                    if tp < t - 0.2:
                        break
        return False

    def _forget(self, temp_id: int) -> bool:
        self._tentative.pop(temp_id, None)
        return self._tracks.pop(temp_id, None) is not None

    def _new_track(self, now: float, t: float, m: BSM, x: float, y: float,
                   need: int = 1) -> None:
        pred = self._new_predictor()
        pred.update(_observation(t, x, y, m))
        hist = ConcisePathHistory(tolerance_m=self.config.ph_tolerance_m)
        if m.path_history is not None:
            self._fill_history(hist, m, t, -math.inf)
        hist.add(t, x, y)
        self._tracks[m.temp_id] = _Track(m.temp_id, pred, hist, m, t, x, y, t, fresh_at=now,
                                         est_x=x, est_y=y, bsm_values=self._bsm_values(m),
                                         need=need)
        self._tracks[m.temp_id].recent.append((t, x, y))
        self.counters["accepted"] += 1
        self.counters["tracks_created"] += 1
        if need > 1:
            if len(self._tentative) >= self.config.max_tentative:
                del self._tracks[next(iter(self._tentative))]
                del self._tentative[next(iter(self._tentative))]
                self.counters["tentative_evicted"] += 1
            self._tentative[m.temp_id] = None

    def _bsm_values(self, m: BSM) -> tuple[float, float, float, bool]:
        """:attr:`_Track.bsm_values` of a track whose latest BSM is ``m``."""
        c = self.config
        return (m.accel_long or 0.0, m.length or c.default_length_m,
                m.width or c.default_width_m, hard_braking(m, HARD_BRAKING_DECEL))

    def _make_room(self, x: float, y: float, host: HostEstimate) -> bool:
        """True when a new track fits (evicting the farthest RV if the newcomer is nearer)."""
        if len(self) < self.config.max_tracks:
            return True
        far_id, far_d2 = None, -1.0
        for tid, tr in self._tracks.items():
            if tr.need > 1:
                continue
            d2 = (tr.est_x - host.x) ** 2 + (tr.est_y - host.y) ** 2
            if d2 > far_d2 or (d2 == far_d2 and far_id is not None and tid > far_id):
                far_id, far_d2 = tid, d2
        if far_id is None or (x - host.x) ** 2 + (y - host.y) ** 2 >= far_d2:
            return False
        self._forget(far_id)
        self.counters["displaced"] += 1
        return True

    def drop(self, temp_id: int) -> bool:
        """Forget the RV ``temp_id`` now (a misbehaving sender put in quarantine): its track
        and trail go, so it is neither predicted nor warned about; counted ``dropped`` (a
        counter that appears on first use).  False when it was not tracked."""
        if not self._forget(temp_id):
            return False
        self.counters["dropped"] = self.counters.get("dropped", 0) + 1
        return True

    def _evict_stale(self, now: float) -> None:
        limit = self.config.stale_after_s
        stale = [tid for tid, tr in self._tracks.items() if now - tr.t > limit]
        for tid in stale:
            self._forget(tid)
        self.counters["evicted_stale"] += len(stale)

    # -- HV ---------------------------------------------------------------------------------
    def _update_host(self, now: float, host: BSM, x: float, y: float) -> HostEstimate:
        c = self.config
        self._host_t = now
        speed = host.speed or 0.0
        heading = host.heading if host.heading is not None else 0.0
        accel = host.accel_long or 0.0
        self._host_predictor.update(Observation(now, x, y, speed, heading, accel,
                                                host.yaw_rate))
        self._host_history.add(now, x, y)
        radius = hv_radius_m(speed, host.yaw_rate)
        history = self._host_history.point_tuple()
        path = HostPath(x, y, heading, radius, history)
        p = self._host_predictor.predict(now + c.horizon_s)
        predicted = HostPath(p.x, p.y, p.heading, radius, ((x, y), *history))
        return HostEstimate(now, x, y, host.lat, host.lon, speed, heading, accel,
                            host.yaw_rate, host.length or c.default_length_m,
                            host.width or c.default_width_m, radius, path, predicted)

    # -- tracking and classification ---------------------------------------------------------
    def _snapshot(self, now: float, host: HostEstimate) -> MapSnapshot:
        c = self.config
        tracks = [tr for tr in self._tracks.values() if tr.need <= 1]
        n = len(tracks)
        later = now + c.horizon_s
        predictors = [tr.predictor for tr in tracks]
        prepare(predictors, later)  # the HGP's forecasts, stacked
        # rows x, pred_x, y, pred_y, speed, pred_speed, heading, pred_heading, var_x, var_y
        values, source = predict_columns(predictors, now, later)
        (x, pred_x, y, pred_y, speed, pred_speed, heading, pred_heading, var_x,
         var_y) = values
        # The rest of the per-RV values, one row per RV; the rows become one flat array,
        # column after column (numpy converts a flat list fastest; filling arrays row by
        # row costs far more), then sliced into the columns.
        rows: list[tuple] = []
        flags: list[tuple[bool, bool]] = []  # (fresh, hard braking)
        for tr, ex, ey in zip(tracks, x.tolist(), y.tolist(), strict=True):
            accel, length, width, hard = tr.bsm_values
            rows.append((now - tr.t, accel, length, width))
            flags.append((tr.fresh_at == now, hard))
            tr.est_x, tr.est_y = ex, ey
        age, accel, length, width = _flat_columns(rows, np.float64).reshape(4, n)
        fresh_hard = _flat_columns(flags, np.bool_)
        fresh, hard = fresh_hard[:n], fresh_hard[n:]
        ids = np.array([tr.temp_id for tr in tracks], dtype=np.int64)
        # now and later, x, y and heading: the rows of both paths, each n long
        zone, predicted_zone = classify_paths(
            (host.path, host.predicted_path), (n, n), values[0:2].reshape(-1),
            values[2:4].reshape(-1), values[6:8].reshape(-1), c.classify)
        if c.trail_lanes and n:
            zone, on_trail = self._trail_lanes(tracks, zone, host)
        else:
            on_trail = np.zeros(n, dtype=bool)
        return _snapshot_of(
            t=now, horizon_s=c.horizon_s, host=host, ids=ids, x=x, y=y, speed=speed,
            heading=heading, accel=accel, var_x=var_x, var_y=var_y, source=tuple(source),
            age=age, fresh=fresh, lane=np.rint(zone.d / c.classify.w_lane).astype(np.int64),
            zone=zone, pred_x=pred_x, pred_y=pred_y, pred_heading=pred_heading,
            pred_speed=pred_speed, predicted_zone=predicted_zone, hard_braking=hard,
            length=length, width=width, on_trail=on_trail, counters=dict(self.counters),
            warnings=(), events=())

    def _trail_lanes(self, tracks: list[_Track], zone: ZoneArrays, host: HostEstimate
                     ) -> tuple[ZoneArrays, npt.NDArray[np.bool_]]:
        """Offsets and lane heading along the trails of RVs ahead (module docstring, 6).

        Candidates: Ahead within ``trail_range_m`` and not Oncoming.  When the HV lies on
        an RV's trail, ``s`` is the distance along it, ``d`` minus the HV's offset from
        it, and Eq. (tc_heading) compares the HV's heading with the trail's there.  The
        trail starts at the RV's current estimate (``est_x, est_y``, set by _snapshot).
        """
        c = self.config
        cand = (zone.ahead & (zone.direction != 1) & (zone.s <= c.trail_range_m)).nonzero()[0]
        used = np.zeros(len(tracks), dtype=bool)
        found = []
        for i in cand.tolist():
            tr = tracks[i]
            trail = ((float(tr.est_x), float(tr.est_y)), *tr.history.point_tuple())
            off = trail_offset(trail, (host.x, host.y))
            if off is not None:
                found.append((i, off))
        if not found:
            return zone, used
        s, d = zone.s.copy(), zone.d.copy()
        lane, diff = zone.lane_heading_deg.copy(), zone.heading_diff_deg.copy()
        lateral, direction = zone.lateral.copy(), zone.direction.copy()
        cc = c.classify
        for i, (si, di, lane_i) in found:
            s[i], d[i], lane[i] = si, -di, lane_i
            diff[i] = diff_i = abs((host.heading - lane_i + 180.0) % 360.0 - 180.0)
            used[i] = True
            # Eqs. (tc_lateral) and (tc_heading) on the new values: the scalar forms make
            # the same float comparisons as lateral_codes / direction_codes on the arrays.
            lateral[i] = LATERAL_CODES.index(classify_lateral(-di, cc.w_lane))
            direction[i] = DIRECTION_CODES.index(classify_direction(diff_i, cc))
        # ahead stays the HV-path classification.
        return ZoneArrays(zone.ahead, lateral, direction, s, d, lane, diff), used

    def _new_predictor(self) -> Predictor:
        return make_predictor(self.config.predictor, **self._predictor_kwargs)


def _observation(t: float, x: float, y: float, m: BSM) -> Observation:
    return Observation(t, x, y, m.speed or 0.0, m.heading or 0.0, m.accel_long or 0.0,
                       m.yaw_rate)


def _flat_columns(rows: list[tuple], dtype: type) -> np.ndarray:
    """The columns of ``rows`` one after the other, as one flat array."""
    return np.array(list(chain.from_iterable(zip(*rows, strict=True))), dtype=dtype)


def _snapshot_of(**values) -> MapSnapshot:
    """``MapSnapshot(**values)`` with every field given, without the frozen dataclass's
    ``__init__`` (one ``object.__setattr__`` per field, a measurable part of a tick with
    a few RVs): MapSnapshot has no ``__post_init__`` and no ``init=False`` field, so an
    instance whose ``__dict__`` holds the fields is the one ``__init__`` would build."""
    snap = object.__new__(MapSnapshot)
    snap.__dict__.update(values)
    return snap


def _with_apps(snap: MapSnapshot, warnings: tuple, events: tuple) -> MapSnapshot:
    """The snapshot with the applications' output (a copy: snapshots are immutable), as
    ``dataclasses.replace`` would make it (see :func:`_snapshot_of`)."""
    return _snapshot_of(**{**snap.__dict__, "warnings": warnings, "events": events})
