"""SPMD-style BSM CSV (Safety Pilot Model Deployment) -> :class:`~catc.mobility.MobilityTable` s.

Format: the SPMD "BSM" / "DAS1 BsmP1" table, one BSM (Part I) per row, 19 columns
``RxDevice, FileId, TxDevice, Gentime, TxRandom, MsgCount, DSecond, Latitude, Longitude,
Elevation, Speed, Heading, Ax, Ay, Az, Yawrate, PathCount, RadiusOfCurve, Confidence``.
Units, from the data dictionary of the UMTRI connected-vehicle documentation
(github.com/caocscar/ConnectedVehicleDocs, ``BSMdocumentation.md`` and
``BSMRxdocumentation.md``, the SPMD BSM tables): Gentime in microseconds since
2004-01-01 00:00:00 UTC, DSecond in milliseconds within the current minute (the J2735
secMark), Latitude/Longitude in degrees (WGS-84), Elevation in m, Speed in m/s (GPS),
Heading in degrees with 0/90/180/270 = north/east/south/west, Ax/Ay/Az in m/s², Yawrate
in deg/s with "negative/positive values corresponding to left/right turns",
RadiusOfCurve as a curvature in 1/m, Confidence in %.  TxDevice is the static half of the
sender's temporary id; RxDevice is the device that logged the row and FileId numbers its
log files.  A BSM's key is (RxDevice, FileId, TxDevice, Gentime).

**No real SPMD file is available to this project** (nothing under ``../shared/data``):
the reader is tested on a file written from a real OpenACC track in this column format
(a round trip) and on hand-written rows with the quirks below; see tests/test_readers.py.

Choices:

* **Header.**  The UMTRI files "do not have any column headers"; the USDOT/ORNL privacy
  tool for these data (usdot-its-jpo-data-portal/privacy-protection-application,
  ``cv-lib/include/bsmp1.hpp``) requires the header line
  ``RxDevice,FileId,TxDevice,Gentime,...``.  Both are read: a first line whose first cell
  is not a number is the header (columns found by name; TxDevice, Gentime, Latitude and
  Longitude are required, other columns may be missing), otherwise the 19 columns are
  taken in the documented order.
* **Rows.**  An empty cell is a missing value.  A row without TxDevice, Gentime,
  Latitude or Longitude is dropped.  Rows with the same TxDevice and Gentime are one BSM
  (e.g. received by several RxDevices, or logged twice): the first in file order is
  kept, the copies are counted in ``meta["duplicate_rows"]``.  Rows may come in any
  order; they are sorted by Gentime.
* **Trips and tracks.**  A table is one trip of one TxDevice: its BSMs from all RxDevices
  and FileIds together (FileId numbers the *receiver's* logs, so copies of one BSM carry
  different FileIds), split into trips where the sender is silent for more than
  :data:`TRIP_GAP_S` (60 s: SPMD trips are ignition cycles, one log file each, so
  consecutive trips of a vehicle are separated by its parking time, while gaps inside a
  trip are seconds long; UMTRI's trip metadata omits time jumps over 1 s).  Tables are
  named ``NAME:TXDEVICE:K`` (K = 1, 2, ... per TxDevice, in time order) and returned in
  order of their first BSM.  Each has one vehicle, id = TxDevice as written, and
  ``default_host`` None: pair it with a real host, or add a synthetic one with
  :func:`catc.hostsim.with_synthetic_host`.  Inside a trip, gaps longer than
  :data:`MAX_BRIDGE_S` (0.6 s) split the track into pieces ``ID``, ``ID#2``, ...
* **Time.**  t = (Gentime - G0) / 1e6 s, where G0 is the start of the UTC minute of the
  trip's first BSM according to its DSecond (G0 = Gentime - 1000 DSecond), so t modulo
  60 s is the broadcast DSecond (secMark) and a re-broadcast BSM carries the original
  secMark.  Without a DSecond, G0 is Gentime floored to a multiple of 60 s.  DSecond and
  not Gentime fixes the minute phase because the data dictionary does not say whether
  Gentime counts leap seconds (2005, 2008 and 2012 each added one).  G0 is
  ``meta["epoch_gentime_us"]``.
* **Resampling** (:func:`resample`, shared with :mod:`catc.datasets.ode`).  BSM times are
  irregular (jitter, lost messages), so every field is linearly interpolated in time
  onto the 10 Hz grid ``phase + k * 0.1 s``, where the phase is the circular mean of the
  BSM times modulo 0.1 s (``meta["time_offset"]``): BSMs sent on a regular 10 Hz
  schedule land on grid instants and come back unchanged.  Heading is unwrapped before
  interpolation.  Grid instants up to 0.05 s beyond a piece's first or last BSM take
  that BSM's values, so every BSM contributes.  A BSM within 0.05 s of the previous kept
  one of the same vehicle is dropped as a repeat.
* **Fields.**  Speed, Heading, Ax (longitudinal acceleration) and Yawrate are measured;
  a missing cell is interpolated from the neighbouring BSMs (counted in the field's
  provenance).  Yawrate positive = right turn = heading increasing, which is this
  project's convention (deg/s, positive clockwise), so it is taken as is.  A field
  missing in every BSM of a piece is derived as in :mod:`catc.datasets.derive` (speed
  from the positions).  Elevation is passed through as ``elev`` (the dictionary does not
  name its datum).  Ay, Az, PathCount, RadiusOfCurve, Confidence, TxRandom and MsgCount
  are not used.  Length and width are not in the table (NaN).
* The ENU origin is the trip's first BSM (Elevation, or 0 when missing).

Errors: content that cannot be such a table raises :class:`ValueError` with a one-line
message starting ``spmd:``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from catc.datasets import derive
from catc.geo import EnuFrame, wrap_deg_360
from catc.mobility import DT, MobilityTable, Track

__all__ = [
    "BSM_FIELDS",
    "COLUMNS",
    "MAX_BRIDGE_S",
    "TRIP_GAP_S",
    "Resampled",
    "grid_phase",
    "looks_like",
    "parse",
    "resample",
]

Array = npt.NDArray[np.float64]

#: The columns of an SPMD BSM table, in the documented order.
COLUMNS = (
    "RxDevice", "FileId", "TxDevice", "Gentime", "TxRandom", "MsgCount", "DSecond",
    "Latitude", "Longitude", "Elevation", "Speed", "Heading", "Ax", "Ay", "Az", "Yawrate",
    "PathCount", "RadiusOfCurve", "Confidence",
)  # fmt: skip
#: A sender silent for longer than this (s) starts a new trip.
TRIP_GAP_S = 60.0
#: The longest interval between two BSMs bridged by interpolation (s): 0.6 s, as nyc.
MAX_BRIDGE_S = (derive.MAX_GAP + 1) * DT
#: The per-sample fields :func:`resample` takes (NaN = unavailable in that BSM).
BSM_FIELDS = ("lat", "lon", "elev", "speed", "heading", "accel", "yaw_rate")

_REQUIRED = ("TxDevice", "Gentime", "Latitude", "Longitude")
#: Column -> BSM field, for the measured fields this reader uses.
_FIELD_COLUMNS = {
    "lat": "Latitude", "lon": "Longitude", "elev": "Elevation", "speed": "Speed",
    "heading": "Heading", "accel": "Ax", "yaw_rate": "Yawrate",
}  # fmt: skip
_EPS = 1e-6
_PROVENANCE = {
    "t": "measured: Gentime (us since 2004-01-01 UTC) minus the trip's minute epoch "
         "G0 = Gentime - 1000 DSecond of its first BSM, in s",
    "lat": "measured: Latitude (deg WGS-84)",
    "lon": "measured: Longitude (deg WGS-84)",
    "elev": "measured: Elevation as given (datum not stated)",
    "x": "derived: ENU east of lat/lon/elev (catc.geo.EnuFrame at the table origin)",
    "y": "derived: ENU north of lat/lon/elev (catc.geo.EnuFrame at the table origin)",
    "speed": "measured: Speed (GPS, m/s)",
    "heading": "measured: Heading (GPS, deg cw from north)",
    "accel": "measured: Ax (longitudinal, m/s²)",
    "yaw_rate": "measured: Yawrate (deg/s; positive = right turn = clockwise, as here)",
    "length": "unknown: not in the SPMD BSM table",
    "width": "unknown: not in the SPMD BSM table",
}  # fmt: skip


# --- resampling BSMs onto the 10 Hz grid (shared with catc.datasets.ode) ------------------


@dataclass(frozen=True)
class Resampled:
    """The tracks :func:`resample` made of one vehicle's BSMs, and what it dropped."""

    tracks: list[Track]
    repeats: int  # BSMs within DT/2 of the previous kept one


