"""Frame transports between the RVE and the OBU: one small interface, backends by name.

Like python-can's ``can.Bus(interface=...)``, a backend is chosen by name and asks for
little: a :class:`Sender` (the RVE side) has :meth:`~Sender.send` for one RV
MessageFrame, :meth:`~Sender.send_host` for one frame of the host vehicle's own state on
its own loss-free channel, and :meth:`~Sender.aclose`; a :class:`Receiver` (the OBU side)
has :meth:`~Receiver.recv`, which returns the next frame from either channel as a
:class:`Received`, and :meth:`~Receiver.aclose`.  Both keep counters in ``stats``.

Both are async context managers that close on exit::

    async with await open_sender("udp", to=("127.0.0.1", 4500),
                                 host_to=("127.0.0.1", 4501)) as tx:
        await tx.send(rv_frame)
        await tx.send_host(hv_frame)

    async with await open_receiver("udp", listen=("127.0.0.1", 4500),
                                   host_listen=("127.0.0.1", 4501)) as rx:
        got = await rx.recv()       # Received(channel="rv" | "host", data, rx_time)

Backends (:data:`KINDS`), each a module with ``open_sender(**options)`` and
``open_receiver(**options)``; adding one touches one module and :data:`_BACKENDS`:

* ``udp`` (:mod:`hil.transport.udp`): one MessageFrame per datagram, a port per channel.
* ``can`` (:mod:`hil.transport.can`): ISO-TP (ISO 15765-2) over a python-can bus
  (``socketcan``, ``virtual``, ``udp_multicast``), classic CAN or CAN FD, one ISO-TP
  address per channel.

Errors: an unknown kind, an address that cannot be bound or reached, or a CAN bus that
cannot be opened raise :class:`TransportError`, whose ``str()`` is one line naming the
address or bus and the OS's reason (the daemons print it and exit 2).  Once open, a
transport never raises for what the network does: lost, refused, oversized or broken
frames are counted in ``stats`` and dropped.
"""

from __future__ import annotations

import abc
import asyncio
import importlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Literal, Self, TypeVar

__all__ = [
    "KINDS",
    "Received",
    "Receiver",
    "Sender",
    "TransportError",
    "open_receiver",
    "open_sender",
]

#: Transport kinds, as given to :func:`open_sender` / :func:`open_receiver`.
KINDS = ("udp", "can")
_BACKENDS = {"udp": "hil.transport.udp", "can": "hil.transport.can"}


class TransportError(Exception):
    """A transport could not be opened or used; ``str()`` is a one-line message."""


def os_reason(exc: BaseException) -> str:
    """The reason in ``exc`` (and the errors that caused it) as one line, e.g.
    ``"[Errno 98] Address already in use"``."""
    parts = []
    seen: BaseException | None = exc
    while seen is not None and len(parts) < 4:
        text = str(seen) or type(seen).__name__
        if text not in parts:
            parts.append(text)
        seen = seen.__cause__ or seen.__context__
    return ": ".join(parts).replace("\n", " ")


def count(stats: dict[str, int], key: str, n: int = 1) -> None:
    """Add ``n`` to the counter ``stats[key]`` (created at 0)."""
    stats[key] = stats.get(key, 0) + n


@dataclass(frozen=True, slots=True)
class Received:
    """One frame as the OBU received it."""

    #: ``"rv"`` (a remote vehicle's MessageFrame) or ``"host"`` (the HV's own state).
    channel: Literal["rv", "host"]
    #: The frame's octets, exactly as sent.
    data: bytes
    #: ``time.monotonic()`` when the frame was complete at the receiver.
    rx_time: float
    #: Wall-clock time (unix s) the frame arrived: the kernel's stamp where the backend
    #: has one (UDP: ``SO_TIMESTAMPNS``), so the time a frame waited in a socket buffer
    #: counts in the OBU's lag; else ``time.time()`` when it was complete.
    arrival: float = 0.0


T = TypeVar("T")


