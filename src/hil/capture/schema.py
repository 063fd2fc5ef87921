"""The capture directory's files, their records, and the key that joins them.

The RVE and the OBU may share one capture directory; each writes only its own files.  Every
record that goes into a file is built by one function here, so a field is added in one
place, and the readers (:mod:`hil.capture.reader`, ``captures score``, ``view``, ``plot``)
read what these build.  Every file is append-only and flushed once per tick
(:mod:`hil.capture.writers`); a killed daemon loses at most its last tick, and the reader
reads a file up to a torn tail and says where it was.  People read the JSON lines (ticks,
events, end records) by hand; the two files that grow with the number of RVs and frames
are compact: ``obu.rx.jsonl.gz`` is JSON lines in one gzip stream flushed per tick
(``zcat`` reads it), ``obu.tracks.bin`` is binary, each tick's rows as residuals against
the same RVs' rows of the tick before (:mod:`hil.capture.tracks`; ``captures tracks DIR``
prints them as JSON lines).

=======================  ======  ==============================================================
file                     writer  one record per ...
=======================  ======  ==============================================================
``rve.config.json``      RVE     run: settings, versions, dataset, host, vehicle ids, channel
                                 (:func:`rve_config`)
``rve.truth.jsonl``      RVE     vehicle and 10 Hz sample: the true state (:func:`truth`)
``rve.schedule.jsonl``   RVE     scheduled message: the channel's decision, and when it was
                                 sent (:func:`scheduled`)
``rve.frames.pcapng``    RVE     frame sent over UDP (or WSMP in Ethernet II)
``rve.frames.asc/.log``  RVE     CAN frame sent (ASC and candump log)
``rve.end.json``         RVE     run: how it ended, written as it ends (:func:`end`); none
                                 when the RVE was killed
``rve.hostbus.log``      RVE     CAN frame of the host's own bus, with ``--host-bus``
                                 (candump log; :mod:`rve.hostbus`)
``rve.gnss.jsonl``       RVE     GNSS epoch, with ``--host-bus``: sent or dropped, the true
                                 position (:mod:`rve.hostbus`)
``obu.config.json``      OBU     run: settings, versions, ENU origin (rewritten once it is known;
                                 :func:`obu_config`)
``obu.end.json``         OBU     run: how it ended (:func:`end`); none when it was killed
``obu.counters.json``    OBU     run: every counter (rewritten every second and at the end)
``obu.rx.jsonl.gz``      OBU     frame received, with what became of it (:func:`received`)
``obu.ticks.jsonl``      OBU     tick: host state, step time, warnings (:func:`tick`)
``obu.tracks.bin``       OBU     tracked RV at every tick (:func:`track_columns`, read back as
                                 :func:`track_rows` made them)
``obu.events.jsonl``     OBU     warning start or end (:func:`event`)
``obu.mbd.jsonl``        OBU     misbehavior finding (every failed check), with ``obu run --mbd``
                                 (:func:`finding`)
``obu.mbr.jsonl``        OBU     misbehavior report: a finding past the reporting threshold, with
                                 ``obu run --mbd`` (:func:`report`)
=======================  ======  ==============================================================

Segments.  With ``obu run --capture-max-mb N`` the OBU's per-tick files (:data:`SEGMENTED`)
are written in segments, a time slice each: segment 0 under the names above, segment k
under :func:`segment_name` (``obu.ticks.000003.jsonl``); when the OBU's files pass N MB the
oldest segment but the first is deleted (:mod:`obu.capture`).  The reader reads the
segments in order and says which are missing.

The join key.  A message is named on both sides by its sender's TemporaryID (8 hex digits),
its msgCnt and its secMark (:func:`message_key`).  The RVE's schedule gives the sequence
number and dataset time from which those two were stamped (:func:`catc.bsm.msg_cnt`,
:func:`catc.bsm.sec_mark`: :func:`scheduled_key`); the OBU's rx records give the decoded
values (:func:`received_key`).  The key repeats after 128 messages and a minute, far longer
than any latency.
"""

from __future__ import annotations

import uuid
from typing import Any

from catc.bsm import msg_cnt, sec_mark

