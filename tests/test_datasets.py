"""Tests for catc.datasets: OpenACC and NGSIM readers, derivations, kind detection.

The real files are read from ../shared/data (skipped when absent) and checked against
their own redundant columns: OpenACC's E/N and Doppler speed against positions from
Lat/Lon, NGSIM's space_headway against the placed tracks.  Thresholds come from what
these files measure (see the comments); synthetic content pins the exact behaviour.
"""

from __future__ import annotations

import csv
import functools
import io

import numpy as np
import pytest

from catc import datasets
from catc.datasets import derive, ngsim, openacc
from catc.geo import EnuFrame, heading_diff_deg
from catc.mobility import DT, MobilityTable, Track
from tests.conftest import shared_path

OPENACC_FILES = (
    "long_setting_dynamic_part16.csv",
    "mixed_dynamic_part7.csv",
    "no_ACC_handling_part40.csv",
    "short_setting_dynamic_part1.csv",
    "short_setting_dynamic_part22.csv",
    "short_setting_handling_part36.csv",
)
DYNAMIC_FILES = tuple(f for f in OPENACC_FILES if "dynamic" in f)
NGSIM_FILE = ("ngsim-i80-pairs", "i80_0400-0415_leader_follower_pairs.csv")
ARRAYS = ("t", "x", "y", "lat", "lon", "elev", "speed", "heading", "accel", "yaw_rate")


@functools.cache
def _read(*parts: str) -> str:
    return shared_path(*parts).read_text()


@functools.cache
def openacc_table(file: str) -> MobilityTable:
    return openacc.parse(_read("openacc-zalazone", file), file)


@functools.cache
def openacc_columns(file: str) -> tuple[list[str], dict[str, np.ndarray]]:
    """Vehicle_order names and the raw columns of a file, parsed independently of catc."""
    lines = _read("openacc-zalazone", file).splitlines()
    names = [n for n in lines[1].split(",")[1:] if n]
    header = lines[5].rstrip(",").split(",")
    rows = [(line.split(",") + [""] * len(header))[: len(header)] for line in lines[6:]]
    values = np.array([[float(c) if c else np.nan for c in row] for row in rows])
    return names, dict(zip(header, values.T, strict=True))


@functools.cache
def ngsim_tables() -> list[MobilityTable]:
    return ngsim.parse(_read(*NGSIM_FILE), NGSIM_FILE[1])


@functools.cache
def ngsim_rows() -> dict[str, dict[str, np.ndarray]]:
    """The NGSIM CSV's columns per pair_id (numeric columns as floats)."""
    rows = list(csv.DictReader(io.StringIO(_read(*NGSIM_FILE))))
    pairs: dict[str, list[dict[str, str]]] = {}
    for row in rows:
        pairs.setdefault(row["pair_id"], []).append(row)
    keys = ("frame_id", "local_y", "preceding_local_y", "space_headway")
    return {
        pid: {k: np.array([float(r[k]) for r in rs]) for k in keys} | {"first": rs[0]}
        for pid, rs in pairs.items()
    }


def _file_rows(file: str, track: Track) -> np.ndarray:
    """Row indices of ``file`` that hold the samples of ``track``."""
    _, columns = openacc_columns(file)
    return np.rint((track.t - columns["Time"][0]) / DT).astype(int)


def _vehicle_index(file: str, vehicle_id: str) -> int:
    names, _ = openacc_columns(file)
    return names.index(vehicle_id.split("#")[0]) + 1


def assert_track_ok(track: Track) -> None:
    """Strict 10 Hz, no gaps, no NaN, equal lengths, heading in [0, 360)."""
    n = len(track)
    assert n >= 50  # shorter pieces are dropped
    for name in ARRAYS:
        values = getattr(track, name)
        assert values.shape == (n,), name
        assert np.isfinite(values).all(), name
    np.testing.assert_allclose(np.diff(track.t), DT, atol=1e-6)
    assert ((track.heading >= 0) & (track.heading < 360)).all()
    assert set(track.provenance) >= {"speed", "heading", "accel", "yaw_rate", "x", "lat"}


# --- derive ----------------------------------------------------------------------------------


