"""catc.hostsim: the IDM equilibrium, stopping without collision, following a curved path."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from catc.datasets import derive, openacc
from catc.geo import EnuFrame
from catc.hostsim import (
    DEFAULT_LENGTH,
    V0_DEFAULT,
    IdmParams,
    equilibrium_gap,
    idm_acceleration,
    idm_follower,
    with_synthetic_host,
)
from catc.mobility import DT, MobilityTable, Track
from tests.conftest import shared_path

ORIGIN = (47.0, 17.0, 200.0)


def straight_leader(speed: np.ndarray, heading_deg: float = 30.0, vid: str = "lead") -> Track:
    """A leader on a straight line from the origin at the given 10 Hz speed profile."""
    t = np.arange(len(speed)) * DT
    dist = np.r_[0.0, np.cumsum((speed[1:] + speed[:-1]) / 2 * DT)]
    h = math.radians(heading_deg)
    x, y = dist * math.sin(h), dist * math.cos(h)
    lat, lon, elev = EnuFrame(*ORIGIN).to_geodetic(x, y, np.zeros_like(x))
    return Track(vid, t, x, y, np.asarray(lat), np.asarray(lon), np.asarray(elev), speed,
                 np.full_like(x, heading_deg), np.gradient(speed, DT), np.zeros_like(x))


def gap(leader: Track, host: Track) -> np.ndarray:
    """Bumper-to-bumper distance between the two (centre positions, both 5 m long)."""
    return np.hypot(leader.x - host.x, leader.y - host.y) - DEFAULT_LENGTH


def openacc_track(file: str, vehicle: str) -> Track:
    text = shared_path("openacc-zalazone", file).read_text()
    return openacc.parse(text, file).tracks[vehicle]


def test_constant_speed_leader_converges_to_the_equilibrium_gap():
    # s* = (s0 + v T) / sqrt(1 - (v / v0)^4) with s0 = 2 m, T = 1.6 s, v = 20, v0 = 30 m/s:
    # (2 + 32) / sqrt(1 - 16/81) = 34 * 9 / sqrt(65) = 37.9544 m.
    by_hand = 34 * 9 / math.sqrt(65)
    params = IdmParams(v0=30.0)
    assert equilibrium_gap(20.0, params, 30.0) == pytest.approx(by_hand, abs=1e-9)
    leader = straight_leader(np.full(3000, 20.0))
    for start in (60.0, 15.0):
        host = idm_follower(leader, initial_gap_m=start, params=params)
        g = gap(leader, host)
        assert g[0] == pytest.approx(start, abs=1e-6)
        assert g[-1] == pytest.approx(by_hand, abs=0.01)
        assert abs(host.speed[-1] - 20.0) < 1e-3 and abs(host.accel[-1]) < 1e-3
        assert g.min() > 0
    # Started at the equilibrium (the default), it stays there exactly.
    host = idm_follower(leader, params=params)
    np.testing.assert_allclose(gap(leader, host), by_hand, atol=1e-6)
    np.testing.assert_allclose(host.accel, 0.0, atol=1e-9)


def test_leader_braking_hard_to_a_stop():
    # 25 m/s, then -8 m/s² to a standstill, which it keeps for 30 s.
    speed = np.r_[np.full(100, 25.0), np.maximum(25.0 - 0.8 * np.arange(1, 40), 0.0),
                  np.zeros(300)]
    leader = straight_leader(speed)
    host = idm_follower(leader)
    g = gap(leader, host)
    assert g.min() > 0.5
    assert host.speed.min() >= 0.0
    assert host.speed[-1] == 0.0 and host.accel[-1] == 0.0
    params = IdmParams()
    # It stops about s0 behind (the braking overshoots s0 a little: 1.90 m here).
    assert abs(g[-1] - params.s0) < 0.25
    # The IDM braked harder than its comfortable b to avoid the collision.
    assert host.accel.min() < -params.b
    # accel is the applied acceleration: it integrates to the speed.
    np.testing.assert_allclose(np.diff(host.speed), host.accel[:-1] * DT, atol=1e-9)


def test_real_openacc_hard_braking_leader():
    # TESLA_MODELX brakes at up to -5 m/s² from 10.9 m/s to 0.12 m/s at t = 335 s.
    leader = openacc_track("short_setting_dynamic_part1.csv", "TESLA_MODELX")
    host = idm_follower(leader)
    g = gap(leader, host)
    assert g.min() > 3.0
    braking = (leader.t > 330) & (leader.t < 340)
    assert leader.accel[braking].min() < -4.5 and leader.speed[braking].min() < 0.2
    assert host.speed[braking].min() < 3.0  # it slows down behind the leader
    assert host.speed.min() >= 0.0


def test_follower_stays_on_a_curved_real_path_and_stops_behind():
    # MAZDA_3 on the handling track: curves (yaw rate up to 16 deg/s), up to 24 m/s, a
    # -6.6 m/s² brake and a standstill at the end.
    leader = openacc_track("short_setting_handling_part36.csv", "MAZDA_3")
    host = idm_follower(leader)
    assert gap(leader, host).min() > 0
    assert host.speed[-1] == 0.0
    # Once on the leader's path (after the straight extension behind its start), the
    # follower is on its polyline: distance to the nearest segment.
    travelled = np.r_[0.0, np.cumsum(np.hypot(np.diff(host.x), np.diff(host.y)))]
    start = equilibrium_gap(leader.speed[0], IdmParams(), V0_DEFAULT) + DEFAULT_LENGTH
    on_path = np.flatnonzero(travelled > start + 0.1)[::3]
    ax, ay, bx, by = leader.x[:-1], leader.y[:-1], leader.x[1:], leader.y[1:]
    dx, dy = bx - ax, by - ay
    norm = np.maximum(dx * dx + dy * dy, 1e-12)
    offsets = []
    for i in on_path:
        u = np.clip(((host.x[i] - ax) * dx + (host.y[i] - ay) * dy) / norm, 0.0, 1.0)
        offsets.append(np.hypot(ax + u * dx - host.x[i], ay + u * dy - host.y[i]).min())
    assert len(offsets) > 800
    assert max(offsets) < 0.01 and np.median(offsets) < 1e-6
    # It turns with the path: headings agree with its own direction of motion.
    moving = host.speed > 2.0
    motion = derive.heading_from_track(host.x, host.y, host.speed)
    diff = (host.heading - motion + 180.0) % 360.0 - 180.0
    assert np.abs(diff[moving]).max() < 6.0 and np.abs(host.yaw_rate).max() > 10.0
    # lat/lon are the same points as x/y (in the leader's table frame).
    frame = EnuFrame(*openacc.parse(
        shared_path("openacc-zalazone", "short_setting_handling_part36.csv").read_text(),
        "x").origin)
    e, n, _ = frame.to_enu(host.lat, host.lon, host.elev)
    assert np.hypot(e - host.x, n - host.y).max() < 0.01


def test_idm_acceleration_terms():
    p = IdmParams()
    assert idm_acceleration(0.0, 1e6, 0.0, p, 30.0) == pytest.approx(p.a)  # free start
    assert idm_acceleration(30.0, 1e6, 0.0, p, 30.0) == pytest.approx(0.0, abs=1e-6)  # at v0
    # Leader pulling away does not shrink s* below s0: at a standstill s* = s0.
    assert idm_acceleration(0.0, p.s0, -5.0, p, 30.0) == pytest.approx(0.0)
    assert idm_acceleration(10.0, 5.0, 10.0, p, 30.0) < -p.b  # closing fast on a short gap
    with pytest.raises(ValueError, match="no IDM equilibrium"):
        equilibrium_gap(30.0, p, 30.0)


def test_default_desired_speed_and_parameter_checks():
    slow = straight_leader(np.full(50, 10.0))
    fast = straight_leader(np.full(50, 40.0))
    host = idm_follower(slow)
    np.testing.assert_allclose(host.speed, 10.0, atol=1e-6)  # started in equilibrium
    table = MobilityTable("t", "x", ORIGIN, {"lead": fast})
    info = with_synthetic_host(table, "lead").meta["synthetic_host"]
    assert info["v0"] == pytest.approx(48.0)  # 1.2 x 40 m/s > 120 km/h
    info = with_synthetic_host(replace(table, tracks={"lead": slow}), "lead").meta[
        "synthetic_host"]
    assert info["v0"] == pytest.approx(V0_DEFAULT)
    for bad in ({"T": 0.0}, {"a": -1.0}, {"s0": -1.0}, {"v0": 0.0}, {"leader_length": 0.0}):
        with pytest.raises(ValueError, match="IdmParams"):
            IdmParams(**bad)
    with pytest.raises(ValueError, match="need >= 3"):
        idm_follower(straight_leader(np.full(2, 10.0)))


def test_with_synthetic_host_adds_the_host():
    leader = straight_leader(np.full(200, 15.0), vid="RV1")
    table = MobilityTable("trip", "spmd", ORIGIN, {"RV1": leader}, meta={"k": 1})
    out = with_synthetic_host(table, "RV1", initial_gap_m=30.0)
    assert list(out.tracks) == ["RV1", "host"] and out.default_host == "host"
    assert out.tracks["RV1"] is leader and table.default_host is None
    assert out.meta["k"] == 1 and out.meta["synthetic_host"]["leader"] == "RV1"
    assert out.meta["synthetic_host"]["initial_gap_m"] == 30.0
    host = out.tracks["host"]
    np.testing.assert_array_equal(host.t, leader.t)
    assert host.length == DEFAULT_LENGTH and "IDM" in host.provenance["speed"]
    # The straight extension behind the leader's start is on the leader's line.
    frame = EnuFrame(*ORIGIN)
    e, n, _ = frame.to_enu(host.lat, host.lon, host.elev)
    assert np.hypot(e - host.x, n - host.y).max() < 0.001
    assert np.allclose(host.heading, 30.0)
    with pytest.raises(ValueError, match="no vehicle 'RV2'"):
        with_synthetic_host(table, "RV2")
    with pytest.raises(ValueError, match="already has"):
        with_synthetic_host(out, "RV1")
