"""The HGP predictor: slope-conditioned posterior, integration, hybrid switching, protocol."""

from __future__ import annotations

import math

import numpy as np
import pytest

from catc.predict import gp
from catc.predict.bank import KernelBank
from catc.predict.base import Observation
from catc.predict.hgp import (
    HgpConfig,
    HgpDirectPredictor,
    HgpPredictor,
    integrate,
    posterior_with_slope,
)

BANK = KernelBank(np.array([[3.0, 1.0, 0.5], [1.0, 0.3, 0.05]]),
                  np.array([[3.0, 0.05, 0.05], [1.0, 0.02, 0.01]]))
NO_SWITCH = dict(accel_max=1e9, yaw_rate_max=1e9, lat_accel_max=1e9, speed_std_max=1e9,
                 heading_std_max=1e9)


def drive(n: int, v0: float = 15.0, a: float = 0.0, yaw: float = 0.0, dt: float = 0.1,
          heading0: float = 90.0) -> list[Observation]:
    """Exact samples of a vehicle with constant acceleration and yaw rate (deg/s, cw)."""
    out, x, y, v, h = [], 0.0, 0.0, v0, heading0
    for k in range(n):
        out.append(Observation(k * dt, x, y, v, h % 360.0, a, yaw))
        sub = 100
        for _ in range(sub):  # fine Euler integration of the truth
            x += v * math.sin(math.radians(h)) * dt / sub
            y += v * math.cos(math.radians(h)) * dt / sub
            v = max(0.0, v + a * dt / sub)
            h += yaw * dt / sub
    return out


def test_slope_posterior_equals_brute_force_conditioning():
    """Build the joint covariance of (f(τ_i), f′(0), f(t*)) by finite differences of κ and
    condition numerically; the closed form must agree."""
    rng = np.random.default_rng(0)
    theta = np.array([1.7, 0.8, 0.3])
    tau = -np.sort(rng.uniform(0, 3, 12))[::-1]
    tau[-1] = 0.0
    y = rng.normal(size=12)
    grid = np.linspace(0, 3, 7)
    h = 1e-4

    def k(a, b):
        return gp.kernel(np.atleast_1d(a), np.atleast_1d(b), theta)

    kfd = lambda t: (k(t, h) - k(t, -h))[:, 0] / (2 * h)  # noqa: E731
    kdd = float((k(h, h) - k(h, -h) - k(-h, h) + k(-h, -h))[0, 0] / (4 * h * h))
    noise, slope, slope_var = 1e-3, 0.4, 1e-2
    n = len(tau)
    K = np.zeros((n + 1, n + 1))
    K[:n, :n] = k(tau, tau) + noise * np.eye(n)
    K[:n, n] = K[n, :n] = kfd(tau)
    K[n, n] = kdd + slope_var
    Ks = np.vstack([k(tau, grid), kfd(grid)])
    mean = Ks.T @ np.linalg.solve(K, np.append(y, slope))
    var = np.diag(k(grid, grid)) - np.sum(Ks * np.linalg.solve(K, Ks), axis=0)
    got_mean, got_var = posterior_with_slope(tau, y, slope, slope_var, grid, theta, noise)
    assert np.allclose(got_mean, mean, atol=1e-6)
    assert np.allclose(got_var, var, atol=1e-6)


def test_integration_rules():
    tau = np.arange(11) * 0.1
    speed = 10.0 + 2.0 * tau  # 2 m/s² along north
    heading = np.zeros(11)
    _x, y = integrate(0.0, 0.0, tau, speed, heading, np.zeros(11), "trapezoid")
    assert y[-1] == pytest.approx(10.0 * 1.0 + 0.5 * 2.0 * 1.0, abs=1e-12)  # exact for linear
    _, y_left = integrate(0.0, 0.0, tau, speed, heading, np.zeros(11), "left")
    assert y_left[-1] == pytest.approx(11.0 - 0.1, abs=1e-9)  # Riemann sum lags by a·Δt·T/2
    # heading variance shrinks the expected displacement by exp(-σ²/2) (paper's E[cos h])
    _, y_var = integrate(0.0, 0.0, tau, np.full(11, 10.0), heading, np.full(11, 0.5))
    assert y_var[-1] == pytest.approx(10.0 * math.exp(-0.25), rel=1e-12)
    with pytest.raises(ValueError):
        integrate(0.0, 0.0, tau, speed, heading, np.zeros(11), "simpson")


@pytest.mark.parametrize("slopes", [True, False])
def test_constant_velocity_is_forecast_exactly(slopes):
    p = HgpPredictor(BANK, HgpConfig(slopes=slopes))
    for o in drive(30):
        p.update(o)
    truth = drive(60)
    for k in (31, 40, 59):
        r = p.predict(truth[k].t)
        assert math.hypot(r.x - truth[k].x, r.y - truth[k].y) < 0.05
        assert r.source == "gp"


