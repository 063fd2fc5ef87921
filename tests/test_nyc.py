"""Tests for catc.datasets.nyc: the NYC CV pilot event JSON reader.

The real FCW event is read from ../shared/data/cv-pilot-samples (skipped when absent).
The axis convention, the yaw sign and the time stamps are checked on the raw JSON,
independently of the reader, and then the table is checked against them.  Synthetic
events pin the exact resampling, duplicate/gap handling, brakes and error messages.
"""

from __future__ import annotations

import functools
import json
from typing import Any

import numpy as np
import pytest

from catc import datasets
from catc.datasets import derive, nyc
from catc.geo import EnuFrame, heading_diff_deg
from catc.mobility import DT, MobilityTable, Track
from tests.conftest import shared_path
from tests.test_datasets import synthetic_ngsim, synthetic_openacc

EVENT = ("cv-pilot-samples", "nycdot-fcw-event.json")
HOST, TARGET = "C7D30386", "A305214A"
ARRAYS = ("t", "x", "y", "lat", "lon", "elev", "speed", "heading", "accel", "yaw_rate")


@functools.cache
def _text() -> str:
    return shared_path(*EVENT).read_text()


@functools.cache
def table() -> MobilityTable:
    return nyc.parse(_text(), "fcw")


@functools.cache
def raw(vehicle_id: str) -> dict[str, np.ndarray]:
    """One vehicle's coreData fields from the raw JSON, in T_s order, exact duplicates of
    T_s removed (parsed without catc)."""
    cores = [item["bsmRecord"]["bsmMsg"]["coreData"] for item in json.loads(_text())["bsmList"]]
    cores = sorted((c for c in cores if c["id"] == vehicle_id), key=lambda c: c["T_s"])
    out = {k: np.array([c[k] for c in cores]) for k in ("T_s", "X_m", "Y_m", "Z_m",
                                                         "speed_mps", "heading_deg")}
    out["yaw_dps"] = np.array([c["accelSet"]["yaw_dps"] for c in cores])
    keep = np.r_[True, np.diff(out["T_s"]) > 0]
    return {k: v[keep] for k, v in out.items()}


def _index(track: Track, t: float) -> int:
    (i,) = np.flatnonzero(np.abs(track.t - t) < 1e-9)
    return int(i)


# --- the real event: conventions measured on the raw data --------------------------------------


@pytest.mark.parametrize("vehicle_id", [HOST, TARGET])
def test_x_is_east_and_y_is_north(vehicle_id: str) -> None:
    """The direction of motion between consecutive positions, atan2(dX, dY) clockwise from
    north, is heading_deg (median 0.17-0.18 deg); with the axes swapped it is 17-20 deg off."""
    r = raw(vehicle_id)
    dx, dy = np.diff(r["X_m"]), np.diff(r["Y_m"])
    moving = np.hypot(dx, dy) / np.diff(r["T_s"]) > 1.0
    heading = r["heading_deg"][1:][moving]
    east_north = np.degrees(np.arctan2(dx, dy))[moving]
    swapped = np.degrees(np.arctan2(dy, dx))[moving]
    assert moving.sum() > 150
    assert np.median(np.abs(heading_diff_deg(east_north, heading))) < 5.0
    assert np.median(np.abs(heading_diff_deg(swapped, heading))) > 10.0
    # The reader keeps the convention: the heading of its x/y track is the measured heading.
    track = table().tracks[vehicle_id]
    from_track = derive.heading_from_track(track.x, track.y, np.full(len(track), 20.0))
    assert np.median(np.abs(heading_diff_deg(from_track, track.heading))) < 1.0


def test_positions_are_metres() -> None:
    """The host's positions advance at its broadcast speed (ratio 1.015 measured)."""
    track = table().tracks[HOST]
    ratio = table().meta["track_speed"][HOST][10:-10] / track.speed[10:-10]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.03)


