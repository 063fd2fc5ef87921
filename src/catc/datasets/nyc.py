"""NYC connected-vehicle pilot EVENT JSON (obfuscated) -> :class:`~catc.mobility.MobilityTable`.

Format (see the data's PROVENANCE.md and the ITS DataHub sandbox's
``doc/nycdot/DataProcessing.txt``): one JSON object ``{"eventHeader": {...}, "bsmList":
[...]}`` per warning event.  The header names the application (``eventType``, e.g.
``fcw``), the host and target temporary ids (``hostVehID``, ``targetVehID``), the
``eventMsgSeqNum`` of the host's and the target's BSM that triggered the warning
(``triggerHVSeqNum``, ``triggerTVSeqNum``) and the application ``parameters``.  Each
``bsmList`` item is ``{"eventMsgSeqNum", "bsmRecord": {"bsmMsg": {"coreData": ...,
"partII": ...}}}``; the host's and the received BSMs are interleaved in one list.  The
obfuscation replaced secMark/lat/long/elev and the raw J2735 integers by
``T_s`` (s; T = 0 is the instant the ASD issued the warning), ``X_m``/``Y_m``/``Z_m`` (m;
(0, 0, 0) is the position of the host's trigger BSM), ``speed_mps``, ``heading_deg``
(deg cw from north) and ``accelSet.long_mpss``/``lat_mpss``/``vert_mpss``/``yaw_dps``;
``size`` stays in cm.  Other ``mapList``/``spatList``/``timList`` keys are ignored, and
so is partII (path history and prediction).

Choices (numbers measured on ``nycdot-fcw-event.json``, the FCW event of PROVENANCE.md):

* **Axes.**  ``X_m`` is east and ``Y_m`` north (DataProcessing.txt: X_m replaces the
  longitude, Y_m the latitude), in metres.  Checked on the real file: the direction of
  motion between consecutive positions, ``atan2(dX, dY)`` clockwise from north, differs
  from ``heading_deg`` by a median 0.18 deg (host) and 0.17 deg (target); with X and Y
  swapped the median difference is 17-20 deg.  The unit is the metre: the host's
  positions advance at 1.015 times its ``speed_mps`` (median +0.33 m/s at ~21.5 m/s).
  ENU = (X_m, Y_m, Z_m) as given.
* **Georeference.**  The file has no latitude or longitude.  The ENU origin is the
  nominal :data:`ORIGIN` (40.7440 N, 73.8370 W, h0 = 0): a point on a Queens freeway,
  matching the event's ``eventLocationBin`` ``NY-QN-FWY``, *not* the true location.
  lat/lon/elev are ``catc.geo.EnuFrame(*ORIGIN).to_geodetic(X_m, Y_m, Z_m)``; the
  geometry between the vehicles is exact, the absolute position is not.
* **Time.**  Each vehicle's ``T_s`` steps by 0.1 s on its own phase: the host's
  T_s = -0.034 + k 0.1 exactly, the target's T_s = -0.015 + k 0.1 with 1 ms jitter
  (one step of 0.099 s and one of 0.101 s).  Per vehicle the BSMs are put in T_s order
  and a BSM whose T_s is within DT/2 of the previous one is dropped as a duplicate
  (the real file repeats T_s *and* position in the next BSM: twice for the host, once
  for the target; the first BSM is kept).  Then every field is **linearly interpolated
  in T_s** onto the common 10 Hz grid ``t = k * DT`` (multiples of
  :data:`catc.mobility.DT`, so T = 0, the warning, is a sample) between the vehicle's
  first and last BSM: the host's values are taken 34 ms after, the target's 15 ms after
  the BSM before each grid instant.  Host and target tracks therefore share instants
  (-6.6 ... 9.3 s, 160 samples each on the real file).  Gaps between BSMs of at most
  ``derive.MAX_GAP + 1`` steps (0.6 s, i.e. up to 5 missing BSMs) are bridged by the same
  interpolation (the real file lacks the host's BSMs at 4.866 s and 7.266 s and the
  target's at -4.915 s); longer gaps split a vehicle, and only the piece holding T = 0
  (else the longest piece) is kept.  Heading is unwrapped before interpolation.
  The per-vehicle phase and jitter are in ``meta["time_offset"]``/``meta["time_jitter"]``.
* **Measured fields.**  ``speed`` is ``speed_mps``, ``heading`` is ``heading_deg``,
  ``accel`` is ``accelSet.long_mpss`` and ``yaw_rate`` is ``accelSet.yaw_dps``, all as
  broadcast (then interpolated as above).  ``yaw_dps`` is positive clockwise (the J2735
  convention, heading increasing): on the real file its regression on the 0.1 s
  heading change has slope 0.97 (host) and 0.86 (target), correlation 0.98 and 0.91
  (0.997 and 0.986 over 1 s differences), and its integral over the event is +8.2 deg
  (host) and +20.4 deg (target) for heading changes of +9.4 and +18.5 deg.
  ``length``/``width`` are ``size`` in cm / 100 (median over the vehicle's BSMs).
  ``long_mpss`` is an accelerometer reading that includes the road grade: on the host it
  exceeds the derivative of ``speed_mps`` by a median 0.10 m/s² while Z_m climbs 4.0 m
  over ~350 m (1.1 %, g * 0.011 = 0.11 m/s²).
* **Stuck speed.**  The target of the real file broadcasts ``speed_mps`` = 5.68 in all
  161 BSMs while its positions advance at a median 22.1 m/s (22.3 m/s at T = 0; its
  heading, yaw rate and acceleration vary normally).  ``speed`` keeps the broadcast
  value (what the host's ASD received and warned on).  The speed from the positions
  (magnitude of the Savitzky-Golay velocity of x/y, as :mod:`catc.datasets.derive` uses
  for headings) is in ``meta["track_speed"][vehicle_id]`` for every vehicle, and a
  broadcast speed that is constant in all BSMs and more than :data:`STUCK_SPEED_DIFF`
  (1 m/s) off the median speed from the positions is flagged in that track's
  ``provenance["speed"]``.  (So this event's warning is explained by the stuck speed:
  by the positions the two keep 39-46 m apart, the gap slowly opening.)
* **Brakes.**  ``wheelBrakes`` is a hex string of the 5-bit J2735 BrakeAppliedStatus
  left-aligned in one byte (named bit 0 ``unavailable`` = 0x80, then leftFront 0x40,
  leftRear 0x20, rightFront 0x10, rightRear 0x08; the real file only has ``00``).
  ``meta["brakes"][vehicle_id]`` is a bool array on the track's grid: True when any
  wheel bit (mask 0x78) is set in the BSM *nearest in time* to the grid instant (the
  unavailable bit alone is False).  Padding bits (0x07) set is an error.
* **Tracks.**  One per vehicle id in ``bsmList`` (the ids as given, hex strings):
  the target first, other vehicles in order of first appearance, the host last;
  ``default_host`` is ``hostVehID``.  Vehicles other than the host and the target that
  cover no grid instant are dropped (listed in ``meta["dropped"]``).
* **meta.**  ``header`` (the whole eventHeader), ``event_type``, ``alert_sent``
  (``eventAlertSent``), ``trigger_hv_seq``/``trigger_tv_seq``, ``parameters``,
  ``trigger_t`` = 0.0 (the warning instant on the table's time axis), ``trigger_bsm_t``
  (vehicle id -> T_s of its trigger BSM: 0.166 s host and 0.185 s target on the real
  file, i.e. 0.17-0.19 s *after* the warning instant T = 0), ``brakes``,
  ``track_speed``, ``time_offset``, ``time_jitter``, ``dropped``.

Errors: content that is not such an event raises :class:`ValueError` with a one-line
message starting ``nyc event:`` and naming the item and field.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from catc.datasets import derive
from catc.geo import EnuFrame, wrap_deg_360
from catc.mobility import DT, MobilityTable, Track

__all__ = ["ORIGIN", "looks_like", "parse"]

Array = npt.NDArray[np.float64]

#: Nominal ENU origin (lat, lon in deg WGS-84, h in m): a Queens freeway point standing in
#: for the undisclosed true location (eventLocationBin "NY-QN-FWY").
ORIGIN = (40.7440, -73.8370, 0.0)
#: The longest interval between two kept BSMs that is bridged by interpolation (s).
MAX_BRIDGE_S = (derive.MAX_GAP + 1) * DT
#: A broadcast speed constant in all BSMs is flagged as stuck when the median speed from
#: the positions differs from it by more than this (m/s).
STUCK_SPEED_DIFF = 1.0
#: Wheel bits of the left-aligned BrakeAppliedStatus byte; the rest of the byte.
WHEEL_MASK = 0x78
_PADDING_MASK = 0x07
_EPS = 1e-6
#: coreData number fields, in the column order of :class:`_Samples` ``values``.
_NUMBERS = (
    ("T_s",), ("X_m",), ("Y_m",), ("Z_m",), ("speed_mps",), ("heading_deg",),
    ("accelSet", "long_mpss"), ("accelSet", "yaw_dps"), ("size", "length"), ("size", "width"),
)  # fmt: skip
_T, _X, _Y, _Z, _SPEED, _HEADING, _ACCEL, _YAW, _LENGTH, _WIDTH = range(len(_NUMBERS))
#: Valid ranges; the J2735 "unavailable" codes fall outside (speed 8191 * 0.02 m/s,
#: heading 28800 * 0.0125 deg, acceleration 2001 * 0.01 m/s²).
_RANGES = {
    _SPEED: (0.0, 163.8),
    _HEADING: (0.0, 359.9999),
    _ACCEL: (-20.0, 20.0),
    _LENGTH: (0.0, 4095.0),
    _WIDTH: (0.0, 1023.0),
}
_INTERP = "linearly interpolated in T_s onto t = k * 0.1 s"
_LINE = (
    f"nominal origin {ORIGIN[0]:.4f} N {-ORIGIN[1]:.4f} W (NY-QN-FWY; the true location is "
    "obfuscated), via catc.geo.EnuFrame"
)
_PROVENANCE = {
    "t": "derived: the 10 Hz grid k * 0.1 s over the span of T_s (s from the warning)",
    "x": f"measured: X_m (m east of the host's trigger BSM), {_INTERP}",
    "y": f"measured: Y_m (m north of the host's trigger BSM), {_INTERP}",
    "lat": f"derived: X_m/Y_m/Z_m as ENU at the {_LINE}, {_INTERP}",
    "lon": f"derived: X_m/Y_m/Z_m as ENU at the {_LINE}, {_INTERP}",
    "elev": f"derived: Z_m as ENU up at the {_LINE} (ellipsoidal, nominal h0 = 0), {_INTERP}",
    "speed": f"measured: speed_mps as broadcast, {_INTERP}",
    "heading": f"measured: heading_deg (deg cw from north), unwrapped and {_INTERP}",
    "accel": f"measured: accelSet.long_mpss, {_INTERP}",
    "yaw_rate": f"measured: accelSet.yaw_dps (positive clockwise), {_INTERP}",
    "length": "measured: size.length (cm / 100), median over the vehicle's BSMs",
    "width": "measured: size.width (cm / 100), median over the vehicle's BSMs",
}


@dataclass(frozen=True)
class _Samples:
    """One vehicle's BSMs in list order: numbers (n, len(_NUMBERS)), brakes, seq nums."""

    values: Array
    braking: npt.NDArray[np.bool_]
    seq: list[Any]


