"""Kinematic baselines and the KF (paper, "Prediction Baseline Models"): hand-computed cases
first, then the Kalman filter's behaviour, then a property test over random inputs."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catc.predict.base import Observation, Predictor
from catc.predict.kalman import KalmanPredictor, measurement, process_noise, transition
from catc.predict.kinematic import (
    TIME_TOLERANCE,
    ConstantAccelerationPredictor,
    ConstantSpeedPredictor,
    CtrvPredictor,
    HoldPredictor,
    wrap_heading,
)

KINEMATIC = (HoldPredictor, ConstantSpeedPredictor, ConstantAccelerationPredictor, CtrvPredictor)
ALL = (*KINEMATIC, KalmanPredictor)


def obs(t: float = 0.0, x: float = 0.0, y: float = 0.0, speed: float = 0.0,
        heading: float = 0.0, accel: float = 0.0, yaw_rate: float = 0.0) -> Observation:
    return Observation(t, x, y, speed, heading, accel, yaw_rate)


def straight_ca(t: float, v0: float = 5.0, a: float = 1.0, heading: float = 30.0,
                x0: float = 100.0, y0: float = -50.0) -> Observation:
    """The true state at ``t`` of a vehicle accelerating along a straight line from t = 0."""
    s = v0 * t + 0.5 * a * t * t
    h = math.radians(heading)
    return obs(t, x0 + s * math.sin(h), y0 + s * math.cos(h), v0 + a * t, heading, a)


# -- hand-computed kinematic cases --------------------------------------------------------

def test_names_and_protocol() -> None:
    assert [cls.name for cls in ALL] == ["hold", "cs", "ca", "ctrv", "kf"]
    for cls in ALL:
        assert isinstance(cls(), Predictor)


def test_hold_returns_last_observation() -> None:
    p = HoldPredictor()
    p.update(obs(0.0, 1.0, 2.0, 5.0, 10.0))
    p.update(obs(0.1, 3.0, 4.0, 6.0, 20.0, accel=2.0, yaw_rate=5.0))
    for t in (0.1, 0.5, 60.0):
        r = p.predict(t)
        assert (r.x, r.y, r.speed, r.heading, r.source) == (3.0, 4.0, 6.0, 20.0, "hold")
        assert math.isnan(r.var_x) and math.isnan(r.var_y)


def test_cs_two_seconds_east() -> None:
    p = ConstantSpeedPredictor()
    p.update(obs(1.0, 5.0, 7.0, speed=10.0, heading=90.0, accel=3.0, yaw_rate=10.0))
    r = p.predict(3.0)
    assert r.x == 25.0
    assert r.y == pytest.approx(7.0, abs=1e-12)
    assert (r.speed, r.heading) == (10.0, 90.0)


def test_ca_braking_stops_and_stays() -> None:
    p = ConstantAccelerationPredictor()
    p.update(obs(0.0, speed=20.0, heading=0.0, accel=-4.0))
    r = p.predict(2.0)  # 20·2 − 2·4 = 32 m, 12 m/s
    assert (r.x, r.y, r.speed) == (pytest.approx(0.0, abs=1e-12), 32.0, 12.0)
    for t in (5.0, 8.0, 100.0):
        r = p.predict(t)
        assert (r.y, r.speed, r.heading) == (50.0, 0.0, 0.0)
        assert r.x == pytest.approx(0.0, abs=1e-12)


def test_ca_accelerating_and_standing_still() -> None:
    p = ConstantAccelerationPredictor()
    p.update(obs(0.0, speed=10.0, heading=270.0, accel=2.0))
    r = p.predict(3.0)  # 30 + 9 = 39 m west, 16 m/s
    assert (r.x, r.y, r.speed) == (pytest.approx(-39.0), pytest.approx(0.0, abs=1e-12), 16.0)
    p.update(obs(4.0, x=1.0, y=2.0, speed=0.0, heading=45.0, accel=-1.0))
    r = p.predict(10.0)  # stopped and braking: stays put
    assert (r.x, r.y, r.speed, r.heading) == (1.0, 2.0, 0.0, 45.0)


def test_ctrv_quarter_circle() -> None:
    radius = 10.0 / (math.pi / 10.0)  # 18 deg/s = π/10 rad/s at 10 m/s
    p = CtrvPredictor()
    p.update(obs(0.0, speed=10.0, heading=0.0, yaw_rate=18.0))
    end = p.predict(5.0)  # clockwise from north: centre (r, 0), ends at (r, r) heading east
    assert (end.x, end.y) == (pytest.approx(radius, rel=1e-12), pytest.approx(radius, rel=1e-12))
    assert end.heading == pytest.approx(90.0)
    assert end.speed == 10.0
    mid = p.predict(2.5)
    c = math.cos(math.pi / 4)
    assert (mid.x, mid.y) == (pytest.approx(radius * (1 - c)), pytest.approx(radius * c))
    assert math.hypot(mid.x - radius, mid.y) == pytest.approx(radius)
    p.update(obs(10.0, speed=10.0, heading=0.0, yaw_rate=-18.0))  # counter-clockwise
    end = p.predict(15.0)
    assert (end.x, end.y) == (pytest.approx(-radius), pytest.approx(radius))
    assert end.heading == pytest.approx(270.0)


@pytest.mark.parametrize(("yaw_rate", "tol"), [(0.0, 1e-12), (1e-12, 1e-12), (-1e-9, 1e-9)])
def test_ctrv_without_turning_is_cs(yaw_rate: float, tol: float) -> None:
    o = obs(2.0, 3.0, -4.0, speed=13.0, heading=123.0, accel=1.0)
    cs, ctrv = ConstantSpeedPredictor(), CtrvPredictor()
    cs.update(o)
    ctrv.update(obs(2.0, 3.0, -4.0, speed=13.0, heading=123.0, accel=1.0, yaw_rate=yaw_rate))
    for t in (2.0, 2.1, 3.0, 12.0):
        a, b = cs.predict(t), ctrv.predict(t)
        assert (b.x, b.y, b.speed) == (pytest.approx(a.x, rel=tol, abs=tol),
                                       pytest.approx(a.y, rel=tol, abs=tol), a.speed)
        assert b.heading == pytest.approx(a.heading, abs=1e-6)


def test_heading_wraps() -> None:
    p = CtrvPredictor()
    p.update(obs(0.0, speed=5.0, heading=350.0, yaw_rate=20.0))
    assert p.predict(1.0).heading == pytest.approx(10.0)
    p.update(obs(1.0, speed=5.0, heading=10.0, yaw_rate=-20.0))
    assert p.predict(2.0).heading == pytest.approx(350.0)
    h = HoldPredictor()
    h.update(obs(0.0, heading=370.0))
    assert h.predict(0.0).heading == pytest.approx(10.0)
    assert -1e-14 % 360.0 == 360.0  # why wrap_heading is more than ``%``
    assert wrap_heading(-1e-14) == 0.0
    assert wrap_heading(-90.0) == 270.0
    assert wrap_heading(720.0) == 0.0


@pytest.mark.parametrize("cls", KINEMATIC)
def test_predict_at_observation_time_is_the_observation(cls: type) -> None:
    p = cls()
    first = obs(0.0, 1.0, 1.0, 3.0, 45.0, 1.0, 2.0)
    last = obs(0.7, 12.345, -6.789, 17.5, 212.25, -3.25, -7.5)
    p.update(first)
    p.update(last)
    r = p.predict(last.t)
    assert (r.x, r.y, r.speed, r.heading) == (last.x, last.y, last.speed, last.heading)
    assert r.source == cls.name
    r = p.predict(last.t - TIME_TOLERANCE / 2)  # time-stamp rounding
    assert (r.x, r.y) == (last.x, last.y)


# -- protocol rules shared by all predictors ----------------------------------------------

@pytest.mark.parametrize("cls", ALL)
def test_lookup_error_before_data_and_after_reset(cls: type) -> None:
    p = cls()
    with pytest.raises(LookupError, match="no observation yet"):
        p.predict(0.0)
    p.update(obs(0.0, 1.0, 2.0, 3.0, 40.0))
    p.update(obs(0.1, 1.2, 2.2, 3.0, 40.0))
    p.reset()
    with pytest.raises(LookupError):
        p.predict(1.0)
    fresh = cls()
    for q in (p, fresh):
        q.update(obs(5.0, -7.0, 8.0, 4.0, 100.0, 0.5, 3.0))
    assert p.predict(6.0) == fresh.predict(6.0)


@pytest.mark.parametrize("cls", ALL)
def test_duplicates_and_replays_are_ignored(cls: type) -> None:
    p, ref = cls(), cls()
    for q in (p, ref):
        q.update(obs(0.0, 0.0, 0.0, 10.0, 90.0))
        q.update(obs(0.1, 1.0, 0.0, 10.0, 90.0))
    p.update(obs(0.1, 50.0, 50.0, 30.0, 0.0))  # same time: duplicate
    p.update(obs(0.05, 50.0, 50.0, 30.0, 0.0))  # earlier: replay
    for t in (0.1, 1.0):
        assert p.predict(t) == ref.predict(t)


@pytest.mark.parametrize("cls", ALL)
def test_invalid_input_raises(cls: type) -> None:
    p = cls()
    with pytest.raises(ValueError):
        p.update(obs(0.0, x=math.nan))
    with pytest.raises(ValueError):
        p.update(obs(0.0, speed=-1.0))
    p.update(obs(1.0, speed=1.0))
    with pytest.raises(ValueError, match="before the last observation"):
        p.predict(0.5)


# -- the Kalman filter --------------------------------------------------------------------

def test_kf_process_noise_composes_over_irregular_intervals() -> None:
    """Q(dt₁ + dt₂) = A(dt₂) Q(dt₁) A(dt₂)ᵀ + Q(dt₂): one step over a gap equals many."""
    q = 0.7
    for d1, d2 in ((0.1, 0.1), (0.1, 0.9), (2.5, 0.3)):
        a = transition(d2)
        np.testing.assert_allclose(process_noise(d1 + d2, q),
                                   a @ process_noise(d1, q) @ a.T + process_noise(d2, q),
                                   rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(transition(d1 + d2), a @ transition(d1), rtol=1e-15)


def _corrupted_start(o: Observation) -> Observation:
    return Observation(o.t, o.x + 8.0, o.y - 5.0, o.speed + 3.0, o.heading + 10.0, o.accel - 2.0)


def test_kf_converges_on_noiseless_ca_line() -> None:
    """Started from a wrong first BSM, the 1 s forecast converges to the true trajectory."""
    kf = KalmanPredictor()
    errors = []
    for k in range(201):  # 20 s at 10 Hz
        o = straight_ca(0.1 * k)
        kf.update(_corrupted_start(o) if k == 0 else o)
        truth = straight_ca(o.t + 1.0)
        r = kf.predict(o.t + 1.0)
        errors.append(math.hypot(r.x - truth.x, r.y - truth.y))
    assert errors[0] > 5.0
    assert errors[-1] < 0.01
    assert max(errors[-50:]) < 0.05
    assert r.speed == pytest.approx(truth.speed, abs=0.01)
    assert r.heading == pytest.approx(30.0, abs=0.01)


def test_kf_tracks_with_irregular_updates() -> None:
    rng = np.random.default_rng(7)
    kf = KalmanPredictor()
    t, gaps = 0.0, []
    kf.update(_corrupted_start(straight_ca(t)))
    while t < 30.0:
        gap = float(rng.choice([0.1, 0.1, 0.2, 0.3, 0.7, 1.5]))  # lost messages
        gaps.append(gap)
        for k in range(1, round(gap / 0.1)):  # predictions inside the gap track the truth
            if t > 15.0:
                truth, r = straight_ca(t + 0.1 * k), kf.predict(t + 0.1 * k)
                assert math.hypot(r.x - truth.x, r.y - truth.y) < 0.05
        t += gap
        kf.update(straight_ca(t))
    assert len(set(gaps)) > 3
    truth, r = straight_ca(t + 2.0), kf.predict(t + 2.0)
    assert math.hypot(r.x - truth.x, r.y - truth.y) < 0.05


def test_kf_follows_a_curve() -> None:
    """On the quarter-circle-per-5-s turn, the centripetal acceleration (speed × yaw rate)
    in the measurement keeps the filter on the arc; CA's own error at 1 s is v·ω²·t³/6."""
    radius = 100.0 / math.pi

    def circle(t: float) -> Observation:
        h = math.radians(18.0 * t)
        return obs(t, radius * (1 - math.cos(h)), radius * math.sin(h), 10.0,
                   wrap_heading(18.0 * t), yaw_rate=18.0)

    kf = KalmanPredictor()
    for k in range(101):
        kf.update(circle(0.1 * k))
    for horizon, tol in ((0.0, 0.05), (1.0, 0.5)):
        r, truth = kf.predict(10.0 + horizon), circle(10.0 + horizon)
        assert math.hypot(r.x - truth.x, r.y - truth.y) < tol
        assert abs((r.heading - truth.heading + 180.0) % 360.0 - 180.0) < 2.0


