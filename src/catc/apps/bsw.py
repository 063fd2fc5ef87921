"""Blind Spot Warning (BSW) and Lane Change Warning (LCW).

Zone: an ongoing RV in the lane left or right of the HV (catc.classify: Left or Right)
whose extent along the HV path overlaps ``[-(L_HV/2 + zone_behind_m), 0]``, i.e. from
the HV's centre (about the driver's shoulder: what is ahead of it the driver sees
through the side window) back to ``zone_behind_m`` behind the HV's rear bumper.  3.0 m is
the rear extent of the blind-spot zone in ISO 17387 (lane change decision aid systems).

* **BSW**: an RV is in the zone now (current zone).
* **LCW**: an RV is not in the zone now but its predicted position at ``t + horizon``
  (the CAM's predicted zone, measured against the HV's own predicted pose) is: the
  paper's example of an RV "behind, but predicted behind right" that the CA-TC hands to
  LCW and BSW.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from catc.apps.events import AppWarning

__all__ = ["BswConfig", "blind_spot"]

_LEFT, _RIGHT = 1, 3  # catc.classify.LATERAL_CODES
_ONGOING = 0
#: ``_SIDE_ONGOING[lateral, direction]``: Left or Right, and Ongoing (one lookup per tick
#: instead of three comparisons and two logical operations).
_SIDE_ONGOING = np.zeros((5, 3), dtype=bool)
_SIDE_ONGOING[[_LEFT, _RIGHT], _ONGOING] = True


@dataclass(frozen=True)
class BswConfig:
    #: How far behind the HV's rear bumper the zone reaches (m), ISO 17387.
    zone_behind_m: float = 3.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.zone_behind_m) and self.zone_behind_m >= 0.0):
            raise ValueError(f"BswConfig.zone_behind_m must be >= 0, got {self.zone_behind_m}")


def _in_zone(zone, length, hv_length: float, config: BswConfig) -> np.ndarray:
    """Rows of the RVs in the zone, ascending."""
    side = _SIDE_ONGOING[zone.lateral, zone.direction]
    rows = side.nonzero()[0]
    if not len(rows):  # the usual tick: no ongoing RV in an adjacent lane
        return rows
    lo = -(0.5 * hv_length + config.zone_behind_m)
    front, rear = zone.s + 0.5 * length, zone.s - 0.5 * length
    return (side & (front > lo) & (rear < 0.0)).nonzero()[0]


def blind_spot(snap, config: BswConfig = BswConfig()) -> list[AppWarning]:
    """BSW and LCW conditions at this tick."""
    hv_len = snap.host.length
    now = _in_zone(snap.zone, snap.length, hv_len, config)
    soon = _in_zone(snap.predicted_zone, snap.length, hv_len, config)
    if len(soon) and len(now):
        soon = np.setdiff1d(soon, now, assume_unique=True)  # keeps soon's order
    out = []
    for app, rows, zone in (("bsw", now, snap.zone), ("lcw", soon, snap.predicted_zone)):
        for i in rows:
            side = "left" if zone.lateral[i] == _LEFT else "right"
            out.append(AppWarning(app, int(snap.ids[i]), float(zone.s[i]), side=side))
    return out
