"""``obu run --host-source vehicle``: the host's own state from its car's CAN bus and a
GNSS receiver, as a host frame every 100 ms of GNSS time.

:class:`VehicleHost` reads the car's CAN bus (a python-can bus: ``--vehicle-can-interface``,
``--vehicle-can-channel``, ``--vehicle-can-fd``) through a DBC and a vehicle profile
(:func:`hil.vehicle.load_profile`, :class:`catc.vehicle.CanDecoder`), and a GNSS receiver
(``--gnss``, :func:`gnss_spec`): NMEA 0183 over UDP or a serial line or pty
(:class:`catc.gnss.NmeaStream`), or gpsd's JSON.  It fuses both with
:class:`catc.hoststate.HostEstimator`, all on the daemon's event loop with
``time.monotonic()`` as the local clock.

Ticks run on GNSS time: the tick of GNSS time ``T`` (a multiple of 100 ms) is due at the
local time the estimator's clock gives for ``T``; its state becomes the host's BSM
(secMark of ``T``), encoded as a UPER MessageFrame and handed to the daemon exactly as a
frame received on the host channel (``push("host", octets, time.time())``), so the host
gate, the tick rule, the clock and the capture work unchanged.  Before the first fix there
is no tick; when the fixes stop the clock keeps its offset and the ticks go on on dead
reckoning (``GNSS silent for 5.0 s: dead reckoning`` once per silence).

Nothing the car or the receiver sends ends the run: bad CAN frames and NMEA are counted
(``can_*``, ``nmea_*``) and logged at most once per reason per second; a lost gpsd
connection or serial line is reopened with a backoff of at most :data:`MAX_BACKOFF_S`.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime as dt
import json
import math
import os
import time
import zlib
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from catc.errors import EncodeError
from catc.gnss import Fix, NmeaStream
from catc.hoststate import EstimatorConfig, HostEstimator, HostState
from catc.j2735 import encode_frame
from catc.vehicle import CanDecoder, slcan
from hil.transport import TransportError, os_reason
from hil.vehicle import load_profile
from obu.options import GnssSpec
from obu.status import RateLimitedLog

__all__ = ["DEFAULT_CHANNELS", "MAX_BACKOFF_S", "TICK_S", "VehicleHost", "vehicle_record"]

#: The host's BSM period on GNSS time (s), and the ticks per second.
TICK_S = 0.1
_PER_S = 10
#: The most frames read from the car's bus in one pass of the event loop.
DRAIN_MAX = 1_000
#: The receive buffer asked for a SocketCAN bus (octets).
CAN_RCVBUF = 4 * 1024 * 1024
#: With nothing from the car (no CAN frame, no GNSS input) for this long (s of the car's
#: time), the OBU stops ticking until it hears from it again.
CAR_SILENT_S = 1.0
#: The longest wait before reopening a lost gpsd connection or serial line (s).
MAX_BACKOFF_S = 5.0
#: The car's bus when no ``--vehicle-can-channel`` is given (not the RV transport's).
DEFAULT_CHANNELS = {"socketcan": "can0", "virtual": "catc-vehicle",
                    "udp_multicast": "239.74.163.3", "slcan": "/dev/ttyACM0"}


def serial_spec(channel: str) -> GnssSpec:
    """A serial CAN adapter's ``PATH[@BAUD]`` (``--vehicle-can-channel``)."""
    path, at, baud = channel.rpartition("@") if "@" in channel else (channel, "", "")
    return GnssSpec("serial", path=path, baud=int(baud) if at and baud.isdigit() else None)