def test_kf_filters_noise() -> None:
    """With measurement noise of the paper's R, the filtered position beats the raw BSM."""
    rng = np.random.default_rng(1)
    std = np.sqrt([10.0, 1.0, 0.5])
    kf = KalmanPredictor(anchor=False)
    raw, filtered = [], []
    for k in range(300):
        o = straight_ca(0.1 * k, v0=10.0, a=0.2)
        n = rng.normal(size=(3, 2)) * std[:, None]
        h = math.radians(o.heading)
        speed = math.hypot(o.speed * math.sin(h) + n[1, 0], o.speed * math.cos(h) + n[1, 1])
        noisy = Observation(o.t, o.x + n[0, 0], o.y + n[0, 1], speed, o.heading,
                            o.accel + n[2, 0])
        kf.update(noisy)
        r = kf.predict(o.t)
        if k >= 50:
            raw.append(math.hypot(noisy.x - o.x, noisy.y - o.y))
            filtered.append(math.hypot(r.x - o.x, r.y - o.y))
    assert np.sqrt(np.mean(np.square(filtered))) < 0.5 * np.sqrt(np.mean(np.square(raw)))


def test_kf_is_anchored_at_the_last_bsm() -> None:
    """At a fresh BSM the estimate is that BSM (paper: KF PTE 0 at PER 0), and the
    forecast moves on from there with the filter's motion."""
    rng = np.random.default_rng(2)
    kf = KalmanPredictor()
    for k in range(40):
        o = straight_ca(0.1 * k, v0=10.0, a=0.0)
        noisy = Observation(o.t, o.x + rng.normal(), o.y + rng.normal(), o.speed, o.heading)
        kf.update(noisy)
        r = kf.predict(o.t)
        assert (r.x, r.y) == (pytest.approx(noisy.x, abs=1e-9), pytest.approx(noisy.y,
                                                                               abs=1e-9))
    ahead = kf.predict(3.9 + 1.0)
    assert math.hypot(ahead.x - noisy.x, ahead.y - noisy.y) == pytest.approx(10.0, abs=0.5)


