"""The comma2k19 RAV4 minute as a trip: the host and the vehicles its radar tracked, both
real measurements (no I/O; :mod:`hil.comma2k19` reads the files).

Time.  Every stream of a comma2k19 segment is stamped on the device's boot clock, and
comma's fused pose gives the GPS time of its frames, so the boot clock maps to UTC:
``UTC = boot + (GPS seconds - boot) - 18`` (GPS was 18 s ahead of UTC in 2018).  The
trip's time is that UTC minus :attr:`MobilityTable.meta` ``utc_base`` (the minute the
segment starts in), so the host's GNSS fixes and the RVs' BSMs share one clock, as on
the road.  The u-blox fixes were logged ``gnss_delay_s`` (0.20 s, measured here) after
their UTC stamps: the receiver's output latency, which ``obu run --gnss-delay`` takes.

The host (``rav4``) is comma's fused ``global_pose`` (INS/GNSS/vision), resampled to
10 Hz: position, speed (of the velocity), heading of the velocity; acceleration and yaw
rate derived (:mod:`catc.datasets.derive`).

The remote vehicles are the radar's tracks (bus 1, TRACK_A_0..15).  A track's address is
reused for a new object when the radar says so (``new``) or after a gap of more than
:data:`GAP_S`; each object seen for at least :data:`MIN_SECONDS` and moving (mean speed
over ground above :data:`MIN_SPEED`: stationary returns are guard rails and signs, not
vehicles) becomes an RV ``radar-21X@T`` (its track's address, and the trip time it
appears at), unless it is one seen longer on another track (the radar reports some
objects twice: within :data:`SAME_M` over their common time).  Its position is the
host's at the same instant plus the radar's range ahead and offset to the left, turned
by the host's heading: the range is from the radar at the front bumper, which is
:data:`RADAR_AHEAD_M` (1.52 m, openpilot's radar-to-camera distance) ahead of the pose's
point (the device at the windscreen), and the RV's reference point is its centre, half
an assumed length (:data:`RV_LENGTH_M`) beyond the rear the radar sees.  Its speed is
the host's plus the relative speed, its heading the host's (the radar gives no lateral
speed).  These radar states are the RVs' truth when the run is scored.

``meta`` has ``utc_base``, ``boot_to_trip_s`` (trip time minus the boot clock) and
``gnss_delay_s``, and also holds what the RVE replays on the host's vehicle side: ``vehicle_can``
(every frame of buses 0 and 1, lengths restored, ``t`` in trip time) and
``gnss_fixes`` (each real u-blox fix with the trip time it was logged at).
"""

from __future__ import annotations

import math

import numpy as np

from catc.datasets import derive
from catc.geo import EnuFrame
from catc.gnss import Fix
from catc.mobility import DT, MobilityTable, Track

__all__ = ["GAP_S", "GPS_UTC_LEAP_S", "MIN_SECONDS", "MIN_SPEED", "RADAR_AHEAD_M",
           "RV_LENGTH_M", "build", "gps_to_unix"]

#: GPS minus UTC in 2018 (s).
GPS_UTC_LEAP_S = 18
_GPS_EPOCH_UNIX = 315_964_800  # 1980-01-06T00:00:00Z
#: A radar object must be seen this long (s) to become an RV.
MIN_SECONDS = 2.0
#: ... and move faster than this over ground (m/s, mean).
MIN_SPEED = 3.0
#: A gap this long (s) on a track's address starts a new object.
GAP_S = 0.5
#: Two radar objects this close (m, median over their common time) are one vehicle.
SAME_M = 2.0
#: The radar (front bumper) ahead of the pose's point (m).
RADAR_AHEAD_M = 1.52
#: The RVs' assumed length and width (m): the radar measures neither.
RV_LENGTH_M, RV_WIDTH_M = 4.5, 1.8
HOST = "rav4"

