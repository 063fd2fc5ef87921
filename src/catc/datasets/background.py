"""Background traffic: a trip with N more vehicles on parallel roads (``dense:N:SPEC``).

An OBU in dense traffic (issue 30: a motorway interchange, 1,000 vehicles in radio range)
has to hear, decode, verify and track every one of them, while the few that matter for
its warnings are the ones on its own road.  :func:`with_background` adds ``n`` such
vehicles to a trip without touching its own: they drive on straight roads parallel to
the host's overall direction (from its first to its last position), each road
:data:`ROAD_GAP_M` or more to the side of the host's start (beyond the lanes of a
motorway: never in the host's lane nor the next), vehicles spread evenly over
±:data:`SPREAD_M` along it, at constant speed (the host's mean speed, a little more or
less per road), no acceleration, no turning.  Roads to the host's right run its way,
those to its left the other way.  Nothing is drawn at random: the same trip and ``n`` give
the same table.

Meant for straight roads (the ``highway-braking`` scenario): on a winding road a parallel
straight line can cross the host's path.  The host's own road and everything on it stay
as they were, so a run's ground truth (FCW events, attacks on the host's lane) is the same
with and without the background.
"""

from __future__ import annotations

import math

import numpy as np

from catc.geo import EnuFrame
from catc.mobility import MobilityTable, Track

__all__ = ["ROAD_GAP_M", "SPREAD_M", "with_background"]

#: The nearest background road is this far to the side of the host's start (m).
ROAD_GAP_M = 40.0
#: Roads are this far apart (m).
ROAD_SPACING_M = 4.0
#: Vehicles per road, at most (the rest go on more roads).
PER_ROAD = 50
#: Vehicles spread over ± this along their road (m), around the host's start.
SPREAD_M = 300.0


def with_background(table: MobilityTable, n: int, host: str | None = None) -> MobilityTable:
    """``table`` with ``n`` background vehicles ``bg0001``... added (module docstring);
    ``host`` (default: the table's ``default_host``) sets the roads' direction.
    ValueError when the trip has no such host, or it does not move."""
    if n < 0:
        raise ValueError(f"background vehicles: need n >= 0, got {n}")
    if n == 0:
        return table
    host = host or table.default_host
    if host not in table.tracks:
        raise ValueError(f"background traffic needs the host; {host!r} is not in the trip")
    h = table.tracks[host]
    dx, dy = float(h.x[-1] - h.x[0]), float(h.y[-1] - h.y[0])
    dist = math.hypot(dx, dy)
    if dist < 1.0:
        raise ValueError(f"background traffic: host {host!r} does not move")
    ux, uy = dx / dist, dy / dist  # the road direction; right of it is (uy, -ux)
    t = h.t
    elapsed = t - t[0]
    v_mean = dist / max(float(elapsed[-1]), 1e-9)
    frame = EnuFrame(*table.origin)
    roads = math.ceil(n / PER_ROAD)
    tracks = dict(table.tracks)
    k = 0
    for r in range(roads):
        side = 1.0 if r % 2 == 0 else -1.0  # right of the host (its way), then left
        offset = side * (ROAD_GAP_M + ROAD_SPACING_M * (r // 2))
        way = side  # right: the host's way; left: the other way
        speed = v_mean * (0.9 + 0.2 * ((r * 7) % 5) / 4.0)  # 0.9..1.1 of the host's
        count = min(PER_ROAD, n - k)
        along0 = np.linspace(-SPREAD_M, SPREAD_M, count, endpoint=False) \
            + (SPREAD_M / count) * (r % 2)
        heading = math.degrees(math.atan2(way * ux, way * uy)) % 360.0
        for s0 in along0.tolist():
            k += 1
            s = s0 + way * speed * elapsed
            x = float(h.x[0]) + ux * s + uy * offset
            y = float(h.y[0]) + uy * s - ux * offset
            lat, lon, elev = frame.to_geodetic(x, y, np.zeros_like(x))
            vid = f"bg{k:04d}"
            tracks[vid] = Track(
                vid, t.copy(), x, y, np.asarray(lat), np.asarray(lon), np.asarray(elev),
                np.full_like(t, speed), np.full_like(t, heading), np.zeros_like(t),
                np.zeros_like(t), 4.5, 1.8,
                {"x": "background", "y": "background", "speed": "background"})
    meta = {**table.meta, "background": {"vehicles": n, "roads": roads,
                                         "nearest_road_m": ROAD_GAP_M}}
    return MobilityTable(table.name, table.kind, table.origin, tracks, table.default_host,
                         meta)
