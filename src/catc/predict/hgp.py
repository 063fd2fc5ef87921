"""The Hybrid Gaussian Process (HGP) predictor of the reference paper (Valiente et al.,
section "Hybrid-learning-based Gaussian Process (HGP) prediction system").

Indirect HGP (``hgp``): two independent GPs model the RV's speed and (unwrapped)
heading over the last ``tw`` received samples.  For each a model θ = {γ, α1, α2} is
chosen from the kernel bank by maximum log marginal likelihood (paper eq. "model
selection"), the posterior gives mean and variance at 0.1 s steps after the last BSM
(eq. "forecasting heading and speed"), and the position is integrated piecewise with
E[s·cos h] = μs·exp(−σh²/2)·cos μh (eq. "position prediction 2"; here with sine for
east because headings are clockwise from north).  Direct HGP (``hgp-d``) puts the GPs
on x and y instead.

Formulation.  Every choice below was measured on both shared datasets (OpenACC and
NGSIM, all trips, PER 90 % and 95 %, one seed); the numbers are in docs/hgp.md.

* Time relative to the last received sample (t ≤ 0) and each series relative to its last
  received value.  With that origin the linear term α2²·t·t' is a slope prior anchored at
  the last sample and the zero prior mean means "no change since the last BSM".
* The window is the last ``tw`` received samples (the paper's TW), not a time span: capping
  it at 15–60 s changed PTE95 by under 4 %, and at 3–10 s it made it worse.
* Slopes (our addition; ``slopes``): each GP is also conditioned on the derivative the
  BSM itself carries at the last sample, the longitudinal acceleration for speed and the
  yaw rate for heading (a derivative observation, R&W 2006 §9.4; the kernel and θ are
  unchanged).  The kinematic baselines use these fields and the paper's HGP did not; at
  PER 90 % the history is sparse and without them the GP learns a turn or a braking only
  seconds late.  Bank models are then chosen by the likelihood of values and slope
  together (``select_with_slopes``).
* Hyperparameter bounds per series from vehicle physics (``speed_bounds``,
  ``heading_bounds``), used by training and by online fits.

Hybrid switching (paper: "GP predictions are swapped with constant speed and constant
acceleration predictions if a specific criterion is met").  The forecast is walked in
0.1 s steps; at the first step where any criterion below holds, the GP is abandoned
for the rest of the gap:

* negative speed (μs < 0): the vehicle is stopping; it stops there (CA with the stop
  rule: speed 0 from then on), source ``"ca"``;
* |dμs/dt| > ``accel_max`` (longitudinal acceleration beyond what a car does), or
* |dμh/dt| > ``yaw_rate_max``, or lateral acceleration μs·|dμh/dt| > ``lat_accel_max``, or
* divergence: σs > ``speed_std_max`` or σh > ``heading_std_max``:
  constant speed and heading from the last plausible GP state, source ``"cs"``.

Online models (paper: "If there is no model in the reduced kernel bank that meets the
required PTE_th a new model is created, added to the bank, and selected"): when a
forecast is first needed after a BSM, the selected models are back-tested on the
window (condition on all but the last ``backtest_s`` seconds, forecast those, compare
integrated positions with the received ones).  If the error exceeds ``pte_th``, new
speed and heading models are fitted by LOO-CV on the window (warm-started from the
selected ones) and added to this predictor's online bank, bounded to ``online_max``
models (oldest dropped first).  Off by default (``online``): with the shipped bank it
changed PTE95 by under 4 % either way at 5–10 times the cost (docs/hgp.md).
"""

from __future__ import annotations

import math
import weakref
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from catc.predict import gp
from catc.predict.bank import KernelBank, default_bank
from catc.predict.base import Observation, Prediction
from catc.predict.kinematic import elapsed

DT = 0.1