def test_pieces_bridge_short_gaps_and_split_long_ones():
    valid = np.ones(40, dtype=bool)
    valid[:2] = False  # leading: outside every piece
    valid[10:15] = False  # 5 missing: bridged
    valid[20:26] = False  # 6 missing: split
    valid[-1] = False
    assert derive.pieces(valid) == [slice(2, 20), slice(26, 39)]
    assert derive.pieces(np.zeros(5, dtype=bool)) == []


def test_fill_gaps_interpolates_linearly_per_column():
    values = np.array([[0.0, 10.0], [np.nan, np.nan], [np.nan, 7.0], [3.0, 13.0]])
    valid = np.array([True, False, False, True])
    expected = [[0, 10], [1, 11], [2, 12], [3, 13]]
    np.testing.assert_allclose(derive.fill_gaps(values, valid), expected)
    with pytest.raises(ValueError, match="first and last"):
        derive.fill_gaps(values[:3], valid[:3])


def test_heading_of_a_straight_track_and_hold_when_stationary():
    t = np.arange(100) * DT
    speed = np.where(t < 5.0, 10.0, 0.0)
    s = np.cumsum(speed) * DT
    x, y = s * np.sin(np.radians(30)), s * np.cos(np.radians(30))
    x[55:] += np.random.default_rng(1).normal(0, 0.05, 45)  # GNSS noise while stopped
    heading = derive.heading_from_track(x, y, speed)
    np.testing.assert_allclose(heading, 30.0, atol=1e-9)
    assert (derive.heading_from_track(x, y, np.zeros(100)) == 0).all()


def test_yaw_rate_across_north_and_accel_of_a_ramp():
    heading = (350.0 + 2.0 * np.arange(60) * DT) % 360  # +2 deg/s through 0
    np.testing.assert_allclose(derive.yaw_rate_from_heading(heading), 2.0, atol=1e-9)
    np.testing.assert_allclose(derive.accel_from_speed(5.0 - 3.0 * np.arange(60) * DT), -3.0)


def test_heading_and_yaw_rate_on_a_circle():
    radius, speed = 140.0, 10.0  # clockwise seen from above: heading increases
    angle = speed / radius * np.arange(300) * DT
    x, y = radius * np.sin(angle), radius * np.cos(angle)
    heading = derive.heading_from_track(x, y, np.full(300, speed))
    expected = np.degrees(angle) + 90.0
    assert np.abs(heading_diff_deg(heading, expected)).max() < 0.01
    np.testing.assert_allclose(
        derive.yaw_rate_from_heading(heading), np.degrees(speed / radius), rtol=1e-3
    )


# --- OpenACC, synthetic ----------------------------------------------------------------------

FRAME = EnuFrame(46.8900, 16.8400, 240.0)


def synthetic_openacc() -> str:
    """Vehicles 2 (east at 10 m/s) and 4 (north at 5 m/s, with gaps) of four named.

    Vehicle 4 misses samples 30-32 (Lat/Lon only: interpolated), 70-79 and 120-129
    (split; the 40-sample piece between them is dropped).  Rows end with a comma.
    """
    n = 200
    t = 100.0 + DT * np.arange(n)
    rows = [f"{v:.1f}" for v in t]
    for k, (e0, ve, vn) in {2: (0.0, 10.0, 0.0), 4: (-20.0, 0.0, 5.0)}.items():
        e, nn = e0 + ve * (t - t[0]), vn * (t - t[0])
        lat, lon, alt = FRAME.to_geodetic(e, nn, np.zeros(n))
        for i in range(n):
            cells = [np.hypot(ve, vn), e[i] + 50, nn[i] - 7, lon[i], lat[i], alt[i]]
            text = [repr(float(c)) for c in cells]
            if k == 4 and 30 <= i <= 32:
                text[3] = text[4] = ""
            if k == 4 and (70 <= i < 80 or 120 <= i < 130):
                text = [""] * 6
            rows[i] += "," + ",".join(text)
    fields = ("Speed", "E", "N", "Lon", "Lat", "Alt")
    header = "Time," + ",".join(f"{f}{k}" for k in (2, 4) for f in fields)
    meta = "Date,8,10,2019\nVehicle_order,LEAD,CAR_A,MID,CAR_B,\nNumber_of_vehicles,4\nACC,1\n"
    return meta + "Distance_setting,S\n" + header + ",IVS2\n" + "".join(r + ",\n" for r in rows)


