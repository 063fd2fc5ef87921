"""UPER (X.691 unaligned PER) codec for the J2735 MessageFrame carrying a BasicSafetyMessage.

The ASN.1 it implements is ``bsm.asn`` beside this file.  BSMcoreData has no
OPTIONAL fields and no extension marker, so it is a fixed 290-bit block; it is
read and written with one big-integer operation and fixed shifts, which is what
makes the codec fast in pure Python.  Part II is walked field by field.

Decoding is total: for any input it returns a :class:`~catc.bsm.BSM` or raises
:class:`~catc.errors.DecodeError`.  What is decoded:

* BSMcoreData in full;
* Part II VehicleSafetyExtensions (id 0): events, pathHistory (with initialPosition
  and currGNSSstatus), pathPrediction and lights;
* Part II SpecialVehicleExtensions (id 1) and SupplementalVehicleExtensions (id 2)
  are checked against their J2735 2020 ASN.1 and kept as their octets; other Part II
  ids and regional extensions are kept as opaque octets.  So a frame carrying them
  re-encodes unchanged, with its Part II items in the order received;
* every Part II value must fill its open type: octets left over after the value
  (beyond the at most 7 bits of padding) are rejected as garbage, and so is a value
  that runs past its octets;
* extension additions (the ``...`` of an extensible SEQUENCE) are skipped, and a
  frame that has them does not re-encode bit-exactly.

OPTIONAL fields that are present but hold their "unavailable" code decode to
``None`` just like absent ones, and ``None`` encodes as absent.
"""

from __future__ import annotations

from catc import units as u
from catc.bsm import (
    BSM,
    AuxBrakes,
    BitString,
    BrakeBoost,
    BrakeStatus,
    ControlStatus,
    DDateTime,
    FullPositionVector,
    PathHistory,
    PathHistoryPoint,
    PathPrediction,
    PositionalAccuracy,
    TransmissionState,
)
from catc.errors import DecodeError, EncodeError
from catc.j2735.bits import BitReader, BitWriter

#: DSRCmsgID of a BasicSafetyMessage.
BSM_MESSAGE_ID = 20
#: Part II id of VehicleSafetyExtensions.
VEHICLE_SAFETY_EXT = 0

_TRANSMISSION = (*TransmissionState, None)  # raw 7 = unavailable
_CORE_BITS = 290

# Raw-offset limits for the core fields whose range does not fill their bit width.
_LAT_SPAN = 1_800_000_001
_LON_SPAN = 3_600_000_000
_HEADING_MAX = 28800
_ANGLE_SPAN = 253
_ACCEL_SPAN = 4001
_VERT_SPAN = 254
_YAW_SPAN = 65534
_VERT_LSB = u.ACCEL_VERT.lsb


def _q(quantity: u.Quantity, raw: int) -> float | None:
    return None if raw == quantity.unavailable else raw * quantity.lsb


_brake_cache: dict[int, BrakeStatus] = {}
#: Entries kept: real traffic uses a few combinations; a flood of garbage that decodes
#: would otherwise fill all 24,576 valid ones (~10 MB, measured growing under
#: bench/obu_flood.py).
_BRAKE_CACHE_MAX = 1024


def _brakes(raw: int) -> BrakeStatus:
    """BrakeSystemStatus from its 15 bits (cached, bounded: real traffic uses few
    combinations)."""
    b = _brake_cache.get(raw)
    if b is None:
        boost = (raw >> 2) & 3
        if boost > 2:
            raise DecodeError("out-of-range", f"brakeBoost={boost} outside 0..2")
        b = BrakeStatus(raw >> 10, ControlStatus((raw >> 8) & 3), ControlStatus((raw >> 6) & 3),
                        ControlStatus((raw >> 4) & 3), BrakeBoost(boost), AuxBrakes(raw & 3))
        if len(_brake_cache) < _BRAKE_CACHE_MAX:
            _brake_cache[raw] = b
    return b


def _accuracy(raw: int) -> PositionalAccuracy:
    orient = raw & 0xFFFF
    smin = (raw >> 16) & 0xFF
    smaj = raw >> 24
    return PositionalAccuracy(
        None if smaj == 255 else smaj * 0.05,
        None if smin == 255 else smin * 0.05,
        None if orient == 65535 else orient * u.ORIENTATION.lsb,
    )


def _accuracy_raw(a: PositionalAccuracy) -> int:
    return ((u.SEMI_AXIS.to_raw(a.semi_major) << 24) | (u.SEMI_AXIS.to_raw(a.semi_minor) << 16)
            | u.ORIENTATION.to_raw(a.orientation))


# --- BSMcoreData -----------------------------------------------------------------------------