@pytest.mark.parametrize("vehicle_id", [HOST, TARGET])
def test_yaw_dps_is_positive_clockwise(vehicle_id: str) -> None:
    """yaw_dps follows the heading change over 1 s (correlation 0.997 host, 0.986 target)
    with a positive slope near 1: positive means heading increasing (clockwise)."""
    r = raw(vehicle_id)
    heading = np.degrees(np.unwrap(np.radians(r["heading_deg"])))
    n = 10
    rate = (heading[n:] - heading[:-n]) / (r["T_s"][n:] - r["T_s"][:-n])
    yaw = np.convolve(r["yaw_dps"], np.ones(n + 1) / (n + 1), mode="valid")
    assert np.corrcoef(rate, yaw)[0, 1] > 0.95
    slope = np.polyfit(rate, yaw, 1)[0]
    assert 0.7 < slope < 1.3
    track = table().tracks[vehicle_id]
    assert np.corrcoef(track.yaw_rate, derive.yaw_rate_from_heading(track.heading))[0, 1] > 0.9
    assert "positive clockwise" in track.provenance["yaw_rate"]


def test_time_stamps_per_vehicle() -> None:
    """Each vehicle steps by 0.1 s on its own phase; the host exactly, the target within 1 ms."""
    meta = table().meta
    assert meta["time_offset"][HOST] == pytest.approx(-0.034, abs=1e-9)
    assert meta["time_offset"][TARGET] == pytest.approx(-0.015, abs=1e-9)
    assert meta["time_jitter"][HOST] < 1e-9
    assert meta["time_jitter"][TARGET] == pytest.approx(0.001, abs=1e-9)
    for vehicle_id in (HOST, TARGET):
        steps = np.diff(raw(vehicle_id)["T_s"])
        # Missing BSMs (0.2 s steps): two of the host's, one of the target's.
        assert np.count_nonzero(np.abs(steps - DT) > 0.002) == 1 + (vehicle_id == HOST)


# --- the real event: the table -----------------------------------------------------------------


def test_real_event_table() -> None:
    tab = table()
    assert (tab.name, tab.kind, tab.origin) == ("fcw", "nyc", nyc.ORIGIN)
    assert list(tab.tracks) == [TARGET, HOST] and tab.default_host == HOST
    host, target = tab.tracks[HOST], tab.tracks[TARGET]
    for track in (host, target):
        assert len(track) == 160
        for name in ARRAYS:
            values = getattr(track, name)
            assert values.shape == (160,) and np.isfinite(values).all(), name
        assert np.all(np.diff(track.t) > 0)
        np.testing.assert_allclose(np.diff(track.t), DT, atol=1e-9)
        np.testing.assert_allclose(track.t / DT, np.round(track.t / DT), atol=1e-9)
        assert track.t[0] == pytest.approx(-6.6) and track.t[-1] == pytest.approx(9.3)
        assert set(track.provenance) >= {*ARRAYS, "length", "width"}
        assert "interpolated" in track.provenance["x"]
        assert track.accel.min() > -0.5 and track.accel.max() < 0.5
    np.testing.assert_array_equal(host.t, target.t)  # same instants: no interpolation needed
    assert (host.length, host.width, target.length, target.width) == (7.82, 2.11, 5.49, 2.16)
    assert 0.0 in host.t.tolist()


def test_real_event_at_the_warning() -> None:
    """T = 0: host 21.9 m/s, target broadcasting 5.68 m/s (but moving at ~22.3), 40.94 m
    apart (reference points; ~34.3 m bumper to bumper)."""
    tab = table()
    host, target = tab.tracks[HOST], tab.tracks[TARGET]
    i = _index(host, tab.meta["trigger_t"])
    assert host.t[i] == 0.0 and target.t[i] == 0.0
    # Host BSMs at -0.034 s (-3.460, -2.781) and 0.066 s (-1.722, -1.390): 34 % of the way.
    assert (host.x[i], host.y[i]) == pytest.approx((-3.460 + 0.34 * 1.738, -2.781 + 0.34 * 1.391))
    assert (target.x[i], target.y[i]) == pytest.approx((28.178 + 0.15 * 1.806,
                                                        23.867 + 0.15 * 1.290))
    assert host.speed[i] == pytest.approx(21.9) and target.speed[i] == pytest.approx(5.68)
    gap = np.hypot(host.x[i] - target.x[i], host.y[i] - target.y[i])
    assert gap == pytest.approx(40.94, abs=0.01)
    assert tab.meta["track_speed"][TARGET][i] == pytest.approx(22.3, abs=0.2)
    assert "CONSTANT 5.68 m/s" in target.provenance["speed"]
    assert "CONSTANT" not in host.provenance["speed"]