def test_openacc_synthetic_ids_gaps_and_host():
    table = openacc.parse(synthetic_openacc(), "synthetic")
    assert table.kind == "openacc" and table.name == "synthetic"
    assert list(table.tracks) == ["CAR_A", "CAR_B", "CAR_B#2"]
    assert table.default_host == "CAR_B"
    a, b, b2 = table.tracks.values()
    assert (len(a), len(b), len(b2)) == (200, 70, 70)
    assert (b.t[0], b2.t[0]) == (100.0, 113.0)
    assert b.provenance["gaps"].startswith("3 ") and b2.provenance["gaps"].startswith("0 ")
    # Origin: first valid sample of the leader (CAR_A: LEAD has no columns).
    assert table.origin == pytest.approx((FRAME.lat0, FRAME.lon0, FRAME.h0), abs=1e-6)
    np.testing.assert_allclose(a.x, 10.0 * (a.t - 100.0), atol=1e-6)
    np.testing.assert_allclose(b.x, -20.0, atol=1e-6)  # interpolated samples on the line
    np.testing.assert_allclose(b.y, 5.0 * (b.t - 100.0), atol=1e-6)
    np.testing.assert_allclose(a.heading, 90.0, atol=1e-6)
    assert np.abs(heading_diff_deg(b2.heading, 0.0)).max() < 1e-6
    for track in table.tracks.values():
        assert_track_ok(track)
        np.testing.assert_allclose(track.accel, 0.0, atol=1e-9)
        np.testing.assert_allclose(track.yaw_rate, 0.0, atol=1e-6)
        assert np.isnan(track.length) and np.isnan(track.width)


# --- OpenACC, real files ---------------------------------------------------------------------


@pytest.mark.parametrize("file", OPENACC_FILES)
def test_openacc_file_parses_into_clean_10hz_tracks(file):
    table = openacc_table(file)
    names, columns = openacc_columns(file)
    with_data = [names[int(h[5:]) - 1] for h in columns if h.startswith("Speed")]
    assert table.default_host == with_data[-1]
    assert {vid.split("#")[0] for vid in table.tracks} == set(with_data)
    assert len(table.tracks) >= len(with_data)
    for track in table.tracks.values():
        assert_track_ok(track)
        assert track.vehicle_id in table.tracks
        # lat/lon/elev and x/y are the same points.
        e, n, _ = EnuFrame(*table.origin).to_enu(track.lat, track.lon, track.elev)
        np.testing.assert_allclose(np.c_[e, n], np.c_[track.x, track.y], atol=1e-6)


@pytest.mark.parametrize("file", OPENACC_FILES)
def test_openacc_xy_match_the_files_en_up_to_a_constant_offset(file):
    # Measured: max residual 0.8 cm (dynamic) to 6.4 cm (handling, 700 m across);
    # the file's E/N are a plane ~5e-5 smaller in scale than the exact ENU frame.
    table, (_, columns) = openacc_table(file), openacc_columns(file)
    diffs = []
    for vid, track in table.tracks.items():
        k, rows = _vehicle_index(file, vid), _file_rows(file, track)
        en = np.c_[columns[f"E{k}"][rows], columns[f"N{k}"][rows]]
        diffs.append((en - np.c_[track.x, track.y])[np.isfinite(en).all(axis=1)])
    diff = np.concatenate(diffs)
    residual = np.linalg.norm(diff - np.median(diff, axis=0), axis=1)
    assert residual.max() < 0.1


@pytest.mark.parametrize("file", OPENACC_FILES)
def test_openacc_speed_from_positions_matches_measured_speed(file):
    # Central differences of x/y vs the Doppler speed.  Measured per-track medians:
    # 0.01-0.10 m/s for most receivers, up to 0.30 m/s for the noisiest (BMW_I3 on the
    # handling track).  0.35 m/s per track and 0.12 m/s pooled catch a wrong scale, a
    # time shift or a misassigned column (each gives metres per second).
    errors = []
    for track in openacc_table(file).tracks.values():
        derived = np.hypot(np.gradient(track.x, DT), np.gradient(track.y, DT))
        error = np.abs(derived - track.speed)
        assert np.median(error) < 0.35, track.vehicle_id
        errors.append(error)
    assert np.median(np.concatenate(errors)) < 0.12


