"""One cell of a sweep: a trip through the RVE's channel into the CA-TC, scored (no I/O).

A sweep (``captures sweep``) is a grid of *cells* (PER × transmission rate, optionally a
burst length) × predictors × trips × seeds.  Each run of the grid is this module's
:func:`run_cell`: the offline simulator of :mod:`catc.replay` (the RVE's send plan from
:mod:`catc.channel`, the OBU's tick rule, the values as a receiver decodes them) drives a
:class:`catc.cam.ContextAwareMap` with the predictor under test and the FCW application,
and the result is scored exactly as ``captures score`` scores a live capture:

* **PTE**: at every tick, for every tracked RV, the 2-D distance between the CAM's
  estimate and the RV's true position at the tick's time (docs/architecture.md, "Metrics").
* **FCW accuracy**: at every tick, the vehicles an FCW warns on against those the FCW on
  the true states warns on (PER 0, 10 Hz, every message delivered; :func:`truth_fcw`),
  vehicle by vehicle (:mod:`catc.apps.verdict`).

The host is the trip's ``default_host`` (OpenACC: the last car of the platoon; NGSIM: the
follower), every other vehicle is an RV.  Every predictor sees the same loss pattern: the
plan is a function of ``(seed, trip, vehicle, message index)`` only.

A :class:`CellResult` keeps every PTE sample (float32), so results of many trips and
seeds pool into exact percentiles (:func:`pool`) whatever the order or the machine they
were computed on.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from catc.apps.verdict import KEYS, Confusion, by_app
from catc.channel import ChannelConfig
from catc.mobility import MobilityTable, Track

__all__ = ["PTE_THRESHOLDS", "Cell", "CellResult", "Row", "cells", "pool", "run_cell",
           "truth_fcw"]

#: PTE thresholds (m) of the paper's threshold-exceedance grid (0.2 to 1.6 m).
PTE_THRESHOLDS = (0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6)


@dataclass(frozen=True, order=True)
class Cell:
    """One channel setting of the grid: PER (fraction), transmission rate (Hz), mean burst
    length (1 = independent losses)."""

    per: float
    rate_hz: float = 10.0
    burst: float = 1.0

    def channel(self) -> ChannelConfig:
        return ChannelConfig(per=self.per, rate_hz=self.rate_hz, burst=self.burst)

    @property
    def label(self) -> str:
        text = f"PER {100 * self.per:g}% @ {self.rate_hz:g} Hz"
        return text if self.burst == 1.0 else f"{text}, burst {self.burst:g}"


def cells(pers: Sequence[float], rates: Sequence[float], *, grid: str = "paper",
          burst: float = 1.0) -> list[Cell]:
    """The cells of a sweep.  ``pers`` are fractions.

    ``grid="paper"``: the paper's two sweeps, PER against Rate: every PER at the highest
    rate, and every rate at the lowest PER (docs/architecture.md, "Paper parameters").
    ``grid="cross"``: every (PER, rate) pair.
    """
    if not pers or not rates:
        raise ValueError("a sweep needs at least one PER and one rate")
    for p in pers:
        if not 0.0 <= p < 1.0:
            raise ValueError(f"PER {100 * p:g}% outside [0, 100)")
    for r in rates:
        if not 0.0 < r <= 10.0:
            raise ValueError(f"rate {r:g} Hz outside (0, 10]")
    if grid == "cross":
        out = [Cell(p, r, burst) for p in pers for r in rates]
    elif grid == "paper":
        out = [Cell(p, max(rates), burst) for p in pers]
        out += [Cell(min(pers), r, burst) for r in rates]
    else:
        raise ValueError(f"unknown grid {grid!r}; known: paper, cross")
    return sorted(set(out))


@dataclass(eq=False)
class CellResult:
    """What one (trip, predictor, cell, seed) run measured."""

    trip: str
    predictor: str
    cell: Cell
    seed: int
    pte: np.ndarray  # float32, every (tick, tracked RV)
    fcw: dict[str, int]  # tp, tn, fp, fn over the host's ticks
    sent: int  # RV messages the channel delivered
    dropped: int  # RV messages the channel lost
    ticks: int
    fcw_events: int  # FCW warning events started


def _host(table: MobilityTable) -> str:
    if table.default_host is None or table.default_host not in table.tracks:
        raise ValueError(f"trip {table.name!r} has no default host; a sweep needs one")
    return table.default_host


def _cam(predictor: str, table: MobilityTable,
         origin: tuple[float, float, float] | None = None):
    from catc.apps import AppsConfig, SafetyApps
    from catc.cam import CamConfig, ContextAwareMap

    return ContextAwareMap(CamConfig(predictor=predictor, origin=origin or table.origin),
                           SafetyApps(AppsConfig(enabled=("fcw",))))


def truth_fcw(table: MobilityTable) -> list[frozenset[int]]:
    """The vehicles (TemporaryIDs) an FCW warns on at each host tick on the true states:
    every message at 10 Hz delivered (values through UPER), the CA predictor (each tick
    has a fresh BSM, so the predictor does not matter).  The definition ``captures score``
    uses; a tick warns when its set is not empty."""
    from catc.replay import plan, simulate

    the_plan = plan(table, ChannelConfig(), 0, _host(table))
    return [frozenset(w.rv_id for w in snap.warnings if w.app == "fcw")
            for snap in simulate(the_plan, _cam("ca", table))]


def fcw_scene(table: MobilityTable) -> MobilityTable:
    """The host and the vehicle ahead of it (the one before it in the table's order, which
    is leader first), under the trip's name so that the channel draws the same losses as
    for the whole trip.  What the FCW is scored on in a sweep: its target is the vehicle
    ahead, and the CA-TC's per-tick cost grows with every RV of a platoon."""
    from dataclasses import replace

    host = _host(table)
    lead = vehicle_ahead(table, host)
    if lead is None:
        raise ValueError(f"trip {table.name!r}: the host {host!r} has no vehicle ahead")
    return replace(table, tracks={lead: table.tracks[lead], host: table.tracks[host]})


