"""The normalised mobility table: every dataset reader produces this.

One :class:`Track` per vehicle, sampled at 10 Hz without gaps, SI units, with both
WGS-84 and local ENU positions.  A :class:`MobilityTable` is one trip (a platoon run,
a leader/follower pair, a SUMO scenario) with its ENU origin.

Conventions as in :mod:`catc.bsm`: heading in degrees clockwise from north in
[0, 360), yaw rate in deg/s positive clockwise, longitudinal acceleration in m/s².
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: The sampling interval every track has (BSM period, the paper's 100 ms).
DT = 0.1


@dataclass(frozen=True, eq=False)
class Track:
    """One vehicle's trajectory.  All arrays have the same length and ``t`` steps by DT."""

    vehicle_id: str
    t: np.ndarray  # s, dataset time
    x: np.ndarray  # m east of the table's origin
    y: np.ndarray  # m north of the table's origin
    lat: np.ndarray  # deg WGS-84
    lon: np.ndarray  # deg WGS-84
    elev: np.ndarray  # m (ellipsoidal height of the ENU frame's convention)
    speed: np.ndarray  # m/s
    heading: np.ndarray  # deg cw from north, [0, 360)
    accel: np.ndarray  # m/s², longitudinal
    yaw_rate: np.ndarray  # deg/s, positive clockwise
    length: float = float("nan")  # m
    width: float = float("nan")  # m
    #: How each derived field was obtained ("measured", or the derivation used).
    provenance: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True, eq=False)
class MobilityTable:
    """One trip: tracks keyed by vehicle id, in the dataset's order (leader first)."""

    name: str
    kind: str  # "openacc", "ngsim", "sumo", ...
    origin: tuple[float, float, float]  # lat0, lon0, h0 of the ENU frame
    tracks: dict[str, Track]
    #: The vehicle a run uses as the host by default (None: the caller must choose).
    default_host: str | None = None
    #: Reader-specific extras (e.g. an event header, per-sample flags); empty by default.
    meta: dict = field(default_factory=dict)
