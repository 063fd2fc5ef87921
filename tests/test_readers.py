"""The BSM-log readers: spmd (SPMD BSM CSV) and ode (ODE JSON, OBU .bin logs), and loading them.

No real SPMD file is available: the spmd tests write one from a real OpenACC track (a
round trip) and hand-write the quirks.  The ode tests read the real ODE test vectors and
WYDOT samples in ../shared/data (skipped with the reason when absent).
"""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime

import numpy as np
import pytest

from catc import datasets
from catc.datasets import ode, openacc, spmd
from catc.geo import EnuFrame
from catc.j2735 import decode_frame, obulog
from catc.mobility import DT, Track
from hil.datasets import DatasetError, load, load_files
from tests.conftest import shared_path

#: Gentime (us since 2004-01-01 UTC) of 2013-04-11 14:02:00 UTC, a minute start.
G0 = round((datetime(2013, 4, 11, 14, 2, tzinfo=UTC)
            - datetime(2004, 1, 1, tzinfo=UTC)).total_seconds()) * 1_000_000
#: J2735 units the written file is quantised to (SI per unit).
SPEED_U, HEADING_U, ACCEL_U, YAW_U = 0.02, 0.0125, 0.01, 0.01


def q(value: float, unit: float) -> float:
    return round(value / unit) * unit


def spmd_rows(track: Track, *, device: str = "1234", start_ms: int = 17_300,
              jitter_us: np.ndarray | None = None) -> list[str]:
    """``track`` as SPMD BSM rows (logged by the sender itself), first BSM at ``start_ms``."""
    rows = []
    for i in range(len(track)):
        offset = round((track.t[i] - track.t[0]) * 1e6) + start_ms * 1000
        gentime = G0 + offset + (0 if jitter_us is None else int(jitter_us[i]))
        dsecond = (gentime - G0) // 1000 % 60000
        rows.append(
            f"{device},7,{device},{gentime},0,{i % 128},{dsecond},{track.lat[i]:.7f},"
            f"{track.lon[i]:.7f},{track.elev[i]:.1f},{q(track.speed[i], SPEED_U):.2f},"
            f"{q(track.heading[i], HEADING_U) % 360:.4f},{q(track.accel[i], ACCEL_U):.2f},"
            f"0.00,0.00,{q(track.yaw_rate[i], YAW_U):.2f},15,0.0,0")
    return rows


def openacc_table(file: str = "short_setting_dynamic_part1.csv"):
    return openacc.parse(shared_path("openacc-zalazone", file).read_text(), file)


def vectors(name: str) -> bytes:
    return shared_path("jpo-ode-bsm-vectors", name).read_bytes()


# --- spmd -----------------------------------------------------------------------------------


@pytest.mark.parametrize("header", [True, False])
def test_spmd_round_trip_of_a_real_openacc_track(header: bool):
    source = openacc_table()
    track = source.tracks["TESLA_MODELX"]  # 550 s, brakes at -5 m/s² to 0.12 m/s
    rows = spmd_rows(track)
    text = "\n".join(([",".join(spmd.COLUMNS)] if header else []) + rows) + "\n"
    assert datasets.detect_kind(text) == "spmd"
    (table,) = datasets.parse("spmd", text, "s")
    assert table.kind == "spmd" and table.name == "s:1234:1" and table.default_host is None
    assert table.meta["epoch_gentime_us"] == G0 and table.meta["time_offset"] == 0.0
    assert table.meta["duplicate_rows"] == 0 and table.meta["file_ids"] == ["7"]
    out = table.tracks["1234"]
    assert len(out) == len(track) == 5497
    np.testing.assert_allclose(out.t, 17.3 + track.t - track.t[0], atol=1e-9)
    # Positions within the 1e-7 deg rounding, in the source's frame.
    np.testing.assert_allclose(out.lat, track.lat, atol=0.51e-7)
    np.testing.assert_allclose(out.lon, track.lon, atol=0.51e-7)
    e, n, _ = EnuFrame(*source.origin).to_enu(out.lat, out.lon, out.elev)
    assert np.hypot(e - track.x, n - track.y).max() < 0.01
    e, n, _ = EnuFrame(*table.origin).to_enu(out.lat, out.lon, out.elev)
    np.testing.assert_allclose(np.c_[e, n], np.c_[out.x, out.y], atol=1e-6)
    # Speed, heading, Ax, Yawrate: measured, back within half a J2735 unit.
    assert np.abs(out.speed - track.speed).max() <= SPEED_U / 2 + 1e-9
    heading_err = (out.heading - track.heading + 180.0) % 360.0 - 180.0
    assert np.abs(heading_err).max() <= HEADING_U / 2 + 1e-6
    assert np.abs(out.accel - track.accel).max() <= ACCEL_U / 2 + 1e-9
    assert np.abs(out.yaw_rate - track.yaw_rate).max() <= YAW_U / 2 + 1e-9
    assert out.provenance["speed"].startswith("measured: Speed")
    assert out.provenance["yaw_rate"].startswith("measured: Yawrate")
    assert math.isnan(out.length) and math.isnan(out.width)


