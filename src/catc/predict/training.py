"""Kernel bank training: the paper's Algorithm 1, clustering, and the H2 measures.

Training walks real trips with a training window of TW samples and, at every step, asks
whether the current (speed, heading) model pair still forecasts the next ``horizon_s``
seconds with a position tracking error under PTE_th, forecasting exactly as the HGP
predictor does (:func:`catc.predict.hgp.forecast_path`).  While it does, the model
persists (model persistency, MP).  When it does not, the best bank pair is tried, and
when no pair meets PTE_th a new pair is fitted on the window by LOO-CV, warm-started
from the best pair, and added (Algorithm 1, "Training: HGP kernel bank generation").
The full bank is then reduced to C_size pairs by k-means on the log hyperparameters
("Offline training and clustering").

Pure: tracks in, banks and statistics out.  Reading datasets and writing the JSON file
is the ``captures train-bank`` command's job.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.cluster.vq import kmeans2

from catc.mobility import Track
from catc.predict import gp
from catc.predict.bank import KernelBank
from catc.predict.forecast import integrate
from catc.predict.hgp import HgpConfig, forecast_path

DT = 0.1


@dataclass(frozen=True)
class TrainConfig:
    tw: int = 30  # training window, samples (paper: 30 = 3 s)
    pte_th: float = 0.5  # m (paper: 0.5 m)
    horizon_s: float = 1.0  # forecast length whose PTE decides whether a model still fits
    stride: int = 1  # samples between successive checks
    #: The forecast being trained for: noise terms, slope observations, integration rule.
    hgp: HgpConfig = field(default_factory=HgpConfig)


@dataclass
class TrainResult:
    bank: KernelBank  # the full bank, before clustering
    mp_s: list[float]  # model persistency of every run of a kept model, seconds
    new_models: int  # pairs fitted (the first one included)
    switches: int  # times the current pair stopped meeting PTE_th
    steps: int  # checks made
    reused: int  # switches answered by an existing bank pair


def series(track: Track) -> tuple[np.ndarray, ...]:
    """t, speed, unwrapped heading (rad), x, y, acceleration, yaw rate (rad/s) of a track."""
    return (track.t, track.speed, np.unwrap(np.radians(track.heading)), track.x, track.y,
            track.accel, np.radians(track.yaw_rate))


def forecast_pte(t, s, h, x, y, a, w, c: int, n_ahead: int, theta_s, theta_h,
                 cfg: TrainConfig) -> float:
    """Largest position error over ``n_ahead`` steps after index ``c`` when the pair
    (θ_s, θ_h) forecasts from the window ending at ``c`` (as the predictor would)."""
    win = slice(c - cfg.tw + 1, c + 1)
    tau = t[win] - t[c]
    grid = np.arange(n_ahead + 1) * DT
    slopes = (a[c], w[c]) if cfg.hgp.slopes else None
    ms, _, mh, vh = forecast_path(tau, s[win] - s[c], h[win] - h[c], slopes, theta_s, theta_h,
                                  grid, cfg.hgp)
    px, py = integrate(x[c], y[c], grid, ms + s[c], mh + h[c], vh, cfg.hgp.integration)
    return float(np.max(np.hypot(px[1:] - x[c + 1:c + 1 + n_ahead],
                                 py[1:] - y[c + 1:c + 1 + n_ahead])))


def _fit_pair(t, s, h, c: int, cfg: TrainConfig, warm: tuple[np.ndarray, np.ndarray]):
    w = slice(c - cfg.tw + 1, c + 1)
    tau = t[w] - t[c]
    return (gp.fit(tau, s[w] - s[c], cfg.hgp.noise_speed, warm[0], cfg.hgp.speed_bounds).theta,
            gp.fit(tau, h[w] - h[c], cfg.hgp.noise_heading, warm[1],
                   cfg.hgp.heading_bounds).theta)


def train(tracks: Sequence[Track], cfg: TrainConfig = TrainConfig(),
          warm: tuple[np.ndarray, np.ndarray] | None = None,
          progress: Callable[[int, int], None] | None = None) -> TrainResult:
    """Algorithm 1 over ``tracks`` (in order).  ``warm`` starts the very first fit."""
    n_ahead = round(cfg.horizon_s / DT)
    warm = warm or (np.array([2.0, 1.0, 0.1]), np.array([2.0, 0.1, 0.01]))
    speed_bank: list[np.ndarray] = []
    heading_bank: list[np.ndarray] = []
    mp_s: list[float] = []
    current: int | None = None
    run_start = 0.0
    switches = reused = steps = 0
    total = sum(max(0, len(tr) - cfg.tw - n_ahead) for tr in tracks)
    for tr in tracks:
        t, s, h, x, y, a, w = series(tr)
        for c in range(cfg.tw - 1, len(tr) - n_ahead, cfg.stride):
            steps += 1
            if progress is not None and steps % 200 == 0:
                progress(steps, total)
            if current is None:
                pair = _fit_pair(t, s, h, c, cfg, warm)
                speed_bank.append(pair[0])
                heading_bank.append(pair[1])
                current, run_start = len(speed_bank) - 1, t[c]
                continue
            if forecast_pte(t, s, h, x, y, a, w, c, n_ahead, speed_bank[current],
                            heading_bank[current], cfg) < cfg.pte_th:
                continue
            switches += 1
            mp_s.append(float(t[c] - run_start))
            ptes = [forecast_pte(t, s, h, x, y, a, w, c, n_ahead, speed_bank[i],
                                 heading_bank[i], cfg) for i in range(len(speed_bank))]
            best = int(np.argmin(ptes))
            if ptes[best] < cfg.pte_th:
                current = best
                reused += 1
            else:
                pair = _fit_pair(t, s, h, c, cfg, (speed_bank[best], heading_bank[best]))
                speed_bank.append(pair[0])
                heading_bank.append(pair[1])
                current = len(speed_bank) - 1
            run_start = t[c]
        if current is not None:
            mp_s.append(float(t[-1 - n_ahead] - run_start))
            current = None  # the next trip starts with a fresh fit, as a new RV would
    bank = KernelBank(np.array(speed_bank), np.array(heading_bank))
    return TrainResult(bank, mp_s, len(speed_bank), switches, steps, reused)


def cluster(bank: KernelBank, size: int, seed: int = 0) -> KernelBank:
    """Reduce ``bank`` to ``size`` pairs: k-means on the 6-D log hyperparameters."""
    if len(bank) <= size:
        return bank
    features = np.log(np.hstack([bank.speed, bank.heading]))
    centroids, labels = kmeans2(features, size, seed=seed, minit="++")
    used = np.unique(labels)
    centroids = np.exp(centroids[used])
    return KernelBank(centroids[:, :3], centroids[:, 3:], dict(bank.meta))


def persistency(tracks: Sequence[Track], bank: KernelBank,
                cfg: TrainConfig = TrainConfig(), trace: dict | None = None,
                ) -> dict[str, float]:
    """Walk ``tracks`` with a fixed ``bank`` (no training) and measure how it fares.

    Returns the mean model persistency (s) and the new-kernel rate: the fraction of
    switches, and the count per minute of driving, at which no bank pair met PTE_th
    (where online HGP would fit a new model).  These are the paper's H2 measures.

    ``trace``, when given, is filled with when things happened, on the driving clock the
    per-minute rate uses (the walked tracks laid end to end):  ``trace["switches"]``, one
    dict per switch: ``track`` (index into ``tracks``), ``vehicle``, ``t_trip_s`` (since
    the track's first sample), ``driven_s`` (since the first walked track's first sample)
    and ``new`` (no bank pair met PTE_th: a new-kernel event); ``trace["tracks"]``, one
    dict per walked track: ``track``, ``vehicle``, ``start_s`` and ``driven_s`` (its
    length, s).  The returned figures are the same with or without it.
    """
    n_ahead = round(cfg.horizon_s / DT)
    mp_s: list[float] = []
    misses = switches = 0
    driven = 0.0
    if trace is not None:
        trace.update(switches=[], tracks=[])
    for k, tr in enumerate(tracks):
        t, s, h, x, y, a, w = series(tr)
        current = None
        run_start = 0.0
        for c in range(cfg.tw - 1, len(tr) - n_ahead, cfg.stride):
            if current is not None and forecast_pte(
                    t, s, h, x, y, a, w, c, n_ahead, bank.speed[current], bank.heading[current],
                    cfg) < cfg.pte_th:
                continue
            ptes = [forecast_pte(t, s, h, x, y, a, w, c, n_ahead, bank.speed[i],
                                 bank.heading[i], cfg) for i in range(len(bank))]
            best = int(np.argmin(ptes))
            if current is not None:
                switches += 1
                mp_s.append(float(t[c] - run_start))
                new = bool(ptes[best] >= cfg.pte_th)
                misses += new
                if trace is not None:
                    trace["switches"].append({
                        "track": k, "vehicle": tr.vehicle_id, "t_trip_s": float(t[c] - t[0]),
                        "driven_s": driven + float(t[c] - t[0]), "new": new})
            current, run_start = best, t[c]
        if current is not None:
            mp_s.append(float(t[-1 - n_ahead] - run_start))
            if trace is not None:
                trace["tracks"].append({"track": k, "vehicle": tr.vehicle_id, "start_s": driven,
                                        "driven_s": float(t[-1] - t[0])})
            driven += float(t[-1] - t[0])
    return {"mp_mean_s": float(np.mean(mp_s)) if mp_s else float("nan"),
            "switches": switches, "new_kernel_events": misses,
            "new_kernel_rate": misses / max(switches, 1),
            "new_kernels_per_min": misses / max(driven / 60.0, 1e-9)}
