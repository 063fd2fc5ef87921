"""CAN transport: ISO-TP (ISO 15765-2) over a python-can bus, classic CAN or CAN FD.

Each channel is one ISO-TP address (11-bit identifiers, normal addressing, so no
payload octet is spent on addressing), given as a pair ``(data_id, fc_id)``: the RVE
sends Single, First and Consecutive Frames with ``data_id`` and the OBU answers with Flow
Control frames on ``fc_id``.  Defaults: RV frames :data:`RV_IDS` = (0x6A0, 0x6A8), the
host vehicle's state :data:`HOST_IDS` = (0x6A1, 0x6A9).  The +8 between a request and
its answer follows OBD-II's physical addressing (0x7E0 → 0x7E8); the identifiers stay
clear of the OBD-II/UDS range 0x7DF–0x7EF and of ISO 15765's reserved 0x7F4–0x7FB, so a
diagnostic tester can share the bus.

ISO-TP parameters (can-isotp 2.x, :data:`ISOTP_DEFAULTS`, any of them can be overridden
with ``isotp_params``):

* classic CAN: 8-octet frames padded with 0xCC (ISO 15765-2's recommended filler, which
  ECUs that expect DLC 8 need); CAN FD (``fd=True``): up to 64-octet frames, padded to
  the next valid FD length, with bit-rate switch.  A 200-octet BSM takes 29 CAN frames
  plus one Flow Control on classic CAN and 4 + 1 on CAN FD, where a frame of up to 62
  octets is a Single Frame with no Flow Control at all;
* the receiver asks for STmin 0 and block size 0: one Flow Control per transfer and no
  pause between Consecutive Frames, the fewest round trips (the links are a dedicated
  HIL bus, vcan or loopback; a slow physical receiver would set ``stmin``/``blocksize``);
* timeouts N_Bs (Flow Control) and N_Cr (Consecutive Frame) 1,000 ms, the ISO values;
* the receiver accepts transfers up to ``max_frame`` octets (default 2,000, as UDP);
  a longer First Frame is answered with Flow Control "overflow" and counted.

**Transfers never interleave on the bus.**  The sender holds one :class:`asyncio.Lock`
across both addresses from a transfer's Single or First Frame until its last
Consecutive Frame has gone to the bus, Flow Control included; each address's ISO-TP
stack is handed one request at a time, and :meth:`CanSender.send` returns only when
that transfer is complete (or has failed).  Concurrent ``send``/``send_host`` calls
queue on the lock in call order.

The ISO-TP state machines (can-isotp's ``TransportLayerLogic``) run in the event loop
thread, with no thread of their own: every CAN frame received for our addresses is fed
to its address's stack at once, the stack's frames are written to the bus as it makes
them, and a timer drives the timeouts while a transfer is in progress.  python-can's
``Notifier`` watches the bus's file descriptor (``socketcan``, ``udp_multicast``) or,
where the bus has none (``virtual``), reads it in a thread and hands each frame to the
loop.

``on_frame(msg: can.Message)``, on either side, is called in the event loop thread with
every raw CAN frame of the two addresses that this side sends (``msg.is_rx`` False) or
receives (``is_rx`` True), in bus order: the sender's trace and the receiver's trace
are the same frames.  A python-can writer's ``on_message_received`` fits; it must be
quick.  Its exceptions are logged and counted (``on_frame_errors``), never raised.

Counters (``stats``):

* sender: ``frames``, ``bytes``, ``rv``, ``host`` (complete transfers), ``can_frames``
  written, ``failed`` transfers, ``errors`` and one counter per can-isotp error
  (``flow_control_timeout``, ``overflow``, ``unexpected_flow_control`` …) or
  ``bus_error`` (the bus refused a frame; the transfer is abandoned).
* receiver: ``frames``, ``bytes``, ``rv``, ``host`` (complete transfers), ``can_frames``
  received, ``errors`` and one counter per can-isotp error, e.g.
  ``wrong_sequence_number``, ``consecutive_frame_timeout``,
  ``unexpected_consecutive_frame``, ``reception_interrupted_with_first_frame``,
  ``frame_too_long``.  A broken transfer is dropped and may count under several reasons
  (a wrong sequence number, then each Consecutive Frame that follows it).

Buses: ``interface`` is a python-can interface name (tested: ``socketcan``, ``virtual``,
``udp_multicast``), ``channel`` its channel (default :data:`DEFAULT_CHANNELS`),
``bus_options`` more keyword arguments for ``can.Bus`` (e.g. ``port`` of
``udp_multicast``).  ``udp_multicast`` needs the ``msgpack`` package (python-can's
``multicast`` extra).  A bus that cannot be opened raises :class:`TransportError`.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can
import isotp

from hil.transport import Receiver, Sender, TransportError, count, os_reason

__all__ = [
    "DEFAULT_CHANNELS",
    "HOST_IDS",
    "ISOTP_DEFAULTS",
    "RV_IDS",
    "CanReceiver",
    "CanSender",
    "open_receiver",
    "open_sender",
]

log = logging.getLogger(__name__)

#: (data_id, fc_id) of the RV frames and of the host vehicle's frames.
RV_IDS = (0x6A0, 0x6A8)
HOST_IDS = (0x6A1, 0x6A9)

#: Channel used when none is given.  ``udp_multicast``: python-can's IPv4 group (IPv4
#: multicast works on ``lo`` with one route, which the namespace tests rely on).
DEFAULT_CHANNELS = {"socketcan": "vcan0", "virtual": "catc-hil",
                    "udp_multicast": "239.74.163.2"}

#: can-isotp parameters of both sides (``tx_data_length``, ``can_fd``,
#: ``bitrate_switch`` and ``max_frame_size`` follow ``fd`` and ``max_frame``).
ISOTP_DEFAULTS: dict[str, Any] = {
    "tx_padding": 0xCC,
    "stmin": 0,
    "blocksize": 0,
    "wftmax": 0,
    "rx_flowcontrol_timeout": 1000,
    "rx_consecutive_frame_timeout": 1000,
    "logger_name": "hil.transport.isotp",
}

DEFAULT_MAX_FRAME = 2000
#: How often a busy stack is looked at for its timeouts (s).
_POLL_S = 0.01
_Ids = tuple[int, int]
OnFrame = Callable[[can.Message], object]


def _reason(error: Exception) -> str:
    """``WrongSequenceNumberError`` → ``wrong_sequence_number``."""
    name = type(error).__name__.removesuffix("Error")
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", name).lower()


class _Port:
    """A bus and the ISO-TP stacks of our two addresses on it, driven from the loop."""

    def __init__(self, bus: can.BusABC, on_frame: OnFrame | None, stats: dict[str, int]) -> None:
        self.bus = bus
        self.on_frame = on_frame
        self.stats = stats
        self.loop = asyncio.get_running_loop()
        self.links: dict[int, _Link] = {}  # by the arbitration id they receive
        self.closed = False
        self.tx_failed = False
        self.notifier: can.Notifier | None = None

    def start(self) -> None:
        """Start reading the bus, once the links are in place."""
        self.notifier = can.Notifier(self.bus, [self._on_message], timeout=0.05, loop=self.loop)

    def _trace(self, msg: can.Message) -> None:
        if self.on_frame is None:
            return
        try:
            self.on_frame(msg)
        except Exception:
            count(self.stats, "on_frame_errors")
            log.exception("on_frame failed on %s", msg)

    def _on_message(self, msg: can.Message) -> None:
        link = self.links.get(msg.arbitration_id)
        if (self.closed or link is None or msg.is_extended_id or msg.is_error_frame
                or msg.is_remote_frame):
            return
        msg.is_rx = True
        count(self.stats, "can_frames")
        self._trace(msg)
        link.feed(isotp.CanMessage(arbitration_id=msg.arbitration_id, data=bytes(msg.data),
                                   is_fd=msg.is_fd, bitrate_switch=msg.bitrate_switch))

    def transmit(self, frame: isotp.CanMessage) -> None:
        """can-isotp's ``txfn``: one frame to the bus."""
        msg = can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                          is_extended_id=frame.is_extended_id, is_fd=frame.is_fd,
                          bitrate_switch=frame.bitrate_switch, is_rx=False,
                          timestamp=time.time())
        try:
            self.bus.send(msg)
        except can.CanError as exc:
            self.tx_failed = True
            count(self.stats, "errors")
            count(self.stats, "bus_error")
            log.warning("CAN %s: cannot send %03X: %s", self.bus.channel_info,
                        frame.arbitration_id, os_reason(exc))
            return
        count(self.stats, "can_frames")
        self._trace(msg)

    def on_isotp_error(self, error: Exception) -> None:
        count(self.stats, "errors")
        count(self.stats, _reason(error))

    def close(self) -> None:
        self.closed = True
        for link in self.links.values():
            link.close()
        if self.notifier is not None:
            self.notifier.stop(timeout=1.0)
        self.bus.shutdown()


