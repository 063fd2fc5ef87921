"""``rve run --host-bus``: the host vehicle's own side, as its OBU would see it: the car's
CAN bus and a GNSS receiver's NMEA 0183.

:func:`prepare` makes the whole schedule before the replay starts (bad values are one
line): the host's CAN frames through the vehicle profile's DBC, every message at its
rate (:func:`catc.vehicle.encode.host_frames`), and a GNSS epoch every 0.1 s of UTC with
seeded noise, latency, losses and outages (:func:`catc.vehicle.encode.gnss_epochs`).  A
dataset that recorded them (``table.meta["vehicle_can"]``, ``table.meta["gnss_fixes"]``)
is replayed as it was instead: bus 0 onto the host CAN bus, bus 1 onto
``--radar-can-channel`` when one is given (else not sent).

:class:`HostBus` opens the host CAN bus with python-can (``--host-can-interface``,
``--host-can-channel``, ``--host-can-fd``; or ``slcan``: it plays a serial USB-CAN adapter
on a pty whose slave the channel links to, :class:`_SlcanPty`) and the NMEA sink
(``--nmea``): ``udp:HOST:PORT`` (one datagram per epoch with all its sentences),
``pty:PATH`` (a pseudo-terminal whose slave PATH links to, for gpsd or an OBU to open; the
link is removed at the end) or ``file:PATH`` (appended).  :meth:`HostBus.run` runs beside
the replay loop of :mod:`rve.run` on the same clock (its :class:`hil.pacing.Pacer`: the
same start, speed and ``--asap``), sending each frame and epoch at its time, and stops
with the replay.

Capture (``--capture``): ``rve.hostbus.log`` (every CAN frame sent, candump log format)
and ``rve.gnss.jsonl`` (every epoch: ``t_send`` and ``t_fix`` in the dataset's clock, UTC,
the position sent, the true one, ``dropped``: null, ``loss`` or ``outage``, and the wall
clock it was sent at), append-only and flushed with the other files.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import socket
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from catc.gnss import DEFAULT_UTC_BASE, Fix, to_nmea
from catc.replay import Plan
from catc.vehicle.encode import FRAME_DTYPE, GnssEpoch, gnss_epochs, host_frames
from hil.capture import CanLogs, JsonLines, schema
from hil.errors import write_error

__all__ = ["HOST_CHANNELS", "HostBus", "HostBusPlan", "ReplayClock", "nmea_spec", "outage",
           "outages", "prepare"]

#: The host CAN bus's channel when none is given: not the RV transport's own default.
HOST_CHANNELS = {"socketcan": "vcan1", "virtual": "catc-hil-host",
                 "udp_multicast": "239.74.163.3", "slcan": "catc-hil-can.pty"}


def nmea_spec(text: str) -> tuple[str, Any]:
    """``udp:HOST:PORT``, ``pty:PATH`` or ``file:PATH`` (the argparse type of --nmea)."""
    from hil.config import destination

    kind, sep, rest = text.partition(":")
    if not sep or not rest or kind not in ("udp", "pty", "file"):
        raise argparse.ArgumentTypeError(
            f"not udp:HOST:PORT, pty:PATH or file:PATH: {text!r}")
    return (kind, destination(rest)) if kind == "udp" else (kind, rest)


def outage(text: str) -> tuple[float, float]:
    """``START:DURATION`` in seconds from the replay's start (--gnss-outage)."""
    a, sep, b = text.partition(":")
    try:
        start, duration = float(a), float(b)
    except ValueError:
        start = duration = math.nan
    if not sep or not (math.isfinite(start) and math.isfinite(duration)) or start < 0 \
            or duration <= 0:
        raise argparse.ArgumentTypeError(
            f"not START:DURATION (s, START >= 0, DURATION > 0): {text!r}")
    return start, duration


def outages(given: Any) -> list[tuple[float, float]]:
    """--gnss-outage's values (strings from the command line or a TOML list, pairs from
    a caller), checked: ValueError, one line, for a bad one."""
    out = []
    for item in given or ():
        if isinstance(item, (tuple, list)) and len(item) == 2:
            item = f"{item[0]}:{item[1]}"
        try:
            out.append(outage(str(item)))
        except argparse.ArgumentTypeError as err:
            raise ValueError(f"--gnss-outage: {err}") from None
    return out


