"""Gaussian-process core of the HGP: kernel, LOO training objective, fit, posterior, bank LML.

Pure numpy/scipy, no I/O.  Names follow the paper (section "Training", eq. "covariance
func": κ, θ = {γ, α1, α2}) and Rasmussen & Williams, *Gaussian Processes for Machine
Learning* (MIT Press 2006), cited below as "R&W 2006": ``K``, ``L``, ``alpha_``.

Model.  Zero prior mean and the paper's compound RBF + linear covariance

    κ(t, t') = α1² exp(−(t − t')² / (2γ²)) + α2² t t'           (paper eq. "covariance func")

on 1-D times ``t`` in seconds.  The caller picks the time origin; the HGP uses times relative
to the last sample (so ``t ≤ 0``) and values relative to the last value.  Observations carry
a fixed white noise σn² (``noise_var``, not optimised): the training covariance is
``K = κ(t, t) + σn² I``.  :func:`posterior` returns the *latent* f*, without σn².

Numerics.  Every solve goes through a Cholesky factor ``L`` of ``K`` (LAPACK ``potrf``, the
routine behind ``scipy.linalg.cho_factor``; it is called directly because at n = 30 the
wrapper's checks cost as much as the factorisation).  ``K⁻¹`` where needed is
``L⁻ᵀ L⁻¹`` with ``L⁻¹`` from LAPACK ``trtri``.  No jitter is added: with ``noise_var > 0``
``K`` is positive definite in exact arithmetic, and if the factorisation still fails
(ill-conditioned θ far outside :data:`DEFAULT_BOUNDS`) the LOO objective returns
``(−inf, zeros)``, :func:`fit` keeps the best point it evaluated, and the likelihood
functions raise :class:`numpy.linalg.LinAlgError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack
from scipy.optimize import Bounds, minimize

__all__ = [
    "DEFAULT_BOUNDS",
    "DEFAULT_NOISE_VAR",
    "DEFAULT_THETA0",
    "FitResult",
    "GPModel",
    "RegularGridBank",
    "bank_log_marginal_likelihood",
    "fit",
    "kernel",
    "kernel_grads",
    "log_marginal_likelihood",
    "loo_log_predictive",
    "posterior",
]

Array = NDArray[np.float64]

DEFAULT_NOISE_VAR = 1e-4
"""σn² on the training diagonal: a 0.01 (m/s or deg) measurement noise, enough to keep
``K`` well conditioned for the HGP's 0.1 s windows."""

DEFAULT_BOUNDS: tuple[tuple[float, float], ...] = ((0.05, 100.0), (1e-3, 1e3), (1e-4, 1e2))
"""Bounds on θ = (γ, α1, α2) for :func:`fit`.

γ (s): from half a sample period at 10 Hz (0.05 s) to 100 s, far longer than any window.
α1 (units of y): RBF amplitude, from 1 mm/s (or 0.001°) to 1000 (a full heading turn).
α2 (units of y per s): slope scale of the linear term, from 1e-4 to 100 per second.
"""

DEFAULT_THETA0: tuple[float, float, float] = (1.0, 1.0, 0.1)
"""Warm start (γ, α1, α2) for :func:`fit` when the caller has no bank model."""

_LOG_2PI = math.log(2.0 * math.pi)


# ---------------------------------------------------------------- validation


def _as_1d(name: str, x: ArrayLike) -> Array:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def _check_window(t: ArrayLike, y: ArrayLike) -> tuple[Array, Array]:
    t_arr, y_arr = _as_1d("t", t), _as_1d("y", y)
    if t_arr.shape != y_arr.shape:
        raise ValueError(f"t and y lengths differ: {t_arr.size} != {y_arr.size}")
    if t_arr.size < 3:
        raise ValueError(f"need at least 3 samples, got {t_arr.size}")
    return t_arr, y_arr


def _check_noise(noise_var: float) -> float:
    nv = float(noise_var)
    if not (math.isfinite(nv) and nv > 0.0):
        raise ValueError(f"noise_var must be finite and > 0, got {noise_var!r}")
    return nv


def _check_theta(theta: ArrayLike, name: str = "theta") -> Array:
    th = np.asarray(theta, dtype=np.float64)
    if th.shape != (3,):
        raise ValueError(f"{name} must be (gamma, alpha1, alpha2), got shape {th.shape}")
    if not (np.all(np.isfinite(th)) and np.all(th > 0.0)):
        raise ValueError(f"{name} must be finite and > 0, got {th.tolist()}")
    return th


