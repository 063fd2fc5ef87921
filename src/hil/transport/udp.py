"""UDP transport: one MessageFrame per datagram, one port per channel (asyncio-dgram
sends; the receiver reads both sockets in the event loop, in order of arrival).

Sender options: ``to=(host, port)`` for the RV frames and ``host_to=(host, port)`` for
the host vehicle's frames.  Receiver options: ``listen=(host, port)`` and
``host_listen=(host, port)``; ``rcvbuf`` (default 4 MiB) is the socket receive buffer
asked for, so that a burst of hundreds of datagrams is not lost at the socket while the
OBU computes a tick; ``max_frame`` (default 2,000 octets) is the largest datagram taken
as a frame.  Hosts are IPv4 or IPv6 addresses or names.

Counters (``stats``):

* sender: ``frames`` and ``bytes`` handed to the kernel, ``rv`` and ``host`` frames per
  channel, ``errors`` and one counter per errno name (``econnrefused`` when nothing
  listens on a loopback port: the ICMP refusal arrives after the datagram, so it is
  counted at a later send or at close).  A send error never raises.
* receiver: ``frames``, ``bytes``, ``rv``, ``host``; ``oversized`` datagrams (longer
  than ``max_frame``, dropped); ``errors`` and per errno name; ``rcvbuf``, the receive
  buffer the kernel granted, in octets as ``getsockopt(SO_RCVBUF)`` reports it (Linux
  doubles the request for its bookkeeping and caps it at ``net.core.rmem_max`` unless
  the process may use ``SO_RCVBUFFORCE``, which is tried first).

The receiver's ``addresses`` maps each channel to the (host, port) it is bound to.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import random
import select
import socket
import struct
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Literal

import asyncio_dgram

from hil.transport import Receiver, Sender, T, TransportError, count, os_reason

__all__ = ["DEFAULT_MAX_FRAME", "DEFAULT_RCVBUF", "open_receiver", "open_sender"]

log = logging.getLogger(__name__)

DEFAULT_RCVBUF = 4 * 1024 * 1024
DEFAULT_MAX_FRAME = 2000

#: The most datagrams read from one socket in one pass (:class:`UdpReceiver`): more
#: than a 4 MiB buffer of BSMs holds.
DRAIN_MAX = 20_000

#: The largest datagram read: a UDP payload never exceeds it.
_READ_SIZE = 65_536

Address = tuple[str, int]


def _text(addr: Address) -> str:
    host, port = addr[0], addr[1]
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _port(addr: Address, verb: str) -> int:
    try:
        port = int(addr[1])
    except (TypeError, ValueError, IndexError):
        port = -1
    if not 0 <= port <= 65535:
        raise TransportError(f"cannot {verb} udp {addr!r}: not a (host, port 0-65535) pair")
    return port


def _count_error(stats: dict[str, int], exc: OSError) -> None:
    count(stats, "errors")
    count(stats, errno.errorcode.get(exc.errno or -1, "oserror").lower())


class UdpSender(Sender):
    """Two connected UDP sockets, one per channel."""

    def __init__(self, streams: dict[str, asyncio_dgram.aio.DatagramClient]) -> None:
        self._streams = streams
        self._closed = False
        #: (address, port) each channel's socket sends from, as the receiver sees it
        self.local = {ch: tuple(s.sockname[:2]) for ch, s in streams.items()}
        self.stats = {"frames": 0, "bytes": 0, "rv": 0, "host": 0, "errors": 0}

    def _collect(self, stream: asyncio_dgram.aio.DatagramClient) -> None:
        """Count the errors the kernel reported on ``stream`` since the last call."""
        while True:
            try:
                _ = stream.exception  # raises the oldest unconsumed error, if any
                return
            except OSError as exc:
                _count_error(self.stats, exc)

    async def _send(self, channel: str, frame: bytes) -> None:
        if self._closed:
            raise TransportError("udp sender is closed")
        stream = self._streams[channel]
        self._collect(stream)
        try:
            await stream.send(frame)
        except OSError as exc:
            _count_error(self.stats, exc)
            return
        self._collect(stream)
        count(self.stats, "frames")
        count(self.stats, "bytes", len(frame))
        count(self.stats, channel)

    async def send(self, frame: bytes) -> None:
        await self._send("rv", frame)

    async def send_host(self, frame: bytes) -> None:
        await self._send("host", frame)

    async def send_many(self, frames: Sequence[bytes], stamp: Callable[[], T]) -> list[T]:
        """The RV frames of a burst straight onto the connected socket, with no await
        between them (asyncio-dgram's send awaits its drained event after each, 7 us a
        frame against 3.5: 1,000 RVs due at one instant), while the transport has nothing
        buffered: what its ``sendto`` does first, without its checks (``python
        bench/rve_pacing.py --vehicles 1000``: p99 7.7 to 6.2 ms with the host flags read
        from a list).  A full socket buffer hands the rest to the transport, which queues
        them; then its drained event once, as its send would."""
        if self._closed:
            raise TransportError("udp sender is closed")
        stream = self._streams["rv"]
        transport = getattr(stream, "_transport", None)
        drained = getattr(stream, "_drained", None)
        if transport is None or drained is None or transport.is_closing():
            return await super().send_many(frames, stamp)
        self._collect(stream)
        out = []
        raw = getattr(transport, "_sock", None)
        k = 0
        if raw is not None and not getattr(transport, "_buffer", True):
            send = raw.send
            try:
                for frame in frames:
                    send(frame)
                    out.append(stamp())
                    k += 1
            except (BlockingIOError, InterruptedError):
                pass  # the transport queues this one and the rest
            except OSError as exc:  # as the transport would report it: dropped, counted
                _count_error(self.stats, exc)
                out.append(stamp())
                k += 1
        for frame in frames[k:]:
            transport.sendto(frame)  # an OSError comes back through the stream: _collect
            out.append(stamp())
        self._collect(stream)
        count(self.stats, "frames", len(frames))
        count(self.stats, "bytes", sum(map(len, frames)))
        count(self.stats, "rv", len(frames))
        await drained.wait()
        return out

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        for stream in self._streams.values():
            self._collect(stream)
            stream.close()


async def open_sender(*, to: Address, host_to: Address) -> UdpSender:
    """Connect one UDP socket to ``to`` (RV frames) and one to ``host_to`` (HV frames)."""
    targets = {"rv": (to[0], _port(to, "reach")), "host": (host_to[0], _port(host_to, "reach"))}
    streams: dict[str, asyncio_dgram.aio.DatagramClient] = {}
    for channel, addr in targets.items():
        try:
            streams[channel] = await asyncio_dgram.connect(addr)
        except (OSError, ValueError) as exc:
            for stream in streams.values():
                stream.close()
            raise TransportError(f"cannot reach udp {_text(addr)}: {os_reason(exc)}") from exc
    return UdpSender(streams)


def _bound_socket(addr: Address, rcvbuf: int) -> tuple[socket.socket, int]:
    """A UDP socket bound to ``addr`` with a receive buffer of ``rcvbuf`` octets asked
    for; the socket and the size the kernel granted."""
    port = _port(addr, "bind")
    try:
        family, kind, proto, _, sockaddr = socket.getaddrinfo(
            addr[0], port, type=socket.SOCK_DGRAM)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as exc:
        raise TransportError(f"cannot bind udp {_text(addr)}: {os_reason(exc)}") from exc
    try:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUFFORCE, rcvbuf)
        except (OSError, AttributeError):  # no CAP_NET_ADMIN, or not Linux
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.bind(sockaddr)
    except OSError as exc:
        sock.close()
        raise TransportError(f"cannot bind udp {_text(addr)}: {os_reason(exc)}") from exc
    granted = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    if granted < rcvbuf:
        log.warning("udp %s: receive buffer %d octets granted, %d asked for "
                    "(raise net.core.rmem_max)", _text(addr), granted, rcvbuf)
    return sock, granted


#: Linux's SO_TIMESTAMPNS (= SCM_TIMESTAMPNS): the kernel stamps each datagram with the
#: time it reached the socket (``struct timespec``, two native longs).
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@ll")
#: Linux's SO_MEMINFO: a socket's memory, ``SK_MEMINFO_VARS`` (9) u32s, the receive
#: queue's allocation first and the drops last.
_SO_MEMINFO = 55
_MEMINFO = struct.Struct("@9I")


def _stamp_arrivals(sock: socket.socket) -> None:
    """Ask the kernel to stamp ``sock``'s datagrams on arrival (not where it cannot)."""
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)