@dataclass(frozen=True)
class HgpConfig:
    """Every parameter of the HGP; defaults follow the paper where it gives one."""

    tw: int = 30  # training window, samples (paper: TW = 30, 3 s)
    # Hyperparameter bounds (γ s, α1, α2) per series, from what a car can do rather than
    # the GP core's generic ones: a speed deviation of at most ~10 m/s and a trend of at
    # most 5 m/s² within a window; a heading deviation of at most ~2 rad and a turn rate
    # of at most 1 rad/s (57°/s).  Without them LOO on short, nearly linear windows drives
    # α1 to 10³ with γ of tens of seconds: a stiff polynomial that extrapolates curvature
    # without limit across long gaps (measured, see the issue note).
    speed_bounds: tuple = ((0.3, 100.0), (1e-3, 10.0), (1e-4, 5.0))
    heading_bounds: tuple = ((0.3, 100.0), (1e-4, 2.0), (1e-5, 1.0))
    min_points: int = 4  # fewer received samples in the window: CA fallback
    horizon_s: float = 10.0  # longest GP forecast; constant speed beyond it
    noise_speed: float = 0.01  # σn² of the speed series, (m/s)²: GNSS speed noise ~0.1 m/s
    noise_heading: float = 3e-5  # σn² of the heading series, rad² (~0.3°)
    accel_max: float = 8.0  # m/s², |dμs/dt| beyond this is implausible
    yaw_rate_max: float = 60.0  # deg/s
    lat_accel_max: float = 8.0  # m/s², μs·|dμh/dt|
    speed_std_max: float = 3.0  # m/s, divergence of the speed forecast
    heading_std_max: float = 25.0  # deg, divergence of the heading forecast
    pte_th: float = 0.5  # m, the paper's PTE_th for creating a model online
    backtest_s: float = 1.0  # s held out at the end of the window for the online check
    online: bool = False  # measured: no gain at 5-10x the cost (see the issue note)
    online_max: int = 32
    integration: str = "trapezoid"  # or "left", the paper's literal recursion
    heading_damping: bool = True  # E[cos h] = exp(−σh²/2)·cos μh (paper); False: cos μh
    # Diagnostics: replace one GP by its kinematic counterpart (needs ``slopes``):
    # speed "ca" = last speed + acceleration·τ; heading "ctrv" = last heading + yaw rate·τ.
    speed_model: str = "gp"
    heading_model: str = "gp"
    window_s: float = math.inf  # also drop samples older than this (s) before the last one
    slopes: bool = True  # condition on the BSM's accel and yaw rate at the last sample
    select_with_slopes: bool = True  # choose bank models by the likelihood of values + slope
    noise_accel: float = 0.005  # (m/s²)², BSM longitudinal acceleration (σ 0.07 m/s²)
    noise_yaw: float = 3e-5  # (rad/s)², BSM yaw rate (σ 0.3 deg/s)


def _window_series(obs: deque, window_s: float = math.inf) -> tuple[np.ndarray, ...]:
    """τ (s, ≤ 0), speed and unwrapped heading (rad) relative to the last sample, x, y,
    for the samples no older than ``window_s`` before the last one."""
    last = obs[-1].t
    arr = np.array([(o.t, o.speed, o.heading, o.x, o.y) for o in obs
                    if last - o.t <= window_s + 1e-9])
    t, s, h, x, y = arr.T
    h = np.unwrap(np.radians(h))
    return t - t[-1], s - s[-1], h - h[-1], x, y


