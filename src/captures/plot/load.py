"""A capture directory read for plotting: :func:`load_run` reads it through the one capture
reader (:func:`hil.capture.read_capture`) and puts every time on the OBU's clock
(:func:`hil.capture.clock_offset`) and every true position in the OBU's ENU frame
(:func:`hil.capture.truth_in_frame`); :func:`auto_times` picks the ticks worth a picture.

The records read are those :mod:`hil.capture.schema` builds: the RVE's true samples
(:func:`~hil.capture.schema.truth`) and scheduled messages
(:func:`~hil.capture.schema.scheduled`), the OBU's ticks (:func:`~hil.capture.schema.tick`),
track rows (:func:`~hil.capture.schema.track_rows`) and warning events
(:func:`~hil.capture.schema.event`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from captures.plot.style import PALETTE
from catc.cam import CamConfig
from hil.capture import clock_offset, read_capture, truth_in_frame

__all__ = ["Run", "Truth", "auto_times", "load_run"]


@dataclass
class Truth:
    """One vehicle's true track in the OBU's frame and clock."""

    name: str
    t: np.ndarray  # OBU clock (s)
    x: np.ndarray  # ENU m in the OBU's frame
    y: np.ndarray
    heading: np.ndarray  # deg clockwise from north, unwrapped (continuous)
    speed: np.ndarray
    yaw_rate: np.ndarray  # deg/s, positive clockwise

    def at(self, t: float) -> tuple[float, float, float, float, float] | None:
        """``(x, y, heading, speed, yaw_rate)`` interpolated at ``t``; None outside."""
        if t < self.t[0] - 1e-6 or t > self.t[-1] + 1e-6:
            return None
        return tuple(float(np.interp(t, self.t, a)) for a in  # type: ignore[return-value]
                     (self.x, self.y, self.heading, self.speed, self.yaw_rate))


@dataclass
class Run:
    """A capture directory read for plotting; every time on the OBU's clock.

    ``tracks`` holds the columns of the OBU's track rows
    (:func:`hil.capture.schema.track_rows`; one entry per row, ordered by tick), plus
    ``pte`` (m, NaN where the truth does not cover the row, exactly the samples of
    :func:`captures.score.score`), ``pred_x, pred_y`` (NaN when the capture has no
    predicted positions) and ``gap_start`` (the row of the same RV's last fresh BSM at or
    before the row, -1 if none).  Rows of tick ``i`` are ``tick_rows[i]:tick_rows[i + 1]``.
    """

    directory: Path
    dataset: str
    predictor: str
    per: float  # fraction
    rate_hz: float
    host_id: str
    names: dict[str, str]  # temp id (hex) -> vehicle name
    offset: float  # OBU clock - dataset time (s)
    w_lane: float
    horizon_s: float
    tick_t: np.ndarray
    tick_host: np.ndarray  # (n, 2) the OBU's HV position
    tick_host_speed: np.ndarray
    tick_warnings: list[list]
    tick_rows: np.ndarray
    tracks: dict[str, np.ndarray]
    truth: dict[str, Truth]  # temp id -> track, the HV included
    events: list[dict]  # the OBU's warning events (hil.capture.schema.event)
    spans: list[tuple[str, str, float, float]]  # (app, rv id, start, end) on the OBU clock
    sched_t: np.ndarray  # RV messages the RVE scheduled, OBU clock
    sched_id: np.ndarray
    sched_dropped: np.ndarray
    colours: dict[str, str] = field(default_factory=dict)  # temp id -> colour

    def name(self, tid: str) -> str:
        return self.names.get(tid, tid)

    def pte_samples(self) -> np.ndarray:
        """Every PTE sample (m), pooled: ``np.percentile(.., 95)`` is score's pte95_m."""
        p = self.tracks["pte"]
        return p[~np.isnan(p)]

    def tick_index(self, t: float) -> int:
        """The tick nearest ``t``."""
        return int(np.argmin(np.abs(self.tick_t - t)))

    def rv_ids(self) -> list[str]:
        """RV ids of the truth, by vehicle name."""
        return sorted((k for k in self.truth if k != self.host_id), key=self.name)


def _truth(truth_rows: list[dict], origin, offset: float, names: dict[str, str]
           ) -> dict[str, Truth]:
    out = {}
    for tid, (rows, t, x, y) in truth_in_frame(truth_rows, origin).items():
        heading = np.degrees(np.unwrap(np.radians([r["heading"] for r in rows])))
        out[tid] = Truth(names.get(tid, rows[0].get("vehicle", tid)), t + offset, x, y,
                         heading, np.array([r["speed"] for r in rows]),
                         np.array([r.get("yaw_rate", 0.0) for r in rows]))
    return out


def _columns(rows: list[dict]) -> dict[str, np.ndarray]:
    def col(key, dtype=float):
        return np.array([r[key] for r in rows], dtype=dtype)

    def pred(*keys):
        for k in keys:
            if rows and k in rows[0]:
                return np.array([np.nan if r.get(k) is None else r[k] for r in rows], float)
        return np.full(len(rows), np.nan)

    z = np.array([r["zone"] for r in rows], dtype=int).reshape(-1, 3)
    pz = np.array([r["predicted_zone"] for r in rows], dtype=int).reshape(-1, 3)
    return {"t": col("t"), "id": col("id", object), "x": col("x"), "y": col("y"),
            "speed": col("speed"), "heading": col("heading"), "source": col("source", object),
            "age": col("age"), "fresh": col("fresh", bool), "lane": col("lane", int),
            "ahead": z[:, 0].astype(bool), "lateral": z[:, 1], "direction": z[:, 2],
            "s": col("s"), "d": col("d"), "p_ahead": pz[:, 0].astype(bool),
            "p_lateral": pz[:, 1], "p_direction": pz[:, 2],
            "pred_x": pred("predicted_x", "pred_x"), "pred_y": pred("predicted_y", "pred_y")}