class UdpReceiver(Receiver):
    """Two bound UDP sockets, one per channel, read by the event loop into one queue in
    the order their datagrams reached the sockets.

    The OBU's tick rule depends on that order (a tick at a host frame takes the RV frames
    that came before it).  Read one datagram per socket per pass, as an asyncio datagram
    transport does, a backlog on the RV socket (a flood, an OBU verifying signatures
    behind real time) let a host frame overtake RV frames sent ahead of it; drained RV
    socket first, RV frames sent after it overtook the host frame.  So whenever either
    socket is readable both are read to the end (RV, host, RV again: every RV datagram
    that arrived before the last host datagram read is then read too) and the batch is
    handed out sorted by the kernel's arrival stamp (``SO_TIMESTAMPNS``; where the kernel
    does not stamp, in the order read)."""

    kind = "udp"

    def __init__(self, socks: dict[str, socket.socket], rcvbuf: int, max_frame: int) -> None:
        self._socks = socks
        #: The bound (host, port) of each channel (useful after binding port 0).
        self.addresses = {ch: s.getsockname()[:2] for ch, s in socks.items()}
        self._max_frame = max_frame
        self._start_queue()
        self._closed = False
        self._loop: asyncio.AbstractEventLoop | None = None
        for sock in socks.values():
            _stamp_arrivals(sock)  # where it cannot, arrivals are in the order read
        self._ancillary = socket.CMSG_SPACE(_TIMESPEC.size)
        self.stats = {"frames": 0, "bytes": 0, "rv": 0, "host": 0, "oversized": 0,
                      "errors": 0, "rcvbuf": rcvbuf}

    async def _open(self) -> None:
        self._loop = asyncio.get_running_loop()
        for sock in self._socks.values():
            sock.setblocking(False)
            self._loop.add_reader(sock.fileno(), self._readable)

    def _readable(self) -> None:
        if self._closed:
            return
        batch: list[tuple[float, int, str, bytes]] = []
        for channel in ("rv", "host", "rv"):
            self._read(channel, batch)
        batch.sort()
        for arrival, _, channel, data in batch:
            if len(data) > self._max_frame:
                count(self.stats, "oversized")
            else:
                self._deliver(channel, data, arrival)  # type: ignore[arg-type]

    def _read(self, channel: str, batch: list[tuple[float, int, str, bytes]]) -> None:
        """Append what waits in ``channel``'s socket buffer to ``batch`` as (arrival,
        order read, channel, octets): at most :data:`DRAIN_MAX` datagrams, a bound
        should a flood outrun the reads."""
        sock = self._socks[channel]
        for _ in range(DRAIN_MAX):
            try:
                data, ancdata, _, _ = sock.recvmsg(_READ_SIZE, self._ancillary)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                _count_error(self.stats, exc)
                return
            arrival = None
            for level, kind, value in ancdata:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS \
                        and len(value) >= _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack_from(value)
                    arrival = sec + nsec * 1e-9
            batch.append((time.time() if arrival is None else arrival, len(batch), channel,
                          data))

    def waiting(self, channel: Literal["rv", "host"] | None = None) -> bool:
        """Also True while a datagram sits in a socket's kernel buffer (``channel``'s
        socket only, when given), not yet read by the event loop.  Over loopback a
        datagram is in the receiver's buffer when ``sendto`` returns, so every RV frame
        sent before a host frame is found here or in the queue once that host frame is
        received."""
        if self._closed:
            return False
        if super().waiting():
            return True
        socks = list(self._socks.values()) if channel is None else [self._socks[channel]]
        ready, _, _ = select.select(socks, [], [], 0)
        return bool(ready)

    def backlog(self) -> dict[str, int]:
        """Also the octets waiting in the sockets' kernel buffers (``SO_MEMINFO``'s
        receive allocation, overhead included) and the datagrams the kernel dropped."""
        out = super().backlog()
        out["socket_bytes"] = out["socket_drops"] = 0
        if self._closed:
            return out
        for sock in self._socks.values():
            try:
                info = _MEMINFO.unpack(sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO,
                                                       _MEMINFO.size))
            except (OSError, struct.error):
                continue
            out["socket_bytes"] += info[0]  # SK_MEMINFO_RMEM_ALLOC
            out["socket_drops"] += info[8]  # SK_MEMINFO_DROPS
        return out

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        for sock in self._socks.values():
            if self._loop is not None:
                self._loop.remove_reader(sock.fileno())
            sock.close()
        self._end()


