"""BSMs from the USDOT JPO ODE's decoded JSON (``J2735Bsm``), as the ODE writes them.

The ODE publishes decoded BSMs with SI values: degrees, metres, m/s, m/s², deg/s,
seconds for path-history time offsets, but centimetres for the vehicle size.  Its
quirks, seen in the jpo-ode test data, are handled here:

* "unavailable" is written as ``null``, as the string ``"UNAVAILABLE"`` (transmission),
  or the key is left out (accuracy orientation);
* a straight path prediction (RadiusOfCurvature 32767) is written as ``0.0``;
  a radius of 0 m is meaningless, so ``0.0`` reads as straight (``inf``);
* VerticalAcceleration is written in G (J2735's 0.02 G units times 0.02);
* Part II ids are ``"VehicleSafetyExtensions"`` or ``"VEHICLESAFETYEXT"``.

Part II content other than VehicleSafetyExtensions is not rebuilt (the ODE JSON
does not carry its encoding).
"""

from __future__ import annotations

import math
from typing import Any

from catc.bsm import (
    BSM,
    AuxBrakes,
    BrakeBoost,
    BrakeStatus,
    ControlStatus,
    PathHistory,
    PathHistoryPoint,
    PathPrediction,
    PositionalAccuracy,
    TransmissionState,
)
from catc.errors import DecodeError
from catc.units import G0

_WHEELS = ("unavailable", "leftFront", "leftRear", "rightFront", "rightRear")
_VSE_IDS = {"VehicleSafetyExtensions", "VEHICLESAFETYEXT"}


def _f(x: Any) -> float | None:
    return None if x is None else float(x)


def _accuracy(d: dict | None) -> PositionalAccuracy | None:
    if d is None:
        return None
    return PositionalAccuracy(_f(d.get("semiMajor")), _f(d.get("semiMinor")),
                              _f(d.get("orientation")))


def _transmission(name: str | None) -> TransmissionState | None:
    if name is None or name.upper() == "UNAVAILABLE":
        return None
    key = name.upper().replace("_", "").replace("GEARS", "_GEARS")
    return TransmissionState[key]


def _brakes(d: dict) -> BrakeStatus:
    wheels = d.get("wheelBrakes") or {}
    mask = sum(1 << (4 - i) for i, name in enumerate(_WHEELS) if wheels.get(name))
    return BrakeStatus(
        wheel_brakes=mask,
        traction=ControlStatus[d.get("traction", "unavailable").upper()],
        abs=ControlStatus[d.get("abs", "unavailable").upper()],
        scs=ControlStatus[d.get("scs", "unavailable").upper()],
        brake_boost=BrakeBoost[d.get("brakeBoost", "unavailable").upper()],
        aux_brakes=AuxBrakes[d.get("auxBrakes", "unavailable").upper()],
    )


def _vse(value: dict) -> dict:
    out: dict = {}
    ph = value.get("pathHistory")
    if ph is not None:
        points = tuple(
            PathHistoryPoint(
                lat_offset=_f(p.get("latOffset")), lon_offset=_f(p.get("lonOffset")),
                elev_offset=_f(p.get("elevationOffset")), time_offset=_f(p.get("timeOffset")),
                speed=_f(p.get("speed")), accuracy=_accuracy(p.get("posAccuracy")),
                heading=_f(p.get("heading")))
            for p in ph.get("crumbData") or ())
        out["path_history"] = PathHistory(points=points)
    pp = value.get("pathPrediction")
    if pp is not None:
        radius = float(pp["radiusOfCurve"])
        out["path_prediction"] = PathPrediction(math.inf if radius == 0.0 else radius,
                                                float(pp["confidence"]))
    return out


def bsm_from_ode(data: dict) -> BSM:
    """A :class:`BSM` from an ODE ``J2735Bsm`` object (``payload.data`` of a record).

    Raises :class:`DecodeError` when the object is not a decoded BSM.
    """
    try:
        core = data["coreData"]
        pos = core["position"]
        accel = core.get("accelSet") or {}
        size = core.get("size") or {}
        vert = accel.get("accelVert")
        fields: dict = {}
        for part in data.get("partII") or ():
            if part.get("id") in _VSE_IDS:
                fields.update(_vse(part.get("value") or {}))
        return BSM(
            msg_cnt=int(core["msgCnt"]),
            temp_id=int(core["id"], 16),
            sec_mark=None if core.get("secMark") is None else int(core["secMark"]),
            lat=_f(pos.get("latitude")), lon=_f(pos.get("longitude")),
            elev=_f(pos.get("elevation")),
            speed=_f(core.get("speed")), heading=_f(core.get("heading")),
            accuracy=_accuracy(core.get("accuracy")) or PositionalAccuracy(),
            transmission=_transmission(core.get("transmission")),
            steering_angle=_f(core.get("angle")),
            accel_long=_f(accel.get("accelLong")), accel_lat=_f(accel.get("accelLat")),
            accel_vert=None if vert is None else float(vert) * G0,
            yaw_rate=float(accel.get("accelYaw") or 0.0),
            brakes=_brakes(core.get("brakes") or {}),
            width=None if size.get("width") is None else size["width"] / 100.0,
            length=None if size.get("length") is None else size["length"] / 100.0,
            **fields,
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise DecodeError("garbage", f"not an ODE J2735Bsm object ({exc!r})") from None
