"""The HGP Gaussian-process core against scikit-learn, brute force and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from catc.predict.gp import (
    DEFAULT_BOUNDS,
    DEFAULT_NOISE_VAR,
    GPModel,
    RegularGridBank,
    bank_log_marginal_likelihood,
    fit,
    kernel,
    kernel_grads,
    log_marginal_likelihood,
    loo_log_predictive,
    posterior,
)

LOG_BOUNDS = np.log(np.array(DEFAULT_BOUNDS))


def regular(n: int, dt: float = 0.1) -> np.ndarray:
    return (np.arange(n) - (n - 1)) * dt


def window(seed: int, n: int = 30, irregular: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A speed-like window: t ≤ 0 relative to the last sample, y relative to the last value."""
    rng = np.random.default_rng(seed)
    if irregular:
        t = np.sort(np.concatenate([[0.0], -rng.uniform(0.0, 0.1 * (n - 1), n - 1)]))
    else:
        t = regular(n)
    y = np.cumsum(rng.normal(0.0, 0.1, n)) + 0.3 * t
    return t, y - y[-1]


def random_theta(rng: np.random.Generator) -> np.ndarray:
    return np.exp(rng.uniform([-1.5, -1.0, -2.5], [1.5, 1.0, 0.5]))


WINDOWS = [window(0), window(1, irregular=True), window(2, n=12, irregular=True),
           window(3, n=45)]


# ---------------------------------------------------------------- kernel


def test_kernel_is_the_papers_covariance_function():
    t1, t2 = np.array([-1.0, -0.3, 0.0]), np.array([-0.5, 0.0])
    gamma, a1, a2 = 0.7, 1.3, 0.4
    k = kernel(t1, t2, (gamma, a1, a2))
    for i, a in enumerate(t1):
        for j, b in enumerate(t2):
            want = a1**2 * math.exp(-((a - b) ** 2) / (2 * gamma**2)) + a2**2 * a * b
            assert k[i, j] == pytest.approx(want, rel=1e-14)


def test_kernel_grads_match_finite_differences():
    t, _ = window(5, n=10, irregular=True)
    log_theta = np.log([0.8, 1.2, 0.3])
    k, dk = kernel_grads(t, np.exp(log_theta))
    np.testing.assert_allclose(k, kernel(t, t, np.exp(log_theta)), rtol=1e-14)
    h = 1e-6
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        fd = (kernel(t, t, np.exp(log_theta + step)) - kernel(t, t, np.exp(log_theta - step)))
        np.testing.assert_allclose(dk[j], fd / (2 * h), rtol=1e-7, atol=1e-9)


# ---------------------------------------------------------------- sklearn


def sklearn_gpr(theta, noise_var: float):
    gpr_mod = pytest.importorskip("sklearn.gaussian_process")
    kernels = pytest.importorskip("sklearn.gaussian_process.kernels")
    gamma, a1, a2 = theta
    kern = (kernels.ConstantKernel(a1**2, "fixed") * kernels.RBF(gamma, "fixed")
            + kernels.ConstantKernel(a2**2, "fixed")
            * kernels.DotProduct(sigma_0=0.0, sigma_0_bounds="fixed"))
    return gpr_mod.GaussianProcessRegressor(kern, alpha=noise_var, optimizer=None,
                                            normalize_y=False)