@pytest.mark.parametrize("file", OPENACC_FILES)
def test_openacc_heading_follows_the_direction_of_motion(file):
    # Direction of the 1 s chord (x[i+5] - x[i-5]) where the car moves > 3 m/s.
    diffs = []
    for track in openacc_table(file).tracks.values():
        de, dn = track.x[10:] - track.x[:-10], track.y[10:] - track.y[:-10]
        moving = (track.speed[5:-5] > 3.0) & (np.hypot(de, dn) > 3.0)
        chord = np.degrees(np.arctan2(de, dn))[moving]
        diffs.append(np.abs(heading_diff_deg(track.heading[5:-5][moving], chord)))
    diff = np.concatenate(diffs)
    assert np.median(diff) < 0.5 and np.percentile(diff, 95) < 3.0


@pytest.mark.parametrize("file", DYNAMIC_FILES)
def test_openacc_dynamic_platform_yaw_rate_is_speed_over_radius(file):
    # The "dynamic" runs circle ZalaZONE's dynamic platform (radius ~143 m), so the yaw
    # rate is not ~0 but v / R (3-5 deg/s).  Measured pooled median error 0.2 deg/s.
    errors = []
    for track in openacc_table(file).tracks.values():
        a = np.c_[2 * track.x, 2 * track.y, np.ones(len(track))]
        (cx, cy, c), *_ = np.linalg.lstsq(a, track.x**2 + track.y**2, rcond=None)
        radius = np.sqrt(c + cx**2 + cy**2)
        assert 135 < radius < 150
        moving = track.speed > 3.0
        expected = np.degrees(track.speed / radius)[moving]
        errors.append(np.abs(np.abs(track.yaw_rate[moving]) - expected))
    assert np.median(np.concatenate(errors)) < 0.4


def test_openacc_hard_braking_reaches_about_minus_5():
    # PROVENANCE: smoothed deceleration to about -5 m/s² in this run (measured -5.0).
    table = openacc_table("short_setting_dynamic_part1.csv")
    peak = min(track.accel.min() for track in table.tracks.values())
    assert -6.0 < peak < -4.5


# --- NGSIM -----------------------------------------------------------------------------------


def test_ngsim_gives_one_table_per_pair_with_leader_then_follower():
    tables, rows = ngsim_tables(), ngsim_rows()
    assert len(tables) == 95
    for table in tables:
        pair_id = table.name.rsplit(":", 1)[1]
        follower, leader = pair_id.split("-")
        assert list(table.tracks) == [leader, follower]
        assert table.default_host == follower and table.kind == "ngsim"
        first = rows[pair_id]["first"]
        for vid, prefix in ((follower, "v_"), (leader, "preceding_")):
            track = table.tracks[vid]
            assert_track_ok(track)
            assert track.length == float(first[f"{prefix}length"])
            assert track.width == float(first[f"{prefix}width"])
        f, lead = table.tracks[follower], table.tracks[leader]
        np.testing.assert_array_equal(f.t, lead.t)


def test_ngsim_spacing_along_the_line_matches_the_data():
    # preceding_local_y - local_y exactly; space_headway (raw NGSIM spacing, the
    # positions are EMD-smoothed) within a median 0.27 m, 95 % within 1.5 m.
    az = np.radians(ngsim.AZIMUTH_DEG)
    along, across = np.array([np.sin(az), np.cos(az)]), np.array([np.cos(az), -np.sin(az)])
    headway_errors = []
    for table in ngsim_tables():
        pair_id = table.name.rsplit(":", 1)[1]
        leader, follower = table.tracks.values()
        delta = np.c_[leader.x - follower.x, leader.y - follower.y]
        np.testing.assert_allclose(delta @ across, 0.0, atol=1e-9)  # same lateral place
        data = rows_at(pair_id, follower.t)
        np.testing.assert_allclose(
            delta @ along, data["preceding_local_y"] - data["local_y"], atol=1e-6
        )
        headway_errors.append(np.abs(delta @ along - data["space_headway"]))
        assert np.abs(heading_diff_deg(np.median(follower.heading), ngsim.AZIMUTH_DEG)) < 1.0
    error = np.concatenate(headway_errors)
    assert np.median(error) < 0.5 and np.percentile(error, 95) < 2.0