def _slope_system(tau: np.ndarray, theta: np.ndarray, noise_var: float,
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
    ``slope`` at τ = 0 (R&W 2006 §9.4: derivative observations)."""
    K, k_fd = _slope_system(tau, theta, noise_var, slope_var)
    n = len(tau)
    Ks = np.empty((n + 1, len(grid)))
    Ks[:n] = gp.kernel(tau, grid, theta)
    Ks[n] = k_fd(grid)
    L = np.linalg.cholesky(K)
    alpha = cho_solve((L, True), np.append(y, slope), check_finite=False)
    v = solve_triangular(L, Ks, lower=True, check_finite=False)
    _, a1, a2 = theta
    var = a1 * a1 + a2 * a2 * grid * grid - np.sum(v * v, axis=0)
    return Ks.T @ alpha, var


def _slope_stack(tau: np.ndarray, thetas: np.ndarray, noise_var: float,
                 slope_var: float) -> np.ndarray:
    """:func:`_slope_system`'s covariance for every model in ``thetas``: (M, n+1, n+1)."""
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
    with the derivative observation appended), batched over the bank."""
    K = _slope_stack(tau, thetas, noise_var, slope_var)
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
        K = _slope_stack(self.tau, thetas, noise_var, slope_var)
        L = np.linalg.cholesky(K)
        eye = np.broadcast_to(np.eye(n + 1), K.shape)
        Linv = np.linalg.solve(L, eye)
        self.Kinv = np.einsum("mki,mkj->mij", Linv, Linv)
        self.const = -np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1) \
            - 0.5 * (n + 1) * math.log(2 * math.pi)

    def lml(self, y: np.ndarray, slope: float) -> np.ndarray:
        z = np.append(y, slope)
        return -0.5 * np.einsum("i,mij,j->m", z, self.Kinv, z) + self.const


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


@dataclass
class _Forecast:
    """A forecast from the last BSM: state at τ = k·DT for k = 0..K."""

    tau: np.ndarray
    x: np.ndarray
    y: np.ndarray
    speed: np.ndarray
    heading: np.ndarray  # deg
    var_x: np.ndarray
    var_y: np.ndarray
    source: list[str]


def integrate(x0: float, y0: float, tau: np.ndarray, mu_s: np.ndarray, mu_h: np.ndarray,
              var_h: np.ndarray, rule: str = "trapezoid") -> tuple[np.ndarray, np.ndarray]:
    """Positions from speed/heading forecasts at ``tau`` (paper eq. "position prediction 2").

    The expected velocity is E[s]·E[sin h], E[s]·E[cos h] with E[cos h] = exp(−σh²/2)·cos μh
    (heading clockwise from north, so east uses sin).  ``rule`` "left" is the paper's
    literal recursion x_{j+1} = x_j + Δt·v_j; "trapezoid" averages v_j and v_{j+1}.
    """
    damp = np.exp(-0.5 * var_h)
    vx = mu_s * damp * np.sin(mu_h)
    vy = mu_s * damp * np.cos(mu_h)
    dt = np.diff(tau)
    if rule == "trapezoid":
        dx, dy = 0.5 * (vx[1:] + vx[:-1]) * dt, 0.5 * (vy[1:] + vy[:-1]) * dt
    elif rule == "left":
        dx, dy = vx[:-1] * dt, vy[:-1] * dt
    else:
        raise ValueError(f"unknown integration rule {rule!r}")
    return (x0 + np.concatenate(([0.0], np.cumsum(dx))),
            y0 + np.concatenate(([0.0], np.cumsum(dy))))


def _read(f: _Forecast, tau: float) -> Prediction:
    """The forecast state ``tau`` seconds after the last BSM (linear between 0.1 s steps)."""
    if tau >= f.tau[-1]:  # beyond the computed horizon: constant speed onwards
        extra = tau - f.tau[-1]
        h = math.radians(f.heading[-1])
        return Prediction(f.x[-1] + f.speed[-1] * extra * math.sin(h),
                          f.y[-1] + f.speed[-1] * extra * math.cos(h), f.speed[-1],
                          f.heading[-1], f.var_x[-1], f.var_y[-1], f.source[-1])
    k = min(int(tau / DT), len(f.tau) - 2)  # float round-off at the horizon's end
    w = min(tau / DT - k, 1.0)
    lerp = lambda a: (1 - w) * a[k] + w * a[k + 1]  # noqa: E731
    dh = (f.heading[k + 1] - f.heading[k] + 180.0) % 360.0 - 180.0
    return Prediction(lerp(f.x), lerp(f.y), lerp(f.speed), (f.heading[k] + w * dh) % 360.0,
                      lerp(f.var_x), lerp(f.var_y), f.source[k + 1])


#: Regular-grid selection caches per bank (held weakly: a bank's factors go with it), then
#: per window length and noise configuration.
_REGULAR_CACHE: weakref.WeakKeyDictionary[
    KernelBank, dict[tuple, tuple[RegularSlopeBank, RegularSlopeBank]]
] = weakref.WeakKeyDictionary()


class _WindowPredictor:
    """What both GP predictors share: the window of received observations and a cached
    forecast from the last one."""

    def __init__(self, tw: int) -> None:
        self._obs: deque[Observation] = deque(maxlen=tw)
        self._forecast: _Forecast | None = None

    def reset(self) -> None:
        self._obs.clear()
        self._forecast = None

    def update(self, obs: Observation) -> None:
        if self._obs and obs.t <= self._obs[-1].t:
            return
        self._obs.append(obs)
        self._forecast = None

    def _since_last(self, t: float) -> tuple[Observation, float]:
        """The last observation and the time from it to ``t`` (LookupError before data)."""
        if not self._obs:
            raise LookupError("no observation yet")
        last = self._obs[-1]
        return last, elapsed(last.t, t)


def _bsm(last: Observation) -> Prediction:
    return Prediction(last.x, last.y, last.speed, last.heading, 0.0, 0.0, "bsm")


class HgpPredictor(_WindowPredictor):
    """Indirect HGP: GPs on speed and heading, positions by integration."""

    name = "hgp"

    def __init__(self, bank: KernelBank | None = None, config: HgpConfig | None = None) -> None:
        self.config = config or HgpConfig()
        super().__init__(self.config.tw)
        self.bank = bank if bank is not None else default_bank()
        self._online_speed: deque[np.ndarray] = deque(maxlen=self.config.online_max)
        self._online_heading: deque[np.ndarray] = deque(maxlen=self.config.online_max)
        #: Counters for captures and the H2 figures.
        self.stats = {"forecasts": 0, "online_models": 0, "switch_ca": 0, "switch_cs": 0}

    def predict(self, t: float) -> Prediction:
        last, tau = self._since_last(t)
        if tau == 0.0:
            return _bsm(last)
        if self._window_len() < self.config.min_points:
            return self._ca(last, tau)
        f = self._forecast
        if f is None or f.tau[-1] < min(tau, self.config.horizon_s):
            f = self._forecast = self._make_forecast(max(tau, 3.0))
        return _read(f, tau)

    def _window_len(self) -> int:
        if math.isinf(self.config.window_s):  # the default: no time cap, no per-tick scan
            return len(self._obs)
        last = self._obs[-1].t
        return sum(1 for o in self._obs if last - o.t <= self.config.window_s + 1e-9)

    # -- internals -----------------------------------------------------------------------
    def _ca(self, last: Observation, tau: float) -> Prediction:
        """Constant acceleration along the last heading, stopping at zero speed."""
        a = last.accel
        stop = -last.speed / a if a < 0 else math.inf
        tt = min(tau, stop)
        dist = last.speed * tt + 0.5 * a * tt * tt
        h = math.radians(last.heading)
        return Prediction(last.x + dist * math.sin(h), last.y + dist * math.cos(h),
                          max(0.0, last.speed + a * tt), last.heading, source="ca")

    def _regular_cache(self, tau: np.ndarray) -> tuple[RegularSlopeBank, ...] | None:
        """The cached selection for a window of ``tw`` samples at exactly DT apart (no loss),
        built once per bank and configuration and shared by all predictors."""
        c = self.config
        if len(tau) != c.tw or np.max(np.abs(np.diff(tau) - DT)) > 1e-6:
            return None
        key = (c.tw, c.noise_speed, c.noise_heading, c.noise_accel, c.noise_yaw)
        per_bank = _REGULAR_CACHE.setdefault(self.bank, {})
        cache = per_bank.get(key)
        if cache is None:
            cache = per_bank[key] = (
                RegularSlopeBank(self.bank.speed, c.tw, c.noise_speed, c.noise_accel),
                RegularSlopeBank(self.bank.heading, c.tw, c.noise_heading, c.noise_yaw))
        return cache

    def _select(self, tau: np.ndarray, ys: np.ndarray, yh: np.ndarray,
                slopes: tuple[float, float] | None = None) -> tuple[np.ndarray, ...]:
        c = self.config
        speed_bank = self.bank.speed
        heading_bank = self.bank.heading
        if self._online_speed:
            speed_bank = np.vstack([speed_bank, np.array(self._online_speed)])
            heading_bank = np.vstack([heading_bank, np.array(self._online_heading)])
        if slopes is not None and c.select_with_slopes:
            cache = None if self._online_speed else self._regular_cache(tau)
            if cache is not None:
                ls, lh = cache[0].lml(ys, slopes[0]), cache[1].lml(yh, slopes[1])
            else:
                ls = lml_with_slope(tau, ys, slopes[0], c.noise_accel, speed_bank,
                                    c.noise_speed)
                lh = lml_with_slope(tau, yh, slopes[1], c.noise_yaw, heading_bank,
                                    c.noise_heading)
        else:
            ls = gp.bank_log_marginal_likelihood(tau, ys, speed_bank, c.noise_speed)
            lh = gp.bank_log_marginal_likelihood(tau, yh, heading_bank, c.noise_heading)
        return speed_bank[int(np.argmax(ls))], heading_bank[int(np.argmax(lh))]

    def _backtest_fails(self, tau, ys, yh, x, y, theta_s, theta_h, s0, h0) -> bool:
        """True when the selected models miss the window's own last ``backtest_s`` by > PTE_th."""
        c = self.config
        split = tau <= -c.backtest_s + 1e-9
        if split.sum() < c.min_points or (~split).sum() < 1:
            return False
        i0 = int(np.nonzero(split)[0][-1])
        tr, ts = tau[: i0 + 1] - tau[i0], tau[i0 + 1:] - tau[i0]
        grid = np.concatenate(([0.0], ts))
        ms, _, mh, vh = forecast_path(tr, ys[: i0 + 1] - ys[i0], yh[: i0 + 1] - yh[i0], None,
                                      theta_s, theta_h, grid, c)
        px, py = integrate(x[i0], y[i0], grid, ms + s0 + ys[i0], mh + h0 + yh[i0], vh,
                           c.integration)
        return bool(np.max(np.hypot(px[1:] - x[i0 + 1:], py[1:] - y[i0 + 1:])) > c.pte_th)

    def _make_forecast(self, horizon: float) -> _Forecast:
        c = self.config
        self.stats["forecasts"] += 1
        last = self._obs[-1]
        tau, ys, yh, x, y = _window_series(self._obs, c.window_s)
        slopes = (last.accel, math.radians(last.yaw_rate)) if c.slopes else None
        theta_s, theta_h = self._select(tau, ys, yh, slopes)
        s0, h0 = last.speed, math.radians(last.heading)
        if c.online and self._backtest_fails(tau, ys, yh, x, y, theta_s, theta_h, s0, h0):
            theta_s = gp.fit(tau, ys, c.noise_speed, theta_s, c.speed_bounds).theta
            theta_h = gp.fit(tau, yh, c.noise_heading, theta_h, c.heading_bounds).theta
            self._online_speed.append(theta_s)
            self._online_heading.append(theta_h)
            self.stats["online_models"] += 1
        n = math.ceil(min(horizon, c.horizon_s) / DT - 1e-9)
        grid = np.arange(n + 1) * DT
        ms, vs, mh, vh = forecast_path(tau, ys, yh, slopes, theta_s, theta_h, grid, c)
        speed = ms + s0
        head = mh + h0
        source = ["gp"] * (n + 1)
        cut = self._implausible(grid, speed, vs, head, vh)
        if cut is not None:
            stop = bool(speed[cut] < 0)
            self.stats["switch_ca" if stop else "switch_cs"] += 1
            keep = max(cut - 1, 0)
            speed[cut:] = 0.0 if stop else max(speed[keep], 0.0)
            head[cut:] = head[keep]
            vs[cut:] = vs[keep]
            vh[cut:] = vh[keep]
            source[cut:] = ["ca" if stop else "cs"] * (n + 1 - cut)
        px, py = integrate(last.x, last.y, grid, speed, head,
                           vh if c.heading_damping else np.zeros_like(vh), c.integration)
        # Position variance from the heading and speed variances, first order, accumulated.
        var_along = np.concatenate(([0.0], np.cumsum(vs[1:] * DT * DT)))
        var_cross = np.concatenate(([0.0], np.cumsum(speed[1:] ** 2 * vh[1:] * DT * DT)))
        sh, ch = np.sin(head), np.cos(head)
        return _Forecast(grid, px, py, speed, np.degrees(head) % 360.0,
                         var_along * sh**2 + var_cross * ch**2,
                         var_along * ch**2 + var_cross * sh**2, source)

    def _implausible(self, grid, speed, vs, head, vh) -> int | None:
        """Index of the first forecast step that breaks a hybrid-switching criterion."""
        c = self.config
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


