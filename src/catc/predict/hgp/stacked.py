"""The fast path: the forecasts of many windows (each a
:class:`~catc.predict.hgp.window.WindowState`) in one set of calls; what the reference,
``HgpPredictor._make_forecast_reference``, computes, to round-off (tests/test_hgp.py).

Per tick: the windows relative to their last sample in one subtraction
(:func:`prepare_many`); bank selection where due (:mod:`~catc.predict.hgp.selection`);
the speed and heading posteriors of all windows, from cached weights for loss-free windows
(:func:`forecast_batch`); then switching, integration and position variances on the
stacked rows (:func:`finish_stack`).
"""

from __future__ import annotations

import math

import numpy as np

from catc.predict import gp, gpkernels
from catc.predict.forecast import DT, Forecast
from catc.predict.hgp.config import HgpConfig
from catc.predict.hgp.gpstack import forecast_grid, posterior_stack, stack
from catc.predict.hgp.online import go_online
from catc.predict.hgp.reference import implausible
from catc.predict.hgp.selection import select_batch
from catc.predict.hgp.window import WindowState


def plausible_rows(c: HgpConfig, ext: np.ndarray) -> np.ndarray:
    """Per row of ``ext`` (B, 6), True when no forecast step can break a hybrid-switching
    criterion (paper: GP predictions "swapped with constant speed and constant
    acceleration predictions if a specific criterion is met"), from the extremes of the
    forecast (least speed, greatest speed, greatest step changes of speed and heading,
    greatest variances).  Each criterion of :func:`~.reference.implausible` is monotone
    in these, so True means it finds nothing; on False it is asked.  A NaN extreme is
    never plausible."""
    lo, hi, ds, dh, vs, vh = ext.T
    yaw = np.degrees(dh) / DT
    ok = lo >= 0.0
    ok &= ds / DT <= c.accel_max
    ok &= yaw <= c.yaw_rate_max
    ok &= hi * np.radians(yaw) <= c.lat_accel_max
    ok &= np.sqrt(vs) <= c.speed_std_max
    ok &= np.degrees(np.sqrt(vh)) <= c.heading_std_max
    return ok


_ALL_GP: dict[int, tuple[str, ...]] = {}


def _all_gp(count: int) -> tuple[str, ...]:
    """The sources of a forecast of ``count`` points that is the GP's throughout (shared:
    forecasts' sources are never changed in place)."""
    src = _ALL_GP.get(count)
    if src is None:
        src = _ALL_GP[count] = ("gp",) * count
    return src


def finish_stack(states: list[WindowState], mean: np.ndarray, var: np.ndarray, start: np.ndarray,
                 grid: np.ndarray) -> list[Forecast]:
    """Switching, integration and position variance for B forecasts of one configuration
    (``states``, :class:`WindowState`, for it and the switching counters):
    ``mean`` and ``var`` (B, 2, len(grid)) of speed and heading relative to the last sample
    (both are overwritten), ``start`` (B, 4) the last speed, heading (rad), x and y.
    The arithmetic of ``HgpPredictor._make_forecast_reference``, on stacked rows:

    * hybrid switching: from the first step that breaks a criterion
      (:func:`~.reference.implausible`) constant acceleration to a stop (μs < 0) or
      constant speed and heading;
    * positions by the paper's piecewise integration, eq. "eq-positionprediction2":
      x̄(t_{j+1}) = x̄(t_j) + (t_{j+1} − t_j)·μs·e^{−σh²/2}·sin μh (east; the paper's cos is
      north, headings here being clockwise from north), trapezoid rule by default
      (``integration="left"`` is the paper's literal recursion);
    * position variances to first order: the speed variance along the heading and
      s²·σh² across it, accumulated over the steps."""
    c = states[0].config
    bsz, _, count = mean.shape
    _, dgrid, half_dgrid = forecast_grid(count)
    start = np.ascontiguousarray(start)
    ext = np.empty((bsz, 6))  # the extremes plausible_rows needs
    gpkernels.shift_rows(mean, var, start, ext)  # means + last values, variances >= 0
    speed, head, vs, vh = mean[:, 0], mean[:, 1], var[:, 0], var[:, 1]
    all_gp = _all_gp(count)
    sources = [all_gp] * bsz
    for i in np.flatnonzero(~plausible_rows(c, ext)).tolist():
        cut = implausible(c, grid, speed[i], vs[i], head[i], vh[i])
        if cut is not None:
            stop = bool(speed[i, cut] < 0)
            states[i].stats["switch_ca" if stop else "switch_cs"] += 1
            keep = max(cut - 1, 0)
            speed[i, cut:] = 0.0 if stop else max(speed[i, keep], 0.0)
            head[i, cut:] = head[i, keep]
            vs[i, cut:] = vs[i, keep]
            vh[i, cut:] = vh[i, keep]
            sources[i] = all_gp[:cut] + ("ca" if stop else "cs",) * (count - cut)
    sc = np.empty((bsz, 2, count))  # sin h, cos h
    np.sin(head, out=sc[:, 0])
    np.cos(head, out=sc[:, 1])
    # Integrated: east and north velocity (E[s]·E[sin h], E[s]·E[cos h], see integrate),
    # the speed variance and the cross-track variance rate s²·σh²; numpy's vectorised
    # sin, cos and exp, then one compiled pass per row (gpkernels.integrate_rows).
    if c.integration not in ("trapezoid", "left"):
        raise ValueError(f"unknown integration rule {c.integration!r}")
    eff = speed * np.exp(-0.5 * vh) if c.heading_damping else np.ascontiguousarray(speed)
    table = np.empty((bsz, 6, count))  # x, y, speed, heading (deg), var_x, var_y
    gpkernels.integrate_rows(eff, sc, mean, var, start, dgrid,
                             half_dgrid, c.integration == "trapezoid", DT * DT, table)
    end = float(grid[-1])
    return [Forecast(grid, row, src, end) for row, src in zip(table, sources, strict=True)]