def grid_phase(t: npt.ArrayLike) -> float:
    """The phase in [0, DT) of sample times on a 10 Hz schedule: their circular mean mod DT,
    rounded to the millisecond."""
    angle = 2.0 * np.pi * np.asarray(t, dtype=np.float64) / DT
    mean = math.atan2(float(np.mean(np.sin(angle))), float(np.mean(np.cos(angle))))
    return round((mean / (2.0 * np.pi) * DT) % DT, 3) % DT  # secMark resolution: 1 ms


def _grid(t: Array, phase: float) -> Array:
    """Instants ``phase + k DT`` in [t[0] - DT/2, t[-1] + DT/2)."""
    k_lo = math.ceil((t[0] - phase) / DT - 0.5 - _EPS)
    k_hi = math.ceil((t[-1] - phase) / DT + 0.5 - _EPS) - 1
    return np.round(phase + np.arange(k_lo, k_hi + 1) * DT, 6)


def _speed_from_track(x: Array, y: Array) -> Array:
    """|Savitzky-Golay velocity| of x/y as :mod:`derive` computes it (m/s)."""
    n = len(x)
    window = min(derive.WINDOW, n if n % 2 else n - 1)
    ve, vn = (derive.savgol_derivative(a, window, derive.POLYORDER, DT)
              for a in (x, y))
    return np.hypot(ve, vn)