@dataclass
class HostBusPlan:
    """What the host bus sends: ``frames`` (:data:`FRAME_DTYPE`-like, bus 0 the host's, 1
    the radar's) and GNSS ``epochs`` (sent or dropped), both within the replay;
    ``recorded`` when they come from the dataset."""

    frames: np.ndarray
    epochs: list[GnssEpoch]
    utc_base: float
    recorded: dict[str, bool] = field(default_factory=dict)


def prepare(args: argparse.Namespace, the_plan: Plan) -> HostBusPlan:
    """The host bus's schedule for ``the_plan`` (ValueError, one line, for bad values;
    :class:`hil.vehicle.ProfileError` for a bad profile or DBC)."""
    table = the_plan.table
    track = table.tracks[the_plan.host_id]
    times = the_plan.events["time"]
    start = float(times[0]) if len(times) else float(track.t[0])
    end = float(times[-1]) if len(times) else start
    utc_base = float(table.meta.get("utc_base", DEFAULT_UTC_BASE))
    recorded = {"can": "vehicle_can" in table.meta, "gnss": "gnss_fixes" in table.meta}
    if recorded["can"]:
        rec = np.asarray(table.meta["vehicle_can"])
        keep = (rec["t"] >= start - 1e-9) & (rec["t"] <= end + 1e-9)
        if getattr(args, "radar_can_channel", None) is None:
            keep &= rec["bus"] == 0
        else:
            keep &= (rec["bus"] == 0) | (rec["bus"] == 1)
        rec = rec[keep]
        frames = np.zeros(len(rec), FRAME_DTYPE)
        for name in FRAME_DTYPE.names:
            frames[name] = rec[name]
        frames = frames[np.argsort(frames["t"], kind="stable")]
    else:
        from hil.vehicle import load_profile

        profile, db = load_profile(args.vehicle, Path(args.dbc) if args.dbc else None)
        frames = host_frames(track, profile, db, start, end)
    if not getattr(args, "host_can_fd", False) and len(frames) \
            and int(frames["length"].max()) > 8:
        raise ValueError("the host bus has frames over 8 octets: give --host-can-fd")
    if recorded["gnss"]:
        epochs = []
        for t_send, fix in table.meta["gnss_fixes"]:
            t_send = float(t_send)
            if start - 1e-9 <= t_send <= end + 1e-9:
                t_fix = fix.t_unix - utc_base
                epochs.append(GnssEpoch(
                    t_send, fix, float(np.interp(t_fix, track.t, track.lat)),
                    float(np.interp(t_fix, track.t, track.lon))))
    else:
        epochs = [e for e in gnss_epochs(
            track, utc_base, noise_m=args.gnss_noise, latency_s=args.gnss_latency / 1000.0,
            loss=args.gnss_loss / 100.0, outages=outages(args.gnss_outage), seed=args.seed,
            start=start, end=end) if e.t_send <= end + 1e-9]
    return HostBusPlan(frames, epochs, utc_base, recorded)


class ReplayClock:
    """The replay's clock as the host bus waits on it: the Pacer's deadlines in real time;
    with ``--asap`` the replay loop's progress (:meth:`advance`), so both streams keep
    their order."""

    def __init__(self, pacer: Any) -> None:
        self.pacer = pacer
        self.now = -math.inf
        self._moved = asyncio.Event()

    def advance(self, t: float) -> None:
        """The replay loop is about to send what is due at ``t``."""
        self.now = t
        self._moved.set()

    async def wait(self, t: float) -> None:
        if self.pacer.speed is not None:
            ahead = self.pacer.deadline(t) - self.pacer.clock()
            if ahead > 0:
                await asyncio.sleep(ahead)
            return
        while self.now < t:
            self._moved.clear()
            await self._moved.wait()