@pytest.mark.parametrize("idx", range(len(WINDOWS)))
@pytest.mark.parametrize("noise_var", [DEFAULT_NOISE_VAR, 1e-2])
def test_posterior_matches_sklearn(idx, noise_var):
    t, y = WINDOWS[idx]
    rng = np.random.default_rng(idx)
    theta = random_theta(rng)
    t_star = np.concatenate([np.arange(1, 31) * 0.1, t[::3], rng.uniform(-3.0, 3.0, 5)])
    gpr = sklearn_gpr(theta, noise_var).fit(t[:, None], y)
    want_mean, want_std = gpr.predict(t_star[:, None], return_std=True)
    mean, var = posterior(t, y, t_star, theta, noise_var)
    np.testing.assert_allclose(mean, want_mean, rtol=1e-8, atol=1e-8)
    # sklearn's return_std is the latent f* (alpha is not added), as is ours.
    np.testing.assert_allclose(var, want_std**2, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("idx", range(len(WINDOWS)))
def test_log_marginal_likelihood_matches_sklearn(idx):
    t, y = WINDOWS[idx]
    theta = random_theta(np.random.default_rng(10 + idx))
    gpr_mod = pytest.importorskip("sklearn.gaussian_process")
    kernels = pytest.importorskip("sklearn.gaussian_process.kernels")
    kern = (kernels.ConstantKernel() * kernels.RBF()
            + kernels.ConstantKernel() * kernels.DotProduct(sigma_0=0.0, sigma_0_bounds="fixed"))
    gpr = gpr_mod.GaussianProcessRegressor(kern, alpha=DEFAULT_NOISE_VAR, optimizer=None)
    gpr.fit(t[:, None], y)
    # sklearn's theta is the log of its own hyperparameters: (α1², γ, α2²).
    gamma, a1, a2 = theta
    want = gpr.log_marginal_likelihood(np.log([a1**2, gamma, a2**2]))
    got = log_marginal_likelihood(t, y, theta, DEFAULT_NOISE_VAR)
    assert got == pytest.approx(want, rel=1e-9, abs=1e-9)


def test_gpmodel_reuse_equals_posterior():
    t, y = WINDOWS[1]
    theta = (0.9, 1.1, 0.2)
    model = GPModel(t, y, theta)
    for t_star in (np.array([0.1]), np.arange(1, 31) * 0.1):
        m1, v1 = model.predict(t_star)
        m2, v2 = posterior(t, y, t_star, theta)
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(v1, v2)
        assert np.all(v1 >= 0.0)


# ---------------------------------------------------------------- LOO


def brute_force_loo(t, y, theta, noise_var) -> float:
    """Σ_i log p(y_i | y_-i): n posteriors, each on the other n − 1 points.  The held-out
    y_i is a noisy observation, so its predictive variance is var(f_i) + σn²."""
    total = 0.0
    for i in range(t.size):
        keep = np.arange(t.size) != i
        mu, var = posterior(t[keep], y[keep], t[i:i + 1], theta, noise_var)
        s2 = var[0] + noise_var
        total += -0.5 * math.log(s2) - (y[i] - mu[0]) ** 2 / (2 * s2) - 0.5 * math.log(2 * math.pi)
    return total


@pytest.mark.parametrize("idx", range(len(WINDOWS)))
@pytest.mark.parametrize("noise_var", [DEFAULT_NOISE_VAR, 1e-2])
def test_loo_closed_form_equals_brute_force(idx, noise_var):
    t, y = WINDOWS[idx]
    theta = random_theta(np.random.default_rng(20 + idx))
    got, _ = loo_log_predictive(np.log(theta), t, y, noise_var)
    want = brute_force_loo(t, y, theta, noise_var)
    assert got == pytest.approx(want, rel=1e-8, abs=1e-8)


def central_difference(t, y, log_theta, noise_var, h=1e-3):
    """Five-point central difference: O(h⁴) truncation, and a step large enough that the
    round-off of L at ill-conditioned θ (~1e-10) stays below 1e-6 of the derivative."""

    def f(x):
        return loo_log_predictive(x, t, y, noise_var)[0]

    out = np.empty(3)
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        x = log_theta
        out[j] = (-f(x + 2 * e) + 8 * f(x + e) - 8 * f(x - e) + f(x - 2 * e)) / (12 * h)
    return out


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), irregular=st.booleans(), n=st.integers(5, 40),
       u=st.tuples(*[st.floats(0.0, 1.0)] * 3))
def test_loo_gradient_matches_finite_differences(seed, irregular, n, u):
    t, y = window(seed, n=n, irregular=irregular)
    log_theta = LOG_BOUNDS[:, 0] + np.array(u) * (LOG_BOUNDS[:, 1] - LOG_BOUNDS[:, 0])
    # θ anywhere in the bounds, but where cond(K) is moderate: beyond ~1e6 the round-off in
    # L defeats any double-precision finite difference (see the mpmath reference test).
    k = kernel(t, t, np.exp(log_theta)) + DEFAULT_NOISE_VAR * np.eye(n)
    assume(np.linalg.cond(k) < 1e5)
    val, grad = loo_log_predictive(log_theta, t, y, DEFAULT_NOISE_VAR)
    assert math.isfinite(val)
    fd = central_difference(t, y, log_theta, DEFAULT_NOISE_VAR)
    scale = max(np.abs(grad).max(), 1.0)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-5 * scale)


# Reference L and ∂L/∂log θ computed with mpmath at 60 digits (K assembled and inverted in
# multiprecision, eq. 5.12, derivative by a 1e-20 central difference) at two corners of the
# bounds where cond(K) ~ 1e8 and double-precision finite differences are off by > 1e-2.
T5 = np.array([-0.4, -0.3, -0.2, -0.1, 0.0])
Y5 = np.array([-0.1277548531143909, -0.1109653394435211, -0.016923074399192876,
               0.0235669373161111, 0.0])