def _piece(vehicle_id: str, t: Array, cols: dict[str, Array], frame: EnuFrame, phase: float,
           provenance: dict[str, str], size: tuple[float, float]) -> Track:
    """One gap-free piece of BSMs (time order, positions present) as a 10 Hz track."""
    grid = _grid(t, phase)
    prov = dict(provenance)

    def at(field: str) -> Array | None:
        ok = np.isfinite(cols[field])
        if not ok.any():
            return None
        values = cols[field][ok]
        if field == "heading":
            values = np.unwrap(values, period=360.0)
        out = np.interp(grid, t[ok], values)
        if not ok.all():
            prov[field] += f"; unavailable in {np.count_nonzero(~ok)} of {len(ok)} BSMs, " \
                           "interpolated from the others"
        return np.asarray(wrap_deg_360(out)) if field == "heading" else out

    lat, lon, elev = at("lat"), at("lon"), at("elev")
    assert lat is not None and lon is not None  # the callers drop BSMs without a position
    if elev is None:
        elev = np.full_like(grid, np.nan)
        prov["elev"] = "unavailable in every BSM"
    x, y, _ = frame.to_enu(lat, lon, np.where(np.isfinite(elev), elev, frame.h0))
    x, y = np.asarray(x), np.asarray(y)
    short = len(grid) < derive.POLYORDER + 1  # too few samples to differentiate

    def derived(field: str, method: str, compute: Callable[[], Array]) -> Array:
        prov[field] = ("derived: fewer than 3 samples, set to 0" if short
                       else f"{method} (unavailable in every BSM)")
        return np.zeros_like(grid) if short else compute()

    speed = at("speed")
    if speed is None:
        speed = derived("speed", "derived: |Savitzky-Golay velocity| of x/y",
                        lambda: _speed_from_track(x, y))
    heading = at("heading")
    if heading is None:
        heading = derived("heading", derive.HEADING_METHOD,
                          lambda: derive.heading_from_track(x, y, speed))
    accel = at("accel")
    if accel is None:
        accel = derived("accel", derive.ACCEL_METHOD, lambda: derive.accel_from_speed(speed))
    yaw_rate = at("yaw_rate")
    if yaw_rate is None:
        yaw_rate = derived("yaw_rate", derive.YAW_RATE_METHOD,
                           lambda: derive.yaw_rate_from_heading(heading))
    steps = np.diff(t)
    bridged = int(np.count_nonzero(steps > 1.5 * DT))
    prov["t"] += (f"; resampled: linear interpolation onto {phase:.3f} s + k * 0.1 s "
                  "(instants <= 0.05 s beyond the first/last BSM hold it)")
    prov["samples"] = (f"{len(t)} BSMs from {t[0]:.3f} to {t[-1]:.3f} s; gaps "
                       f"(0.15-{MAX_BRIDGE_S:g} s) bridged: {bridged}")
    return Track(
        vehicle_id=vehicle_id, t=grid, x=x, y=y, lat=lat, lon=lon, elev=elev, speed=speed,
        heading=heading, accel=accel, yaw_rate=yaw_rate, length=float(size[0]),
        width=float(size[1]), provenance=prov)