def test_spmd_irregular_times_are_resampled_onto_the_grid():
    track = openacc_table().tracks["TESLA_MODELX"]
    jitter = np.random.default_rng(3).integers(-5000, 5001, len(track))  # +-5 ms
    rows = spmd_rows(track, jitter_us=jitter)
    del rows[1000:1004]  # 0.5 s without BSMs: bridged
    (table,) = spmd.parse("\n".join(rows), "j")
    out = table.tracks["1234"]
    assert len(out) == len(track) and table.meta["time_offset"] == 0.0
    assert np.allclose(np.diff(out.t), DT)
    assert "bridged: 1" in out.provenance["samples"]
    e, n, _ = EnuFrame(*openacc_table().origin).to_enu(out.lat, out.lon, out.elev)
    # Off by at most speed x jitter (16.6 m/s x 5 ms) plus the bridged curvature.
    assert np.hypot(e - track.x, n - track.y).max() < 0.15
    assert np.abs(out.speed - track.speed).max() < 0.05


def quirk_rows() -> str:
    """Hand-written rows: duplicates, rows out of order, a missing cell, a missing position,
    a second trip 2 minutes later, and a 1 s gap inside a trip."""
    header = ",".join(spmd.COLUMNS)
    lon_step = 1.0 / (111_320 * math.cos(math.radians(42.3)))  # 1 m east per 0.1 s at 10 m/s

    def row(rx, file_id, device, k, *, base_ms=30_000, speed="10.00", lat="42.3000000"):
        gentime = G0 + (base_ms + 100 * k) * 1000
        dsecond = (base_ms + 100 * k) % 60000
        lon = f"{-83.7 + k * lon_step:.7f}"
        return (f"{rx},{file_id},{device},{gentime},77,{k % 128},{dsecond},{lat},{lon},"
                f"250.0,{speed},90.0000,0.00,0.00,0.00,0.00,10,0.0,0")

    lines = [header]
    lines += [row(101, 1, 101, k) for k in (0, 1, 2, 3, 4, 6, 5)]  # 6 before 5
    lines.append(row(205, 9, 101, 3, speed="99.00"))  # the same BSM logged by RxDevice 205
    lines.append(row(101, 1, 101, 7, speed=""))  # missing Speed
    lines += [row(101, 1, 101, k) for k in (9, 8)]
    lines.append(row(101, 1, 101, 10, lat=""))  # no position: dropped
    lines += [row(101, 2, 101, k, base_ms=150_000) for k in range(5)]  # the next trip
    lines += [row(102, 4, 102, k, base_ms=30_050) for k in (*range(5), *range(15, 20))]
    return "\n".join(lines) + "\n"


def test_spmd_quirks():
    tables = spmd.parse(quirk_rows(), "q")
    assert [t.name for t in tables] == ["q:101:1", "q:102:1", "q:101:2"]
    first, other, second = tables
    track = first.tracks["101"]
    assert list(first.tracks) == ["101"] and len(track) == 10
    np.testing.assert_allclose(track.t, 30.0 + 0.1 * np.arange(10), atol=1e-9)
    np.testing.assert_allclose(track.speed, 10.0)  # the first copy kept, the gap filled
    assert "unavailable in 1 of 10 BSMs" in track.provenance["speed"]
    assert np.all(np.diff(track.x) > 0.99) and np.all(np.diff(track.x) < 1.01)  # east, 1 m
    assert first.meta["duplicate_rows"] == 1 and first.meta["rows"] == 10
    assert first.meta["rx_devices"] == ["101"] and first.meta["file_ids"] == ["1"]
    # A trip two minutes later: its own table, its own minute epoch.
    assert len(second.tracks["101"]) == 5
    assert second.meta["epoch_gentime_us"] - first.meta["epoch_gentime_us"] == 120_000_000
    np.testing.assert_allclose(second.tracks["101"].t, 30.0 + 0.1 * np.arange(5), atol=1e-9)
    # A 1 s gap inside a trip splits the track; the grid keeps that sender's 50 ms phase.
    assert list(other.tracks) == ["102", "102#2"] and other.meta["time_offset"] == 0.05
    np.testing.assert_allclose(other.tracks["102#2"].t, 31.55 + 0.1 * np.arange(5), atol=1e-9)


