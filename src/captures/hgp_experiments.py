"""The paper's H1 and H2 experiments on real trips, as plain rows and figures.

* **H1** (fit time against the training window TW): :func:`h1_fit_time` times the fit the
  HGP makes when it needs a new kernel (``gp.fit``: the paper's LOO objective, warm-started
  from the most likely bank model, within ``HgpConfig.speed_bounds``) on real 10 Hz speed
  windows of each TW, next to scikit-learn's ``GaussianProcessRegressor`` fitting the same
  kernel (α1² RBF(γ) + α2² t·t', same noise, bounds, warm start, windows) by its marginal
  likelihood.  The paper's real-time threshold is 100 ms.
* **H2** (model persistency MP against the bank size C_size): :func:`h2_cluster_size` gives
  the rows `make bank` measured and recorded in the bank's JSON (not re-measured here).
* **H2** (new kernels on unforeseen trips): :func:`h2_new_kernel_rate` walks held-out trips
  with the fixed bank (:func:`catc.predict.training.persistency`) and bins the new-kernel
  events over driving time.  By default the trips are the bank's own held-out files.

Functions return plain dicts and lists for ``captures report``; ``plot_*`` draw them on a
matplotlib Axes.  ``python -m captures.hgp_experiments [DATA]`` prints all three.
"""

from __future__ import annotations

import os

# One BLAS thread, as in the OBU: threads only add overhead on these small matrices.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import hashlib
import importlib.util
import math
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from catc.mobility import MobilityTable, Track
from catc.predict import gp
from catc.predict.bank import KernelBank, default_bank
from catc.predict.hgp import HgpConfig
from catc.predict.training import DT, TrainConfig, persistency
from hil.datasets import load

THRESHOLD_MS = 100.0
"""The paper's real-time requirement for the safety applications (H1)."""

PAPER_C_SIZE = 16
"""The cluster size the paper chose (H2)."""

H1_TWS = (5, 10, 20, 30, 40, 50, 60, 100)
TRAIN = TrainConfig()
"""The training parameters of the shipped bank (TW 30, PTE_th 0.5 m, 1 s horizon)."""
OPENACC = "openacc-zalazone"
DATA_DIR = Path(os.environ.get("CATC_SHARED_DATA", "../shared/data"))


def _tracks(items: Sequence[MobilityTable | Track]) -> list[Track]:
    """Tracks of ``items``: tables (every track, in order) or tracks as they are."""
    out: list[Track] = []
    for item in items:
        out.extend([item] if isinstance(item, Track) else item.tracks.values())
    return out


# ---------------------------------------------------------------- H1


def _window_ends(track: Track, tw: int) -> np.ndarray:
    """Indices ``c`` such that samples ``c - tw + 1 … c`` have finite speeds and follow each
    other at exactly DT (no gap)."""
    bad = np.concatenate(([0], np.cumsum(~np.isfinite(track.speed) | ~np.isfinite(track.t))))
    gap = np.concatenate(([0, 0], np.cumsum(np.abs(np.diff(track.t) - DT) > 1e-3 * DT)))
    c = np.arange(tw - 1, len(track))
    return c[(bad[c + 1] == bad[c + 1 - tw]) & (gap[c + 1] == gap[c + 2 - tw])]


