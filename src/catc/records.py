"""BSMs as flat JSON-ready records: the form ``captures decode`` prints and ``rve encode`` reads.

The keys are a command-line contract (docs/architecture.md): ``msgCnt, id, secMark, lat, lon,
elev, speed, heading, accel_long, accel_lat, accel_vert, yaw_rate, width, length``.
Values are SI and degrees (see :mod:`catc.bsm`), ``id`` is 8 hex digits, and an
unavailable field is ``None`` (JSON ``null``).  Each value is rounded to the
resolution of its J2735 field, so ``speed`` prints as ``0.28`` and not as
``0.28000000000000003``; rounding to the LSB loses nothing.

``full=True`` adds the rest of the message under further keys (accuracy, transmission,
steering angle, brakes, Part II).
"""

from __future__ import annotations

import math
from typing import Any

from catc.bsm import BSM, BrakeStatus, PathHistory, PositionalAccuracy

#: The record keys in the order ``captures decode`` prints them.
KEYS = ("msgCnt", "id", "secMark", "lat", "lon", "elev", "speed", "heading", "accel_long",
        "accel_lat", "accel_vert", "yaw_rate", "width", "length")

# Decimal places that represent each field's LSB exactly.
_DIGITS = {"lat": 7, "lon": 7, "elev": 1, "speed": 2, "heading": 4, "accel_long": 2,
           "accel_lat": 2, "accel_vert": 6, "yaw_rate": 2, "width": 2, "length": 2,
           "semi_major": 2, "semi_minor": 2, "orientation": 6, "steering_angle": 1,
           "lat_offset": 7, "lon_offset": 7, "elev_offset": 1, "time_offset": 2,
           "coarse_heading": 1, "radius_of_curve": 1, "confidence": 1}


def _r(x: float | None, key: str) -> float | None:
    if x is None or math.isinf(x):
        return x
    return round(x, _DIGITS[key])


def _accuracy(a: PositionalAccuracy | None) -> dict | None:
    if a is None:
        return None
    return {"semi_major": _r(a.semi_major, "semi_major"),
            "semi_minor": _r(a.semi_minor, "semi_minor"),
            "orientation": _r(a.orientation, "orientation")}


def _brakes(b: BrakeStatus) -> dict:
    return {"wheel_brakes": f"{b.wheel_brakes:05b}", "applied": b.applied,
            "traction": b.traction.name.lower(), "abs": b.abs.name.lower(),
            "scs": b.scs.name.lower(), "brake_boost": b.brake_boost.name.lower(),
            "aux_brakes": b.aux_brakes.name.lower()}


def _path_history(ph: PathHistory) -> list[dict]:
    return [{"lat_offset": _r(p.lat_offset, "lat_offset"),
             "lon_offset": _r(p.lon_offset, "lon_offset"),
             "elev_offset": _r(p.elev_offset, "elev_offset"),
             "time_offset": _r(p.time_offset, "time_offset"),
             "speed": _r(p.speed, "speed"), "heading": _r(p.heading, "coarse_heading"),
             "accuracy": _accuracy(p.accuracy)}
            for p in ph.points]


def bsm_to_record(bsm: BSM, full: bool = False) -> dict[str, Any]:
    """The flat record of ``bsm`` (``full`` adds every other field)."""
    rec: dict[str, Any] = {
        "msgCnt": bsm.msg_cnt, "id": bsm.id_hex, "secMark": bsm.sec_mark,
        "lat": _r(bsm.lat, "lat"), "lon": _r(bsm.lon, "lon"), "elev": _r(bsm.elev, "elev"),
        "speed": _r(bsm.speed, "speed"), "heading": _r(bsm.heading, "heading"),
        "accel_long": _r(bsm.accel_long, "accel_long"),
        "accel_lat": _r(bsm.accel_lat, "accel_lat"),
        "accel_vert": _r(bsm.accel_vert, "accel_vert"),
        "yaw_rate": _r(bsm.yaw_rate, "yaw_rate"),
        "width": _r(bsm.width, "width"), "length": _r(bsm.length, "length"),
    }
    if full:
        pp = bsm.path_prediction
        rec.update({
            "accuracy": _accuracy(bsm.accuracy),
            "transmission": None if bsm.transmission is None else bsm.transmission.name.lower(),
            "steering_angle": _r(bsm.steering_angle, "steering_angle"),
            "brakes": _brakes(bsm.brakes),
            "path_history": None if bsm.path_history is None else
            _path_history(bsm.path_history),
            "path_prediction": None if pp is None else {
                "radius_of_curve": None if math.isinf(pp.radius_of_curve) else
                _r(pp.radius_of_curve, "radius_of_curve"),
                "straight": math.isinf(pp.radius_of_curve),
                "confidence": _r(pp.confidence, "confidence")},
            "events": None if bsm.events is None else f"{bsm.events.value:0{bsm.events.size}b}",
            "lights": None if bsm.lights is None else f"{bsm.lights.value:0{bsm.lights.size}b}",
            "part2_other_ids": [pid for pid, _ in bsm.part2_other],
        })
    return rec


def _opt(rec: dict, key: str) -> float | None:
    value = rec.get(key)
    return None if value is None else float(value)


def bsm_from_record(rec: dict[str, Any]) -> BSM:
    """A :class:`BSM` from a flat record (the :data:`KEYS`; missing keys are unavailable).

    Raises ``ValueError`` naming the key when a value has the wrong type.
    """
    try:
        temp_id = int(str(rec["id"]), 16)
        return BSM(
            msg_cnt=int(rec.get("msgCnt", 0)), temp_id=temp_id,
            sec_mark=None if rec.get("secMark") is None else int(rec["secMark"]),
            lat=_opt(rec, "lat"), lon=_opt(rec, "lon"), elev=_opt(rec, "elev"),
            speed=_opt(rec, "speed"), heading=_opt(rec, "heading"),
            accel_long=_opt(rec, "accel_long"), accel_lat=_opt(rec, "accel_lat"),
            accel_vert=_opt(rec, "accel_vert"), yaw_rate=float(rec.get("yaw_rate") or 0.0),
            width=_opt(rec, "width"), length=_opt(rec, "length"),
        )
    except KeyError as exc:
        raise ValueError(f"record has no {exc.args[0]!r} key") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f"bad value in record: {exc}") from None