def _check_thetas(thetas: ArrayLike) -> Array:
    th = np.asarray(thetas, dtype=np.float64)
    if th.ndim != 2 or th.shape[1] != 3 or th.shape[0] < 1:
        raise ValueError(f"thetas must have shape (M, 3) with M >= 1, got {th.shape}")
    if not (np.all(np.isfinite(th)) and np.all(th > 0.0)):
        raise ValueError("thetas must be finite and > 0")
    return th


def _check_bounds(bounds: ArrayLike) -> Array:
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (3, 2):
        raise ValueError(f"bounds must be 3 (low, high) pairs, got shape {b.shape}")
    if not (np.all(np.isfinite(b)) and np.all(b[:, 0] > 0.0) and np.all(b[:, 0] <= b[:, 1])):
        raise ValueError(f"bounds must satisfy 0 < low <= high < inf, got {b.tolist()}")
    return b


@lru_cache(maxsize=64)
def _cached_log_bounds(key: tuple[tuple[float, ...], ...]) -> Bounds:
    return Bounds(*np.log(_check_bounds(key)).T)


def _log_bounds(bounds: ArrayLike) -> Bounds:
    """Validated bounds in log θ as a scipy ``Bounds``, cached: building and checking them
    costs about as much as two LOO evaluations at n = 30."""
    try:
        key = tuple(tuple(float(v) for v in pair) for pair in bounds)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        _check_bounds(bounds)
        raise
    return _cached_log_bounds(key)


# ---------------------------------------------------------------- kernel


def kernel(t1: ArrayLike, t2: ArrayLike, theta: ArrayLike) -> Array:
    """κ(t1, t2) of the paper's eq. "covariance func", shape (len(t1), len(t2)), no noise."""
    a, b = _as_1d("t1", t1), _as_1d("t2", t2)
    gamma, a1, a2 = _check_theta(theta)
    d = a[:, None] - b[None, :]
    return a1 * a1 * np.exp(d * d * (-0.5 / (gamma * gamma))) + a2 * a2 * np.outer(a, b)


def kernel_grads(t: ArrayLike, theta: ArrayLike) -> tuple[Array, Array]:
    """``K = κ(t, t)`` (no noise) and ``dK[j] = ∂K/∂log θ_j``, shape (3, n, n).

    With ``E = exp(−D/(2γ²))``, ``D = (t_i − t_j)²``:  ∂K/∂log γ = α1² E∘D/γ²,
    ∂K/∂log α1 = 2α1² E,  ∂K/∂log α2 = 2α2² t tᵀ.  σn² is fixed, so it has no gradient.
    """
    tt = _as_1d("t", t)
    gamma, a1, a2 = _check_theta(theta)
    d = tt[:, None] - tt[None, :]
    sq = d * d
    e = np.exp(sq * (-0.5 / (gamma * gamma)))
    s1, s2 = a1 * a1, a2 * a2
    tt_out = np.outer(tt, tt)
    k = s1 * e + s2 * tt_out
    dk = np.stack([(s1 / (gamma * gamma)) * e * sq, 2.0 * s1 * e, 2.0 * s2 * tt_out])
    return k, dk


# ---------------------------------------------------------------- LOO objective


