"""What one CAM step gives: the HV (:class:`HostEstimate`), every confirmed RV as column
arrays with its zones now and predicted (:class:`MapSnapshot`), one RV as plain values
(:class:`RvView`).

Reference paper, section "Context-Aware Target Classification (CA-TC)": the local map
with its classifications, on which the safety applications (:mod:`catc.apps`) run.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from catc.classify import HostPath, ZoneArrays

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class HostEstimate:
    """The HV at a tick: pose and motion in the run's ENU frame, and its path."""

    t: float
    x: float
    y: float
    lat: float
    lon: float
    speed: float
    heading: float
    accel: float
    yaw_rate: float
    length: float
    width: float
    radius_m: float  # signed radius of the predicted path (inf = straight)
    path: HostPath  # the path the current positions are classified against
    predicted_path: HostPath  # the HV's predicted pose at t + horizon


@dataclass(frozen=True, slots=True)
class RvView:
    """One RV of a :class:`MapSnapshot`, as plain values (for logs, tests and captures)."""

    temp_id: int
    x: float
    y: float
    speed: float
    heading: float
    accel: float
    var_x: float
    var_y: float
    source: str
    age: float
    fresh: bool
    lane: int
    zone: object  # catc.classify.Zone
    predicted_x: float
    predicted_y: float
    predicted_zone: object  # catc.classify.Zone
    hard_braking: bool
    length: float
    width: float
    verified: bool = True


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """The CAM after one step: the HV, every tracked RV (column arrays, one row per RV in
    the map's order), classifications, warnings and counters.

    Columns: ``ids`` (TemporaryID), ``x, y`` (m), ``speed`` (m/s), ``heading`` (deg),
    ``accel`` (m/s², from the RV's last BSM), ``var_x, var_y`` (m², NaN for models
    without uncertainty), ``source`` (what produced the estimate: ``bsm``, ``gp``, ``ca``,
    ...), ``age`` (s since the last BSM was generated), ``fresh`` (a BSM was applied in
    this step), ``lane`` (lane offset, positive right), ``zone`` / ``predicted_zone``
    (:class:`catc.classify.ZoneArrays`), ``pred_x, pred_y, pred_heading, pred_speed`` (at
    ``t + horizon_s``), ``hard_braking``, ``length, width`` (m), ``on_trail``,
    ``verified`` (the RV's latest accepted BSM was verified, or verification is not
    deferred: see ``ContextAwareMap.step``; the applications see only verified rows).
    """

    t: float
    horizon_s: float
    host: HostEstimate
    ids: npt.NDArray[np.int64]
    x: Array
    y: Array
    speed: Array
    heading: Array
    accel: Array
    var_x: Array
    var_y: Array
    source: tuple[str, ...]
    age: Array
    fresh: npt.NDArray[np.bool_]
    lane: npt.NDArray[np.int64]
    zone: ZoneArrays
    pred_x: Array
    pred_y: Array
    pred_heading: Array
    pred_speed: Array
    predicted_zone: ZoneArrays
    hard_braking: npt.NDArray[np.bool_]
    length: Array
    width: Array
    #: The RV's offsets were measured along its own trail (lane estimation).
    on_trail: npt.NDArray[np.bool_]
    #: The RV's latest accepted BSM was verified (False: deferred, not verified yet).
    verified: npt.NDArray[np.bool_]
    counters: Mapping[str, int]
    #: Per-tick warning conditions: (app, rv_id) pairs whose condition holds now.
    warnings: tuple[tuple[str, int], ...] = ()
    #: Start/end events raised in this step (:class:`catc.apps.events.AppEvent`).
    events: tuple = ()

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, temp_id: int) -> int:
        """Row of RV ``temp_id`` (``KeyError`` when it is not tracked)."""
        hits = np.flatnonzero(self.ids == temp_id)
        if not len(hits):
            raise KeyError(temp_id)
        return int(hits[0])

    def rv(self, i: int) -> RvView:
        """Row ``i`` as an :class:`RvView`."""
        return RvView(int(self.ids[i]), float(self.x[i]), float(self.y[i]),
                      float(self.speed[i]), float(self.heading[i]), float(self.accel[i]),
                      float(self.var_x[i]), float(self.var_y[i]), self.source[i],
                      float(self.age[i]), bool(self.fresh[i]), int(self.lane[i]),
                      self.zone.zone(i), float(self.pred_x[i]), float(self.pred_y[i]),
                      self.predicted_zone.zone(i), bool(self.hard_braking[i]),
                      float(self.length[i]), float(self.width[i]), bool(self.verified[i]))

    def __iter__(self) -> Iterator[RvView]:
        return (self.rv(i) for i in range(len(self)))



def snapshot_of(**values) -> MapSnapshot:
    """``MapSnapshot(**values)`` with every field given, without the frozen dataclass's
    ``__init__`` (one ``object.__setattr__`` per field, a measurable part of a tick with
    a few RVs): MapSnapshot has no ``__post_init__`` and no ``init=False`` field, so an
    instance whose ``__dict__`` holds the fields is the one ``__init__`` would build."""
    snap = object.__new__(MapSnapshot)
    snap.__dict__.update(values)
    return snap


#: The per-row fields of a MapSnapshot (sliced by :func:`rows_of`).
_ROW_FIELDS = ("ids", "x", "y", "speed", "heading", "accel", "var_x", "var_y", "age", "fresh",
               "lane", "pred_x", "pred_y", "pred_heading", "pred_speed", "hard_braking",
               "length", "width", "on_trail", "verified")


def rows_of(snap: MapSnapshot, mask: npt.NDArray[np.bool_]) -> MapSnapshot:
    """The snapshot with only the rows where ``mask`` is True (the HV, counters, warnings
    and events as they are): what the applications see when some rows are unverified."""
    idx = np.flatnonzero(mask)
    values = dict(snap.__dict__)
    for name in _ROW_FIELDS:
        values[name] = values[name][idx]
    values["source"] = tuple(snap.source[i] for i in idx.tolist())
    for name in ("zone", "predicted_zone"):
        z = values[name]
        values[name] = type(z)(*(getattr(z, f)[idx] for f in z.__dataclass_fields__))
    return snapshot_of(**values)


def with_apps(snap: MapSnapshot, warnings: tuple, events: tuple) -> MapSnapshot:
    """The snapshot with the applications' output (a copy: snapshots are immutable), as
    ``dataclasses.replace`` would make it (see :func:`snapshot_of`)."""
    return snapshot_of(**{**snap.__dict__, "warnings": warnings, "events": events})