def test_slopes_carry_the_bsm_acceleration_and_yaw_rate():
    """A vehicle that has just started braking and turning: its history shows neither yet,
    only the BSM's acceleration and yaw rate do.  With slopes the forecast follows them."""
    hist = drive(30, v0=20.0)
    last = Observation(hist[-1].t + 0.1, hist[-1].x + 2.0, hist[-1].y, 20.0, 90.0, -4.0, 10.0)
    with_s = HgpPredictor(BANK, HgpConfig(slopes=True, **NO_SWITCH))
    without = HgpPredictor(BANK, HgpConfig(slopes=False, **NO_SWITCH))
    for p in (with_s, without):
        for o in [*hist, last]:
            p.update(o)
    a, b = with_s.predict(last.t + 2.0), without.predict(last.t + 2.0)
    assert b.speed == pytest.approx(20.0, abs=0.1) and b.heading == pytest.approx(90.0, abs=0.1)
    assert a.speed < b.speed - 1.0  # braking is forecast only with slopes
    assert a.heading > b.heading + 3.0  # so is the turn


def test_negative_speed_switches_to_a_stop():
    p = HgpPredictor(BANK, HgpConfig(**NO_SWITCH))
    for o in drive(30, v0=9.0, a=-2.5):  # braking, 1.75 m/s left at the last BSM
        p.update(o)
    last = p._obs[-1]
    far = p.predict(last.t + 5.0)
    later = p.predict(last.t + 8.0)
    assert far.source == "ca" and far.speed == 0.0
    assert (far.x, far.y) == (later.x, later.y)  # stopped means stopped
    assert far.x - last.x < 1.75 * 5.0  # it stopped well short of constant speed
    assert p.stats["switch_ca"] >= 1


@pytest.mark.parametrize("limit", [{"accel_max": 0.5}, {"speed_std_max": 1e-4},
                                   {"heading_std_max": 1e-4}])
def test_each_plausibility_criterion_switches_to_constant_speed(limit):
    cfg = HgpConfig(**{**NO_SWITCH, **limit})
    p = HgpPredictor(BANK, cfg)
    for o in drive(31, v0=10.0, a=2.0):
        p.update(o)
    r = p.predict(p._obs[-1].t + 3.0)
    assert r.source == "cs"
    assert p.stats["switch_cs"] == 1


def test_yaw_rate_criterion():
    p = HgpPredictor(BANK, HgpConfig(**{**NO_SWITCH, "yaw_rate_max": 5.0}))
    for o in drive(31, v0=10.0, yaw=30.0):
        p.update(o)
    assert p.predict(p._obs[-1].t + 2.0).source == "cs"


def test_protocol_rules():
    p = HgpPredictor(BANK)
    with pytest.raises(LookupError):
        p.predict(0.0)
    obs = drive(5)
    for o in obs:
        p.update(o)
    p.update(obs[2])  # a replay is ignored
    r = p.predict(obs[-1].t)
    assert (r.x, r.y, r.source) == (obs[-1].x, obs[-1].y, "bsm")
    with pytest.raises(ValueError):
        p.predict(obs[-1].t - 1.0)
    p.reset()
    with pytest.raises(LookupError):
        p.predict(1.0)


def test_too_little_history_falls_back_to_ca():
    p = HgpPredictor(BANK)
    o = Observation(0.0, 0.0, 0.0, 10.0, 0.0, -2.0, 0.0)
    p.update(o)
    r = p.predict(2.0)
    assert r.source == "ca" and r.y == pytest.approx(10.0 * 2 - 0.5 * 2 * 4)


def test_online_models_are_created_and_bounded():
    cfg = HgpConfig(online=True, online_max=2, pte_th=1e-6)
    p = HgpPredictor(BANK, cfg)
    for k, o in enumerate(drive(60, v0=12.0, a=1.0, yaw=5.0)):
        p.update(o)
        if k >= 30:
            p.predict(o.t + 0.5)
    assert p.stats["online_models"] > 2
    assert len(p._state.online_speed) == 2


def test_direct_hgp_on_constant_velocity():
    p = HgpDirectPredictor()
    for o in drive(30, v0=15.0, heading0=30.0):
        p.update(o)
    truth = drive(50, v0=15.0, heading0=30.0)
    r = p.predict(truth[45].t)
    assert math.hypot(r.x - truth[45].x, r.y - truth[45].y) < 0.2
    assert r.heading == pytest.approx(30.0, abs=1.0)


def test_batched_slope_likelihood_equals_the_joint_gaussian():
    from scipy.stats import multivariate_normal

    from catc.predict.hgp.reference import lml_with_slope, slope_system

    rng = np.random.default_rng(4)
    tau = np.append(-np.sort(rng.uniform(0.1, 3, 9))[::-1], 0.0)
    y, slope = rng.normal(size=10), 0.3
    thetas = np.array([[1.7, 0.8, 0.3], [0.5, 0.1, 0.02], [20.0, 1.5, 0.9]])
    got = lml_with_slope(tau, y, slope, 1e-2, thetas, 1e-3)
    for theta, value in zip(thetas, got, strict=True):
        K, _ = slope_system(tau, theta, 1e-3, 1e-2)
        assert value == pytest.approx(
            multivariate_normal(np.zeros(11), K).logpdf(np.append(y, slope)), abs=1e-8)


