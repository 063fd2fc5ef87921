"""J2735 ``BSMcoreData`` in UPER: the fixed 290-bit block every BSM opens with.

BSMcoreData has no OPTIONAL fields and no extension marker, so it is a fixed 290-bit
block; it is read and written with one big-integer operation and fixed shifts, which is
what makes the codec fast in pure Python.  Field order and widths: ``bsm.asn``
(msgCnt 7, id 32, secMark 16, lat 31, long 32, elev 16, accuracy 32, transmission 3,
speed 13, heading 15, angle 8, accelSet 12 + 12 + 8 + 16, brakes 15, size 10 + 12).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from catc import units as u
from catc.bsm import (
    BSM,
    AuxBrakes,
    BrakeBoost,
    BrakeStatus,
    ControlStatus,
    PositionalAccuracy,
)
from catc.errors import DecodeError, EncodeError
from catc.j2735.uper._elements import TRANSMISSION, accuracy_from_raw, accuracy_raw

CORE_BITS = 290

# Raw-offset limits for the core fields whose range does not fill their bit width.
_LAT_SPAN = 1_800_000_001
_LON_SPAN = 3_600_000_000
_HEADING_MAX = 28800
_ANGLE_SPAN = 253
_ACCEL_SPAN = 4001
_VERT_SPAN = 254
_YAW_SPAN = 65534
_VERT_LSB = u.ACCEL_VERT.lsb


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


_accuracy_cache: dict[int, PositionalAccuracy] = {}
_ACCURACY_CACHE_MAX = 1024  # as _BRAKE_CACHE_MAX: a sender's accuracy changes seldom


def _accuracy(raw: int) -> PositionalAccuracy:
    """PositionalAccuracy from its 32 bits (cached, bounded, as :func:`_brakes`)."""
    a = _accuracy_cache.get(raw)
    if a is None:
        a = accuracy_from_raw(raw)
        if len(_accuracy_cache) < _ACCURACY_CACHE_MAX:
            _accuracy_cache[raw] = a
    return a


def _positional_maker(cls: type, n: int) -> Callable[[tuple], Any]:
    """A function of one tuple ``c`` that makes ``cls(*c)``, for a frozen slotted
    dataclass whose first ``n`` fields ``c`` holds and whose other fields have defaults:
    the same object, made by setting each slot through its descriptor.  That takes half
    the time of the generated ``__init__``, which goes through ``object.__setattr__``
    for each field (25 for a BSM) to get past ``frozen``.  Generated code, as dataclasses
    makes ``__init__``; for a class without ``__post_init__`` only."""
    fields = dataclasses.fields(cls)
    if hasattr(cls, "__post_init__") or any(
            f.default is dataclasses.MISSING for f in fields[n:]):
        raise TypeError(f"{cls.__name__}: no positional maker")
    scope: dict[str, Any] = {"_new": object.__new__, "_cls": cls}
    lines = ["def make(c):", "    o = _new(_cls)"]
    for i, f in enumerate(fields):
        scope[f"_s{i}"] = getattr(cls, f.name).__set__
        if i < n:
            lines.append(f"    _s{i}(o, c[{i}])")
        else:
            scope[f"_d{i}"] = f.default
            lines.append(f"    _s{i}(o, _d{i})")
    lines.append("    return o")
    exec("\n".join(lines), scope)  # the class's own field names and values only
    return scope["make"]


def decode_core(v: int) -> tuple:
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
        TRANSMISSION[trans],
        None if angle == 127 else angle * 1.5,
        None if along == 2001 else along * 0.01,
        None if alat == 2001 else alat * 0.01,
        None if vert == -127 else vert * _VERT_LSB,
        (yaw - 32767) * 0.01,
        _brakes(brakes),
        None if width == 0 else width * 0.01,
        None if length == 0 else length * 0.01,
    )


#: ``BSM(*decode_core(v))`` for a BSM of BSMcoreData only, in half the time.
core_bsm = _positional_maker(BSM, 18)


def core_raw(m: BSM) -> int:
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
    v = (v << 32) | accuracy_raw(m.accuracy)
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
