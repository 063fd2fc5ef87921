"""What a forecast starts from: the received observations (:class:`WindowPredictor`, both
predictors), and for the indirect HGP the window as running arrays with the models in use,
the online bank and the caches shared by all predictors on one bank
(:class:`WindowState`), the explicit state the fast path works on.

The window is the last ``tw`` received samples (the paper's TW = 30), headings unwrapped
one sample at a time; a window of samples exactly DT apart (no loss: a full one, or a
vehicle heard for less than ``tw`` samples) uses the selection and posterior caches of
the regular grid of its length, built once per bank.
"""

from __future__ import annotations

import math
import weakref
from collections import deque
from dataclasses import dataclass

import numpy as np

from catc.predict.bank import KernelBank
from catc.predict.base import Observation
from catc.predict.forecast import DT, Forecast
from catc.predict.hgp.config import HgpConfig
from catc.predict.hgp.gpstack import forecast_grid, series_consts
from catc.predict.hgp.reference import RegularSlopeBank, RegularSlopePosterior
from catc.predict.kinematic import elapsed


class WindowPredictor:
    """What both GP predictors share: the window of received observations and a cached
    forecast from the last one."""

    def __init__(self, tw: int) -> None:
        self._obs: deque[Observation] = deque(maxlen=tw)
        self._forecast: Forecast | None = None

    def reset(self) -> None:
        self._obs.clear()
        self._forecast = None

    def update(self, obs: Observation) -> None:
        if self._obs and obs.t <= self._obs[-1].t:
            return
        self._obs.append(obs)
        self._forecast = None

    def _since_last(self, t: float) -> tuple[Observation, float]:
        """The last observation and the time from it to ``t`` (LookupError before data)."""
        if not self._obs:
            raise LookupError("no observation yet")
        last = self._obs[-1]
        return last, elapsed(last.t, t)


@dataclass
class Selection:
    """The models in use: θ per series, their bank rows (None for models from elsewhere:
    online ones, or a selection on values only) and their constants (2, 6)."""

    theta_s: np.ndarray
    theta_h: np.ndarray
    index: tuple[int, int] | None
    consts: np.ndarray


class BankCache:
    """What all predictors on one bank and noise configuration share: the bank as stacked
    model constants (speed rows, then heading rows) and the regular-grid selection and
    posterior caches."""

    def __init__(self, bank: KernelBank, c: HgpConfig) -> None:
        self.m = len(bank.speed)
        self.thetas = np.vstack([bank.speed, bank.heading])
        self.consts = series_consts(self.thetas, self.m, c)
        self.pairs: dict[tuple[int, int], np.ndarray] = {}
        self.regular: dict[int, tuple[RegularSlopeBank, RegularSlopeBank]] = {}
        self.posterior: dict[tuple[int, int], tuple[RegularSlopePosterior, ...]] = {}

    def regular_bank(self, bank: KernelBank, c: HgpConfig, n: int | None = None
                     ) -> tuple[RegularSlopeBank, ...]:
        """The selection cache of a window of ``n`` samples (default ``c.tw``, a full
        one) exactly DT apart (no loss) for ``bank``, this cache's bank: built once per
        length, shared by all predictors."""
        n = c.tw if n is None else n
        cache = self.regular.get(n)
        if cache is None:
            cache = self.regular[n] = (
                RegularSlopeBank(bank.speed, n, c.noise_speed, c.noise_accel),
                RegularSlopeBank(bank.heading, n, c.noise_heading, c.noise_yaw))
        return cache

    def regular_posteriors(self, bank: KernelBank, c: HgpConfig, count: int,
                           n: int | None = None) -> tuple[RegularSlopePosterior, ...]:
        """The speed and heading :class:`RegularSlopePosterior` of every model of ``bank``
        (this cache's), for a regular window of ``n`` samples (default ``c.tw``) and a
        forecast of ``count`` points."""
        n = c.tw if n is None else n
        post = self.posterior.get((n, count))
        if post is None:
            grid = forecast_grid(count)[0]
            post = self.posterior[n, count] = (
                RegularSlopePosterior(bank.speed, n, c.noise_speed, c.noise_accel, grid),
                RegularSlopePosterior(bank.heading, n, c.noise_heading, c.noise_yaw, grid))
        return post

    def pair(self, i: int, j: int) -> np.ndarray:
        """The constants of speed model ``i`` and heading model ``j``, (2, 6)."""
        p = self.pairs.get((i, j))
        if p is None:
            p = self.pairs[i, j] = self.consts[[i, self.m + j]]
        return p


#: Per-bank caches (held weakly: a bank's factors go with it), then per noise configuration.
_BANK_CACHE: weakref.WeakKeyDictionary[KernelBank, dict[tuple, BankCache]] = \
    weakref.WeakKeyDictionary()


def bank_cache(bank: KernelBank, c: HgpConfig) -> BankCache:
    per_bank = _BANK_CACHE.setdefault(bank, {})
    key = (c.noise_speed, c.noise_heading, c.noise_accel, c.noise_yaw)
    cache = per_bank.get(key)
    if cache is None:
        cache = per_bank[key] = BankCache(bank, c)
    return cache