class _NmeaSink:
    """Where the NMEA goes: a UDP peer, a pseudo-terminal or a file (module docstring)."""

    def __init__(self, spec: tuple[str, Any]) -> None:
        self.kind, self.where = spec
        self.dropped = 0  # epochs a full pty did not take
        self._sock: socket.socket | None = None
        self._fds: tuple[int, int] | None = None
        self._link: str | None = None
        self._file: Any = None
        if self.kind == "udp":
            host, port = self.where
            try:
                info = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
            except OSError as err:
                raise OSError(err.errno, f"cannot resolve NMEA host {host}: "
                              f"{err.strerror}") from None
            self._sock = socket.socket(info[0], socket.SOCK_DGRAM)
            self._addr = info[4]
        elif self.kind == "pty":
            path = self.where
            if os.path.lexists(path) and not os.path.islink(path):
                raise FileExistsError(f"--nmea pty:{path}: exists and is no symbolic link")
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._fds = (master, slave)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            try:
                os.symlink(os.ttyname(slave), path)
            except OSError:
                self.close()
                raise
            self._link = path
        else:
            self._file = open(self.where, "ab")  # noqa: SIM115

    @property
    def name(self) -> str:
        """The pty's slave device (for ``pty:``), else the sink's spec."""
        if self._fds is not None:
            return os.ttyname(self._fds[1])
        return f"{self.kind}:{self.where}"

    def send(self, data: bytes) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):  # nobody listening: UDP drops it
                self._sock.sendto(data, self._addr)
        elif self._fds is not None:
            try:
                os.write(self._fds[0], data)
            except BlockingIOError:  # nobody reads the pty: drop the epoch
                self.dropped += 1
        else:
            try:
                self._file.write(data)
                self._file.flush()
            except OSError as err:
                raise write_error(err, self.where) from None

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
        if self._link is not None:
            with contextlib.suppress(OSError):
                if os.path.islink(self._link):
                    os.unlink(self._link)
            self._link = None
        if self._fds is not None:
            for fd in self._fds:
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._fds = None
        if self._file is not None:
            self._file.close()


class _SlcanPty:
    """A serial CAN adapter played on a pseudo-terminal (``--host-can-interface slcan``):
    each frame is written as its slcan line (:mod:`catc.vehicle.slcan`) to the pty's
    master; PATH links to its slave, which an OBU opens as it would a USB-CAN adapter's
    tty.  What the OBU sends the adapter (``S6``, ``O``) is read and ignored.  A pty
    nobody reads fills up: the frame is then refused (``can.CanError``, counted)."""

    def __init__(self, path: str) -> None:
        self.sink = _NmeaSink(("pty", path))

    def send(self, msg: Any, timeout: float | None = None) -> None:
        import can

        from catc.vehicle.slcan import encode

        assert self.sink._fds is not None
        master = self.sink._fds[0]
        with contextlib.suppress(BlockingIOError, OSError):
            os.read(master, 4096)  # the OBU's commands to its adapter
        try:
            os.write(master, encode(msg.arbitration_id, bytes(msg.data), fd=msg.is_fd))
        except BlockingIOError:
            raise can.CanError("the pty is full: nobody reads it") from None

    def shutdown(self) -> None:
        self.sink.close()


def _open_can(interface: str, channel: str, fd: bool) -> Any:
    import can

    from hil.transport import TransportError, os_reason

    if interface == "slcan":
        try:
            return _SlcanPty(channel)
        except OSError as exc:
            raise TransportError(f"cannot make the slcan pty {channel}: "
                                 f"{os_reason(exc)}") from exc

    try:
        return can.Bus(interface=interface, channel=channel, fd=fd, receive_own_messages=False)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        raise TransportError(
            f"cannot open host CAN bus {interface}:{channel}: {os_reason(exc)}") from exc