def _pte_and_gaps(tracks: dict[str, np.ndarray], truth: dict[str, Truth], offset: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per track row: the PTE (m; the join of :mod:`captures.score`, same arithmetic, one
    RV at a time) and the row of the RV's last fresh BSM (-1 if none)."""
    pte = np.full(len(tracks["t"]), np.nan)
    gap_start = np.full(len(tracks["t"]), -1, dtype=int)
    ids = tracks["id"]
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        fresh_rows = np.where(tracks["fresh"][rows], rows, -1)
        gap_start[rows] = np.maximum.accumulate(fresh_rows)
        tr = truth.get(tid)
        if tr is None:
            continue  # not a vehicle of this run (garbage that got a track)
        td = tracks["t"][rows] - offset
        t0 = tr.t - offset
        ok = (td >= t0[0] - 1e-6) & (td <= t0[-1] + 1e-6)
        rows, td = rows[ok], td[ok]
        pte[rows] = np.hypot(tracks["x"][rows] - np.interp(td, t0, tr.x),
                             tracks["y"][rows] - np.interp(td, t0, tr.y))
    return pte, gap_start


def _spans(events: list[dict], end_t: float) -> list[tuple[str, str, float, float]]:
    """(app, rv, start, end) of every warning; one still open at the end ends there."""
    open_: dict[tuple[str, str, float], float] = {}
    spans = []
    for e in events:
        key = (e["app"], e["rv"], e["t_start"])
        if e["kind"] == "start":
            open_[key] = e["t"]
        elif e["kind"] == "end":
            spans.append((e["app"], e["rv"], e["t_start"], e["t"]))
            open_.pop(key, None)
    spans += [(app, rv, start, max(start, end_t)) for (app, rv, start) in open_]
    return sorted(spans, key=lambda s: (s[2], s[0], s[1]))


def load_run(directory: Path | str) -> Run:
    """Read a capture directory (:class:`hil.capture.CaptureError` when it cannot be)."""
    cap = read_capture(Path(directory), rx=False)
    rve_cfg, obu_cfg = cap.rve_config, cap.obu_config
    names = {tid: v for v, tid in rve_cfg["vehicles"].items()}
    host_id = rve_cfg["vehicles"].get(rve_cfg.get("host"), "")
    offset = clock_offset(cap.truth, cap.ticks, cap.directory)
    truth = _truth(cap.truth, obu_cfg["origin"], offset, names)
    if not host_id:
        host_id = next((r["id"] for r in cap.truth if r["host"]), "")

    cap.tracks.sort(key=lambda r: r["t"])  # stable: rows of a tick stay in map order
    tracks = _columns(cap.tracks)
    tick_t = np.array([tk["t"] for tk in cap.ticks])
    tick_rows = np.searchsorted(tracks["t"], np.append(tick_t, np.inf) - 1e-6)
    tracks["pte"], tracks["gap_start"] = _pte_and_gaps(tracks, truth, offset)

    rv_sched = [r for r in cap.schedule if r["channel"] == "rv"]
    cam = CamConfig()
    out = Run(
        directory=cap.directory, dataset=rve_cfg.get("dataset", {}).get("name", "?"),
        predictor=str(obu_cfg.get("settings", {}).get("predictor")),
        per=float(rve_cfg.get("channel", {}).get("per", math.nan)),
        rate_hz=float(rve_cfg.get("channel", {}).get("rate_hz", math.nan)),
        host_id=host_id, names=names, offset=offset, w_lane=cam.classify.w_lane,
        horizon_s=cam.horizon_s, tick_t=tick_t,
        tick_host=np.array([tk["host"] for tk in cap.ticks], dtype=float).reshape(-1, 2),
        tick_host_speed=np.array([tk.get("host_speed", math.nan) for tk in cap.ticks]),
        tick_warnings=[tk.get("warnings", []) for tk in cap.ticks], tick_rows=tick_rows,
        tracks=tracks, truth=truth, events=cap.events,
        spans=_spans(cap.events, float(tick_t[-1])),
        sched_t=np.array([r["t"] for r in rv_sched], dtype=float) + offset,
        sched_id=np.array([r["id"] for r in rv_sched], dtype=object),
        sched_dropped=np.array([r["dropped"] for r in rv_sched], dtype=bool))
    extra = sorted(set(tracks["id"]) - set(truth))  # tracked but not in the truth
    for i, tid in enumerate([*out.rv_ids(), *extra]):
        out.colours[tid] = PALETTE[i % len(PALETTE)]
    return out


def auto_times(run: Run, most: int = 8) -> list[float]:
    """Interesting tick times: every FCW start, the middle of the run and the tick of the
    largest PTE; at most ``most``, at least 0.5 s apart, sorted."""
    fcw = sorted({round(e["t"], 3) for e in run.events
                  if e["app"] == "fcw" and e["kind"] == "start"})
    t = run.tick_t
    wanted = [*fcw[: max(1, most - 2)], float(t[len(t) // 2])]
    pte = run.tracks["pte"]
    if np.isfinite(pte).any():
        wanted.append(float(run.tracks["t"][int(np.nanargmax(pte))]))
    chosen: list[float] = []
    for w in wanted:
        tt = float(t[run.tick_index(w)])
        if all(abs(tt - c) >= 0.5 for c in chosen):
            chosen.append(tt)
    return sorted(chosen[:most])
