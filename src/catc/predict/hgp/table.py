"""Many RVs' HGP predictors as one table (issue 30, item 3): what
:class:`~catc.predict.hgp.predictor.HgpPredictor` objects compute, bit for bit, with each
RV's window, kinematic branches and forecast in rows of shared arrays, so that a CA-TC tick
at 1,000 RVs updates them in one compiled call and plans their answers with array
operations instead of a Python call per RV.

* :class:`HgpTable` holds the rows; :class:`HgpRow` is one RV's handle, a
  :class:`~catc.predict.base.Predictor` (``update`` queues the observation, ``predict``
  answers at once).  ``update`` of a whole tick is :meth:`HgpTable.flush`: the
  branches' scores at each BSM that ends a gap (Python, as
  :meth:`~catc.predict.hgp.branches.Branches.score_gap`), then the Kalman branch's time
  and measurement update and the window's push for every row in one compiled loop
  (:func:`~catc.predict.hgp.rows.apply`), in rounds when a row has several observations.
* :meth:`HgpTable.prepare` makes the forecasts due, stacked
  (:func:`~catc.predict.hgp.stacked.forecast_batch`'s steps, on the rows' arrays);
  :meth:`HgpTable.columns` answers every row at two times as
  :func:`catc.predict.predict_columns` does.
* The configurations it takes (:func:`supported`): the shipped HGP (selection with
  slopes, no online models, no time cap on the window, GP speed and heading, CA and KF
  branches by switching, not blending).  Others stay with the objects.

The arithmetic is the objects': the same functions on the same numbers (the compiled
loop is ``KalmanPredictor.update``'s and ``WindowState.push``'s, operation for
operation, and tests/test_hgp_table.py holds every answer to theirs, bit for bit).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np

from catc.compiled import compiled
from catc.predict.bank import KernelBank, default_bank
from catc.predict.base import Observation, Prediction
from catc.predict.forecast import (
    DT,
    Forecast,
    bsm_prediction,
    covers,
    fill_columns,
    read,
    read_xy,
)
from catc.predict.hgp.branches import Branches
from catc.predict.hgp.config import HgpConfig
from catc.predict.hgp.gpstack import forecast_grid, forecast_steps, posterior_stack
from catc.predict.hgp.predictor import HgpPredictor
from catc.predict.hgp.rows import kernel, positions
from catc.predict.hgp.selection import (
    SELECT_CHUNK,
    bank_indices,
    regular_index,
    regular_indices,
    still_fits,
)
from catc.predict.hgp.stacked import POSTERIOR_CHUNK, finish_stack, regular_posteriors
from catc.predict.hgp.window import bank_cache
from catc.predict.kalman import KalmanPredictor
from catc.predict.kinematic import (
    TIME_TOLERANCE,
    ConstantAccelerationPredictor,
    check_observation,
    elapsed,
)

__all__ = ["HgpRow", "HgpTable", "supported"]

#: Columns of the rows' last observation (:class:`Observation`'s fields).
_T, _X, _Y, _SPEED, _HEADING, _ACCEL, _YAW = range(7)
#: Where :func:`~.rows.positions` puts each branch's x (then y).
_BRANCH_XY = {"ca": 0, "kf": 2}


def supported(c: HgpConfig) -> bool:
    """Whether :class:`HgpTable` computes what ``HgpPredictor(config=c)`` does (module
    docstring)."""
    return (c.slopes and c.select_with_slopes and not c.online and math.isinf(c.window_s)
            and c.speed_model == "gp" and c.heading_model == "gp" and not c.branch_blend
            and set(c.branches) <= {"ca", "kf"} and len(set(c.branches)) == len(c.branches))


class _Scores:
    """One row's branch scores, in the attributes
    :meth:`~catc.predict.hgp.branches.Branches.add` keeps them in."""

    __slots__ = ("choice", "config", "margins", "score", "scored", "weights")

    def __init__(self, c: HgpConfig, margins: list[float]) -> None:
        classes = len(c.branch_edges) + 1
        self.config, self.margins = c, margins
        self.score = [[0.0] * (len(c.branches) + 1) for _ in range(classes)]
        self.scored = [0] * classes
        self.choice = [0] * classes
        self.weights: list = [None] * classes


class _View:
    """What :func:`~catc.predict.hgp.stacked.finish_stack` reads of a window: its
    configuration and its switch counters (the others are the table's arrays)."""

    __slots__ = ("config", "stats")

    def __init__(self, c: HgpConfig) -> None:
        self.config = c
        self.stats = {"switch_ca": 0, "switch_cs": 0}


class _Prepared:
    """Windows prepared for a forecast (``stacked.prepare_many``): those of one length as
    rows of one array (window i is ``arrays[which[i]][at[i]]``), and which are regular."""

    __slots__ = ("arrays", "at", "regular", "which")

    def __init__(self, n: int) -> None:
        self.arrays: list[np.ndarray] = []
        self.which = np.zeros(n, dtype=np.int64)
        self.at = np.zeros(n, dtype=np.int64)
        self.regular = np.zeros(n, dtype=bool)

    def rel(self, i: int) -> np.ndarray:
        return self.arrays[self.which[i]][self.at[i]]

    def stack(self, items: np.ndarray) -> np.ndarray:
        """The windows ``items`` (one length) stacked, (len(items), 3, n + 1)."""
        return self.arrays[self.which[items[0]]][self.at[items]]


class HgpRow:
    """One RV's HGP predictor, a row of an :class:`HgpTable` (a
    :class:`~catc.predict.base.Predictor`).  ``update`` is queued until the table's next
    :meth:`~HgpTable.flush` (every read flushes first); :meth:`release` gives the row
    back (the handle is dead from then on)."""

    __slots__ = ("alive", "slot", "table")
    name = "hgp"

    def __init__(self, table: HgpTable, slot: int) -> None:
        self.table, self.slot, self.alive = table, slot, True

    def update(self, obs: Observation) -> None:
        self.table._pending.append((self, obs))

    def predict(self, t: float) -> Prediction:
        answer = self.table.plan(self, t)
        return read(*answer) if answer.__class__ is tuple else answer

    def reset(self) -> None:
        raise NotImplementedError("a table row is released, not reset")

    def release(self) -> None:
        self.table.release(self)

    @property
    def stats(self) -> dict[str, int]:
        """``HgpPredictor.stats``: forecasts, selections and hybrid switches so far."""
        t, s = self.table, self.slot
        switches = t._views[s].stats
        return {"forecasts": int(t.n_forecasts[s]), "selections": int(t.n_selections[s]),
                "online_models": 0, "switch_ca": switches["switch_ca"],
                "switch_cs": switches["switch_cs"]}


class HgpTable:
    """The rows (module docstring).  ``bank`` and ``config`` as :class:`HgpPredictor`'s;
    ValueError for a configuration it does not compute (:func:`supported`)."""

    def __init__(self, bank: KernelBank | None = None, config: HgpConfig | None = None,
                 capacity: int = 64) -> None:
        c = config or HgpConfig()
        if not supported(c):
            raise ValueError("HgpTable: this HgpConfig is computed by HgpPredictor only")
        self.config = c
        self.bank = bank if bank is not None else default_bank()
        self.shared = bank_cache(self.bank, c)
        self._margins = c.margins()
        self._kf = KalmanPredictor()  # the branches as the objects make them (KINEMATIC)
        self._ca = ConstantAccelerationPredictor()
        self._kernel = kernel()
        self._positions = compiled(positions)
        self._cap = 0
        self._free: list[int] = []
        self._dead: list[int] = []
        self._pending: list[tuple[HgpRow, Observation]] = []
        self._grow(capacity)

    # -- rows -----------------------------------------------------------------------------
    def _grow(self, capacity: int) -> None:
        old, n = self._cap, max(capacity, 2 * self._cap)
        tw = self.config.tw

        def grown(a: np.ndarray | None, shape: tuple, fill: float) -> np.ndarray:
            out = np.full((n, *shape), fill, dtype=np.float64 if isinstance(fill, float)
                          else np.int64)
            if a is not None:
                out[:old] = a
            return out

        g = getattr
        self.buf = grown(g(self, "buf", None), (5, 2 * tw + 2), 0.0)  # as WindowState
        self.lo = grown(g(self, "lo", None), (), 0)
        self.hi = grown(g(self, "hi", None), (), 0)
        self.run = grown(g(self, "run", None), (), 0)
        self.since = grown(g(self, "since", None), (), 0)
        self.sel = grown(g(self, "sel", None), (2,), -1)
        self.turn = grown(g(self, "turn", None), (), 0.0)
        self.last = grown(g(self, "last", None), (7,), math.nan)
        self.kf_t = grown(g(self, "kf_t", None), (), math.nan)
        self.kf_h = grown(g(self, "kf_h", None), (), 0.0)
        self.kf_e = grown(g(self, "kf_e", None), (3,), 0.0)
        self.kf_n = grown(g(self, "kf_n", None), (3,), 0.0)
        self.kf_p = grown(g(self, "kf_p", None), (6,), 0.0)
        self.kf_a = grown(g(self, "kf_a", None), (2,), 0.0)
        self.f_end = grown(g(self, "f_end", None), (), math.nan)
        self.choice = grown(g(self, "choice", None), (len(self.config.branch_edges) + 1,), 0)
        self.n_forecasts = grown(g(self, "n_forecasts", None), (), 0)
        self.n_selections = grown(g(self, "n_selections", None), (), 0)
        extra = n - old
        self.forecast: list[Forecast | None] = g(self, "forecast", []) + [None] * extra
        self._scores: list[_Scores | None] = g(self, "_scores", []) + [None] * extra
        self._views: list[_View | None] = g(self, "_views", []) + [None] * extra
        self._free.extend(range(n - 1, old - 1, -1))
        self._cap = n

    def row(self) -> HgpRow:
        """A new, empty row."""
        if not self._free:
            self.flush()  # a row released before may come back (its updates dropped)
            if not self._free:
                self._grow(2 * self._cap)
        s = self._free.pop()
        c = self.config
        self.lo[s] = self.hi[s] = self.run[s] = self.since[s] = 0
        self.sel[s] = -1
        self.turn[s] = 0.0
        self.last[s] = math.nan
        self.kf_t[s] = math.nan
        self.f_end[s] = math.nan
        self.choice[s] = self.n_forecasts[s] = self.n_selections[s] = 0
        self.forecast[s] = None
        self._scores[s] = _Scores(c, self._margins)
        self._views[s] = _View(c)
        return HgpRow(self, s)

    def release(self, row: HgpRow) -> None:
        """Give ``row`` back; its queued updates are dropped at the next flush."""
        if row.alive:
            row.alive = False
            self._dead.append(row.slot)

    # -- update ---------------------------------------------------------------------------
    def flush(self) -> None:
        """Apply the queued updates, in order (module docstring)."""
        pending, self._pending = self._pending, []
        rounds: list[list[tuple[int, Observation]]] = [[]]
        seen: dict[int, int] = {}
        for row, obs in pending:
            if not row.alive:
                continue
            k = seen.get(row.slot, 0)
            seen[row.slot] = k + 1
            if k == len(rounds):
                rounds.append([])
            rounds[k].append((row.slot, obs))
        for items in rounds:
            if items:
                self._round(items)
        if self._dead:
            self._free.extend(self._dead)
            self._dead = []

    def _round(self, items: list[tuple[int, Observation]]) -> None:
        """One observation per row: ``HgpPredictor.update`` of each."""
        c = self.config
        edges, horizon, long_gap = c.branch_edges, c.horizon_s, c.reselect_gap_s + 1e-6
        last_t = self.last[:, _T]
        slots, rows, keep, scored = [], [], [], []
        for s, obs in items:
            check_observation(obs)  # what the branches' updates check first
            prev_t = float(last_t[s])
            if prev_t == prev_t:  # a previous observation
                if obs.t <= prev_t:
                    continue
                gap = obs.t - prev_t
                f = self.forecast[s]
                if gap > DT + 1e-6 and f is not None and covers(f, gap, horizon):
                    scored.append((s, obs, bisect.bisect_left(edges, gap), read_xy(f, gap)))
                if gap > long_gap and still_fits(c, f, gap, obs.x, obs.y):
                    keep.append(s)
            slots.append(s)
            rows.append(obs)
        if not slots:
            return
        if scored:
            self._score(scored)
        kept = self.sel[keep] if keep else None  # the kernel drops these selections
        kf = self._kf
        self._kernel(np.array(slots, dtype=np.int64), np.array(rows, dtype=np.float64),
                     self.buf, self.lo, self.hi, self.turn, self.run, self.since, self.sel,
                     self.last, self.kf_t, self.kf_h, self.kf_e, self.kf_n, self.kf_p,
                     self.kf_a, c.tw, kf.q, kf._r[0], kf._r[1], kf._r[2], c.reselect_gap_s,
                     kf.anchor)
        if keep:
            self.sel[keep] = kept
        forecast = self.forecast
        for s in slots:
            forecast[s] = None
        self.f_end[slots] = math.nan

    def _score(self, scored: list[tuple[int, Observation, int, tuple[float, float]]]
               ) -> None:
        """``Branches.score_gap``'s scores at each ``(row, obs, gap class, the GP's
        position read from its forecast)``: the branches' positions at the BSMs that end
        the gaps in one compiled loop (:func:`~.rows.positions`)."""
        names = self.config.branches
        if names:
            slots = np.array([item[0] for item in scored], dtype=np.int64)
            if "kf" in names and np.isnan(self.kf_t[slots]).any():  # never: its LookupError
                for item in scored:
                    self._branch(item[0], "kf").position(item[1].t)
            xy = np.empty((len(scored), 4))
            self._positions(slots, np.array([item[1].t for item in scored]), self.last,
                            self.kf_t, self.kf_h, self.kf_e, self.kf_n, self.kf_a, xy)
            cols = [_BRANCH_XY[name] for name in names]
            pos = xy.tolist()
        for k, (s, obs, g, (gx, gy)) in enumerate(scored):
            x, y = obs.x, obs.y
            errs = [(gx - x) ** 2 + (gy - y) ** 2]
            if names:
                here = pos[k]
                errs.extend((here[j] - x) ** 2 + (here[j + 1] - y) ** 2 for j in cols)
            scores = self._scores[s]
            Branches.add(scores, g, errs)  # type: ignore[arg-type]  # its attributes
            self.choice[s, g] = scores.choice[g]

    def _branch(self, s: int, name: str) -> KalmanPredictor | ConstantAccelerationPredictor:
        """The kinematic branch ``name`` of row ``s``: an object of its class, holding the
        row's state (the same object each time: read it before the next call)."""
        if name == "ca":
            ca = self._ca
            ca._last = Observation(*self.last[s].tolist())
            return ca
        kf = self._kf
        t = float(self.kf_t[s])
        kf._t = None if t != t else t
        kf._east = tuple(self.kf_e[s].tolist())
        kf._north = tuple(self.kf_n[s].tolist())
        kf._p = tuple(self.kf_p[s].tolist())
        kf._heading = float(self.kf_h[s])
        kf._anchor = tuple(self.kf_a[s].tolist())
        return kf

    # -- forecasts ------------------------------------------------------------------------
    def prepare(self, rows: Sequence[HgpRow], t: float) -> int:
        """:func:`~catc.predict.hgp.predictor.forecast_many` for ``rows``: the forecasts
        that answering at ``t`` needs, made stacked; how many."""
        self.flush()
        c = self.config
        slots = np.fromiter((r.slot for r in rows), dtype=np.int64, count=len(rows))
        tau = t - self.last[slots, _T]
        with np.errstate(invalid="ignore"):
            due = (tau > 0.0) & ~(self.f_end[slots] >= np.minimum(tau, c.horizon_s) - 1e-9)
        due &= self.hi[slots] - self.lo[slots] >= c.min_points
        idx = np.flatnonzero(due)
        if not len(idx):
            return 0
        steps: dict[float, int] = {}
        counts = []
        for h in np.maximum(tau[idx], 3.0).tolist():
            n = steps.get(h)
            if n is None:
                n = steps[h] = forecast_steps(h, c)
            counts.append(n)
        self._forecasts(slots[idx], np.array(counts, dtype=np.int64))
        return len(idx)

    def _prepared(self, slots: np.ndarray) -> _Prepared:
        """``stacked.prepare_many`` of the rows ``slots``: each window relative to its
        last sample, and whether it is regular (``WindowState.cache_for``: samples DT
        apart, the regular-grid cache of its length), the windows of each length
        gathered and subtracted at once."""
        lo, hi, last = self.lo[slots], self.hi[slots], self.last
        out = _Prepared(len(slots))
        lengths = hi - lo
        width = self.buf.shape[2]
        for n in np.unique(lengths).tolist():
            same = np.flatnonzero(lengths == n)
            fs = slots[same]
            idx = ((fs * (5 * width))[:, None, None] + (np.arange(3) * width)[None, :, None]
                   + (lo[same][:, None] + np.arange(n))[:, None, :])
            win = self.buf.reshape(-1).take(idx)
            rel = np.empty((len(same), 3, n + 1))
            np.subtract(win, win[:, :, -1:], out=rel[:, :, :n])
            rel[:, 0, n] = 0.0
            rel[:, 1, n] = last[fs, _ACCEL]
            rel[:, 2, n] = [math.radians(v) for v in last[fs, _YAW].tolist()]
            if n >= 2:
                steps = np.diff(rel[:, 0, :n], axis=1)
                steps -= DT
                out.regular[same] = (np.abs(steps).max(axis=1) <= 1e-6) & (self.run[fs] >= n)
            out.which[same], out.at[same] = len(out.arrays), np.arange(len(same))
            out.arrays.append(rel)
        return out

    def _select(self, slots: np.ndarray, prep: _Prepared, items: np.ndarray) -> None:
        """``selection.select_batch`` of the rows ``slots[items]``."""
        rows = slots[items]
        self.n_selections[rows] += 1
        self.since[rows] = 0
        for same in self._by_length(items[prep.regular[items]], prep).values():
            cache = self.shared.regular_bank(self.bank, self.config,
                                             prep.rel(same[0]).shape[1] - 1)
            if len(same) == 1:
                i = same[0]
                self.sel[slots[i]] = regular_index(prep.rel(i), cache)
            else:
                self.sel[slots[same]] = np.array(
                    regular_indices(prep.stack(np.array(same)), cache)).T
        for todo in self._by_length(items[~prep.regular[items]], prep).values():
            for lo in range(0, len(todo), SELECT_CHUNK):
                chunk = np.array(todo[lo:lo + SELECT_CHUNK])
                self.sel[slots[chunk]] = np.array(
                    bank_indices(prep.stack(chunk), self.shared)).T

    @staticmethod
    def _by_length(items: np.ndarray, prep: _Prepared) -> dict[int, list[int]]:
        """``items`` grouped by window length, in the order of each length's first."""
        groups: dict[int, list[int]] = {}
        for i in items.tolist():
            groups.setdefault(prep.rel(i).shape[1], []).append(i)
        return groups

    def _forecasts(self, slots: np.ndarray, counts: np.ndarray) -> None:
        """``stacked.forecast_batch`` of the rows ``slots``, ``counts[i]`` points each; the
        forecasts kept in the rows."""
        c = self.config
        prep = self._prepared(slots)
        self.n_forecasts[slots] += 1
        stale = np.flatnonzero((self.sel[slots, 0] < 0) | (self.since[slots] >= c.reselect_every))
        if len(stale):
            self._select(slots, prep, stale)
        # groups of one window length and forecast length, in the order of their first row
        keys = (self.hi[slots] - self.lo[slots]) * 100_000 + counts
        _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        consts, m = self.shared.consts, self.shared.m
        views = self._views
        for g in np.argsort(first, kind="stable").tolist():
            members = np.flatnonzero(inverse == g)
            count = int(counts[members[0]])
            grid = forecast_grid(count)[0]
            ms = slots[members]
            sel = self.sel[ms]
            pairs = np.stack([consts[sel[:, 0]], consts[m + sel[:, 1]]], axis=1)
            regular = prep.regular[members]
            direct = np.flatnonzero(~regular)
            if len(direct) == len(members) <= POSTERIOR_CHUNK:
                mean, var = posterior_stack(prep.stack(members), grid, pairs)
            else:
                mean = np.empty((len(members), 2, count))
                var = np.empty((len(members), 2, count))
                reg = np.flatnonzero(regular)
                if len(reg):  # cached weights: one matrix product per bank model in use
                    n = prep.rel(int(members[reg[0]])).shape[1] - 1
                    regular_posteriors(self.shared.regular_posteriors(self.bank, c, count, n),
                                       sel[reg].astype(np.intp),
                                       prep.stack(members[reg]), reg.tolist(), mean, var)
                for lo in range(0, len(direct), POSTERIOR_CHUNK):
                    rows = direct[lo:lo + POSTERIOR_CHUNK]
                    mean[rows], var[rows] = posterior_stack(prep.stack(members[rows]), grid,
                                                            pairs[rows])
            last = self.last[ms]
            start = np.empty((len(ms), 4))
            start[:, 0] = last[:, _SPEED]
            start[:, 1] = [math.radians(h) for h in last[:, _HEADING].tolist()]
            start[:, 2] = last[:, _X]
            start[:, 3] = last[:, _Y]
            ms_list = ms.tolist()
            made = finish_stack([views[s] for s in ms_list], mean, var, start, grid)
            forecast = self.forecast
            for s, f in zip(ms_list, made, strict=True):
                forecast[s] = f
            self.f_end[ms] = made[0].end

    # -- answers --------------------------------------------------------------------------
    def plan(self, row: HgpRow, t: float):
        """``HgpPredictor.plan(t)`` of ``row``: a Prediction, or ``(forecast, tau)``."""
        self.flush()
        s = row.slot
        if self.last[s, _T] != self.last[s, _T]:
            raise LookupError("no observation yet")
        c = self.config
        last = Observation(*self.last[s].tolist())
        tau = elapsed(last.t, t)
        if tau == 0.0:
            return bsm_prediction(last)
        if self.hi[s] - self.lo[s] < c.min_points:
            return HgpPredictor._ca(last, tau)
        f = self.forecast[s]
        if f is None or not covers(f, tau, c.horizon_s):
            self._forecasts(np.array([s]), np.array([forecast_steps(max(tau, 3.0), c)]))
            f = self.forecast[s]
        b = int(self.choice[s, bisect.bisect_left(c.branch_edges, tau)])
        if b:  # the GP's forecast is still made: it is scored at the next BSM
            return self._branch(s, c.branches[b - 1]).predict(t)
        return f, tau

    def columns(self, rows: Sequence[HgpRow], t0: float, t1: float
                ) -> tuple[np.ndarray, list[str]]:
        """:func:`catc.predict.predict_columns` of ``rows`` at ``t0 <= t1``, after
        :meth:`prepare` for ``t1``: the (10, n) array and the sources at ``t0``."""
        self.flush()
        c = self.config
        n = len(rows)
        slots = np.fromiter((r.slot for r in rows), dtype=np.int64, count=n)
        out = np.empty((10, n))
        sources = [""] * n
        if not n:
            return out, sources
        last = self.last[slots]
        if np.isnan(last[:, _T]).any():
            raise LookupError("no observation yet")
        tau0, tau1 = _elapsed_many(last[:, _T], t0), _elapsed_many(last[:, _T], t1)
        edges = np.asarray(c.branch_edges, dtype=np.float64)
        short = self.hi[slots] - self.lo[slots] < c.min_points
        with np.errstate(invalid="ignore"):
            uncovered = ~(self.f_end[slots] >= np.minimum(tau1, c.horizon_s) - 1e-9)
        scalar = short | uncovered if t0 <= t1 else np.ones(n, dtype=bool)
        reads: tuple[list, list] = ([], [])  # per time: (column, (forecast, tau))
        whole: tuple[list, list] = ([], [])  # per time: (column, Prediction)
        for j, (tau, t) in enumerate(((tau0, t0), (tau1, t1))):
            fresh = tau == 0.0
            b = self.choice[slots, np.searchsorted(edges, tau, side="left")]
            gp = ~scalar & ~fresh & (b == 0)
            kin = ~scalar & ~fresh & (b != 0)
            bsm = ~scalar & fresh
            cols = np.flatnonzero(bsm)
            out[j:8:2, cols] = last[cols][:, [_X, _Y, _SPEED, _HEADING]].T
            if j == 0:
                out[8:, cols] = 0.0
                for i in cols.tolist():
                    sources[i] = "bsm"
            forecast = self.forecast
            reads[j].extend((i, (forecast[s], tu)) for i, s, tu in zip(
                np.flatnonzero(gp).tolist(), slots[gp].tolist(), tau[gp].tolist(),
                strict=True))
            for i in np.flatnonzero(kin).tolist():
                name = c.branches[int(b[i]) - 1]
                _whole(whole, sources, j, i, self._branch(int(slots[i]), name).predict(t))
        for i in np.flatnonzero(scalar).tolist():
            row = rows[i]
            for j, t in enumerate((t0, t1)):
                a = self.plan(row, t)
                if a.__class__ is tuple:
                    reads[j].append((i, a))
                else:
                    _whole(whole, sources, j, i, a)
        fill_columns(out, sources, whole, reads)
        return out, sources


def _whole(whole: tuple[list, list], sources: list[str], j: int, i: int,
           p: Prediction) -> None:
    """Prediction ``p`` of column ``i`` at time ``j`` as a row of :func:`fill_columns`."""
    whole[j].append((i, p.x, p.y, p.speed, p.heading, p.var_x, p.var_y))
    if j == 0:
        sources[i] = p.source


def _elapsed_many(last_t: np.ndarray, t: float) -> np.ndarray:
    """:func:`~catc.predict.kinematic.elapsed` of each of ``last_t`` (its ValueError for
    the first one too late)."""
    dt = t - last_t
    early = dt < 0.0
    if early.any():
        if (dt < -TIME_TOLERANCE).any():
            elapsed(float(last_t[np.argmax(dt < -TIME_TOLERANCE)]), t)  # raises
        dt = np.where(early, 0.0, dt)
    return dt

