"""Every parameter of the Context-Aware Map (:class:`CamConfig`), each default with its source.

Reference paper, section "Context-Aware Target Classification (CA-TC)"; the admission
rules these parameters bound are described in :mod:`catc.cam` (step 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from catc.classify import ClassifyConfig
from catc.predict import make_predictor


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
    #: ... but while the least recently heard was heard within this (s: one lost message
    #: at 10 Hz), the newcomer is dropped instead (``tentative_full``): with more real
    #: newcomers than ``max_tentative`` (1,016 vehicles heard at once), evicting would
    #: go round and none would ever be confirmed (issue 30, ``dense:`` runs).
    tentative_grace_s: float = 0.25
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
    #: With ``predictor="hgp"`` (a configuration :func:`catc.predict.hgp.table.supported`
    #: takes): every RV's predictor a row of one :class:`~catc.predict.hgp.table.HgpTable`
    #: and its concise path history a row of one :class:`catc.cam._histories.PathHistories`,
    #: the same answers bit for bit at a fraction of the cost per tick; False: one
    #: :class:`~catc.predict.hgp.HgpPredictor` and one
    #: :class:`~catc.pathhistory.ConcisePathHistory` object per RV (``bench/step.py`` times
    #: both).  Other predictors keep the objects (and start without numba).
    batched: bool = True

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
        if not self.tentative_grace_s >= 0.0:
            raise ValueError("CamConfig.tentative_grace_s must be >= 0")
        make_predictor(self.predictor)  # an unknown name fails here, not at the first RV