def looks_like(text: str) -> bool:
    """True when ``text`` is a JSON object with ``eventHeader`` and ``bsmList`` keys."""
    body = text.lstrip("\ufeff").lstrip()
    if not body.startswith("{") or '"eventHeader"' not in body or '"bsmList"' not in body:
        return False
    try:
        data = json.loads(body)
    except ValueError:
        return False
    return isinstance(data, dict) and "eventHeader" in data and "bsmList" in data


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"nyc event: {where} is not a number ({value!r})")
    if not math.isfinite(value):
        raise ValueError(f"nyc event: {where} is not finite ({value!r})")
    return float(value)


def _wheel_brakes(value: Any, where: str) -> bool:
    """Any wheel brake applied, from the left-aligned BrakeAppliedStatus hex string."""
    try:
        bits = int(value, 16) if isinstance(value, str) and value.strip() else -1
    except ValueError:
        bits = -1
    if not 0 <= bits <= 0xFF:
        raise ValueError(f"nyc event: {where} is not a one-byte hex string ({value!r})")
    if bits & _PADDING_MASK:
        raise ValueError(f"nyc event: {where} {value!r} sets padding bits (0x07)")
    return bool(bits & WHEEL_MASK)


def _core(item: Any, i: int) -> dict[str, Any]:
    if not isinstance(item, dict):
        raise ValueError(f"nyc event: bsmList item {i} is not an object")
    core = item.get("bsmRecord", {})
    core = core.get("bsmMsg", {}) if isinstance(core, dict) else None
    core = core.get("coreData") if isinstance(core, dict) else None
    if not isinstance(core, dict):
        raise ValueError(f"nyc event: bsmList item {i} has no bsmRecord.bsmMsg.coreData")
    return core


