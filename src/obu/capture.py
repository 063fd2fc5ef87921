"""The OBU's capture directory (``obu run --capture DIR``): its files and records, all as
:mod:`hil.capture.schema` names and builds them.

The JSON-lines files are append-only and flushed at every tick, so ``kill -9`` loses at
most the last tick; the config and the counters are rewritten whole (through a temporary
file and a rename, so a reader never sees half of one).  A write that fails (a full
disk) raises :class:`hil.errors.WriteError` naming the file; :meth:`ObuCapture.end` still
flushes and closes the others and writes the end record, which names the failure.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from catc.bsm import BSM
from catc.cam import MapSnapshot
from hil.capture import JsonLines, claim, finish, schema, versions
from hil.errors import write_error

__all__ = ["ObuCapture", "Received"]

#: An RV message at its tick: the BSM, its receive time (unix s), its octets and its
#: IEEE 1609.2 verdict (None when frames are not verified).
Received = tuple[BSM, float | None, bytes, str | None]


class ObuCapture:
    """The files of one OBU run in ``directory`` (created): ``obu.config.json`` at once
    (and again with the ENU origin at the first tick), the JSON-lines records as they
    come, ``obu.mbr.jsonl`` only with ``--mbd``."""

    def __init__(self, directory: Path, args: argparse.Namespace) -> None:
        self.dir = directory
        directory.mkdir(parents=True, exist_ok=True)
        claim(directory, "obu", getattr(args, "overwrite", False))
        self.run_id = schema.new_run_id()
        self.started = time.time()
        self.rx = JsonLines(directory / schema.OBU_RX)
        self.ticks = JsonLines(directory / schema.OBU_TICKS)
        self.tracks = JsonLines(directory / schema.OBU_TRACKS)
        self.events = JsonLines(directory / schema.OBU_EVENTS)
        self.mbr = JsonLines(directory / schema.OBU_MBR) if args.mbd else None
        self.settings = schema.settings(args)
        self.origin_written = False
        self.write_config(None)

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
            self.run_id, exit, reason, self.started, time.time(), **counts), indent=1))

    def write_counters(self, counters: dict[str, Any]) -> None:
        self._replace(schema.OBU_COUNTERS, json.dumps(counters, indent=1, sort_keys=True))

    def frame(self, rx_unix: float | None, channel: str, data: bytes, status: str,
              **details: Any) -> None:
        """One received frame and what became of it (:func:`hil.capture.schema.received`,
        whose keywords ``details`` are)."""
        self.rx.write(schema.received(rx_unix, channel, data, status, **details))

    def message(self, received: Received, status: str, **details: Any) -> None:
        """One decoded RV message, stepped at a tick (``ok``) or never (``unticked``)."""
        m, rx_unix, data, verdict = received
        self.frame(rx_unix, "rv", data, status, sender=(m.temp_id, m.msg_cnt, m.sec_mark),
                   verdict=verdict, **details)

    def report(self, t_unix: float, t: float, reporter: int | None, detection: Any,
               bsm: BSM, data: bytes) -> None:
        """A misbehavior detection (:func:`hil.capture.schema.report`), with ``--mbd``."""
        if self.mbr is not None:
            self.mbr.write(schema.report(t_unix, t, reporter, detection, bsm, data))

    def event(self, record: dict[str, Any]) -> None:
        """A warning's start or end (:func:`hil.capture.schema.event`)."""
        self.events.write(record)

    def tick(self, snap: MapSnapshot, host_sec_mark: int, step_ms: float, decided: float,
             received: list[Received]) -> None:
        """One tick: the RV messages it took, the tick, its tracks; then flush."""
        for r in received:
            self.message(r, "ok", tick=snap.t, decided_unix=decided)
        self.ticks.write(schema.tick(snap, host_sec_mark, step_ms, decided))
        for row in schema.track_rows(snap, host_sec_mark):
            self.tracks.write(row)
        self.flush()

    def _files(self) -> list[JsonLines]:
        return [f for f in (self.rx, self.ticks, self.tracks, self.events, self.mbr)
                if f is not None]

    def flush(self) -> None:
        for f in self._files():
            f.flush()

    def end(self, exit: str, reason: str, failure: OSError | None = None,
            **counts: int) -> None:
        """Flush and close every file (all of them, even when one fails), then write how
        the run ended; ``failure`` (a write that failed just before) or a file that could
        not be written now raises once the end record says so (the run's own error, when
        it had one, stays its reason)."""
        failure = finish(self._files(), failure)
        if failure is not None and exit != "error":
            exit, reason = schema.failed(failure)
        self.write_end(exit, reason, **counts)
        if failure is not None:
            raise failure
