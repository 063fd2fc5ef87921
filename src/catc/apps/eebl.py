"""Emergency Electronic Brake Light (EEBL): an RV ahead, in the HV's lane or an adjacent
one, brakes hard.

Target classification (reference paper, Figure "Target Classifications areas used by the
safety applications"): EEBL takes RVs classified Ahead, Ongoing, and Left / On Centre /
Right, within ``range_m``.  Hard braking is what the RV's own BSM says
(:func:`catc.cam.hard_braking`): the eventHardBraking flag, ABS engaged, or a
longitudinal deceleration of at least 0.4 g (SAE J2945/1's hard-braking event threshold).
Unlike FCW, the RV need not be the nearest one: EEBL exists to warn of braking hidden
behind the vehicle in front.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from catc.apps.events import AppWarning

__all__ = ["EeblConfig", "eebl"]

_LEFT, _CENTRE, _RIGHT = 1, 2, 3  # catc.classify.LATERAL_CODES
_ONGOING = 0  # catc.classify.DIRECTION_CODES


@dataclass(frozen=True)
class EeblConfig:
    #: Farthest RV ahead (m) that warns: 300 m, the range DSRC V2V safety messages are
    #: designed for (SAE J2945/1 minimum performance), and several seconds of travel.
    range_m: float = 300.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.range_m) and self.range_m > 0.0):
            raise ValueError(f"EeblConfig.range_m must be positive, got {self.range_m}")


def eebl(snap, config: EeblConfig = EeblConfig()) -> list[AppWarning]:
    """EEBL warning conditions at this tick (one per RV that meets them)."""
    if not snap.hard_braking.any():  # the usual tick: nothing else to look at
        return []
    z = snap.zone
    mask = (z.ahead & (z.direction == _ONGOING) & (z.lateral >= _LEFT) & (z.lateral <= _RIGHT)
            & (z.s <= config.range_m) & snap.hard_braking)
    return [AppWarning("eebl", int(snap.ids[i]), float(z.s[i])) for i in np.flatnonzero(mask)]
