"""J2735 Part II ``VehicleSafetyExtensions`` (partII-Id 0) in UPER, decoded in full.

``VehicleSafetyExtensions ::= SEQUENCE { events VehicleEventFlags OPTIONAL, pathHistory
PathHistory OPTIONAL, pathPrediction PathPrediction OPTIONAL, lights ExteriorLights
OPTIONAL, ... }``: events and lights are extensible BIT STRINGs, ``PathHistory`` carries
an optional ``initialPosition`` (``FullPositionVector``), ``currGNSSstatus`` and 1..23
``PathHistoryPoint``s.  See ``catc/j2735/bsm.asn``.
"""

from __future__ import annotations

from catc import units as u
from catc.bsm import (
    BSM,
    BitString,
    FullPositionVector,
    PathHistory,
    PathHistoryPoint,
    PathPrediction,
    PositionalAccuracy,
)
from catc.errors import DecodeError, EncodeError
from catc.j2735.bits import BitReader, BitWriter
from catc.j2735.uper._elements import (
    TRANSMISSION,
    accuracy_from_raw,
    accuracy_raw,
    read_ddatetime,
    scaled,
    skip_extensions,
    write_ddatetime,
)

#: Part II id of VehicleSafetyExtensions.
VEHICLE_SAFETY_EXT = 0


def _read_ext_bitstring(r: BitReader, root_size: int, what: str) -> BitString:
    """BIT STRING (SIZE(root_size, ...)) (X.691 §16.6 and §16.11)."""
    if r.read(1, what):
        size = r.length(what)
        return BitString(r.read(size, what), size)
    return BitString(r.read(root_size, what), root_size)


def _write_ext_bitstring(w: BitWriter, bits: BitString, root_size: int, what: str) -> None:
    if not 0 <= bits.value < (1 << bits.size):
        raise EncodeError(f"{what}: value does not fit in {bits.size} bits")
    if bits.size == root_size:
        w.write(0, 1)
    else:
        w.write(1, 1)
        w.length(bits.size, what)
    w.write(bits.value, bits.size)


def _read_accuracy(r: BitReader) -> PositionalAccuracy:
    return accuracy_from_raw(r.read(32, "PositionalAccuracy"))


def _read_fpv(r: BitReader) -> FullPositionVector:
    ext = r.read(1, "FullPositionVector")
    present = r.read(8, "FullPositionVector preamble")
    utc = read_ddatetime(r) if present & 0x80 else None
    lon = r.constrained(-1_799_999_999, 1_800_000_001, 32, "FullPositionVector.long")
    lat = r.constrained(-900_000_000, 900_000_001, 31, "FullPositionVector.lat")
    elev = u.ELEVATION.from_raw(r.read(16, "elevation") - 4096) if present & 0x40 else None
    heading = (u.HEADING.from_raw(r.constrained(0, 28800, 15, "FullPositionVector.heading"))
               if present & 0x20 else None)
    trans = speed = None
    if present & 0x10:
        trans = TRANSMISSION[r.read(3, "TransmissionAndSpeed")]
        speed = u.SPEED.from_raw(r.read(13, "TransmissionAndSpeed"))
    accuracy = _read_accuracy(r) if present & 0x08 else None
    time_conf = r.constrained(0, 39, 6, "timeConfidence") if present & 0x04 else None
    pos_conf = (r.read(4, "posConfidence"), r.read(4, "posConfidence")) if present & 0x02 else None
    speed_conf = ((r.read(3, "speedConfidence"), r.read(3, "speedConfidence"),
                   r.read(2, "speedConfidence")) if present & 0x01 else None)
    if ext:
        skip_extensions(r, "FullPositionVector")
    return FullPositionVector(
        lat=u.LATITUDE.from_raw(lat), lon=u.LONGITUDE.from_raw(lon), elevation=elev,
        heading=heading, transmission=trans, speed=speed, accuracy=accuracy, utc_time=utc,
        time_confidence=time_conf, pos_confidence=pos_conf, speed_confidence=speed_conf)


