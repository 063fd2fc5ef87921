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

Model persistency (paper: a selected model stays the best for many samples): the bank
selection is reused for up to ``reselect_every`` = 10 received BSMs and redone sooner after
a gap of more than ``reselect_gap_s`` = 0.25 s (two or more BSMs lost in a row).  Measured
on both datasets at PER 0–95 %: PTE95 within 1.5 % of selecting at every BSM, at about a
quarter of the selections at PER 50 % (docs/hgp.md).

Cost.  An OBU makes one forecast per RV and received BSM; at 31 × 31 a LAPACK call from
Python is mostly call overhead, not arithmetic.  The readable formulas (the functions up to
the "fast path" marker and :meth:`HgpPredictor._make_forecast_reference`) are the reference
the tests hold the fast path to (1e-9 m over 3 s): the window kept as running arrays; the
exponentials of every window and model by numpy in one pass, and the Cholesky
factorisations, solves and likelihoods of all of them in compiled kernels that factor many
systems side by side (:mod:`catc.predict.gpkernels`, numba); cached posterior weights for
loss-free windows; one cumsum for positions and variances; and :func:`forecast_many`,
which stacks all of it over the predictors due at a tick.
"""

from __future__ import annotations

import bisect
import math
import threading
import weakref
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from catc.predict import gp, gpkernels
from catc.predict.bank import KernelBank, default_bank
from catc.predict.base import Observation, Prediction, Predictor, register_batch
from catc.predict.forecast import (
    DT,
    Forecast,
    bsm_prediction,
    constant_speed,
    covers,
    integrate,
    read,
    read_xy,
)
from catc.predict.kinematic import elapsed
from catc.predict.kinematic_table import KINEMATIC


@dataclass(frozen=True)
class HgpConfig:
    """Every parameter of the HGP; defaults follow the paper where it gives one.  Checked
    when made (``ValueError``): ``reselect_every`` an integer >= 1, ``branch_edges``
    ascending, ``branch_margin`` one number or one per gap class, ``branches`` names of
    :data:`catc.predict.kinematic_table.KINEMATIC`."""

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
    # Model persistency: the bank selection is redone only every ``reselect_every``
    # received samples and after a gap longer than ``reselect_gap_s`` between two received
    # samples (0.25 s: two or more BSMs lost in a row at 10 Hz); in between the selected θ
    # are reused.  1 and inf select at every sample (the behaviour before).  Measured on
    # both datasets: PTE95 within 1.5 % of that at PER 0-95 % (docs/hgp.md).
    reselect_every: int = 10
    reselect_gap_s: float = 0.25
    # Data-driven hybrid (issue 17; docs/hgp.md "Branches"): kinematic predictors run beside
    # the GP (names from catc.predict, e.g. ("ca", "kf")).  At every BSM that ends a gap
    # (one or more BSMs lost) each branch's squared position error at that BSM, from what
    # it had forecast over the gap, enters a running score per branch (exponentially
    # weighted, ``branch_decay`` the weight of the old score), one score per gap-length
    # class (``branch_edges``, s: a gap of 0.2 s and one of 5 s are different questions);
    # at ``tau`` s into a gap the branch with the lowest score of tau's class answers, a
    # kinematic one only when its score is below ``branch_margin`` × the GP's; a class
    # without scores yet is answered by the GP.  () is the GP alone (its own switching
    # above still applies).  Measured (bench/hgp_ablation.py, docs/hgp.md "Branches"):
    # CA and KF with margin 0.5 take 3-14 % off PTE95 at PER 10-50 % on both datasets
    # and add at most 1.7 % at 80-95 %; margin 1 gains more at low PER and loses up to
    # 5 % at PER 90 %; adding CTRV changed little.  Shipped: margin 1 for gaps up to
    # 0.35 s and 0.5 for longer ones (per class: a float is every class's), chosen by
    # leave-one-trip-out over both datasets (docs/hgp.md, "A margin per gap class").
    branches: tuple = ("ca", "kf")
    branch_decay: float = 0.8
    branch_margin: float | tuple = (1.0, 0.5, 0.5, 0.5)  # or one for every gap class
    branch_edges: tuple = (0.35, 1.05, 3.05)
    # Blend instead of switching (> 0): at tau the answer is the mean of the branches'
    # (the GP's too) whose score in tau's class is at most ``branch_blend`` × the best,
    # weighted by score ** -blend_power (1: inverse-MSE weights); inf: every branch.  Off
    # (0): measured, it trades NGSIM's low and 90 % PER against OpenACC's 80-95 % as the
    # margin does (docs/hgp.md, "Blending instead of switching").
    branch_blend: float = 0.0
    blend_power: float = 1.0  # weights ∝ score ** -blend_power

    def __post_init__(self) -> None:
        if int(self.reselect_every) != self.reselect_every or self.reselect_every < 1:
            raise ValueError(f"reselect_every must be an integer >= 1, got "
                             f"{self.reselect_every!r}")
        if list(self.branch_edges) != sorted(self.branch_edges):
            raise ValueError(f"branch_edges must be ascending, got {self.branch_edges!r}")
        self.margins()
        unknown = [name for name in self.branches if name not in KINEMATIC]
        if unknown:
            raise ValueError(f"branches must be kinematic predictors "
                             f"({', '.join(KINEMATIC)}), got {unknown[0]!r}")

    def margins(self) -> list[float]:
        """``branch_margin`` for each gap class (ValueError unless one, or one per class)."""
        classes = len(self.branch_edges) + 1
        if isinstance(self.branch_margin, (int, float)):
            return [float(self.branch_margin)] * classes
        if len(self.branch_margin) == classes:
            return [float(m) for m in self.branch_margin]
        raise ValueError(f"branch_margin: one per gap class ({classes}), got "
                         f"{self.branch_margin!r}")


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
            K, k_fd = _slope_system(self.tau, theta, noise_var, slope_var)
            Ks = np.vstack([gp.kernel(self.tau, grid, theta), k_fd(grid)])
            L = np.linalg.cholesky(K)
            weights.append(cho_solve((L, True), Ks, check_finite=False).T)
            v = solve_triangular(L, Ks, lower=True, check_finite=False)
            _, a1, a2 = theta
            variances.append(a1 * a1 + a2 * a2 * grid * grid - np.sum(v * v, axis=0))
        self.weights = np.array(weights)  # (M, len(grid), n + 1)
        self.var = np.array(variances)  # (M, len(grid))


# ---------------------------------------------------------------- fast path
#
# The functions above are the readable formulas, and the reference the tests compare the
# ones below with.  These compute the same quantities with far fewer numpy and LAPACK
# calls (that, not arithmetic, is what a 31 × 31 system costs from Python), stacked over
# models and over predictors: ``forecast_many`` runs one set of calls for many predictors.

# Columns of a model-constants row: the kernels' (catc.predict.gpkernels.C ...).
_C, _LOG_S1, _S1, _S2, _KDD, _NOISE = (gpkernels.C, gpkernels.LOG_S1, gpkernels.S1,
                                       gpkernels.S2, gpkernels.KDD, gpkernels.NOISE)


def _consts(thetas: np.ndarray, noise: np.ndarray, slope_var: np.ndarray) -> np.ndarray:
    """Per model row θ = (γ, α1, α2) with its value and slope noise, the columns of
    :data:`catc.predict.gpkernels.C` and after: −1/(2γ²), log α1², α1², α2², var f′(0) +
    slope noise, value noise; shape (R, gpkernels.CONSTS)."""
    th = np.asarray(thetas, dtype=float)
    gamma, a1, a2 = th[:, 0], th[:, 1], th[:, 2]
    out = np.empty((len(th), gpkernels.CONSTS))
    out[:, _C] = -0.5 / (gamma * gamma)
    out[:, _S1] = a1 * a1
    out[:, _S2] = a2 * a2
    out[:, _KDD] = a1 * a1 / (gamma * gamma) + a2 * a2 + slope_var
    out[:, _NOISE] = noise
    out[:, _LOG_S1] = np.log(a1 * a1)
    return out


def _series_consts(thetas: np.ndarray, m: int, c: HgpConfig) -> np.ndarray:
    """:func:`_consts` for ``m`` speed models followed by heading models under config ``c``."""
    heading = np.arange(len(thetas)) >= m
    return _consts(thetas, np.where(heading, c.noise_heading, c.noise_speed),
                   np.where(heading, c.noise_yaw, c.noise_accel))


#: Work arrays per thread, grown as needed and reused: a fresh (32, 32, 32) array for every
#: bank selection costs more in page faults (≈ 2 µs per 4 kB page here) than its
#: arithmetic, because malloc maps and unmaps allocations of this size each time.
_SCRATCH = threading.local()


def _scratch(name: str, shape: tuple[int, ...]) -> np.ndarray:
    """This thread's work array ``name``, as a C-contiguous view of ``shape``; its previous
    contents are undefined and it is valid until the next request for ``name``."""
    size = math.prod(shape)
    buf = _SCRATCH.__dict__.get(name)
    if buf is None or buf.size < size:
        buf = _SCRATCH.__dict__[name] = np.empty(max(size, 2 * (0 if buf is None else buf.size)))
    return buf[:size].reshape(shape)


def _underflows(span: float, c_min: float) -> bool:
    """Whether exp(c·d²) may underflow for time differences up to ``span`` s and the most
    negative c = −1/(2γ²): numpy's exp is tens of times slower on results below the normal
    range (x < −708), so exponents are clipped at −700 (exp(−700) ≈ 1e−304, as good as 0
    next to the other terms) when this says so."""
    return span * span * -c_min > 690.0


_TRIL: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _tril(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the packed lower triangle of an n × n matrix (cached)."""
    t = _TRIL.get(n)
    if t is None:
        t = _TRIL[n] = np.tril_indices(n)
    return t