def test_regular_grid_selection_cache_equals_the_direct_likelihood():
    from catc.predict.hgp import RegularSlopeBank, lml_with_slope

    rng = np.random.default_rng(5)
    thetas = np.array([[1.7, 0.8, 0.3], [0.5, 0.1, 0.02], [20.0, 1.5, 0.9]])
    cache = RegularSlopeBank(thetas, 30, 0.01, 0.005)
    y = np.cumsum(rng.normal(size=30)) * 0.1
    y -= y[-1]
    assert np.allclose(cache.lml(y, 0.4), lml_with_slope(cache.tau, y, 0.4, 0.005, thetas, 0.01),
                       atol=1e-8)


@pytest.mark.parametrize("samples", [30, 15, 4])
def test_predictor_uses_the_cache_only_on_regular_windows(samples):
    """A window of samples DT apart uses the regular grid's cache of its length (a full
    one, or a vehicle heard for fewer than tw samples): the same forecast, to round-off,
    as the direct path; a lost message means no cache."""
    p = HgpPredictor(BANK)
    obs = drive(40, v0=12.0, a=0.5, yaw=3.0)
    for o in obs[:samples]:
        p.update(o)
    full = p._state.regular_cache(np.arange(-29, 1) * 0.1)
    short = p._state.regular_cache(np.arange(-28, 1) * 0.1)
    assert full is not None and short is not None and short is not full
    assert short[0].Kinv.shape[1] == 30  # 29 values and the slope
    assert p._state.regular_cache(np.array([0.0])) is None
    tau = np.arange(-29, 1) * 0.1
    tau[3] += 0.05
    assert p._state.regular_cache(tau) is None  # a lost message
    t = obs[samples - 1].t + 1.5
    a = p.predict(t)
    q = HgpPredictor(BANK, HgpConfig(select_with_slopes=True))
    q._state.regular_cache = lambda tau: None  # force the direct path
    for o in obs[:samples]:
        q.update(o)
    b = q.predict(t)
    assert (a.x, a.y) == (pytest.approx(b.x, abs=1e-9), pytest.approx(b.y, abs=1e-9))
    assert q._state.selection.index == p._state.selection.index


def test_regular_cache_belongs_to_its_bank():
    """Two banks never share cached factors, even if one is created after the other is gone."""
    obs = drive(30, v0=12.0, a=0.5, yaw=3.0)
    tau = np.arange(-29, 1) * 0.1
    p1 = HgpPredictor(BANK)
    other = KernelBank(BANK.speed * 2.0, BANK.heading * 2.0)
    p2 = HgpPredictor(other)
    for o in obs:
        p1.update(o)
        p2.update(o)
    c1, c2 = p1._state.regular_cache(tau), p2._state.regular_cache(tau)
    assert c1 is not c2
    assert not np.allclose(c1[0].Kinv, c2[0].Kinv)


# -- the fast path: same forecasts as the readable formulas ------------------------------


def random_track(rng, n: int, per: float, dt: float = 0.1) -> list[Observation]:
    """A random drive (acceleration and yaw rate random walks, heading wrapping through
    north) sampled at 10 Hz, each sample kept with probability 1 − ``per`` (the last always)."""
    out, t, x, y = [], 100.0, 0.0, 0.0
    v, h = 5.0 + 25.0 * rng.random(), 360.0 * rng.random()
    a, w = rng.normal(0.0, 1.0), rng.normal(0.0, 8.0)
    for k in range(n):
        t = round(t + dt, 1)
        a = float(np.clip(a + rng.normal(0.0, 0.4), -6.0, 3.0))
        w = float(np.clip(w + rng.normal(0.0, 2.0), -40.0, 40.0))
        v = max(0.0, v + a * dt)
        h = (h + w * dt) % 360.0
        x += v * math.sin(math.radians(h)) * dt
        y += v * math.cos(math.radians(h)) * dt
        if rng.random() >= per or k == n - 1:
            out.append(Observation(t, x, y, v, h, a, w))
    return out


def assert_same_forecast(f, g):
    """Equal to 1e-9 m over the OBU's 3 s forecasts.  Longer ones may differ by more, by
    round-off alone: a heading GP with a 3e-5 rad² noise has a covariance of condition
    number ~1e7, and two float64 factorisations of it (LAPACK's and the compiled kernel's)
    each land ~2e-11 rad from the exact posterior (checked with mpmath on the worst window
    here); that difference, times speed and time, integrates to ~1e-9 m at 7 s.  So past
    3 s the bound grows with the square of the horizon."""
    assert tuple(f.source) == tuple(g.source)
    assert np.array_equal(f.tau, g.tau)
    atol = 1e-9 * max(1.0, f.tau[-1] / 3.0) ** 2
    for name in ("x", "y", "speed", "var_x", "var_y"):
        assert np.allclose(getattr(f, name), getattr(g, name), rtol=0.0, atol=atol), name
    dh = (f.heading - g.heading + 180.0) % 360.0 - 180.0
    assert np.max(np.abs(dh)) < 1e-7  # degrees: 2e-9 rad