def test_spmd_detection_and_errors():
    text = quirk_rows()
    assert spmd.looks_like(text)
    headerless = "\n".join(text.splitlines()[1:])
    assert datasets.detect_kind(headerless) == "spmd"
    assert [t.name for t in datasets.parse("spmd", headerless, "q")] == [
        "q:101:1", "q:102:1", "q:101:2"]
    for other in ("1,2,3\n", "RxDevice,x\n", "pair_id,time,x\n", "Date,1\n",
                  "1,2,3," * 6 + "4\n"):
        assert not spmd.looks_like(other)
    with pytest.raises(ValueError, match="spmd: header lacks Gentime"):
        spmd.parse("RxDevice,FileId,TxDevice,Latitude,Longitude\n1,1,1,42,-83\n", "x")
    with pytest.raises(ValueError, match="spmd: bad number in column Speed"):
        spmd.parse(text.replace("10.00", "fast", 1), "x")
    with pytest.raises(ValueError, match="spmd: no row has"):
        spmd.parse(",".join(spmd.COLUMNS) + "\n1,1,,5,,,,,,,,,,,,,,,\n", "x")


# --- ode: real files ----------------------------------------------------------------------


def test_ode_bsm_log_during_event_bin():
    data = vectors("bsmLogDuringEvent.bin")
    assert datasets.detect_kind(data) == "ode"
    (table,) = datasets.parse("ode", data, "ev")
    assert table.kind == "ode" and table.meta["container"] == "obulog:bsmLogDuringEvent"
    # Two vehicles; the logging vehicle (direction EV) is the host, listed last.
    assert list(table.tracks) == ["31325431", "31325433"]
    assert table.default_host == "31325433"
    assert table.meta["sources"] == {"31325433": ["EV"], "31325431": ["RV"]}
    assert table.meta["epoch_iso"] == "2018-05-01T16:04:00Z" and table.meta["bsms"] == 222
    for track in table.tracks.values():
        assert len(track) == 129  # 12.8 s at 10 Hz (93 and 129 BSMs)
        assert np.allclose(np.diff(track.t), DT)
        assert track.speed.max() < 1.0  # both nearly standing
        assert (track.length, track.width) == pytest.approx((5.7, 1.9))
    # Each grid instant is within 5 ms of a BSM of the host: its values are that BSM's.
    host = table.tracks["31325433"]
    own = [decode_frame(r.frame) for r in obulog.iter_records(data) if r.direction == "EV"]
    marks = {b.sec_mark: b for b in own}
    for i in range(0, len(host), 10):
        near = [m for m in marks if abs(m - host.t[i] * 1000) <= 5]
        assert near, host.t[i]
        bsm = marks[near[0]]
        assert abs(host.lat[i] - bsm.lat) < 2e-7 and abs(host.heading[i] - bsm.heading) < 1e-6


def test_ode_json_of_the_same_log_gives_the_same_table():
    text = shared_path("jpo-ode-bsm-vectors", "bsmLogDuringEvent.json").read_text()
    assert datasets.detect_kind(text) == "ode"
    (from_json,) = datasets.parse("ode", text, "ev")
    (from_bin,) = datasets.parse("ode", vectors("bsmLogDuringEvent.bin"), "ev")
    assert from_json.default_host == from_bin.default_host == "31325433"
    assert from_json.meta["epoch_utc"] == from_bin.meta["epoch_utc"]
    assert list(from_json.tracks) == list(from_bin.tracks)
    for vid, a in from_json.tracks.items():
        b = from_bin.tracks[vid]
        for name in ("t", "x", "y", "lat", "lon", "elev", "speed", "heading", "accel",
                     "yaw_rate"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-9,
                                       err_msg=f"{vid} {name}")