def speed_windows(tables: Sequence[MobilityTable | Track], tw: int, count: int, seed: int = 0,
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` windows of ``tw`` consecutive real speed samples, drawn without replacement
    (seeded) from every valid position in ``tables``, as the HGP sees them: ``(tau, y)`` with
    times and speeds relative to the window's last sample.  Fewer when fewer exist."""
    tracks = _tracks(tables)
    ends = [(k, c) for k, tr in enumerate(tracks) for c in _window_ends(tr, tw)]
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.choice(len(ends), size=min(count, len(ends)), replace=False))
    out = []
    for k, c in (ends[p] for p in picks):
        w = slice(c - tw + 1, c + 1)
        tr = tracks[k]
        out.append((tr.t[w] - tr.t[c], tr.speed[w] - tr.speed[c]))
    return out


def _best_ms(fn: Callable[[], object], repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def sklearn_gpr(theta0: np.ndarray, noise_var: float, bounds: Sequence[Sequence[float]]):
    """scikit-learn's regressor with the paper's kernel α1² RBF(γ) + α2² t·t' started at
    ``theta0`` = (γ, α1, α2) within ``bounds`` (on γ, α1, α2; the amplitudes enter squared),
    white noise ``noise_var`` on the diagonal, no restarts and no normalisation."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, DotProduct

    (gamma, a1, a2), (g_b, a1_b, a2_b) = theta0, np.asarray(bounds, dtype=float)
    rbf = ConstantKernel(a1 * a1, tuple(a1_b**2)) * RBF(gamma, tuple(g_b))
    linear = ConstantKernel(a2 * a2, tuple(a2_b**2)) * DotProduct(0.0, "fixed")
    return GaussianProcessRegressor(rbf + linear, alpha=noise_var, n_restarts_optimizer=0)


def _stats(ms: list[float]) -> tuple[float | None, float | None]:
    if not ms:
        return None, None
    return float(np.median(ms)), float(np.percentile(ms, 95))


def h1_fit_time(tables: Sequence[MobilityTable | Track], tws: Sequence[int] = H1_TWS,
                windows: int = 40, repeats: int = 3, seed: int = 0, sklearn: bool = True,
                bank: KernelBank | None = None, cfg: HgpConfig | None = None) -> list[dict]:
    """Fit time against TW (H1), one row per TW with enough real windows.

    Each window is fitted as the HGP fits a new speed kernel: ``gp.fit`` with
    ``cfg.noise_speed`` and ``cfg.speed_bounds``, warm-started from the bank's speed model
    of highest marginal likelihood on the window; sklearn gets the same kernel, noise,
    bounds, warm start and window (skipped, None, when ``sklearn`` is False or it is not
    installed).  A window's time is the best of ``repeats`` runs; a row gives the median
    and 95th percentile over windows, in ms.

    Keys: ``tw``, ``window_s``, ``windows``, ``repeats``, ``ours_median_ms``,
    ``ours_p95_ms``, ``sklearn_median_ms``, ``sklearn_p95_ms``, ``ratio`` (sklearn median /
    ours median), ``threshold_ms`` (the paper's 100 ms), ``ours_under_threshold`` and
    ``sklearn_under_threshold`` (p95 below it).
    """
    bank = default_bank() if bank is None else bank
    cfg = HgpConfig() if cfg is None else cfg
    peer = sklearn and importlib.util.find_spec("sklearn") is not None
    rows = []
    for tw in tws:
        wins = speed_windows(tables, tw, windows, seed)
        if not wins:
            continue
        ours: list[float] = []
        theirs: list[float] = []
        for tau, y in wins:
            lml = gp.bank_log_marginal_likelihood(tau, y, bank.speed, cfg.noise_speed)
            theta0 = bank.speed[int(np.argmax(lml))]
            ours.append(_best_ms(lambda tau=tau, y=y, th=theta0: gp.fit(
                tau, y, cfg.noise_speed, th, cfg.speed_bounds), repeats))
            if peer:
                model, x = sklearn_gpr(theta0, cfg.noise_speed, cfg.speed_bounds), tau[:, None]
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # optimiser at a bound: not our concern
                    theirs.append(_best_ms(lambda m=model, x=x, y=y: m.fit(x, y), repeats))
        (om, op), (sm, sp) = _stats(ours), _stats(theirs)
        rows.append({"tw": tw, "window_s": round(tw * DT, 6), "windows": len(wins),
                     "repeats": repeats, "ours_median_ms": om, "ours_p95_ms": op,
                     "sklearn_median_ms": sm, "sklearn_p95_ms": sp,
                     "ratio": None if sm is None else sm / om, "threshold_ms": THRESHOLD_MS,
                     "ours_under_threshold": op < THRESHOLD_MS,
                     "sklearn_under_threshold": None if sp is None else sp < THRESHOLD_MS})
    return rows


# ---------------------------------------------------------------- H2


def h2_cluster_size(bank_meta: dict | None = None) -> list[dict]:
    """MP against C_size as `make bank` recorded it in the bank's JSON (``stats`` →
    ``mp_vs_cluster_size``): one row per C_size with ``cluster_size``, ``mp_mean_s``,
    ``switches``, ``new_kernel_events``, ``new_kernel_rate``, ``new_kernels_per_min`` and
    ``source``.  ``bank_meta`` is a bank's ``meta`` (or its whole JSON object); by default
    the shipped bank's."""
    meta = default_bank().meta if bank_meta is None else bank_meta
    rows = (meta.get("stats") or {}).get("mp_vs_cluster_size")
    if not rows:
        raise ValueError("bank has no stats.mp_vs_cluster_size: not made by captures train-bank")
    source = ("recorded by `make bank` (captures train-bank), not re-measured: persistency "
              "of the unclustered training bank reduced to each C_size, on a sample of the "
              f"training tracks; command: {meta.get('command', '?')}")
    return [{**row, "source": source} for row in rows]


def holdout_tables(bank_meta: dict | None = None, data_dir: Path | None = None,
                   ) -> list[MobilityTable]:
    """The trips of the bank's held-out files (``meta["holdout"]``: name → SHA-256), read
    from ``data_dir`` (default ``../shared/data/openacc-zalazone``).  Raises
    FileNotFoundError when none is there and ValueError when a file's digest differs."""
    meta = default_bank().meta if bank_meta is None else bank_meta
    folder = DATA_DIR / OPENACC if data_dir is None else Path(data_dir)
    files = [(folder / name, digest) for name, digest in (meta.get("holdout") or {}).items()
             if (folder / name).is_file()]
    if not files:
        raise FileNotFoundError(f"none of the bank's held-out files is in {folder}")
    for path, digest in files:
        if hashlib.sha256(path.read_bytes()).hexdigest() != digest:
            raise ValueError(f"{path} is not the file the bank held out (SHA-256 differs)")
    return [table for path, _ in files for table in load(str(path))]


def h2_new_kernel_rate(tables: Sequence[MobilityTable | Track] | None = None,
                       bank: KernelBank | None = None, cfg: TrainConfig = TRAIN,
                       bin_s: float = 60.0) -> dict:
    """New-kernel events over driving time when ``bank`` (default: the shipped one) meets
    trips it was not trained on (default: its held-out files, :func:`holdout_tables`).

    The trips' tracks are walked in order, laid end to end on one driving clock (the one
    ``persistency`` divides by).  Keys: ``source``; ``params`` (tw, pte_th, horizon_s);
    ``bank_pairs``; ``tracks``; ``driven_s``; ``bin_s``; ``totals`` (what
    :func:`~catc.predict.training.persistency` returns for the same input); ``events``
    (every model switch: ``track``, ``vehicle``, ``t_trip_s``, ``driven_s``, ``new``);
    ``bins`` (``start_s``, ``end_s``, ``switches``, ``new_kernels``, ``rate_per_min``,
    ``cumulative``, ``cumulative_switches``, ``cumulative_ratio``: new kernels per switch
    so far, the paper's "ratio of generating new models"); and, for the default trips,
    ``recorded`` (the bank's ``stats.holdout``, measured by `make bank`).
    """
    bank = default_bank() if bank is None else bank
    recorded = None
    if tables is None:
        tables = holdout_tables(bank.meta)
        recorded = (bank.meta.get("stats") or {}).get("holdout")
    tracks = _tracks(tables)
    trace: dict = {}
    totals = persistency(tracks, bank, cfg, trace)
    driven = float(sum(tr["driven_s"] for tr in trace["tracks"]))
    events = trace["switches"]
    n_bins = math.ceil(driven / bin_s) if driven > 0 else 0
    edges = np.minimum(np.arange(n_bins + 1) * bin_s, driven)
    switches = np.histogram([e["driven_s"] for e in events], edges)[0] if n_bins else []
    new = np.histogram([e["driven_s"] for e in events if e["new"]], edges)[0] if n_bins else []
    bins = []
    cum = cum_sw = 0
    for i in range(n_bins):
        cum, cum_sw = cum + int(new[i]), cum_sw + int(switches[i])
        bins.append({"start_s": float(edges[i]), "end_s": float(edges[i + 1]),
                     "switches": int(switches[i]), "new_kernels": int(new[i]),
                     "rate_per_min": int(new[i]) / ((edges[i + 1] - edges[i]) / 60.0),
                     "cumulative": cum, "cumulative_switches": cum_sw,
                     "cumulative_ratio": cum / cum_sw if cum_sw else None})
    names = sorted({t.name for t in tables if isinstance(t, MobilityTable)})
    return {"source": f"{len(tracks)} tracks ({', '.join(names) or 'given tracks'}) walked "
                      f"with a fixed {len(bank)}-pair bank, no training (persistency)",
            "params": {"tw": cfg.tw, "pte_th": cfg.pte_th, "horizon_s": cfg.horizon_s},
            "bank_pairs": len(bank), "tracks": len(trace["tracks"]), "driven_s": driven,
            "bin_s": bin_s, "totals": totals, "events": events, "bins": bins,
            **({"recorded": recorded} if recorded is not None else {})}


# ---------------------------------------------------------------- figures


def plot_h1(ax, rows: Sequence[dict]) -> None:
    """Fit time (median, band to p95) against TW, ours and sklearn, and the 100 ms line."""
    tw = [r["tw"] for r in rows]
    for key, label, marker in (("ours", "HGP LOO fit (gp.fit)", "o"),
                               ("sklearn", "sklearn GaussianProcessRegressor", "s")):
        if not rows or rows[0][f"{key}_median_ms"] is None:
            continue
        med = [r[f"{key}_median_ms"] for r in rows]
        (line,) = ax.plot(tw, med, marker=marker, label=f"{label}, median")
        ax.fill_between(tw, med, [r[f"{key}_p95_ms"] for r in rows], color=line.get_color(),
                        alpha=0.2, label=f"{label}, to p95")
    ax.axhline(THRESHOLD_MS, color="red", linestyle="--",
               label=f"real-time threshold ({THRESHOLD_MS:g} ms, paper)")
    ax.set_yscale("log")
    ax.set_xlabel("training window TW [samples at 10 Hz]")
    ax.set_ylabel("kernel fit time [ms]")
    ax.set_title("H1: new-kernel fit time against TW")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")


def _legend(ax, twin, loc: str) -> None:
    handles, labels = ax.get_legend_handles_labels()
    more, more_labels = twin.get_legend_handles_labels()
    ax.legend(handles + more, labels + more_labels, loc=loc, fontsize="small")


def plot_h2_cluster(ax, rows: Sequence[dict]):
    """MP (left axis) and the new-kernel rate per switch (right axis) against C_size, with
    the paper's choice C_size = 16 marked.  Returns the right-hand Axes."""
    size = [r["cluster_size"] for r in rows]
    ax.plot(size, [r["mp_mean_s"] for r in rows], "o-", label="model persistency MP")
    ax.axvline(PAPER_C_SIZE, color="grey", linestyle=":",
               label=f"paper's choice C_size = {PAPER_C_SIZE}")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("cluster size C_size [bank pairs]")
    ax.set_ylabel("mean MP [s]")
    ax.set_title("H2: model persistency against bank size")
    twin = ax.twinx()
    twin.plot(size, [r["new_kernel_rate"] for r in rows], "s--", color="tab:orange",
              label="new-kernel rate (of switches)")
    twin.set_ylabel("new kernels per switch")
    twin.set_ylim(0, 1.05)
    _legend(ax, twin, "center right")
    return twin


def plot_h2_rate(ax, result: dict):
    """New kernels per minute in each bin of driving time (bars, left axis), the overall
    rate, and the cumulative count (right axis).  Returns the right-hand Axes."""
    bins = result["bins"]
    ax.bar([b["start_s"] / 60 for b in bins], [b["rate_per_min"] for b in bins],
           width=[(b["end_s"] - b["start_s"]) / 60 for b in bins], align="edge", alpha=0.5,
           label=f"new kernels / min ({result['bin_s']:g} s bins)")
    ax.axhline(result["totals"]["new_kernels_per_min"], color="black", linestyle="--",
               label="overall rate")
    ax.set_xlabel("driving time [min]")
    ax.set_ylabel("new kernels per minute")
    ax.set_title("H2: new kernels on held-out trips")
    times = [e["driven_s"] / 60 for e in result["events"] if e["new"]]
    twin = ax.twinx()
    twin.step([0.0, *times, result["driven_s"] / 60], [0, *range(1, len(times) + 1), len(times)],
              where="post", color="tab:red", label="cumulative new kernels")
    twin.set_ylabel("cumulative new kernels")
    ax.set_ylim(bottom=0)
    twin.set_ylim(bottom=0)
    _legend(ax, twin, "upper left")
    return twin


# ---------------------------------------------------------------- manual check


def _table(rows: Sequence[dict], cols: Sequence[str]) -> str:
    def cell(v) -> str:
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 1e4 else f"{v:.0f}"
        return "-" if v is None else str(v)

    body = [[cell(r[c]) for c in cols] for r in rows]
    widths = [max(len(c), *(len(b[i]) for b in body)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.rjust(w) for c, w in zip(cols, widths, strict=True))]
    lines += ["  ".join(v.rjust(w) for v, w in zip(b, widths, strict=True)) for b in body]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="The paper's H1 and H2 experiments on real data.")
    ap.add_argument("data", nargs="?", type=Path, default=DATA_DIR,
                    help=f"shared data folder holding {OPENACC}/ (default {DATA_DIR})")
    ap.add_argument("--windows", type=int, default=40, help="H1 windows per TW (40)")
    ap.add_argument("--repeats", type=int, default=3, help="H1 timed runs per window (3)")
    ap.add_argument("--no-sklearn", action="store_true", help="H1 without the sklearn peer")
    ap.add_argument("--bin", type=float, default=60.0, help="H2 rate bin, s of driving (60)")
    ap.add_argument("--figure", type=Path, help="also save the three figures to this file")
    args = ap.parse_args(argv)

    folder = args.data / OPENACC
    t0 = time.perf_counter()
    h1 = h1_fit_time(load(str(folder)), windows=args.windows, repeats=args.repeats,
                     sklearn=not args.no_sklearn)
    print(f"H1: fit time against TW ({time.perf_counter() - t0:.0f} s)")
    print(_table(h1, ("tw", "windows", "ours_median_ms", "ours_p95_ms", "sklearn_median_ms",
                      "sklearn_p95_ms", "ratio", "ours_under_threshold")))
    h2c = h2_cluster_size()
    print(f"\nH2: MP against C_size — {h2c[0]['source']}")
    print(_table(h2c, ("cluster_size", "mp_mean_s", "switches", "new_kernel_events",
                       "new_kernel_rate", "new_kernels_per_min")))
    t0 = time.perf_counter()
    rate = h2_new_kernel_rate(holdout_tables(data_dir=folder), bin_s=args.bin)
    print(f"\nH2: {rate['source']}, {rate['driven_s'] / 60:.1f} min "
          f"({time.perf_counter() - t0:.0f} s)")
    print(_table(rate["bins"], ("start_s", "end_s", "switches", "new_kernels", "rate_per_min",
                                "cumulative", "cumulative_ratio")))
    print("totals:  ", rate["totals"])
    print("recorded:", default_bank().meta.get("stats", {}).get("holdout"))
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 3, figsize=(18, 5), layout="constrained")
        plot_h1(axes[0], h1)
        plot_h2_cluster(axes[1], h2c)
        plot_h2_rate(axes[2], rate)
        fig.savefig(args.figure, dpi=120)
        print(f"wrote {args.figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