def rows_at(pair_id: str, t: np.ndarray) -> dict[str, np.ndarray]:
    """The pair's CSV columns at the track times (t = frame_id * 0.1)."""
    data = ngsim_rows()[pair_id]
    index = np.searchsorted(data["frame_id"], np.rint(t / DT))
    np.testing.assert_array_equal(data["frame_id"][index], np.rint(t / DT))
    return {k: v[index] for k, v in data.items() if k != "first"}


def test_ngsim_georeference_and_frame_gap():
    tables = {t.name.rsplit(":", 1)[1]: t for t in ngsim_tables()}
    frame = EnuFrame(*ngsim.ORIGIN)
    for table in tables.values():
        assert table.origin == ngsim.ORIGIN
        for track in table.tracks.values():
            e, n, _ = frame.to_enu(track.lat, track.lon, track.elev)
            np.testing.assert_allclose(np.c_[e, n], np.c_[track.x, track.y], atol=1e-6)
            assert np.hypot(track.x, track.y).max() < 700  # the ~500 m study section
    # Pair 1175-1167 skips frames 3347-3406: only the longer piece after it is kept.
    assert tables["1175-1167"].tracks["1175"].t[0] == pytest.approx(340.7)


# --- detection, dispatch, errors -------------------------------------------------------------


def test_detect_kind_and_parse_dispatch():
    assert datasets.KINDS == ("openacc", "ngsim", "nyc", "spmd", "ode", "sumo")
    text = synthetic_openacc()
    assert datasets.detect_kind(text) == "openacc"
    assert [t.name for t in datasets.parse("openacc", text, "s")] == ["s"]
    assert datasets.detect_kind(_read(*NGSIM_FILE)) == "ngsim"
    for other in ("", "time,x,y\n1,2,3\n", "Date,8\nfoo\n", "pair_id,x\n"):
        assert datasets.detect_kind(other) is None
    with pytest.raises(ValueError, match="unknown dataset kind"):
        datasets.parse("gpx", text, "s")


def test_detect_kind_on_real_openacc_files():
    for file in OPENACC_FILES:
        assert datasets.detect_kind(_read("openacc-zalazone", file)) == "openacc"


NGSIM_HEADER = (
    "pair_id,time,duration,vehicle_id,frame_id,local_x,local_y,v_length,v_width,v_class,"
    "v_vel,v_acc,lane_id,preceding,space_headway,time_headway,preceding_local_y,"
    "preceding_length,preceding_width,preceding_class,preceding_vel,preceding_acc"
)
NGSIM_ROW = "2-1,0.0,6.0,2,{f},2.4,{y},4.5,1.8,2,8.0,0.0,1,1,20.0,2.5,{p},4.8,1.9,2,8.0,0.0"


def synthetic_ngsim(frames: range = range(100, 160)) -> str:
    rows = [NGSIM_ROW.format(f=f, y=0.8 * (f - 100), p=20 + 0.8 * (f - 100)) for f in frames]
    return NGSIM_HEADER + "\n" + "\n".join(rows) + "\n"


def test_ngsim_synthetic_pair():
    (table,) = datasets.parse("ngsim", synthetic_ngsim(), "s")
    assert table.name == "s:2-1" and list(table.tracks) == ["1", "2"]
    leader, follower = table.tracks.values()
    np.testing.assert_allclose(follower.t, np.arange(100, 160) * DT)
    np.testing.assert_allclose(follower.heading, ngsim.AZIMUTH_DEG, atol=1e-6)
    np.testing.assert_allclose(np.hypot(leader.x - follower.x, leader.y - follower.y), 20.0)
    assert ngsim.parse(synthetic_ngsim(range(100, 140)), "s") == []  # 4 s: dropped