def test_ode_rx_msg_log_skips_the_non_bsm_frame():
    data = vectors("rxMsg_BSM.bin")
    (table,) = datasets.parse("ode", data, "rx")
    assert table.meta["container"] == "obulog:rxMsg"
    assert table.meta["skipped"] == {"not a BSM frame": 1} and table.meta["bsms"] == 227
    assert list(table.tracks) == ["FDCC0000"] and table.default_host is None
    track = table.tracks["FDCC0000"]
    assert len(track) == 232 and track.t[0] == pytest.approx(36.5)  # secMark 36500
    assert "bridged: 5" in track.provenance["samples"]  # 5 BSMs 0.2 s apart
    assert table.meta["epoch_iso"] == "2017-10-25T22:38:00Z"


def test_ode_bare_j2735bsm_lines_use_secmark_only():
    text = shared_path("jpo-ode-bsm-vectors", "128_bsms.json").read_text()
    assert datasets.detect_kind(text) == "ode"
    (table,) = datasets.parse("ode", text, "w")
    assert table.meta["time_source"] == "secmark" and table.meta["epoch_utc"] is None
    assert list(table.tracks) == ["BEA10000", "19BB0000"] and table.default_host is None
    # Every BSM is there twice, and 19BB0000 repeats some secMarks: dropped as repeats.
    assert table.meta["repeats"] == {"BEA10000": 32, "19BB0000": 36}
    for track in table.tracks.values():  # across the minute rollover (59.9 -> 0.0 s)
        assert track.t[0] < 60.0 < track.t[-1] and np.allclose(np.diff(track.t), DT)
    stuck = table.tracks["19BB0000"]  # its heading is unavailable in every BSM
    assert stuck.provenance["heading"].startswith("derived: direction")
    assert table.tracks["BEA10000"].provenance["heading"].startswith("measured")


@pytest.mark.parametrize(("version", "vid", "t0", "host"), [
    (3, "5B820000", 58.0, "5B820000"),  # a bsmTx record: the logging vehicle's own BSM
    (5, "CB950124", 28.589, None),
    (6, "CB950124", 28.589, None),
])
def test_ode_single_wydot_bsm(version: int, vid: str, t0: float, host: str | None):
    path = shared_path("cv-pilot-samples", f"wydot-filtered-bsm-schemaVersion{version}.json")
    text = path.read_text()
    assert datasets.detect_kind(text) is None  # one BSM is no trajectory: name it ode:PATH
    core = json.loads(text)["payload"]["data"]["coreData"]
    (table,) = load(f"ode:{path}")
    assert list(table.tracks) == [vid] and table.default_host == host
    track = table.tracks[vid]
    assert len(track) == 1 and track.t[0] == pytest.approx(t0)
    assert track.lat[0] == pytest.approx(core["position"]["latitude"], abs=1e-9)
    assert track.speed[0] == pytest.approx(core["speed"])
    assert track.heading[0] == pytest.approx(core["heading"])
    assert track.yaw_rate[0] == pytest.approx(core["accelSet"]["accelYaw"])
    assert track.length == core["size"]["length"] / 100
    if "accelLong" not in core["accelSet"]:
        assert track.accel[0] == 0.0 and "fewer than 3" in track.provenance["accel"]


def test_ode_yaw_rate_sign_on_the_wydot_bsm():
    """+2.29 deg/s yaw, +97.5 m radius, and a path history that turns clockwise."""
    path = shared_path("cv-pilot-samples", "wydot-filtered-bsm-schemaVersion6.json")
    data = json.loads(path.read_text())["payload"]["data"]
    crumbs = data["partII"][0]["value"]["pathHistory"]["crumbData"]
    lat0 = math.radians(data["coreData"]["position"]["latitude"])
    east = np.r_[0.0, [c["lonOffset"] * 111_320 * math.cos(lat0) for c in crumbs]][::-1]
    north = np.r_[0.0, [c["latOffset"] * 110_950 for c in crumbs]][::-1]  # oldest first
    for sign in (1, -1):  # the rotation sense does not depend on the offsets' sign
        motion = np.degrees(np.arctan2(sign * np.diff(east), sign * np.diff(north)))
        turn = np.diff(np.unwrap(motion, period=360.0))
        assert turn.sum() > 80 and (turn > -1).all()
    (table,) = load(f"ode:{path}")
    assert table.tracks["CB950124"].yaw_rate[0] == pytest.approx(2.29)
    assert data["partII"][0]["value"]["pathPrediction"]["radiusOfCurve"] > 0


