"""Helpers for comparing decoded BSMs with independent expectations."""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET

from catc.bsm import BSM


def assert_close(actual, expected, path: str = "bsm", tol: float = 1e-9) -> None:
    """Recursive equality of dataclasses/tuples with a tolerance on floats."""
    if dataclasses.is_dataclass(expected):
        assert type(actual) is type(expected), f"{path}: {type(actual)} != {type(expected)}"
        for f in dataclasses.fields(expected):
            assert_close(getattr(actual, f.name), getattr(expected, f.name), f"{path}.{f.name}",
                         tol)
    elif isinstance(expected, tuple) and not isinstance(expected, int):
        assert isinstance(actual, tuple) and len(actual) == len(expected), \
            f"{path}: {actual!r} != {expected!r}"
        for i, (a, e) in enumerate(zip(actual, expected, strict=True)):
            assert_close(a, e, f"{path}[{i}]", tol)
    elif isinstance(expected, float) and not isinstance(actual, bool):
        assert actual is not None, f"{path}: None != {expected!r}"
        if math.isinf(expected):
            assert actual == expected, f"{path}: {actual!r} != {expected!r}"
        else:
            assert math.isclose(actual, expected, rel_tol=0, abs_tol=tol), \
                f"{path}: {actual!r} != {expected!r}"
    else:
        assert actual == expected, f"{path}: {actual!r} != {expected!r}"


def assert_same_except_extras(actual: BSM, expected: BSM) -> None:
    """Compare what the ODE JSON carries: everything but opaque Part II and events/lights."""
    assert_close(
        dataclasses.replace(actual, part2_other=(), regional=(), events=None, lights=None,
                            vse_position=None),
        expected,
    )


# --- XER (the ODE's asn1c decoder output): raw integers, scaled here with literal LSBs -----

def _int(elem: ET.Element, tag: str) -> int:
    found = elem.find(tag)
    assert found is not None, f"XER has no <{tag}>"
    return int(found.text)


def _opt(raw: int, unavailable: int | None, lsb: float) -> float | None:
    return None if raw == unavailable else raw * lsb


def expected_from_xer(bsm_elem: ET.Element) -> dict:
    """The SI values a correct decoder must give for an XER <BasicSafetyMessage>.

    Scales are written out here, independently of catc.units.
    """
    core = bsm_elem.find("coreData")
    acc = core.find("accuracy")
    accel = core.find("accelSet")
    size = core.find("size")
    out = {
        "msg_cnt": _int(core, "msgCnt"),
        "id_hex": core.find("id").text.strip().upper(),
        "sec_mark": _opt(_int(core, "secMark"), 65535, 1),
        "lat": _opt(_int(core, "lat"), 900000001, 1e-7),
        "lon": _opt(_int(core, "long"), 1800000001, 1e-7),
        "elev": _opt(_int(core, "elev"), -4096, 0.1),
        "semi_major": _opt(_int(acc, "semiMajor"), 255, 0.05),
        "semi_minor": _opt(_int(acc, "semiMinor"), 255, 0.05),
        "orientation": _opt(_int(acc, "orientation"), 65535, 360 / 65535),
        "transmission": core.find("transmission")[0].tag,
        "speed": _opt(_int(core, "speed"), 8191, 0.02),
        "heading": _opt(_int(core, "heading"), 28800, 0.0125),
        "steering_angle": _opt(_int(core, "angle"), 127, 1.5),
        "accel_long": _opt(_int(accel, "long"), 2001, 0.01),
        "accel_lat": _opt(_int(accel, "lat"), 2001, 0.01),
        "accel_vert": _opt(_int(accel, "vert"), -127, 0.02 * 9.80665),
        "yaw_rate": _int(accel, "yaw") * 0.01,
        "wheel_brakes": int(core.find("brakes/wheelBrakes").text, 2),
        "width": _opt(_int(size, "width"), 0, 0.01),
        "length": _opt(_int(size, "length"), 0, 0.01),
        "points": [],
        "radius": None,
        "part2_ids": [int(p.text) for p in bsm_elem.iter("partII-Id")],
    }
    for p in bsm_elem.iter("PathHistoryPoint"):
        out["points"].append((
            _opt(_int(p, "latOffset"), -131072, 1e-7),
            _opt(_int(p, "lonOffset"), -131072, 1e-7),
            _opt(_int(p, "elevationOffset"), -2048, 0.1),
            _opt(_int(p, "timeOffset"), 65535, 0.01),
        ))
    pp = bsm_elem.find(".//pathPrediction")
    if pp is not None:
        radius = _int(pp, "radiusOfCurve")
        out["radius"] = (math.inf if radius == 32767 else radius * 0.1,
                         _int(pp, "confidence") * 0.5)
    return out


def assert_matches_xer(bsm: BSM, bsm_elem: ET.Element) -> None:
    exp = expected_from_xer(bsm_elem)
    transmission = exp.pop("transmission")
    assert (bsm.transmission is None) == (transmission == "unavailable")
    assert bsm.id_hex == exp.pop("id_hex")
    assert bsm.brakes.wheel_brakes == exp.pop("wheel_brakes")
    points = exp.pop("points")
    radius = exp.pop("radius")
    part2_ids = exp.pop("part2_ids")
    got = {
        **{k: getattr(bsm, k) for k in exp if hasattr(bsm, k)},
        "semi_major": bsm.accuracy.semi_major,
        "semi_minor": bsm.accuracy.semi_minor,
        "orientation": bsm.accuracy.orientation,
    }
    for key, value in exp.items():
        if value is None:
            assert got[key] is None, f"{key}: {got[key]!r} should be unavailable"
        else:
            assert got[key] is not None and math.isclose(got[key], value, abs_tol=1e-9), \
                f"{key}: {got[key]!r} != {value!r}"
    ph = bsm.path_history.points if bsm.path_history else ()
    assert len(ph) == len(points)
    for p, e in zip(ph, points, strict=True):
        assert_close((p.lat_offset, p.lon_offset, p.elev_offset, p.time_offset), e)
    if radius is not None:
        assert_close((bsm.path_prediction.radius_of_curve, bsm.path_prediction.confidence),
                     radius)
    assert list(bsm.part2_ids) == part2_ids