OPENACC_OK = synthetic_openacc()
BAD = [
    ("openacc", "Date,8,10,2019\nVehicle_order,A,\n", "openacc: no Time column"),
    ("openacc", OPENACC_OK.replace("Vehicle_order", "Order"), "no Vehicle_order"),
    ("openacc", OPENACC_OK.replace("LEAD,CAR_A,MID,CAR_B,", "A,B,"), "column index 4"),
    ("openacc", OPENACC_OK.replace(",Alt4", ",X"), "vehicle 4 lacks columns Alt"),
    ("openacc", OPENACC_OK.replace("100.3,", "abc,"), "bad number"),
    ("openacc", OPENACC_OK.replace("100.3,", "100.35,"), "10 Hz"),
    ("openacc", OPENACC_OK.split("Time,")[0] + "Time,Speed1,Lat1,Lon1,Alt1\n", "no data rows"),
    ("openacc", OPENACC_OK.split("Time,")[0] + "Time,Speed1,Lat1,Lon1,Alt1\n0.0,,,,\n", "no row"),
    ("openacc", "\n".join(OPENACC_OK.splitlines()[:40]), "no vehicle has 5 s"),
    ("ngsim", "", "no pair_id header"),
    ("ngsim", NGSIM_HEADER + "\n", "no data rows"),
    ("ngsim", synthetic_ngsim().replace(",local_y,", ",ly,"), "missing columns local_y"),
    ("ngsim", synthetic_ngsim().replace(",4.5,", ",x,"), "bad number in column v_length"),
    ("ngsim", synthetic_ngsim() + "2-1,0.0\n", "number of cells"),
    ("ngsim", synthetic_ngsim() + synthetic_ngsim().split("\n", 1)[1], "repeats a frame_id"),
]


@pytest.mark.parametrize(("kind", "text", "message"), BAD)
def test_malformed_content_raises_one_line_value_error(kind, text, message):
    with pytest.raises(ValueError, match=message) as info:
        datasets.parse(kind, text, "bad")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("n,window", [(3, 3), (7, 7), (11, 11), (12, 11), (500, 11), (40, 5)])
def test_savgol_derivative_equals_scipys_savgol_filter(n, window):
    from scipy.signal import savgol_filter

    from catc.datasets.derive import savgol_derivative

    values = np.cumsum(np.random.default_rng(n).normal(size=n))
    want = savgol_filter(values, window, 2, deriv=1, delta=0.1, mode="interp")
    np.testing.assert_allclose(savgol_derivative(values, window, 2, 0.1), want,
                               rtol=0, atol=1e-9)


# --- background traffic (dense:N:SPEC, issue 30) -------------------------------------------------


def test_dense_spec_adds_background_roads_beside_the_host_and_keeps_the_trip():
    from catc.datasets.background import ROAD_GAP_M
    from hil.datasets import DatasetError, load_table

    plain = load_table("scenario:highway-braking", None)
    dense = load_table("dense:120:scenario:highway-braking", None)
    bg = {k: tr for k, tr in dense.tracks.items() if k.startswith("bg")}
    assert len(bg) == 120 and len(dense.tracks) == len(plain.tracks) + 120
    for k, tr in plain.tracks.items():  # the trip itself is untouched
        assert np.array_equal(dense.tracks[k].x, tr.x) and np.array_equal(dense.tracks[k].y, tr.y)
    host = dense.tracks["host"]
    frame = EnuFrame(*dense.origin)
    ways = set()
    for tr in bg.values():
        assert np.hypot(tr.x - host.x, tr.y - host.y).min() >= ROAD_GAP_M - 1.0
        # positions, speed and heading agree: 0.1 s steps of speed * DT along the heading
        step = np.hypot(np.diff(tr.x), np.diff(tr.y))
        assert np.allclose(step, tr.speed[1:] * DT, rtol=1e-9)
        lat, lon, _ = frame.to_geodetic(tr.x, tr.y, 0.0)
        assert np.allclose(lat, tr.lat) and np.allclose(lon, tr.lon)
        ways.add(round(heading_diff_deg(float(tr.heading[0]), float(host.heading[0]))))
    assert ways == {0, 180}  # one side the host's way, the other side the other way
    for bad in ("dense:x:scenario:highway-braking", "dense:-3:scenario:highway-braking",
                "dense:5"):
        with pytest.raises(DatasetError, match="dense:N:SPEC"):
            load_table(bad, None)