class Sender(abc.ABC):
    """The RVE side of a transport.  ``stats`` counts ``frames`` and ``bytes`` sent per
    channel and the errors by reason (see the backend)."""

    stats: dict[str, int]

    @abc.abstractmethod
    async def send(self, frame: bytes) -> None:
        """Send one RV MessageFrame."""

    @abc.abstractmethod
    async def send_host(self, frame: bytes) -> None:
        """Send one frame of the host vehicle's state on its own channel."""

    async def send_many(self, frames: Sequence[bytes], stamp: Callable[[], T]) -> list[T]:
        """Send RV frames in order, back to back, each ``stamp()``-ed as soon as it left
        (a backend may do it faster than :meth:`send` one by one)."""
        out = []
        for frame in frames:
            await self.send(frame)
            out.append(stamp())
        return out

    @abc.abstractmethod
    async def aclose(self) -> None:
        """Release the sockets or the bus; calling it again does nothing."""

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.aclose()


class Receiver(abc.ABC):
    """The OBU side of a transport.  ``stats`` counts the ``frames`` and ``bytes``
    received per channel and the dropped frames by reason (see the backend).

    Backends call :meth:`_deliver` for every complete frame and :meth:`_end` when
    closed; frames wait in one queue for :meth:`recv`."""

    stats: dict[str, int]
    #: The backend's name, for the "closed" error.
    kind: str = ""

    def _start_queue(self) -> None:
        self._queue: asyncio.Queue[Received | None] = asyncio.Queue()
        self._ended = False  # the end mark (None) is in the queue

    def _deliver(self, channel: Literal["rv", "host"], data: bytes,
                 arrival: float | None = None) -> None:
        self._queue.put_nowait(Received(channel, data, time.monotonic(),
                                        time.time() if arrival is None else arrival))
        count(self.stats, "frames")
        count(self.stats, "bytes", len(data))
        count(self.stats, channel)

    def _end(self) -> None:
        self._queue.put_nowait(None)
        self._ended = True

    async def recv(self) -> Received:
        """The next frame from either channel, in arrival order.  Raises
        :class:`TransportError` once the receiver is closed."""
        got = await self._queue.get()
        if got is None:
            self._queue.put_nowait(None)  # every later recv() fails the same way
            raise TransportError(f"{self.kind} receiver is closed")
        return got

    def waiting(self, channel: Literal["rv", "host"] | None = None) -> bool:
        """True while a frame that has reached this receiver is not yet handed out by
        :meth:`recv`: in its queue, or (for backends that can tell) still in the kernel's
        socket buffer; with ``channel``, where the backend can tell, a frame of that
        channel.  The OBU drains the RV frames before a tick: they arrived before the
        host frame that triggers it."""
        return self._queue.qsize() > self._ended  # the end mark is no frame

    def backlog(self) -> dict[str, int]:
        """What waits to be handed out: ``queued`` frames in this receiver's queue and,
        for backends that can tell, ``socket_bytes`` in the kernel's receive buffers and
        the datagrams the kernel dropped for want of room (``socket_drops``)."""
        return {"queued": max(0, self._queue.qsize() - self._ended)}

    @abc.abstractmethod
    async def aclose(self) -> None:
        """Release the sockets or the bus; calling it again does nothing."""

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.aclose()


def _backend(kind: str):
    if kind not in _BACKENDS:
        raise TransportError(f"unknown transport {kind!r} (known: {', '.join(KINDS)})")
    return importlib.import_module(_BACKENDS[kind])


async def open_sender(kind: str, **options) -> Sender:
    """Open the sending side of transport ``kind``; ``options`` are the backend's
    (:func:`hil.transport.udp.open_sender`, :func:`hil.transport.can.open_sender`)."""
    return await _backend(kind).open_sender(**options)


async def open_receiver(kind: str, **options) -> Receiver:
    """Open the receiving side of transport ``kind``; ``options`` are the backend's
    (:func:`hil.transport.udp.open_receiver`, :func:`hil.transport.can.open_receiver`)."""
    return await _backend(kind).open_receiver(**options)