def vehicle_ahead(table: MobilityTable, host: str, reach_m: float = 150.0,
                  half_lane_m: float = 2.5) -> str | None:
    """The vehicle ahead of ``host``: at each of the host's samples, the nearest vehicle
    in its lane ahead (within ``reach_m`` along the host's heading, ``half_lane_m``
    across) gets a vote, and the most votes win.  None when no vehicle is ever there
    and the host is first in the table's order; else the one before it in that order
    (leader first, as the two-vehicle trips of OpenACC and NGSIM are)."""
    h = table.tracks[host]
    rad = np.radians(h.heading)
    sin_h, cos_h = np.sin(rad), np.cos(rad)
    best = np.full(len(h.t), np.inf)
    who = np.full(len(h.t), -1)
    names = list(table.tracks)
    for j, vid in enumerate(names):
        if vid == host:
            continue
        tr = table.tracks[vid]
        inside = (h.t >= tr.t[0]) & (h.t <= tr.t[-1])
        if not inside.any():
            continue
        dx = np.interp(h.t, tr.t, tr.x) - h.x
        dy = np.interp(h.t, tr.t, tr.y) - h.y
        along = dx * sin_h + dy * cos_h
        across = dx * cos_h - dy * sin_h
        near = inside & (along > 0.0) & (along < reach_m) & (np.abs(across) < half_lane_m) \
            & (along < best)
        best[near] = along[near]
        who[near] = j
    votes = np.bincount(who[who >= 0], minlength=len(names))
    if votes.any():
        return names[int(np.argmax(votes))]
    k = names.index(host)
    return names[k - 1] if k > 0 else None


def received_mask(track_t: np.ndarray, cell: Cell, seed: int, key: str) -> np.ndarray:
    """Which 10 Hz samples of a vehicle reach the receiver: :func:`catc.channel.schedule`
    (rate subsampling, then loss), keyed like :func:`catc.replay.plan` (``TRIP/VEHICLE``),
    so the track engine and the CA-TC see the same losses."""
    from catc.channel import schedule

    sch = schedule(cell.channel(), seed, key, track_t)
    out = np.zeros(len(track_t), dtype=bool)
    out[sch["index"][~sch["dropped"]]] = True
    return out


def track_errors(table: MobilityTable, predictor: str, cell: Cell, seed: int
                 ) -> tuple[np.ndarray, int, int]:
    """PTE at every 10 Hz tick of every vehicle of ``table`` (each one an RV predicted on
    its own, as in the paper's trip-by-trip evaluation), with (sent, dropped) counts.
    Ticks before a vehicle's first received message are not scored."""
    errors, sent, dropped = lockstep_errors(
        [(f"{table.name}/{vid}", tr) for vid, tr in table.tracks.items()], predictor, cell,
        seed)
    return np.concatenate(errors) if errors else np.zeros(0, np.float32), sent, dropped


