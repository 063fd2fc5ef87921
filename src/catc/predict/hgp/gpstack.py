"""The fast path's GP arithmetic: the formulas of :mod:`catc.predict.hgp.reference`
stacked over bank models and over windows, with far fewer numpy and LAPACK calls (that,
not arithmetic, is what a 31 × 31 system costs from Python).

numpy computes the exponentials of the RBF term of κ (paper eq. "covariance func") for
every window and model in one matrix product (:func:`_window_exps`): for windows of
received BSMs, on the 0.1 s grid, one per DT step of their span rather than one per
element of each covariance (a table the kernels read by index); the compiled kernels
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


#: Window times within this of a multiple of DT count as on the grid (the tolerance of the
#: regular-window check; epoch-second times carry rounding errors of ~2e-7 s).
GRID_TOL = 1e-6

#: A grid window's table of exponentials is used while it has at most this many entries per
#: packed element (a window spanning hours would make it long: then exponentials per element).
_TABLE_MAX = 4


def _grid_steps(tau: np.ndarray) -> np.ndarray | None:
    """The windows' times ``tau`` (B, n, ascending to 0) as whole DT steps back, (B, n)
    int64, if every time is on the grid (within :data:`GRID_TOL`), the steps descend (no
    two samples in one step) and the span is short enough for a table
    (:data:`_TABLE_MAX`); else None."""
    steps = np.rint(tau * (-1.0 / DT))
    if (np.abs(steps * DT + tau).max(initial=0.0) > GRID_TOL
            or steps.max(initial=0.0) >= _TABLE_MAX * tau.shape[1] * (tau.shape[1] + 1) / 2
            or (steps[:, 1:] >= steps[:, :-1]).any()):
        return None
    return steps.astype(np.int64)


def on_grid(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``tau`` (B, n) and its :func:`_grid_steps`; times on the grid are replaced by their
    exact multiples of DT (a received BSM's time is; its difference from the last one's as
    float seconds is only within ~1e-7 s of it)."""
    steps = _grid_steps(tau)
    return (tau, None) if steps is None else (steps * -DT, steps)


def _window_exps(tau: np.ndarray, steps: np.ndarray | None, coef: np.ndarray,
                 name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """α1²·exp(c·d²) = exp(c·d² + log α1²), the RBF term of κ (paper eq. "covariance func",
    c = −1/(2γ²)), for the packed lower triangle of the time differences d of each window
    ``tau`` (B, n), under models whose rows c and log α1² are ``coef`` (2, M), shared by all
    windows, or (B, 2, M), one set per window.

    Returned as a table and where to read it: ``(tab, tw, pidx)``, element q of window b
    under model s is ``tab[tw[b], pidx[b, q], s]``.  Windows on the 0.1 s grid of received
    BSMs (``steps``, from :func:`on_grid`) have only as many distinct d as DT steps in their
    span, so ``tab`` holds exp(c·(k·DT)² + log α1²) per step k (tens of exponentials per
    model, not n(n+1)/2: bench/gp_kernels.py, selections × 0.71) and ``pidx`` the steps;
    other windows (``steps`` None) get every element's exponential (``pidx`` the
    identity).  One matrix product of [d², 1] with the rows, into work array ``name``."""
    bsz, n = tau.shape
    rows, cols = _tril(n)
    if steps is not None:
        span = int(steps[:, 0].max(initial=0)) + 1
        pidx = np.subtract(steps.take(cols, axis=1), steps.take(rows, axis=1))
        d = np.arange(span) * DT
        lhs = _scratch("lhs", (span, 2))
        np.multiply(d, d, out=lhs[:, 0])
        lhs[:, 1] = 1.0
        per_window = coef.ndim == 3
        e = np.matmul(lhs, coef, out=_scratch(
            name, (bsz if per_window else 1, span, coef.shape[-1])))
        if _underflows(d[-1], float(coef[..., 0, :].min())):
            np.maximum(e, -700.0, out=e)
        tw = np.arange(bsz) if per_window else np.zeros(bsz, dtype=np.int64)
        return np.exp(e, out=e), tw, pidx
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
    pidx = np.broadcast_to(np.arange(len(rows)), (bsz, len(rows))).copy()
    return np.exp(e, out=e), np.arange(bsz), pidx


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
    tau, steps = on_grid(tau)
    tab, tw, pidx = _window_exps(tau, steps, p[:, _C:_LOG_S1 + 1].T, "lml")
    out = np.empty((bsz, len(p)))
    gpkernels.select_lml(tab, tw, pidx, np.ascontiguousarray(tau), np.ascontiguousarray(z),
                         p, m, out, _scratch("factor", ((n + 1) * (n + 1) * len(p),)))
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
    tau, steps = on_grid(rel[:, 0, :n])
    if steps is not None:
        rel = rel.copy()
        rel[:, 0, :n] = tau
    p = np.ascontiguousarray(p)
    tab, tw, pidx = _window_exps(tau, steps, p[:, :, _C:_LOG_S1 + 1].transpose(0, 2, 1),
                                 "cov")
    mean = np.empty((bsz, 2, len(grid)))
    var = np.empty((bsz, 2, len(grid)))
    gpkernels.posterior(tab, tw, pidx, np.ascontiguousarray(rel), grid, p, mean, var,
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