@pytest.mark.parametrize("overrides", [
    {}, {"slopes": False, "select_with_slopes": False}, {"select_with_slopes": False},
    {"integration": "left", "heading_damping": False}, {"window_s": 4.0},
    {"speed_model": "ca", "heading_model": "ctrv"}, {"accel_max": 1.0, "yaw_rate_max": 5.0},
])
def test_fast_forecast_equals_the_readable_formulas(overrides):
    """Random windows, regular (no loss: the cached selection and posterior weights) and
    irregular (direct likelihoods), short and full, over long gaps too: the fast forecast
    equals the reference implementation (the code before it was made fast) to 1e-9."""
    rng = np.random.default_rng(11)
    cfg = HgpConfig(**overrides)
    regular = irregular = 0
    for trial in range(36):
        per = (0.0, 0.5, 0.9, 0.97)[trial % 4]
        p = HgpPredictor(config=cfg)
        for o in random_track(rng, int(rng.integers(8, 120)), per):
            p.update(o)
        if len(p._obs) < 4:
            continue
        _, cache = p._state.prepare()
        regular += cache is not None
        irregular += cache is None
        for horizon in (3.0, 7.35):
            assert_same_forecast(p._make_forecast(horizon), p._make_forecast_reference(horizon))
    assert regular >= 3 and irregular >= 10


def test_running_window_equals_the_observation_window():
    """The running arrays (kept across wrap-arounds of their buffer and of the heading
    through north) give the same τ, speed and unwrapped heading as window_series."""
    from catc.predict.hgp.reference import window_series

    rng = np.random.default_rng(3)
    for window_s in (math.inf, 2.5):
        p = HgpPredictor(config=HgpConfig(window_s=window_s))
        for k, o in enumerate(random_track(rng, 400, 0.3)):
            p.update(o)
            if k % 7 == 0 and len(p._obs) >= 2:
                rel, _ = p._state.prepare()
                tau, ys, yh, _, _ = window_series(p._obs, window_s)
                n = len(tau)
                assert rel.shape == (3, n + 1)
                assert np.allclose(rel[:, :n], [tau, ys, yh], rtol=0.0, atol=1e-12)
        p.reset()
        with pytest.raises(LookupError):
            p.predict(1.0)


def test_only_windows_of_distinct_grid_steps_get_a_table():
    """The table of exponentials per DT step needs every time on the grid, one sample per
    step, ascending; anything else gets an exponential per element."""
    from catc.predict.hgp.gpstack import on_grid

    ok = np.array([[-0.3, -0.1 + 2e-7, 0.0]])
    assert on_grid(ok)[1].tolist() == [[3, 1, 0]]
    assert on_grid(ok)[0].tolist() == [[-0.30000000000000004, -0.1, -0.0]]
    for bad in ([-0.3, -0.15, 0.0], [-0.1, -0.1 + 5e-7, 0.0], [-0.1, -0.3, 0.0],
                [-900.0, -0.1, 0.0]):  # off the grid, one step twice, descending, too long
        tau, steps = on_grid(np.array([bad]))
        assert steps is None and tau.tolist() == [bad]


@pytest.mark.parametrize("aligned", [False, True], ids=["off-grid", "on-grid"])
def test_stacked_likelihood_and_posterior_equal_the_readable_formulas(aligned):
    """Times anywhere (an exponential per covariance element) and on the 0.1 s grid of
    received BSMs (a table per DT step, gpstack._window_exps), one window spanning 80 s."""
    from catc.predict.hgp import lml_with_slope
    from catc.predict.hgp.gpstack import lml_stack, on_grid, posterior_stack, series_consts

    rng = np.random.default_rng(8)
    cfg = HgpConfig()
    speed = np.array([[1.7, 0.8, 0.3], [0.31, 5.0, 0.02], [90.0, 1.5, 0.9]])
    heading = np.array([[3.0, 0.05, 0.05], [0.3, 2.0, 0.01], [60.0, 1e-4, 1e-5]])
    thetas = np.vstack([speed, heading])
    consts = series_consts(thetas, 3, cfg)
    grid = np.arange(31) * 0.1
    rels, pairs, wants = [], [], []
    for span in (2.9, 12.0, 80.0):  # the last underflows exp for the short γ
        tau = np.append(-np.sort(rng.uniform(0.05, span, 19))[::-1], 0.0)
        if aligned:  # distinct steps back, with the rounding of epoch-second times
            tau[:19] = -np.sort(rng.choice(np.arange(1, int(span * 10)), 19, replace=False)
                                )[::-1] * 0.1 + rng.uniform(-2e-7, 2e-7, 19)
        snapped, steps = on_grid(tau[None])
        assert (steps is not None) == aligned
        if aligned:  # what the times mean: whole steps of 0.1 s
            assert np.abs(snapped[0] - tau).max() < 3e-7
            tau = snapped[0]
        z = np.vstack([np.append(np.cumsum(rng.normal(size=20)) * 0.1, 0.4),
                       np.append(np.cumsum(rng.normal(size=20)) * 0.01, -0.05)])
        z[:, 19] = 0.0
        got = lml_stack(tau[None], z[None], consts, 3, thetas)[0]
        wants.append(np.concatenate([
            lml_with_slope(tau, z[0, :20], z[0, 20], cfg.noise_accel, speed, cfg.noise_speed),
            lml_with_slope(tau, z[1, :20], z[1, 20], cfg.noise_yaw, heading,
                           cfg.noise_heading)]))
        assert np.allclose(got, wants[-1], rtol=1e-12, atol=1e-8)
        rels.append(np.vstack([np.append(tau, 0.0), z]))
        pairs.append((int(rng.integers(3)), int(rng.integers(3))))
    stacked = np.stack(rels)  # several windows in one call
    assert np.allclose(lml_stack(stacked[:, 0, :-1], stacked[:, 1:], consts, 3, thetas),
                       wants, rtol=1e-12, atol=1e-8)
    mean, var = posterior_stack(np.stack(rels), grid,
                                 np.stack([consts[[i, 3 + j]] for i, j in pairs]))
    for b, (rel, (i, j)) in enumerate(zip(rels, pairs, strict=True)):
        for s, (theta, noise, slope_var) in enumerate(
                [(speed[i], cfg.noise_speed, cfg.noise_accel),
                 (heading[j], cfg.noise_heading, cfg.noise_yaw)]):
            m, v = posterior_with_slope(rel[0, :20], rel[1 + s, :20], rel[1 + s, 20],
                                        slope_var, grid, theta, noise)
            assert np.allclose(mean[b, s], m, rtol=0.0, atol=1e-9)
            assert np.allclose(var[b, s], v, rtol=0.0, atol=1e-9)