def resample(vehicle_id: str, t: npt.ArrayLike, values: dict[str, npt.ArrayLike],
             frame: EnuFrame, phase: float, provenance: dict[str, str],
             size: tuple[float, float] = (math.nan, math.nan)) -> Resampled:
    """One vehicle's BSMs (any order) -> 10 Hz tracks, split at gaps over MAX_BRIDGE_S.

    ``t`` are the BSM times (s); ``values`` has one array per :data:`BSM_FIELDS` entry
    (NaN = unavailable; lat and lon must be present in every BSM); ``phase`` places the
    grid (:func:`grid_phase`); ``provenance`` describes the measured fields and ``t``;
    ``size`` is (length, width) in m.  See the module doc, "Resampling" and "Fields".
    """
    t = np.asarray(t, dtype=np.float64)
    if t.size == 0:
        raise ValueError(f"vehicle {vehicle_id} has no BSM")
    order = np.argsort(t, kind="stable")
    t = t[order]
    cols = {f: np.asarray(values[f], dtype=np.float64)[order] for f in BSM_FIELDS}
    keep = np.ones(len(t), dtype=bool)
    last = t[0]
    for j in range(1, len(t)):
        keep[j] = t[j] - last > DT / 2
        last = t[j] if keep[j] else last
    t, cols = t[keep], {f: c[keep] for f, c in cols.items()}
    starts = np.r_[0, np.flatnonzero(np.diff(t) > MAX_BRIDGE_S + 1e-3) + 1, len(t)]
    tracks = []
    for k, (a, b) in enumerate(itertools.pairwise(starts)):
        piece_id = vehicle_id if k == 0 else f"{vehicle_id}#{k + 1}"
        piece = {f: c[a:b] for f, c in cols.items()}
        tracks.append(_piece(piece_id, t[a:b], piece, frame, phase, provenance, size))
    return Resampled(tracks, int(np.count_nonzero(~keep)))


# --- the SPMD table -------------------------------------------------------------------------


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def looks_like(text: str) -> bool:
    """Whether text is an SPMD BSM table: its header, or 19 plausible numeric columns."""
    lines = [ln for ln in text.lstrip("\ufeff")[:8192].splitlines()[:6] if ln.strip()]
    if not lines:
        return False
    first = [c.strip() for c in lines[0].split(",")]
    if first[:4] == list(COLUMNS[:4]):
        return True
    for line in lines[:5]:
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != len(COLUMNS) or not all(c == "" or _is_number(c) for c in cells):
            return False
        gentime, dsecond, lat, lon = (float(cells[j] or "nan") for j in (3, 6, 7, 8))
        if not (1e14 < gentime < 1e16 and abs(lat) <= 90 and abs(lon) <= 180):
            return False
        if math.isfinite(dsecond) and not 0 <= dsecond < 61000:
            return False
    return True


def _columns(lines: list[str]) -> tuple[dict[str, int], list[str]]:
    """Column name -> index, and the data lines (the header, if any, removed)."""
    first = [c.strip() for c in lines[0].split(",")]
    if _is_number(first[0]) or first[0] == "":
        return {name: j for j, name in enumerate(COLUMNS)}, lines
    index = {name: j for j, name in enumerate(first)}
    missing = [c for c in _REQUIRED if c not in index]
    if missing:
        raise ValueError(f"spmd: header lacks {', '.join(missing)}")
    return index, lines[1:]


def _cells(lines: list[str], width: int) -> npt.NDArray[np.str_]:
    rows = [(line.split(",") + [""] * width)[:width] for line in lines]
    if not rows:
        raise ValueError("spmd: no data rows")
    return np.char.strip(np.array(rows, dtype=str))