class _Link:
    """One ISO-TP address (one channel): can-isotp's state machine, fed from the loop."""

    def __init__(self, port: _Port, channel: str, txid: int, rxid: int,
                 params: dict[str, Any], deliver: Callable[[str, bytes], None] | None) -> None:
        self.port = port
        self.channel = channel
        self.deliver = deliver
        self._inbox: deque[isotp.CanMessage] = deque()
        self._timer: asyncio.TimerHandle | None = None
        self._request: isotp.TransportLayerLogic.SendRequest | None = None
        self._done: asyncio.Future[bool] | None = None
        self.stack = isotp.TransportLayerLogic(
            rxfn=self._rxfn, txfn=port.transmit,
            address=isotp.Address(isotp.AddressingMode.Normal_11bits, txid=txid, rxid=rxid),
            error_handler=port.on_isotp_error, params=params,
            post_send_callback=self._on_request)
        port.links[rxid] = self

    def _rxfn(self, timeout: float) -> isotp.CanMessage | None:
        return self._inbox.popleft() if self._inbox else None

    def _on_request(self, request: isotp.TransportLayerLogic.SendRequest) -> None:
        self._request = request

    def feed(self, frame: isotp.CanMessage) -> None:
        self._inbox.append(frame)
        self.process()

    def _on_timer(self) -> None:
        self._timer = None
        self.process()

    def process(self) -> None:
        """Run the state machine on what has arrived and on its timers."""
        stack = self.stack
        stack.process()
        if self.port.tx_failed:  # the bus refused a frame: abandon the transfer
            self.port.tx_failed = False
            stack.stop_sending()
        while self.deliver is not None and stack.available():
            self.deliver(self.channel, bytes(stack.recv()))
        request = self._request
        if request is not None and request.complete_event.is_set():
            self._request = None
            if self._done is not None and not self._done.done():
                self._done.set_result(request.success)
        self._schedule()

    def _schedule(self) -> None:
        stack = self.stack
        if stack.is_tx_transmitting_cf():  # paced by the receiver's STmin
            delay = stack.next_cf_delay() or 0.0
        elif stack.transmitting() or stack.is_rx_active():
            if self._timer is not None:
                return
            delay = _POLL_S
        else:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self.port.loop.call_later(delay, self._on_timer)

    def transfer(self, frame: bytes) -> asyncio.Future[bool]:
        """Start sending ``frame``; the future is its success, set when it is done."""
        self._done = self.port.loop.create_future()
        self.stack.send(frame)
        self.process()
        return self._done

    def abort(self) -> None:
        self.stack.stop_sending()
        self._request = None

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._done is not None and not self._done.done():
            self._done.set_result(False)