def _window_exps(tau: np.ndarray, coef: np.ndarray, name: str) -> np.ndarray:
    """α1²·exp(c·d²) = exp(c·d² + log α1²) for the packed lower triangle of the squared
    time differences d² of each window ``tau`` (B, n), under models whose rows c and
    log α1² are ``coef`` (2, M), shared by all windows, or (B, 2, M), one set per window:
    one matrix product of [d², 1] with them, into work array ``name``; (B, P, M)."""
    bsz, n = tau.shape
    rows, cols = _tril(n)
    lhs = _scratch("lhs", (bsz, len(rows), 2))
    # (ndarray.take, not np.take: the latter's Python wrapper was 3 % of an OBU tick)
    d2 = np.subtract(tau.take(rows, axis=1, out=_scratch("rows", (bsz, len(rows)))),
                     tau.take(cols, axis=1, out=_scratch("cols", (bsz, len(rows)))),
                     out=lhs[:, :, 0])
    np.multiply(d2, d2, out=d2)
    lhs[:, :, 1] = 1.0
    e = np.matmul(lhs, coef, out=_scratch(name, (bsz, len(rows), coef.shape[-1])))
    if _underflows(-float(tau[:, 0].min()), float(coef[..., 0, :].min())):
        np.maximum(e, -700.0, out=e)
    return np.exp(e, out=e)


def _lml_stack(tau: np.ndarray, z: np.ndarray, p: np.ndarray, m: int,
               thetas: np.ndarray) -> np.ndarray:
    """:func:`lml_with_slope` of B windows under S = 2m models: ``tau`` (B, n), each ending
    at 0, ``z`` (B, 2, n + 1) the speed and heading values with their slope, ``p`` (S, 6) the
    constants of ``thetas`` (m speed models scored on z[:, 0], then m heading models on
    z[:, 1]).  Returns (B, S).

    numpy computes the exponentials of every window and model, the packed lower triangle
    of the value covariance, as exp(c·d² + log α1²) with one matrix product for all models
    (broadcasting per-model constants costs three times more);
    :func:`catc.predict.gpkernels.select_lml` assembles, factors and scores them, the
    models of a window interleaved."""
    del thetas  # the constants carry everything
    bsz, n = tau.shape
    e = _window_exps(tau, p[:, _C:_LOG_S1 + 1].T, "lml")
    out = np.empty((bsz, len(p)))
    gpkernels.select_lml(e, np.ascontiguousarray(tau), np.ascontiguousarray(z), p, m, out,
                         _scratch("factor", ((n + 1) * (n + 1) * len(p),)))
    return out


