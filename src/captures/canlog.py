"""The BSMs in a CAN capture: a candump log (``candump -L``, the RVE's ``rve.frames.log``)
or a Vector ASC file (``rve.frames.asc``), read with python-can's readers.

Every 11-bit identifier that carries ISO-TP (ISO 15765-2, normal addressing) gets its own
listen-only ISO-TP receiver (can-isotp's ``TransportLayerLogic`` with ``listen_mode``: it
reassembles Single, First and Consecutive Frames and sends no Flow Control), so any
sender's transfers come back whole, classic CAN or CAN FD, whatever the identifiers.
Flow Control frames carry no payload and give nothing.  Each transfer is then unpacked
like a UDP payload (IEEE 1609.2, OBU log, raw UPER; :func:`catc.j2735.sniff.unpack_payload`);
its ``meta`` has the CAN identifier, the channel and the time of its last CAN frame.
A broken transfer (a lost Consecutive Frame, a wrong sequence number) is dropped by the
ISO-TP receiver and counted in :attr:`CanLogFrames.isotp_errors` by reason.
"""

from __future__ import annotations

import logging
import re
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from catc.errors import DecodeError
from catc.j2735.sniff import Extracted, unpack_payload

_CANDUMP = re.compile(r"^\(\d+(\.\d+)?\)\s+\S+\s+[0-9A-Fa-f]{1,8}#")
_ASC_HEAD = re.compile(r"^(date|base)\s", re.IGNORECASE)
#: can-isotp logs each error as a warning too; they are counted here instead.
_ISOTP_LOGGER = "captures.canlog.isotp"
logging.getLogger(_ISOTP_LOGGER).setLevel(logging.ERROR)


def can_log_kind(text: str) -> str | None:
    """``"candump"`` or ``"asc"`` when ``text`` is a CAN log of that format, else None."""
    for line in text.splitlines()[:5]:
        line = line.strip()
        if not line:
            continue
        if _CANDUMP.match(line):
            return "candump"
        if _ASC_HEAD.match(line):
            return "asc"
        return None
    return None


@dataclass
class CanLogFrames:
    """What :func:`read_can_log` found: the frames and what went wrong on the way."""

    frames: list[Extracted]
    can_frames: int = 0
    isotp_errors: Counter = field(default_factory=Counter)


class _Listener:
    """A listen-only ISO-TP receiver of one arbitration id."""

    def __init__(self, can_id: int, errors: Counter) -> None:
        import isotp

        self._isotp = isotp
        self._inbox: deque = deque()
        self._errors = errors
        self.stack = isotp.TransportLayerLogic(
            rxfn=lambda _timeout: self._inbox.popleft() if self._inbox else None,
            txfn=lambda _msg: None,
            address=isotp.Address(isotp.AddressingMode.Normal_11bits, txid=0x7FF,
                                  rxid=can_id),
            error_handler=self._error,
            params={"listen_mode": True, "max_frame_size": 1 << 16, "can_fd": True,
                    "logger_name": _ISOTP_LOGGER,
                    "rx_consecutive_frame_timeout": 3_600_000})

    def _error(self, error: Exception) -> None:
        name = re.sub(r"(?<!^)(?=[A-Z])", "_", type(error).__name__.removesuffix("Error"))
        self._errors[name.lower()] += 1

    def feed(self, msg: Any) -> list[bytes]:
        self._inbox.append(self._isotp.CanMessage(arbitration_id=msg.arbitration_id,
                                            data=bytes(msg.data), is_fd=msg.is_fd))
        self.stack.process()
        out = []
        while (payload := self.stack.recv()) is not None:
            out.append(bytes(payload))
        return out


def read_can_log(path: str | Path, kind: str) -> CanLogFrames:
    """The ISO-TP transfers of a candump log or ASC file, unpacked (module docstring)."""
    import can

    reader = can.CanutilsLogReader if kind == "candump" else can.ASCReader
    result = CanLogFrames(frames=[])
    listeners: dict[int, _Listener] = {}
    try:
        for msg in reader(str(path)):
            result.can_frames += 1
            if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame or not msg.data:
                continue
            listener = listeners.get(msg.arbitration_id)
            if listener is None:
                listener = listeners[msg.arbitration_id] = _Listener(msg.arbitration_id,
                                                                     result.isotp_errors)
            for payload in listener.feed(msg):
                for frame, meta in unpack_payload(payload, "isotp"):
                    layers = ["can", *meta["layers"]]
                    result.frames.append(Extracted(frame, f"can-{kind}", {
                        **meta, "layers": layers, "index": len(result.frames),
                        "can_id": f"{msg.arbitration_id:03X}", "channel": msg.channel,
                        "time": msg.timestamp, "fd": msg.is_fd}))
    except (ValueError, IndexError) as err:
        raise DecodeError("garbage", f"{path}: not a readable {kind} CAN log: {err}") from err
    return result