__all__ = [
    "ENDINGS",
    "LEGACY",
    "OBU_CONFIG",
    "OBU_COUNTERS",
    "OBU_END",
    "OBU_EVENTS",
    "OBU_MBD",
    "OBU_MBR",
    "OBU_RX",
    "OBU_TICKS",
    "OBU_TRACKS",
    "OBU_VERIFY",
    "RVE_CAN_STEM",
    "RVE_CONFIG",
    "RVE_END",
    "RVE_GNSS",
    "RVE_HOSTBUS_LOG",
    "RVE_PCAPNG",
    "RVE_SCHEDULE",
    "RVE_TRUTH",
    "SEGMENTED",
    "end",
    "event",
    "failed",
    "hex_id",
    "message_key",
    "new_run_id",
    "obu_config",
    "received",
    "received_key",
    "report",
    "rve_config",
    "scheduled",
    "scheduled_key",
    "segment_name",
    "sent",
    "settings",
    "tick",
    "track_columns",
    "track_rows",
    "truth",
    "unverified",
    "verified_late",
]

RVE_CONFIG = "rve.config.json"
RVE_TRUTH = "rve.truth.jsonl"
RVE_SCHEDULE = "rve.schedule.jsonl"
RVE_PCAPNG = "rve.frames.pcapng"
#: ``rve.frames.asc`` and ``rve.frames.log``
RVE_CAN_STEM = "rve.frames"
RVE_END = "rve.end.json"
#: ``rve run --host-bus``: every CAN frame of the host's own bus (candump log), and every
#: GNSS epoch (sent or dropped, with the true position)
RVE_HOSTBUS_LOG = "rve.hostbus.log"
RVE_GNSS = "rve.gnss.jsonl"
OBU_CONFIG = "obu.config.json"
OBU_END = "obu.end.json"
OBU_COUNTERS = "obu.counters.json"
OBU_RX = "obu.rx.jsonl.gz"
OBU_TICKS = "obu.ticks.jsonl"
OBU_TRACKS = "obu.tracks.bin"
OBU_EVENTS = "obu.events.jsonl"
OBU_MBD = "obu.mbd.jsonl"
OBU_MBR = "obu.mbr.jsonl"
#: ``obu run --verify-policy on-demand``: what became of each message that reached its
#: tick unverified, once known (:func:`verified_late`)
OBU_VERIFY = "obu.verify.jsonl"
#: The OBU's files written per tick, in segments under ``--capture-max-mb``.
SEGMENTED = (OBU_RX, OBU_TICKS, OBU_TRACKS, OBU_EVENTS, OBU_MBD, OBU_MBR, OBU_VERIFY)
#: What captures written before 2026-11-27 called two of them (the reader reads both).
LEGACY = {OBU_RX: "obu.rx.jsonl", OBU_TRACKS: "obu.tracks.jsonl"}


def segment_name(name: str, k: int) -> str:
    """The file of segment ``k`` of ``name`` (one of :data:`SEGMENTED`): the name itself
    for segment 0, else the segment number before the extension
    (``obu.rx.000002.jsonl.gz``)."""
    if k == 0:
        return name
    daemon, stream, ext = name.split(".", 2)
    return f"{daemon}.{stream}.{k:06d}.{ext}"

MessageKey = tuple[str, int, int]


def hex_id(temp_id: int) -> str:
    """A TemporaryID as the captures write it: 8 upper-case hex digits."""
    return f"{temp_id:08X}"


def message_key(temp_id: str, count: int, mark: int) -> MessageKey:
    """The name of one message in every capture file: (TemporaryID hex, msgCnt, secMark)."""
    return (temp_id, count, mark)


def scheduled_key(record: dict) -> MessageKey:
    """:func:`message_key` of an ``rve.schedule.jsonl`` record (stamped from seq and t)."""
    return (record["id"], msg_cnt(record["seq"]), sec_mark(record["t"]))


def received_key(record: dict) -> MessageKey:
    """:func:`message_key` of an ``obu.rx.jsonl.gz`` record (the decoded msgCnt and secMark;
    None where the frame did not decode)."""
    return (record.get("id"), record.get("msgCnt"), record.get("sec_mark"))


