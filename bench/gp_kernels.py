"""The HGP's compiled kernels against LAPACK, side by side, one core.

The work of one OBU tick at 500 RVs and PER 50 % (``bench/step.py``): ~75 bank selections
(32 models each, a 31 × 31 covariance with the slope row: one Cholesky and one forward
solve per model) and ~250 forecasts (2 series each: a Cholesky and 31 forward solves for
the grid).  Three ways to do the factorisations and solves of the selections:

* ``lapack``: scipy's ``dpotrf`` and ``dtrtrs`` per system, from Python (what
  ``catc.predict.hgp`` did before the kernels);
* ``numpy``: numpy's stacked ``linalg.cholesky`` and ``linalg.solve`` over all systems at
  once;
* ``kernel``: :func:`catc.predict.gpkernels.select_lml` (through
  ``catc.predict.hgp.gpstack.lml_stack``, with numpy's exponentials), the systems of a window
  interleaved (it also assembles the covariances from the exponentials and sums the
  likelihoods, which the other two rows leave out).

And the posteriors of ``--forecasts`` forecasts: ``lapack`` (``dpotrf`` + ``dtrtrs`` on
[z | K*] per series, as before) against :func:`catc.predict.gpkernels.posterior`
(through ``catc.predict.hgp.gpstack.posterior_stack``, exponentials included).  All
rows get the same windows (random gaps at PER 50 %, bank models); the likelihoods and
posterior means of the rows agree (printed: the largest difference).  Best of
``--repeat`` runs (a shared VM: timings vary by ±10 %).

    python bench/gp_kernels.py [--json] [--windows 75] [--forecasts 250] [--repeat 5]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.linalg import lapack  # noqa: E402

from catc.predict import gp  # noqa: E402
from catc.predict.bank import default_bank  # noqa: E402
from catc.predict.hgp import HgpConfig  # noqa: E402
from catc.predict.hgp.gpstack import (  # noqa: E402
    forecast_grid,
    lml_stack,
    posterior_stack,
    series_consts,
)
from catc.predict.hgp.reference import slope_system  # noqa: E402


def windows(b: int, n: int = 30, seed: int = 0) -> np.ndarray:
    """(b, 3, n + 1) windows: τ at PER 50 % (ending at 0, then 0), speed and heading."""
    rng = np.random.default_rng(seed)
    out = np.empty((b, 3, n + 1))
    for i in range(b):
        gaps = rng.geometric(0.5, n - 1) * 0.1  # 0.1 s times the attempts to the next BSM
        out[i, 0, :n] = np.concatenate((-np.cumsum(gaps[::-1])[::-1], [0.0]))
        out[i, 0, n] = 0.0
        out[i, 1, :n] = np.cumsum(rng.normal(0, 0.1, n))
        out[i, 2, :n] = np.cumsum(rng.normal(0, 0.01, n))
        out[i, 1:, :n] -= out[i, 1:, n - 1:n]
        out[i, 1, n], out[i, 2, n] = rng.normal(0, 0.5), rng.normal(0, 0.05)
    return out


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def selections(rel: np.ndarray, repeat: int) -> dict:
    c = HgpConfig()
    bank = default_bank()
    m = len(bank.speed)
    thetas = np.vstack([bank.speed, bank.heading])
    noise = [(c.noise_speed, c.noise_accel)] * m + [(c.noise_heading, c.noise_yaw)] * m
    n = rel.shape[2] - 1
    mats = np.array([[slope_system(r[0, :n], th, nv, sv)[0] for th, (nv, sv)
                      in zip(thetas, noise, strict=True)] for r in rel])  # (B, S, k, k)
    zs = np.array([[r[1 + (s >= m)] for s in range(2 * m)] for r in rel])  # (B, S, k)

    def with_lapack() -> np.ndarray:
        out = np.empty(mats.shape[:2])
        for b in range(mats.shape[0]):
            for s in range(mats.shape[1]):
                L, _ = lapack.dpotrf(mats[b, s], lower=1, clean=0)
                w, _ = lapack.dtrtrs(L, zs[b, s], lower=1)
                out[b, s] = -0.5 * w @ w - np.log(np.diagonal(L)).sum()
        return out

    def with_numpy() -> np.ndarray:
        L = np.linalg.cholesky(mats)
        w = np.linalg.solve(L, zs[..., None])[..., 0]
        return -0.5 * np.einsum("bsi,bsi->bs", w, w) - np.log(
            np.diagonal(L, axis1=2, axis2=3)).sum(axis=-1)

    consts = series_consts(thetas, m, c)

    def with_kernel() -> np.ndarray:
        return lml_stack(rel[:, 0, :-1], rel[:, 1:], consts, m, thetas) \
            + 0.5 * (n + 1) * np.log(2 * np.pi)

    ref = with_lapack()
    rows = {}
    for name, fn in (("lapack", with_lapack), ("numpy", with_numpy), ("kernel", with_kernel)):
        got = fn()
        rows[name] = {"ms": round(best(fn, repeat) * 1e3, 3),
                      "max_diff": float(np.max(np.abs(got - ref)))}
    return rows


def posteriors(rel: np.ndarray, repeat: int) -> dict:
    c = HgpConfig()
    bank = default_bank()
    m = len(bank.speed)
    thetas = np.vstack([bank.speed, bank.heading])
    consts = series_consts(thetas, m, c)
    rng = np.random.default_rng(1)
    pick = [(int(rng.integers(m)), m + int(rng.integers(m))) for _ in range(len(rel))]
    p = np.array([consts[list(ij)] for ij in pick])  # (B, 2, 9)
    grid = forecast_grid(31)[0]
    n = rel.shape[2] - 1
    noise = ((c.noise_speed, c.noise_accel), (c.noise_heading, c.noise_yaw))
    systems = []
    for r, ij in zip(rel, pick, strict=True):
        for s in range(2):
            K, k_fd = slope_system(r[0, :n], thetas[ij[s]], *noise[s])
            ks = np.vstack([gp.kernel(r[0, :n], grid, thetas[ij[s]]), k_fd(grid)])
            systems.append((K, np.column_stack([r[1 + s], ks])))

    def with_lapack() -> np.ndarray:
        out = np.empty((len(systems), len(grid)))
        for i, (K, rhs) in enumerate(systems):
            L, _ = lapack.dpotrf(K, lower=1, clean=0)
            v, _ = lapack.dtrtrs(L, rhs, lower=1)
            out[i] = v[:, 1:].T @ v[:, 0]
        return out

    def with_kernel() -> np.ndarray:
        return posterior_stack(rel, grid, p)[0].reshape(len(systems), -1)

    ref = with_lapack()
    rows = {}
    for name, fn in (("lapack", with_lapack), ("kernel", with_kernel)):
        got = fn()
        rows[name] = {"ms": round(best(fn, repeat) * 1e3, 3),
                      "max_diff": float(np.max(np.abs(got - ref)))}
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--windows", type=int, default=75, help="bank selections (default 75)")
    ap.add_argument("--forecasts", type=int, default=250, help="forecasts (default 250)")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    if min(args.windows, args.forecasts, args.repeat) < 1:
        ap.error("--windows, --forecasts and --repeat must be >= 1")
    warm = windows(2)
    selections(warm, 1)
    posteriors(warm, 1)  # compile or load the kernels before timing
    sel = selections(windows(args.windows), args.repeat)
    post = posteriors(windows(args.forecasts, seed=3), args.repeat)
    result = {"selections": {"windows": args.windows, "systems": args.windows * 32, **sel},
              "posteriors": {"forecasts": args.forecasts, "systems": 2 * args.forecasts,
                             **post},
              "python": platform.python_version(), "machine": platform.machine()}
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print("HGP kernels against LAPACK, one core (best of "
          f"{args.repeat}; what one tick at 500 RVs, PER 50 % needs)")
    print(f"{'work':<34} {'way':>7} {'ms':>8} {'us/system':>10} {'x lapack':>9} {'max diff':>10}")
    for label, key, count in ((f"{args.windows} selections x 32 models", "selections",
                               args.windows * 32),
                              (f"{args.forecasts} forecasts x 2 series, 31 pts", "posteriors",
                               2 * args.forecasts)):
        rows = result[key]
        base = rows["lapack"]["ms"]
        for way in ("lapack", "numpy", "kernel"):
            if way in rows:
                r = rows[way]
                print(f"{label:<34} {way:>7} {r['ms']:>8.2f} {r['ms'] * 1e3 / count:>10.2f} "
                      f"{base / r['ms']:>8.1f}x {r['max_diff']:>10.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