def test_real_event_meta() -> None:
    meta = table().meta
    assert meta["event_type"] == "fcw" and meta["alert_sent"] is True
    assert (meta["trigger_hv_seq"], meta["trigger_tv_seq"]) == (5233, 4431)
    assert meta["parameters"]["timeToCrash"] == "1"
    assert meta["header"]["hostVehID"] == HOST and meta["trigger_t"] == 0.0
    assert meta["trigger_bsm_t"] == {HOST: 0.166, TARGET: 0.185}
    # The host's trigger BSM is the origin of X/Y/Z (DataProcessing.txt).
    r = raw(HOST)
    (k,) = np.flatnonzero(r["T_s"] == 0.166)
    assert (r["X_m"][k], r["Y_m"][k], r["Z_m"][k]) == (0.0, 0.0, 0.0)
    for vehicle_id in (HOST, TARGET):
        brakes = meta["brakes"][vehicle_id]
        assert brakes.dtype == bool and brakes.shape == (160,) and not brakes.any()
    assert meta["dropped"] == []


def test_real_event_georeference() -> None:
    frame = EnuFrame(*nyc.ORIGIN)
    for vehicle_id, track in table().tracks.items():
        e, n, u = frame.to_enu(track.lat, track.lon, track.elev)
        np.testing.assert_allclose(np.c_[e, n], np.c_[track.x, track.y], atol=1e-6)
        r = raw(vehicle_id)  # up is Z_m (interpolated like x and y)
        np.testing.assert_allclose(u, np.interp(track.t, r["T_s"], r["Z_m"]), atol=1e-6)
        assert np.abs(track.lat - nyc.ORIGIN[0]).max() < 0.01
        assert np.abs(track.lon - nyc.ORIGIN[1]).max() < 0.01
        assert np.abs(track.elev).max() < 10


def test_real_event_detection_and_dispatch() -> None:
    assert datasets.detect_kind(_text()) == "nyc"
    (tab,) = datasets.parse("nyc", _text(), "x")
    assert tab.kind == "nyc" and tab.name == "x"
    for other in ("wydot-filtered-bsm-schemaVersion6.json",
                  "thea-filtered-bsm-schemaVersion1.json"):
        assert datasets.detect_kind(shared_path("cv-pilot-samples", other).read_text()) is None


# --- synthetic events ---------------------------------------------------------------------------


def bsm(vid: str, seq: int, t: float, x: float, y: float = 0.0, **core: Any) -> dict[str, Any]:
    """One bsmList item; ``core`` overrides coreData fields (None deletes one)."""
    data: dict[str, Any] = {
        "msgCnt": seq % 128, "id": vid, "X_m": x, "Y_m": y, "Z_m": 0.0, "T_s": t,
        "speed_mps": 10.0, "heading_deg": 90.0,
        "accelSet": {"long_mpss": 0.1, "lat_mpss": 0.0, "vert_mpss": 0.0, "yaw_dps": 0.0},
        "brakes": {"wheelBrakes": "00", "traction": "unavailable"},
        "size": {"width": 180, "length": 450},
    }  # fmt: skip
    for key, value in core.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    return {"eventMsgSeqNum": seq, "bsmRecord": {"bsmMsg": {"coreData": data}}}


def drive(vid: str, phase: float, x0: float, v: float, n: int = 21, **core: Any) -> list[dict]:
    return [bsm(vid, 100 + k, round(phase + k * DT, 3), x0 + v * (phase + k * DT), **core)
            for k in range(n)]


def event(items: list[dict], **header: Any) -> str:
    head = {"hostVehID": "H", "targetVehID": "T", "eventType": "fcw", "eventAlertSent": True,
            "triggerHVSeqNum": 110, "triggerTVSeqNum": 110, **header}
    return json.dumps({"eventHeader": head, "bsmList": items})