class _Window:
    """What the LOO objective needs of one window, computed once per fit.

    ``planes`` holds [E∘D, E, t tᵀ, I] (D = (t_i − t_j)², E = exp(−D/(2γ²))) so that both
    ``K = (0, α1², α2², σn²) · planes`` and the three gradient contractions are single
    matrix products; E and E∘D are refreshed in place for each θ.
    """

    __slots__ = ("coef", "g_planes", "k_planes", "n", "planes", "sq", "t", "y")

    def __init__(self, t: Array, y: Array, noise_var: float) -> None:
        n = t.size
        d = t[:, None] - t[None, :]
        self.sq = d * d
        self.planes = np.zeros((4, n, n))
        self.planes[2] = np.outer(t, t)
        self.planes[3] = np.eye(n)
        flat = self.planes.reshape(4, n * n)
        self.k_planes, self.g_planes = flat[1:], flat[:3]
        self.coef = np.array([1.0, 1.0, noise_var])
        self.t, self.y, self.n = t, y, n

    def loo(self, log_theta: Array) -> tuple[float, Array]:
        """R&W 2006 eqs. 5.10–5.13 on this window; see :func:`loo_log_predictive`."""
        log_g, log_a1, log_a2 = log_theta.tolist()
        inv_g2, s1, s2 = math.exp(-2.0 * log_g), math.exp(2.0 * log_a1), math.exp(2.0 * log_a2)
        n, e = self.n, self.planes[1]
        np.multiply(self.sq, -0.5 * inv_g2, out=e)
        np.exp(e, out=e)
        self.coef[0], self.coef[1] = s1, s2
        k = (self.coef @ self.k_planes).reshape(n, n)
        # K is symmetric, so its C-ordered buffer is the Fortran-ordered K LAPACK wants.
        low, info = lapack.dpotrf(k.T, lower=1, clean=1, overwrite_a=1)
        if info != 0:
            return -math.inf, np.zeros(3)
        linv, info = lapack.dtrtri(low, lower=1, overwrite_c=1)
        if info != 0:
            return -math.inf, np.zeros(3)
        kinv = linv.T @ linv
        alpha = kinv @ self.y
        kd = kinv.diagonal()
        w = 1.0 / kd
        aw = alpha * w
        # eq. 5.12 with μ_i, σ_i² of eqs. 5.10–5.11 substituted:
        # L = Σ ½ log [K⁻¹]_ii − α_i² / (2 [K⁻¹]_ii) − ½ log 2π
        loo = 0.5 * (np.log(kd).sum() - alpha @ aw - n * _LOG_2PI)
        # eq. 5.13, ∂L/∂θ_j = Σ_i (α_i [Z_j α]_i − ½ (1 + α_i²/[K⁻¹]_ii) [Z_j K⁻¹]_ii) / [K⁻¹]_ii
        # with Z_j = K⁻¹ ∂K/∂θ_j, folded into one matrix G so that ∂L/∂θ_j = Σ_kl G_kl ∂K_kl/∂θ_j;
        # ∂K/∂log θ = (α1²/γ² E∘D, 2α1² E, 2α2² t tᵀ).
        c = 0.5 * (w + aw * aw)  # ½ (1 + α_i²/[K⁻¹]_ii) / [K⁻¹]_ii
        g = (kinv @ aw)[:, None] * alpha
        g -= (kinv * c) @ kinv
        np.multiply(e, self.sq, out=self.planes[0])
        grad = np.dot(self.g_planes, g.ravel())
        grad *= (s1 * inv_g2, 2.0 * s1, 2.0 * s2)
        return float(loo), grad


def loo_log_predictive(
    log_theta: ArrayLike, t: ArrayLike, y: ArrayLike, noise_var: float = DEFAULT_NOISE_VAR
) -> tuple[float, Array]:
    """The paper's LOO objective L(t, X, θ) and its gradient w.r.t. log θ.

    Closed form from ``K⁻¹`` (R&W 2006 §5.4.2): μ_i = y_i − [K⁻¹y]_i/[K⁻¹]_ii (eq. 5.10),
    σ_i² = 1/[K⁻¹]_ii (eq. 5.11), L = Σ_i −½ log σ_i² − (y_i − μ_i)²/(2σ_i²) − ½ log 2π
    (eq. 5.12), gradient eq. 5.13.  ``K`` includes σn², so σ_i² is the predictive variance of
    the noisy y_i given the other n − 1 points.  Returns ``(−inf, zeros(3))`` when the
    Cholesky factorisation of ``K`` fails.
    """
    tt, yy = _check_window(t, y)
    lt = np.asarray(log_theta, dtype=np.float64)
    if lt.shape != (3,) or not np.all(np.isfinite(lt)):
        raise ValueError(f"log_theta must be 3 finite values, got {np.asarray(log_theta)!r}")
    return _Window(tt, yy, _check_noise(noise_var)).loo(lt)


# ---------------------------------------------------------------- fit


@dataclass(frozen=True, slots=True)
class FitResult:
    """Outcome of :func:`fit`: θ = (γ, α1, α2), the LOO objective there, L-BFGS-B iterations,
    and whether the optimiser met its tolerance (False also when it hit ``max_iter``)."""

    theta: Array
    loo: float
    n_iter: int
    converged: bool