async def open_receiver(*, listen: Address, host_listen: Address, rcvbuf: int = DEFAULT_RCVBUF,
                        max_frame: int = DEFAULT_MAX_FRAME) -> UdpReceiver:
    """Bind one UDP socket to ``listen`` (RV frames) and one to ``host_listen``."""
    socks: dict[str, socket.socket] = {}
    granted: list[int] = []
    try:
        for channel, addr in (("rv", listen), ("host", host_listen)):
            socks[channel], size = _bound_socket(addr, rcvbuf)
            granted.append(size)
    except TransportError:
        for sock in socks.values():
            sock.close()
        raise
    receiver = UdpReceiver(socks, min(granted), max_frame)
    await receiver._open()
    return receiver


def wait_bound(ports: list[int], timeout: float = 15.0, alive=None) -> bool:
    """Wait until a UDP socket is bound to each of ``ports`` on this machine (a daemon
    started with them is listening): True when they are, False after ``timeout`` s or as
    soon as ``alive()`` says the daemon exited.  Reads /proc/net/udp and udp6, so binding
    nothing itself (a probe bind could take the port from the daemon); where they do not
    exist it waits a second and says True."""
    tables = [Path("/proc/net/udp"), Path("/proc/net/udp6")]
    if not tables[0].exists():
        time.sleep(1.0)
        return True
    want = {f"{p:04X}" for p in ports}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        bound = set()
        for table in tables:
            with contextlib.suppress(OSError):
                for line in table.read_text().splitlines()[1:]:
                    local = line.split()[1]  # ADDRESS:PORT in hex
                    bound.add(local.rsplit(":", 1)[1])
        if want <= bound:
            return True
        if alive is not None and not alive():
            return False
        time.sleep(0.02)
    return False


