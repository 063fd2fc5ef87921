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
   vehicle, heard every 0.1-0.2 s, outlives one-off ids; but while that one was heard
   within ``tentative_grace_s``, the newcomer is dropped instead, ``tentative_full``, so
   that more real newcomers than the table holds are confirmed in turns rather than
   evicting each other for ever), and they do not count against
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

The package: ``_map.py`` the map and its step (steps 4-7), ``_tracks.py`` the tracks
and their admission (steps 1-3), ``_snapshot.py`` what a step returns, ``_config.py``
:class:`CamConfig`, ``_clock.py`` time from secMark, ``_warm.py`` a daemon's warm-up.
"""

from catc.cam._clock import SecMarkClock, message_time
from catc.cam._config import CamConfig
from catc.cam._map import ContextAwareMap
from catc.cam._snapshot import HostEstimate, MapSnapshot, RvView, rows_of
from catc.cam._tracks import COUNTERS, EVENT_HARD_BRAKING, HARD_BRAKING_DECEL, hard_braking
from catc.cam._warm import warm_up

__all__ = [
    "COUNTERS",
    "EVENT_HARD_BRAKING",
    "HARD_BRAKING_DECEL",
    "CamConfig",
    "ContextAwareMap",
    "HostEstimate",
    "MapSnapshot",
    "RvView",
    "SecMarkClock",
    "hard_braking",
    "message_time",
    "rows_of",
    "warm_up",
]