def test_ode_detection_leaves_other_files_alone():
    for name in ("bsm.json", "expected-bsm.json", "decoder-input-bsm.json",
                 "BsmReceiverTest_ValidBSM_expected.json"):
        text = shared_path("jpo-ode-bsm-vectors", name).read_text()
        assert datasets.detect_kind(text) is None, name
    assert datasets.detect_kind(vectors("bsm.uper")) is None
    nyc = shared_path("cv-pilot-samples", "nycdot-fcw-event.json").read_text()
    assert datasets.detect_kind(nyc) == "nyc"
    thea = shared_path("cv-pilot-samples", "thea-filtered-bsm-schemaVersion1.json")
    assert datasets.detect_kind(thea.read_text()) is None
    assert not ode.looks_like("[1, 2]") and not ode.looks_like('{"a": 1}\n{"b": 2}')


# --- ode: synthetic quirks and errors ----------------------------------------------------


def ode_record(vid: str, sec_mark: int | None, lat: float | None, when: str) -> dict:
    core = {"msgCnt": 1, "id": vid, "secMark": sec_mark,
            "position": {"latitude": lat, "longitude": -105.0, "elevation": 1500.0},
            "accelSet": {"accelYaw": 0.0, "accelLong": 0.5}, "speed": 10.0, "heading": 0.0,
            "size": {"width": 180, "length": 450}}
    return {"metadata": {"recordGeneratedAt": when, "bsmSource": "RV"},
            "payload": {"data": {"coreData": core}}}


def test_ode_json_quirks():
    logged = datetime(2020, 2, 3, 4, 5, 59, 990_000, tzinfo=UTC).timestamp()  # 40 ms late
    records = [ode_record("0000000A", (59_950 + 100 * k) % 60_000, 41.0 + k * 1e-5,
                          datetime.fromtimestamp(logged + 0.1 * k, UTC).isoformat())
               for k in range(3)]
    records.insert(1, {"metadata": {}, "payload": {"data": {"messageFrame": "TIM"}}})
    records.append(ode_record("0000000A", 400, None, "2020-02-03T04:06:00.4Z"))
    text = json.dumps(records)
    assert datasets.detect_kind(text) is None  # the second record is not a BSM
    (table,) = datasets.parse("ode", text, "x")
    assert table.meta["skipped"] == {"not a decoded BSM record": 1,
                                     "BSM without a position": 1}
    track = table.tracks["0000000A"]
    # secMark 59950 of minute 04:05, then 50 and 150 of 04:06 (nearest the record times).
    assert table.meta["epoch_iso"] == "2020-02-03T04:05:00Z"
    np.testing.assert_allclose(track.t, [59.95, 60.05, 60.15], atol=1e-9)
    assert table.meta["time_offset"] == 0.05
    assert (track.length, track.width) == pytest.approx((4.5, 1.8))


def test_ode_errors():
    with pytest.raises(ValueError, match="ode: not JSON"):
        ode.parse("not json at all", "x")
    with pytest.raises(ValueError, match="ode: neither JSON nor an OBU log"):
        ode.parse(b"\xff\xfe\x00\x01binary garbage", "x")
    with pytest.raises(ValueError, match="ode: no BSM with a position"):
        ode.parse('[{"a": 1}]', "x")
    with pytest.raises(ValueError, match="only ode reads binary"):
        datasets.parse("openacc", b"\x00\x01", "x")


# --- loading files --------------------------------------------------------------------------


def test_loader_reads_obu_logs_as_bytes(tmp_path):
    directory = shared_path("jpo-ode-bsm-vectors")
    (table,) = load(str(directory / "bsmLogDuringEvent.bin"))  # detected from the bytes
    assert table.kind == "ode" and table.name == "bsmLogDuringEvent"
    (table,) = load(f"ode:{directory / 'rxMsg_BSM.bin'}")
    assert list(table.tracks) == ["FDCC0000"]
    found = {f.name: [t.kind for t in tables] for f, tables in load_files(str(directory))}
    assert found == {"128_bsms.json": ["ode"], "bsmLogDuringEvent.bin": ["ode"],
                     "bsmLogDuringEvent.json": ["ode"], "rxMsg_BSM.bin": ["ode"]}
    assert len(load_files(f"ode:{directory}")) == 4
    with pytest.raises(DatasetError, match="only ode reads binary"):
        load(f"openacc:{directory / 'bsmLogDuringEvent.bin'}")
    spmd_file = tmp_path / "trips.csv"
    spmd_file.write_text(quirk_rows())
    assert [t.name for t in load(str(spmd_file))] == [
        "trips:101:1", "trips:102:1", "trips:101:2"]