def window_rel(win: np.ndarray, accel: float, yaw_rate: float, slopes: bool) -> np.ndarray:
    """A window's rows t, speed and heading (``win``, (3 or more, n)) relative to its last
    sample, (3, n + 1): τ then 0 (the slope's time), speed then ``accel``, heading then
    ``yaw_rate`` in rad/s (zeros without ``slopes``)."""
    n = win.shape[1]
    rel = np.empty((3, n + 1))
    np.subtract(win[:3], win[:3, -1:], out=rel[:, :n])
    rel[0, n] = 0.0
    if slopes:
        rel[1, n] = accel
        rel[2, n] = math.radians(yaw_rate)
    else:
        rel[1:, n] = 0.0
    return rel


class WindowState:
    """What a forecast of one RV starts from, and all that the fast path reads and writes:
    the window of received samples as running arrays, the models in use, the online bank,
    the caches shared with the other predictors on the same bank, and the counters.  An
    :class:`~catc.predict.hgp.predictor.HgpPredictor` keeps one and hands it to
    :func:`~catc.predict.hgp.stacked.forecast_batch`."""

    def __init__(self, bank: KernelBank, c: HgpConfig) -> None:
        self.config = c
        self.bank = bank
        self.shared = bank_cache(bank, c)
        self.online_speed: deque[np.ndarray] = deque(maxlen=c.online_max)
        self.online_heading: deque[np.ndarray] = deque(maxlen=c.online_max)
        #: Counters for captures and the H2 figures.
        self.stats = {"forecasts": 0, "selections": 0, "online_models": 0, "switch_ca": 0,
                      "switch_cs": 0}
        # The window as running arrays: one column per received sample (rows t, speed,
        # unwrapped heading in rad, x, y), columns lo..hi of a buffer twice as long.
        self.buf = np.empty((5, 2 * c.tw + 2))
        self.reset()

    def reset(self) -> None:
        """Forget the window and the selection (not the online bank nor the counters)."""
        self.lo = self.hi = 0
        self.turn = 0.0  # what unwrapping the heading has added so far, rad
        self.run = 0  # received samples in a row exactly DT apart
        self.last: Observation | None = None  # the last received sample
        self.selection: Selection | None = None
        self.since_selection = 0  # samples received since the selection was made

    def push(self, obs: Observation, keep: bool = False) -> None:
        """Append a received sample (later than the last one); ``keep``: the selection
        survives a long gap before it (:func:`~.selection.still_fits`)."""
        c = self.config
        prev = self.last
        h = math.radians(obs.heading)
        if prev is None:
            self.run = 1
        else:
            dd = h - math.radians(prev.heading)  # np.unwrap's rule, one step at a time
            if abs(dd) >= math.pi:
                mod = (dd + math.pi) % (2.0 * math.pi) - math.pi
                if mod == -math.pi and dd > 0:
                    mod = math.pi
                self.turn += mod - dd
            gap = obs.t - prev.t
            self.run = self.run + 1 if abs(gap - DT) <= 2e-6 else 1
            if gap > c.reselect_gap_s + 1e-6 and not keep:
                self.selection = None
        buf = self.buf
        if self.hi == buf.shape[1]:
            keep = c.tw - 1
            buf[:, :keep] = buf[:, self.hi - keep:self.hi]
            self.hi = keep
        buf[:, self.hi] = (obs.t, obs.speed, h + self.turn, obs.x, obs.y)
        self.hi += 1
        self.lo = max(0, self.hi - c.tw)
        self.since_selection += 1
        self.last = obs

    def window(self) -> np.ndarray:
        """The window's running arrays (rows t, speed, unwrapped heading rad, x, y)."""
        win = self.buf[:, self.lo:self.hi]
        if not math.isinf(self.config.window_s):
            win = win[:, int(np.argmax(win[0, -1] - win[0] <= self.config.window_s + 1e-9)):]
        return win

    def prepare(self) -> tuple[np.ndarray, tuple[RegularSlopeBank, ...] | None]:
        """The window relative to its last sample, (3, n + 1): τ then 0 (the slope's time);
        speed then the BSM's acceleration; heading (rad) then its yaw rate (rad/s); and the
        regular-grid selection cache if it is a full window of samples DT apart, else None."""
        last = self.last
        rel = window_rel(self.window(), last.accel, last.yaw_rate, self.config.slopes)
        return rel, self.cache_for(rel)

    def cache_for(self, rel: np.ndarray) -> tuple[RegularSlopeBank, ...] | None:
        """The regular-grid selection cache for the prepared window ``rel``, or None."""
        n = rel.shape[1] - 1
        regular = self.run >= n and not self.online_speed
        return self.regular_cache(rel[0, :n]) if regular else None

    def regular_cache(self, tau: np.ndarray) -> tuple[RegularSlopeBank, ...] | None:
        """The cached selection for a window of samples at exactly DT apart (no loss) at
        times ``tau``, one per length, built once per bank and configuration and shared by
        all predictors; None for other windows (and fewer than two samples)."""
        if len(tau) < 2 or np.max(np.abs(np.diff(tau) - DT)) > 1e-6:
            return None
        return self.regular_bank(len(tau))

    def regular_bank(self, n: int | None = None) -> tuple[RegularSlopeBank, ...]:
        """:meth:`regular_cache` of ``n`` samples (default ``tw``) without the check that
        the window is regular (the caller made it, e.g. for many windows at once:
        :func:`~.stacked.prepare_many`)."""
        return self.shared.regular_bank(self.bank, self.config, n)

    def regular_posteriors(self, count: int, n: int | None = None
                           ) -> tuple[RegularSlopePosterior, ...]:
        """:meth:`BankCache.regular_posteriors` of this window's bank."""
        return self.shared.regular_posteriors(self.bank, self.config, count, n)