def fit(
    t: ArrayLike,
    y: ArrayLike,
    noise_var: float = DEFAULT_NOISE_VAR,
    theta0: ArrayLike = DEFAULT_THETA0,
    bounds: ArrayLike = DEFAULT_BOUNDS,
    max_iter: int = 50,
    ftol: float = 1e-4,
) -> FitResult:
    """Learn θ by maximising the LOO objective (paper, "Training"; R&W 2006 §5.4.2).

    L-BFGS-B (``scipy.optimize.minimize``) in log θ with the analytic gradient (eq. 5.13),
    box-bounded by ``bounds``, warm-started from ``theta0`` (the HGP passes the most likely
    bank model; it is clipped into ``bounds``).  ``max_iter`` caps the iterations; ``ftol`` is
    L-BFGS-B's relative reduction tolerance, (L_k+1 − L_k)/max(|L_k|, 1) ≤ ftol.  The default
    1e-4 (about 0.01 nats on a TW = 30 speed window, where |L| ≈ 100) stops a few hundredths
    of a nat short of the tight optimum with no worse 3 s forecast error, at about a third of
    the cost of ftol = 1e-9 (``bench/gp_fit.py`` measures both).

    The result is the best point evaluated.  Points where the Cholesky factorisation fails
    are reported to L-BFGS-B as +inf (as scikit-learn does); if every point fails,
    ``loo`` is −inf and ``theta`` is the clipped warm start.
    """
    if not (isinstance(max_iter, int | np.integer) and max_iter >= 1):
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    if not (math.isfinite(ftol) and ftol > 0.0):
        raise ValueError(f"ftol must be finite and > 0, got {ftol!r}")
    tt, yy = _check_window(t, y)
    win = _Window(tt, yy, _check_noise(noise_var))
    log_b = _log_bounds(bounds)
    x0 = np.clip(np.log(_check_theta(theta0, "theta0")), log_b.lb, log_b.ub)

    best = [math.inf, x0]

    def objective(x: Array) -> tuple[float, Array]:
        val, grad = win.loo(x)
        if val == -math.inf:
            return math.inf, grad
        if -val < best[0]:
            best[0], best[1] = -val, x.copy()
        return -val, -grad

    res = minimize(objective, x0, jac=True, method="L-BFGS-B", bounds=log_b,
                   options={"maxiter": int(max_iter), "ftol": float(ftol), "gtol": 1e-6})
    return FitResult(theta=np.exp(best[1]), loo=-best[0], n_iter=int(res.nit),
                     converged=bool(res.success) and math.isfinite(best[0]))


# ---------------------------------------------------------------- posterior


class GPModel:
    """A GP conditioned on one window, reusable for many ``t_star`` (R&W 2006 Algorithm 2.1).

    ``L_`` is the Cholesky factor of ``K = κ(t, t) + σn² I`` and ``alpha_ = Lᵀ \\ (L \\ y)``;
    :meth:`predict` gives the paper's eq. "forecastingheadingspeed" mean and variance.
    """

    __slots__ = ("L_", "alpha_", "noise_var", "t", "theta")

    def __init__(
        self, t: ArrayLike, y: ArrayLike, theta: ArrayLike, noise_var: float = DEFAULT_NOISE_VAR
    ) -> None:
        self.t, yy = _check_window(t, y)
        self.theta = _check_theta(theta)
        self.noise_var = _check_noise(noise_var)
        gamma, a1, a2 = self.theta
        d = self.t[:, None] - self.t[None, :]
        k = a1 * a1 * np.exp(d * d * (-0.5 / (gamma * gamma))) + a2 * a2 * np.outer(self.t, self.t)
        k.flat[:: self.t.size + 1] += self.noise_var
        low, info = lapack.dpotrf(k.T, lower=1, clean=1, overwrite_a=1)  # K = Kᵀ, no copy
        if info != 0:
            raise np.linalg.LinAlgError(f"K is not positive definite for theta={self.theta}")
        self.L_ = low
        self.alpha_ = lapack.dpotrs(low, yy, lower=1)[0]

    def predict(self, t_star: ArrayLike) -> tuple[Array, Array]:
        """Mean ``K*ᵀ alpha_`` and latent variance ``diag(K**) − Σ v²``, ``v = L \\ K*``.

        The variance excludes σn² (it is the variance of f*, like sklearn's ``return_std``)
        and is clipped at 0 against round-off.
        """
        ts = _as_1d("t_star", t_star)
        gamma, a1, a2 = self.theta
        s1, s2 = a1 * a1, a2 * a2
        d = self.t[:, None] - ts[None, :]
        k_star = s1 * np.exp(d * d * (-0.5 / (gamma * gamma))) + s2 * np.outer(self.t, ts)
        mean = k_star.T @ self.alpha_
        v = lapack.dtrtrs(self.L_, k_star, lower=1)[0]
        var = s1 + s2 * ts * ts - np.einsum("ij,ij->j", v, v)
        return mean, np.maximum(var, 0.0)


def posterior(
    t: ArrayLike,
    y: ArrayLike,
    t_star: ArrayLike,
    theta: ArrayLike,
    noise_var: float = DEFAULT_NOISE_VAR,
) -> tuple[Array, Array]:
    """Predictive mean and latent variance at ``t_star`` (R&W 2006 Algorithm 2.1)."""
    return GPModel(t, y, theta, noise_var).predict(t_star)


# ---------------------------------------------------------------- marginal likelihood


