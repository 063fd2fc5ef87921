"""The OBU's capture directory (``obu run --capture DIR``): its files and records, all as
:mod:`hil.capture.schema` names and builds them.

The per-tick files (``obu.rx.jsonl.gz``, ``obu.ticks.jsonl``, ``obu.tracks.bin``,
``obu.events.jsonl``, ``obu.mbr.jsonl``) are append-only and flushed at every tick, so
``kill -9`` loses at most the last tick; the config and the counters are rewritten whole
(through a temporary file and a rename, so a reader never sees half of one).

"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from catc.bsm import BSM
from catc.cam import MapSnapshot
from hil.capture import GzipJsonLines, JsonLines, TrackWriter, claim, schema, versions

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
        self.mbd = bool(args.mbd)
        self._open(0)
        self.settings = schema.settings(args)
        self.origin_written = False
        self.write_config(None)

    def _open(self, k: int) -> None:
        """The per-tick files of segment ``k`` (0: the names of the schema)."""
        def path(name: str) -> Path:
            return self.dir / schema.segment_name(name, k)

        self.rx = GzipJsonLines(path(schema.OBU_RX))
        self.ticks = JsonLines(path(schema.OBU_TICKS))
        self.tracks = TrackWriter(path(schema.OBU_TRACKS))
        self.events = JsonLines(path(schema.OBU_EVENTS))
        self.mbr = JsonLines(path(schema.OBU_MBR)) if self.mbd else None

    def _replace(self, name: str, text: str) -> None:
        tmp = self.dir / f"{name}.tmp"
        tmp.write_text(text)
        tmp.replace(self.dir / name)

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
        self.tracks.write(snap.t, host_sec_mark, schema.track_columns(snap))
        self.flush()

    def _files(self) -> list[Any]:
        return [f for f in (self.rx, self.ticks, self.tracks, self.events, self.mbr)
                if f is not None]

    def flush(self) -> None:
        for f in self._files():
            f.flush()

    def close(self) -> None:
        for f in self._files():
            f.close()