MP_REFERENCE = [
    ((100.0, 100.0, 1e-3), -12.4739953377136,
     (0.0449384797266, -0.0609639081491, -7.68745244713e-8)),
    ((100.0, 1e-2, 10.0), -7.24569614599188,
     (-4.33087680375e-5, -0.575143572232, 0.000232132290776)),
]


@pytest.mark.parametrize(("theta", "want_loo", "want_grad"), MP_REFERENCE)
def test_loo_gradient_matches_multiprecision_reference_when_ill_conditioned(
        theta, want_loo, want_grad):
    val, grad = loo_log_predictive(np.log(theta), T5, Y5, DEFAULT_NOISE_VAR)
    assert val == pytest.approx(want_loo, rel=1e-6)
    # cond(K) ~ 1e8: the double-precision gradient keeps ~5 significant digits, and the last
    # one moves with the BLAS build (4.6e-5 seen with numpy 2.4 / OpenBLAS).
    np.testing.assert_allclose(grad, want_grad, rtol=2e-4)


def test_loo_returns_minus_inf_when_cholesky_fails():
    # Identical times and a vanishing noise make K rank one.
    t, y = np.zeros(4), np.array([0.1, -0.2, 0.0, 0.3])
    val, grad = loo_log_predictive(np.log([1.0, 1.0, 1.0]), t, y, noise_var=1e-300)
    assert val == -math.inf
    np.testing.assert_array_equal(grad, np.zeros(3))
    with pytest.raises(np.linalg.LinAlgError):
        GPModel(t, y, (1.0, 1.0, 1.0), noise_var=1e-300)
    res = fit(t, y, noise_var=1e-300, theta0=(1.0, 2.0, 0.5))
    assert res.loo == -math.inf
    assert not res.converged
    np.testing.assert_allclose(res.theta, (1.0, 2.0, 0.5))


# ---------------------------------------------------------------- fit


@pytest.mark.parametrize("idx", range(len(WINDOWS)))
def test_fit_improves_on_warm_start_and_stays_in_bounds(idx):
    t, y = WINDOWS[idx]
    theta0 = np.array([2.0, 0.5, 0.05])
    start, _ = loo_log_predictive(np.log(theta0), t, y)
    res = fit(t, y, DEFAULT_NOISE_VAR, theta0)
    assert res.loo > start
    assert res.loo == pytest.approx(loo_log_predictive(np.log(res.theta), t, y)[0], rel=1e-12)
    assert np.all(np.log(res.theta) >= LOG_BOUNDS[:, 0] - 1e-12)
    assert np.all(np.log(res.theta) <= LOG_BOUNDS[:, 1] + 1e-12)
    assert 1 <= res.n_iter <= 50


def test_fit_respects_custom_bounds_and_clips_the_warm_start():
    t, y = WINDOWS[0]
    bounds = ((0.5, 0.6), (0.1, 10.0), (0.01, 1.0))
    res = fit(t, y, theta0=(50.0, 1.0, 0.1), bounds=bounds)
    assert 0.5 - 1e-12 <= res.theta[0] <= 0.6 + 1e-12


def test_fit_max_iter_caps_iterations():
    t, y = WINDOWS[0]
    res = fit(t, y, theta0=(20.0, 0.01, 5.0), max_iter=1)
    assert res.n_iter <= 1
    assert not res.converged


def test_fit_recovers_hyperparameters_of_the_prior():
    true = np.array([0.5, 1.0, 0.3])
    t = regular(60, dt=0.2)
    k = kernel(t, t, true) + DEFAULT_NOISE_VAR * np.eye(t.size)
    chol = np.linalg.cholesky(k)
    fitted = []
    for seed in range(5):
        y = chol @ np.random.default_rng(seed).normal(size=t.size)
        res = fit(t, y, DEFAULT_NOISE_VAR, theta0=(2.0, 0.3, 1.0), max_iter=200, ftol=1e-10)
        fitted.append(res.theta)
    median = np.median(fitted, axis=0)
    # γ is well identified by 60 samples over 24 length scales, α1 loosely (the linear term
    # absorbs part of the amplitude); α2, the variance of one slope seen once, is not.
    assert 0.8 * true[0] < median[0] < 1.25 * true[0]
    assert true[1] / 3.0 < median[1] < 3.0 * true[1]


# ---------------------------------------------------------------- bank