def _decode_core(v: int) -> tuple:
    """BSM constructor arguments from the 290-bit BSMcoreData block ``v``."""
    length = v & 0xFFF
    width = (v >> 12) & 0x3FF
    brakes = (v >> 22) & 0x7FFF
    yaw = (v >> 37) & 0xFFFF
    vert = (v >> 53) & 0xFF
    alat = (v >> 61) & 0xFFF
    along = (v >> 73) & 0xFFF
    angle = (v >> 85) & 0xFF
    heading = (v >> 93) & 0x7FFF
    speed = (v >> 108) & 0x1FFF
    trans = (v >> 121) & 0x7
    accuracy = (v >> 124) & 0xFFFFFFFF
    elev = ((v >> 156) & 0xFFFF) - 4096
    lon = (v >> 172) & 0xFFFFFFFF
    lat = (v >> 204) & 0x7FFFFFFF
    sec_mark = (v >> 235) & 0xFFFF
    temp_id = (v >> 251) & 0xFFFFFFFF
    msg_cnt = v >> 283
    if lat > _LAT_SPAN:
        raise DecodeError("out-of-range", f"lat={lat - 900_000_000} outside constraint")
    if lon > _LON_SPAN:
        raise DecodeError("out-of-range", f"long={lon - 1_799_999_999} outside constraint")
    if heading > _HEADING_MAX:
        raise DecodeError("out-of-range", f"heading={heading} outside 0..28800")
    if angle > _ANGLE_SPAN:
        raise DecodeError("out-of-range", f"angle={angle - 126} outside -126..127")
    if along > _ACCEL_SPAN or alat > _ACCEL_SPAN:
        raise DecodeError("out-of-range", "accelSet long/lat outside -2000..2001")
    if vert > _VERT_SPAN:
        raise DecodeError("out-of-range", f"accelSet vert={vert - 127} outside -127..127")
    if yaw > _YAW_SPAN:
        raise DecodeError("out-of-range", f"accelSet yaw={yaw - 32767} outside -32767..32767")
    lat -= 900_000_000
    lon -= 1_799_999_999
    angle -= 126
    along -= 2000
    alat -= 2000
    vert -= 127
    # Positional, in BSM field order: msg_cnt .. length.
    return (
        msg_cnt,
        temp_id,
        None if sec_mark == 65535 else sec_mark,
        None if lat == 900_000_001 else lat * 1e-7,
        None if lon == 1_800_000_001 else lon * 1e-7,
        None if elev == -4096 else elev * 0.1,
        None if speed == 8191 else speed * 0.02,
        None if heading == 28800 else heading * 0.0125,
        _accuracy(accuracy),
        _TRANSMISSION[trans],
        None if angle == 127 else angle * 1.5,
        None if along == 2001 else along * 0.01,
        None if alat == 2001 else alat * 0.01,
        None if vert == -127 else vert * _VERT_LSB,
        (yaw - 32767) * 0.01,
        _brakes(brakes),
        None if width == 0 else width * 0.01,
        None if length == 0 else length * 0.01,
    )


def _core_raw(m: BSM) -> int:
    """The 290-bit BSMcoreData of ``m`` as one integer."""
    if not 0 <= m.temp_id <= 0xFFFFFFFF:
        raise EncodeError(f"temp_id={m.temp_id!r} is not a 32-bit unsigned integer")
    sec_mark = 65535 if m.sec_mark is None else m.sec_mark
    if not 0 <= sec_mark <= 65535:
        raise EncodeError(f"sec_mark={sec_mark!r} outside 0..65535")
    b = m.brakes
    if not 0 <= b.wheel_brakes <= 0b11111:
        raise EncodeError(f"wheel_brakes={b.wheel_brakes!r} is not a 5-bit mask")
    trans = 7 if m.transmission is None else int(m.transmission)
    v = m.msg_cnt & 0x7F
    v = (v << 32) | m.temp_id
    v = (v << 16) | sec_mark
    v = (v << 31) | (u.LATITUDE.to_raw(m.lat) + 900_000_000)
    v = (v << 32) | (u.LONGITUDE.to_raw(m.lon) + 1_799_999_999)
    v = (v << 16) | (u.ELEVATION.to_raw(m.elev) + 4096)
    v = (v << 32) | _accuracy_raw(m.accuracy)
    v = (v << 3) | trans
    v = (v << 13) | u.SPEED.to_raw(m.speed)
    v = (v << 15) | u.HEADING.to_raw(m.heading)
    v = (v << 8) | (u.STEERING.to_raw(m.steering_angle) + 126)
    v = (v << 12) | (u.ACCEL.to_raw(m.accel_long) + 2000)
    v = (v << 12) | (u.ACCEL.to_raw(m.accel_lat) + 2000)
    v = (v << 8) | (u.ACCEL_VERT.to_raw(m.accel_vert) + 127)
    v = (v << 16) | (u.YAW_RATE.to_raw(m.yaw_rate) + 32767)
    v = (v << 15) | ((b.wheel_brakes << 10) | (b.traction << 8) | (b.abs << 6) | (b.scs << 4)
                     | (b.brake_boost << 2) | b.aux_brakes)
    v = (v << 10) | u.WIDTH.to_raw(m.width)
    return (v << 12) | u.LENGTH.to_raw(m.length)


