"""The comma2k19 RAV4 minute, read from its files: the host's real CAN, GNSS, IMU and
pose, and the vehicles its radar tracked.

A comma2k19 segment (``../shared/data/comma2k19-example``; comma.ai, MIT licence) holds
every stream as ``t.npy`` (seconds since the device booted) and ``value.npy``.  The boot
clock is the one clock all streams share, so it is the physical time here:

* :func:`ublox_fixes`: the u-blox fixes (10 Hz) with the boot time each was logged at
  and its UTC stamp (ms), as :class:`catc.gnss.Fix`;
* :func:`pose`: comma's fused INS/GNSS/vision ``global_pose`` (20 Hz, ECEF), the
  reference for the host's true path, as WGS-84 with speed and heading;
* :func:`gyro`: the IMU's yaw rate (deg/s clockwise: the z axis of its forward-right-down
  axes points down);
* :func:`wheel_speed`: comma's processed wheel speed (m/s);
* :func:`radar`: the stock radar's tracks (range ahead, left offset, relative speed).

The raw CAN frames are :func:`hil.vehicle.comma2k19_can`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from catc.geo import EnuFrame, ecef_to_geodetic
from catc.gnss import Fix
from hil.vehicle import ProfileError

__all__ = ["gyro", "pose", "radar", "segment_of", "ublox_fixes", "wheel_speed"]


def segment_of(path: Path | str) -> Path:
    """The segment folder at ``path``: the folder itself, or the one ``segment_*``
    folder inside it."""
    path = Path(path)
    if (path / "processed_log").is_dir():
        return path
    found = sorted(p for p in path.glob("*") if (p / "processed_log").is_dir()) \
        if path.is_dir() else []
    if len(found) != 1:
        raise ProfileError(f"{path}: not a comma2k19 segment (no processed_log folder"
                           f"{'' if not found else f'; {len(found)} segments in it'})")
    return found[0]


def _load(segment: Path, *parts: str) -> tuple[np.ndarray, np.ndarray]:
    base = segment.joinpath(*parts)
    try:
        return np.load(base / "t.npy"), np.load(base / "value.npy")
    except (FileNotFoundError, ValueError) as err:
        raise ProfileError(f"{segment}: cannot read {'/'.join(parts)}: {err}") from None


def ublox_fixes(segment: Path) -> tuple[np.ndarray, list[Fix]]:
    """The boot time each u-blox fix was logged at, and the fixes (UTC from their own
    millisecond stamps; no standard deviations: ``live_gnss_ublox`` has none)."""
    t, v = _load(segment, "processed_log", "GNSS", "live_gnss_ublox")
    fixes = [Fix(t_unix=float(r[3]) / 1000.0, lat=float(r[0]), lon=float(r[1]),
                 alt_m=float(r[4]), speed_mps=float(r[2]), course_deg=float(r[5]) % 360.0,
                 quality=1) for r in v]
    return np.asarray(t, dtype=np.float64), fixes


def pose(segment: Path) -> dict[str, np.ndarray]:
    """comma's fused pose: ``t`` (boot s), ``lat``, ``lon``, ``h`` (ellipsoidal m),
    ``speed`` (m/s), ``heading`` (deg clockwise from north, of the velocity), ``gps_time``
    (GPS seconds of the week)."""
    t = np.load(segment / "global_pose" / "frame_times.npy")
    ecef = np.load(segment / "global_pose" / "frame_positions.npy")
    vel = np.load(segment / "global_pose" / "frame_velocities.npy")
    gps = np.load(segment / "global_pose" / "frame_gps_times.npy")
    lat, lon, h = ecef_to_geodetic(ecef[:, 0], ecef[:, 1], ecef[:, 2])
    frame = EnuFrame(float(lat[0]), float(lon[0]), 0.0)
    ve, vn, _ = frame.rotation @ vel.T
    return {"t": np.asarray(t, dtype=np.float64), "lat": np.asarray(lat),
            "lon": np.asarray(lon), "h": np.asarray(h),
            "speed": np.hypot(ve, vn), "heading": np.degrees(np.arctan2(ve, vn)) % 360.0,
            "gps_time": np.asarray(gps[:, 1], dtype=np.float64)}


def gyro(segment: Path) -> tuple[np.ndarray, np.ndarray]:
    """The IMU's yaw rate: boot times and deg/s, positive clockwise (J2735's sign)."""
    t, v = _load(segment, "processed_log", "IMU", "gyro")
    return np.asarray(t, dtype=np.float64), np.degrees(v[:, 2])


def wheel_speed(segment: Path) -> tuple[np.ndarray, np.ndarray]:
    """comma's processed vehicle speed from CAN: boot times and m/s."""
    t, v = _load(segment, "processed_log", "CAN", "speed")
    return np.asarray(t, dtype=np.float64), np.asarray(v, dtype=np.float64).ravel()


def radar(segment: Path) -> dict[str, np.ndarray]:
    """The radar's tracks: ``t`` (boot s), ``forward`` (m ahead), ``left`` (m to the
    left), ``rel_speed`` (m/s, positive opening), ``address`` (the track's CAN id) and
    ``new`` (a new object on that track from this row)."""
    t, v = _load(segment, "processed_log", "CAN", "radar")
    return {"t": np.asarray(t, dtype=np.float64), "forward": v[:, 0], "left": v[:, 1],
            "rel_speed": v[:, 2], "address": v[:, 5].astype(np.int64),
            "new": v[:, 6] > 0}


def table(path: Path | str, with_can: bool = True):
    """The segment at ``path`` as a trip (:func:`catc.datasets.comma2k19.build`): the
    host from comma's pose, the RVs from its radar, and in ``meta`` the real CAN of
    buses 0 and 1 and the u-blox fixes for the RVE's vehicle side."""
    from catc.datasets.comma2k19 import build

    segment = segment_of(path)
    can = None
    if with_can:
        from hil.vehicle import comma2k19_can, rav4_lengths

        lengths = rav4_lengths()
        can = comma2k19_can(segment, {0: lengths[0], 1: lengths[1]})
    week = float(np.load(segment / "global_pose" / "frame_gps_times.npy")[0, 0])
    fix_t, fixes = ublox_fixes(segment)
    return build(segment.name, pose(segment), radar(segment), fix_t, fixes, can, week)