def _field(core: dict[str, Any], path: tuple[str, ...], i: int) -> Any:
    value: Any = core
    for key in path:
        value = value.get(key) if isinstance(value, dict) else None
    if value is None:
        raise ValueError(f"nyc event: bsmList item {i} has no coreData.{'.'.join(path)}")
    return value


def _row(core: dict[str, Any], i: int) -> tuple[list[float], bool]:
    """The numbers of one coreData (in :data:`_NUMBERS` order) and its wheel-brake flag."""
    row = []
    for k, path in enumerate(_NUMBERS):
        where = f"bsmList item {i} coreData.{'.'.join(path)}"
        value = _number(_field(core, path, i), where)
        low, high = _RANGES.get(k, (-math.inf, math.inf))
        if not low <= value <= high:
            raise ValueError(f"nyc event: {where} = {value:g} is outside [{low:g}, {high:g}] "
                             "(J2735 'unavailable'?)")
        row.append(value)
    wheels = _field(core, ("brakes", "wheelBrakes"), i)
    return row, _wheel_brakes(wheels, f"bsmList item {i} coreData.brakes.wheelBrakes")


def _vehicles(bsm_list: list[Any]) -> dict[str, _Samples]:
    """The BSMs of each vehicle id, in order of first appearance."""
    rows: dict[str, list[list[float]]] = {}
    brakes: dict[str, list[bool]] = {}
    seqs: dict[str, list[Any]] = {}
    for i, item in enumerate(bsm_list):
        core = _core(item, i)
        vehicle_id = core.get("id")
        if not isinstance(vehicle_id, str) or not vehicle_id.strip():
            raise ValueError(f"nyc event: bsmList item {i} has no coreData.id")
        row, braking = _row(core, i)
        rows.setdefault(vehicle_id, []).append(row)
        brakes.setdefault(vehicle_id, []).append(braking)
        seqs.setdefault(vehicle_id, []).append(item.get("eventMsgSeqNum"))
    return {
        v: _Samples(np.array(rows[v]), np.array(brakes[v], dtype=bool), seqs[v]) for v in rows
    }