def lockstep_errors(tracks: Sequence[tuple[str, Track]], predictor: str, cell: Cell,
                    seed: int) -> tuple[list[np.ndarray], int, int]:
    """:func:`track_errors` for many vehicles at once, each with its own predictor and its
    channel key (``TRIP/VEHICLE``): they advance in lockstep, sample by sample, so the HGP
    family and the neural baselines forecast stacked (:func:`catc.predict.prepare_at`), as
    the OBU does; the result is the one-by-one replay's to round-off
    (:func:`catc.evaluate.replay_track` is the readable form).  Returns the scored PTEs of
    each vehicle (float32) and the (sent, dropped) counts."""
    from catc.channel import sent_indices
    from catc.evaluate import observations
    from catc.predict import STACKED, make_predictor, prepare_at

    models = [make_predictor(predictor) for _ in tracks]
    obs = [observations(tr) for _, tr in tracks]
    rx = [received_mask(tr.t, cell, seed, key).tolist() for key, tr in tracks]
    sent = sum(sum(r) for r in rx)
    dropped = sum(len(sent_indices(len(tr), cell.rate_hz)) for _, tr in tracks) - sent
    errs = [np.full(len(o), np.nan) for o in obs]
    started = [False] * len(tracks)
    lengths = [len(o) for o in obs]
    stacked = predictor in STACKED
    for k in range(max(lengths, default=0)):
        live = [i for i, n in enumerate(lengths) if k < n]
        for i in live:
            if rx[i][k]:
                models[i].update(obs[i][k])
                started[i] = True
        live = [i for i in live if started[i]]
        if stacked:
            prepare_at([(models[i], obs[i][k].t) for i in live])
        for i in live:
            o = obs[i][k]
            p = models[i].predict(o.t)
            errs[i][k] = math.hypot(p.x - o.x, p.y - o.y)
    return [e[~np.isnan(e)].astype(np.float32) for e in errs], sent, dropped


def cam_run(table: MobilityTable, predictor: str, cell: Cell, seed: int,
            truth: Sequence[frozenset[int]] | None = None, *, wire: bool = True,
            pte: bool = True, origin: tuple[float, float, float] | None = None,
            positions: dict[tuple[float, int], tuple[float, float]] | None = None
            ) -> CellResult:
    """Run ``table`` through ``cell``'s channel into the CA-TC with ``predictor`` and score
    it as ``captures score`` scores a live capture: PTE of every tracked RV at every tick,
    FCW per tick against ``truth`` (:func:`truth_fcw` of the table, computed when None).

    ``wire``: BSM values through UPER encode/decode, as a live OBU receives them.
    ``pte``: False leaves the PTE out (an empty array), for runs scored on the FCW only.
    ``origin``: the CAM's ENU origin (default the table's); a live OBU's, to compare
    its estimates with these.  ``positions``: a dict filled with every tick's estimates,
    ``{(tick time rounded to 1 ms, TemporaryID): (x, y)}``, as ``obu.tracks.jsonl`` has them.
    """
    from catc.replay import plan, simulate, temp_id

    host_id = _host(table)
    if truth is None:
        truth = truth_fcw(table)
    the_plan = plan(table, cell.channel(), seed, host_id)
    ev = the_plan.events
    rv = ~ev["host"]
    sent = int((rv & ~ev["dropped"]).sum())
    dropped = int((rv & ev["dropped"]).sum())
    host_t = table.tracks[host_id].t
    cam = _cam(predictor, table, origin)
    # truth in the CAM's frame, as `captures score` moves it (positions from lat/lon)
    truth_tracks = {}
    for v in the_plan.vehicles[1:]:
        tr = table.tracks[v]
        x, y, _ = cam.frame.to_enu(tr.lat, tr.lon, 0.0)
        truth_tracks[temp_id(v)] = (tr.t, np.atleast_1d(x), np.atleast_1d(y))
    errors: list[np.ndarray] = []
    confusion = Confusion(("fcw",))
    events = 0
    k = -1
    for k, snap in enumerate(simulate(the_plan, cam, wire=wire)):
        t = float(host_t[k])  # the tick's dataset time (the snapshot's is on the secMark clock)
        if positions is not None:
            for i, tid in enumerate(snap.ids.tolist()):
                positions[(round(snap.t, 3), tid)] = (float(snap.x[i]), float(snap.y[i]))
        if pte and len(snap):
            keep, ex, ey = [], [], []
            for i, tid in enumerate(snap.ids.tolist()):
                tt = truth_tracks.get(tid)
                if tt is None or not tt[0][0] - 1e-6 <= t <= tt[0][-1] + 1e-6:
                    continue
                keep.append(i)
                ex.append(np.interp(t, tt[0], tt[1]))
                ey.append(np.interp(t, tt[0], tt[2]))
            if keep:
                errors.append(np.hypot(snap.x[keep] - np.array(ex), snap.y[keep] - np.array(ey)))
        events += sum(1 for e in snap.events if e.app == "fcw" and e.kind == "start")
        if k < len(truth):  # vehicle by vehicle, as captures score counts
            confusion.add({"fcw": truth[k]}, by_app((w.app, w.rv_id) for w in snap.warnings))
    pte = np.concatenate(errors).astype(np.float32) if errors else np.zeros(0, np.float32)
    return CellResult(table.name, predictor, cell, seed, pte, confusion.counts["fcw"], sent,
                      dropped, k + 1, events)