def _write_fpv(w: BitWriter, p: FullPositionVector) -> None:
    has_speed = p.speed is not None or p.transmission is not None
    flags = (p.utc_time, p.elevation, p.heading, has_speed or None, p.accuracy,
             p.time_confidence, p.pos_confidence, p.speed_confidence)
    w.write(0, 1)
    w.write(sum(1 << (7 - i) for i, f in enumerate(flags) if f is not None), 8)
    if p.utc_time is not None:
        write_ddatetime(w, p.utc_time)
    w.write(u.LONGITUDE.to_raw(p.lon) + 1_799_999_999, 32)
    w.write(u.LATITUDE.to_raw(p.lat) + 900_000_000, 31)
    if p.elevation is not None:
        w.write(u.ELEVATION.to_raw(p.elevation) + 4096, 16)
    if p.heading is not None:
        w.write(u.HEADING.to_raw(p.heading), 15)
    if has_speed:
        w.write(7 if p.transmission is None else int(p.transmission), 3)
        w.write(u.SPEED.to_raw(p.speed), 13)
    if p.accuracy is not None:
        w.write(accuracy_raw(p.accuracy), 32)
    if p.time_confidence is not None:
        w.constrained(p.time_confidence, 0, 39, 6, "timeConfidence")
    if p.pos_confidence is not None:
        w.constrained(p.pos_confidence[0], 0, 15, 4, "posConfidence.pos")
        w.constrained(p.pos_confidence[1], 0, 15, 4, "posConfidence.elevation")
    if p.speed_confidence is not None:
        w.constrained(p.speed_confidence[0], 0, 7, 3, "speedConfidence.heading")
        w.constrained(p.speed_confidence[1], 0, 7, 3, "speedConfidence.speed")
        w.constrained(p.speed_confidence[2], 0, 3, 2, "speedConfidence.throttle")


def _read_point(r: BitReader) -> PathHistoryPoint:
    ext = r.read(1, "PathHistoryPoint")
    present = r.read(3, "PathHistoryPoint preamble")
    head = r.read(64, "PathHistoryPoint")  # latOffset 18, lonOffset 18, elevation 12, time 16
    time_offset = (head & 0xFFFF) + 1
    if time_offset > 65535:  # TimeOffset ::= INTEGER (1..65535): raw 0xFFFF is 65536
        raise DecodeError("out-of-range",
                          f"PathHistoryPoint.timeOffset={time_offset} outside 1..65535")
    elev = ((head >> 16) & 0xFFF) - 2048
    lon = ((head >> 28) & 0x3FFFF) - 131072
    lat = (head >> 46) - 131072
    speed = scaled(u.SPEED, r.read(13, "PathHistoryPoint.speed")) if present & 4 else None
    accuracy = _read_accuracy(r) if present & 2 else None
    heading = (scaled(u.COARSE_HEADING, r.constrained(0, 240, 8, "PathHistoryPoint.heading"))
               if present & 1 else None)
    if ext:
        skip_extensions(r, "PathHistoryPoint")
    return PathHistoryPoint(
        lat_offset=scaled(u.OFFSET_LL, lat), lon_offset=scaled(u.OFFSET_LL, lon),
        elev_offset=scaled(u.VERT_OFFSET, elev), time_offset=scaled(u.TIME_OFFSET, time_offset),
        speed=speed, accuracy=accuracy, heading=heading)