_HOST_PROVENANCE = {
    "t": "measured: comma global_pose frame times (boot clock) mapped to UTC by its GPS times",
    "lat": "measured: comma global_pose (fused INS/GNSS/vision), ECEF to WGS-84",
    "lon": "measured: comma global_pose (fused INS/GNSS/vision), ECEF to WGS-84",
    "elev": "measured: comma global_pose, ellipsoidal height",
    "x": "derived: ENU east of lat/lon at the table origin",
    "y": "derived: ENU north of lat/lon at the table origin",
    "speed": "measured: comma global_pose velocity, horizontal norm",
    "heading": derive.HEADING_METHOD,
    "accel": derive.ACCEL_METHOD,
    "yaw_rate": derive.YAW_RATE_METHOD,
    "length": "RAV4 2017: 4.57 m", "width": "RAV4 2017: 1.85 m",
}
_RV_PROVENANCE = {
    "t": "measured: radar track times (boot clock) mapped to UTC",
    "x": "derived: host pose + heading-turned radar range (+1.52 m radar to pose point, "
         "+2.25 m half length) and left offset",
    "y": "derived: as x", "lat": "derived: from x, y", "lon": "derived: from x, y",
    "elev": "derived: the host's",
    "speed": "derived: host speed + radar relative speed",
    "heading": "assumed: the host's (the radar gives no lateral speed)",
    "accel": derive.ACCEL_METHOD, "yaw_rate": "assumed: the host's",
    "length": "assumed 4.5 m", "width": "assumed 1.8 m",
}


def gps_to_unix(week: float, tow: float) -> float:
    """UTC unix seconds of GPS week ``week``, time of week ``tow`` (2018's leap)."""
    return _GPS_EPOCH_UNIX + week * 604_800.0 + tow - GPS_UTC_LEAP_S


def build(name: str, pose: dict[str, np.ndarray], radar: dict[str, np.ndarray],
          fix_t: np.ndarray, fixes: list[Fix], can: np.ndarray | None,
          gps_week: float) -> MobilityTable:
    """The trip (see the module docstring) from :func:`hil.comma2k19.pose`,
    :func:`hil.comma2k19.radar`, :func:`hil.comma2k19.ublox_fixes` and
    :func:`hil.vehicle.comma2k19_can` (None: no CAN in ``meta``)."""
    offset = float(np.median(pose["gps_time"] - pose["t"]))  # GPS tow - boot
    utc0 = gps_to_unix(gps_week, float(pose["t"][0]) + offset)
    base = math.floor(utc0 / 60.0) * 60  # a whole minute: secMarks are the trip's
    shift = gps_to_unix(gps_week, offset) - base  # boot -> trip time

    def trip(t: np.ndarray) -> np.ndarray:
        return np.asarray(t, dtype=np.float64) + shift

    tp = trip(pose["t"])
    grid = np.arange(math.ceil(tp[0] / DT) * DT, tp[-1], DT)
    frame = EnuFrame(float(pose["lat"][0]), float(pose["lon"][0]), 0.0)
    pe, pn, _ = frame.to_enu(pose["lat"], pose["lon"], 0.0)
    hdg = np.unwrap(np.radians(pose["heading"]))
    host_e, host_n = np.interp(grid, tp, pe), np.interp(grid, tp, pn)
    host_h = np.interp(grid, tp, hdg)
    host_v = np.interp(grid, tp, pose["speed"])
    elev = np.interp(grid, tp, pose["h"])
    lat, lon, _ = frame.to_geodetic(host_e, host_n, 0.0)
    tracks = {HOST: derive.track(HOST, grid, (host_e, host_n, lat, lon, elev), host_v, None,
                                 dict(_HOST_PROVENANCE), (4.57, 1.85))}
    tracks.update(_radar_vehicles(radar, trip, grid, frame, (host_e, host_n, host_h,
                                                             host_v, elev), tracks[HOST]))
    sent_after = [float(lt) + shift - (f.t_unix - base) for lt, f in zip(fix_t, fixes,
                                                                         strict=True)]
    meta = {"utc_base": int(base), "boot_to_trip_s": shift,
            "gnss_delay_s": round(float(np.median(sent_after)), 3),
            "gnss_fixes": [(float(lt) + shift, f) for lt, f in zip(fix_t, fixes,
                                                                    strict=True)],
            "source": "comma2k19"}
    if can is not None:
        moved = can.copy()
        moved["t"] = moved["t"] + shift
        meta["vehicle_can"] = moved
    return MobilityTable(name=name, kind="comma2k19",
                         origin=(frame.lat0, frame.lon0, 0.0), tracks=tracks,
                         default_host=HOST, meta=meta)