def _ephemeral_low() -> int:
    """The lowest port the kernel hands out to ``bind(0)`` and to connected sockets."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range", encoding="ascii") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_ports(n: int = 2, host: str = "127.0.0.1") -> list[int]:
    """``n`` UDP ports on ``host`` that were free a moment ago (for tests, benches, demo).

    They are drawn at random below the kernel's ephemeral range (10000 up to it): a port
    from there is never what another socket gets from ``bind(0)`` or from connecting (a
    sender's local port), so between this call and its user's bind no other process takes
    it by chance, and nothing sent to it lands in someone's ephemeral socket.  (Drawn from
    the ephemeral range, as before, a daemon of one test could send into another test's
    receiver under pytest-xdist.)  Where that range starts below 11000, ``bind(0)``."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    low = _ephemeral_low()
    rng = random.SystemRandom()
    socks: list[socket.socket] = []
    try:
        for _ in range(50 * n):
            if len(socks) == n:
                break
            s = socket.socket(family, socket.SOCK_DGRAM)
            try:
                s.bind((host, rng.randrange(10000, low) if low >= 11000 else 0))
            except OSError:
                s.close()
                continue
            socks.append(s)
        if len(socks) < n:
            raise OSError(errno.EADDRINUSE, f"no {n} free udp ports on {host}")
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()