#: Windows per posterior call: bounds the work arrays (23 kB per window).
POSTERIOR_CHUNK = 64


def prepare_many(states: list[WindowState]) -> list[tuple]:
    """:meth:`WindowState.prepare` of each window (times and values relative to the last
    received sample, the slope appended); full windows (``tw`` samples, no time
    cap: nearly all of them) in one stacked subtraction, the same numbers."""
    c = states[0].config
    out: list = [None] * len(states)
    full, wins = [], []
    if c.slopes and math.isinf(c.window_s):
        for i, s in enumerate(states):
            if s.hi - s.lo == c.tw:
                full.append(i)
                wins.append(s.buf[:3, s.lo:s.hi])
    if len(full) > 1:
        win = stack(wins)
        n = c.tw
        rel = np.empty((len(full), 3, n + 1))
        np.subtract(win, win[:, :, -1:], out=rel[:, :, :n])
        rel[:, 0, n] = 0.0
        last = [states[i].last for i in full]
        rel[:, 1, n] = [o.accel for o in last]
        rel[:, 2, n] = [math.radians(o.yaw_rate) for o in last]
        # WindowState.cache_for of each, its regularity check (regular_cache) made for all
        # at once: samples DT apart to 1e-6 s
        steps = np.diff(rel[:, 0, :n], axis=1)
        steps -= DT
        regular = (np.abs(steps).max(axis=1) <= 1e-6).tolist()
        bank = None  # one configuration and bank: one cache for all
        for i, r, ok in zip(full, rel, regular, strict=True):
            s = states[i]
            if ok and s.run >= n and not s.online_speed:
                if bank is None:
                    bank = s.regular_bank()
                out[i] = (r, bank)
            else:
                out[i] = (r, None)
    for i, s in enumerate(states):
        if out[i] is None:
            out[i] = s.prepare()
    return out


def _regular_posteriors(states: list[WindowState], prepared: list[tuple],
                        members: list[int], rows: list[int], count: int, mean: np.ndarray,
                        var: np.ndarray) -> None:
    """Into ``mean[rows]`` and ``var[rows]``: the posteriors of regular windows (rows
    of ``members``, indices into ``states`` and ``prepared``) from the cached weights of
    their models (:meth:`WindowState.regular_posteriors`), one matrix product per model in
    use instead of two dot products per window."""
    first = members[rows[0]]
    regular_posteriors(
        states[first].regular_posteriors(count, prepared[first][0].shape[1] - 1),
        np.array([states[members[r]].selection.index for r in rows], dtype=np.intp),
        stack([prepared[members[r]][0] for r in rows]), rows, mean, var)