def _objects(radar: dict[str, np.ndarray]) -> list[tuple[int, np.ndarray]]:
    """(address, row indices) of each radar object, in the order they appear."""
    out = []
    for addr in np.unique(radar["address"]):
        rows = np.flatnonzero(radar["address"] == addr)
        rows = rows[np.isfinite(radar["forward"][rows]) & np.isfinite(radar["left"][rows])]
        if not len(rows):
            continue
        cut = np.flatnonzero(radar["new"][rows][1:]
                             | (np.diff(radar["t"][rows]) > GAP_S)) + 1
        out += [(int(addr), piece) for piece in np.split(rows, cut) if len(piece)]
    out.sort(key=lambda o: (radar["t"][o[1][0]], o[0]))
    return out


def _radar_vehicles(radar: dict[str, np.ndarray], trip, grid: np.ndarray,
                    frame: EnuFrame, host: tuple[np.ndarray, ...],
                    host_track: Track) -> dict[str, Track]:
    host_e, host_n, host_h, host_v, elev = host
    out: dict[str, Track] = {}
    objects = _objects(radar)  # the longest first: a copy seen for less is dropped
    objects.sort(key=lambda o: -(radar["t"][o[1][-1]] - radar["t"][o[1][0]]))
    for addr, rows in objects:
        t = trip(radar["t"][rows])
        on = (grid >= t[0]) & (grid <= t[-1])
        if t[-1] - t[0] < MIN_SECONDS or on.sum() < MIN_SECONDS / DT:
            continue
        g = grid[on]
        fwd = np.interp(g, t, radar["forward"][rows]) + RADAR_AHEAD_M + RV_LENGTH_M / 2
        left = np.interp(g, t, radar["left"][rows])
        speed = host_v[on] + np.interp(g, t, radar["rel_speed"][rows])
        if float(np.mean(speed)) < MIN_SPEED:
            continue
        h = host_h[on]
        # heading clockwise from north: ahead is (sin h, cos h), left is (-cos h, sin h)
        e = host_e[on] + fwd * np.sin(h) - left * np.cos(h)
        n = host_n[on] + fwd * np.cos(h) + left * np.sin(h)
        if any(_same(g, e, n, other) for other in out.values()):
            continue  # the radar reports one object on two tracks at times
        lat, lon, _ = frame.to_geodetic(e, n, 0.0)
        vid = f"radar-{addr:x}@{g[0]:.1f}"
        out[vid] = Track(
            vehicle_id=vid, t=g, x=e, y=n, lat=np.asarray(lat), lon=np.asarray(lon),
            elev=elev[on], speed=np.maximum(speed, 0.0), heading=np.degrees(h) % 360.0,
            accel=derive.accel_from_speed(np.maximum(speed, 0.0)),
            yaw_rate=host_track.yaw_rate[on], length=RV_LENGTH_M, width=RV_WIDTH_M,
            provenance=dict(_RV_PROVENANCE))
    return dict(sorted(out.items(), key=lambda kv: (kv[1].t[0], kv[0])))


def _same(t: np.ndarray, e: np.ndarray, n: np.ndarray, other: Track) -> bool:
    """Whether a radar object is ``other`` again: half their common time or more, and
    within :data:`SAME_M` of it at the median."""
    common = np.isin(np.round(t / DT), np.round(other.t / DT))
    if common.sum() < 0.5 * len(t):
        return False
    theirs = np.isin(np.round(other.t / DT), np.round(t / DT))
    d = np.hypot(e[common] - other.x[theirs], n[common] - other.y[theirs])
    return bool(np.median(d) < SAME_M)