class HostBus:
    """The host bus of one replay: :meth:`open`, :meth:`run` beside the replay, :meth:`close`.
    ``counts``: ``host_can_frames`` sent, ``host_can_errors`` (the bus refused a frame),
    ``nmea_epochs`` sent, ``gnss_dropped`` (lost or in an outage), ``nmea_full`` (a pty
    nobody read)."""

    def __init__(self, args: argparse.Namespace, hplan: HostBusPlan,
                 capture_dir: Path | None = None) -> None:
        self.args = args
        self.plan = hplan
        self.capture_dir = capture_dir
        self.fd = bool(args.host_can_fd)
        self.channel = args.host_can_channel or HOST_CHANNELS.get(args.host_can_interface,
                                                                  "can1")
        self.buses: dict[int, Any] = {}
        self.names: dict[int, str] = {}
        self.sink: _NmeaSink | None = None
        self.canlog: CanLogs | None = None
        self.gnsslog: JsonLines | None = None
        self.counts = {"host_can_frames": 0, "host_can_errors": 0, "nmea_epochs": 0,
                       "gnss_dropped": 0}

    def open(self) -> None:
        """Open the buses, the NMEA sink and the capture files (TransportError or OSError,
        one line, when one cannot be; everything opened is closed again)."""
        try:
            self.buses[0] = _open_can(self.args.host_can_interface, self.channel, self.fd)
            self.names[0] = self.channel
            radar = self.args.radar_can_channel
            if radar is not None and (self.plan.frames["bus"] == 1).any():
                self.buses[1] = _open_can(self.args.host_can_interface, radar, self.fd)
                self.names[1] = radar
            if self.args.nmea is not None:
                self.sink = _NmeaSink(self.args.nmea)
            if self.capture_dir is not None:
                import can

                self.canlog = CanLogs([can.CanutilsLogWriter(
                    self.capture_dir / schema.RVE_HOSTBUS_LOG, channel=self.channel,
                    append=True)])
                self.gnsslog = JsonLines(self.capture_dir / schema.RVE_GNSS)
        except BaseException:
            self.close()
            raise

    def files(self) -> list[Any]:
        """The capture files, for the replay's capture to flush and close."""
        return [f for f in (self.canlog, self.gnsslog) if f is not None]

    async def run(self, clock: ReplayClock) -> None:
        """Send every frame and epoch at its time on ``clock``; returns when all are sent
        (cancel it to stop early)."""
        import can

        frames = self.plan.frames
        epochs = self.plan.epochs
        f_t = frames["t"].tolist()
        e_t = [e.t_send for e in epochs]
        i = k = 0
        while i < len(f_t) or k < len(e_t):
            due = min(f_t[i] if i < len(f_t) else math.inf,
                      e_t[k] if k < len(e_t) else math.inf)
            await clock.wait(due)
            while i < len(f_t) and f_t[i] <= due:
                row = frames[i]
                bus_no = int(row["bus"])
                bus = self.buses.get(bus_no)
                i += 1
                if bus is None:
                    continue
                length = int(row["length"])
                data = bytes(row["data"]).ljust(length, b"\0")[:length]
                address = int(row["address"])
                msg = can.Message(arbitration_id=address, data=data,
                                  is_extended_id=address > 0x7FF, is_fd=self.fd,
                                  bitrate_switch=self.fd, is_rx=False,
                                  timestamp=time.time(), channel=self.names[bus_no])
                try:
                    bus.send(msg)
                except can.CanError:
                    self.counts["host_can_errors"] += 1
                    continue
                self.counts["host_can_frames"] += 1
                if self.canlog is not None:
                    self.canlog.on_message_received(msg)
            while k < len(e_t) and e_t[k] <= due:
                self._epoch(epochs[k])
                k += 1

    def _epoch(self, e: GnssEpoch) -> None:
        sent_unix = None
        if e.dropped is None:
            if self.sink is not None:
                self.sink.send(b"".join(to_nmea(e.fix)))
            sent_unix = time.time()
            self.counts["nmea_epochs"] += 1
        else:
            self.counts["gnss_dropped"] += 1
        if self.gnsslog is not None:
            self.gnsslog.write(_gnss_record(e, self.plan.utc_base, sent_unix))

    def close(self) -> None:
        """Close the buses and the NMEA sink (the capture files go with the capture)."""
        for bus in self.buses.values():
            with contextlib.suppress(Exception):
                bus.shutdown()
        self.buses.clear()
        if self.sink is not None:
            self.counts["nmea_full"] = self.sink.dropped
            self.sink.close()
            self.sink = None


def _gnss_record(e: GnssEpoch, utc_base: float, sent_unix: float | None) -> dict[str, Any]:
    fix: Fix = e.fix
    return {"t_send": round(e.t_send, 6), "t_fix": round(fix.t_unix - utc_base, 6),
            "utc": fix.t_unix, "lat": fix.lat, "lon": fix.lon, "alt_m": fix.alt_m,
            "speed_mps": fix.speed_mps, "course_deg": fix.course_deg,
            "std_m": fix.std_lat_m, "true_lat": e.true_lat, "true_lon": e.true_lon,
            "dropped": e.dropped, "sent_unix": sent_unix}