def _phase(t: Array) -> tuple[float, float]:
    """A time series' offset from the k * DT grid (median, s) and its jitter about it (max |.|)."""
    offset = float(np.median(t - np.round(t / DT) * DT))
    residual = t - offset
    return offset, float(np.max(np.abs(residual - np.round(residual / DT) * DT)))


def _grid(t: Array) -> Array | None:
    """Grid instants k * DT inside [t[0], t[-1]] not inside a gap longer than MAX_BRIDGE_S.

    Of the pieces such gaps leave, the one holding T = 0, else the longest, is returned;
    None when no instant is covered.
    """
    k = np.arange(math.ceil(t[0] / DT - _EPS), math.floor(t[-1] / DT + _EPS) + 1)
    grid = np.round(k * DT, 6)  # exact 0.0 at the warning, no float residue
    if grid.size == 0:
        return None
    after = np.clip(np.searchsorted(t, grid - _EPS), 1, len(t) - 1)
    covered = (t[after] - t[after - 1] <= MAX_BRIDGE_S + 5e-3) | (
        np.abs(t[after] - grid) <= _EPS) | (np.abs(t[after - 1] - grid) <= _EPS)
    pieces = derive.pieces(covered, max_gap=0)
    if not pieces:
        return None
    zero = [p for p in pieces if grid[p.start] <= _EPS and grid[p.stop - 1] >= -_EPS]
    return grid[zero[0] if zero else max(pieces, key=lambda p: p.stop - p.start)]


