"""SI ↔ J2735 integer units: exactness, saturation, unavailable, and the array form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catc import units as u
from catc.bsm import (
    BSM,
    CORE_QUANTITIES,
    BrakeStatus,
    PositionalAccuracy,
    TransmissionState,
    from_array,
    quantize,
    to_array,
)
from catc.errors import EncodeError
from catc.j2735 import decode_frame, encode_frame

ALL = [u.LATITUDE, u.LONGITUDE, u.ELEVATION, u.SEMI_AXIS, u.ORIENTATION, u.SPEED, u.HEADING,
       u.STEERING, u.ACCEL, u.ACCEL_VERT, u.YAW_RATE, u.WIDTH, u.LENGTH, u.OFFSET_LL,
       u.VERT_OFFSET, u.TIME_OFFSET, u.COARSE_HEADING, u.CONFIDENCE]


@pytest.mark.parametrize("q", ALL, ids=lambda q: q.name)
@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_every_legal_raw_value_survives_si_and_back(q, data):
    raw = data.draw(st.integers(q.lo, q.hi) | st.sampled_from([q.lo, q.hi]))
    assert q.to_raw(q.from_raw(raw)) == raw
    if q.unavailable is not None:
        assert q.from_raw(q.unavailable) is None
        assert q.to_raw(None) == q.to_raw(math.nan) == q.unavailable


@pytest.mark.parametrize("q", ALL, ids=lambda q: q.name)
def test_array_form_equals_scalar_form(q):
    rng = np.random.default_rng(7)
    span = (q.hi - q.lo) * q.lsb
    x = np.concatenate([rng.uniform(q.lo * q.lsb - span, q.hi * q.lsb + span, 2000),
                        [np.inf, -np.inf, 1e300, -1e300, 0.0, q.lo * q.lsb, q.hi * q.lsb]])
    if q.unavailable is not None:
        x = np.append(x, np.nan)
    scalar = np.array([q.to_raw(v) for v in x.tolist()])
    assert np.array_equal(q.to_raw_array(x), scalar)
    back = q.from_raw_array(scalar)
    expected = np.array([np.nan if v is None else v for v in map(q.from_raw, scalar.tolist())])
    assert np.array_equal(back, expected, equal_nan=True)


def test_saturation_and_wrap_follow_j2735():
    assert u.SPEED.to_raw(200.0) == 8190  # 163.8 m/s or greater
    assert u.SPEED.to_raw(-1.0) == 0
    assert u.ACCEL.to_raw(-35.0) == -2000 and u.ACCEL.to_raw(35.0) == 2000
    assert u.ELEVATION.to_raw(-500.0) == -4095 and u.ELEVATION.to_raw(7000.0) == 61439
    assert u.STEERING.to_raw(300.0) == 126 and u.STEERING.to_raw(-300.0) == -126
    assert u.ACCEL_VERT.to_raw(-100.0) == -126  # -127 is reserved for unavailable
    assert u.HEADING.to_raw(360.0) == 0 and u.HEADING.to_raw(-90.0) == 21600  # 270°
    assert u.HEADING.to_raw(359.99999) == 0  # rounds up to a full turn, wraps
    assert u.LONGITUDE.to_raw(-180.0) == 1_800_000_000 and u.LONGITUDE.to_raw(190.0) == \
        -1_700_000_000
    assert u.WIDTH.to_raw(0.001) == 1  # a real width never becomes "unavailable" (0)
    assert u.radius_to_raw(math.inf) == 32767 and u.radius_from_raw(32767) == math.inf
    assert u.radius_to_raw(5000.0) == 32767 and u.radius_to_raw(-3276.7) == -32767
    assert u.radius_to_raw(-250.04) == -2500
    with pytest.raises(EncodeError):
        u.YAW_RATE.to_raw(None)


def test_rounding_is_to_nearest_ties_to_even():
    assert u.SPEED.to_raw(0.01) == 0 and u.SPEED.to_raw(0.03) == 2  # 0.5 and 1.5 LSB
    assert u.SPEED.to_raw(0.0100001) == 1
    assert np.array_equal(u.SPEED.to_raw_array(np.array([0.01, 0.03])), [0, 2])


def _random_bsms(n: int, seed: int = 3) -> list[BSM]:
    rng = np.random.default_rng(seed)

    def maybe(x: float) -> float | None:
        return None if rng.random() < 0.1 else float(x)

    return [BSM(msg_cnt=int(rng.integers(128)), temp_id=int(rng.integers(2**32)),
                sec_mark=None if rng.random() < 0.1 else int(rng.integers(60000)),
                lat=maybe(rng.uniform(-90, 90)), lon=maybe(rng.uniform(-180, 180)),
                elev=maybe(rng.uniform(-100, 3000)), speed=maybe(rng.uniform(0, 60)),
                heading=maybe(rng.uniform(0, 360)),
                accuracy=PositionalAccuracy(maybe(rng.uniform(0, 5)), maybe(rng.uniform(0, 5)),
                                            maybe(rng.uniform(0, 360))),
                transmission=None if rng.random() < 0.5 else TransmissionState.FORWARD_GEARS,
                steering_angle=maybe(rng.uniform(-180, 180)),
                accel_long=maybe(rng.normal(0, 3)), accel_lat=maybe(rng.normal(0, 1)),
                accel_vert=maybe(rng.normal(0, 1)), yaw_rate=float(rng.normal(0, 10)),
                brakes=BrakeStatus(wheel_brakes=int(rng.integers(32))),
                width=maybe(rng.uniform(1.5, 2.5)), length=maybe(rng.uniform(3, 18)))
            for _ in range(n)]


def test_array_form_round_trips_and_quantizes_like_the_codec():
    bsms = _random_bsms(500)
    arr = to_array(bsms)
    assert arr.dtype.names is not None and len(arr) == 500
    assert from_array(arr) == bsms
    decoded = to_array([decode_frame(encode_frame(b)) for b in bsms])
    quantized = quantize(arr)
    for name in arr.dtype.names:
        assert np.array_equal(quantized[name], decoded[name],
                              equal_nan=name in CORE_QUANTITIES), name


def test_sec_mark_and_msg_cnt_wrap():
    from catc.bsm import msg_cnt, sec_mark

    assert sec_mark(0.0) == 0
    assert sec_mark(59.9994) == 59_999
    assert sec_mark(59.9996) == 0  # rounds to the next minute, which wraps
    assert sec_mark(61.25) == 1_250
    assert sec_mark(3600.1) == 100
    assert [msg_cnt(s) for s in (0, 127, 128, 300)] == [0, 127, 0, 44]