def test_kf_variance_grows_with_horizon() -> None:
    kf = KalmanPredictor()
    for k in range(50):
        kf.update(straight_ca(0.1 * k))
    last = 4.9
    variances = [kf.predict(last + h) for h in (0.0, 0.1, 0.5, 1.0, 2.0, 5.0)]
    assert all(r.var_x == r.var_y for r in variances)
    v = [r.var_x for r in variances]
    assert all(a < b for a, b in itertools.pairwise(v))
    assert v[0] < 10.0  # better than one BSM's position variance
    assert kf.predict(last + 1.0).source == "kf"


def test_kf_forecast_stops_instead_of_reversing() -> None:
    kf = KalmanPredictor()
    for k in range(11):  # braking from 20 m/s at 4 m/s² for 1 s: 16 m/s at y = 18 m
        kf.update(straight_ca(0.1 * k, v0=20.0, a=-4.0, heading=0.0, x0=0.0, y0=0.0))
    for horizon in (4.0, 6.0, 60.0):  # stops 16²/8 = 32 m further, after 4 s
        r = kf.predict(1.0 + horizon)
        assert (r.x, r.y) == (pytest.approx(0.0, abs=1e-6), pytest.approx(50.0, abs=1e-6))
        assert (r.speed, r.heading) == (pytest.approx(0.0, abs=1e-9), 0.0)
    r = kf.predict(3.0)
    assert (r.y, r.speed) == (pytest.approx(42.0, abs=1e-6), pytest.approx(8.0, abs=1e-6))


