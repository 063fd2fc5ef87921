"""The OBU's capture directory (``obu run --capture DIR``): its files and records, all as
:mod:`hil.capture.schema` names and builds them.

The per-tick files (``obu.rx.jsonl.gz``, ``obu.ticks.jsonl``, ``obu.tracks.bin``,
``obu.events.jsonl``, ``obu.mbd.jsonl``, ``obu.mbr.jsonl``) are append-only and flushed at
every tick, so ``kill -9`` loses at most the last tick; the config and the counters are
rewritten whole (through a temporary file and a rename, so a reader never sees half of
one).

The cap (``obu run --capture-max-mb N``).  The per-tick files are then written in
segments of N/10 MB, a time slice each: after a tick that took the current segment past
N/10 MB every file starts its next segment (:func:`hil.capture.schema.segment_name`), and
while the OBU's files take more than 0.9 N MB (room for the new segment) the oldest
segment is deleted, but never the first (the start of the run: its ENU origin, its first
tick, which the score's clocks join on) nor the current one.  The directory thus holds
the run's start and its latest minutes, within N MB and one tick's records; ``captures
score`` reads what is left, names the deleted segments, and counts their ticks as missing
(an incomplete run).  The counters and the end record say how many segments were written
and deleted.  A write that fails (a full disk) raises
:class:`hil.errors.WriteError` naming the file; :meth:`ObuCapture.end` still flushes and
closes the others and writes the end record, which names the failure.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from catc.bsm import BSM
from catc.cam import MapSnapshot
from hil.capture import GzipJsonLines, JsonLines, TrackWriter, claim, finish, schema, versions
from hil.errors import write_error

__all__ = ["OBU_VEHICLE", "ObuCapture", "Received"]

#: The host's estimated state at every tick, with ``--host-source vehicle``
#: (:func:`obu.vehicle.vehicle_record`); not segmented.
OBU_VEHICLE = "obu.vehicle.jsonl"

#: An RV message at its tick: the BSM, its receive time (unix s), its octets, its
#: IEEE 1609.2 verdict (None when frames are not verified, or not yet) and, verifying on
#: demand, when it was verified (``at-once``, ``queue``, ``deferred``: not by its tick).
Received = tuple[BSM, float | None, bytes, str | None, str | None]


class ObuCapture:
    """The files of one OBU run in ``directory`` (created): ``obu.config.json`` at once
    (and again with the ENU origin at the first tick), the JSON-lines records as they
    come, ``obu.mbd.jsonl`` and ``obu.mbr.jsonl`` only with ``--mbd``."""

    def __init__(self, directory: Path, args: argparse.Namespace) -> None:
        self.dir = directory
        directory.mkdir(parents=True, exist_ok=True)
        claim(directory, "obu", getattr(args, "overwrite", False))
        self.run_id = schema.new_run_id()
        self.started = time.time()
        self.mbd = bool(args.mbd)
        self.ondemand = (getattr(args, "verify", None) == "enforce"
                         and getattr(args, "verify_policy", "all") == "on-demand")
        cap_mb = getattr(args, "capture_max_mb", None)
        self.max_bytes = None if cap_mb is None else float(cap_mb) * 1e6
        self.segment = 0
        self.dropped: list[int] = []
        self._open(0)
        self.vehicle_log = (JsonLines(directory / OBU_VEHICLE)
                            if getattr(args, "host_source", None) == "vehicle" else None)
        self.settings = schema.settings(args)
        self.origin_written = False
        self.write_config(None)

    def _open(self, k: int) -> None:
        """The per-tick files of segment ``k``."""
        def path(name: str) -> Path:
            return self.dir / schema.segment_name(name, k)

        self.rx = GzipJsonLines(path(schema.OBU_RX))
        self.ticks = JsonLines(path(schema.OBU_TICKS))
        self.tracks = TrackWriter(path(schema.OBU_TRACKS))
        self.events = JsonLines(path(schema.OBU_EVENTS))
        self.mbd_log = JsonLines(path(schema.OBU_MBD)) if self.mbd else None
        self.mbr = JsonLines(path(schema.OBU_MBR)) if self.mbd else None
        self.verify_log = JsonLines(path(schema.OBU_VERIFY)) if self.ondemand else None

    def _segment_bytes(self) -> int:
        return sum(f.tell() for f in self._files())

    def _rotate(self) -> None:
        """Start the next segment when this one is full; then delete the oldest segments
        but the first while the OBU's files are over the cap (module docstring)."""
        if self.max_bytes is None or self._segment_bytes() < self.max_bytes / 10:
            return
        self.close()
        self.segment += 1
        self._open(self.segment)
        sizes: dict[int, int] = {}
        other = 0
        for p in self.dir.glob("obu.*"):
            parts = p.name.split(".")
            k = int(parts[2]) if len(parts) > 3 and parts[2].isdigit() else None
            if p.name in schema.SEGMENTED:
                k = 0
            try:
                size = p.stat().st_size
            except OSError:  # a config's temporary file, renamed meanwhile
                continue
            if k is None:
                other += size
            else:
                sizes[k] = sizes.get(k, 0) + size
        total = other + sum(sizes.values())
        for k in sorted(sizes):
            if total <= self.max_bytes * 0.9:  # room for the segment just started
                break
            if k in (0, self.segment):
                continue
            for name in schema.SEGMENTED:
                (self.dir / schema.segment_name(name, k)).unlink(missing_ok=True)
            total -= sizes[k]
            self.dropped.append(k)

    def _segments(self) -> dict[str, int]:
        """What the counters and the end record say of a capped capture's segments."""
        if self.max_bytes is None:
            return {}
        return {"capture_segments": self.segment + 1,
                "capture_segments_deleted": len(self.dropped)}

    def _replace(self, name: str, text: str) -> None:
        tmp = self.dir / f"{name}.tmp"
        try:
            tmp.write_text(text)
            tmp.replace(self.dir / name)
        except OSError as err:
            raise write_error(err, tmp) from None

    def write_config(self, origin: list[float] | None) -> None:
        """``obu.config.json`` with the ENU origin ``[lat, lon, h]`` (None before the
        first tick)."""
        config = schema.obu_config(self.settings, versions(), origin, self.started,
                                   self.run_id)
        self._replace(schema.OBU_CONFIG, json.dumps(config, indent=1, default=str))

    def write_origin(self, origin: list[float]) -> None:
        """The map's ENU origin into the config, once (the first tick that has it)."""
        if not self.origin_written:
            self.write_config(origin)
            self.origin_written = True

    def write_end(self, exit: str, reason: str, **counts: int) -> None:
        """How the run ended (``obu.end.json``, :func:`hil.capture.schema.end`)."""
        self._replace(schema.OBU_END, json.dumps(schema.end(
            self.run_id, exit, reason, self.started, time.time(), **counts,
            **self._segments()), indent=1))

    def write_counters(self, counters: dict[str, Any]) -> None:
        self._replace(schema.OBU_COUNTERS, json.dumps(counters | self._segments(), indent=1,
                                                      sort_keys=True))

    def frame(self, rx_unix: float | None, channel: str, data: bytes, status: str,
              **details: Any) -> None:
        """One received frame and what became of it (:func:`hil.capture.schema.received`,
        whose keywords ``details`` are)."""
        self.rx.write(schema.received(rx_unix, channel, data, status, **details))

    def message(self, received: Received, status: str, **details: Any) -> None:
        """One decoded RV message, stepped at a tick (``ok``) or never (``unticked``)."""
        m, rx_unix, data, verdict, verify = received
        self.frame(rx_unix, "rv", data, status, sender=(m.temp_id, m.msg_cnt, m.sec_mark),
                   verdict=verdict, verify=verify, **details)

    def late(self, rx_unix: float, bsm: BSM, outcome: str, stepped: bool) -> None:
        """What became of a deferred message stepped unverified, or dropped from the
        verification queue (:func:`hil.capture.schema.verified_late`)."""
        if self.verify_log is not None:
            self.verify_log.write(schema.verified_late(
                time.time(), rx_unix, (bsm.temp_id, bsm.msg_cnt, bsm.sec_mark), outcome,
                stepped))

    def finding(self, t_unix: float, t: float, reporter: int | None, detection: Any,
                bsm: BSM, data: bytes) -> None:
        """A misbehavior finding (:func:`hil.capture.schema.finding`), with ``--mbd``."""
        if self.mbd_log is not None:
            self.mbd_log.write(schema.finding(t_unix, t, reporter, detection, bsm, data))

    def report(self, t_unix: float, t: float, reporter: int | None, detection: Any,
               bsm: BSM, data: bytes) -> None:
        """A misbehavior report (:func:`hil.capture.schema.report`), with ``--mbd``."""
        if self.mbr is not None:
            self.mbr.write(schema.report(t_unix, t, reporter, detection, bsm, data))

    def event(self, record: dict[str, Any]) -> None:
        """A warning's start or end (:func:`hil.capture.schema.event`)."""
        self.events.write(record)

    def vehicle(self, record: dict[str, Any]) -> None:
        """The host's estimated state at a tick (``--host-source vehicle``), flushed."""
        if self.vehicle_log is not None:
            self.vehicle_log.write(record)
            self.vehicle_log.flush()

    def tick(self, snap: MapSnapshot, host_sec_mark: int, step_ms: float, decided: float,
             received: list[Received]) -> None:
        """One tick: the RV messages it took, the tick, its tracks; then flush (and, with
        a cap, start the next segment when this one is full)."""
        for r in received:
            self.message(r, "ok", tick=snap.t, decided_unix=decided)
        self.ticks.write(schema.tick(snap, host_sec_mark, step_ms, decided))
        self.tracks.write(snap.t, host_sec_mark, schema.track_columns(snap))
        self.flush()
        self._rotate()

    def _files(self) -> list[Any]:
        return [f for f in (self.rx, self.ticks, self.tracks, self.events, self.mbd_log,
                            self.mbr, self.verify_log) if f is not None]

    def flush(self) -> None:
        for f in self._files():
            f.flush()

    def close(self) -> None:
        """Flush and close the per-tick files (all of them, even when one fails; then the
        first failure raises)."""
        failure = finish(self._files())
        if failure is not None:
            raise failure

    def end(self, exit: str, reason: str, failure: OSError | None = None,
            **counts: int) -> None:
        """Flush and close every file (all of them, even when one fails), then write how
        the run ended; ``failure`` (a write that failed just before) or a file that could
        not be written now raises once the end record says so (the run's own error, when
        it had one, stays its reason)."""
        failure = finish(self._files() + [f for f in (self.vehicle_log,) if f is not None],
                         failure)
        if failure is not None and exit != "error":
            exit, reason = schema.failed(failure)
        self.write_end(exit, reason, **counts)
        if failure is not None:
            raise failure
