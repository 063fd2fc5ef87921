"""Recorded BSMs (JPO ODE JSON, OBU ``.bin`` logs) -> a :class:`~catc.mobility.MobilityTable`.

Real BSMs from deployed on-board units, to be re-broadcast by the RVE.  Two containers:

* **ODE JSON** (text): ``OdeBsmData`` records ``{"metadata": {...}, "payload": {"data":
  J2735Bsm}}`` as the jpo-ode publishes them, or bare ``J2735Bsm`` objects
  ``{"coreData": ..., "partII": ...}`` (the ODE's ``128_bsms.json``/``bsm.json``), as one
  JSON object, a JSON array, or JSON lines.  Decoded by :func:`catc.j2735.ode.bsm_from_ode`
  (SI units already; its quirks are handled there).  Records that are not decoded BSMs
  (other payloads, hex only) are skipped and counted in ``meta["skipped"]``.
* **OBU logs** (bytes): the WYDOT/CDOT binary logs (``bsmTx``, ``bsmLogDuringEvent``,
  ``rxMsg``, ``dnMsg``) that :mod:`catc.j2735.obulog` frames; each record's MessageFrame
  is decoded by :func:`catc.j2735.decode_frame`.  Frames of other messages (e.g. a TIM in
  an rxMsg log) are skipped and counted.

``parse`` takes ``str`` or ``bytes``: bytes that are UTF-8 text without control
characters are read as JSON, other bytes as an OBU log.

Choices:

* **Vehicles.**  One track per TemporaryID (``coreData.id``), id = its 8 hex digits
  upper case (``31325431``), so a log and its ODE JSON give the same ids.  Tracks in
  order of their first BSM, the host last.  ``default_host`` is the vehicle whose BSMs
  the log marks as the logging vehicle's own (``EV``: the OBU log record's direction, the
  ODE's ``metadata.bsmSource``, or an ODE ``recordType`` of ``bsmTx``) when exactly one
  is; otherwise None (an rxMsg log only holds received BSMs): choose one or add
  :func:`catc.hostsim.with_synthetic_host`.
* **Time.**  A BSM's time is its secMark (ms within the UTC minute), placed in the
  minute, of the three around it, nearest to the record's UTC time: the OBU log record
  header's time, or the ODE's ``metadata.recordGeneratedAt`` (the same value: the ODE
  copies it from the log).  ``odeReceivedAt`` is not used: it is when the ODE ingested
  the file (2019-04-09 for ``bsmLogDuringEvent.json``, whose records were generated on
  2018-05-01).  The record time alone is not the BSM time: in ``rxMsg_BSM.bin`` it
  differs from the secMarks (all on a 100 ms grid) by -118 to +35 ms, in
  ``bsmLogDuringEvent.bin`` the remote vehicle's secMarks run 93-105 ms ahead of the
  record times while the logging vehicle's own match them to 0.1 ms; and a log may be
  written out of order (``bsmLogDuringEvent`` is newest first).  A BSM without secMark
  (or with a leap-second secMark >= 60000) takes the record time.  t = seconds since
  ``meta["epoch_utc"]`` (Unix seconds), the start of the UTC minute of the table's first
  BSM, so t modulo 60 s is the broadcast secMark.  When the records carry no time (bare
  J2735Bsm objects), the secMarks are unwrapped in file order (a step back of more than
  30 s is the next minute), t counts from the minute of the first BSM, and
  ``epoch_utc`` is None.
* **Resampling** as :func:`catc.datasets.spmd.resample`: every field linearly
  interpolated in time onto ``phase + k * 0.1 s`` (phase: circular mean of all the
  table's BSM times modulo 0.1 s, ``meta["time_offset"]``), instants within 0.05 s
  beyond a piece's first/last BSM holding it; BSMs of a vehicle within 0.05 s of its
  previous kept one are dropped as repeats (``128_bsms.json`` holds every BSM twice);
  gaps over 0.6 s split a vehicle into pieces ``ID``, ``ID#2``...  A single BSM gives a
  one-sample track.
* **Fields.**  All measured, as broadcast: lat/lon (deg WGS-84), elev (m; J2735
  elevation is above the WGS-84 ellipsoid), speed (m/s), heading (deg cw from north),
  accel = ``accelSet.long`` (m/s²), yaw_rate = ``accelSet.yaw`` (deg/s, J2735 YawRate:
  positive clockwise, as here: the WYDOT BSM of ``wydot-filtered-bsm-schemaVersion6.json``
  reports +2.29 deg/s and radiusOfCurve +97.5 m while its path history turns clockwise,
  the direction of motion rotating by +87 deg over its last 14 s); length/width =
  ``size`` (median over the vehicle's BSMs).  "Unavailable" values are interpolated
  from the vehicle's other BSMs, or derived as in :mod:`catc.datasets.derive` when no
  BSM of a piece has them (e.g. the heading of 19BB0000 in ``128_bsms.json``).  BSMs
  without a position are dropped (counted).
* The ENU origin is the position of the table's first BSM (elevation 0 if unavailable).
* **Auto-detection** (:func:`looks_like`) claims an OBU log, or JSON whose first two
  records are decoded BSMs.  A file of one BSM (``bsm.json``, the WYDOT samples) is one
  sample, not a trajectory, and is left to ``ode:PATH``.

Errors: content that holds no usable BSM raises :class:`ValueError` with a one-line
message starting ``ode:``.
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

from catc.bsm import BSM
from catc.datasets.spmd import BSM_FIELDS, grid_phase, resample
from catc.errors import DecodeError
from catc.geo import EnuFrame
from catc.j2735 import BSM_MESSAGE_ID, decode_frame, frame_message_id, obulog
from catc.j2735.ode import bsm_from_ode
from catc.j2735.sniff import as_text
from catc.mobility import MobilityTable, Track

__all__ = ["looks_like", "parse"]

_ZONE = re.compile(r"\[[^\]]*\]$")
_MINUTE_MS = 60_000
_PROVENANCE = {
    "lat": "measured: BSM latitude (deg WGS-84)",
    "lon": "measured: BSM longitude (deg WGS-84)",
    "elev": "measured: BSM elevation (m above the WGS-84 ellipsoid)",
    "x": "derived: ENU east of lat/lon/elev (catc.geo.EnuFrame at the table origin)",
    "y": "derived: ENU north of lat/lon/elev (catc.geo.EnuFrame at the table origin)",
    "speed": "measured: BSM speed (m/s)",
    "heading": "measured: BSM heading (deg cw from north)",
    "accel": "measured: BSM accelSet.long (m/s²)",
    "yaw_rate": "measured: BSM accelSet.yaw (deg/s, J2735: positive clockwise)",
    "length": "measured: BSM size.length (median over the vehicle's BSMs)",
    "width": "measured: BSM size.width (median over the vehicle's BSMs)",
}
_TIME = {
    "log": "measured: BSM secMark in the UTC minute nearest the record's time (OBU log "
           "header / ODE recordGeneratedAt), s since meta['epoch_utc']",
    "secmark": "measured: BSM secMark, minute rollovers counted in file order (no record "
               "time in the file), s since the minute of the first BSM",
}  # fmt: skip


@dataclass(frozen=True)
class _Record:
    bsm: BSM
    time: float | None  # the record's UTC time (Unix s), if it has one
    source: str | None  # "EV" (the logging vehicle's own) | "RV" | None


def _json_records(text: str) -> list[Any]:
    text = text.lstrip("\ufeff").strip()
    try:
        doc = json.loads(text)
    except ValueError:
        pass
    else:
        return doc if isinstance(doc, list) else [doc]
    try:
        return [json.loads(line) for line in text.splitlines() if line.strip()]
    except ValueError as exc:
        raise ValueError(f"ode: not JSON, JSON lines or an OBU log ({exc})") from None


def _bsm_object(record: Any) -> tuple[dict | None, dict]:
    """(the J2735Bsm object, the ODE metadata) of a JSON record; (None, {}) if it has none."""
    if not isinstance(record, dict):
        return None, {}
    if isinstance(record.get("coreData"), dict):
        return record, {}
    payload = record.get("payload")
    data = payload.get("data") if isinstance(payload, dict) else None
    if isinstance(data, dict) and isinstance(data.get("coreData"), dict):
        metadata = record.get("metadata")
        return data, metadata if isinstance(metadata, dict) else {}
    return None, {}


def _utc_seconds(stamp: Any) -> float | None:
    """ODE time stamps ("2018-05-01T16:04:23.694Z", "...Z[UTC]") -> Unix seconds."""
    if not isinstance(stamp, str):
        return None
    try:
        when = datetime.fromisoformat(_ZONE.sub("", stamp.strip()))
    except ValueError:
        return None
    return (when if when.tzinfo else when.replace(tzinfo=UTC)).timestamp()


def _from_json(text: str, skipped: Counter[str]) -> list[_Record]:
    records = []
    for item in _json_records(text):
        data, metadata = _bsm_object(item)
        if data is None:
            skipped["not a decoded BSM record"] += 1
            continue
        try:
            bsm = bsm_from_ode(data)
        except DecodeError:
            skipped["undecodable J2735Bsm"] += 1
            continue
        source = metadata.get("bsmSource")
        if source is None and metadata.get("recordType") == "bsmTx":
            source = "EV"  # a bsmTx log holds the logging vehicle's own BSMs
        records.append(_Record(bsm, _utc_seconds(metadata.get("recordGeneratedAt")),
                               source if source in ("EV", "RV") else None))
    return records


def _from_obulog(data: bytes, skipped: Counter[str]) -> tuple[list[_Record], str]:
    found: list[obulog.LogRecord] = []
    try:
        for record in obulog.iter_records(data):
            found.append(record)
    except DecodeError as exc:
        if not found:
            raise ValueError(f"ode: neither JSON nor an OBU log ({exc})") from None
        skipped["truncated last record"] += 1
    records = []
    for record in found:
        try:
            if frame_message_id(record.frame) != BSM_MESSAGE_ID:
                skipped["not a BSM frame"] += 1
                continue
            bsm = decode_frame(record.frame)
        except DecodeError:
            skipped["undecodable frame"] += 1
            continue
        records.append(_Record(bsm, record.utc_time, record.direction))
    return records, f"obulog:{found[0].kind}"


def looks_like(content: str | bytes) -> bool:
    """Whether content is an OBU log or JSON whose first two records are decoded BSMs."""
    if isinstance(content, bytes):
        text = as_text(content)
        if text is None:
            return obulog.looks_like_obulog(content)
        content = text
    text = content.lstrip("\ufeff").strip()
    if text[:1] not in ("{", "["):
        return False
    try:
        doc = json.loads(text)
        first = doc[:2] if isinstance(doc, list) else [doc]
    except ValueError:
        lines = [line for line in text.splitlines()[:2] if line.strip()]
        try:
            first = [json.loads(line) for line in lines]
        except ValueError:
            return False
    def is_bsm(item: Any) -> bool:
        data, _ = _bsm_object(item)
        position = data["coreData"].get("position") if data is not None else None
        return isinstance(position, dict) and "latitude" in position
    return len(first) == 2 and all(is_bsm(item) for item in first)


def _times_ms(records: list[_Record]) -> tuple[np.ndarray, str]:
    """Each record's BSM time in integer ms (see the module doc, Time) and the method."""
    if all(r.time is not None for r in records):
        out = []
        for r in records:
            ref = round(r.time * 1000)
            mark = r.bsm.sec_mark
            if mark is None or mark >= _MINUTE_MS:
                out.append(ref)
                continue
            minute = ref // _MINUTE_MS * _MINUTE_MS
            out.append(min((minute + d + mark for d in (-_MINUTE_MS, 0, _MINUTE_MS)),
                           key=lambda ms: abs(ms - ref)))
        return np.array(out, dtype=np.int64), "log"
    marks = [r.bsm.sec_mark for r in records]
    if any(m is None or m >= _MINUTE_MS for m in marks):
        raise ValueError("ode: a BSM without secMark in records without a time")
    unwrapped = np.unwrap(np.array(marks, dtype=np.float64), period=_MINUTE_MS)
    return np.round(unwrapped).astype(np.int64), "secmark"