def bank_thetas(m: int = 16, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([random_theta(rng) for _ in range(m)])


@pytest.mark.parametrize("idx", range(len(WINDOWS)))
def test_bank_lml_equals_per_model(idx):
    t, y = WINDOWS[idx]
    thetas = bank_thetas()
    got = bank_log_marginal_likelihood(t, y, thetas)
    want = [log_marginal_likelihood(t, y, th) for th in thetas]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)


def test_regular_grid_bank_equals_uncached():
    thetas = bank_thetas()
    cache = RegularGridBank(thetas, 30, dt=0.1)
    np.testing.assert_allclose(cache.t, regular(30), atol=1e-15)
    ys = np.array([window(s)[1] for s in range(4)])
    for y in ys:
        want = [log_marginal_likelihood(cache.t, y, th) for th in thetas]
        np.testing.assert_allclose(cache.lml(y), want, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(cache.lml(y), bank_log_marginal_likelihood(cache.t, y, thetas),
                                   rtol=1e-9, atol=1e-9)
    stacked = cache.lml(ys)
    assert stacked.shape == (4, 16)
    np.testing.assert_allclose(stacked[2], cache.lml(ys[2]), rtol=1e-12)


def test_bank_selects_the_generating_model():
    thetas = np.array([[0.3, 0.2, 0.01], [2.0, 3.0, 0.01], [0.5, 0.01, 1.0]])
    cache = RegularGridBank(thetas, 30)
    k = kernel(cache.t, cache.t, thetas[1]) + DEFAULT_NOISE_VAR * np.eye(30)
    y = np.linalg.cholesky(k) @ np.random.default_rng(0).normal(size=30)
    assert int(np.argmax(cache.lml(y))) == 1


# ---------------------------------------------------------------- validation


T3, Y3 = np.array([-0.2, -0.1, 0.0]), np.array([0.1, 0.0, 0.0])


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: fit(T3, Y3[:2]), "lengths differ"),
        (lambda: fit(T3[:2], Y3[:2]), "at least 3"),
        (lambda: fit(T3, [0.0, math.nan, 0.0]), "non-finite"),
        (lambda: fit(np.zeros((3, 1)), Y3), "1-D"),
        (lambda: fit(T3, Y3, noise_var=0.0), "noise_var"),
        (lambda: fit(T3, Y3, noise_var=math.inf), "noise_var"),
        (lambda: fit(T3, Y3, theta0=(1.0, -1.0, 1.0)), "theta0"),
        (lambda: fit(T3, Y3, theta0=(1.0, 1.0)), "theta0"),
        (lambda: fit(T3, Y3, bounds=((1.0, 0.5), (1.0, 2.0), (1.0, 2.0))), "bounds"),
        (lambda: fit(T3, Y3, bounds=((0.0, 1.0), (1.0, 2.0), (1.0, 2.0))), "bounds"),
        (lambda: fit(T3, Y3, bounds=((0.1, 1.0),)), "bounds"),
        (lambda: fit(T3, Y3, bounds=5.0), "bounds"),
        (lambda: fit(T3, Y3, max_iter=0), "max_iter"),
        (lambda: fit(T3, Y3, max_iter=2.5), "max_iter"),
        (lambda: fit(T3, Y3, ftol=0.0), "ftol"),
        (lambda: loo_log_predictive([0.0, math.nan, 0.0], T3, Y3), "log_theta"),
        (lambda: posterior(T3, Y3, [math.inf], (1.0, 1.0, 1.0)), "t_star"),
        (lambda: kernel(T3, T3, (0.0, 1.0, 1.0)), "theta"),
        (lambda: log_marginal_likelihood(T3, Y3, (1.0, 1.0, 1.0), noise_var=-1.0), "noise_var"),
        (lambda: bank_log_marginal_likelihood(T3, Y3, [1.0, 1.0, 1.0]), r"\(M, 3\)"),
        (lambda: bank_log_marginal_likelihood(T3, Y3, [[1.0, 1.0, math.nan]]), "thetas"),
        (lambda: RegularGridBank([[1.0, 1.0, 1.0]], 2), "n must"),
        (lambda: RegularGridBank([[1.0, 1.0, 1.0]], 5, dt=0.0), "dt"),
        (lambda: RegularGridBank([[1.0, 1.0, 1.0]], 5).lml(np.zeros(4)), "grid's 5"),
        (lambda: RegularGridBank([[1.0, 1.0, 1.0]], 3).lml([0.0, math.nan, 0.0]), "non-finite"),
    ],
)
def test_bad_inputs_raise_value_error(call, message):
    with pytest.raises(ValueError, match=message):
        call()
