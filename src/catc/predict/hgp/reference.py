"""The HGP's readable formulas: the reference the fast path is held to (1e-9 m over 3 s,
tests/test_hgp.py), and what the bank training uses (:mod:`catc.predict.training`).

Paper section "Hybrid-learning-based Gaussian Process (HGP) prediction system".  Times are
relative to the last received sample (τ ≤ 0) and each series relative to its last value;
the kernel is the paper's κ(t, t') = α1² exp(−(t−t')²/(2γ²)) + α2² t t' (eq. "covariance
func", :func:`catc.predict.gp.kernel`), θ = {γ, α1, α2}.  With ``slopes`` each GP is also
conditioned on the derivative the BSM carries at τ = 0 (R&W 2006 §9.4, derivative
observations): the covariance gains a row and column (:func:`slope_system`).

* :func:`lml_with_slope`, :class:`RegularSlopeBank`: the model-selection score (paper eq.
  "eq-,odelselection": log p(θ | S, t) = −½ SᵀK⁻¹S − ½ log det K − n/2 log 2π, R&W 2006
  eq. 2.30) with the slope appended;
* :func:`posterior_with_slope`, :class:`RegularSlopePosterior`, :func:`forecast_path`: the
  speed and heading forecasts (paper eq. "eq:forecastingheadingspeed": μ* = K1 K2⁻¹ S,
  Σ* = K3 − K1 K2⁻¹ K1ᵀ; R&W 2006 Algorithm 2.1);
* :func:`implausible`: the hybrid switching criteria (paper: "GP predictions are swapped
  with constant speed and constant acceleration predictions if a specific criterion is
  met").
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from catc.predict import gp
from catc.predict.forecast import DT
from catc.predict.hgp.config import HgpConfig


def window_series(obs: deque, window_s: float = math.inf) -> tuple[np.ndarray, ...]:
    """τ (s, ≤ 0), speed and unwrapped heading (rad) relative to the last sample, x, y,
    for the samples no older than ``window_s`` before the last one."""
    last = obs[-1].t
    arr = np.array([(o.t, o.speed, o.heading, o.x, o.y) for o in obs
                    if last - o.t <= window_s + 1e-9])
    t, s, h, x, y = arr.T
    h = np.unwrap(np.radians(h))
    return t - t[-1], s - s[-1], h - h[-1], x, y


def slope_system(tau: np.ndarray, theta: np.ndarray, noise_var: float,
                 slope_var: float) -> tuple[np.ndarray, object]:
    """Covariance of (f(τ_1..n) + noise, f′(0) + noise) and the cross-covariance function.

    For κ(t, s) = α1² exp(−(t−s)²/(2γ²)) + α2² t s the cross-covariance of f(t) with f′(0) is
    ∂κ/∂s|₀ = α1² t/γ² exp(−t²/(2γ²)) + α2² t, and var f′(0) = α1²/γ² + α2² (R&W 2006 §9.4).
    """
    gamma, a1, a2 = theta

    def k_fd(t: np.ndarray) -> np.ndarray:
        return a1 * a1 * t / (gamma * gamma) * np.exp(-0.5 * t * t / (gamma * gamma)) \
            + a2 * a2 * t

    n = len(tau)
    K = np.empty((n + 1, n + 1))
    K[:n, :n] = gp.kernel(tau, tau, theta) + noise_var * np.eye(n)
    K[:n, n] = K[n, :n] = k_fd(tau)
    K[n, n] = a1 * a1 / (gamma * gamma) + a2 * a2 + slope_var
    return K, k_fd


def posterior_with_slope(tau: np.ndarray, y: np.ndarray, slope: float, slope_var: float,
                         grid: np.ndarray, theta: np.ndarray,
                         noise_var: float) -> tuple[np.ndarray, np.ndarray]:
    """GP posterior conditioned on the values ``y`` at ``tau`` and on the derivative
    ``slope`` at τ = 0 (R&W 2006 §9.4: derivative observations): the paper's eq.
    "eq:forecastingheadingspeed", μ* = K1 K2⁻¹ S and Σ* = K3 − K1 K2⁻¹ K1ᵀ (diagonal), by
    R&W 2006 Algorithm 2.1 (its line numbers below)."""
    K, k_fd = slope_system(tau, theta, noise_var, slope_var)
    n = len(tau)
    Ks = np.empty((n + 1, len(grid)))  # K1ᵀ: the window (and slope) against the grid
    Ks[:n] = gp.kernel(tau, grid, theta)
    Ks[n] = k_fd(grid)
    L = np.linalg.cholesky(K)  # line 2
    alpha = cho_solve((L, True), np.append(y, slope), check_finite=False)  # line 3
    v = solve_triangular(L, Ks, lower=True, check_finite=False)  # line 5
    _, a1, a2 = theta
    var = a1 * a1 + a2 * a2 * grid * grid - np.sum(v * v, axis=0)  # line 6: κ(t*, t*) − vᵀv
    return Ks.T @ alpha, var  # line 4


def slope_stack(tau: np.ndarray, thetas: np.ndarray, noise_var: float,
                slope_var: float) -> np.ndarray:
    """:func:`slope_system`'s covariance for every model in ``thetas``: (M, n+1, n+1)."""
    gamma, a1, a2 = (thetas[:, i, None] for i in range(3))
    n = len(tau)
    sq = (tau[:, None] - tau[None, :]) ** 2
    K = np.empty((len(thetas), n + 1, n + 1))
    K[:, :n, :n] = (a1 * a1)[:, :, None] * np.exp(-0.5 * sq / (gamma * gamma)[:, :, None]) \
        + (a2 * a2)[:, :, None] * np.outer(tau, tau) + noise_var * np.eye(n)
    k_fd = a1 * a1 * tau / (gamma * gamma) * np.exp(-0.5 * tau * tau / (gamma * gamma)) \
        + a2 * a2 * tau
    K[:, :n, n] = K[:, n, :n] = k_fd
    K[:, n, n] = (a1 * a1 / (gamma * gamma) + a2 * a2)[:, 0] + slope_var
    return K


