"""The IMM predictor (catc.predict.imm): checked cycle by cycle against filterpy's
IMMEstimator (Labbe's independent implementation of Blom & Bar-Shalom's IMM), and on
trajectories whose model is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from catc.predict import make_predictor
from catc.predict.base import Observation
from catc.predict.imm import (
    DT,
    ImmPredictor,
    markov,
    measurement_vector,
    noises,
    transitions,
)

filterpy_kalman = pytest.importorskip("filterpy.kalman", reason="filterpy (test extra)")

#: Distinct modes for the tests of the mechanism: with the shipped PSDs (8 m²/s³, chosen on
#: real trips) CV and CT are wide and CA wins on exact, noise-free trajectories.
SHARP = {"q_cv": 0.5, "q_ct": 0.5}


def _circle(n: int, speed: float = 15.0, yaw_deg: float = 12.0, accel: float = 0.0,
            noise: float = 0.0, seed: int = 0) -> list[Observation]:
    """Samples every DT of a vehicle turning clockwise at ``yaw_deg``/s from heading 0."""
    rng = np.random.default_rng(seed)
    out = []
    x = y = 0.0
    h = 0.0
    s = speed
    for k in range(n):
        out.append(Observation(k * DT, x + noise * rng.normal(), y + noise * rng.normal(),
                               s, h % 360.0, accel, yaw_deg))
        # exact arc over DT (constant speed within the step when accel = 0)
        w = math.radians(yaw_deg)
        h0 = math.radians(h)
        if abs(w) < 1e-12:
            x += s * DT * math.sin(h0)
            y += s * DT * math.cos(h0)
        else:
            x += s / w * (math.cos(h0) - math.cos(h0 + w * DT))
            y += s / w * (math.sin(h0 + w * DT) - math.sin(h0))
        h += yaw_deg * DT
        s = max(0.0, s + accel * DT)
    return out


def test_each_cycle_equals_filterpys_imm_estimator() -> None:
    """Same models, noises, Markov chain and measurements through filterpy's
    IMMEstimator: the mode probabilities and every model's state and covariance agree."""
    obs = _circle(80, speed=14.0, yaw_deg=9.0, noise=0.4, seed=3)
    imm = ImmPredictor()
    kfs = []
    for _ in range(3):
        f = filterpy_kalman.KalmanFilter(dim_x=6, dim_z=6)
        f.H = np.eye(6)
        f.R = imm.r.copy()
        kfs.append(f)
    ref = None
    for i, o in enumerate(obs):
        z = measurement_vector(o)
        if i == 0:
            for f in kfs:
                f.x = z.reshape(6, 1).copy()
                f.P = imm.r.copy()
            ref = filterpy_kalman.IMMEstimator(kfs, [1 / 3] * 3, markov())
        else:
            fs, qs = transitions(DT, math.radians(obs[i - 1].yaw_rate)), noises(DT)
            for j, f in enumerate(kfs):
                f.F, f.Q = fs[j], qs[j]
            ref.predict()
            ref.update(z.reshape(6, 1))
        imm.update(o)
        np.testing.assert_allclose(imm.mu, ref.mu, rtol=1e-9, atol=1e-12)
        for j, f in enumerate(kfs):
            np.testing.assert_allclose(imm.x[j], f.x[:, 0], rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(imm.p[j], f.P, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(imm.state, ref.x[:, 0], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(("yaw", "accel", "winner"),
                         [(0.0, 0.0, "cv"), (15.0, 0.0, "ct"), (0.0, -3.0, "ca")])
def test_the_mode_that_fits_the_motion_wins(yaw: float, accel: float, winner: str) -> None:
    imm = ImmPredictor(**SHARP)
    for o in _circle(40, speed=20.0, yaw_deg=yaw, accel=accel):
        imm.update(o)
    assert ("cv", "ca", "ct")[int(np.argmax(imm.mu))] == winner, imm.mu


def test_a_turn_is_followed_through_a_gap() -> None:
    """A 1.1 s gap in a 12 deg/s turn at 15 m/s: the IMM (CT mode) stays within 5 cm of
    the arc; the KF, whose constant acceleration vector only approximates the turn,
    misses it by 0.24 m."""
    obs = _circle(61, yaw_deg=12.0)
    imm, kf = ImmPredictor(**SHARP), make_predictor("kf")
    for o in obs[:50]:
        imm.update(o)
        kf.update(o)
    truth = obs[60]
    p, q = imm.predict(truth.t), kf.predict(truth.t)
    err_imm = math.hypot(p.x - truth.x, p.y - truth.y)
    err_kf = math.hypot(q.x - truth.x, q.y - truth.y)
    assert err_imm < 0.05 and 4.0 * err_imm < err_kf, (err_imm, err_kf)
    assert p.var_x > 0.0 and p.var_y > 0.0


def test_a_braking_vehicle_stops_instead_of_reversing() -> None:
    obs = _circle(30, speed=8.0, accel=-4.0)  # stops 2 s after the start
    imm = ImmPredictor()
    for o in obs[:12]:
        imm.update(o)
    far = imm.predict(obs[11].t + 10.0)
    later = imm.predict(obs[11].t + 20.0)
    # CV and CT keep rolling; the CA mode (dominant) stops: the mixture moves little.
    assert far.y < obs[11].y + 8.0 * 10.0 * 0.5
    assert later.y - far.y < 0.5 * (far.y - obs[11].y)


def test_fresh_bsm_is_its_own_estimate_and_bad_input() -> None:
    imm = make_predictor("imm")
    with pytest.raises(LookupError):
        imm.predict(0.0)
    obs = _circle(20, yaw_deg=5.0, noise=0.3)
    for o in obs:
        imm.update(o)
    p = imm.predict(obs[-1].t)
    assert (p.x, p.y) == pytest.approx((obs[-1].x, obs[-1].y), abs=1e-9)
    imm.update(obs[5])  # an old one: ignored
    assert imm.predict(obs[-1].t).x == pytest.approx(p.x, abs=1e-12)
    with pytest.raises(ValueError):
        imm.update(Observation(obs[-1].t + 0.1, 0.0, 0.0, -1.0, 0.0))
    with pytest.raises(ValueError):
        ImmPredictor(p_stay=1.0)
    imm.reset()
    with pytest.raises(LookupError):
        imm.predict(0.0)