def _fileno(bus: Any) -> int | None:
    """The bus's file descriptor for the event loop, or None (it has none)."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, AttributeError, OSError, ValueError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


class _Frame:
    """A CAN frame read from a serial adapter, shaped as python-can's Message for
    :meth:`VehicleHost._on_can`."""

    __slots__ = ("arbitration_id", "data", "is_fd")
    is_error_frame = is_remote_frame = False

    def __init__(self, arbitration_id: int, data: bytes, is_fd: bool) -> None:
        self.arbitration_id, self.data, self.is_fd = arbitration_id, data, is_fd
_WATCH = b'?WATCH={"enable":true,"json":true};\n'
#: The counters of a dropped CAN frame and NMEA line, with what the log line says.
_CAN_BAD = {"can_bad_checksum": "bad checksum on id {}", "can_unknown_id": "unknown id {}",
            "can_bad_length": "bad length on id {}",
            "can_undecodable": "undecodable frame of id {}"}
_NMEA_BAD = {"nmea_bad_checksum": "NMEA sentence with a bad checksum",
             "nmea_garbage": "garbage that is no NMEA sentence",
             "nmea_too_long": "a line too long for NMEA"}


def vehicle_record(state: HostState, est: HostEstimator) -> dict[str, Any]:
    """A tick of ``obu.vehicle.jsonl``: the estimator's state and what it has learnt."""
    def r(x: float | None, n: int) -> float | None:
        return None if x is None else round(x, n)

    return {"t_gnss": round(state.t_gnss, 3), "lat": round(state.lat, 8),
            "lon": round(state.lon, 8), "speed": r(state.speed, 4),
            "heading": r(state.heading, 4), "yaw_rate": round(state.yaw_rate, 4),
            "std_m": round(state.std_m, 3), "gnss_age_s": round(max(0.0, state.gnss_age_s), 3),
            "gnss_lost": state.gnss_lost, "latency": round(est.latency, 3),
            "latency_fitted": est.latency_fitted, "bias": round(est.bias, 5),
            "scale": round(est.scale, 6)}