def lml_with_slope(tau: np.ndarray, y: np.ndarray, slope: float, slope_var: float,
                   thetas: np.ndarray, noise_var: float) -> np.ndarray:
    """Log marginal likelihood of (values, slope) under each model in ``thetas`` (R&W eq. 2.30
    with the derivative observation appended), batched over the bank: the score of the
    paper's model selection, eq. "eq-,odelselection"."""
    K = slope_stack(tau, thetas, noise_var, slope_var)
    n = len(tau)
    z = np.append(y, slope)
    try:
        L = np.linalg.cholesky(K)
    except np.linalg.LinAlgError:  # one ill-conditioned model: score them one by one
        return np.array([lml_with_slope(tau, y, slope, slope_var, th[None], noise_var)[0]
                         if _is_pd(K[i]) else -np.inf for i, th in enumerate(thetas)])
    w = np.linalg.solve(L, np.broadcast_to(z, (len(thetas), n + 1))[..., None])[..., 0]
    logdet = np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1)
    return -0.5 * np.einsum("mi,mi->m", w, w) - logdet - 0.5 * (n + 1) * math.log(2 * math.pi)


class RegularSlopeBank:
    """:func:`lml_with_slope` for the regular grid τ = −(n−1)·DT … 0, with every model's
    K⁻¹ and log-determinant computed once: a new window costs one einsum."""

    def __init__(self, thetas: np.ndarray, n: int, noise_var: float, slope_var: float) -> None:
        self.tau = (np.arange(n) - (n - 1)) * DT
        K = slope_stack(self.tau, thetas, noise_var, slope_var)
        L = np.linalg.cholesky(K)
        eye = np.broadcast_to(np.eye(n + 1), K.shape)
        Linv = np.linalg.solve(L, eye)
        self.Kinv = np.einsum("mki,mkj->mij", Linv, Linv)
        self.const = -np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1) \
            - 0.5 * (n + 1) * math.log(2 * math.pi)

    def lml(self, y: np.ndarray, slope: float) -> np.ndarray:
        return self.lml_z(np.append(y, slope))

    def lml_z(self, z: np.ndarray) -> np.ndarray:
        """:meth:`lml` of the window values with the slope appended, z = (y, slope)."""
        m, k, _ = self.Kinv.shape
        q = (self.Kinv.reshape(m * k, k) @ z).reshape(m, k) @ z  # zᵀK⁻¹z, two products
        return -0.5 * q + self.const