def _stack_k(t: Array, thetas: Array, noise_var: float) -> Array:
    """``K_m = κ(t, t | θ_m) + σn² I`` for every row of ``thetas``, shape (M, n, n)."""
    d = t[:, None] - t[None, :]
    sq = d * d
    g, a1, a2 = thetas.T
    k = (a1 * a1)[:, None, None] * np.exp(sq[None] * (-0.5 / (g * g))[:, None, None])
    k += (a2 * a2)[:, None, None] * np.outer(t, t)[None]
    k[:, np.arange(t.size), np.arange(t.size)] += noise_var
    return k


def log_marginal_likelihood(
    t: ArrayLike, y: ArrayLike, theta: ArrayLike, noise_var: float = DEFAULT_NOISE_VAR
) -> float:
    """log p(y | t, θ) = −½ yᵀK⁻¹y − Σ log L_ii − n/2 log 2π (R&W 2006 eq. 2.30, Alg. 2.1);
    the score the paper maximises to select a bank model (eq. "eq-,odelselection")."""
    model = GPModel(t, y, theta, noise_var)
    yy = np.asarray(y, dtype=np.float64)
    return float(-0.5 * yy @ model.alpha_ - np.log(model.L_.diagonal()).sum()
                 - 0.5 * yy.size * _LOG_2PI)


def bank_log_marginal_likelihood(
    t: ArrayLike, y: ArrayLike, thetas: ArrayLike, noise_var: float = DEFAULT_NOISE_VAR
) -> Array:
    """R&W 2006 eq. 2.30 for every bank model θ_m (rows of ``thetas``, shape (M, 3)) at once:
    one batched Cholesky and one batched solve over the (M, n, n) stack.  Returns (M,)."""
    tt, yy = _check_window(t, y)
    k = _stack_k(tt, _check_thetas(thetas), _check_noise(noise_var))
    low = np.linalg.cholesky(k)
    z = np.linalg.solve(low, np.broadcast_to(yy[:, None], (k.shape[0], yy.size, 1)))[..., 0]
    logdet_half = np.log(np.diagonal(low, axis1=1, axis2=2)).sum(axis=1)
    return -0.5 * np.einsum("mi,mi->m", z, z) - logdet_half - 0.5 * yy.size * _LOG_2PI


class RegularGridBank:
    """Bank LML cache for the regular grid ``t = −(n−1)·dt, …, −dt, 0`` (relative to the last
    sample): each model's whitening ``L_m⁻¹`` and ``log|K_m|`` are computed once, so scoring a
    new window is one matrix product (R&W 2006 eq. 2.30 with yᵀK⁻¹y = ‖L⁻¹y‖²).

    ``lml(y)`` equals :func:`bank_log_marginal_likelihood` on the same grid.
    """

    __slots__ = ("_const", "_w", "dt", "n", "noise_var", "t", "thetas")

    def __init__(
        self, thetas: ArrayLike, n: int, dt: float = 0.1, noise_var: float = DEFAULT_NOISE_VAR
    ) -> None:
        if int(n) != n or n < 3:
            raise ValueError(f"n must be an integer >= 3, got {n!r}")
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt must be finite and > 0, got {dt!r}")
        self.thetas = _check_thetas(thetas)
        self.n, self.dt = int(n), float(dt)
        self.noise_var = _check_noise(noise_var)
        self.t = (np.arange(self.n, dtype=np.float64) - (self.n - 1)) * self.dt
        low = np.linalg.cholesky(_stack_k(self.t, self.thetas, self.noise_var))
        eye = np.broadcast_to(np.eye(self.n), low.shape)
        self._w = np.linalg.solve(low, eye).reshape(-1, self.n)
        logdet_half = np.log(np.diagonal(low, axis1=1, axis2=2)).sum(axis=1)
        self._const = -logdet_half - 0.5 * self.n * _LOG_2PI

    def lml(self, y: ArrayLike) -> Array:
        """log p(y | θ_m) for every model: shape (M,) for a window ``y`` of length n on the
        grid ``self.t``, or (B, M) for a (B, n) stack of windows."""
        yy = np.asarray(y, dtype=np.float64)
        if yy.ndim not in (1, 2) or yy.shape[-1] != self.n:
            raise ValueError(f"window length must be the grid's {self.n}, got shape {yy.shape}")
        if not np.isfinite(yy).all():
            raise ValueError("y contains non-finite values")
        z = (self._w @ yy.T).reshape(len(self.thetas), self.n, -1)
        q = np.einsum("min,min->nm", z, z)
        out = self._const - 0.5 * q
        return out[0] if yy.ndim == 1 else out