def test_kf_heading_of_a_stopped_vehicle_is_the_observed_one() -> None:
    kf = KalmanPredictor()
    for k in range(5):
        kf.update(obs(0.1 * k, 3.0, 4.0, speed=0.0, heading=123.0))
    r = kf.predict(2.0)
    assert (r.speed, r.heading) == (pytest.approx(0.0, abs=1e-9), 123.0)
    assert (r.x, r.y) == (pytest.approx(3.0), pytest.approx(4.0))


class _MatrixKalman:
    """The filter in its textbook matrix form (numpy), the reference for the scalar code."""

    def __init__(self, q: float, r: tuple[float, float, float]) -> None:
        self.q, self.r = q, np.diag(r)
        self.t = None

    def update(self, o: Observation) -> None:
        z = measurement(o)
        if self.t is None:
            self.x, self.p = z, self.r.copy()
        else:
            dt = o.t - self.t
            a = transition(dt)
            prior = a @ self.x
            cov = a @ self.p @ a.T + process_noise(dt, self.q)
            gain = np.linalg.solve(cov + self.r, cov).T
            keep = np.eye(3) - gain
            self.x = prior + gain @ (z - prior)
            cov = keep @ cov @ keep.T + gain @ self.r @ gain.T
            self.p = 0.5 * (cov + cov.T)
        self.t = o.t