@dataclass(frozen=True)
class HgpDirectConfig:
    """Parameters of the direct HGP; the switching limits mean what they mean for ``hgp``."""

    tw: int = 30
    min_points: int = 4
    horizon_s: float = 10.0
    noise_pos: float = 0.01  # σn² of the x and y series, m² (GNSS noise after smoothing)
    accel_max: float = 8.0  # m/s², from second differences of the mean path
    position_std_max: float = 5.0  # m, divergence
    theta0: tuple[float, float, float] = (2.0, 1.0, 10.0)  # first warm start: γ s, α1 m, α2 m/s


class HgpDirectPredictor(_WindowPredictor):
    """Direct HGP (``hgp-d``): GPs on x and y relative to the last BSM.

    x and y have no trained bank of their own (their scale is set by the speed, not by
    the driver), so each forecast fits both models by LOO-CV, warm-started from the
    previous forecast's fit.  Switching: a forecast step whose implied acceleration
    exceeds ``accel_max`` or whose position standard deviation exceeds
    ``position_std_max`` ends the GP; the vehicle continues at the last plausible
    velocity (source ``"cs"``).
    """

    name = "hgp-d"

    def __init__(self, config: HgpDirectConfig | None = None) -> None:
        self.config = config or HgpDirectConfig()
        super().__init__(self.config.tw)
        self._theta = (np.array(self.config.theta0), np.array(self.config.theta0))

    def reset(self) -> None:
        super().reset()
        self._theta = (np.array(self.config.theta0), np.array(self.config.theta0))

    def predict(self, t: float) -> Prediction:
        last, tau = self._since_last(t)
        if tau == 0.0:
            return _bsm(last)
        if len(self._obs) < self.config.min_points:
            h = math.radians(last.heading)
            return Prediction(last.x + last.speed * tau * math.sin(h),
                              last.y + last.speed * tau * math.cos(h), last.speed,
                              last.heading, source="cs")
        f = self._forecast
        if f is None or f.tau[-1] < min(tau, self.config.horizon_s):
            f = self._forecast = self._make_forecast(max(tau, 3.0))
        return _read(f, tau)

    def _make_forecast(self, horizon: float) -> _Forecast:
        c = self.config
        last = self._obs[-1]
        tau, _, _, x, y = _window_series(self._obs)
        rx, ry = x - x[-1], y - y[-1]
        theta_x = gp.fit(tau, rx, c.noise_pos, self._theta[0]).theta
        theta_y = gp.fit(tau, ry, c.noise_pos, self._theta[1]).theta
        self._theta = (theta_x, theta_y)
        n = math.ceil(min(horizon, c.horizon_s) / DT - 1e-9)
        grid = np.arange(n + 1) * DT
        mx, vx = gp.posterior(tau, rx, grid, theta_x, c.noise_pos)
        my, vy = gp.posterior(tau, ry, grid, theta_y, c.noise_pos)
        px, py = mx + last.x, my + last.y
        vx, vy = np.maximum(vx, 0.0), np.maximum(vy, 0.0)
        velx, vely = np.gradient(px, DT), np.gradient(py, DT)
        accel = np.hypot(np.gradient(velx, DT), np.gradient(vely, DT))
        bad = (accel > c.accel_max) | (np.sqrt(np.maximum(vx, vy)) > c.position_std_max)
        bad[0] = False
        source = ["gp"] * (n + 1)
        idx = np.flatnonzero(bad)
        if len(idx):
            cut = int(idx[0])
            keep = max(cut - 1, 0)
            steps = np.arange(1, n + 2 - cut) * DT
            px[cut:] = px[keep] + velx[keep] * steps
            py[cut:] = py[keep] + vely[keep] * steps
            velx[cut:], vely[cut:] = velx[keep], vely[keep]
            vx[cut:], vy[cut:] = vx[keep], vy[keep]
            source[cut:] = ["cs"] * (n + 1 - cut)
        speed = np.hypot(velx, vely)
        heading = np.where(speed > 0.5, np.degrees(np.arctan2(velx, vely)) % 360.0,
                           last.heading)
        return _Forecast(grid, px, py, speed, heading, vx, vy, source)