def interleave(*lists: list[dict]) -> list[dict]:
    return [item for group in zip(*lists, strict=True) for item in group]


def test_synthetic_resampling_is_exact_for_linear_motion() -> None:
    host = drive("H", -1.034, 0.0, 10.0)
    target = drive("T", -1.015, 50.0, 5.0, size={"width": 200, "length": 500})
    tab = nyc.parse(event(interleave(host, target)), "s")
    assert list(tab.tracks) == ["T", "H"] and tab.default_host == "H"
    h, t = tab.tracks["H"], tab.tracks["T"]
    np.testing.assert_allclose(h.t, np.arange(-10, 10) * DT, atol=1e-12)
    np.testing.assert_array_equal(h.t, t.t)
    np.testing.assert_allclose(h.x, 10.0 * h.t, atol=1e-9)
    np.testing.assert_allclose(t.x, 50.0 + 5.0 * t.t, atol=1e-9)
    np.testing.assert_allclose(h.heading, 90.0)
    np.testing.assert_allclose(h.accel, 0.1)
    assert (t.length, t.width, h.length, h.width) == (5.0, 2.0, 4.5, 1.8)
    assert tab.meta["trigger_bsm_t"] == {"H": pytest.approx(-0.034), "T": pytest.approx(-0.015)}
    assert tab.meta["track_speed"]["H"] == pytest.approx(np.full(20, 10.0))
    # The speed is constant at the position speed: not flagged as stuck.
    assert "CONSTANT" not in h.provenance["speed"]
    assert "CONSTANT 10 m/s" in nyc.parse(
        event(interleave(drive("H", -1.034, 0.0, 20.0), target)), "s"
    ).tracks["H"].provenance["speed"]


def test_synthetic_heading_wraps_through_north() -> None:
    items = [bsm("H", k, -1.03 + k * DT, k * 1.0, heading_deg=(355.0 + k) % 360.0,
                 accelSet={"long_mpss": 0.0, "yaw_dps": 10.0}) for k in range(21)]
    track = nyc.parse(event(items, targetVehID=None), "s").tracks["H"]
    expected = (355.0 + (track.t + 1.03) / DT) % 360.0
    np.testing.assert_allclose(heading_diff_deg(track.heading, expected), 0.0, atol=1e-9)
    assert track.heading.min() >= 0.0 and track.heading.max() < 360.0
    np.testing.assert_allclose(track.yaw_rate, 10.0)


def test_synthetic_duplicates_gaps_and_pieces() -> None:
    host = drive("H", -1.034, 0.0, 10.0, n=41)
    host.insert(12, bsm("H", 112, host[11]["bsmRecord"]["bsmMsg"]["coreData"]["T_s"], 99.0))
    del host[5:8]  # 3 missing BSMs: bridged
    target = drive("T", -1.015, 50.0, 5.0, n=41)
    del target[25:33]  # 8 missing BSMs after T = 0: the piece with T = 0 is kept
    other = [bsm("O", 1, 0.5, 3.0)]  # one BSM: covers no grid instant, dropped
    tab = nyc.parse(event(host + other + target), "s")
    h, t = tab.tracks["H"], tab.tracks["T"]
    np.testing.assert_allclose(h.x, 10.0 * h.t, atol=1e-9)  # the duplicate's 99 m is dropped
    assert h.t[0] == pytest.approx(-1.0) and h.t[-1] == pytest.approx(2.9) and len(h) == 40
    assert "dropped: 1" in h.provenance["samples"] and "bridged: 1" in h.provenance["samples"]
    assert t.t[0] == pytest.approx(-1.0) and t.t[-1] == pytest.approx(1.3)
    np.testing.assert_allclose(t.x, 50.0 + 5.0 * t.t, atol=1e-9)
    assert list(tab.tracks) == ["T", "H"] and tab.meta["dropped"] == ["O"]


@pytest.mark.parametrize(("code", "applied"), [("00", False), ("80", False), ("40", True),
                                               ("08", True), ("F8", True)])
