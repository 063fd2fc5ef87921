"""Online models (paper, "Forecasting": "If there is no model in the reduced kernel bank
that meets the required PTE_th a new model is created, added to the bank, and selected").

The selected models are back-tested on the window (condition on all but its last
``backtest_s``, forecast those, compare integrated positions with the received ones); if
they miss by more than ``pte_th``, new speed and heading models are fitted by LOO-CV on the
window (:func:`catc.predict.gp.fit`, warm-started from the selected ones) and added to the
predictor's online bank.  Off by default (``HgpConfig.online``, docs/reference/predictors.md).
"""

from __future__ import annotations

import math

import numpy as np

from catc.predict import gp
from catc.predict.forecast import integrate
from catc.predict.hgp.config import HgpConfig
from catc.predict.hgp.gpstack import series_consts
from catc.predict.hgp.reference import forecast_path
from catc.predict.hgp.window import Selection, WindowState


def backtest_fails(c: HgpConfig, tau: np.ndarray, ys: np.ndarray, yh: np.ndarray,
                   x: np.ndarray, y: np.ndarray, theta_s: np.ndarray, theta_h: np.ndarray,
                   s0: float, h0: float) -> bool:
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
                                series_consts(np.array([theta_s, theta_h]), 1, c))
