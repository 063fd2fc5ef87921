"""The RVE's capture directory (``rve run --capture DIR``), written through
:mod:`hil.capture.schema`.

* ``rve.config.json``: the run's settings, versions and vehicle ids
  (:func:`hil.capture.schema.rve_config`), written when the capture opens;
* ``rve.truth.jsonl``: the true state of every vehicle at every 10 Hz sample
  (:func:`hil.capture.schema.truth`), up to the last host tick sent;
* ``rve.end.json``: how the run ended (:func:`hil.capture.schema.end`), written as it
  ends, after the other files are closed (:meth:`Capture.end`); missing when the RVE was
  killed;
* ``rve.schedule.jsonl``: every scheduled message with its channel decision and, when
  sent, its wall-clock send time and lateness (:func:`hil.capture.schema.scheduled`,
  :func:`hil.capture.schema.sent`);
* ``rve.frames.pcapng`` (UDP datagrams with their IP/UDP headers, or with ``--framing
  wsmp`` Ethernet II frames of ethertype 0x88DC as over the air) or ``rve.frames.asc`` and
  ``rve.frames.log`` (every raw CAN frame, :func:`hil.capture.can_log`);
* with ``--host-bus``, ``rve.hostbus.log`` and ``rve.gnss.jsonl`` (:mod:`rve.hostbus`),
  which :meth:`Capture.attach` adds.

Every file is append-only; the replay flushes them at every host tick.  A write that
fails (a full disk) raises :class:`hil.errors.WriteError` naming the file; the others
are flushed and closed all the same, and the end record names the failure.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from catc.channel import CAUSES
from catc.j2735.ieee1609 import ETHERTYPE_WSMP
from catc.replay import Plan, temp_id
from hil.capture import (
    JsonLines,
    PcapngWriter,
    can_log,
    claim,
    ethernet,
    finish,
    schema,
    udp_packet,
    versions,
)
from hil.errors import write_error
from rve.framing import framing_of

__all__ = ["Capture", "can_channel"]

Address = tuple[str, int]


def can_channel(args: argparse.Namespace) -> str:
    """The bus channel the CAN frames go out on, as the candump log names it."""
    if args.can_channel:
        return str(args.can_channel)
    from hil.transport.can import DEFAULT_CHANNELS

    return DEFAULT_CHANNELS.get(args.can_interface, "can0")


class Capture:
    """The RVE's capture files (module docstring) for one replay of ``the_plan``."""

    def __init__(self, directory: Path, the_plan: Plan, args: argparse.Namespace) -> None:
        self.dir = directory
        directory.mkdir(parents=True, exist_ok=True)
        claim(directory, "rve", bool(getattr(args, "overwrite", False)))
        self.run_id = schema.new_run_id()
        self.started = time.time()
        self.schedule = JsonLines(directory / schema.RVE_SCHEDULE)
        self.truth = JsonLines(directory / schema.RVE_TRUTH)
        self.wsmp = framing_of(args) == "wsmp"  # the pcapng gets Ethernet/0x88DC frames
        self.pcap = PcapngWriter(directory / schema.RVE_PCAPNG) \
            if args.transport == "udp" else None
        self.canlog = can_log(directory / schema.RVE_CAN_STEM, can_channel(args)) \
            if args.transport == "can" else None
        self.to: Address = args.to
        self.host_to: Address = args.host_to
        #: where each channel's datagrams come from (the sockets' own ports): :meth:`sources`
        self.src: dict[str, Address] = {}
        table = the_plan.table
        config = schema.rve_config(
            schema.settings(args), versions(), (table.name, table.kind, table.origin),
            the_plan.host_id, {v: temp_id(v) for v in the_plan.vehicles},
            dataclasses.asdict(the_plan.config), the_plan.seed, self.started, self.run_id)
        with open(directory / schema.RVE_CONFIG, "w", encoding="utf-8") as f:
            json.dump(config, f, indent=1, default=str)
        self._truth_pos = {v: 0 for v in the_plan.vehicles}
        #: more files flushed and closed with these (``--host-bus``'s: :meth:`attach`)
        self.extra: list[Any] = []

    def attach(self, files: list[Any]) -> None:
        """Flush ``files`` with the others at every host tick and close them at the end
        (writers of :mod:`hil.capture.writers`, :class:`hil.capture.CanLogs`)."""
        self.extra.extend(files)

    def sources(self, src: dict[str, Address]) -> None:
        """The sender's local address of each channel (``rv``, ``host``), for the pcapng."""
        self.src = src

    def write_truth(self, the_plan: Plan, up_to: float) -> None:
        """Truth rows of every vehicle for samples generated at or before ``up_to``."""
        for v in the_plan.vehicles:
            tr = the_plan.table.tracks[v]
            lo = self._truth_pos[v]
            hi = int(np.searchsorted(tr.t, up_to + 1e-9, side="right"))
            for i in range(lo, hi):
                self.truth.write(schema.truth(
                    v, temp_id(v), i, float(tr.t[i]), float(tr.lat[i]), float(tr.lon[i]),
                    float(tr.x[i]), float(tr.y[i]), float(tr.speed[i]),
                    float(tr.heading[i]), float(tr.accel[i]), float(tr.yaw_rate[i]),
                    v == the_plan.host_id))
            self._truth_pos[v] = hi

    def write_event(self, ev: Any, vehicle: str, tid: int, frame: bytes | None,
                    when: tuple[float, float] | None, attack: Any = None) -> None:
        """The schedule record of one planned event of ``vehicle`` (TemporaryID ``tid``),
        labelled with the ``attack`` that changed it; its ``frame`` into the pcapng when
        it was sent at ``when`` (wall clock, lateness s)."""
        host = bool(ev["host"])
        channel = "host" if host else "rv"
        record = schema.scheduled(
            vehicle, tid, channel, int(ev["index"]), int(ev["seq"]), float(ev["t"]),
            bool(ev["dropped"]), CAUSES[int(ev["cause"])],
            None if ev["dropped"] else float(ev["delay"]),
            attack=None if attack is None else attack.kind)
        if frame is not None:
            schema.sent(record, when[0], when[1], len(frame))
            if self.pcap is not None:
                self._pcap(channel, tid, frame, when[0])
        self.schedule.write(record)

    def write_attack(self, record: dict[str, Any], frame: bytes,
                     when: tuple[float, float]) -> None:
        """The schedule record (labelled with its attack) and capture of an attack frame
        (:meth:`rve.attacking.Attacking.frames`) sent at ``when``."""
        record = schema.sent(dict(record), when[0], when[1], len(frame))
        if self.pcap is not None:
            self._pcap("rv", int(record["id"], 16), frame, when[0])
        self.schedule.write(record)

    def _pcap(self, channel: str, tid: int, frame: bytes, t_unix: float) -> None:
        """One sent frame into the pcapng: as a UDP datagram, or with --framing wsmp as it
        goes over the air (Ethernet II, ethertype 0x88DC, from a MAC made of the sender's
        TemporaryID)."""
        if self.wsmp:
            mac = b"\x02\x00" + tid.to_bytes(4, "big")
            self.pcap.write(ethernet(b"\xff" * 6, mac, ETHERTYPE_WSMP, frame), t_unix,
                            self.pcap.ETHERNET)
        else:
            self.pcap.write(udp_packet(self.src[channel],
                                       self.host_to if channel == "host" else self.to,
                                       frame), t_unix)

    def flush(self) -> None:
        """Hand every file's new lines and frames to the OS (once per host tick)."""
        self.schedule.flush()
        self.truth.flush()
        if self.pcap is not None:
            self.pcap.flush()
        if self.canlog is not None:
            self.canlog.flush()
        for f in self.extra:
            f.flush()

    def write_end(self, exit: str, reason: str, **counts: int) -> None:
        """How the run ended (``rve.end.json``, :func:`hil.capture.schema.end`)."""
        path = self.dir / schema.RVE_END
        try:
            with open(path, "w", encoding="utf-8") as f:
                json.dump(schema.end(self.run_id, exit, reason, self.started, time.time(),
                                     **counts), f, indent=1)
        except OSError as err:
            raise write_error(err, path) from None

    def end(self, exit: str, reason: str, **counts: int) -> None:
        """Flush and close every file (all of them, even when one fails), then write how
        the run ended; a file that could not be written raises once the end record says
        so (the run's own error, when it had one, stays its reason)."""
        failure = finish(f for f in (self.schedule, self.truth, self.pcap, self.canlog,
                                     *self.extra) if f is not None)
        if failure is not None and exit != "error":
            exit, reason = schema.failed(failure)
        self.write_end(exit, reason, **counts)
        if failure is not None:
            raise failure