def settings(args: Any) -> dict[str, Any]:
    """A daemon's settings for its config file: every parsed flag (tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in vars(args).items() if k not in ("func", "parser")}


# --- the RVE's records ------------------------------------------------------------------

def rve_config(settings: dict[str, Any], versions: dict[str, str], dataset: tuple[str, str, Any],
               host: str, ids: dict[str, int], channel: dict[str, Any], seed: int,
               started_unix: float, run_id: str) -> dict[str, Any]:
    """The RVE's run (``rve.config.json``): its :func:`settings` and software
    ``versions``, the dataset's (name, kind, ENU origin), the host vehicle, every
    vehicle's TemporaryID (``ids``), the channel model's settings and seed, when the run
    started (wall clock) and its ``run_id`` (:func:`new_run_id`; the end record's too)."""
    name, kind, origin = dataset
    return {"settings": settings, "versions": versions,
            "dataset": {"name": name, "kind": kind, "origin": origin}, "host": host,
            "vehicles": {v: hex_id(tid) for v, tid in ids.items()}, "channel": channel,
            "seed": seed, "started_unix": started_unix, "run_id": run_id}


def truth(vehicle: str, temp_id: int, index: int, t: float, lat: float, lon: float,
          x: float, y: float, speed: float, heading: float, accel: float, yaw_rate: float,
          host: bool) -> dict[str, Any]:
    """One true sample of a vehicle (``rve.truth.jsonl``): dataset time ``t`` (s),
    WGS-84 degrees, the dataset's ENU metres, m/s, degrees from north, m/s², deg/s."""
    return {"vehicle": vehicle, "id": hex_id(temp_id), "index": index, "t": t, "lat": lat,
            "lon": lon, "x": x, "y": y, "speed": speed, "heading": heading, "accel": accel,
            "yaw_rate": yaw_rate, "host": host}


def scheduled(vehicle: str, temp_id: int, channel: str, index: int, seq: int, t: float,
              dropped: bool, cause: str, delay: float | None,
              attack: str | None = None, **extra: Any) -> dict[str, Any]:
    """One scheduled message (``rve.schedule.jsonl``): the vehicle's sample ``index``
    (-1 for an attack's own frame) sent as its ``seq``-th message generated at dataset
    time ``t``; the channel's decision (``dropped``, ``cause``, ``delay`` s); the attack
    that made or changed it, and ``extra`` (an attack's ``signer``).  :func:`sent` adds
    what happened on the wire."""
    record = {"vehicle": vehicle, "id": hex_id(temp_id), "channel": channel, "index": index,
              "seq": seq, "t": t, "dropped": dropped, "cause": cause, "delay": delay}
    if attack is not None:
        record["attack"] = attack
    record.update(extra)
    return record


def sent(record: dict[str, Any], sent_unix: float, late_s: float, octets: int
         ) -> dict[str, Any]:
    """A :func:`scheduled` record once its frame went out: wall-clock send time, lateness
    against its deadline (ms, 4 decimals) and the frame's size."""
    record.update(sent_unix=sent_unix, late_ms=round(late_s * 1000.0, 4), octets=octets)
    return record


# --- the OBU's records ------------------------------------------------------------------

def obu_config(settings: dict[str, Any], versions: dict[str, str],
               origin: list[float] | None, started_unix: float, run_id: str
               ) -> dict[str, Any]:
    """The OBU's run (``obu.config.json``): its :func:`settings`, the software's versions
    (:func:`hil.capture.writers.versions`), the ENU origin ``[lat, lon, h]`` of its map
    (None until its first tick; the file is rewritten once it is known), when the run
    started (wall clock) and its ``run_id``."""
    return {"settings": settings, "versions": versions, "origin": origin,
            "started_unix": started_unix, "run_id": run_id}


def new_run_id() -> str:
    """A run's id: 32 random hex digits, in its config and its end record."""
    return uuid.uuid4().hex


#: How a daemon's run ended (:func:`end`): it finished its job (the replay sent, the OBU
#: idle or at its --duration), a signal stopped it (SIGTERM, SIGINT), or an error did.
#: A killed daemon writes nothing: its end file is missing.
ENDINGS = ("clean", "signal", "error")


def failed(err: BaseException) -> tuple[str, str]:
    """``(exit, reason)`` of a run that an exception ended: Ctrl-C (``KeyboardInterrupt``,
    before a daemon's own handlers or inside a step) is the signal SIGINT, anything else
    an error named by its type and message."""
    if isinstance(err, KeyboardInterrupt):
        return "signal", "SIGINT"
    return "error", f"{type(err).__name__}: {err}"


def end(run_id: str, exit: str, reason: str, started_unix: float, ended_unix: float,
        **counts: int) -> dict[str, Any]:
    """How a daemon's run ended (``rve.end.json``, ``obu.end.json``): its ``run_id`` (as in
    its config), ``exit`` one of :data:`ENDINGS`, the ``reason`` in words (the signal's
    name, the error's message), when it started and ended, and its totals (``counts``:
    ticks, frames sent...)."""
    if exit not in ENDINGS:
        raise ValueError(f"exit {exit!r}: not one of {ENDINGS}")
    return {"run_id": run_id, "exit": exit, "reason": reason, "started_unix": started_unix,
            "ended_unix": ended_unix, **counts}


def received(rx_unix: float, channel: str, data: bytes, status: str, *,
             sender: tuple[int, int, int | None] | None = None, verdict: str | None = None,
             tick: float | None = None, decided_unix: float | None = None,
             why: str | None = None, verify: str | None = None) -> dict[str, Any]:
    """One received frame (``obu.rx.jsonl.gz``) and what became of it: ``status`` is ``ok``
    (stepped at ``tick``, decided at ``decided_unix``), ``unticked`` (received after the
    last host frame), ``rejected`` (failed IEEE 1609.2 verification under enforce),
    ``quarantined`` (dropped by misbehavior detection, ``why``: ``quarantine``, its
    sender is in quarantine; ``copy`` or ``stale``, a replayed message, no evidence
    against anyone; ``id-conflict``, an id another certificate holds; captures before
    2026-11-28 have no ``why``), ``withheld`` (urgent, held back by the OBU's bound on
    the ECDSA at once and still unverified at its tick: never stepped; ``verify``
    ``held``), ``shed`` (waited longer than ``obu run --shed-after`` for an OBU behind
    real time: dropped undecoded) or the decode error's reason.
    ``sender`` is what the frame says of itself, (TemporaryID, msgCnt, secMark), where it
    decodes; ``verdict`` the 1609.2 verdict where frames are verified.  ``verify`` (``obu
    run --verify-policy on-demand``; absent before 2026-12-06 and under ``all``): when its
    signature was verified, ``at-once`` (on arrival: the verdict is that one), ``queue``
    (deferred, verified before its tick: the verdict too) or ``deferred`` (not verified by
    its tick, so stepped unverified; no verdict here: :func:`verified_late` says what became
    of it).  The frame's octets are kept in hex, so ``captures decode`` can decode the
    capture again."""
    record: dict[str, Any] = {"rx_unix": rx_unix, "channel": channel}
    if sender is not None:
        record.update(id=hex_id(sender[0]), msgCnt=sender[1], sec_mark=sender[2])
    record["status"] = status
    if why is not None:
        record["why"] = why
    if verdict is not None:
        record["verdict"] = verdict
    if verify is not None:
        record["verify"] = verify
    if tick is not None:
        record.update(tick=tick, decided_unix=decided_unix)
    record.update(octets=len(data), hex=data.hex())
    return record


def verified_late(t_unix: float, rx_unix: float, sender: tuple[int, int, int | None],
                  outcome: str, stepped: bool) -> dict[str, Any]:
    """What became of a deferred message (``obu.verify.jsonl``) that its tick stepped
    unverified (``stepped``), or that was dropped from the verification queue before its
    tick: at ``t_unix`` (wall clock), the message received at ``rx_unix`` from ``sender``
    (TemporaryID, msgCnt, secMark: its ``obu.rx`` record's key) ended ``outcome``: ``ok``
    or the verdict that rejected it (verified late), ``skipped`` (dropped from the queue
    unverified) or ``pending`` (still queued when the OBU stopped)."""
    return {"t_unix": t_unix, "rx_unix": rx_unix, "id": hex_id(sender[0]),
            "msgCnt": sender[1], "sec_mark": sender[2], "outcome": outcome,
            "stepped": stepped}


def _finite(x: float, digits: int) -> float | None:
    return round(x, digits) if x == x else None


def tick(snap: Any, host_sec_mark: int, step_ms: float, decided_unix: float
         ) -> dict[str, Any]:
    """One OBU tick (``obu.ticks.jsonl``) of :class:`catc.cam.MapSnapshot` ``snap``: its
    time on the host's secMark clock, the host's ENU position, speed and heading, how many
    RVs it tracked, the step's CPU time, when it was decided, and every warning that holds
    as ``[app, RV id, range m, threshold m or None, side]``."""
    return {
        "t": snap.t, "sec_mark": host_sec_mark,
        "host": [round(snap.host.x, 4), round(snap.host.y, 4)],
        "host_speed": round(snap.host.speed, 3), "host_heading": round(snap.host.heading, 3),
        "tracked": len(snap), "step_ms": round(step_ms, 3), "decided_unix": decided_unix,
        "warnings": [[w.app, hex_id(w.rv_id), round(w.range_m, 3),
                      _finite(w.threshold_m, 3), w.side] for w in snap.warnings],
        **unverified(snap)}


def unverified(snap: Any) -> dict[str, Any]:
    """``unverified``: the RVs (hex ids) whose track no verified message fed last (the
    snapshot's ``verified`` column, verify on demand); ``{}`` when there is none."""
    verified = getattr(snap, "verified", None)
    if verified is None or verified.all():
        return {}
    return {"unverified": [hex_id(int(i)) for i in snap.ids[~verified]]}


def track_rows(snap: Any, host_sec_mark: int) -> list[dict[str, Any]]:
    """Every tracked RV of ``snap`` as rows (``obu.tracks.bin`` read back, the live view): the
    estimate (ENU m, m/s, degrees), where it came from (``source``: the predictor or
    ``bsm``), its age and freshness, lane, zone now and at the prediction horizon
    (``[ahead, lateral code, direction code]``, :mod:`catc.classify`), and the path-frame
    offsets ``s``, ``d``."""
    z, pz = snap.zone, snap.predicted_zone
    rows = []
    for i in range(len(snap)):
        rows.append({
            "t": snap.t, "sec_mark": host_sec_mark, "id": hex_id(int(snap.ids[i])),
            "x": round(float(snap.x[i]), 7), "y": round(float(snap.y[i]), 7),
            "speed": round(float(snap.speed[i]), 3), "heading": round(float(snap.heading[i]), 3),
            "source": snap.source[i], "age": round(float(snap.age[i]), 3),
            "fresh": bool(snap.fresh[i]), "lane": int(snap.lane[i]),
            "zone": [bool(z.ahead[i]), int(z.lateral[i]), int(z.direction[i])],
            "s": round(float(z.s[i]), 3), "d": round(float(z.d[i]), 3),
            "predicted_x": round(float(snap.pred_x[i]), 7),
            "predicted_y": round(float(snap.pred_y[i]), 7),
            "predicted_zone": [bool(pz.ahead[i]), int(pz.lateral[i]), int(pz.direction[i])]})
    return rows


def track_columns(snap: Any) -> dict[str, Any]:
    """Every tracked RV of ``snap`` as columns (``obu.tracks.bin``, one block per tick,
    :class:`hil.capture.tracks.TrackWriter`): the fields of :func:`track_rows`, the zones
    split into ``ahead, lateral, direction`` and ``p_ahead, p_lateral, p_direction``.  The
    file keeps what :func:`track_rows` rounds to: positions to 1e-7 m, the rest to 1e-3."""
    z, pz = snap.zone, snap.predicted_zone
    return {"id": snap.ids, "x": snap.x, "y": snap.y, "speed": snap.speed,
            "heading": snap.heading, "source": snap.source, "age": snap.age,
            "fresh": snap.fresh, "lane": snap.lane, "ahead": z.ahead, "lateral": z.lateral,
            "direction": z.direction, "s": z.s, "d": z.d, "predicted_x": snap.pred_x,
            "predicted_y": snap.pred_y, "p_ahead": pz.ahead, "p_lateral": pz.lateral,
            "p_direction": pz.direction}


def event(e: Any) -> dict[str, Any]:
    """A warning's start or end (``obu.events.jsonl``, and the OBU's stdout): the app, the
    RV, the time it happened and the time the warning started."""
    return {"app": e.app, "kind": e.kind, "rv": hex_id(int(e.rv_id)),
            "t": e.t_start if e.kind == "start" else e.t_end, "t_start": e.t_start}


def finding(t_unix: float, t: float, reporter: int | None, detection: Any, bsm: Any,
            data: bytes) -> dict[str, Any]:
    """A misbehavior finding (``obu.mbd.jsonl``): when (wall clock, host clock), who
    found it (the host's TemporaryID), the :class:`catc.mbd.Detection` and the message
    that raised it."""
    d = detection
    return {"t_unix": t_unix, "t": t, "reporter": None if reporter is None else hex_id(reporter),
            "suspect": hex_id(d.suspect), "check": d.check, "score": round(d.score, 4),
            "evidence": d.evidence, "other": None if d.other is None else hex_id(d.other),
            "msgCnt": bsm.msg_cnt, "sec_mark": bsm.sec_mark, "hex": data.hex()}


def report(t_unix: float, t: float, reporter: int | None, detection: Any, bsm: Any,
           data: bytes) -> dict[str, Any]:
    """A misbehavior report (``obu.mbr.jsonl``; :attr:`catc.mbd.MisbehaviorDetector.reports`):
    a finding, as :func:`finding` has it, filed once its sender's evidence passed the
    reporting threshold.  ``found_t`` is when it was found (host clock; earlier than
    ``t`` for the weak findings that led there); the message is the one that filed it."""
    return {**finding(t_unix, t, reporter, detection, bsm, data), "found_t": detection.t}