def test_plausibility_bound_never_passes_a_switch():
    """The cheap bound on the extremes never calls a forecast plausible that implausible
    would cut (it only skips work); forecasts built to sit near every threshold."""
    from catc.predict.hgp.reference import implausible
    from catc.predict.hgp.stacked import plausible_rows

    rng = np.random.default_rng(2)
    p = HgpPredictor(BANK)
    c = p.config
    grid = np.arange(31) * 0.1
    passed = cut = 0
    for _ in range(3000):
        speed = rng.uniform(0.0, 30.0) + np.cumsum(rng.normal(0, rng.uniform(0.01, 0.3), 31))
        head = np.cumsum(rng.normal(0, rng.uniform(0.0005, 0.015), 31))
        vs = rng.uniform(0, 1, 31) * rng.uniform(0, 1.1 * c.speed_std_max**2)
        vh = rng.uniform(0, 1, 31) * rng.uniform(0, 1.1 * math.radians(c.heading_std_max)**2)
        ext = [speed.min(), speed.max(), np.abs(np.diff(speed)).max(),
               np.abs(np.diff(head)).max(), vs.max(), vh.max()]
        found = implausible(c, grid, speed, vs, head, vh)
        if plausible_rows(c, np.array([ext]))[0]:
            passed += 1
            assert found is None
        cut += found is not None
    assert passed > 300 and cut > 300