def _params(fd: bool, max_frame: int, overrides: dict[str, Any] | None) -> dict[str, Any]:
    params = dict(ISOTP_DEFAULTS, tx_data_length=64 if fd else 8, can_fd=fd,
                  bitrate_switch=fd, max_frame_size=max_frame)
    params.update(overrides or {})
    return params


def _open_bus(interface: str, channel: str | None, fd: bool, rx_ids: list[int],
              bus_options: dict[str, Any] | None) -> can.BusABC:
    if channel is None:
        channel = DEFAULT_CHANNELS.get(interface)
    filters = [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in rx_ids]
    try:
        return can.Bus(interface=interface, channel=channel, fd=fd, can_filters=filters,
                       **(bus_options or {}))
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        raise TransportError(
            f"cannot open CAN bus {interface}:{channel}: {os_reason(exc)}") from exc


class CanSender(Sender):
    """The RVE side: data frames out on both addresses, Flow Control in."""

    def __init__(self, bus: can.BusABC, rv_ids: _Ids, host_ids: _Ids,
                 params: dict[str, Any], on_frame: OnFrame | None) -> None:
        self.stats = {"frames": 0, "bytes": 0, "rv": 0, "host": 0, "can_frames": 0,
                      "failed": 0, "errors": 0}
        self._port = _Port(bus, on_frame, self.stats)
        self._links = {ch: _Link(self._port, ch, ids[0], ids[1], params, None)
                       for ch, ids in (("rv", rv_ids), ("host", host_ids))}
        self._port.start()
        self._lock = asyncio.Lock()  # one transfer at a time, across both addresses
        self._closed = False

    async def _send(self, channel: str, frame: bytes) -> None:
        if not frame:
            raise ValueError("an ISO-TP transfer carries at least one octet")
        link = self._links[channel]
        async with self._lock:
            if self._closed:
                raise TransportError("can sender is closed")
            done = link.transfer(frame)
            try:
                ok = await done
            except asyncio.CancelledError:
                link.abort()
                raise
        if ok:
            count(self.stats, "frames")
            count(self.stats, "bytes", len(frame))
            count(self.stats, channel)
        else:
            count(self.stats, "failed")

    async def send(self, frame: bytes) -> None:
        await self._send("rv", frame)

    async def send_host(self, frame: bytes) -> None:
        await self._send("host", frame)

    async def aclose(self) -> None:
        if not self._closed:
            self._closed = True
            self._port.close()


