"""Bank model selection: the speed and heading models θ* with the highest log marginal
likelihood of the window (paper eq. "eq-,odelselection"; with ``select_with_slopes`` the
likelihood of values and slope together).

:func:`select` by the readable formulas (the reference), :func:`select_batch` stacked over
the windows due at a tick (the same choice).  Model persistency (paper: a selected model
stays the best for many samples): the predictor asks for a selection only every
``reselect_every`` samples and after a gap longer than ``reselect_gap_s``.
"""

from __future__ import annotations

import numpy as np

from catc.predict import gp
from catc.predict.forecast import Forecast, covers, read_xy
from catc.predict.hgp.config import HgpConfig
from catc.predict.hgp.gpstack import lml_stack, series_consts, stack
from catc.predict.hgp.reference import RegularSlopeBank, lml_with_slope
from catc.predict.hgp.window import BankCache, Selection, WindowState


def select(s: WindowState, tau: np.ndarray, ys: np.ndarray, yh: np.ndarray,
           slopes: tuple[float, float] | None = None) -> tuple[np.ndarray, ...]:
    """Bank selection by maximum likelihood (paper eq. "eq-,odelselection"), by the
    readable formulas (the reference for the stacked selection of :func:`select_batch`):
    the speed and heading models θ* of the bank and online bank."""
    c = s.config
    speed_bank = s.bank.speed
    heading_bank = s.bank.heading
    if s.online_speed:
        speed_bank = np.vstack([speed_bank, np.array(s.online_speed)])
        heading_bank = np.vstack([heading_bank, np.array(s.online_heading)])
    if slopes is not None and c.select_with_slopes:
        cache = None if s.online_speed else s.regular_cache(tau)
        if cache is not None:
            ls, lh = cache[0].lml(ys, slopes[0]), cache[1].lml(yh, slopes[1])
        else:
            ls = lml_with_slope(tau, ys, slopes[0], c.noise_accel, speed_bank,
                                c.noise_speed)
            lh = lml_with_slope(tau, yh, slopes[1], c.noise_yaw, heading_bank,
                                c.noise_heading)
    else:
        ls = gp.bank_log_marginal_likelihood(tau, ys, speed_bank, c.noise_speed)
        lh = gp.bank_log_marginal_likelihood(tau, yh, heading_bank, c.noise_heading)
    return speed_bank[int(np.argmax(ls))], heading_bank[int(np.argmax(lh))]


def still_fits(c: HgpConfig, f: Forecast | None, gap: float, x: float, y: float) -> bool:
    """Whether a gap of ``gap`` s that ends at position (``x``, ``y``) keeps the models in
    use (``HgpConfig.reselect_fit_m``): the GP's forecast ``f`` over the gap, made with
    them, lands within ``reselect_fit_m`` of it.  False without such a forecast."""
    fit = c.reselect_fit_m
    if fit <= 0.0 or f is None or not covers(f, gap, c.horizon_s):
        return False
    gx, gy = read_xy(f, gap)
    return (gx - x) ** 2 + (gy - y) ** 2 <= fit * fit


def own_selection(s: WindowState, rel: np.ndarray,
                  cache: tuple[RegularSlopeBank, ...] | None) -> Selection | None:
    """The selection for this window when it is not worth stacking with others (a regular
    window's cached one, an online bank, selection on values only); None otherwise."""
    c = s.config
    n = rel.shape[1] - 1
    tau, ys, yh = rel[0, :n], rel[1, :n], rel[2, :n]
    if not (c.slopes and c.select_with_slopes):
        theta_s, theta_h = select(s, tau, ys, yh, None)
        return Selection(theta_s, theta_h, None,
                         series_consts(np.array([theta_s, theta_h]), 1, c))
    if s.online_speed:
        speed = np.vstack([s.bank.speed, np.array(s.online_speed)])
        thetas = np.vstack([speed, s.bank.heading, np.array(s.online_heading)])
        m = len(speed)
        lml = lml_stack(tau[None], rel[None, 1:], series_consts(thetas, m, c), m,
                        thetas)[0]
        pair = np.array([thetas[int(np.argmax(lml[:m]))], thetas[m + int(np.argmax(lml[m:]))]])
        return Selection(pair[0], pair[1], None, series_consts(pair, 1, c))
    if cache is None:
        return None
    i, j = regular_index(rel, cache)
    return Selection(s.bank.speed[i], s.bank.heading[j], (i, j), s.shared.pair(i, j))