def _write_point(w: BitWriter, p: PathHistoryPoint) -> None:
    w.write((4 if p.speed is not None else 0) | (2 if p.accuracy is not None else 0)
            | (1 if p.heading is not None else 0), 4)  # extension bit 0, then 3 presence bits
    w.write(((u.OFFSET_LL.to_raw(p.lat_offset) + 131072) << 46)
            | ((u.OFFSET_LL.to_raw(p.lon_offset) + 131072) << 28)
            | ((u.VERT_OFFSET.to_raw(p.elev_offset) + 2048) << 16)
            | (u.TIME_OFFSET.to_raw(p.time_offset) - 1), 64)
    if p.speed is not None:
        w.write(u.SPEED.to_raw(p.speed), 13)
    if p.accuracy is not None:
        w.write(accuracy_raw(p.accuracy), 32)
    if p.heading is not None:
        w.write(u.COARSE_HEADING.to_raw(p.heading), 8)


def _read_path_history(r: BitReader) -> PathHistory:
    ext = r.read(1, "PathHistory")
    present = r.read(2, "PathHistory preamble")
    initial = _read_fpv(r) if present & 2 else None
    gnss = BitString(r.read(8, "currGNSSstatus"), 8) if present & 1 else None
    count = r.read(5, "crumbData count") + 1
    if count > 23:
        raise DecodeError("out-of-range", f"crumbData has {count} points, at most 23 allowed")
    points = tuple(_read_point(r) for _ in range(count))
    if ext:
        skip_extensions(r, "PathHistory")
    return PathHistory(points=points, initial_position=initial, gnss_status=gnss)


def _write_path_history(w: BitWriter, ph: PathHistory) -> None:
    if not 1 <= len(ph.points) <= 23:
        raise EncodeError(f"path history needs 1..23 points, got {len(ph.points)}")
    w.write((2 if ph.initial_position is not None else 0)
            | (1 if ph.gnss_status is not None else 0), 3)
    if ph.initial_position is not None:
        _write_fpv(w, ph.initial_position)
    if ph.gnss_status is not None:
        if ph.gnss_status.size != 8:
            raise EncodeError("currGNSSstatus is a BIT STRING of exactly 8 bits")
        w.write(ph.gnss_status.value, 8)
    w.write(len(ph.points) - 1, 5)
    for p in ph.points:
        _write_point(w, p)


def read_vse(r: BitReader) -> dict:
    """VehicleSafetyExtensions as BSM keyword arguments (none when all four are absent)."""
    ext = r.read(1, "VehicleSafetyExtensions")
    present = r.read(4, "VehicleSafetyExtensions preamble")
    out: dict = {}
    if present & 8:
        out["events"] = _read_ext_bitstring(r, 13, "events")
    if present & 4:
        out["path_history"] = _read_path_history(r)
    if present & 2:
        ext_pp = r.read(1, "PathPrediction")
        radius = r.constrained(-32767, 32767, 16, "radiusOfCurve")
        confidence = r.constrained(0, 200, 8, "confidence")
        if ext_pp:
            skip_extensions(r, "PathPrediction")
        out["path_prediction"] = PathPrediction(u.radius_from_raw(radius), confidence * 0.5)
    if present & 1:
        out["lights"] = _read_ext_bitstring(r, 9, "lights")
    if ext:
        skip_extensions(r, "VehicleSafetyExtensions")
    return out


def encode_vse(m: BSM) -> bytes:
    """The VehicleSafetyExtensions of ``m`` (with no fields when all four are None)."""
    parts = (m.events, m.path_history, m.path_prediction, m.lights)
    w = BitWriter()
    w.write(sum(1 << (3 - i) for i, p in enumerate(parts) if p is not None), 5)
    if m.events is not None:
        _write_ext_bitstring(w, m.events, 13, "events")
    if m.path_history is not None:
        _write_path_history(w, m.path_history)
    if m.path_prediction is not None:
        w.write(0, 1)
        w.write(u.radius_to_raw(m.path_prediction.radius_of_curve) + 32767, 16)
        w.write(u.CONFIDENCE.to_raw(m.path_prediction.confidence), 8)
    if m.lights is not None:
        _write_ext_bitstring(w, m.lights, 9, "lights")
    return w.to_bytes()