def test_synthetic_wheel_brakes(code: str, applied: bool) -> None:
    items = drive("H", -1.034, 0.0, 10.0)
    items[10]["bsmRecord"]["bsmMsg"]["coreData"]["brakes"] = {"wheelBrakes": code}
    brakes = nyc.parse(event(items, targetVehID=None), "s").meta["brakes"]["H"]
    # BSM 10 is at -0.034 s: nearest to the grid instant 0.0 only.
    assert brakes.tolist() == [False] * 10 + [applied] + [False] * 9


def test_meta_defaults_to_an_empty_dict_per_table() -> None:
    a = MobilityTable("a", "x", (0.0, 0.0, 0.0), {})
    b = MobilityTable("b", "x", (0.0, 0.0, 0.0), {})
    assert a.meta == {} and a.meta is not b.meta


def test_detect_kind_keeps_the_other_kinds() -> None:
    items = interleave(drive("H", -1.034, 0.0, 10.0), drive("T", -1.015, 50.0, 5.0))
    assert datasets.detect_kind(event(items)) == "nyc"
    assert datasets.detect_kind("\ufeff  " + event(items)) == "nyc"
    assert datasets.detect_kind(synthetic_openacc()) == "openacc"
    assert datasets.detect_kind(synthetic_ngsim()) == "ngsim"
    assert "nyc" in datasets.KINDS
    for other in ('{"eventHeader": {}}', '{"eventHeader": 1, "bsmList": [', "[]",
                  '["eventHeader", "bsmList"]', '{"bsmList": [], "x": "eventHeader"}'):
        assert datasets.detect_kind(other) is None


# --- errors --------------------------------------------------------------------------------------

_OK = interleave(drive("H", -1.034, 0.0, 10.0), drive("T", -1.015, 50.0, 5.0))


def _with(i: int, **core: Any) -> list[dict]:
    items = json.loads(json.dumps(_OK))
    old = items[i]["bsmRecord"]["bsmMsg"]["coreData"]
    items[i] = bsm(old["id"], items[i]["eventMsgSeqNum"], old["T_s"], old["X_m"], **core)
    return items


BAD = [
    ("{not json", "nyc event: not JSON"),
    ("[1, 2]", "nyc event: not a JSON object with eventHeader and bsmList"),
    (event([]), "nyc event: bsmList is not a non-empty list"),
    (event(_OK, hostVehID=None), "nyc event: eventHeader has no hostVehID"),
    (event(_with(12, X_m=None)), "nyc event: bsmList item 12 has no coreData.X_m"),
    (event(_with(3, T_s="0.1")), r"nyc event: bsmList item 3 coreData.T_s is not a number"),
    (event(_with(4, accelSet={"long_mpss": 0.0})),
     "nyc event: bsmList item 4 has no coreData.accelSet.yaw_dps"),
    (event(_with(5, heading_deg=360.0)), r"item 5 coreData.heading_deg = 360 is outside"),
    (event(_with(6, speed_mps=163.82)), r"item 6 coreData.speed_mps = 163.82 is outside"),
    (event(_with(7, brakes={"wheelBrakes": "zz"})),
     "item 7 coreData.brakes.wheelBrakes is not a one-byte hex string"),
    (event(_with(8, brakes={"wheelBrakes": "01"})), "sets padding bits"),
    (event(_with(9, id=None)), "nyc event: bsmList item 9 has no coreData.id"),
    (event([*_OK, {"eventMsgSeqNum": 1}]), "item 42 has no bsmRecord.bsmMsg.coreData"),
    (event(_OK, targetVehID="X"), "nyc event: targetVehID X has no BSM in bsmList"),
    (event(_OK, hostVehID="X"), "nyc event: hostVehID X has no BSM in bsmList"),
    (event([bsm("H", 1, 0.01, 0.0), bsm("H", 2, 0.02, 0.0)], targetVehID=None),
     "vehicle H has no two BSMs around a 0.1 s grid instant"),
]


@pytest.mark.parametrize(("text", "message"), BAD)
def test_malformed_events(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message) as err:
        nyc.parse(text, "bad")
    assert "\n" not in str(err.value)