def run_cell(table: MobilityTable, predictor: str, cell: Cell, seed: int,
             truth: Sequence[frozenset[int]] | None = None, *, fcw: bool = True) -> CellResult:
    """One sweep run: PTE from :func:`track_errors` (every vehicle of the trip), FCW from
    :func:`cam_run` on the :func:`fcw_scene` (skipped when ``fcw`` is False).  ``truth``:
    :func:`truth_fcw` of the scene."""
    pte, sent, dropped = track_errors(table, predictor, cell, seed)
    conf = dict.fromkeys(KEYS, 0)
    ticks = events = 0
    if fcw:
        scene = fcw_scene(table)
        r = cam_run(scene, predictor, cell, seed, truth, wire=False, pte=False)
        conf, ticks, events = r.fcw, r.ticks, r.fcw_events
    return CellResult(table.name, predictor, cell, seed, pte, conf, sent, dropped, ticks,
                      events)


@dataclass
class Row:
    """One row of a sweep's table: a (dataset, predictor, cell) pooled over trips and seeds.

    The contract's keys (docs/architecture.md: ``dataset, predictor, per, rate, pte95_m,
    fcw_accuracy, n_ticks``) plus what the report needs."""

    dataset: str
    predictor: str
    per: float  # %
    rate: float  # Hz
    burst: float
    pte95_m: float | None
    pte_mean_m: float | None
    fcw_accuracy: float | None
    n_ticks: int  # PTE samples: (tick, tracked RV) pairs
    host_ticks: int
    fcw: dict[str, int]
    exceedances: dict[str, int]  # PTE_th (m, as text) -> samples with PTE > PTE_th
    sent: int
    dropped: int
    fcw_events: int
    trips: int
    seeds: list[int] = field(default_factory=list)

    def as_dict(self) -> dict:
        from dataclasses import asdict

        return asdict(self)


def pool(dataset: str, results: Iterable[CellResult], trips: int | None = None) -> Row:
    """One row from the results of one (dataset, predictor, cell) over trips and seeds.

    A result may be a part: PTE of a group of trips with zero FCW counts, or the FCW of a
    trip with no PTE; parts add up.  ``trips``: how many trips the row covers (default:
    the distinct ``trip`` names of the results)."""
    results = list(results)
    if not results:
        raise ValueError("nothing to pool")
    first = results[0]
    if any(r.predictor != first.predictor or r.cell != first.cell for r in results):
        raise ValueError("pool() takes the results of one predictor and one cell")
    # Sort for a result independent of completion order (percentiles are anyway).
    results.sort(key=lambda r: (r.trip, r.seed))
    e = np.concatenate([r.pte for r in results]).astype(np.float64)
    conf = {k: sum(r.fcw[k] for r in results) for k in KEYS}
    total = sum(conf.values())
    return Row(
        dataset=dataset, predictor=first.predictor, per=round(100 * first.cell.per, 6),
        rate=first.cell.rate_hz, burst=first.cell.burst,
        pte95_m=round(float(np.percentile(e, 95)), 4) if len(e) else None,
        pte_mean_m=round(float(e.mean()), 4) if len(e) else None,
        fcw_accuracy=round((conf["tp"] + conf["tn"]) / total, 5) if total else None,
        n_ticks=len(e), host_ticks=sum(r.ticks for r in results), fcw=conf,
        exceedances={f"{th:g}": int((e > th).sum()) for th in PTE_THRESHOLDS},
        sent=sum(r.sent for r in results), dropped=sum(r.dropped for r in results),
        fcw_events=sum(r.fcw_events for r in results),
        trips=len({r.trip for r in results}) if trips is None else trips,
        seeds=sorted({r.seed for r in results}))