def regular_index(rel: np.ndarray, cache: tuple[RegularSlopeBank, ...]) -> tuple[int, int]:
    """The bank rows (speed, heading) of the best models for one full regular window
    ``rel`` (prepared, (3, n + 1)), from the regular-grid cache."""
    return int(np.argmax(cache[0].lml_z(rel[1]))), int(np.argmax(cache[1].lml_z(rel[2])))


def regular_indices(rels: np.ndarray, cache: tuple[RegularSlopeBank, ...]
                    ) -> tuple[list[int], list[int]]:
    """:func:`regular_index` of many full regular windows (``rels`` (B, 3, n + 1)), their
    scores :meth:`RegularSlopeBank.lml_z` computed for all at once."""
    best = []
    for series, bank in ((1, cache[0]), (2, cache[1])):
        m, k, _ = bank.Kinv.shape
        z = rels[:, series]  # (B, k)
        q = np.einsum("bmk,bk->bm", (z @ bank.Kinv.reshape(m * k, k).T).reshape(-1, m, k), z)
        best.append(np.argmax(-0.5 * q + bank.const, axis=1).tolist())
    return best[0], best[1]


def bank_indices(rels: np.ndarray, shared: BankCache) -> tuple[list[int], list[int]]:
    """The bank rows (speed, heading) of the best models for windows ``rels`` (B, 3,
    n + 1) of one length, by :func:`~.gpstack.lml_stack`: at most :data:`SELECT_CHUNK`
    at once."""
    m = shared.m
    lml = lml_stack(rels[:, 0, :-1], rels[:, 1:], shared.consts, m, shared.thetas)
    return np.argmax(lml[:, :m], axis=1).tolist(), np.argmax(lml[:, m:], axis=1).tolist()


def _select_regular(items: list[tuple[WindowState, np.ndarray, tuple]]) -> None:
    """:func:`own_selection` of regular windows of one length, ``(state, prepared window,
    cache)`` (one bank and configuration: one cache serves all), by
    :func:`regular_indices`."""
    shared, cache = items[0][0].shared, items[0][2]
    best_s, best_h = regular_indices(stack([rel for _, rel, _ in items]), cache)
    for (s, _, _), i, j in zip(items, best_s, best_h, strict=True):
        s.selection = Selection(s.bank.speed[i], s.bank.heading[j], (i, j), shared.pair(i, j))


def _by_length(items: list) -> list[list]:
    """``items`` (``(state, prepared window, ...)``) grouped by window length, in the
    order of each length's first item."""
    groups: dict[int, list] = {}
    for item in items:
        groups.setdefault(item[1].shape[1], []).append(item)
    return list(groups.values())


#: Windows per stacked call: bounds the work arrays (a selection's exponentials are
#: 120 kB per window).
SELECT_CHUNK = 16


def select_batch(states: list[WindowState], rels: list[np.ndarray],
                 caches: list[tuple[RegularSlopeBank, ...] | None]) -> None:
    """Select bank models for these windows, θ* = argmax over the bank of
    :func:`~.gpstack.lml_stack` per series (paper eq. "eq-,odelselection"), the windows of
    one length stacked: the same choice as :func:`select`."""
    todo = []
    regular: list[tuple[WindowState, np.ndarray, tuple]] = []
    c = states[0].config if states else None
    batch_regular = c is not None and c.slopes and c.select_with_slopes
    for s, rel, cache in zip(states, rels, caches, strict=True):
        s.stats["selections"] += 1
        s.since_selection = 0
        if batch_regular and cache is not None and not s.online_speed:
            regular.append((s, rel, cache))  # own_selection's cached case, for all at once
            continue
        sel = own_selection(s, rel, cache)
        if sel is None:
            todo.append((s, rel))
        else:
            s.selection = sel
    for same in _by_length(regular):  # one cache per window length
        if len(same) == 1:
            s, rel, cache = same[0]
            s.selection = own_selection(s, rel, cache)
        else:
            _select_regular(same)
    for items in _by_length(todo):
        shared = items[0][0].shared
        m = shared.m
        for lo in range(0, len(items), SELECT_CHUNK):
            chunk = items[lo:lo + SELECT_CHUNK]
            best_s, best_h = bank_indices(stack([r for _, r in chunk]), shared)
            for (s, _), i, j in zip(chunk, best_s, best_h, strict=True):
                s.selection = Selection(shared.thetas[i], shared.thetas[m + j], (i, j),
                                        shared.pair(i, j))