def _is_pd(K: np.ndarray) -> bool:
    try:
        np.linalg.cholesky(K)
    except np.linalg.LinAlgError:
        return False
    return True


def forecast_path(tau: np.ndarray, ys: np.ndarray, yh: np.ndarray, slopes: tuple | None,
                  theta_s: np.ndarray, theta_h: np.ndarray, grid: np.ndarray,
                  config: HgpConfig) -> tuple[np.ndarray, ...]:
    """Speed and heading forecasts (relative to the last sample) at ``grid``: (μs, σs², μh, σh²).

    ``slopes`` is (acceleration m/s², yaw rate rad/s) at the last sample, or None.  This is
    the one forecast both the predictor and the bank training use.
    """
    c = config
    if slopes is None:
        ms, vs = gp.posterior(tau, ys, grid, theta_s, c.noise_speed)
        mh, vh = gp.posterior(tau, yh, grid, theta_h, c.noise_heading)
    else:
        ms, vs = posterior_with_slope(tau, ys, slopes[0], c.noise_accel, grid, theta_s,
                                      c.noise_speed)
        mh, vh = posterior_with_slope(tau, yh, slopes[1], c.noise_yaw, grid, theta_h,
                                      c.noise_heading)
        if c.speed_model == "ca":
            ms, vs = slopes[0] * grid, np.zeros_like(grid)
        if c.heading_model == "ctrv":
            mh, vh = slopes[1] * grid, np.zeros_like(grid)
    return ms, np.maximum(vs, 0.0), mh, np.maximum(vh, 0.0)


class RegularSlopePosterior:
    """:func:`posterior_with_slope` for the regular grid τ = −(n−1)·DT … 0 and every bank
    model, as weights: mean = W[m]·(y, slope), and a variance that does not depend on the
    data, both computed once per (model, window length, forecast length)."""

    def __init__(self, thetas: np.ndarray, n: int, noise_var: float, slope_var: float,
                 grid: np.ndarray) -> None:
        self.tau = (np.arange(n) - (n - 1)) * DT
        weights, variances = [], []
        for theta in thetas:
            K, k_fd = slope_system(self.tau, theta, noise_var, slope_var)
            Ks = np.vstack([gp.kernel(self.tau, grid, theta), k_fd(grid)])
            L = np.linalg.cholesky(K)
            weights.append(cho_solve((L, True), Ks, check_finite=False).T)
            v = solve_triangular(L, Ks, lower=True, check_finite=False)
            _, a1, a2 = theta
            variances.append(a1 * a1 + a2 * a2 * grid * grid - np.sum(v * v, axis=0))
        self.weights = np.array(weights)  # (M, len(grid), n + 1)
        self.var = np.array(variances)  # (M, len(grid))


def implausible(c: HgpConfig, grid: np.ndarray, speed: np.ndarray, vs: np.ndarray,
                head: np.ndarray, vh: np.ndarray) -> int | None:
    """Index of the first forecast step that breaks a hybrid-switching criterion (paper:
    "GP predictions are swapped with constant speed and constant acceleration predictions
    if a specific criterion is met"; the criteria, ours, are listed in
    :mod:`catc.predict.hgp`), or None."""
    accel = np.diff(speed) / DT
    yaw = np.degrees(np.diff(head)) / DT
    bad = np.zeros(len(grid), dtype=bool)
    bad[1:] |= speed[1:] < 0
    bad[1:] |= np.abs(accel) > c.accel_max
    bad[1:] |= np.abs(yaw) > c.yaw_rate_max
    bad[1:] |= np.abs(speed[1:] * np.radians(yaw)) > c.lat_accel_max
    bad |= np.sqrt(vs) > c.speed_std_max
    bad |= np.degrees(np.sqrt(vh)) > c.heading_std_max
    idx = np.flatnonzero(bad)
    return int(idx[0]) if len(idx) else None
