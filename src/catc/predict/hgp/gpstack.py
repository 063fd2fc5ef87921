"""The fast path's GP arithmetic: the formulas of :mod:`catc.predict.hgp.reference`
stacked over bank models and over windows, with far fewer numpy and LAPACK calls (that,
not arithmetic, is what a 31 × 31 system costs from Python).

numpy computes the exponentials of the RBF term of κ (paper eq. "covariance func") for
every window and model in one matrix product (:func:`_window_exps`); the compiled kernels
of :mod:`catc.predict.gpkernels` assemble the covariances, factor them side by side and
give the selection scores (:func:`lml_stack`, paper eq. "eq-,odelselection") or the
posteriors (:func:`posterior_stack`, paper eq. "eq:forecastingheadingspeed").  A model is
one row of constants (:func:`consts`); work arrays are reused per thread.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from catc.predict import gpkernels
from catc.predict.forecast import DT
from catc.predict.hgp.config import HgpConfig

# Columns of a model-constants row: the kernels' (catc.predict.gpkernels.C ...).
_C, _LOG_S1, _S1, _S2, _KDD, _NOISE = (gpkernels.C, gpkernels.LOG_S1, gpkernels.S1,
                                       gpkernels.S2, gpkernels.KDD, gpkernels.NOISE)


def consts(thetas: np.ndarray, noise: np.ndarray, slope_var: np.ndarray) -> np.ndarray:
    """Per model row θ = (γ, α1, α2) with its value and slope noise, the columns of
    :data:`catc.predict.gpkernels.C` and after: −1/(2γ²), log α1², α1², α2², var f′(0) +
    slope noise, value noise; shape (R, gpkernels.CONSTS).  The kernel is the paper's
    κ(t, t') = α1² exp(−(t−t')²/(2γ²)) + α2² t t' (eq. "covariance func"), and
    var f′(0) = α1²/γ² + α2² (R&W 2006 §9.4, as :func:`~.reference.slope_system`)."""
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


def series_consts(thetas: np.ndarray, m: int, c: HgpConfig) -> np.ndarray:
    """:func:`consts` for ``m`` speed models followed by heading models under config ``c``."""
    heading = np.arange(len(thetas)) >= m
    return consts(thetas, np.where(heading, c.noise_heading, c.noise_speed),
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
    """α1²·exp(c·d²) = exp(c·d² + log α1²), the RBF term of κ (paper eq. "covariance func",
    c = −1/(2γ²)), for the packed lower triangle of the squared
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


def lml_stack(tau: np.ndarray, z: np.ndarray, p: np.ndarray, m: int,
              thetas: np.ndarray) -> np.ndarray:
    """:func:`~.reference.lml_with_slope` (the score of the paper's model selection, eq.
    "eq-,odelselection": −½ zᵀK⁻¹z − ½ log det K − (n+1)/2 log 2π with z the values and
    the slope; R&W 2006 Algorithm 2.1, lines 2 and 7) of B windows under S = 2m models:
    ``tau`` (B, n), each ending
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


def posterior_stack(rel: np.ndarray, grid: np.ndarray,
                    p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~.reference.posterior_with_slope` of speed and heading for B windows at once:
    the paper's eq. "eq:forecastingheadingspeed" (μ* = K1 K2⁻¹ S, Σ* = K3 − K1 K2⁻¹ K1ᵀ,
    diagonal) by R&W 2006 Algorithm 2.1, lines 2-6, in the compiled kernel.

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


def stack(arrays: list[np.ndarray]) -> np.ndarray:
    """``np.stack(arrays)`` for arrays of one shape, a third of its cost (no per-array
    ``expand_dims``)."""
    return np.concatenate(arrays).reshape(len(arrays), *arrays[0].shape)


_GRIDS: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def forecast_grid(count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The forecast times k·DT for k < count, their differences and half those (cached)."""
    g = _GRIDS.get(count)
    if g is None:
        tau = np.arange(count) * DT
        dt = np.diff(tau)
        g = _GRIDS[count] = (tau, dt, 0.5 * dt)
    return g


def forecast_steps(horizon: float, c: HgpConfig) -> int:
    """Forecast points (0.1 s steps from τ = 0) for a forecast ``horizon`` s long."""
    return math.ceil(min(horizon, c.horizon_s) / DT - 1e-9) + 1
