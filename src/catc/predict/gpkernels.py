"""Compiled kernels of the HGP's hot path: bank selection and posteriors for many small
GP systems at once (numba, ``cache=True``: compiled once per machine, then loaded).

Why compiled.  One OBU tick at 500 RVs and PER 50 % selects bank models for ~75 windows
(32 models each: ~2,400 Cholesky factorisations of 31 × 31) and makes ~250 forecasts
(500 more factorisations and triangular solves with 32 right-hand sides).  From Python
each LAPACK call costs ~6 µs, mostly call overhead at this size, and the calls could not
be batched (numpy's stacked ``cholesky`` is slower still: ``python bench/gp_kernels.py``).
Here the systems of one batch are *interleaved*: element (i, j) of every system lies side
by side in memory, so each scalar step of the textbook Cholesky and forward
substitution is one loop over the systems that the compiler turns into SIMD, with no
reductions reassociated (the arithmetic of each system is the textbook order; the
reference formulas in :mod:`catc.predict.hgp.reference` agree to round-off, tests/test_hgp.py).

The exponentials are computed by numpy beforehand (vectorised ``exp`` is ~8 times faster
than the scalar libm one a numba loop calls); the kernels assemble the covariances from
them.  Model constants are the rows of :func:`catc.predict.hgp.gpstack.consts`.

Packed storage: the lower triangle (i ≥ j) of an n × n matrix in row order, element (i, j)
at i·(i+1)/2 + j (numpy's ``tril_indices`` order).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Columns of a model-constants row (:func:`catc.predict.hgp.gpstack.consts` fills them): for
#: θ = (γ, α1, α2), −1/(2γ²), log α1² (these two adjacent: one matrix product makes the
#: exponents), α1², α2², var f′(0) + slope noise, value noise.
C, LOG_S1, S1, S2, KDD, NOISE = range(6)
CONSTS = 6

#: Systems factored together in :func:`posterior`: 32 doubles are four AVX-512 registers
#: (eight AVX2 ones) per step, and a block's matrices (31 × 31 × 32 × 8 B = 246 kB) stay in
#: the L2 cache.
BLOCK = 32

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True, "boundscheck": False}


@njit(**_OPTS)
def _factor(a, k, nb, bad):  # pragma: no cover - compiled
    """Cholesky in place of the lower triangles of ``a[:k, :k, :nb]`` (nb interleaved
    systems).  A system whose pivot is not positive (or NaN) is marked in ``bad`` and
    continued with pivot 1, so that the others finish; its results are meaningless."""
    acc = np.empty(nb)
    for s in range(nb):
        bad[s] = False
    for j in range(k):
        for i in range(j, k):
            for s in range(nb):
                acc[s] = a[i, j, s]
            for q in range(j):
                for s in range(nb):
                    acc[s] -= a[i, q, s] * a[j, q, s]
            if i == j:
                for s in range(nb):
                    ok = acc[s] > 0.0
                    bad[s] = bad[s] or not ok
                    a[j, j, s] = math.sqrt(acc[s]) if ok else 1.0
            else:
                for s in range(nb):
                    a[i, j, s] = acc[s] / a[j, j, s]


@njit(**_OPTS)
def _solve(a, k, nb, rhs, out):  # pragma: no cover - compiled
    """Forward substitution L out = rhs for nb interleaved factors ``a`` (rhs, out (k, nb))."""
    for i in range(k):
        for s in range(nb):
            out[i, s] = rhs[i, s]
        for q in range(i):
            for s in range(nb):
                out[i, s] -= a[i, q, s] * out[q, s]
        for s in range(nb):
            out[i, s] /= a[i, i, s]


@njit(**_OPTS)
def _assemble(a, e, pidx, tau, tt_w, n, nb, s2, m2c, noise, kdd):  # pragma: no cover
    """The (n + 1) × (n + 1) covariance of n values at ``tau`` (ending at 0) and the slope
    at 0 (catc.predict.hgp.reference.slope_system) for nb interleaved systems on the same times,
    lower triangle: ``e[pidx[q], s]`` the packed element q's α1²·exp(c·d²) of the values
    under model s, ``tt_w`` scratch (nb,).  (:func:`posterior` assembles its own: its
    systems have different times.)"""
    for i in range(n):
        base = i * (i + 1) // 2
        for j in range(i + 1):
            tt = tau[i] * tau[j]
            q = pidx[base + j]
            for s in range(nb):
                a[i, j, s] = e[q, s] + s2[s] * tt
        for s in range(nb):
            a[i, i, s] += noise[s]
    # slope row: ∂κ(τ_j, s)/∂s at s = 0 = τ_j·(α1²/γ²·exp(−τ_j²/(2γ²)) + α2²); the
    # exponential is the packed entry (n−1, j), since τ_{n−1} = 0
    last = (n - 1) * n // 2
    for j in range(n):
        q = pidx[last + j]
        for s in range(nb):
            tt_w[s] = e[q, s] * m2c[s] + s2[s]
        for s in range(nb):
            a[n, j, s] = tau[j] * tt_w[s]
    for s in range(nb):
        a[n, n, s] = kdd[s]


@njit(**_OPTS)
def select_lml(tab, tw, pidx, tau, z, p, m, out, a):  # pragma: no cover - compiled
    """Log marginal likelihood of each window under each model, values and slope together
    (catc.predict.hgp.reference.lml_with_slope).

    ``tab[tw[b], pidx[b, q], s]``: α1²·exp(c·d²) of packed element q (P = n(n+1)/2) of
    window b under model s (:func:`catc.predict.hgp.gpstack._window_exps`);
    ``tau`` (B, n) each ending at 0; ``z`` (B, 2, n + 1) speed and heading values with their
    slope; ``p`` (S, CONSTS) model constants, the first ``m`` speed models (scored on z[:, 0]),
    then heading ones (on z[:, 1]); ``out`` (B, S); ``a`` a work array of at least
    (n + 1)² · S (a fresh one per call costs page faults: 250 kB).  A model whose
    covariance is not positive definite scores −inf."""
    bsz, n = tau.shape
    ns = tab.shape[2]
    k = n + 1
    a = a[:k * k * ns].reshape((k, k, ns))
    w = np.empty((k, ns))
    zz = np.empty((k, ns))
    tt_w = np.empty(ns)
    bad = np.empty(ns, dtype=np.bool_)
    s2 = p[:, S2].copy()
    m2c = -2.0 * p[:, C]
    noise = p[:, NOISE].copy()
    kdd = p[:, KDD].copy()
    half_log_2pi = 0.5 * k * math.log(2.0 * math.pi)
    for b in range(bsz):
        _assemble(a, tab[tw[b]], pidx[b], tau[b], tt_w, n, ns, s2, m2c, noise, kdd)
        _factor(a, k, ns, bad)
        for i in range(k):
            for s in range(m):
                zz[i, s] = z[b, 0, i]
            for s in range(m, ns):
                zz[i, s] = z[b, 1, i]
        _solve(a, k, ns, zz, w)
        for s in range(ns):
            out[b, s] = -half_log_2pi
        for i in range(k):
            for s in range(ns):
                out[b, s] -= 0.5 * w[i, s] * w[i, s] + math.log(a[i, i, s])
        for s in range(ns):
            if bad[s]:
                out[b, s] = -np.inf


@njit(**_OPTS)
def posterior(tab, tw, pidx, rel, grid, p, mean, var, a):  # pragma: no cover - compiled
    """Posterior mean and latent variance at ``grid`` (0, Δ, 2Δ, …) of R = 2B systems, each
    conditioned on its values and slope (catc.predict.hgp.reference.posterior_with_slope); system
    r = 2b + c is series c (0 speed, 1 heading) of window b.

    ``tab[tw[b], pidx[b, q], c]``: α1²·exp(c·d²) of packed element q of window b under its
    model for series c (:func:`catc.predict.hgp.gpstack._window_exps`); ``rel``
    (B, 3, n + 1): τ then 0, speed values and slope, heading values and slope; ``p``
    (B, 2, CONSTS) the model constants; ``mean``, ``var`` (B, 2, G); ``a`` a work array of at
    least (n + 1)² · BLOCK.

    The covariances with the grid, α1²·exp(c·(g − τ_i)²), are not exponentials of their
    own: from g = 0, where it is the window's entry (n−1, i) (τ_{n−1} = 0), each grid step
    multiplies by exp(c·(2a+1)·Δ²)·exp(−2c·Δ·τ_i), the ratio of consecutive ones (relative
    error ≤ 2 ulp per step; these enter the mean and variance linearly).  Values below
    1e-290 are flushed to 0 (they only decrease, and subnormals are slow).
    Raises when a covariance is not positive definite (it never is for bank models)."""
    bsz = rel.shape[0]
    nr = 2 * bsz
    g_count = grid.shape[0]
    dt = grid[1] - grid[0] if g_count > 1 else 0.0
    n = rel.shape[2] - 1
    k = n + 1
    a = a[:k * k * BLOCK].reshape((k, k, BLOCK))
    zz = np.empty((k, BLOCK))
    w = np.empty((k, BLOCK))
    ks = np.empty((k, BLOCK))
    v = np.empty((k, BLOCK))
    cur = np.empty((n, BLOCK))
    step = np.empty((n, BLOCK))
    bad = np.empty(BLOCK, dtype=np.bool_)
    tau = np.empty((k, BLOCK))
    s1 = np.empty(BLOCK)
    s2 = np.empty(BLOCK)
    cc = np.empty(BLOCK)
    m2c = np.empty(BLOCK)
    noise = np.empty(BLOCK)
    kdd = np.empty(BLOCK)
    u = np.empty(BLOCK)
    last = (n - 1) * n // 2
    for r0 in range(0, nr, BLOCK):
        nb = min(BLOCK, nr - r0)
        for s in range(nb):
            b, c = divmod(r0 + s, 2)
            s1[s] = p[b, c, S1]
            s2[s] = p[b, c, S2]
            cc[s] = p[b, c, C]
            m2c[s] = -2.0 * p[b, c, C]
            noise[s] = p[b, c, NOISE]
            kdd[s] = p[b, c, KDD]
            for i in range(n):
                tau[i, s] = rel[b, 0, i]
            for i in range(k):
                zz[i, s] = rel[b, 1 + c, i]
            e = tab[tw[b]]
            pb = pidx[b]
            for i in range(n):
                for j in range(i + 1):
                    a[i, j, s] = e[pb[i * (i + 1) // 2 + j], c]
            for i in range(n):
                cur[i, s] = e[pb[last + i], c]
                step[i, s] = math.exp(2.0 * cc[s] * dt * tau[i, s] * -1.0)
        for i in range(n):
            for j in range(i + 1):
                for s in range(nb):
                    a[i, j, s] += s2[s] * tau[i, s] * tau[j, s]
            for s in range(nb):
                a[i, i, s] += noise[s]
        for j in range(n):
            for s in range(nb):
                a[n, j, s] = tau[j, s] * (cur[j, s] * m2c[s] + s2[s])
        for s in range(nb):
            a[n, n, s] = kdd[s]
        _factor(a, k, nb, bad)
        for s in range(nb):
            if bad[s]:
                raise np.linalg.LinAlgError("slope covariance not positive definite")
        _solve(a, k, nb, zz, w)
        for g in range(g_count):
            gt = grid[g]
            for i in range(n):
                for s in range(nb):
                    ks[i, s] = cur[i, s] + s2[s] * gt * tau[i, s]
            for s in range(nb):  # the slope column: ∂κ(g, s)/∂s at 0
                ks[n, s] = gt * (cur[n - 1, s] * m2c[s] + s2[s])
            _solve(a, k, nb, ks, v)
            for s in range(nb):
                b, c = divmod(r0 + s, 2)
                mv = 0.0
                vv = s1[s] + s2[s] * gt * gt
                for i in range(k):
                    mv += v[i, s] * w[i, s]
                    vv -= v[i, s] * v[i, s]
                mean[b, c, g] = mv
                var[b, c, g] = vv
            if g + 1 < g_count:
                for s in range(nb):
                    u[s] = math.exp(cc[s] * (2 * g + 1) * dt * dt)
                for i in range(n):
                    for s in range(nb):
                        x = cur[i, s] * u[s] * step[i, s]
                        cur[i, s] = x if x >= 1e-290 else 0.0


_RAD2DEG = 180.0 / math.pi  # numpy's degrees() multiplies by this same constant


@njit(**_OPTS)
def integrate_rows(eff, sc, mean, var, start, dgrid, half, trapezoid, dt2,
                   table):  # pragma: no cover - compiled
    """The positions and position variances of B forecasts in one pass per row
    (catc.predict.hgp.stacked.finish_stack): what twenty numpy passes over the rows computed,
    with the same operations in the same order.  ``eff`` (B, G) the speed times the
    heading damping (or the speed), ``sc`` (B, 2, G) sin and cos of the heading, ``mean``
    and ``var`` (B, 2, G) speed and heading (rad) and their variances, ``start`` (B, 4)
    the last speed, heading, x and y; ``dgrid`` and ``half`` the grid steps and their
    halves; ``trapezoid`` the rule (else left Riemann); ``dt2`` Δt²; ``table`` (B, 6, G)
    out: x, y, speed, heading (deg, [0, 360)), var_x, var_y."""
    bsz, _, count = mean.shape
    for i in range(bsz):
        x0 = start[i, 2]
        y0 = start[i, 3]
        ae = an = av = ac = 0.0
        pe = pn = 0.0
        for j in range(count):
            speed = mean[i, 0, j]
            re = eff[i, j] * sc[i, 0, j]
            rn = eff[i, j] * sc[i, 1, j]
            if j > 0:
                if trapezoid:
                    se = (re + pe) * half[j - 1]
                    sn = (rn + pn) * half[j - 1]
                else:
                    se = pe * dgrid[j - 1]
                    sn = pn * dgrid[j - 1]
                sv = var[i, 0, j] * dt2
                sx = var[i, 1, j] * (speed * speed) * dt2
                if j == 1:  # a cumulative sum starts at its first term (not 0 + it)
                    ae, an, av, ac = se, sn, sv, sx
                else:
                    ae += se
                    an += sn
                    av += sv
                    ac += sx
            pe, pn = re, rn
            table[i, 0, j] = ae + x0
            table[i, 1, j] = an + y0
            table[i, 2, j] = speed
            table[i, 3, j] = (mean[i, 1, j] * _RAD2DEG) % 360.0
            s2 = sc[i, 0, j] * sc[i, 0, j]
            c2 = sc[i, 1, j] * sc[i, 1, j]
            table[i, 4, j] = s2 * av + ac * c2
            table[i, 5, j] = c2 * av + ac * s2


@njit(**_OPTS)
def shift_rows(mean, var, start, ext):  # pragma: no cover - compiled
    """For B forecasts (catc.predict.hgp.stacked.finish_stack): add the last speed and heading
    ``start[:, :2]`` to the relative means (B, 2, G), clip negative variances to 0 (NaN
    stays NaN, as numpy's maximum leaves it), and write each row's extremes to ``ext``
    (B, 6): least and greatest speed, greatest step change of speed and of heading,
    greatest speed and heading variance (NaN where numpy's reductions give NaN)."""
    bsz, _, count = mean.shape
    nan = np.nan
    for i in range(bsz):
        for c in range(2):
            s = start[i, c]
            prev = 0.0
            step = 0.0
            vmax = -np.inf
            lo = np.inf
            hi = -np.inf
            bad = False
            for j in range(count):
                m = mean[i, c, j] + s
                mean[i, c, j] = m
                v = var[i, c, j]
                if v < 0.0:
                    v = 0.0
                    var[i, c, j] = v
                if m != m or v != v:
                    bad = True
                if j > 0:
                    d = abs(m - prev)
                    if d > step:
                        step = d
                if v > vmax:
                    vmax = v
                if m < lo:
                    lo = m
                if m > hi:
                    hi = m
                prev = m
            if bad:
                step = vmax = lo = hi = nan
            if c == 0:
                ext[i, 0] = lo
                ext[i, 1] = hi
            ext[i, 2 + c] = step
            ext[i, 4 + c] = vmax
