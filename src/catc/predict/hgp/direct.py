"""The direct HGP (``hgp-d``): GPs on x and y relative to the last BSM (paper, section
"Prediction Baseline Models": "the (x, y) predictions can be obtained following two
different approach, i.e, direct (D) or indirect (I)").
"""

from __future__ import annotations

import math

import numpy as np

from catc.predict import gp
from catc.predict.base import Observation, Prediction
from catc.predict.forecast import DT, Forecast, bsm_prediction, constant_speed, covers, read
from catc.predict.hgp.config import HgpDirectConfig
from catc.predict.hgp.reference import window_series
from catc.predict.hgp.window import WindowPredictor


class HgpDirectPredictor(WindowPredictor):
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
        tau, _, _, x, y = window_series(self._obs)
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
