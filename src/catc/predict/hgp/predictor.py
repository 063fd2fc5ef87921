"""The indirect HGP predictor (``hgp``): the answers at any time from the last forecast,
the branches, or the fallbacks; and :func:`forecast_many_at`, which makes the forecasts due
at a tick stacked.  :class:`HgpPredictor` is a :class:`~catc.predict.base.BatchPredictor`
with :func:`forecast_many_at` as its preparer (:func:`~catc.predict.base.register_batch`).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable

import numpy as np

from catc.predict.bank import KernelBank, default_bank
from catc.predict.base import Observation, Plan, Prediction, register_batch
from catc.predict.forecast import DT, Forecast, bsm_prediction, covers, integrate, read
from catc.predict.hgp.branches import Branches
from catc.predict.hgp.config import HgpConfig
from catc.predict.hgp.gpstack import forecast_steps
from catc.predict.hgp.online import backtest_fails, fit_online
from catc.predict.hgp.reference import forecast_path, implausible, window_series
from catc.predict.hgp.selection import select, still_fits
from catc.predict.hgp.stacked import forecast_batch
from catc.predict.hgp.window import WindowPredictor, WindowState
from catc.predict.kinematic import elapsed

#: One instance per distinct configuration, so that predictors can be grouped by identity.
_CONFIGS: dict[HgpConfig, HgpConfig] = {}


class HgpPredictor(WindowPredictor):
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
        keep = (prev is not None and obs.t - prev.t > self.config.reselect_gap_s + 1e-6
                and still_fits(self.config, self._forecast, obs.t - prev.t, obs.x, obs.y))
        self._obs.append(obs)  # WindowPredictor.update, its time check done above
        self._forecast = None
        self._state.push(obs, keep)

    def predict(self, t: float) -> Prediction:
        answer = self.plan(t)
        return read(*answer) if answer.__class__ is tuple else answer

    def plan(self, t: float) -> Plan:
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

    def plan_pair(self, t0: float, t1: float) -> tuple[Plan, Plan]:
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
    @staticmethod
    def _ca(last: Observation, tau: float) -> Prediction:
        """Constant acceleration along the last heading, stopping at zero speed."""
        a = last.accel
        stop = -last.speed / a if a < 0 else math.inf
        tt = min(tau, stop)
        dist = last.speed * tt + 0.5 * a * tt * tt
        h = math.radians(last.heading)
        return Prediction(last.x + dist * math.sin(h), last.y + dist * math.cos(h),
                          max(0.0, last.speed + a * tt), last.heading, source="ca")

    def _make_forecast(self, horizon: float) -> Forecast:
        return forecast_batch([self._state], [forecast_steps(horizon, self.config)])[0]

    def _make_forecast_reference(self, horizon: float) -> Forecast:
        """The forecast by the readable formulas, selecting every time: what
        :meth:`_make_forecast` computed before it was made fast, kept as the reference the
        tests compare it with and as the "before" of ``bench/hgp_forecast.py``."""
        c = self.config
        s = self._state
        s.stats["forecasts"] += 1
        last = self._obs[-1]
        tau, ys, yh, x, y = window_series(self._obs, c.window_s)
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
    steps: dict[tuple[float, int], int] = {}  # forecast_steps by (horizon, config)
    for p, t in items:
        obs = getattr(p, "_obs", None)
        if not obs or not isinstance(p, HgpPredictor):
            continue
        tau = t - obs[-1].t
        if not tau > 0.0:
            continue
        c = p.config
        f = p._forecast  # most are still covered: asked first, covers() inlined
        if f is not None and f.end >= min(tau, c.horizon_s) - 1e-9:
            continue
        if (len(obs) if p._uncapped else p._window_len()) < c.min_points:
            continue
        horizon = max(tau, 3.0)
        count = steps.get((horizon, id(c)))
        if count is None:
            count = steps[horizon, id(c)] = forecast_steps(horizon, c)
        key = (id(c), id(p._state.shared))
        group = groups.get(key)
        if group is None:
            group = groups[key] = []
        group.append((p, count))
    for group in groups.values():
        preds = [p for p, _ in group]
        made = forecast_batch([p._state for p in preds], [n for _, n in group])
        for p, f in zip(preds, made, strict=True):
            p._forecast = f
    return sum(len(group) for group in groups.values())


register_batch(HgpPredictor, forecast_many_at, plans=True)