def _column(bsms: list[BSM], field: str) -> np.ndarray:
    attr = {"accel": "accel_long"}.get(field, field)
    return np.array([math.nan if getattr(b, attr) is None else getattr(b, attr) for b in bsms],
                    dtype=np.float64)


def _median(values: np.ndarray) -> float:
    ok = values[np.isfinite(values)]
    return float(np.median(ok)) if ok.size else math.nan


def parse(content: str | bytes, name: str) -> MobilityTable:
    """Parse ODE JSON text or an OBU log into one table (see the module doc)."""
    skipped: Counter[str] = Counter()
    text = as_text(content) if isinstance(content, bytes) else content
    if text is None:
        records, container = _from_obulog(bytes(content), skipped)
    else:
        records, container = _from_json(text, skipped), "ode-json"
    positioned = [r for r in records if r.bsm.lat is not None and r.bsm.lon is not None]
    if len(positioned) < len(records):
        skipped["BSM without a position"] += len(records) - len(positioned)
    if not positioned:
        raise ValueError(f"ode: no BSM with a position ({dict(skipped) or 'empty'})")
    ms, method = _times_ms(positioned)
    epoch_ms = int(ms.min()) // _MINUTE_MS * _MINUTE_MS
    t = (ms - epoch_ms) / 1000.0
    phase = grid_phase(t)

    by_vehicle: dict[str, list[int]] = {}
    for i in np.argsort(t, kind="stable"):
        by_vehicle.setdefault(f"{positioned[i].bsm.temp_id:08X}", []).append(int(i))
    sources = {v: {positioned[i].source for i in idx} for v, idx in by_vehicle.items()}
    own = [v for v, s in sources.items() if s == {"EV"}]
    host = own[0] if len(own) == 1 else None
    order = [v for v in by_vehicle if v != host] + ([host] if host else [])

    first = positioned[int(np.argmin(t))].bsm
    frame = EnuFrame(first.lat, first.lon, first.elev if first.elev is not None else 0.0)
    provenance = {"t": _TIME[method], **_PROVENANCE}
    tracks: dict[str, Track] = {}
    repeats: dict[str, int] = {}
    for vehicle in order:
        idx = by_vehicle[vehicle]
        bsms = [positioned[i].bsm for i in idx]
        values = {f: _column(bsms, f) for f in BSM_FIELDS}
        size = (_median(_column(bsms, "length")), _median(_column(bsms, "width")))
        made = resample(vehicle, t[idx], values, frame, phase, provenance, size)
        tracks.update((track.vehicle_id, track) for track in made.tracks)
        repeats[vehicle] = made.repeats
    epoch = epoch_ms / 1000.0 if method == "log" else None
    return MobilityTable(
        name=name,
        kind="ode",
        origin=(frame.lat0, frame.lon0, frame.h0),
        tracks=tracks,
        default_host=host,
        meta={
            "container": container,
            "epoch_utc": epoch,
            "epoch_iso": None if epoch is None else
                datetime.fromtimestamp(epoch, UTC).isoformat().replace("+00:00", "Z"),
            "time_source": method,
            "time_offset": phase,
            "bsms": len(positioned),
            "sources": {v: sorted(s - {None}) for v, s in sources.items()},
            "repeats": repeats,
            "skipped": dict(skipped),
        },
    )