# --- Generic helpers for extensible types ----------------------------------------------------

def _skip_extensions(r: BitReader, what: str) -> None:
    """Skip the extension additions of an extensible SEQUENCE (X.691 §19.7-19.9)."""
    count = r.small_length(f"{what} extension bitmap")
    present = r.read(count, f"{what} extension bitmap")
    for _ in range(bin(present).count("1")):
        r.open_type(f"{what} extension addition")


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


# --- Part II: VehicleSafetyExtensions ----------------------------------------------------------

def _read_accuracy(r: BitReader) -> PositionalAccuracy:
    return _accuracy(r.read(32, "PositionalAccuracy"))


#: DDateTime components: name, lower bound, upper bound, bits (all OPTIONAL, no extension).
_DDATETIME = (("year", 0, 4095, 12), ("month", 0, 12, 4), ("day", 0, 31, 5),
              ("hour", 0, 31, 5), ("minute", 0, 60, 6), ("second", 0, 65535, 16),
              ("offset", -840, 840, 11))


def _read_ddatetime(r: BitReader) -> DDateTime:
    present = r.read(7, "DDateTime preamble")
    values = {}
    for i, (name, lo, hi, nbits) in enumerate(_DDATETIME):
        if present & (1 << (6 - i)):
            values[name] = r.constrained(lo, hi, nbits, f"DDateTime.{name}")
    return DDateTime(**values)


def _write_ddatetime(w: BitWriter, t: DDateTime) -> None:
    values = [getattr(t, name) for name, *_ in _DDATETIME]
    w.write(sum(1 << (6 - i) for i, v in enumerate(values) if v is not None), 7)
    for (name, lo, hi, nbits), v in zip(_DDATETIME, values, strict=True):
        if v is not None:
            w.constrained(v, lo, hi, nbits, f"DDateTime.{name}")


