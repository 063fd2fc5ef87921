"""The host's state from CAN and GNSS (catc.hoststate), on the real comma2k19 minute
against comma's fused pose (../shared/data; skipped, with the reason, when absent), and
on made-up inputs for the rules: no state before a fix, the GNSS clock, dead reckoning
through a silence."""

from __future__ import annotations

import math

import pytest
from bench import host_state

from catc.gnss import Fix
from catc.hoststate import EstimatorConfig, HostEstimator
from tests.conftest import shared_path


@pytest.fixture(scope="module")
def segment():
    from hil import comma2k19

    return comma2k19.segment_of(shared_path("comma2k19-example"))


@pytest.fixture(scope="module")
def minute(segment):
    return host_state.run(segment)


def test_position_speed_and_yaw_rate_against_comma_s_pose_at_every_tick(minute):
    """Issue 29's bar: position p95 at most 1.0 m off global_pose (the raw fixes at their
    logged times are 1.9 m p95 off: the receiver's latency, measured here, matters);
    speed within 0.1 m/s of the wheel speed; yaw rate within 1 deg/s of the gyro once
    KINEMATICS' bias is learnt."""
    assert minute["ticks"] >= 590  # 10 Hz over the minute
    assert minute["raw_fixes_at_logged_time_m"]["p95"] > 1.5
    assert minute["position_m"]["p95"] <= 1.0
    assert minute["position_m"]["p95"] < 0.6 * minute["raw_fixes_at_logged_time_m"]["p95"]
    # the latency fit (0.05 s, standard error 0.014 s) is not sure enough to replace the
    # 0.1 s prior on one minute; either is far from the 0.2 s the fixes' stamps say
    lag, se = minute["latency_fit"]
    assert 0.0 < lag < 0.15 and se < 0.03
    assert not minute["latency_fitted"] and minute["latency_s"] == 0.1
    assert minute["speed_mps"]["p95"] <= 0.1
    assert minute["yaw_rate_dps"]["max"] <= 1.0
    assert 0.2 <= minute["yaw_bias_dps"] <= 0.6  # KINEMATICS reads ~0.45 deg/s high
    assert minute["heading_deg"]["p95"] <= 1.5
    assert minute["counters"]["gnss_fixes"] == 579


def test_six_seconds_without_gnss_dead_reckoning_stays_within_2_m(segment):
    r = host_state.run(segment, drop=(20.0, 6.0))
    assert r["position_in_dropout_m"]["n"] >= 55
    assert r["position_in_dropout_m"]["max"] <= 2.0  # ~100 m driven on CAN alone
    assert r["counters"]["gnss_silent"] == 1  # silent past 5 s: told once, ticks go on


def _fix(t: float, north_m: float, speed: float = 10.0) -> Fix:
    return Fix(t_unix=t, lat=37.0 + north_m / 111_000.0, lon=-122.0, speed_mps=speed,
               course_deg=0.0, std_lat_m=0.5, std_lon_m=0.5)


def test_no_state_before_a_fix_then_the_gnss_clock():
    est = HostEstimator(EstimatorConfig(gnss_delay_s=0.2, latency_s=0.0))
    est.can(5.0, {"speed_mps": 10.0, "yaw_rate_dps": 0.0})
    assert est.state(5.0) is None and est.gnss_time(5.0) is None
    est.fix(5.3, _fix(1_767_225_600.1, 0.0))
    # the sentences arrived 0.2 s after the stamp: GNSS time at local 5.3 is stamp + 0.2
    assert est.gnss_time(5.3) == pytest.approx(1_767_225_600.3)
    assert est.local_time(1_767_225_600.4) == pytest.approx(5.4)
    s = est.state(5.3)
    assert s.t_gnss == pytest.approx(1_767_225_600.3) and s.speed == 10.0
    bsm = s.bsm(130, 0x1234)
    assert bsm.msg_cnt == 2 and bsm.sec_mark == 300 and bsm.heading == 0.0


def test_dead_reckoning_through_a_silence_then_gnss_lost():
    est = HostEstimator(EstimatorConfig(latency_s=0.0, gnss_timeout_s=5.0))
    base = 1_767_225_600.0
    for k in range(50):  # 5 s driving north at 10 m/s, CAN at 100 Hz
        for j in range(10):
            t = k * 0.1 + j * 0.01
            est.can(t, {"speed_mps": 10.0, "yaw_rate_dps": 0.0})
        est.fix(k * 0.1 + 0.1, _fix(base + k * 0.1 + 0.1, 10.0 * (k * 0.1 + 0.1)))
    for j in range(600):  # 6 s more of CAN, no GNSS
        est.can(5.0 + j * 0.01, {"speed_mps": 10.0, "yaw_rate_dps": 0.0})
    s = est.state(11.0)
    north = (s.lat - 37.0) * 111_000.0
    assert north == pytest.approx(110.0, abs=1.0)
    assert s.gnss_lost and s.gnss_age_s == pytest.approx(6.0)
    assert est.counters["gnss_silent"] == 1
    assert s.std_m > est.config.fix_std_m * 0.3  # the position grew uncertain
    assert math.isfinite(s.heading)


def test_a_stale_fix_is_counted_and_ignored():
    est = HostEstimator()
    est.fix(1.0, _fix(100.0, 0.0))
    est.fix(1.1, _fix(100.0, 5.0))
    assert est.counters["gnss_fixes_stale"] == 1 and est.counters["gnss_fixes"] == 1


def test_bad_settings_are_one_line():
    with pytest.raises(ValueError, match="GNSS delay"):
        EstimatorConfig(gnss_delay_s=-1.0)
    with pytest.raises(ValueError, match="latency"):
        EstimatorConfig(latency_s=3.0)
