"""A synthetic host vehicle that follows a real leader: the Intelligent Driver Model.

The paper's 100-Car runs have only a real leader (RV); the HV is made by a car-following
model.  Here it is the IDM of Treiber, Hennecke & Helbing, "Congested traffic states in
empirical observations and microscopic simulations", Phys. Rev. E 62, 1805 (2000)
[THH2000], in the form of Treiber & Kesting, *Traffic Flow Dynamics* (Springer 2013),
Sec. 11.3 [TK2013]:

    dv/dt = a [1 - (v / v0)^δ - (s*(v, Δv) / s)^2],
    s*(v, Δv) = s0 + max(0, v T + v Δv / (2 sqrt(a b))),

with s the bumper-to-bumper gap to the leader and Δv = v - v_leader the approach rate
(the max(0, .) of [TK2013] keeps s* >= s0 when the leader pulls away).  At a constant
leader speed v the follower settles at the equilibrium gap
s_e(v) = (s0 + v T) / sqrt(1 - (v / v0)^δ).

Parameters (:class:`IdmParams`), defaults from [THH2000] (its car parameters):
T = 1.6 s, a = 0.73 m/s², b = 1.67 m/s², s0 = 2 m, δ = 4 and a vehicle length of 5 m.
Other common sets: the IDM's Wikipedia example keeps a, b, s0, δ and the length but uses
T = 1.5 s and v0 = 30 m/s; Treiber's IDM applet page gives T = 1.8 s, a = 1 m/s²,
b = 3 m/s² (pass them explicitly if wanted).  The desired speed v0 of
[THH2000] is 120 km/h; here ``v0=None`` means max(120 km/h, 1.2 x the leader's top
speed), so that the desired speed never binds while following: at the leader's top speed
(v / v0)^4 <= 0.48 and s_e <= 1.4 (s0 + v T).  (v0 equal to the leader's top speed would
make s_e infinite whenever the leader cruises at it.)

Geometry.  The follower drives along the leader's own path.  Its longitudinal position
is an arc length along the polyline of the leader's x/y samples, thinned so that
consecutive vertices are at least :data:`MIN_VERTEX_SPACING` (0.5 m) apart: GNSS jitter of
a standing leader (cm per sample; 0.6 m summed over 19 s stopped on the OpenACC handling
track) then adds no length.  The leader's own position on it is the arc length of its
last vertex plus its distance from that vertex.  Positions are vehicle centres (the BSM
reference point), so the gap is s = (arc_leader - arc_follower) - (l_leader +
l_follower) / 2.  The follower's x/y, lat/lon, elev and heading are interpolated
linearly along the path at its arc length (heading unwrapped; at a vertex they are the
leader's values when it was there).

Start.  Both start at the leader's first instant; the follower starts ``initial_gap_m``
(bumper to bumper; default the equilibrium gap s_e at the leader's initial speed) behind
the leader, at the leader's initial speed.  Behind the leader's first position the path
is extended straight back along the leader's initial heading; lat/lon there come from a
local ENU frame at the leader's first position (its axes and the table's differ by the
angle between their verticals, 0.009 deg per km between the two points: < 1 cm over a
50 m extension when the leader starts within 1 km of the table origin).  The follower
reaches the leader's own path after initial_gap_m + (l_leader + l_follower) / 2 metres.

Integration.  Ballistic update at the track's 10 Hz (Treiber & Kanagaraj, "Comparing
numerical integration schemes for time-continuous car-following models", Physica A 419,
183 (2015)): with a_i the IDM acceleration at t_i,
v_{i+1} = v_i + a_i DT and x_{i+1} = x_i + v_i DT + a_i DT² / 2; when v_i + a_i DT < 0
the vehicle stops inside the step, x_{i+1} = x_i - v_i² / (2 a_i) and v_{i+1} = 0, so the
speed is never negative.  ``accel`` is the acceleration applied over each step: the IDM's
a_i, or -v_i / DT in a step that ends stopped, and 0 while standing (where the IDM asks
for a negative one); at the last sample it is the IDM's a at that instant (clipped the
same way).  The yaw rate is derived from the heading (:mod:`catc.datasets.derive`).  A gap
below 1 cm (a collision, which the IDM does not define) is taken as 1 cm.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from catc.datasets import derive
from catc.geo import EnuFrame, wrap_deg_360
from catc.mobility import DT, MobilityTable, Track

__all__ = [
    "DEFAULT_LENGTH",
    "MIN_VERTEX_SPACING",
    "V0_DEFAULT",
    "IdmParams",
    "equilibrium_gap",
    "idm_acceleration",
    "idm_follower",
    "with_synthetic_host",
]

Array = npt.NDArray[np.float64]

#: [THH2000]'s desired speed, 120 km/h in m/s.
V0_DEFAULT = 120.0 / 3.6
#: ``v0=None`` is at least this many times the leader's top speed.
V0_MARGIN = 1.2
#: [THH2000]'s vehicle length (m), used when a length is unknown.
DEFAULT_LENGTH = 5.0
#: Leader samples closer than this (m) to the previous vertex add no vertex to the path.
MIN_VERTEX_SPACING = 0.5
#: The smallest gap (m) the IDM is evaluated at.
MIN_GAP = 0.01


@dataclass(frozen=True)
class IdmParams:
    """IDM parameters (SI units), defaults from [THH2000]; see the module doc."""

    v0: float | None = None  # desired speed, m/s; None: max(V0_DEFAULT, 1.2 x leader's max)
    T: float = 1.6  # desired time headway, s
    a: float = 0.73  # maximum acceleration, m/s²
    b: float = 1.67  # comfortable deceleration, m/s² (positive)
    s0: float = 2.0  # minimum gap at standstill, m
    delta: float = 4.0  # acceleration exponent δ
    length: float = DEFAULT_LENGTH  # the follower's length, m
    leader_length: float | None = None  # m; None: the leader track's, else DEFAULT_LENGTH

    def __post_init__(self) -> None:
        for name in ("T", "a", "b", "delta", "length"):
            if not getattr(self, name) > 0:
                raise ValueError(f"IdmParams.{name} must be > 0, got {getattr(self, name)}")
        if not self.s0 >= 0:
            raise ValueError(f"IdmParams.s0 must be >= 0, got {self.s0}")
        if self.v0 is not None and not self.v0 > 0:
            raise ValueError(f"IdmParams.v0 must be > 0 or None, got {self.v0}")
        if self.leader_length is not None and not self.leader_length > 0:
            raise ValueError(f"IdmParams.leader_length must be > 0, got {self.leader_length}")


def idm_acceleration(v: float, gap: float, dv: float, p: IdmParams, v0: float) -> float:
    """The IDM acceleration (m/s²) at speed v, gap s and approach rate Δv = v - v_leader."""
    s_star = p.s0 + max(0.0, v * p.T + v * dv / (2.0 * math.sqrt(p.a * p.b)))
    return p.a * (1.0 - (v / v0) ** p.delta - (s_star / max(gap, MIN_GAP)) ** 2)


def equilibrium_gap(v: float, p: IdmParams, v0: float) -> float:
    """s_e(v) = (s0 + v T) / sqrt(1 - (v / v0)^δ): the steady gap behind a leader at v (m)."""
    if v >= v0:
        raise ValueError(f"no IDM equilibrium at v = {v} >= v0 = {v0}")
    return (p.s0 + v * p.T) / math.sqrt(1.0 - (v / v0) ** p.delta)


@dataclass(frozen=True)
class _Path:
    """The leader's path: vertices by arc length, and the leader's arc position per sample."""

    arc: Array  # arc length of each vertex (m), increasing
    columns: dict[str, Array]  # x, y, lat, lon, elev, heading (unwrapped) at the vertices
    leader_arc: Array  # the leader's arc position at each of its samples

    @classmethod
    def of(cls, leader: Track, behind: float) -> _Path:
        """The thinned polyline of ``leader``, extended ``behind`` metres back from its start."""
        x, y = leader.x, leader.y
        vertices = [0]
        for i in range(1, len(x)):
            j = vertices[-1]
            if math.hypot(x[i] - x[j], y[i] - y[j]) >= MIN_VERTEX_SPACING:
                vertices.append(i)
        idx = np.array(vertices)
        arc = np.r_[0.0, np.cumsum(np.hypot(np.diff(x[idx]), np.diff(y[idx])))]
        is_vertex = np.zeros(len(x), dtype=bool)
        is_vertex[idx] = True
        last = np.maximum.accumulate(np.where(is_vertex, np.arange(len(x)), 0))
        arc_of = np.zeros(len(x))
        arc_of[idx] = arc
        leader_arc = arc_of[last] + np.hypot(x - x[last], y - y[last])

        h0 = float(leader.heading[0])
        east, north = math.sin(math.radians(h0)), math.cos(math.radians(h0))
        elev0 = float(leader.elev[0]) if math.isfinite(leader.elev[0]) else 0.0
        lat_b, lon_b, _ = EnuFrame(float(leader.lat[0]), float(leader.lon[0]), elev0).to_geodetic(
            -behind * east, -behind * north, 0.0)
        heading = np.unwrap(leader.heading[idx], period=360.0)
        columns = {
            "x": np.r_[x[0] - behind * east, x[idx]],
            "y": np.r_[y[0] - behind * north, y[idx]],
            "lat": np.r_[lat_b, leader.lat[idx]],
            "lon": np.r_[lon_b, leader.lon[idx]],
            "elev": np.r_[leader.elev[0], leader.elev[idx]],
            "heading": np.r_[heading[0], heading],
        }
        return cls(np.r_[-behind, arc], columns, leader_arc)

    def at(self, s: Array) -> dict[str, Array]:
        return {name: np.interp(s, self.arc, col) for name, col in self.columns.items()}


def _check(leader: Track) -> None:
    if len(leader) < derive.POLYORDER + 1:
        raise ValueError(f"leader {leader.vehicle_id} has {len(leader)} samples; need >= 3")
    if not np.allclose(np.diff(leader.t), DT, atol=1e-3):
        raise ValueError(f"leader {leader.vehicle_id} is not sampled every {DT} s")


def _follow(leader: Track, initial_gap_m: float | None, p: IdmParams,
            vehicle_id: str) -> tuple[Track, dict[str, Any]]:
    """The follower track and the effective v0, lengths and initial gap."""
    _check(leader)
    v_lead = np.maximum(np.asarray(leader.speed, dtype=np.float64), 0.0)
    v0 = p.v0 if p.v0 is not None else max(V0_DEFAULT, V0_MARGIN * float(v_lead.max()))
    l_lead = p.leader_length or (leader.length if math.isfinite(leader.length)
                                 else DEFAULT_LENGTH)
    half = (l_lead + p.length) / 2.0
    gap0 = equilibrium_gap(float(v_lead[0]), p, v0) if initial_gap_m is None \
        else float(initial_gap_m)
    if not gap0 > 0:
        raise ValueError(f"initial_gap_m must be > 0, got {gap0}")
    path = _Path.of(leader, gap0 + half + 1.0)

    n = len(leader)
    s, v, acc = np.empty(n), np.empty(n), np.empty(n)
    s[0], v[0] = -(gap0 + half), v_lead[0]
    for i in range(n):
        a_i = idm_acceleration(v[i], path.leader_arc[i] - s[i] - half, v[i] - v_lead[i], p, v0)
        stops = v[i] + a_i * DT < 0.0
        acc[i] = -v[i] / DT if stops else a_i
        if i == n - 1:
            break
        if stops:
            s[i + 1] = s[i] - v[i] ** 2 / (2.0 * a_i) if a_i < 0 else s[i]
            v[i + 1] = 0.0
        else:
            s[i + 1] = s[i] + v[i] * DT + 0.5 * a_i * DT**2
            v[i + 1] = v[i] + a_i * DT

    where = path.at(s)
    heading = np.asarray(wrap_deg_360(where["heading"]))
    cite = "IDM (Treiber, Hennecke & Helbing 2000)"
    provenance = {
        "t": f"the leader {leader.vehicle_id}'s instants",
        "speed": f"synthetic: {cite} following {leader.vehicle_id}, ballistic update at "
                 f"{DT:g} s (catc.hostsim)",
        "accel": f"synthetic: the {cite} acceleration applied over each step",
        "x": f"synthetic: {leader.vehicle_id}'s path (thinned polyline) at the follower's arc "
             "length; straight back along its initial heading before its start",
        "heading": f"synthetic: {leader.vehicle_id}'s heading along its path at the "
                   "follower's arc length",
        "yaw_rate": derive.YAW_RATE_METHOD,
        "length": "synthetic: IdmParams.length",
        "width": "unknown",
    }
    for name in ("y", "lat", "lon", "elev"):
        provenance[name] = provenance["x"]
    track = Track(
        vehicle_id=vehicle_id, t=np.array(leader.t, dtype=np.float64), x=where["x"],
        y=where["y"], lat=where["lat"], lon=where["lon"], elev=where["elev"], speed=v,
        heading=heading, accel=acc, yaw_rate=derive.yaw_rate_from_heading(heading),
        length=p.length, width=math.nan, provenance=provenance)
    effective = {"v0": v0, "leader_length": l_lead, "length": p.length,
                 "initial_gap_m": gap0}
    return track, effective


def idm_follower(leader: Track, *, initial_gap_m: float | None = None,
                 params: IdmParams = IdmParams(), vehicle_id: str = "host") -> Track:
    """A vehicle following ``leader`` along its path by the IDM (see the module doc).

    ``initial_gap_m`` is the bumper-to-bumper gap at the leader's first instant (None:
    the IDM equilibrium gap at the leader's initial speed, which needs that speed below
    v0).  The returned track has the
    leader's instants and the leader's frame (x/y in the same ENU frame).
    """
    return _follow(leader, initial_gap_m, params, vehicle_id)[0]


def with_synthetic_host(table: MobilityTable, leader_id: str, *,
                        initial_gap_m: float | None = None, params: IdmParams = IdmParams(),
                        vehicle_id: str = "host") -> MobilityTable:
    """``table`` plus an IDM host following ``leader_id``, which becomes ``default_host``.

    ``meta["synthetic_host"]`` records the leader, the parameters and the effective v0,
    lengths and initial gap.
    """
    if leader_id not in table.tracks:
        raise ValueError(f"table {table.name!r} has no vehicle {leader_id!r}; "
                         f"vehicles: {', '.join(table.tracks)}")
    if vehicle_id in table.tracks:
        raise ValueError(f"table {table.name!r} already has a vehicle {vehicle_id!r}")
    host, effective = _follow(table.tracks[leader_id], initial_gap_m, params, vehicle_id)
    meta = {**table.meta, "synthetic_host": {"leader": leader_id, "model": "IDM",
                                             "params": asdict(params), **effective}}
    return replace(table, tracks={**table.tracks, vehicle_id: host}, default_host=vehicle_id,
                   meta=meta)