def _numbers(cells: npt.NDArray[np.str_], column: str) -> Array:
    try:
        return np.where(cells == "", "nan", cells).astype(np.float64)
    except ValueError as exc:
        raise ValueError(f"spmd: bad number in column {column} ({exc})") from None


def _epoch_us(gentime: float, dsecond: float) -> float:
    """G0: the start (Gentime, us) of the UTC minute of a BSM (see the module doc, Time)."""
    if math.isfinite(dsecond) and 0 <= dsecond < 60000:
        return gentime - round(dsecond) * 1000.0
    return gentime - gentime % 60e6


def parse(text: str, name: str) -> list[MobilityTable]:
    """Parse the contents of one SPMD BSM CSV: one table per trip (see the module doc)."""
    lines = [ln for ln in text.lstrip("\ufeff").splitlines() if ln.strip()]
    if not lines:
        raise ValueError("spmd: empty file")
    index, lines = _columns(lines)
    cells = _cells(lines, max(index.values()) + 1)

    def column(col: str) -> npt.NDArray[np.str_]:
        return cells[:, index[col]] if col in index else np.full(len(cells), "")

    tx = column("TxDevice")
    numbers = {c: _numbers(column(c), c) for c in ("Gentime", "DSecond", *_FIELD_COLUMNS.values())}
    gentime = numbers["Gentime"]
    usable = (tx != "") & np.isfinite(gentime)
    usable &= np.isfinite(numbers["Latitude"]) & np.isfinite(numbers["Longitude"])
    if not usable.any():
        raise ValueError("spmd: no row has TxDevice, Gentime, Latitude and Longitude")
    # The first copy of each (TxDevice, Gentime) in file order, then time order per sender.
    rows = np.flatnonzero(usable)
    _, codes = np.unique(tx[rows], return_inverse=True)
    pos = np.lexsort((rows, gentime[rows], codes))
    order = rows[pos]
    first = np.r_[True, (np.diff(codes[pos]) != 0) | (np.diff(gentime[order]) != 0)]
    kept = order[first]
    copies = np.zeros(len(cells), dtype=int)
    copies[kept] = np.bincount(np.cumsum(first) - 1) - 1
    ids = {c: column(c) for c in ("RxDevice", "FileId")}

    trips: list[tuple[float, MobilityTable]] = []
    for device in dict.fromkeys(tx[kept]):
        mine = kept[tx[kept] == device]
        breaks = np.flatnonzero(np.diff(gentime[mine]) > TRIP_GAP_S * 1e6) + 1
        for k, trip in enumerate(np.split(mine, breaks), start=1):
            table = _trip(f"{name}:{device}:{k}", str(device), trip, numbers, ids)
            table.meta["duplicate_rows"] = int(copies[trip].sum())
            trips.append((float(gentime[trip[0]]), table))
    return [table for _, table in sorted(trips, key=lambda item: item[0])]


def _trip(table_name: str, device: str, rows: npt.NDArray[np.intp],
          numbers: dict[str, Array], ids: dict[str, npt.NDArray[np.str_]]) -> MobilityTable:
    """The table of one trip: ``rows`` are its BSMs (indices into the data, time order)."""
    epoch = round(_epoch_us(numbers["Gentime"][rows[0]], numbers["DSecond"][rows[0]]))
    t = np.round((numbers["Gentime"][rows] - epoch) / 1e6, 6)
    values = {f: numbers[c][rows] for f, c in _FIELD_COLUMNS.items()}
    h0 = values["elev"][0] if math.isfinite(values["elev"][0]) else 0.0
    frame = EnuFrame(values["lat"][0], values["lon"][0], h0)
    phase = grid_phase(t)
    made = resample(device, t, values, frame, phase, _PROVENANCE)
    return MobilityTable(
        name=table_name,
        kind="spmd",
        origin=(frame.lat0, frame.lon0, frame.h0),
        tracks={track.vehicle_id: track for track in made.tracks},
        default_host=None,
        meta={
            "tx_device": device,
            "epoch_gentime_us": epoch,
            "time_offset": phase,
            "rows": len(rows),
            "repeats": made.repeats,
            "rx_devices": sorted(set(ids["RxDevice"][rows].tolist()) - {""}),
            "file_ids": sorted(set(ids["FileId"][rows].tolist()) - {""}),
        },
    )