class CanReceiver(Receiver):
    """The OBU side: data frames in on both addresses, Flow Control out."""

    kind = "can"

    def __init__(self, bus: can.BusABC, rv_ids: _Ids, host_ids: _Ids,
                 params: dict[str, Any], on_frame: OnFrame | None) -> None:
        self.stats = {"frames": 0, "bytes": 0, "rv": 0, "host": 0, "can_frames": 0,
                      "errors": 0}
        self._start_queue()
        self._port = _Port(bus, on_frame, self.stats)
        for ch, ids in (("rv", rv_ids), ("host", host_ids)):
            _Link(self._port, ch, ids[1], ids[0], params, self._deliver)
        self._port.start()
        self._closed = False

    async def aclose(self) -> None:
        if not self._closed:
            self._closed = True
            self._port.close()
            self._end()


async def open_sender(*, interface: str, channel: str | None = None, fd: bool = False,
                      rv_ids: _Ids = RV_IDS, host_ids: _Ids = HOST_IDS,
                      on_frame: OnFrame | None = None,
                      isotp_params: dict[str, Any] | None = None,
                      bus_options: dict[str, Any] | None = None) -> CanSender:
    """Open the bus and the RVE's two ISO-TP addresses (see the module docstring)."""
    params = _params(fd, DEFAULT_MAX_FRAME, isotp_params)
    bus = _open_bus(interface, channel, fd, [rv_ids[1], host_ids[1]], bus_options)
    try:
        return CanSender(bus, rv_ids, host_ids, params, on_frame)
    except BaseException:
        bus.shutdown()
        raise


async def open_receiver(*, interface: str, channel: str | None = None, fd: bool = False,
                        rv_ids: _Ids = RV_IDS, host_ids: _Ids = HOST_IDS,
                        on_frame: OnFrame | None = None, max_frame: int = DEFAULT_MAX_FRAME,
                        isotp_params: dict[str, Any] | None = None,
                        bus_options: dict[str, Any] | None = None) -> CanReceiver:
    """Open the bus and the OBU's two ISO-TP addresses (see the module docstring)."""
    params = _params(fd, max_frame, isotp_params)
    bus = _open_bus(interface, channel, fd, [rv_ids[0], host_ids[0]], bus_options)
    try:
        return CanReceiver(bus, rv_ids, host_ids, params, on_frame)
    except BaseException:
        bus.shutdown()
        raise