@pytest.mark.parametrize("seed", range(4))
def test_kf_scalar_arithmetic_is_the_matrix_filter(seed: int) -> None:
    """The written-out float arithmetic of KalmanPredictor is the matrix form of the
    Kalman filter: same state and covariance after irregular updates (noise, turns,
    gaps of lost messages), and the same propagated position variance."""
    rng = np.random.default_rng(seed)
    q, r = float(rng.uniform(0.1, 3.0)), tuple(rng.uniform(0.2, 12.0, 3).tolist())
    kf, ref = KalmanPredictor(q=q, r=r), _MatrixKalman(q, r)
    t = 0.0
    for _ in range(300):
        t += float(rng.choice([0.1, 0.1, 0.2, 0.5, 1.3]))
        o = Observation(t, float(rng.normal(0, 50)), float(rng.normal(0, 50)),
                        float(rng.uniform(0, 30)), float(rng.uniform(0, 360)),
                        float(rng.normal(0, 2)), float(rng.normal(0, 10)))
        kf.update(o)
        ref.update(o)
        np.testing.assert_allclose(kf.state, ref.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(kf.covariance, ref.p, rtol=1e-9, atol=1e-12)
    for dt in (0.0, 0.1, 1.0, 4.0):
        row = transition(dt)[0]
        var = row @ ref.p @ row + q * dt**5 / 20.0
        assert kf.predict(t + dt).var_x == pytest.approx(var, rel=1e-9)


def test_compiled_kf_step_is_the_python_one_bit_for_bit() -> None:
    """The KF's update is compiled (numba); it must make the very float operations of its
    Python source, in order (no fused multiply-adds, no reassociation): every output
    equal, not close, over random filters and irregular steps."""
    from catc.predict.kalman import _kf_step, compiled_kf_step

    step = compiled_kf_step()

    rng = np.random.default_rng(5)
    for _ in range(2000):
        args = (float(rng.choice([0.1, 0.2, 0.3, 1.3, 4.0])), float(rng.uniform(0.0, 3.0)),
                tuple(rng.uniform(0.05, 12.0, 3).tolist()),
                tuple((rng.uniform(0.0, 5.0, 6) * [1, 0.1, 0.1, 1, 0.1, 1]).tolist()),
                tuple(rng.normal(0, 30, 3).tolist()), tuple(rng.normal(0, 30, 3).tolist()),
                tuple(rng.normal(0, 30, 3).tolist()), tuple(rng.normal(0, 30, 3).tolist()))
        assert step(*args) == _kf_step(*args)


def test_kf_parameters_are_checked() -> None:
    with pytest.raises(ValueError):
        KalmanPredictor(q=-1.0)
    with pytest.raises(ValueError):
        KalmanPredictor(r=(10.0, 0.0, 0.5))


# -- property: finite outputs, heading in [0, 360) ----------------------------------------

_finite = {"allow_nan": False, "allow_infinity": False}
_observation = st.tuples(
    st.floats(0.001, 5.0, **_finite),  # dt to the previous one
    st.floats(-1e5, 1e5, **_finite), st.floats(-1e5, 1e5, **_finite),
    st.floats(0.0, 80.0, **_finite), st.floats(-720.0, 720.0, **_finite),
    st.floats(-10.0, 10.0, **_finite), st.floats(-180.0, 180.0, **_finite))


def _fed(rows: list[tuple[float, ...]]) -> tuple[list[Predictor], float]:
    """Every predictor fed the observations ``rows`` (dt, x, y, speed, heading, accel,
    yaw rate), and the last time."""
    predictors = [cls() for cls in ALL]
    t = 0.0
    for dt, x, y, speed, heading, accel, yaw_rate in rows:
        t += dt
        for p in predictors:
            p.update(Observation(t, x, y, speed, heading, accel, yaw_rate))
    return predictors, t


@settings(max_examples=150, deadline=None)
@given(st.lists(_observation, min_size=1, max_size=15), st.floats(0.0, 60.0, **_finite))
def test_outputs_are_finite_and_heading_in_range(rows: list[tuple[float, ...]],
                                                 horizon: float) -> None:
    predictors, t = _fed(rows)
    for p in predictors:
        for when in (t, t + horizon):
            r = p.predict(when)
            assert all(math.isfinite(v) for v in (r.x, r.y, r.speed, r.heading))
            assert 0.0 <= r.heading < 360.0
            assert r.speed >= 0.0
            if p.name == "kf":
                assert math.isfinite(r.var_x) and r.var_x > 0.0


@settings(max_examples=150, deadline=None)
@given(st.lists(_observation, min_size=1, max_size=15), st.floats(0.0, 60.0, **_finite))
def test_position_is_the_predicted_position_bit_for_bit(rows: list[tuple[float, ...]],
                                                        horizon: float) -> None:
    """``position(t)`` (what the HGP's branch scores use) is ``predict(t)``'s x and y,
    exactly, whatever the state: stops of the stop rule, reversing headings, long gaps."""
    predictors, t = _fed(rows)
    for p in predictors:
        for when in (t, t + horizon, t + 0.1):
            r = p.predict(when)
            assert p.position(when) == (r.x, r.y), p.name
