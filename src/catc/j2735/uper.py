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
* other Part II content and regional extensions are kept as opaque octets, so a
  frame carrying them re-encodes unchanged;
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


def _brakes(raw: int) -> BrakeStatus:
    """BrakeSystemStatus from its 15 bits (cached: real traffic uses few combinations)."""
    b = _brake_cache.get(raw)
    if b is None:
        boost = (raw >> 2) & 3
        if boost > 2:
            raise DecodeError("out-of-range", f"brakeBoost={boost} outside 0..2")
        b = BrakeStatus(raw >> 10, ControlStatus((raw >> 8) & 3), ControlStatus((raw >> 6) & 3),
                        ControlStatus((raw >> 4) & 3), BrakeBoost(boost), AuxBrakes(raw & 3))
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


def _decode_vse(data: bytes) -> dict:
    r = BitReader(data)
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


def _encode_vse(m: BSM) -> bytes | None:
    parts = (m.events, m.path_history, m.path_prediction, m.lights)
    if parts == (None, None, None, None):  # no Part II (most BSMs): no generator to run
        return None
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
        for _ in range(count):
            part_id = r.read(6, "partII-Id")
            value = r.open_type("partII-Value")
            if part_id == VEHICLE_SAFETY_EXT and not have_vse:
                have_vse = True
                fields.update(_decode_vse(value))
            else:
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
    vse = _encode_vse(m)
    part2 = ([(VEHICLE_SAFETY_EXT, vse)] if vse is not None else []) + list(m.part2_other)
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