def _read_fpv(r: BitReader) -> FullPositionVector:
    ext = r.read(1, "FullPositionVector")
    present = r.read(8, "FullPositionVector preamble")
    utc = _read_ddatetime(r) if present & 0x80 else None
    lon = r.constrained(-1_799_999_999, 1_800_000_001, 32, "FullPositionVector.long")
    lat = r.constrained(-900_000_000, 900_000_001, 31, "FullPositionVector.lat")
    elev = u.ELEVATION.from_raw(r.read(16, "elevation") - 4096) if present & 0x40 else None
    heading = (u.HEADING.from_raw(r.constrained(0, 28800, 15, "FullPositionVector.heading"))
               if present & 0x20 else None)
    trans = speed = None
    if present & 0x10:
        trans = _TRANSMISSION[r.read(3, "TransmissionAndSpeed")]
        speed = u.SPEED.from_raw(r.read(13, "TransmissionAndSpeed"))
    accuracy = _read_accuracy(r) if present & 0x08 else None
    time_conf = r.constrained(0, 39, 6, "timeConfidence") if present & 0x04 else None
    pos_conf = (r.read(4, "posConfidence"), r.read(4, "posConfidence")) if present & 0x02 else None
    speed_conf = ((r.read(3, "speedConfidence"), r.read(3, "speedConfidence"),
                   r.read(2, "speedConfidence")) if present & 0x01 else None)
    if ext:
        _skip_extensions(r, "FullPositionVector")
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
        _write_ddatetime(w, p.utc_time)
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
        w.write(_accuracy_raw(p.accuracy), 32)
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
    speed = _q(u.SPEED, r.read(13, "PathHistoryPoint.speed")) if present & 4 else None
    accuracy = _read_accuracy(r) if present & 2 else None
    heading = (_q(u.COARSE_HEADING, r.constrained(0, 240, 8, "PathHistoryPoint.heading"))
               if present & 1 else None)
    if ext:
        _skip_extensions(r, "PathHistoryPoint")
    return PathHistoryPoint(
        lat_offset=_q(u.OFFSET_LL, lat), lon_offset=_q(u.OFFSET_LL, lon),
        elev_offset=_q(u.VERT_OFFSET, elev), time_offset=_q(u.TIME_OFFSET, time_offset),
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
        w.write(_accuracy_raw(p.accuracy), 32)
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
        _skip_extensions(r, "PathHistory")
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


def _read_vse(r: BitReader) -> dict:
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
            _skip_extensions(r, "PathPrediction")
        out["path_prediction"] = PathPrediction(u.radius_from_raw(radius), confidence * 0.5)
    if present & 1:
        out["lights"] = _read_ext_bitstring(r, 9, "lights")
    if ext:
        _skip_extensions(r, "VehicleSafetyExtensions")
    return out


def _encode_vse(m: BSM) -> bytes:
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


# --- Part II: SpecialVehicleExtensions and SupplementalVehicleExtensions -------------------------
#
# Checked against the J2735 2020 ASN.1 (written out in bsm.asn) and kept as octets.  Each
# walker reads one type and keeps nothing; a field that fills its bit width (every raw
# value legal) is read as bits, a field with a narrower range is checked.

def _int(r: BitReader, lo: int, hi: int, what: str) -> int:
    """INTEGER (lo..hi): a constrained whole number in the fewest bits (X.691 §11.5.6)."""
    return r.constrained(lo, hi, (hi - lo).bit_length(), what)


def _size(r: BitReader, lo: int, hi: int, what: str) -> int:
    """The number of elements of a SEQUENCE (SIZE(lo..hi)) OF (X.691 §20.6)."""
    return _int(r, lo, hi, f"{what} count")


def _bits(nbits: int, what: str):
    """A walker for a field whose every ``nbits`` value is legal."""
    return lambda r: r.read(nbits, what)


def _range(lo: int, hi: int, what: str):
    """A walker for INTEGER (lo..hi)."""
    return lambda r: _int(r, lo, hi, what)


def _enum(count: int, what: str):
    """A walker for an ENUMERATED of ``count`` root values and an extension marker."""
    return lambda r: r.enumerated(count, True, what)


def _preamble(r: BitReader, n_optional: int, what: str) -> tuple[int, int]:
    """The extension bit and the presence bitmap of an extensible SEQUENCE (X.691 §19)."""
    head = r.read(1 + n_optional, f"{what} preamble")
    return head >> n_optional, head & ((1 << n_optional) - 1)


def _walk_optionals(r: BitReader, what: str, walkers: tuple) -> None:
    """An extensible SEQUENCE whose components are all OPTIONAL, one walker each."""
    n = len(walkers)
    ext, present = _preamble(r, n, what)
    for i, walk in enumerate(walkers):
        if present >> (n - 1 - i) & 1:
            walk(r)
    if ext:
        _skip_extensions(r, what)


def _walk_regional(r: BitReader) -> None:
    """SEQUENCE (SIZE(1..4)) OF RegionalExtension: regionId INTEGER (0..255) and an open
    type, whose content is not checked (the REGION content sets are extensible)."""
    for _ in range(_size(r, 1, 4, "regional")):
        r.read(8, "regionId")
        r.open_type("regExtValue")


def _walk_pivot(r: BitReader) -> None:
    """PivotPointDescription ::= SEQUENCE { pivotOffset Offset-B11, pivotAngle Angle,
    pivots PivotingAllowed (BOOLEAN), ... }"""
    ext = r.read(1, "PivotPointDescription")
    r.read(11, "PivotPointDescription.pivotOffset")  # -1024..1023
    _int(r, 0, 28800, "PivotPointDescription.pivotAngle")
    r.read(1, "PivotPointDescription.pivots")
    if ext:
        _skip_extensions(r, "PivotPointDescription")


def _walk_trailer_point(r: BitReader) -> None:
    """TrailerHistoryPoint ::= SEQUENCE { pivotAngle Angle, timeOffset TimeOffset,
    positionOffset Node-XY-24b, elevationOffset VertOffset-B07 OPTIONAL,
    heading CoarseHeading OPTIONAL, ... }"""
    ext, present = _preamble(r, 2, "TrailerHistoryPoint")
    _int(r, 0, 28800, "TrailerHistoryPoint.pivotAngle")
    _int(r, 1, 65535, "TrailerHistoryPoint.timeOffset")
    r.read(24, "TrailerHistoryPoint.positionOffset")  # x, y: Offset-B12 -2048..2047
    if present & 2:
        r.read(7, "TrailerHistoryPoint.elevationOffset")  # -64..63
    if present & 1:
        _int(r, 0, 240, "TrailerHistoryPoint.heading")
    if ext:
        _skip_extensions(r, "TrailerHistoryPoint")


def _walk_trailer_unit(r: BitReader) -> None:
    """TrailerUnitDescription ::= SEQUENCE { isDolly IsDolly, width VehicleWidth,
    length VehicleLength, height VehicleHeight OPTIONAL, mass TrailerMass OPTIONAL,
    bumperHeights BumperHeights OPTIONAL, centerOfGravity VehicleHeight OPTIONAL,
    frontPivot PivotPointDescription, rearPivot PivotPointDescription OPTIONAL,
    rearWheelOffset Offset-B12 OPTIONAL, positionOffset Node-XY-24b,
    elevationOffset VertOffset-B07 OPTIONAL, crumbData TrailerHistoryPointList OPTIONAL,
    ... }"""
    ext, present = _preamble(r, 8, "TrailerUnitDescription")
    r.read(1 + 10 + 12, "TrailerUnitDescription")  # isDolly, width 0..1023, length 0..4095
    if present & 0x80:
        r.read(7, "TrailerUnitDescription.height")  # 0..127
    if present & 0x40:
        r.read(8, "TrailerUnitDescription.mass")  # 0..255
    if present & 0x20:
        r.read(14, "TrailerUnitDescription.bumperHeights")  # front, rear: 0..127
    if present & 0x10:
        r.read(7, "TrailerUnitDescription.centerOfGravity")
    _walk_pivot(r)
    if present & 8:
        _walk_pivot(r)
    if present & 4:
        r.read(12, "TrailerUnitDescription.rearWheelOffset")  # -2048..2047
    r.read(24, "TrailerUnitDescription.positionOffset")
    if present & 2:
        r.read(7, "TrailerUnitDescription.elevationOffset")
    if present & 1:
        for _ in range(_size(r, 1, 23, "TrailerUnitDescription.crumbData")):
            _walk_trailer_point(r)
    if ext:
        _skip_extensions(r, "TrailerUnitDescription")


def _walk_trailer_data(r: BitReader) -> None:
    """TrailerData ::= SEQUENCE { notUsed SSPindex, connection PivotPointDescription,
    units SEQUENCE (SIZE(1..8)) OF TrailerUnitDescription, ... }"""
    ext = r.read(1, "TrailerData")
    r.read(5, "TrailerData.notUsed")  # 0..31
    _walk_pivot(r)
    for _ in range(_size(r, 1, 8, "TrailerData.units")):
        _walk_trailer_unit(r)
    if ext:
        _skip_extensions(r, "TrailerData")


def _walk_privileged_events(r: BitReader) -> None:
    """PrivilegedEvents ::= SEQUENCE { notUsed SSPindex, event PrivilegedEventFlags, ... }"""
    ext = r.read(1, "PrivilegedEvents")
    r.read(5 + 16, "PrivilegedEvents")  # 0..31, BIT STRING (SIZE(16))
    if ext:
        _skip_extensions(r, "PrivilegedEvents")


def _walk_emergency_details(r: BitReader) -> None:
    """EmergencyDetails ::= SEQUENCE { notUsed SSPindex, sirenUse SirenInUse,
    lightsUse LightbarInUse, multi MultiVehicleResponse, events PrivilegedEvents OPTIONAL,
    responseType ResponseType OPTIONAL, ... }"""
    ext, present = _preamble(r, 2, "EmergencyDetails")
    r.read(5 + 2 + 3 + 2, "EmergencyDetails")  # 0..31, then enumerations of 4, 8 and 4
    if present & 2:
        _walk_privileged_events(r)
    if present & 1:
        r.enumerated(7, True, "EmergencyDetails.responseType")
    if ext:
        _skip_extensions(r, "EmergencyDetails")


def _walk_event_description(r: BitReader) -> None:
    """EventDescription ::= SEQUENCE { typeEvent ITIScodes, description SEQUENCE
    (SIZE(1..8)) OF ITIScodes OPTIONAL, priority Priority OPTIONAL, heading HeadingSlice
    OPTIONAL, extent Extent OPTIONAL, regional ... OPTIONAL, ... }"""
    ext, present = _preamble(r, 5, "EventDescription")
    r.read(16, "EventDescription.typeEvent")  # ITIScodes 0..65535
    if present & 16:
        r.read(16 * _size(r, 1, 8, "EventDescription.description"), "EventDescription")
    if present & 8:
        r.read(8, "EventDescription.priority")  # OCTET STRING (SIZE(1))
    if present & 4:
        r.read(16, "EventDescription.heading")  # BIT STRING (SIZE(16))
    if present & 2:
        r.read(4, "EventDescription.extent")  # 16 values
    if present & 1:
        _walk_regional(r)
    if ext:
        _skip_extensions(r, "EventDescription")


def _walk_special(r: BitReader) -> None:
    """SpecialVehicleExtensions ::= SEQUENCE { vehicleAlerts EmergencyDetails OPTIONAL,
    description EventDescription OPTIONAL, trailers TrailerData OPTIONAL, ... }"""
    _walk_optionals(r, "SpecialVehicleExtensions",
                    (_walk_emergency_details, _walk_event_description, _walk_trailer_data))


def _walk_wiper_set(r: BitReader) -> None:
    """WiperSet ::= SEQUENCE { statusFront WiperStatus, rateFront WiperRate,
    statusRear WiperStatus OPTIONAL, rateRear WiperRate OPTIONAL } (no extension marker)"""
    present = r.read(2, "WiperSet preamble")
    r.enumerated(7, True, "WiperSet.statusFront")
    r.read(7, "WiperSet.rateFront")  # 0..127
    if present & 2:
        r.enumerated(7, True, "WiperSet.statusRear")
    if present & 1:
        r.read(7, "WiperSet.rateRear")


def _walk_weather_report(r: BitReader) -> None:
    """WeatherReport ::= SEQUENCE { isRaining EssPrecipYesNo, rainRate EssPrecipRate
    OPTIONAL, precipSituation EssPrecipSituation OPTIONAL, solarRadiation
    EssSolarRadiation OPTIONAL, friction EssMobileFriction OPTIONAL,
    roadFriction CoefficientOfFriction OPTIONAL, ... }"""
    ext, present = _preamble(r, 5, "WeatherReport")
    r.enumerated(3, False, "WeatherReport.isRaining")
    if present & 16:
        r.read(16, "WeatherReport.rainRate")  # 0..65535
    if present & 8:
        r.enumerated(15, False, "WeatherReport.precipSituation")
    if present & 4:
        r.read(16, "WeatherReport.solarRadiation")  # 0..65535
    if present & 2:
        _int(r, 0, 101, "WeatherReport.friction")
    if present & 1:
        _int(r, 0, 50, "WeatherReport.roadFriction")
    if ext:
        _skip_extensions(r, "WeatherReport")


def _walk_obstacle(r: BitReader) -> None:
    """ObstacleDetection ::= SEQUENCE { obDist ObstacleDistance, obDirect ObstacleDirection,
    description ITIScodes(523..541) OPTIONAL, locationDetails GenericLocations OPTIONAL,
    dateTime DDateTime, vertEvent VerticalAccelerationThreshold OPTIONAL, ... }"""
    ext, present = _preamble(r, 3, "ObstacleDetection")
    r.read(15, "ObstacleDetection.obDist")  # 0..32767
    _int(r, 0, 28800, "ObstacleDetection.obDirect")
    if present & 4:
        _int(r, 523, 541, "ObstacleDetection.description")
    if present & 2:
        r.enumerated(96, True, "ObstacleDetection.locationDetails")
    _read_ddatetime(r)
    if present & 1:
        r.read(5, "ObstacleDetection.vertEvent")  # BIT STRING (SIZE(5))
    if ext:
        _skip_extensions(r, "ObstacleDetection")


def _walk_disabled_vehicle(r: BitReader) -> None:
    """DisabledVehicle ::= SEQUENCE { statusDetails ITIScodes(523..541),
    locationDetails GenericLocations OPTIONAL, ... }"""
    ext, present = _preamble(r, 1, "DisabledVehicle")
    _int(r, 523, 541, "DisabledVehicle.statusDetails")
    if present:
        r.enumerated(96, True, "DisabledVehicle.locationDetails")
    if ext:
        _skip_extensions(r, "DisabledVehicle")


def _walk_speed_profile(r: BitReader) -> None:
    """SpeedProfile ::= SEQUENCE { speedReports SEQUENCE (SIZE(1..20)) OF GrossSpeed, ... }"""
    ext = r.read(1, "SpeedProfile")
    r.read(5 * _size(r, 1, 20, "SpeedProfile.speedReports"), "speedReports")  # 0..31 each
    if ext:
        _skip_extensions(r, "SpeedProfile")


def _walk_rtcm(r: BitReader) -> None:
    """RTCMPackage ::= SEQUENCE { rtcmHeader RTCMheader OPTIONAL, msgs SEQUENCE (SIZE(1..5))
    OF RTCMmessage, ... }; RTCMmessage ::= OCTET STRING (SIZE(1..1023))"""
    ext, present = _preamble(r, 1, "RTCMPackage")
    if present:  # RTCMheader: GNSSstatus (8 bits), AntennaOffsetSet (Offset-B12, B09, B10)
        r.read(8 + 12 + 9 + 10, "RTCMPackage.rtcmHeader")
    for _ in range(_size(r, 1, 5, "RTCMPackage.msgs")):
        r.octets(_int(r, 1, 1023, "RTCMmessage length"), "RTCMmessage")
    if ext:
        _skip_extensions(r, "RTCMPackage")


def _walk_supplemental(r: BitReader) -> None:
    """SupplementalVehicleExtensions ::= SEQUENCE { classification BasicVehicleClass,
    classDetails VehicleClassification, vehicleData VehicleData, weatherReport
    WeatherReport, weatherProbe WeatherProbe, obstacle ObstacleDetection, status
    DisabledVehicle, speedProfile SpeedProfile, theRTCM RTCMPackage, regional SEQUENCE
    (SIZE(1..4)) OF RegionalExtension, ... }, every component OPTIONAL"""
    _walk_optionals(r, "SupplementalVehicleExtensions", _SUPPLEMENTAL)


#: VehicleClassification ::= SEQUENCE { keyType BasicVehicleClass, role BasicVehicleRole,
#: iso3883 Iso3833VehicleType, hpmsType VehicleType, vehicleType VehicleGroupAffected,
#: responseEquip IncidentResponseEquipment, responderType ResponderGroupAffected,
#: fuelType FuelType, regional ..., ... }, every component OPTIONAL.  The ITIS
#: enumerations have 35, 72 and 14 root values, and an extension marker.
_VEHICLE_CLASSIFICATION = (
    _bits(8, "VehicleClassification.keyType"), _enum(23, "VehicleClassification.role"),
    _range(0, 100, "VehicleClassification.iso3883"),
    _enum(16, "VehicleClassification.hpmsType"),
    _enum(35, "VehicleClassification.vehicleType"),
    _enum(72, "VehicleClassification.responseEquip"),
    _enum(14, "VehicleClassification.responderType"),
    _bits(4, "VehicleClassification.fuelType"), _walk_regional)

#: VehicleData ::= SEQUENCE { height VehicleHeight, bumpers BumperHeights, mass VehicleMass,
#: trailerWeight TrailerWeight (0..64255), ... }, every component OPTIONAL.
_VEHICLE_DATA = (_bits(7, "VehicleData.height"), _bits(14, "VehicleData.bumpers"),
                 _bits(8, "VehicleData.mass"), _range(0, 64255, "VehicleData.trailerWeight"))

#: WeatherProbe ::= SEQUENCE { airTemp AmbientAirTemperature (0..191), airPressure
#: AmbientAirPressure, rainRates WiperSet, ... }, every component OPTIONAL.
_WEATHER_PROBE = (_range(0, 191, "WeatherProbe.airTemp"), _bits(8, "WeatherProbe.airPressure"),
                  _walk_wiper_set)

#: The components of SupplementalVehicleExtensions, in order (see _walk_supplemental).
_SUPPLEMENTAL = (
    _bits(8, "SupplementalVehicleExtensions.classification"),  # BasicVehicleClass 0..255
    lambda r: _walk_optionals(r, "VehicleClassification", _VEHICLE_CLASSIFICATION),
    lambda r: _walk_optionals(r, "VehicleData", _VEHICLE_DATA),
    _walk_weather_report,
    lambda r: _walk_optionals(r, "WeatherProbe", _WEATHER_PROBE),
    _walk_obstacle, _walk_disabled_vehicle, _walk_speed_profile, _walk_rtcm, _walk_regional)

#: Part II content checked here, by partII-Id: the type's name and its walker.
_PART2_TYPES = {1: ("SpecialVehicleExtensions", _walk_special),
                2: ("SupplementalVehicleExtensions", _walk_supplemental)}
#: (partII-Id, value) pairs already found valid: a vehicle repeats the same content.
_valid_part2: set[tuple[int, bytes]] = set()
_VALID_PART2_MAX = 1024


def _read_open_type(value: bytes, read, name: str):
    """``read`` applied to the inner encoding of an open type (X.691 §11.2).

    The value must end within its octets and leave at most the 7 bits that pad it to a
    whole octet.  Running past the octets or leaving more is garbage, not truncation:
    the frame around the open type is complete, its content is not of the type.
    Errors name the type: ``"{name}: {what went wrong}"``.
    """
    r = BitReader(value)
    try:
        result = read(r)
    except DecodeError as err:
        detail = str(err).partition(": ")[2]
        if err.reason == "truncated":
            raise DecodeError("garbage", f"{name}: the value runs past its {len(value)} "
                                         f"octets ({detail})") from None
        raise DecodeError(err.reason, f"{name}: {detail}") from None
    if r.remaining >= 8:
        raise DecodeError("garbage", f"{name}: {r.remaining // 8} octets left after the value")
    return result


def _check_part2(part_id: int, value: bytes) -> None:
    """Reject a Part II value of id 1 or 2 that is not of its type; other ids pass."""
    checked = _PART2_TYPES.get(part_id)
    if checked is None or (part_id, value) in _valid_part2:
        return
    _read_open_type(value, checked[1], checked[0])
    if len(_valid_part2) >= _VALID_PART2_MAX:
        _valid_part2.clear()
    _valid_part2.add((part_id, value))


# --- BasicSafetyMessage and MessageFrame -------------------------------------------------------

def _read_bsm(r: BitReader) -> BSM:
    head = r.read(3 + _CORE_BITS, "BasicSafetyMessage")
    core = _decode_core(head & ((1 << _CORE_BITS) - 1))
    ext = head >> (_CORE_BITS + 2)
    present = (head >> _CORE_BITS) & 3
    if not (ext or present):
        return BSM(*core)
    fields: dict = {}
    if present & 2:
        count = r.read(3, "partII count") + 1
        other = []
        have_vse = False
        for index in range(count):
            part_id = r.read(6, "partII-Id")
            value = r.open_type("partII-Value")
            if part_id == VEHICLE_SAFETY_EXT and not have_vse:
                have_vse = True
                vse = _read_open_type(value, _read_vse, "VehicleSafetyExtensions")
                fields.update(vse)
                if index or not vse:  # where the default (first, if not empty) is wrong
                    fields["vse_position"] = index
                continue
            _check_part2(part_id, value)
            other.append((part_id, value))
        fields["part2_other"] = tuple(other)
    if present & 1:
        count = r.read(2, "regional count") + 1
        fields["regional"] = tuple((r.read(8, "regionId"), r.open_type("regExtValue"))
                                   for _ in range(count))
    if ext:
        _skip_extensions(r, "BasicSafetyMessage")
    return BSM(*core, **fields)


def _write_bsm(w: BitWriter, m: BSM) -> None:
    if m.vse_position is not None and m.vse_position < 0:
        raise EncodeError(f"vse_position={m.vse_position!r} is negative")
    part2 = list(m.part2_other)
    vse_at = m.vse_index
    if vse_at is not None:  # in the order received, see BSM.vse_position
        part2.insert(vse_at, (VEHICLE_SAFETY_EXT, _encode_vse(m)))
    if len(part2) > 8:
        raise EncodeError(f"at most 8 Part II items, got {len(part2)}")
    if len(m.regional) > 4:
        raise EncodeError(f"at most 4 regional extensions, got {len(m.regional)}")
    w.write((2 if part2 else 0) | (1 if m.regional else 0), 3)
    w.write(_core_raw(m), _CORE_BITS)
    if part2:
        w.write(len(part2) - 1, 3)
        for part_id, value in part2:
            w.constrained(part_id, 0, 63, 6, "partII-Id")
            w.open_type(value, "partII-Value")
    if m.regional:
        w.write(len(m.regional) - 1, 2)
        for region_id, value in m.regional:
            w.constrained(region_id, 0, 255, 8, "regionId")
            w.open_type(value, "regExtValue")


def encode_bsm(m: BSM) -> bytes:
    """A bare UPER BasicSafetyMessage (no MessageFrame)."""
    w = BitWriter()
    _write_bsm(w, m)
    return w.to_bytes()


def decode_bsm(data: bytes) -> BSM:
    """Decode a bare UPER BasicSafetyMessage.  Trailing octets are ignored."""
    try:
        return _read_bsm(BitReader(data))
    except (ValueError, TypeError) as exc:  # enum construction inside a malformed frame
        if isinstance(exc, DecodeError):
            raise
        raise DecodeError("garbage", f"BasicSafetyMessage: {exc}") from None


def encode_frame(m: BSM) -> bytes:
    """A UPER MessageFrame (messageId 20) carrying ``m``: what goes on the air."""
    body = encode_bsm(m)
    n = len(body)
    if n < 0x80:
        return b"\x00\x14" + bytes((n,)) + body
    if n < 0x4000:
        return b"\x00\x14" + (0x8000 | n).to_bytes(2, "big") + body
    raise EncodeError(f"BSM of {n} octets needs a fragmented length")


def frame_message_id(data: bytes) -> int:
    """The messageId of a UPER MessageFrame, without decoding the rest."""
    if len(data) < 2:
        raise DecodeError("truncated",
                          f"MessageFrame needs 2 octets for messageId, got {len(data)}")
    return int.from_bytes(data[:2], "big") & 0x7FFF


def decode_frame(data: bytes) -> BSM:
    """Decode a UPER MessageFrame carrying a BasicSafetyMessage.

    Raises :class:`DecodeError` with reason ``wrong-message-id`` for any other
    message, ``truncated`` when the frame is cut short, and ``garbage`` or
    ``out-of-range`` when the bits cannot be a BSM.  Octets after the frame are
    ignored (deployed logs pad frames).
    """
    n = len(data)
    if n < 3:
        raise DecodeError("truncated", f"MessageFrame needs at least 3 octets, got {n}")
    # Octet-aligned header: extension bit + 15-bit messageId, then the open type's
    # length determinant (X.691 §11.9.3.5-8).  Extension additions after the value
    # (extension bit set) are ignored.
    message_id = ((data[0] << 8) | data[1]) & 0x7FFF
    if message_id != BSM_MESSAGE_ID:
        raise DecodeError("wrong-message-id",
                          f"messageId {message_id} is not a BasicSafetyMessage (20)")
    length = data[2]
    start = 3
    if length & 0x80:
        if length & 0x40:
            raise DecodeError("unsupported", "MessageFrame.value: fragmented length (>= 16K)")
        if n < 4:
            raise DecodeError("truncated", "MessageFrame.value: length determinant cut short")
        length = ((length & 0x3F) << 8) | data[3]
        start = 4
    if n - start < length:
        raise DecodeError("truncated",
                          f"MessageFrame.value: needs {length} octets, {n - start} left")
    return decode_bsm(data[start:start + length])