def regular_posteriors(post: tuple, idx: np.ndarray, rels: np.ndarray, rows: list[int],
                       mean: np.ndarray, var: np.ndarray) -> None:
    """:func:`_regular_posteriors` given the cached posteriors ``post``, the windows' bank
    rows ``idx`` (R, 2) and their prepared windows ``rels`` (R, 3, n + 1)."""
    rows_a = np.array(rows, dtype=np.intp)
    for series in (0, 1):
        models = idx[:, series]
        var[rows_a, series] = post[series].var[models]
        weights = post[series].weights
        for model in np.unique(models).tolist():
            sel = np.flatnonzero(models == model)
            mean[rows_a[sel], series] = rels[sel, series + 1] @ weights[model].T


def forecast_batch(states: list[WindowState], counts: list[int]) -> list[Forecast]:
    """Forecasts of ``counts[i]`` points from each window (all on one bank and
    configuration), computed stacked; what ``HgpPredictor._make_forecast_reference``
    computes, to round-off, with the selection renewed as ``reselect_every`` and
    ``reselect_gap_s`` say: model selection where due (paper eq. "eq-,odelselection",
    :func:`~.selection.select_batch`), online models if on, then the speed and heading
    forecasts (paper eq. "eq:forecastingheadingspeed"): cached posterior weights for a
    regular full window, else :func:`~.gpstack.posterior_stack`; then
    :func:`finish_stack`."""
    c = states[0].config
    prepared = prepare_many(states)
    stale = []
    every = c.reselect_every
    for i, s in enumerate(states):
        s.stats["forecasts"] += 1
        if s.selection is None or s.since_selection >= every:
            stale.append(i)
    if stale:
        select_batch([states[i] for i in stale], [prepared[i][0] for i in stale],
                     [prepared[i][1] for i in stale])
    if c.online:
        for s, (rel, _) in zip(states, prepared, strict=True):
            go_online(s, rel)
    out: list[Forecast | None] = [None] * len(states)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, ((rel, _), count) in enumerate(zip(prepared, counts, strict=True)):
        key = (rel.shape[1], count)
        group = groups.get(key)
        if group is None:
            group = groups[key] = []
        group.append(i)
    for (_, count), members in groups.items():
        grid = forecast_grid(count)[0]
        direct = []
        regular: list[int] = []
        for row, i in enumerate(members):
            if c.slopes:
                if states[i].selection.index is not None and prepared[i][1] is not None:
                    regular.append(row)
                else:
                    direct.append(row)
        if len(direct) == len(members) <= POSTERIOR_CHUNK:  # the usual case: one call
            rels = [prepared[i][0] for i in members]
            consts = [states[i].selection.consts for i in members]
            mean, var = posterior_stack(stack(rels), grid, stack(consts))
        else:
            mean = np.empty((len(members), 2, count))
            var = np.empty((len(members), 2, count))
            if not c.slopes:
                for row, i in enumerate(members):
                    rel, sel = prepared[i][0], states[i].selection
                    tau = rel[0, :-1]
                    mean[row, 0], var[row, 0] = gp.posterior(tau, rel[1, :-1], grid,
                                                             sel.theta_s, c.noise_speed)
                    mean[row, 1], var[row, 1] = gp.posterior(tau, rel[2, :-1], grid,
                                                             sel.theta_h, c.noise_heading)
            if regular:
                _regular_posteriors(states, prepared, members, regular, count, mean, var)
            for lo in range(0, len(direct), POSTERIOR_CHUNK):
                rows = direct[lo:lo + POSTERIOR_CHUNK]
                chunk = [members[r] for r in rows]
                mean[rows], var[rows] = posterior_stack(
                    stack([prepared[i][0] for i in chunk]), grid,
                    stack([states[i].selection.consts for i in chunk]))
        if c.slopes and c.speed_model == "ca":  # diagnostics: kinematic speed or heading
            for row, i in enumerate(members):
                mean[row, 0], var[row, 0] = prepared[i][0][1, -1] * grid, 0.0
        if c.slopes and c.heading_model == "ctrv":
            for row, i in enumerate(members):
                mean[row, 1], var[row, 1] = prepared[i][0][2, -1] * grid, 0.0
        start = np.array([(o.speed, math.radians(o.heading), o.x, o.y)
                          for o in (states[i].last for i in members)])
        for i, f in zip(members, finish_stack([states[i] for i in members], mean, var, start,
                                              grid), strict=True):
            out[i] = f
    return out  # type: ignore[return-value]