def _track_speed(x: Array, y: Array) -> Array:
    """Speed from the positions: |Savitzky-Golay velocity| as in :mod:`derive` (m/s)."""
    n = len(x)
    window = min(derive.WINDOW, n if n % 2 else n - 1)
    if window <= derive.POLYORDER:
        return np.full(n, np.nan)
    ve, vn = (derive.savgol_derivative(a, window, derive.POLYORDER, DT)
              for a in (x, y))
    return np.hypot(ve, vn)


def _resampled(
    vehicle_id: str, samples: _Samples, frame: EnuFrame
) -> tuple[Track, dict[str, Any]] | None:
    """The vehicle's track on the 10 Hz grid and its meta entries (None: no grid instant)."""
    order = np.argsort(samples.values[:, _T], kind="stable")
    values, braking = samples.values[order], samples.braking[order]
    # Drop a BSM within DT/2 of the previous *kept* one (runs of duplicates collapse to one).
    keep = np.ones(len(values), dtype=bool)
    last = values[0, _T]
    for j in range(1, len(keep)):
        keep[j] = values[j, _T] - last > DT / 2
        last = values[j, _T] if keep[j] else last
    values, braking = values[keep], braking[keep]
    t_bsm = values[:, _T]
    if len(t_bsm) < 2:
        return None
    grid = _grid(t_bsm)
    if grid is None:
        return None

    def at(column: Array) -> Array:
        return np.interp(grid, t_bsm, column)

    x, y, z = at(values[:, _X]), at(values[:, _Y]), at(values[:, _Z])
    lat, lon, elev = frame.to_geodetic(x, y, z)
    speed = at(values[:, _SPEED])
    heading = np.asarray(wrap_deg_360(at(np.unwrap(values[:, _HEADING], period=360.0))))
    nearest = np.clip(np.searchsorted(t_bsm, grid), 1, len(t_bsm) - 1)
    nearest -= (grid - t_bsm[nearest - 1]) <= (t_bsm[nearest] - grid)
    track_speed = _track_speed(x, y)
    offset, jitter = _phase(t_bsm)
    steps = np.diff(t_bsm)
    gaps = int(np.count_nonzero((steps > 1.5 * DT) & (steps <= MAX_BRIDGE_S + 5e-3)))
    provenance = {
        **_PROVENANCE,
        "t": f"{_PROVENANCE['t']}; the BSMs' T_s = {offset:+.3f} s + k * 0.1 s (jitter "
             f"{jitter * 1e3:.0f} ms), so the grid is {-offset * 1e3:+.0f} ms off them",
        "samples": f"{len(samples.seq)} BSMs; duplicate T_s dropped: "
                   f"{int(np.count_nonzero(~keep))}; gaps (<= {MAX_BRIDGE_S:g} s) bridged: {gaps}; "
                   f"kept {grid[0]:g} ... {grid[-1]:g} s",
    }
    moving = float(np.median(track_speed)) if np.isfinite(track_speed).all() else np.nan
    if np.ptp(values[:, _SPEED]) == 0 and abs(moving - values[0, _SPEED]) > STUCK_SPEED_DIFF:
        provenance["speed"] += (
            f"; CONSTANT {values[0, _SPEED]:g} m/s in all BSMs while the positions advance "
            f"at a median {moving:.1f} m/s (stuck speed source; see meta['track_speed'])"
        )
    track = Track(
        vehicle_id=vehicle_id, t=grid, x=x, y=y, lat=np.asarray(lat), lon=np.asarray(lon),
        elev=np.asarray(elev), speed=speed, heading=heading, accel=at(values[:, _ACCEL]),
        yaw_rate=at(values[:, _YAW]), length=float(np.median(values[:, _LENGTH])) / 100.0,
        width=float(np.median(values[:, _WIDTH])) / 100.0, provenance=provenance,
    )  # fmt: skip
    meta = {
        "brakes": braking[nearest],
        "track_speed": track_speed,
        "time_offset": offset,
        "time_jitter": jitter,
    }
    return track, meta


