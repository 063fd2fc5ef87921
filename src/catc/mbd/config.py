"""Every threshold of the misbehavior checks, with its source.

The thresholds are F2MD's (IRT-SystemX/veins-f2md, commit 1d529e5,
``src/veins/modules/application/f2md/``: ``F2MDParameters.h``, written "P.h" below, and
``F2MDVeinsApp.cc`` for the vehicle limits).  Where one had to change for a 10 Hz BSM on a
real radio, its comment says why; the ones marked "ours" have no F2MD counterpart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = ["MbdConfig"]


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
    #: ... and in the host's path ahead: at most this far (m) across it (half a 3.6 m lane,
    #: the zone classifier's On Centre, plus 0.9 m of position error; the centre of a car
    #: in the next lane is some 3.6 m across, 4.2 m for the honest newcomers of the NGSIM
    #: scene, docs/log/2026-11-28-mbd-in-path.md).  Beside or behind the host a first
    #: message is where honest cars are first heard on real roads (merges, radio shadows,
    #: the edge of a dataset's view); there it is weak evidence.  Ours.
    sa_path_halfwidth_m: float = 2.7
    #: No sudden appearance while a vehicle in range could still be unheard: F2MD's
    #: P.h MAX_SA_TIME = 2.1 s (two of its 1 Hz beacons) is a blind warm-up, in which a
    #: ghost that starts at once is never one (issue 28).  Ours ends when the loss measured
    #: so far (:meth:`catc.mbd.state.Senders.unheard_s`: its rate and its burst length, on
    #: the senders' secMark gaps) leaves a vehicle in range unheard with probability below
    #: ``sa_unheard_p`` ...
    sa_unheard_p: float = 1e-4
    #: ... and never before this many nominal message intervals (0.5 s at 10 Hz: a first
    #: message delayed by jitter or reordering) ...
    sa_warmup_intervals: float = 5.0
    #: ... nor later than this many (a loss estimate an attacker inflates with gaps in its
    #: own secMarks cannot blind the check for longer: 3 s at 10 Hz).  Ours.
    sa_warmup_max_intervals: float = 30.0
    #: A new id that continues the path of an id last heard up to this long ago (s) is a
    #: pseudonym change, not an appearance (J2735 TemporaryIDs change with the pseudonym
    #: certificate, possibly after a silent period of a few seconds), plus the time the
    #: measured loss may hide its last and first messages (twice ``Senders.unheard_s``:
    #: at 1 Hz and 30 % loss a real split track of OpenACC is silent for 6 s).  Ours.
    sa_link_time_s: float = 5.0
    #: ... and last heard at least this long (s) before the new id's first message: half
    #: a 10 Hz interval (an id still sending alongside is a neighbour).  Ours.
    sa_link_min_gap_s: float = 0.05
    #: ... "continues": within ``sa_link_accel_mps2 dt² / 2 + max_mgt_rng_up_m`` of where
    #: the old id's last speed and heading would have taken it (0.3 g of unannounced
    #: acceleration or braking during the silence).  Ours.
    sa_link_accel_mps2: float = 3.0
    #: A sudden appearance inside the safety range behind another vehicle (in its radio
    #: shadow) is weak when that vehicle has been heard for at least this long (s), so
    #: that ids which appear together do not shield each other.  Ours.
    sa_shadow_heard_s: float = 1.0
    #: ... and when in the host's path ahead, no warning may be raised on it for this long
    #: (s; :meth:`catc.mbd.MisbehaviorDetector.muted`): a ghost placed behind a real
    #: leader that brakes at once (on the NGSIM scene, 8 m beyond a truck 12 m ahead)
    #: raised FCW and EEBL before it ran into the truck.  3 s: some 30 messages to fail a
    #: check in.  Ours.
    sa_confirm_s: float = 3.0
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
    #: (MAX_DELTA_INTER - dt) / MAX_DELTA_INTER, exceeds 0.5.  Ours differs for unequal
    #: footprints: the IoU as if both were the smaller one's size
    #: (:func:`catc.mbd.geometry.overlap`), since a car inside a truck has an IoU of 0.29
    #: (a ghost stopped in a truck's path, on the NGSIM scene, was never caught).
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
    #: Evidence attaches to the signer (the HashedId8 of the certificate that signed the
    #: message; the TemporaryID when unsigned).  It is quarantined when ``quarantine_k`` of
    #: its messages fail within ``quarantine_window_s`` (a message counts once, however
    #: many checks it fails: a single GNSS glitch is one), or at once on a strong finding
    #: (sudden appearance inside the safety range, intersection, Sybil, an id another
    #: signer holds).  The window is F2MD's AggregationApp's (``deltaTrustTime`` = 10 s,
    #: F2MDVeinsApp.h: the BSMs of the last 10 s are judged together); in the real data
    #: here no honest id fails more than one message in any 30 s
    #: (docs/log/2026-11-27-mbd-signers.md).
    quarantine_k: int = 3
    quarantine_window_s: float = 10.0
    #: How long (s) from the last detection a quarantine lasts; renewed by new detections.
    quarantine_s: float = 10.0
    #: A sender quarantined on a strong finding (a fabricated vehicle) stays quarantined
    #: while it keeps transmitting: each of its messages renews the quarantine.
    sticky_strong: bool = True
    # -- identity (ours) -------------------------------------------------------------------
    #: A TemporaryID belongs to the first signer heard with it until that signer has not
    #: used it for this long (s); another signer claiming it before is an id conflict.  A
    #: pseudonym certificate is used for minutes and the TemporaryID changes with it (SAE
    #: J2945/1), so an id silent for 5 min is not coming back.  Ours.
    id_hold_s: float = 300.0
    #: Messages remembered per sender to recognise an exact copy (msgCnt, secMark and
    #: position) of one already heard: 3.2 s at 10 Hz, past the 2 s generationTime window
    #: of the verifier; an older copy is older than the reorder window, dropped too.
    copies_kept: int = 32
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
        if not all(isinstance(x, int) for x in (self.quarantine_k, self.sybil_messages,
                                                 self.copies_kept)):
            raise ValueError("MbdConfig.quarantine_k, sybil_messages and copies_kept are "
                             "counts (int)")
        if not self.sa_unheard_p < 1.0:
            raise ValueError(f"MbdConfig.sa_unheard_p must be below 1, got {self.sa_unheard_p}")