def _posterior_stack(rel: np.ndarray, grid: np.ndarray,
                     p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`posterior_with_slope` of speed and heading for B windows at once.

    ``rel`` (B, 3, n + 1): τ (ending at 0, then a 0 for the slope point), the speed values
    and slope, the heading values and slope; ``p`` (B, 2, 6) each window's speed and heading
    model constants.  Returns the means and latent variances (not clipped), (B, 2, len(grid)).

    numpy computes the exponentials of each window's value covariance under its two models
    (one batched matrix product), :func:`catc.predict.gpkernels.posterior` the rest, the
    2B systems interleaved in blocks."""
    bsz, _, k = rel.shape
    n = k - 1
    tau = rel[:, 0, :n]
    p = np.ascontiguousarray(p)
    e = _window_exps(tau, p[:, :, _C:_LOG_S1 + 1].transpose(0, 2, 1), "cov")
    mean = np.empty((bsz, 2, len(grid)))
    var = np.empty((bsz, 2, len(grid)))
    gpkernels.posterior(e, np.ascontiguousarray(rel), grid, p, mean, var,
                        _scratch("factor", (k * k * gpkernels.BLOCK,)))
    return mean, var


def _plausible_rows(c: HgpConfig, ext: np.ndarray) -> np.ndarray:
    """Per row of ``ext`` (B, 6), True when no forecast step can break a switching
    criterion, from the extremes of the forecast (least speed, greatest speed, greatest
    step changes of speed and heading, greatest variances).  Each criterion of
    :func:`implausible` is monotone in these, so True means it finds
    nothing; on False it is asked.  A NaN extreme is never plausible."""
    lo, hi, ds, dh, vs, vh = ext.T
    yaw = np.degrees(dh) / DT
    ok = lo >= 0.0
    ok &= ds / DT <= c.accel_max
    ok &= yaw <= c.yaw_rate_max
    ok &= hi * np.radians(yaw) <= c.lat_accel_max
    ok &= np.sqrt(vs) <= c.speed_std_max
    ok &= np.degrees(np.sqrt(vh)) <= c.heading_std_max
    return ok


_ALL_GP: dict[int, tuple[str, ...]] = {}


def _all_gp(count: int) -> tuple[str, ...]:
    """The sources of a forecast of ``count`` points that is the GP's throughout (shared:
    forecasts' sources are never changed in place)."""
    src = _ALL_GP.get(count)
    if src is None:
        src = _ALL_GP[count] = ("gp",) * count
    return src


def _finish_stack(states: list, mean: np.ndarray, var: np.ndarray, start: np.ndarray,
                  grid: np.ndarray) -> list[Forecast]:
    """Switching, integration and position variance for B forecasts of one configuration
    (``states``, :class:`WindowState`, for it and the switching counters):
    ``mean`` and ``var`` (B, 2, len(grid)) of speed and heading relative to the last sample
    (both are overwritten), ``start`` (B, 4) the last speed, heading (rad), x and y.
    The arithmetic of :meth:`HgpPredictor._make_forecast_reference`, on stacked rows."""
    c = states[0].config
    bsz, _, count = mean.shape
    _, dgrid, half_dgrid = _grid(count)
    start = np.ascontiguousarray(start)
    ext = np.empty((bsz, 6))  # the extremes _plausible_rows needs
    gpkernels.shift_rows(mean, var, start, ext)  # means + last values, variances >= 0
    speed, head, vs, vh = mean[:, 0], mean[:, 1], var[:, 0], var[:, 1]
    all_gp = _all_gp(count)
    sources = [all_gp] * bsz
    for i in np.flatnonzero(~_plausible_rows(c, ext)).tolist():
        cut = implausible(c, grid, speed[i], vs[i], head[i], vh[i])
        if cut is not None:
            stop = bool(speed[i, cut] < 0)
            states[i].stats["switch_ca" if stop else "switch_cs"] += 1
            keep = max(cut - 1, 0)
            speed[i, cut:] = 0.0 if stop else max(speed[i, keep], 0.0)
            head[i, cut:] = head[i, keep]
            vs[i, cut:] = vs[i, keep]
            vh[i, cut:] = vh[i, keep]
            sources[i] = all_gp[:cut] + ("ca" if stop else "cs",) * (count - cut)
    sc = np.empty((bsz, 2, count))  # sin h, cos h
    np.sin(head, out=sc[:, 0])
    np.cos(head, out=sc[:, 1])
    # Integrated: east and north velocity (E[s]·E[sin h], E[s]·E[cos h], see integrate),
    # the speed variance and the cross-track variance rate s²·σh²; numpy's vectorised
    # sin, cos and exp, then one compiled pass per row (gpkernels.integrate_rows).
    if c.integration not in ("trapezoid", "left"):
        raise ValueError(f"unknown integration rule {c.integration!r}")
    eff = speed * np.exp(-0.5 * vh) if c.heading_damping else np.ascontiguousarray(speed)
    table = np.empty((bsz, 6, count))  # x, y, speed, heading (deg), var_x, var_y
    gpkernels.integrate_rows(eff, sc, mean, var, start, dgrid,
                             half_dgrid, c.integration == "trapezoid", DT * DT, table)
    end = float(grid[-1])
    return [Forecast(grid, row, src, end) for row, src in zip(table, sources, strict=True)]


class _BankCache:
    """What all predictors on one bank and noise configuration share: the bank as stacked
    model constants (speed rows, then heading rows) and the regular-grid selection and
    posterior caches."""

    def __init__(self, bank: KernelBank, c: HgpConfig) -> None:
        self.m = len(bank.speed)
        self.thetas = np.vstack([bank.speed, bank.heading])
        self.consts = _series_consts(self.thetas, self.m, c)
        self.pairs: dict[tuple[int, int], np.ndarray] = {}
        self.regular: dict[int, tuple[RegularSlopeBank, RegularSlopeBank]] = {}
        self.posterior: dict[tuple[int, int], tuple[RegularSlopePosterior, ...]] = {}

    def pair(self, i: int, j: int) -> np.ndarray:
        """The constants of speed model ``i`` and heading model ``j``, (2, 6)."""
        p = self.pairs.get((i, j))
        if p is None:
            p = self.pairs[i, j] = self.consts[[i, self.m + j]]
        return p


#: Per-bank caches (held weakly: a bank's factors go with it), then per noise configuration.
_BANK_CACHE: weakref.WeakKeyDictionary[KernelBank, dict[tuple, _BankCache]] = \
    weakref.WeakKeyDictionary()

#: One instance per distinct configuration, so that predictors can be grouped by identity.
_CONFIGS: dict[HgpConfig, HgpConfig] = {}


def _bank_cache(bank: KernelBank, c: HgpConfig) -> _BankCache:
    per_bank = _BANK_CACHE.setdefault(bank, {})
    key = (c.noise_speed, c.noise_heading, c.noise_accel, c.noise_yaw)
    cache = per_bank.get(key)
    if cache is None:
        cache = per_bank[key] = _BankCache(bank, c)
    return cache


def position_of(predictor: Predictor) -> Callable[[float], tuple[float, float]]:
    """(x, y) of ``predictor.predict(t)``, for a branch without a ``position`` method."""
    def position(t: float) -> tuple[float, float]:
        p = predictor.predict(t)
        return p.x, p.y
    return position


class Branches:
    """The kinematic predictors that run beside the GP (``HgpConfig.branches``) and their
    running scores per gap class: which one answers a gap, or the blend's weights (issue
    17; docs/hgp.md "Branches").  Made from :data:`catc.predict.kinematic_table.KINEMATIC`."""

    def __init__(self, c: HgpConfig) -> None:
        self.config = c
        self.kin: list[Predictor] = [KINEMATIC[name]() for name in c.branches]
        # where each branch puts the vehicle at t, for its score (position() where a
        # predictor has it: the x, y of predict() without the rest)
        self.xy = [getattr(k, "position", None) or position_of(k) for k in self.kin]
        # per gap class: GP, then each kinematic branch
        self.score = [[0.0] * (len(self.kin) + 1) for _ in range(len(c.branch_edges) + 1)]
        self.scored = [0] * (len(c.branch_edges) + 1)
        # per gap class, the branch that answers (kept up to date by add) and the margin
        # a kinematic branch must beat the GP by
        self.choice = [0] * (len(c.branch_edges) + 1)
        self.margins = c.margins()
        # per gap class, the blend's weights (branch_blend; None: the GP alone)
        self.weights: list[list[float] | None] = [None] * (len(c.branch_edges) + 1)

    def reset(self) -> None:
        """Forget the branches' histories and every score."""
        for k in self.kin:
            k.reset()
        self.score = [[0.0] * len(row) for row in self.score]
        self.scored = [0] * len(self.scored)
        self.choice = [0] * len(self.choice)
        self.weights = [None] * len(self.weights)

    def update(self, obs: Observation) -> None:
        """Feed every branch the received observation."""
        for k in self.kin:
            k.update(obs)

    def gap_class(self, tau: float) -> int:
        """The gap class of ``tau``: the number of ``branch_edges`` below it."""
        return bisect.bisect_left(self.config.branch_edges, tau)

    def score_gap(self, obs: Observation, gap: float, f: Forecast | None) -> None:
        """Score each branch at ``obs``, the BSM that ends a gap of ``gap`` s, the GP by
        its forecast ``f`` over the gap (nothing when no BSM was lost or the GP has no
        forecast over the gap).  Call it before the branches see ``obs``."""
        if gap <= DT + 1e-6:
            return
        if f is None or not covers(f, gap, self.config.horizon_s):
            return
        gx, gy = read_xy(f, gap)
        x, y = obs.x, obs.y
        errs = [(gx - x) ** 2 + (gy - y) ** 2]
        for position in self.xy:
            px, py = position(obs.t)
            errs.append((px - x) ** 2 + (py - y) ** 2)
        self.add(bisect.bisect_left(self.config.branch_edges, gap), errs)

    def add(self, g: int, errs: list[float]) -> None:
        """Enter one squared error per branch (the GP first) into gap class ``g``'s
        scores, and renew that class's choice (and blend weights)."""
        c = self.config
        d = c.branch_decay
        row = [d * old + (1.0 - d) * e for old, e in zip(self.score[g], errs, strict=True)]
        self.score[g] = row
        self.scored[g] += 1
        k = min(range(1, len(row)), key=row.__getitem__)
        self.choice[g] = k if row[k] < self.margins[g] * row[0] else 0
        if c.branch_blend:
            lim = c.branch_blend * max(min(row), 1e-12)
            inv = [max(e, 1e-12) ** -c.blend_power if e <= lim else 0.0 for e in row]
            total = sum(inv)
            self.weights[g] = [v / total for v in inv]

    def blend(self, t: float, gp: Prediction, w: list[float]) -> Prediction:
        """The branches' answers at ``t`` averaged with weights ``w`` (GP first); heading
        by its differences from the GP's, variances the GP's."""
        x, y, speed, dh = w[0] * gp.x, w[0] * gp.y, w[0] * gp.speed, 0.0
        for k, wk in zip(self.kin, w[1:], strict=True):
            if wk:
                p = k.predict(t)
                x += wk * p.x
                y += wk * p.y
                speed += wk * p.speed
                dh += wk * ((p.heading - gp.heading + 180.0) % 360.0 - 180.0)
        return Prediction(x, y, speed, (gp.heading + dh) % 360.0, gp.var_x, gp.var_y,
                          gp.source)


class _WindowPredictor:
    """What both GP predictors share: the window of received observations and a cached
    forecast from the last one."""

    def __init__(self, tw: int) -> None:
        self._obs: deque[Observation] = deque(maxlen=tw)
        self._forecast: Forecast | None = None

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


@dataclass
class Selection:
    """The models in use: θ per series, their bank rows (None for models from elsewhere:
    online ones, or a selection on values only) and their constants (2, 6)."""

    theta_s: np.ndarray
    theta_h: np.ndarray
    index: tuple[int, int] | None
    consts: np.ndarray


_GRIDS: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _grid(count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The forecast times k·DT for k < count, their differences and half those (cached)."""
    g = _GRIDS.get(count)
    if g is None:
        tau = np.arange(count) * DT
        dt = np.diff(tau)
        g = _GRIDS[count] = (tau, dt, 0.5 * dt)
    return g


def _steps(horizon: float, c: HgpConfig) -> int:
    """Forecast points (0.1 s steps from τ = 0) for a forecast ``horizon`` s long."""
    return math.ceil(min(horizon, c.horizon_s) / DT - 1e-9) + 1


class WindowState:
    """What a forecast of one RV starts from, and all that the fast path reads and writes:
    the window of received samples as running arrays, the models in use, the online bank,
    the caches shared with the other predictors on the same bank, and the counters.  An
    :class:`HgpPredictor` keeps one and hands it to :func:`_forecast_batch`."""

    def __init__(self, bank: KernelBank, c: HgpConfig) -> None:
        self.config = c
        self.bank = bank
        self.shared = _bank_cache(bank, c)
        self.online_speed: deque[np.ndarray] = deque(maxlen=c.online_max)
        self.online_heading: deque[np.ndarray] = deque(maxlen=c.online_max)
        #: Counters for captures and the H2 figures.
        self.stats = {"forecasts": 0, "selections": 0, "online_models": 0, "switch_ca": 0,
                      "switch_cs": 0}
        # The window as running arrays: one column per received sample (rows t, speed,
        # unwrapped heading in rad, x, y), columns lo..hi of a buffer twice as long.
        self.buf = np.empty((5, 2 * c.tw + 2))
        self.reset()

    def reset(self) -> None:
        """Forget the window and the selection (not the online bank nor the counters)."""
        self.lo = self.hi = 0
        self.turn = 0.0  # what unwrapping the heading has added so far, rad
        self.run = 0  # received samples in a row exactly DT apart
        self.last: Observation | None = None  # the last received sample
        self.selection: Selection | None = None
        self.since_selection = 0  # samples received since the selection was made

    def push(self, obs: Observation) -> None:
        """Append a received sample (later than the last one)."""
        c = self.config
        prev = self.last
        h = math.radians(obs.heading)
        if prev is None:
            self.run = 1
        else:
            dd = h - math.radians(prev.heading)  # np.unwrap's rule, one step at a time
            if abs(dd) >= math.pi:
                mod = (dd + math.pi) % (2.0 * math.pi) - math.pi
                if mod == -math.pi and dd > 0:
                    mod = math.pi
                self.turn += mod - dd
            gap = obs.t - prev.t
            self.run = self.run + 1 if abs(gap - DT) <= 2e-6 else 1
            if gap > c.reselect_gap_s + 1e-6:
                self.selection = None
        buf = self.buf
        if self.hi == buf.shape[1]:
            keep = c.tw - 1
            buf[:, :keep] = buf[:, self.hi - keep:self.hi]
            self.hi = keep
        buf[:, self.hi] = (obs.t, obs.speed, h + self.turn, obs.x, obs.y)
        self.hi += 1
        self.lo = max(0, self.hi - c.tw)
        self.since_selection += 1
        self.last = obs

    def window(self) -> np.ndarray:
        """The window's running arrays (rows t, speed, unwrapped heading rad, x, y)."""
        win = self.buf[:, self.lo:self.hi]
        if not math.isinf(self.config.window_s):
            win = win[:, int(np.argmax(win[0, -1] - win[0] <= self.config.window_s + 1e-9)):]
        return win

    def prepare(self) -> tuple[np.ndarray, tuple[RegularSlopeBank, ...] | None]:
        """The window relative to its last sample, (3, n + 1): τ then 0 (the slope's time);
        speed then the BSM's acceleration; heading (rad) then its yaw rate (rad/s); and the
        regular-grid selection cache if it is a full window of samples DT apart, else None."""
        c = self.config
        last = self.last
        win = self.window()
        n = win.shape[1]
        rel = np.empty((3, n + 1))
        np.subtract(win[:3], win[:3, -1:], out=rel[:, :n])
        rel[0, n] = 0.0
        if c.slopes:
            rel[1, n] = last.accel
            rel[2, n] = math.radians(last.yaw_rate)
        else:
            rel[1:, n] = 0.0
        return rel, self.cache_for(rel)

    def cache_for(self, rel: np.ndarray) -> tuple[RegularSlopeBank, ...] | None:
        """The regular-grid selection cache for the prepared window ``rel``, or None."""
        n = rel.shape[1] - 1
        regular = self.run >= n == self.config.tw and not self.online_speed
        return self.regular_cache(rel[0, :n]) if regular else None

    def regular_cache(self, tau: np.ndarray) -> tuple[RegularSlopeBank, ...] | None:
        """The cached selection for a window of ``tw`` samples at exactly DT apart (no loss),
        built once per bank and configuration and shared by all predictors."""
        c = self.config
        if len(tau) != c.tw or np.max(np.abs(np.diff(tau) - DT)) > 1e-6:
            return None
        regular = self.shared.regular
        cache = regular.get(c.tw)
        if cache is None:
            cache = regular[c.tw] = (
                RegularSlopeBank(self.bank.speed, c.tw, c.noise_speed, c.noise_accel),
                RegularSlopeBank(self.bank.heading, c.tw, c.noise_heading, c.noise_yaw))
        return cache

    def regular_posterior(self, i: int, j: int, count: int,
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For a full regular window and a forecast of ``count`` points: the posterior weights
        of speed model ``i`` and heading model ``j`` and their variances (2, count) (cached
        per bank; see :class:`RegularSlopePosterior`)."""
        c = self.config
        post = self.shared.posterior.get((c.tw, count))
        if post is None:
            grid = _grid(count)[0]
            post = self.shared.posterior[c.tw, count] = (
                RegularSlopePosterior(self.bank.speed, c.tw, c.noise_speed, c.noise_accel,
                                      grid),
                RegularSlopePosterior(self.bank.heading, c.tw, c.noise_heading, c.noise_yaw,
                                      grid))
        return post[0].weights[i], post[1].weights[j], np.vstack([post[0].var[i],
                                                                  post[1].var[j]])


def implausible(c: HgpConfig, grid: np.ndarray, speed: np.ndarray, vs: np.ndarray,
                head: np.ndarray, vh: np.ndarray) -> int | None:
    """Index of the first forecast step that breaks a hybrid-switching criterion."""
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


def select(s: WindowState, tau: np.ndarray, ys: np.ndarray, yh: np.ndarray,
           slopes: tuple[float, float] | None = None) -> tuple[np.ndarray, ...]:
    """Bank selection by maximum likelihood, by the readable formulas (the reference for
    the stacked selection of :func:`_select_batch`)."""
    c = s.config
    speed_bank = s.bank.speed
    heading_bank = s.bank.heading
    if s.online_speed:
        speed_bank = np.vstack([speed_bank, np.array(s.online_speed)])
        heading_bank = np.vstack([heading_bank, np.array(s.online_heading)])
    if slopes is not None and c.select_with_slopes:
        cache = None if s.online_speed else s.regular_cache(tau)
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


def own_selection(s: WindowState, rel: np.ndarray,
                  cache: tuple[RegularSlopeBank, ...] | None) -> Selection | None:
    """The selection for this window when it is not worth stacking with others (a regular
    window's cached one, an online bank, selection on values only); None otherwise."""
    c = s.config
    n = rel.shape[1] - 1
    tau, ys, yh = rel[0, :n], rel[1, :n], rel[2, :n]
    if not (c.slopes and c.select_with_slopes):
        theta_s, theta_h = select(s, tau, ys, yh, None)
        return Selection(theta_s, theta_h, None,
                         _series_consts(np.array([theta_s, theta_h]), 1, c))
    if s.online_speed:
        speed = np.vstack([s.bank.speed, np.array(s.online_speed)])
        thetas = np.vstack([speed, s.bank.heading, np.array(s.online_heading)])
        m = len(speed)
        lml = _lml_stack(tau[None], rel[None, 1:], _series_consts(thetas, m, c), m,
                         thetas)[0]
        pair = np.array([thetas[int(np.argmax(lml[:m]))], thetas[m + int(np.argmax(lml[m:]))]])
        return Selection(pair[0], pair[1], None, _series_consts(pair, 1, c))
    if cache is None:
        return None
    i = int(np.argmax(cache[0].lml_z(rel[1])))
    j = int(np.argmax(cache[1].lml_z(rel[2])))
    return Selection(s.bank.speed[i], s.bank.heading[j], (i, j), s.shared.pair(i, j))


def backtest_fails(c: HgpConfig, tau, ys, yh, x, y, theta_s, theta_h, s0, h0) -> bool:
    """True when the selected models miss the window's own last ``backtest_s`` by > PTE_th."""
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


def fit_online(s: WindowState, tau: np.ndarray, ys: np.ndarray, yh: np.ndarray,
               theta_s: np.ndarray, theta_h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """New speed and heading models fitted by LOO-CV on the window, warm-started from
    ``theta_s`` and ``theta_h``, added to the online bank (and counted)."""
    c = s.config
    theta_s = gp.fit(tau, ys, c.noise_speed, theta_s, c.speed_bounds).theta
    theta_h = gp.fit(tau, yh, c.noise_heading, theta_h, c.heading_bounds).theta
    s.online_speed.append(theta_s)
    s.online_heading.append(theta_h)
    s.stats["online_models"] += 1
    return theta_s, theta_h


def go_online(s: WindowState, rel: np.ndarray) -> None:
    """Online models: back-test the selection on the window and replace it by new fits
    (added to the online bank) when it misses by more than PTE_th."""
    c = s.config
    n = rel.shape[1] - 1
    tau, ys, yh = rel[0, :n], rel[1, :n], rel[2, :n]
    win, last, sel = s.window(), s.last, s.selection
    if backtest_fails(c, tau, ys, yh, win[3], win[4], sel.theta_s, sel.theta_h,
                      last.speed, math.radians(last.heading)):
        theta_s, theta_h = fit_online(s, tau, ys, yh, sel.theta_s, sel.theta_h)
        s.selection = Selection(theta_s, theta_h, None,
                                _series_consts(np.array([theta_s, theta_h]), 1, c))


class HgpPredictor(_WindowPredictor):
    """Indirect HGP: GPs on speed and heading, positions by integration."""

    name = "hgp"

    def __init__(self, bank: KernelBank | None = None, config: HgpConfig | None = None) -> None:
        c = config or HgpConfig()
        try:  # one instance per distinct configuration, for forecast_many's grouping
            self.config = _CONFIGS.setdefault(c, c)
        except TypeError:  # a field given as a list: unhashable, grouped alone
            self.config = c
        super().__init__(c.tw)
        self.bank = bank if bank is not None else default_bank()
        self._state = WindowState(self.bank, self.config)
        #: Counters for captures and the H2 figures.
        self.stats = self._state.stats
        self._branches = Branches(self.config)
        self._uncapped = math.isinf(c.window_s)  # the window is all of _obs

    def reset(self) -> None:
        super().reset()
        self._state.reset()
        self._branches.reset()

    def update(self, obs: Observation) -> None:
        prev = self._obs[-1] if self._obs else None
        if prev is not None and obs.t <= prev.t:
            return
        branches = self._branches
        if branches.kin:
            if prev is not None:
                branches.score_gap(obs, obs.t - prev.t, self._forecast)
            branches.update(obs)
        self._obs.append(obs)  # _WindowPredictor.update, its time check done above
        self._forecast = None
        self._state.push(obs)

    def predict(self, t: float) -> Prediction:
        answer = self.plan(t)
        return read(*answer) if answer.__class__ is tuple else answer

    def plan(self, t: float) -> Prediction | tuple[Forecast, float]:
        """What :meth:`predict` answers at ``t``: the Prediction, or ``(forecast, tau)``
        when the answer is the GP forecast read ``tau`` s after the last BSM (for
        :func:`catc.predict.predict_columns`, which reads many at once)."""
        last, tau = self._since_last(t)
        if tau == 0.0:
            return bsm_prediction(last)
        c = self.config
        if (len(self._obs) if self._uncapped else self._window_len()) < c.min_points:
            return self._ca(last, tau)
        f = self._forecast
        if f is None or not covers(f, tau, c.horizon_s):
            f = self._forecast = self._make_forecast(max(tau, 3.0))
        branches = self._branches
        if branches.kin:
            g = bisect.bisect_left(c.branch_edges, tau)
            if c.branch_blend:
                w = branches.weights[g]
                if w is not None:
                    return branches.blend(t, read(f, tau), w)
            else:
                branch = branches.choice[g]
                if branch:  # the GP's forecast is still made: it is scored at the next BSM
                    return branches.kin[branch - 1].predict(t)
        return f, tau

    def plan_pair(self, t0: float, t1: float) -> tuple:
        """``(plan(t0), plan(t1))``, the very answers of the two calls (t0 ≤ t1), in one:
        the CA-TC asks every RV at now and at now + 2 s, after its forecasts were made
        (then neither call makes one, and this shares their lookups)."""
        obs, f = self._obs, self._forecast
        if not obs or f is None or not t0 <= t1:
            return self.plan(t0), self.plan(t1)
        last = obs[-1]
        tau0, tau1 = elapsed(last.t, t0), elapsed(last.t, t1)
        c = self.config
        if ((len(obs) if self._uncapped else self._window_len()) < c.min_points
                or f.end < min(tau1, c.horizon_s) - 1e-9 or c.branch_blend):
            return self.plan(t0), self.plan(t1)  # a forecast to make, a blend, or CA
        branches = self._branches
        kin, choice = branches.kin, branches.choice
        if tau0 == 0.0:
            a0 = bsm_prediction(last)
        else:
            b = choice[bisect.bisect_left(c.branch_edges, tau0)] if kin else 0
            a0 = kin[b - 1].predict(t0) if b else (f, tau0)
        if tau1 == 0.0:
            return a0, bsm_prediction(last)
        b = choice[bisect.bisect_left(c.branch_edges, tau1)] if kin else 0
        return a0, kin[b - 1].predict(t1) if b else (f, tau1)

    def branch(self, tau: float) -> int:
        """Which branch answers ``tau`` s after the last BSM: 0 the GP, k the k-th of
        ``config.branches``."""
        return self._branches.choice[self._branches.gap_class(tau)]

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

    def _make_forecast(self, horizon: float) -> Forecast:
        return _forecast_batch([self._state], [_steps(horizon, self.config)])[0]

    def _make_forecast_reference(self, horizon: float) -> Forecast:
        """The forecast by the readable formulas, selecting every time: what
        :meth:`_make_forecast` computed before it was made fast, kept as the reference the
        tests compare it with and as the "before" of ``bench/hgp_forecast.py``."""
        c = self.config
        s = self._state
        s.stats["forecasts"] += 1
        last = self._obs[-1]
        tau, ys, yh, x, y = _window_series(self._obs, c.window_s)
        slopes = (last.accel, math.radians(last.yaw_rate)) if c.slopes else None
        theta_s, theta_h = select(s, tau, ys, yh, slopes)
        s0, h0 = last.speed, math.radians(last.heading)
        if c.online and backtest_fails(c, tau, ys, yh, x, y, theta_s, theta_h, s0, h0):
            theta_s, theta_h = fit_online(s, tau, ys, yh, theta_s, theta_h)
        n = math.ceil(min(horizon, c.horizon_s) / DT - 1e-9)
        grid = np.arange(n + 1) * DT
        ms, vs, mh, vh = forecast_path(tau, ys, yh, slopes, theta_s, theta_h, grid, c)
        speed = ms + s0
        head = mh + h0
        source = ["gp"] * (n + 1)
        cut = implausible(c, grid, speed, vs, head, vh)
        if cut is not None:
            stop = bool(speed[cut] < 0)
            s.stats["switch_ca" if stop else "switch_cs"] += 1
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
        return Forecast(grid, np.array([px, py, speed, np.degrees(head) % 360.0,
                                         var_along * sh**2 + var_cross * ch**2,
                                         var_along * ch**2 + var_cross * sh**2]), source)


#: Windows per stacked call: bounds the work arrays (a selection's exponentials are
#: 120 kB per window, a posterior's 23 kB).
_SELECT_CHUNK = 16
_POSTERIOR_CHUNK = 64


def _stack(arrays: list[np.ndarray]) -> np.ndarray:
    """``np.stack(arrays)`` for arrays of one shape, a third of its cost (no per-array
    ``expand_dims``)."""
    return np.concatenate(arrays).reshape(len(arrays), *arrays[0].shape)


def _select_batch(states: list[WindowState], rels: list[np.ndarray],
                  caches: list[tuple[RegularSlopeBank, ...] | None]) -> None:
    """Select bank models for these windows: the same choice as :func:`select`."""
    todo = []
    for s, rel, cache in zip(states, rels, caches, strict=True):
        s.stats["selections"] += 1
        s.since_selection = 0
        sel = own_selection(s, rel, cache)
        if sel is None:
            todo.append((s, rel))
        else:
            s.selection = sel
    by_len: dict[int, list[tuple[WindowState, np.ndarray]]] = {}
    for item in todo:
        by_len.setdefault(item[1].shape[1], []).append(item)
    for items in by_len.values():
        shared = items[0][0].shared
        m = shared.m
        for lo in range(0, len(items), _SELECT_CHUNK):
            chunk = items[lo:lo + _SELECT_CHUNK]
            rels = _stack([r for _, r in chunk])
            lml = _lml_stack(rels[:, 0, :-1], rels[:, 1:], shared.consts, m, shared.thetas)
            best_s = np.argmax(lml[:, :m], axis=1).tolist()
            best_h = np.argmax(lml[:, m:], axis=1).tolist()
            for (s, _), i, j in zip(chunk, best_s, best_h, strict=True):
                s.selection = Selection(shared.thetas[i], shared.thetas[m + j], (i, j),
                                        shared.pair(i, j))


def _prepare_many(states: list[WindowState]) -> list[tuple]:
    """:meth:`WindowState.prepare` of each window; full windows (``tw`` samples, no time
    cap: nearly all of them) in one stacked subtraction, the same numbers."""
    c = states[0].config
    out: list = [None] * len(states)
    full, wins = [], []
    if c.slopes and math.isinf(c.window_s):
        for i, s in enumerate(states):
            if s.hi - s.lo == c.tw:
                full.append(i)
                wins.append(s.buf[:3, s.lo:s.hi])
    if len(full) > 1:
        win = _stack(wins)
        n = c.tw
        rel = np.empty((len(full), 3, n + 1))
        np.subtract(win, win[:, :, -1:], out=rel[:, :, :n])
        rel[:, 0, n] = 0.0
        last = [states[i].last for i in full]
        rel[:, 1, n] = [o.accel for o in last]
        rel[:, 2, n] = [math.radians(o.yaw_rate) for o in last]
        for i, r in zip(full, rel, strict=True):
            out[i] = (r, states[i].cache_for(r))
    for i, s in enumerate(states):
        if out[i] is None:
            out[i] = s.prepare()
    return out


def _forecast_batch(states: list[WindowState], counts: list[int]) -> list[Forecast]:
    """Forecasts of ``counts[i]`` points from each window (all on one bank and
    configuration), computed stacked; what :meth:`HgpPredictor._make_forecast_reference`
    computes, to round-off, with the selection renewed as ``reselect_every`` and
    ``reselect_gap_s`` say."""
    c = states[0].config
    prepared = _prepare_many(states)
    stale = []
    for i, s in enumerate(states):
        s.stats["forecasts"] += 1
        if s.selection is None or s.since_selection >= c.reselect_every:
            stale.append(i)
    if stale:
        _select_batch([states[i] for i in stale], [prepared[i][0] for i in stale],
                      [prepared[i][1] for i in stale])
    if c.online:
        for s, (rel, _) in zip(states, prepared, strict=True):
            go_online(s, rel)
    out: list[Forecast | None] = [None] * len(states)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, ((rel, _), count) in enumerate(zip(prepared, counts, strict=True)):
        groups.setdefault((rel.shape[1], count), []).append(i)
    for (_, count), members in groups.items():
        grid = _grid(count)[0]
        direct = []
        for row, i in enumerate(members):
            sel, cache = states[i].selection, prepared[i][1]
            if c.slopes and not (sel.index is not None and cache is not None):
                direct.append(row)
        if len(direct) == len(members) <= _POSTERIOR_CHUNK:  # the usual case: one call
            rels = [prepared[i][0] for i in members]
            consts = [states[i].selection.consts for i in members]
            mean, var = _posterior_stack(_stack(rels), grid, _stack(consts))
        else:
            mean = np.empty((len(members), 2, count))
            var = np.empty((len(members), 2, count))
            for row, i in enumerate(members):
                s, rel, sel = states[i], prepared[i][0], states[i].selection
                if not c.slopes:
                    tau = rel[0, :-1]
                    mean[row, 0], var[row, 0] = gp.posterior(tau, rel[1, :-1], grid,
                                                             sel.theta_s, c.noise_speed)
                    mean[row, 1], var[row, 1] = gp.posterior(tau, rel[2, :-1], grid,
                                                             sel.theta_h, c.noise_heading)
                elif sel.index is not None and prepared[i][1] is not None:
                    w_s, w_h, var[row] = s.regular_posterior(*sel.index, count)
                    np.dot(w_s, rel[1], out=mean[row, 0])
                    np.dot(w_h, rel[2], out=mean[row, 1])
            for lo in range(0, len(direct), _POSTERIOR_CHUNK):
                rows = direct[lo:lo + _POSTERIOR_CHUNK]
                chunk = [members[r] for r in rows]
                mean[rows], var[rows] = _posterior_stack(
                    _stack([prepared[i][0] for i in chunk]), grid,
                    _stack([states[i].selection.consts for i in chunk]))
        if c.slopes and c.speed_model == "ca":  # diagnostics: kinematic speed or heading
            for row, i in enumerate(members):
                mean[row, 0], var[row, 0] = prepared[i][0][1, -1] * grid, 0.0
        if c.slopes and c.heading_model == "ctrv":
            for row, i in enumerate(members):
                mean[row, 1], var[row, 1] = prepared[i][0][2, -1] * grid, 0.0
        start = np.array([(o.speed, math.radians(o.heading), o.x, o.y)
                          for o in (states[i].last for i in members)])
        for i, f in zip(members, _finish_stack([states[i] for i in members], mean, var, start,
                                               grid), strict=True):
            out[i] = f
    return out  # type: ignore[return-value]


def forecast_many(predictors: Iterable[object], t: float) -> int:
    """Make, stacked, the forecast each HGP predictor in ``predictors`` will need to answer
    ``predict(t)``, and cache it there: the same forecast ``predict`` would make itself (to
    round-off), at a fraction of the cost when many are due at once.  Call it once per tick
    with the latest time the tick will ask for (the OBU: now + 2 s), then ``predict`` as
    usual; a forecast reaching ``t`` serves every earlier time too.  Predictors whose cached
    forecast already reaches ``t``, that have no data (or too little for a GP) and non-HGP
    predictors are left alone.  Returns the number of forecasts made."""
    return forecast_many_at((p, t) for p in predictors)


def forecast_many_at(items: Iterable[tuple[object, float]]) -> int:
    """:func:`forecast_many` with a time per predictor: ``(predictor, t)`` pairs (predictors
    on different clocks, e.g. the vehicles of many trips replayed in lockstep)."""
    groups: dict[tuple[int, int], list[tuple[HgpPredictor, int]]] = {}
    for p, t in items:
        if not isinstance(p, HgpPredictor) or not p._obs:
            continue
        tau = t - p._obs[-1].t
        if not tau > 0.0:
            continue
        c = p.config
        f = p._forecast  # most are still covered: asked first, covers() inlined
        if f is not None and f.end >= min(tau, c.horizon_s) - 1e-9:
            continue
        if p._window_len() < c.min_points:
            continue
        groups.setdefault((id(c), id(p._state.shared)), []).append((p, _steps(max(tau, 3.0), c)))
    for group in groups.values():
        preds = [p for p, _ in group]
        made = _forecast_batch([p._state for p in preds], [n for _, n in group])
        for p, f in zip(preds, made, strict=True):
            p._forecast = f
    return sum(len(group) for group in groups.values())


register_batch(HgpPredictor, forecast_many_at, plans=True)


def warm_up() -> None:
    """Load (or, on a machine's first run, compile) the compiled kernels now, with one
    forecast of a window with losses: a daemon calls this before its first tick, which
    would otherwise take ~0.2 s longer (several seconds on a cold compile cache)."""
    p = HgpPredictor()
    for k in range(12):
        if k % 3:
            p.update(Observation(0.1 * k, 0.0, 2.0 * k, 20.0, 0.0, 0.0, 0.0))
    p.predict(2.0)


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
    #: Model persistency, as ``HgpConfig.reselect_every``: θ is re-fitted when at least
    #: this many BSMs arrived since the last fit (1 = at every forecast, as before).  Each
    #: fit is two LOO optimisations (~3 ms each on x/y windows): re-fitting at every BSM
    #: made hgp-d 8× the cost of hgp in a sweep; 10 cuts its cost 3.5× and moves PTE95 both
    #: ways (NGSIM, 30 pairs: +32 % at PER 50 %, −12 % at 90 %; docs/hgp.md).
    refit_every: int = 10


class HgpDirectPredictor(_WindowPredictor):
    """Direct HGP (``hgp-d``): GPs on x and y relative to the last BSM.

    x and y have no trained bank of their own (their scale is set by the speed, not by
    the driver), so forecasts fit both models by LOO-CV, warm-started from the previous
    fit, and keep θ for ``refit_every`` BSMs (the posterior always uses the latest window).
    Switching: a forecast step whose implied acceleration
    exceeds ``accel_max`` or whose position standard deviation exceeds
    ``position_std_max`` ends the GP; the vehicle continues at the last plausible
    velocity (source ``"cs"``).
    """

    name = "hgp-d"

    def __init__(self, config: HgpDirectConfig | None = None) -> None:
        self.config = config or HgpDirectConfig()
        super().__init__(self.config.tw)
        self._theta = (np.array(self.config.theta0), np.array(self.config.theta0))
        self._since_fit: int | None = None

    def reset(self) -> None:
        super().reset()
        self._theta = (np.array(self.config.theta0), np.array(self.config.theta0))
        self._since_fit = None  # BSMs since the last fit; None: never fitted

    def update(self, obs: Observation) -> None:
        fresh = not self._obs or obs.t > self._obs[-1].t
        super().update(obs)
        if fresh and self._since_fit is not None:
            self._since_fit += 1

    def predict(self, t: float) -> Prediction:
        last, tau = self._since_last(t)
        if tau == 0.0:
            return bsm_prediction(last)
        if len(self._obs) < self.config.min_points:
            return constant_speed(last, tau)
        f = self._forecast
        if f is None or not covers(f, tau, self.config.horizon_s):
            f = self._forecast = self._make_forecast(max(tau, 3.0))
        return read(f, tau)

    def _make_forecast(self, horizon: float) -> Forecast:
        c = self.config
        last = self._obs[-1]
        tau, _, _, x, y = _window_series(self._obs)
        rx, ry = x - x[-1], y - y[-1]
        if self._since_fit is None or self._since_fit >= c.refit_every:
            self._theta = (gp.fit(tau, rx, c.noise_pos, self._theta[0]).theta,
                           gp.fit(tau, ry, c.noise_pos, self._theta[1]).theta)
            self._since_fit = 0
        theta_x, theta_y = self._theta
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
        return Forecast(grid, np.array([px, py, speed, heading, vx, vy]), source)
