"""The comma2k19 RAV4 minute as a trip (``comma2k19:PATH``): the host from comma's fused
pose and the RVs from its radar, on one UTC clock, with the real CAN and fixes in
``meta`` for the RVE's vehicle side (../shared/data; skipped, with the reason, when
absent)."""

from __future__ import annotations

import numpy as np
import pytest

from catc.bsm import sec_mark
from catc.datasets.comma2k19 import RADAR_AHEAD_M, RV_LENGTH_M
from catc.vehicle import toyota_checksum
from hil import comma2k19
from hil.datasets import DatasetError, load_table
from tests.conftest import shared_path


@pytest.fixture(scope="module")
def segment():
    return comma2k19.segment_of(shared_path("comma2k19-example"))


@pytest.fixture(scope="module")
def table(segment):
    return load_table(f"comma2k19:{segment.parent}", None)


def test_the_trip_is_on_utc_and_the_host_is_comma_s_pose(table, segment):
    assert table.kind == "comma2k19" and table.default_host == "rav4"
    base = table.meta["utc_base"]
    assert base % 60 == 0 and base == 1_533_226_440  # 2018-08-02T16:14:00Z
    host = table.tracks["rav4"]
    assert 590 <= len(host) <= 600 and np.allclose(np.diff(host.t), 0.1)
    # the u-blox fixes were logged 0.20 s after their UTC stamps (its output latency)
    assert table.meta["gnss_delay_s"] == pytest.approx(0.204, abs=0.01)
    # the host's secMarks are its UTC's: 16:14:48.5 is secMark 48,500
    assert sec_mark(float(host.t[0])) == round((host.t[0] % 60) * 1000)
    p = comma2k19.pose(segment)
    assert float(np.max(np.abs(np.interp(host.t[:50], host.t, host.speed)
                               - p["speed"][1:100:2][:50]))) < 0.5


def test_rvs_are_the_radar_s_moving_tracks_placed_from_the_host(table, segment):
    rvs = {k: v for k, v in table.tracks.items() if k != "rav4"}
    assert 15 <= len(rvs) <= 30
    assert all(k.startswith("radar-21") for k in rvs)
    assert all(float(np.mean(tr.speed)) > 3.0 for tr in rvs.values())
    # one radar row against its RV: the range ahead and the offset to the left
    r = comma2k19.radar(segment)
    host = table.tracks["rav4"]
    tr = max(rvs.values(), key=len)
    i = len(tr) // 2
    addr = int(tr.vehicle_id.split("@")[0].split("-")[1], 16)
    rows = np.flatnonzero(r["address"] == addr)
    trip = r["t"][rows] + table.meta["boot_to_trip_s"]
    j = int(np.argmin(np.abs(trip - tr.t[i])))
    k = int(np.argmin(np.abs(host.t - tr.t[i])))
    h = np.radians(host.heading[k])
    dx, dy = tr.x[i] - host.x[k], tr.y[i] - host.y[k]
    along = dx * np.sin(h) + dy * np.cos(h)
    left = -dx * np.cos(h) + dy * np.sin(h)
    assert along == pytest.approx(r["forward"][rows[j]] + RADAR_AHEAD_M + RV_LENGTH_M / 2,
                                  abs=1.0)
    assert left == pytest.approx(r["left"][rows[j]], abs=0.5)


def test_meta_holds_the_real_buses_with_their_lengths_and_the_fixes(table):
    can = table.meta["vehicle_can"]
    assert set(np.unique(can["bus"])) == {0, 1} and len(can) == 98_800
    host = table.tracks["rav4"]
    assert can["t"][0] == pytest.approx(host.t[0], abs=0.2)
    assert int(((can["bus"] == 0) & (can["address"] == 0xAA)).sum()) > 4_000
    speed = can[(can["bus"] == 0) & (can["address"] == 0xB4)]  # SPEED: checksummed
    assert len(speed) > 2_000
    for row in speed:  # lengths restored: the checksum passes on every frame
        data = bytes(row["data"]).ljust(8, b"\0")[: int(row["length"])]
        assert len(data) == 8 and data[-1] == toyota_checksum(0xB4, data)
    fixes = table.meta["gnss_fixes"]
    assert len(fixes) == 579
    t_log, fix = fixes[100]
    assert t_log - (fix.t_unix - table.meta["utc_base"]) == pytest.approx(0.2, abs=0.05)


def test_a_folder_that_is_no_segment_is_one_line(tmp_path):
    with pytest.raises(DatasetError, match="not a comma2k19 segment"):
        load_table(f"comma2k19:{tmp_path}", None)


def test_the_profile_s_signs_agree_with_the_car_s_motion(table):
    """KINEMATICS: ACCEL_X is positive when the RAV4 brakes (the profile turns it), and
    ACCEL_Y, like J2735's lateral acceleration, is positive to the right: on the minute,
    1 s means of each against the fused pose's acceleration and speed x yaw rate."""
    from catc.vehicle import CanDecoder
    from hil.vehicle import load_profile

    profile, db = load_profile("toyota-rav4-2017")
    decoder = CanDecoder(profile, db)
    can = table.meta["vehicle_can"]
    rows = []
    for r in can[(can["bus"] == 0) & (can["address"] == 0x24)]:
        data = bytes(r["data"]).ljust(8, b"\0")[: int(r["length"])]
        if decoder.take(float(r["t"]), 0x24, data):
            s = decoder.state
            rows.append((float(r["t"]), s["accel_long_mps2"], s["accel_lat_mps2"]))
    a = np.array(rows)
    host = table.tracks["rav4"]
    inner = (host.t > a[0, 0] + 0.5) & (host.t < a[-1, 0] - 0.5)
    t = host.t[inner]
    mean = [np.array([a[(a[:, 0] > x - 0.5) & (a[:, 0] < x + 0.5), k].mean() for x in t])
            for k in (1, 2)]
    lateral = host.speed[inner] * np.radians(host.yaw_rate[inner])
    assert np.corrcoef(mean[0], host.accel[inner])[0, 1] > 0.85
    assert np.corrcoef(mean[1], lateral)[0, 1] > 0.75