def _tpv_fix(doc: Any) -> Fix | None:
    """A gpsd TPV object with a 2D or 3D fix as a :class:`Fix`; None for anything else."""
    if not isinstance(doc, dict) or doc.get("class") != "TPV":
        return None
    mode, when = doc.get("mode"), doc.get("time")
    lat, lon = doc.get("lat"), doc.get("lon")
    if not isinstance(mode, int) or mode < 2 or not isinstance(when, str):
        return None
    if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in (lat, lon)):
        return None
    try:
        t = dt.datetime.fromisoformat(when.replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None

    def num(key: str) -> float | None:
        x = doc.get(key)
        return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None

    alt = num("altHAE")
    return Fix(t, float(lat), float(lon), alt_m=alt if alt is not None else num("alt"),
               speed_mps=num("speed"), course_deg=num("track"),
               std_lat_m=num("epy"), std_lon_m=num("epx"))


class VehicleHost:
    """The host's state from the car (module docstring).  ``push(channel, octets,
    arrival)`` hands each host frame to the daemon; ``log`` is its rate-limited log;
    ``cap`` its capture (or None), which gets :func:`vehicle_record` per tick.  Bad
    settings raise :class:`hil.vehicle.ProfileError` (here) or
    :class:`hil.transport.TransportError` (:meth:`start`), one line each."""

    def __init__(self, args: argparse.Namespace, push: Callable[[str, bytes, float], None],
                 log: RateLimitedLog, cap: Any = None) -> None:
        self.args = args
        self.push = push
        self.log = log
        self.cap = cap
        profile, db = load_profile(args.vehicle, Path(args.dbc) if args.dbc else None)
        self.decoder = CanDecoder(profile, db)
        self.fields: dict[int, list[str]] = {}  # frame id -> the fields it updates
        for name, rule in profile.fields.items():
            fid = db.get_message_by_name(rule.message).frame_id
            self.fields.setdefault(fid, []).append(name)
        self.nmea = NmeaStream()
        self.slcan = slcan.SlcanStream()
        lat = getattr(args, "gnss_latency", "auto")
        self.est = HostEstimator(EstimatorConfig(
            gnss_delay_s=float(getattr(args, "gnss_delay", 0.1)),
            latency_s=None if lat in (None, "auto") else float(lat)))
        self.temp_id = (args.host_id if args.host_id is not None
                        else zlib.crc32(profile.name.encode()))
        self.profile = profile
        self.counters: Counter[str] = Counter()
        self.spec: GnssSpec = args.gnss
        self.seq = 0
        self.bus: Any = None
        self.notifier: Any = None
        self.reader_fd: int | None = None
        self.tasks: list[asyncio.Task] = []
        self.transport: asyncio.DatagramTransport | None = None
        self.fixed = asyncio.Event()  # the first fix came: ticks may start
        #: when (monotonic) the car last said anything (CAN or GNSS): ``--idle-exit``
        self.last_input = time.monotonic()
        #: the car's seconds per second of this process (``--time-scale``: 1 on a car,
        #: the RVE's ``--speed`` on the bench)
        self.scale = float(getattr(args, "time_scale", 1.0) or 1.0)
        self.silences = 0

    def clock(self) -> float:
        """The local clock the estimator runs on: monotonic seconds times the scale."""
        return time.monotonic() * self.scale

    def where(self) -> str:
        """The car's bus and the GNSS source, for the ready line."""
        a = self.args
        channel = a.vehicle_can_channel or DEFAULT_CHANNELS.get(a.vehicle_can_interface)
        return (f"vehicle {self.profile.name} can {a.vehicle_can_interface} {channel}, "
                f"gnss {self.spec}")

    # ---- start and stop ----------------------------------------------------------------
    async def start(self) -> None:
        """Open the car's bus and the GNSS source, start the ticks; a bus or a source
        that cannot be opened raises :class:`TransportError` (one line)."""
        import can

        a, loop = self.args, asyncio.get_running_loop()
        channel = a.vehicle_can_channel or DEFAULT_CHANNELS.get(a.vehicle_can_interface)
        slcan = a.vehicle_can_interface == "slcan"
        if slcan:  # a serial USB-CAN adapter (or rve's on a pty): read here, in chunks
            tty_spec = serial_spec(channel)
            fd = None
            if os.path.exists(tty_spec.path):
                fd = self._open_serial(tty_spec, "CAN serial")
                self._adapter_open(fd)
            else:  # not plugged in yet (or rve has not made its pty): wait for it
                self.log("can_serial", f"vehicle CAN: no adapter at {tty_spec.path} yet: "
                                       "waiting for it")
        else:
            try:
                self.bus = can.Bus(interface=a.vehicle_can_interface, channel=channel,
                                   fd=bool(a.vehicle_can_fd))
            except (can.CanError, OSError, ValueError, ImportError,
                    NotImplementedError) as exc:
                raise TransportError(f"cannot open the vehicle's CAN bus "
                                     f"{a.vehicle_can_interface}:{channel}: "
                                     f"{os_reason(exc)}") from exc
        self._grow_rcvbuf()
        try:
            if slcan:
                self.tasks.append(asyncio.create_task(
                    self._serial(tty_spec, fd, self._slcan_bytes, "can")))
            elif _fileno(self.bus) is not None:  # SocketCAN: drain on the event loop
                loop.add_reader(_fileno(self.bus), self._drain)
                self.reader_fd = _fileno(self.bus)
            else:  # no file descriptor (virtual, udp_multicast): python-can's thread
                self.notifier = can.Notifier(self.bus, [self._on_can], timeout=0.05,
                                             loop=loop)
            spec = self.spec
            if spec.kind == "udp":
                await self._open_udp(spec)
            elif spec.kind == "serial":
                fd = self._open_serial(spec)  # a missing device is a bad setting
                self.tasks.append(asyncio.create_task(self._serial(spec, fd)))
            else:
                self.tasks.append(asyncio.create_task(self._gpsd(spec)))
            self.tasks.append(asyncio.create_task(self._ticks()))
            for task in self.tasks:
                task.add_done_callback(self._ended)
        except BaseException:
            await self.aclose()
            raise

    def _drain(self) -> None:
        """Every frame waiting in the bus's socket, up to :data:`DRAIN_MAX` a call
        (python-can's Notifier reads one per event-loop pass: a busy loop fell behind a
        car's ~335 frames/s)."""
        for _ in range(DRAIN_MAX):
            try:
                msg = self.bus.recv(0)
            except Exception as err:  # a bus that fails: said, and kept
                self.counters["can_read_errors"] += 1
                self.log("can_read", f"vehicle CAN: cannot read: {err}")
                return
            if msg is None:
                return
            self._on_can(msg)

    def _grow_rcvbuf(self) -> None:
        """A SocketCAN bus's receive buffer grown to :data:`CAN_RCVBUF` (as the UDP
        receiver's): the kernel's default holds ~100 frames, a third of a second of a
        car's bus, and a busy moment of the OBU would lose frames from it.  The size the
        kernel granted is counted (``vehicle_can_rcvbuf``)."""
        import socket

        sock = getattr(self.bus, "socket", None)
        if not isinstance(sock, socket.socket):
            return
        for option in ("SO_RCVBUFFORCE", "SO_RCVBUF"):  # FORCE: past rmem_max, as root
            with contextlib.suppress(OSError, AttributeError):
                sock.setsockopt(socket.SOL_SOCKET, getattr(socket, option), CAN_RCVBUF)
                break
        with contextlib.suppress(OSError):
            self.counters["vehicle_can_rcvbuf"] = sock.getsockopt(socket.SOL_SOCKET,
                                                                  socket.SO_RCVBUF)

    def _ended(self, task: asyncio.Task) -> None:
        """A task of this object ended other than by :meth:`aclose`: a bug, said once."""
        if not task.cancelled() and task.exception() is not None:
            self.counters["vehicle_task_failed"] += 1
            err = task.exception()
            self.log("vehicle_task", f"vehicle host stopped: {type(err).__name__}: {err}")

    async def aclose(self) -> None:
        for task in self.tasks:
            task.cancel()
        for task in self.tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self.tasks = []
        if self.transport is not None:
            self.transport.close()
            self.transport = None
        if self.reader_fd is not None:
            asyncio.get_running_loop().remove_reader(self.reader_fd)
            self.reader_fd = None
        if self.notifier is not None:
            self.notifier.stop(timeout=1.0)
            self.notifier = None
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    def all_counters(self) -> dict[str, int]:
        """The decoder's (``can_``), the NMEA reader's (``nmea_``), the estimator's
        (``gnss_``, ``can_updates``) and this object's own (``vehicle_``, ``gnss_``)."""
        out: dict[str, int] = {}
        for c in (self.decoder.counters, self.nmea.counters, self.est.counters,
                  self.slcan.counters, self.counters):
            out.update(c)
        return out

    # ---- the car's CAN bus -------------------------------------------------------------
    def _on_can(self, msg: Any) -> None:
        """One frame of the car's bus (on the event loop)."""
        if msg.is_error_frame or msg.is_remote_frame:
            self.counters["can_error_or_remote"] += 1
            return
        self.last_input = time.monotonic()
        t = self.clock()
        c = self.decoder.counters
        before = [c[k] for k in _CAN_BAD]
        address = msg.arbitration_id
        if self.decoder.take(t, address, bytes(msg.data)):
            state = self.decoder.state
            self.est.can(t, {n: state[n] for n in self.fields.get(address, ()) if n in state})
            return
        for (key, what), n in zip(_CAN_BAD.items(), before, strict=True):
            if c[key] != n:
                self.log(key, f"vehicle CAN: {what.format(f'0x{address:03X}')}: "
                                 "frame dropped")

    def _adapter_open(self, fd: int) -> None:
        """Open a serial CAN adapter: close, 500 kbit/s, open (slcan's ``C``, ``S6``,
        ``O``); a pty played by rve ignores them."""
        with contextlib.suppress(OSError):
            os.write(fd, slcan.OPEN)

    def _slcan_bytes(self, data: bytes) -> None:
        """slcan octets from the car's adapter: each frame to :meth:`_on_can`."""
        before = self.slcan.counters["slcan_bad"]
        for address, payload, fd in self.slcan.feed(data):
            self._on_can(_Frame(address, payload, fd))
        if self.slcan.counters["slcan_bad"] != before:
            self.log("slcan_bad", "vehicle CAN: a serial line that is no slcan frame: "
                                  "dropped")

    # ---- GNSS --------------------------------------------------------------------------
    def _nmea(self, data: bytes) -> None:
        """NMEA octets from any source."""
        self.last_input = time.monotonic()
        t = self.clock()
        c = self.nmea.counters
        before = [c[k] for k in _NMEA_BAD]
        fixes = self.nmea.feed(data)
        for (key, what), n in zip(_NMEA_BAD.items(), before, strict=True):
            if c[key] != n:
                self.log(key, f"GNSS: {what}: dropped")
        for fix in fixes:
            self._fix(t, fix)

    def _fix(self, t: float, fix: Fix) -> None:
        self.est.fix(t, fix)
        if self.est.offset is not None:
            self.fixed.set()

    async def _open_udp(self, spec: GnssSpec) -> None:
        host = self

        class Protocol(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: Any) -> None:
                host._nmea(data)

            def error_received(self, exc: Exception) -> None:
                host.counters["gnss_udp_errors"] += 1

        loop = asyncio.get_running_loop()
        try:
            self.transport, _ = await loop.create_datagram_endpoint(
                Protocol, local_addr=(spec.host, spec.port))
        except OSError as exc:
            raise TransportError(f"cannot bind GNSS udp {spec.host}:{spec.port}: "
                                 f"{os_reason(exc)}") from exc

    def _open_serial(self, spec: GnssSpec, what: str = "GNSS serial") -> int:
        """The serial device or pty, non-blocking, raw, at its baud rate."""
        import termios
        import tty

        try:
            fd = os.open(spec.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            raise TransportError(f"cannot open {what} {spec.path}: "
                                 f"{os_reason(exc)}") from exc
        with contextlib.suppress(termios.error, OSError):  # a FIFO or a file: no tty
            tty.setraw(fd, termios.TCSANOW)
            attrs = termios.tcgetattr(fd)
            attrs[2] |= termios.CLOCAL | termios.CREAD
            speed = getattr(termios, f"B{spec.baud}", None) if spec.baud else None
            if speed is not None:
                attrs[4] = attrs[5] = speed
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        return fd

    async def _serial(self, spec: GnssSpec, fd: int | None,
                      sink: Callable[[bytes], None] | None = None,
                      what: str = "gnss") -> None:
        """Read the serial line until it ends (EOF, EIO: a pty's other side closed),
        then reopen it with a bounded backoff; its octets go to ``sink`` (the NMEA
        reader, or the slcan one for ``what`` ``can``)."""
        loop = asyncio.get_running_loop()
        sink = sink or self._nmea
        delay = 0.1 if what == "can" else 0.5
        while True:
            if fd is None:
                try:
                    fd = self._open_serial(spec, f"{what.upper()} serial")
                    if what == "can":
                        self._adapter_open(fd)
                except TransportError as err:
                    self.counters[f"{what}_serial_open_failed"] += 1
                    self.log(f"{what}_serial", f"{err}: retrying in {delay:.1f} s")
                    await asyncio.sleep(delay)
                    delay = min(2 * delay, MAX_BACKOFF_S)
                    continue
            ended = loop.create_future()

            def readable(fd: int = fd, ended: asyncio.Future = ended) -> None:
                try:
                    data = os.read(fd, 4096)
                except (BlockingIOError, InterruptedError):
                    return
                except OSError as exc:
                    data, why = b"", os_reason(exc)
                else:
                    why = "end of file"
                if data:
                    sink(data)
                elif not ended.done():
                    loop.remove_reader(fd)
                    ended.set_result(why)

            loop.add_reader(fd, readable)
            try:
                why = await ended
                delay = 0.1 if what == "can" else 0.5
            finally:
                loop.remove_reader(fd)
                os.close(fd)
                fd = None
            self.counters[f"{what}_serial_lost"] += 1
            self.log(f"{what}_serial", f"{what.upper()} serial {spec.path} lost ({why}): "
                                       "reopening")
            await asyncio.sleep(delay)

    async def _gpsd(self, spec: GnssSpec) -> None:
        """gpsd's JSON (``?WATCH``): every TPV with a 2D or 3D fix; reconnect with a
        bounded backoff when the connection fails or is lost."""
        delay = 0.5
        while True:
            try:
                reader, writer = await asyncio.open_connection(spec.host, spec.port)
            except OSError as exc:
                self.counters["gnss_gpsd_connect_failed"] += 1
                self.log("gpsd", f"gpsd {spec.host}:{spec.port}: {os_reason(exc)}: "
                                 f"retrying in {delay:.1f} s")
                await asyncio.sleep(delay)
                delay = min(2 * delay, MAX_BACKOFF_S)
                continue
            why = "closed by gpsd"
            try:
                writer.write(_WATCH)
                await writer.drain()
                self.counters["gnss_gpsd_connects"] += 1
                while True:
                    try:
                        line = await reader.readline()
                    except ValueError:  # a line over the stream's limit
                        self.counters["gnss_gpsd_bad"] += 1
                        continue
                    if not line:
                        break
                    delay = 0.5  # gpsd talks: the next loss starts the backoff anew
                    self._gpsd_line(line)
            except OSError as exc:
                why = os_reason(exc)
            finally:
                writer.close()
            self.counters["gnss_gpsd_lost"] += 1
            self.log("gpsd", f"gpsd connection lost ({spec.host}:{spec.port}: {why}): "
                             f"reconnecting in {delay:.1f} s")
            await asyncio.sleep(delay)
            delay = min(2 * delay, MAX_BACKOFF_S)

    def _gpsd_line(self, line: bytes) -> None:
        self.last_input = time.monotonic()
        t = self.clock()
        try:
            doc = json.loads(line)
        except (ValueError, UnicodeDecodeError):
            self.counters["gnss_gpsd_bad"] += 1
            self.log("gpsd_bad", "gpsd: a line that is no JSON: dropped")
            return
        fix = _tpv_fix(doc)
        if fix is not None:
            self.counters["gnss_gpsd_fixes"] += 1
            self._fix(t, fix)

    # ---- the ticks ---------------------------------------------------------------------
    async def _ticks(self) -> None:
        """A host frame at every 100 ms of GNSS time (module docstring)."""
        await self.fixed.wait()
        est = self.est
        k = None  # the next tick's number (its GNSS time * 10)
        while True:
            now = self.clock()
            g = est.gnss_time(now) * _PER_S
            if k is None or k > g + 10:  # the first: the first fix's own epoch; or
                k = math.ceil(est.last_stamp * _PER_S - 1e-4)  # GNSS time went back
            wait = est.local_time(k / _PER_S) - now
            if wait > 0.0:  # re-read the clock at least every 50 ms: a fix may move it
                await asyncio.sleep(min(wait / self.scale, 0.05))
                continue
            newest = math.floor(g + 1e-4)  # over 3 ticks late: the newest only (the
            if newest > k + 3:  # first fix's epoch comes up to its delay late: caught up)
                self.counters["vehicle_ticks_skipped"] += newest - k
                k = newest
            if now - self.scale * (time.monotonic() - self.last_input) < now - CAR_SILENT_S:
                # nothing from the car at all (no CAN, no GNSS): its ignition is off, or
                # the bench stopped; no host to tick (a GNSS silence alone is dead
                # reckoned on CAN)
                self.counters["vehicle_ticks_silent"] += 1
                self.log("vehicle_silent", f"vehicle: no CAN and no GNSS for "
                                           f"{CAR_SILENT_S:.0f} s: no ticks")
            else:
                self._tick(k / _PER_S)
            k += 1

    def _tick(self, t_gnss: float) -> None:
        est = self.est
        state = est.state(est.local_time(t_gnss))  # the state at T, though inputs came after
        if state is None:
            return
        state = replace(state, t_gnss=t_gnss)  # its secMark that of T, exactly
        if est.counters["gnss_silent"] != self.silences:
            self.silences = est.counters["gnss_silent"]
            self.log("gnss_silent", f"GNSS silent for {est.config.gnss_timeout_s:.1f} s: "
                                    "dead reckoning")
        try:
            frame = encode_frame(state.bsm(self.seq, self.temp_id))
        except (EncodeError, ValueError, OverflowError) as err:
            self.counters["vehicle_encode_errors"] += 1
            self.log("vehicle_encode", f"host state not encodable: {err}")
            return
        self.seq += 1
        self.counters["vehicle_ticks"] += 1
        self.push("host", frame, time.time())
        if self.cap is not None:
            self.cap.vehicle(vehicle_record(state, est))