def _header(data: Any) -> tuple[dict[str, Any], list[Any]]:
    if not isinstance(data, dict) or "eventHeader" not in data or "bsmList" not in data:
        raise ValueError("nyc event: not a JSON object with eventHeader and bsmList")
    header, bsm_list = data["eventHeader"], data["bsmList"]
    if not isinstance(header, dict):
        raise ValueError("nyc event: eventHeader is not an object")
    if not isinstance(bsm_list, list) or not bsm_list:
        raise ValueError("nyc event: bsmList is not a non-empty list")
    if not isinstance(header.get("hostVehID"), str):
        raise ValueError("nyc event: eventHeader has no hostVehID")
    return header, bsm_list


def parse(text: str, name: str) -> MobilityTable:
    """Parse the contents of one NYC CV pilot event JSON into a table (see the module doc)."""
    try:
        data = json.loads(text.lstrip("\ufeff"))
    except ValueError as exc:
        raise ValueError(f"nyc event: not JSON ({exc})") from None
    header, bsm_list = _header(data)
    host, target = header["hostVehID"], header.get("targetVehID")
    vehicles = _vehicles(bsm_list)
    for role, vehicle_id in (("hostVehID", host), ("targetVehID", target)):
        if vehicle_id is not None and vehicle_id not in vehicles:
            raise ValueError(f"nyc event: {role} {vehicle_id} has no BSM in bsmList")
    order = [target] if target is not None and target != host else []
    order += [v for v in vehicles if v not in (host, target)] + [host]

    frame = EnuFrame(*ORIGIN)
    tracks: dict[str, Track] = {}
    meta: dict[str, Any] = {
        "header": header,
        "event_type": header.get("eventType"),
        "alert_sent": header.get("eventAlertSent"),
        "trigger_hv_seq": header.get("triggerHVSeqNum"),
        "trigger_tv_seq": header.get("triggerTVSeqNum"),
        "parameters": header.get("parameters", {}),
        "trigger_t": 0.0,
        "trigger_bsm_t": {},
        **{key: {} for key in ("brakes", "track_speed", "time_offset", "time_jitter")},
        "dropped": [],
    }
    triggers = {host: header.get("triggerHVSeqNum"), target: header.get("triggerTVSeqNum")}
    for vehicle_id in order:
        samples = vehicles[vehicle_id]
        made = _resampled(vehicle_id, samples, frame)
        if made is None:
            if vehicle_id in (host, target):
                raise ValueError(f"nyc event: vehicle {vehicle_id} has no two BSMs around a "
                                 "0.1 s grid instant")
            meta["dropped"].append(vehicle_id)
            continue
        tracks[vehicle_id], extra = made
        for key, value in extra.items():
            meta[key][vehicle_id] = value
        seq = triggers.get(vehicle_id)
        if seq is not None and seq in samples.seq:
            meta["trigger_bsm_t"][vehicle_id] = float(samples.values[samples.seq.index(seq), _T])
    return MobilityTable(
        name=name,
        kind="nyc",
        origin=(frame.lat0, frame.lon0, frame.h0),
        tracks=tracks,
        default_host=host,
        meta=meta,
    )
