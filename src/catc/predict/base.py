"""The predictor interface: one remote vehicle's received history in, its state at any later
time out.

A predictor is fed the observations decoded from one RV's BSMs, in arrival order, with
the dataset time each was generated at.  When messages are lost the times are
irregular.  It answers the RV's ENU position, speed and heading at any time at or after
the last observation, with a position variance where the model has one.  Every
predictor registered in :mod:`catc.predict` implements this protocol.

Conventions (the same as :mod:`catc.bsm`): ENU metres (x east, y north) in the run's
local frame, speed in m/s, heading in degrees clockwise from north, longitudinal
acceleration in m/s², yaw rate in deg/s positive clockwise (J2735 YawRate).  Velocity
is therefore ``(speed·sin h, speed·cos h)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True, slots=True)
class Observation:
    """What one BSM tells a predictor about the RV, already in the run's ENU frame."""

    t: float
    x: float
    y: float
    speed: float
    heading: float
    accel: float = 0.0
    yaw_rate: float = 0.0


@dataclass(slots=True)
class Prediction:
    """The predicted state; ``var_x``/``var_y`` are NaN for models without uncertainty.

    ``source`` names what produced it (for example ``"gp"`` or ``"ca"`` when HGP's
    hybrid switch fell back), so that captures can show when each model was in use.

    Not frozen, unlike :class:`Observation`: every ``predict`` returns a new one, ~1,500
    a tick at 500 RVs, and a frozen dataclass's ``__init__`` (one ``object.__setattr__``
    per field) costs 1.8 µs against 0.4 µs here (~2 ms a tick).
    """

    x: float
    y: float
    speed: float
    heading: float
    var_x: float = math.nan
    var_y: float = math.nan
    source: str = ""


@runtime_checkable
class Predictor(Protocol):
    name: str

    def update(self, obs: Observation) -> None:
        """Add one received observation (times must not decrease; duplicates are ignored)."""

    def predict(self, t: float) -> Prediction:
        """The state at time ``t`` (normally ``t >= `` the last observation's time).

        Raises ``LookupError`` before the first observation.
        """

    def reset(self) -> None:
        """Forget all history."""


def heading_velocity(speed: float, heading_deg: float) -> tuple[float, float]:
    """ENU velocity (east, north) of a vehicle moving at ``speed`` on ``heading_deg``."""
    h = math.radians(heading_deg)
    return speed * math.sin(h), speed * math.cos(h)