def test_reselection_every_k_samples_and_after_gaps():
    cfg = HgpConfig(reselect_every=3, reselect_gap_s=0.25, reselect_fit_m=0.0)
    p = HgpPredictor(BANK, cfg)
    obs = drive(60, v0=12.0, a=0.3, yaw=2.0)
    counts = []
    for o in obs[:20]:
        p.update(o)
        if len(p._obs) >= cfg.min_points:
            p.predict(o.t + 0.5)
            p.predict(o.t + 1.5)  # no new sample: never a new selection
        counts.append(p.stats["selections"])
    assert counts[3:] == [1 + (k - 3) // 3 for k in range(3, 20)]
    p.update(obs[22])  # two messages lost: a gap of 0.3 s > 0.25 s
    p.predict(obs[22].t + 0.5)
    assert p.stats["selections"] == counts[-1] + 1
    p.update(obs[24])  # one lost (0.2 s): counted, not a gap
    p.predict(obs[24].t + 0.5)
    assert p.stats["selections"] == counts[-1] + 1
    every = HgpPredictor(BANK, HgpConfig(reselect_every=1))
    for o in obs[:20]:
        every.update(o)
        if len(every._obs) >= 4:
            every.predict(o.t + 0.5)
    assert every.stats["selections"] == 17
    with pytest.raises(ValueError):  # checked by the configuration itself
        HgpConfig(reselect_every=0)


def test_a_gap_the_models_forecast_well_keeps_the_selection():
    """``reselect_fit_m``: a long gap reselects only when the GP's forecast over it, made
    with the models in use, missed the BSM that ends it by more than that."""
    obs = drive(60, v0=12.0, a=0.3, yaw=2.0)
    for fit, moved, again in ((0.0, 0.0, True), (0.25, 0.0, False), (0.25, 1.0, True)):
        p = HgpPredictor(BANK, HgpConfig(reselect_every=100, reselect_fit_m=fit))
        for o in obs[:20]:
            p.update(o)
            p.predict(o.t + 0.1)
        before = p.stats["selections"]
        assert before == 1
        end = obs[23]._replace(x=obs[23].x + moved)  # three lost: 0.4 s
        p.update(end)
        p.predict(end.t + 0.1)
        assert p.stats["selections"] == before + again, (fit, moved)


def test_reused_selection_is_the_selection_made_then():
    """Between reselections the forecast uses the θ chosen at the last one (model
    persistency), not a new choice; with reselect_every=1 it equals the reference."""
    rng = np.random.default_rng(5)
    track = random_track(rng, 80, 0.5)
    lazy = HgpPredictor(config=HgpConfig(reselect_every=1000, reselect_gap_s=math.inf))
    fresh = HgpPredictor(config=HgpConfig(reselect_every=1))
    first = None
    for o in track:
        lazy.update(o)
        fresh.update(o)
        if len(lazy._obs) >= 4:
            lazy.predict(o.t + 0.1)
            fresh.predict(o.t + 0.1)
            first = first or lazy._state.selection
            assert lazy._state.selection is first
    ref = fresh._make_forecast_reference(3.0)
    assert_same_forecast(fresh._make_forecast(3.0), ref)
    assert fresh.stats["selections"] > 20 and lazy.stats["selections"] == 1


def test_forecast_many_equals_predicting_one_by_one():
    from catc.predict.hgp import forecast_many
    from catc.predict.kinematic import ConstantSpeedPredictor

    rng = np.random.default_rng(9)
    tracks = [random_track(rng, 160, per) for per in (0.0, 0.3, 0.5, 0.5, 0.8, 0.95) * 4]
    cfg = HgpConfig(reselect_every=4, reselect_gap_s=0.25)
    batch = [HgpPredictor(config=cfg) for _ in tracks]
    alone = [HgpPredictor(config=cfg) for _ in tracks]
    others = [ConstantSpeedPredictor(), HgpPredictor(config=cfg)]  # left alone
    made = compared = 0
    times = sorted({o.t for tr in tracks for o in tr})
    for t in times:
        for tr, b, a in zip(tracks, batch, alone, strict=True):
            for o in tr:
                if o.t == t:
                    b.update(o)
                    a.update(o)
        made += forecast_many([*batch, *others], t + 2.0)
        for b, a in zip(batch, alone, strict=True):
            for when in (t, t + 2.0):
                try:
                    pa = a.predict(when)
                except (LookupError, ValueError):
                    with pytest.raises((LookupError, ValueError)):
                        b.predict(when)
                    continue
                pb = b.predict(when)
                assert pb.source == pa.source
                assert np.allclose([pb.x, pb.y, pb.speed, pb.var_x, pb.var_y],
                                   [pa.x, pa.y, pa.speed, pa.var_x, pa.var_y], atol=1e-9,
                                   equal_nan=True)
                assert abs((pb.heading - pa.heading + 180) % 360 - 180) < 1e-7
                compared += 1
    assert made > 1000 and compared > 4000
    assert sum(b.stats["forecasts"] for b in batch) == made
    assert forecast_many(batch, times[-1] + 2.0) == 0  # all cached already


def test_predict_columns_are_exactly_the_one_by_one_predictions():
    """The CA-TC reads every RV's state at now and now + 2 s as columns
    (catc.predict.predict_columns: forecasts read all at once, branch and BSM answers
    one by one): the very numbers of predict(), bit for bit, whichever branch answers,
    beyond the forecast's end too; other predictors in the same call are asked
    directly."""
    from catc.predict import make_predictor, predict_columns, prepare

    rng = np.random.default_rng(4)
    tracks = [random_track(rng, 120, per) for per in (0.0, 0.3, 0.5, 0.8, 0.95) * 4]
    preds = [HgpPredictor() for _ in tracks] + [make_predictor("kf"), make_predictor("ca")]
    tracks += [tracks[0], tracks[1]]
    times = sorted({o.t for tr in tracks for o in tr})
    kinds: set[str] = set()
    for t in times[5:]:
        for tr, p in zip(tracks, preds, strict=True):
            for o in tr:
                if o.t == t:
                    p.update(o)
        live = [p for p in preds if (p._obs if isinstance(p, HgpPredictor) else p._t
                                     if hasattr(p, "_t") else p._last)]
        for later in (t + 2.0, t + 4.5):  # 4.5 s: past a 3 s forecast's end
            if later == t + 2.0:
                prepare(live, later)  # as the CA-TC does: then no call makes a forecast
            cols, sources = predict_columns(live, t, later)
            for i, p in enumerate(live):
                a, b = p.predict(t), p.predict(later)
                np.testing.assert_array_equal(  # NaN (no variance) equals NaN here
                    cols[:, i], [a.x, b.x, a.y, b.y, a.speed, b.speed, a.heading,
                                 b.heading, a.var_x, a.var_y])
                assert sources[i] == a.source
                kinds.add(a.source)
                kinds.add(b.source)
    assert {"bsm", "gp", "ca", "kf"} <= kinds
    # the branch score's reader: read()'s position, to the bit, within and beyond the end
    from catc.predict.forecast import read, read_xy

    f = next(p._forecast for p in preds if getattr(p, "_forecast", None) is not None)
    for tau in np.linspace(0.0, f.end + 1.5, 97).tolist():
        r = read(f, tau)
        assert read_xy(f, tau) == (r.x, r.y)


def test_the_batch_interface_is_declared_not_discovered():
    """predict_columns and prepare_at ask the registry of catc.predict.base, by class: the
    HGP (and its subclasses) plans and prepares, hgp-d and the kinematic ones do neither;
    a class declaring plans without plan and plan_pair is refused."""
    from catc.predict import make_predictor
    from catc.predict.base import BatchSupport, batch_support, register_batch
    from catc.predict.hgp import forecast_many_at

    class Sub(HgpPredictor):
        pass

    for cls in (HgpPredictor, Sub):
        assert batch_support(cls) == BatchSupport(forecast_many_at, plans=True)
    for name in ("hgp-d", "ca", "kf", "imm"):
        assert batch_support(type(make_predictor(name))) is None, name

    class NoPlans:
        pass

    with pytest.raises(TypeError, match="plan"):
        register_batch(NoPlans, plans=True)
    assert batch_support(NoPlans) is None


def test_branches_answer_where_their_recent_gaps_were_better():
    """A vehicle on an exact constant-acceleration path with every other BSM lost: CA
    predicts each gap's end (to the truth's integration error), the GP does not quite,
    so CA answers gaps of that class (its prediction, exactly); a longer gap, a class not
    scored yet, is the GP's; reset forgets the scores."""
    obs = drive(80, v0=12.0, a=1.5, heading0=30.0)
    p = HgpPredictor(BANK, HgpConfig(branches=("ca",), branch_margin=1.0))
    from catc.predict import make_predictor

    ref = make_predictor("ca")
    for o in obs[:60:2]:
        p.update(o)
        ref.update(o)
        p.predict(o.t + 0.1)  # the gap is bridged (the OBU asks at every tick)
    last = obs[58]
    assert p.branch(0.2) == 1 and p.branch(5.0) == 0
    got, want = p.predict(last.t + 0.2), ref.predict(last.t + 0.2)
    assert (got.x, got.y, got.source) == (want.x, want.y, want.source)
    assert p.predict(last.t + 5.0).source in ("gp", "cs", "ca")
    score = p._branches.score[0]
    assert score[0] > 2.0 * score[1]  # squared errors (GP 0.4 mm, CA 0.15 mm)
    p.reset()
    assert p.branch(0.2) == 0 and not any(p._branches.scored)
    # a branch without position() (the IMM) is scored by its predict()'s x and y
    p = HgpPredictor(BANK, HgpConfig(branches=("imm", "ca"), branch_margin=1.0))
    assert not hasattr(p._branches.kin[0], "position")
    for o in obs[:60:2]:
        p.update(o)
        p.predict(o.t + 0.1)
    assert p._branches.scored[0] > 20 and p._branches.score[0][1] > 0.0 and p.branch(0.2) in (1, 2)


def test_blend_weights_branches_by_inverse_score_and_drops_the_bad_ones():
    """branch_blend: the answer in a gap is the branches' answers (the GP's read of its
    forecast, CA's) averaged with weights 1/score over those scoring within the ratio
    of the best; the same run with ratio 1 keeps only the best branch."""
    from catc.predict import make_predictor
    from catc.predict.forecast import read

    obs = drive(80, v0=12.0, a=1.5, heading0=30.0)
    for ratio in (math.inf, 1.0):
        p = HgpPredictor(BANK, HgpConfig(branches=("ca",), branch_blend=ratio))
        ref = make_predictor("ca")
        for o in obs[:60:2]:
            p.update(o)
            ref.update(o)
            p.predict(o.t + 0.1)
        t = obs[58].t + 0.2
        got, gp, ca = p.predict(t), read(p._forecast, p._since_last(t)[1]), ref.predict(t)
        s_gp, s_ca = p._branches.score[0]
        assert s_gp > 2.0 * s_ca > 0.0
        w_ca = (1 / s_ca) / (1 / s_gp + 1 / s_ca) if ratio > 1 else 1.0
        assert got.x == pytest.approx((1 - w_ca) * gp.x + w_ca * ca.x, abs=1e-12)
        assert got.y == pytest.approx((1 - w_ca) * gp.y + w_ca * ca.y, abs=1e-12)
        assert got.speed == pytest.approx((1 - w_ca) * gp.speed + w_ca * ca.speed, abs=1e-12)
        assert (got.var_x, got.var_y) == (gp.var_x, gp.var_y)
        assert min(gp.x, ca.x) <= got.x <= max(gp.x, ca.x) and gp.x != ca.x


def test_the_margin_can_differ_by_gap_class():
    """branch_margin per gap class: the class of one-BSM gaps follows its own margin
    (CA's score there is ~1/3 of the GP's: margin 1 takes CA, 0.1 keeps the GP); one
    number, int or float, is every class's; a list of the wrong length is refused."""
    obs = drive(80, v0=12.0, a=1.5, heading0=30.0)
    for margins, want in (((1.0, 0.1, 0.1, 0.1), 1), ((0.1, 1.0, 1.0, 1.0), 0), (1, 1)):
        p = HgpPredictor(BANK, HgpConfig(branches=("ca",), branch_margin=margins))
        for o in obs[:60:2]:
            p.update(o)
            p.predict(o.t + 0.1)
        assert p.branch(0.2) == want
    with pytest.raises(ValueError, match="one per gap class"):
        HgpConfig(branch_margin=(1.0, 0.5))
    with pytest.raises(ValueError, match="ascending"):
        HgpConfig(branch_edges=(1.0, 0.5))
    with pytest.raises(ValueError, match="kinematic predictors"):
        HgpConfig(branches=("ca", "hgp"))


def test_before_any_scored_gap_the_gp_answers():
    obs = drive(60, v0=12.0, a=1.5)
    a, b = HgpPredictor(BANK), HgpPredictor(BANK, HgpConfig(branches=()))
    for o in obs[:58]:  # no BSM lost: nothing scored
        a.update(o)
        b.update(o)
    assert a.predict(obs[57].t + 0.7) == b.predict(obs[57].t + 0.7)


def test_kernel_bench_agrees_with_lapack():
    """bench/gp_kernels.py runs, and its compiled rows give LAPACK's likelihoods and
    posterior means (to the round-off of 31 × 31 systems of condition up to ~1e7)."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    bench = Path(__file__).resolve().parent.parent / "bench" / "gp_kernels.py"
    out = subprocess.run([sys.executable, str(bench), "--json", "--windows", "3",
                          "--forecasts", "3", "--repeat", "1"], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res["selections"]["kernel"]["max_diff"] < 1e-6
    assert res["posteriors"]["kernel"]["max_diff"] < 1e-8
    assert all(r["ms"] > 0 for key in ("selections", "posteriors")
               for r in res[key].values() if isinstance(r, dict))


def test_compiled_row_passes_are_the_numpy_reductions():
    """gpkernels.shift_rows (the first pass of finish_stack) against the numpy it
    replaced: the shifted means, the clipped variances and the extremes bit for bit,
    NaN where numpy's reductions give NaN (such a row is never plausible)."""
    from catc.predict import gpkernels
    from catc.predict.hgp.stacked import plausible_rows

    rng = np.random.default_rng(8)
    mean = rng.normal(0, 3, (40, 2, 31))
    var = rng.normal(0.1, 0.2, (40, 2, 31))  # some negative: clipped to 0
    start = rng.normal(0, 10, (40, 4))
    mean[3, 0, 7] = np.nan
    var[5, 1, 2] = np.nan
    m, v = mean + start[:, :2, None], np.maximum(var, 0.0)
    want = np.empty((40, 6))
    want[:, 0], want[:, 1] = m[:, 0].min(axis=1), m[:, 0].max(axis=1)
    want[:, 2:4] = np.abs(np.diff(m, axis=2)).max(axis=2)
    want[:, 4:6] = v.max(axis=2)
    ext = np.empty((40, 6))
    gpkernels.shift_rows(mean, var, start, ext)
    np.testing.assert_array_equal(mean, m)
    np.testing.assert_array_equal(var, v)
    ok = ~np.isnan(want).any(axis=1)
    np.testing.assert_array_equal(ext[ok], want[ok])
    assert np.isnan(ext[3]).any() and np.isnan(ext[5]).any()
    c = HgpConfig()
    assert plausible_rows(c, ext).tolist() == plausible_rows(c, want).tolist()
    assert not plausible_rows(c, ext)[[3, 5]].any()


@pytest.mark.parametrize("rule", ["trapezoid", "left"])
def test_compiled_integration_is_the_numpy_one(rule):
    """gpkernels.integrate_rows (positions and position variances of finish_stack) is the
    numpy arithmetic it replaced, bit for bit: rates, trapezoid or left rule, one
    cumulative sum per quantity, heading in degrees wrapped to [0, 360)."""
    from catc.predict import gpkernels
    from catc.predict.forecast import DT
    from catc.predict.hgp.gpstack import forecast_grid

    rng = np.random.default_rng(11)
    bsz, count = 30, 31
    _, dgrid, half = forecast_grid(count)
    mean = np.stack([rng.uniform(0, 30, (bsz, count)),
                     rng.normal(0, 4, (bsz, count))], axis=1)  # headings of any sign
    var = rng.uniform(0, 0.3, (bsz, 2, count))
    start = rng.normal(0, 100, (bsz, 4))
    speed, head, vs, vh = mean[:, 0], mean[:, 1], var[:, 0], var[:, 1]
    sc = np.stack([np.sin(head), np.cos(head)], axis=1)
    eff = speed * np.exp(-0.5 * vh)
    # the numpy passes (what finish_stack did)
    rate = np.empty((bsz, 4, count))
    np.multiply(eff[:, None], sc, out=rate[:, :2])
    rate[:, 2] = vs
    np.multiply(vh, speed * speed, out=rate[:, 3])
    seg = np.empty((bsz, 4, count - 1))
    if rule == "trapezoid":
        np.add(rate[:, :2, 1:], rate[:, :2, :-1], out=seg[:, :2])
        seg[:, :2] *= half
    else:
        np.multiply(rate[:, :2, :-1], dgrid, out=seg[:, :2])
    np.multiply(rate[:, 2:, 1:], DT * DT, out=seg[:, 2:])
    acc = np.empty((bsz, 4, count))
    acc[..., 0] = 0.0
    np.cumsum(seg, axis=2, out=acc[..., 1:])
    want = np.empty((bsz, 6, count))
    np.add(acc[:, :2], start[:, 2:, None], out=want[:, :2])
    want[:, 2] = speed
    np.remainder(np.degrees(head), 360.0, out=want[:, 3])
    sq = sc * sc
    np.multiply(sq, acc[:, 2:3], out=want[:, 4:6])
    want[:, 4:6] += acc[:, 3:4] * sq[:, ::-1]
    got = np.empty((bsz, 6, count))
    gpkernels.integrate_rows(eff, sc, mean, var, start, dgrid, half, rule == "trapezoid",
                             DT * DT, got)
    np.testing.assert_array_equal(got, want)
