"""CAN frames over a serial line: the Lawicel "slcan" ASCII protocol (no I/O).

The cheap USB-CAN adapters an integrator plugs into a car's OBD port (CANable, USBtin,
CANtact, and the Lawicel CANUSB whose protocol it is) show up as a serial device and
speak slcan: ``tIIILDD..\\r`` for a standard frame (3 hex digits of id, the length, the
data in hex), ``TIIIIIIIILDD..\\r`` for an extended one, ``d``/``D`` (and ``b``/``B``
with bit-rate switch) for CAN FD with a hex length code; commands such as ``S6\\r`` (500
kbit/s) and ``O\\r`` (open) go the other way.  python-can's ``slcan`` interface speaks it
too, but reads its serial port a byte per call; the OBU reads a pty or a tty in chunks on
its event loop, so :class:`SlcanStream` parses the lines here.  ``rve run --host-bus
--host-can-interface slcan`` plays the adapter on a pty (:func:`encode`).

Bad input never raises: a line that is no frame (a malformed id or length, data that
does not match the length, a line too long) is counted (``slcan_bad``) and dropped;
the adapter's replies to commands (``\\r``, ``\\a``, ``z``, ``Z``, versions) are
counted as ``slcan_other``.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

__all__ = ["FD_LENGTHS", "SlcanStream", "encode"]

#: CAN FD's lengths by length code (0-15).
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_MAX_LINE = 1 + 8 + 1 + 128 + 4  # an extended FD frame of 64 octets, and some slack
#: The commands a host sends an adapter to open it at 500 kbit/s (the RAV4's car bus).
OPEN = b"C\rS6\rO\r"


def encode(address: int, data: bytes, fd: bool = False) -> bytes:
    """The slcan line of one frame (an id above 0x7FF is an extended one)."""
    extended = address > 0x7FF
    if fd:
        code = FD_LENGTHS.index(len(data)) if len(data) in FD_LENGTHS else None
        if code is None:
            raise ValueError(f"CAN FD has no length {len(data)}")
        head = ("D" if extended else "d") + (f"{address:08X}" if extended
                                              else f"{address:03X}") + f"{code:X}"
    else:
        if len(data) > 8:
            raise ValueError(f"classic CAN carries at most 8 octets, not {len(data)}")
        head = ("T" if extended else "t") + (f"{address:08X}" if extended
                                              else f"{address:03X}") + str(len(data))
    return (head + data.hex().upper() + "\r").encode("ascii")


@dataclass
class SlcanStream:
    """Reads slcan lines from bytes as they come: :meth:`feed` returns the frames
    completed, as ``(address, data, is_fd)``.  ``counters``: ``slcan_frames``,
    ``slcan_bad``, ``slcan_other``."""

    counters: Counter = field(default_factory=Counter)
    _buf: bytes = b""

    def feed(self, data: bytes) -> list[tuple[int, bytes, bool]]:
        self._buf += data.replace(b"\n", b"\r")
        *lines, self._buf = self._buf.split(b"\r")
        if len(self._buf) > _MAX_LINE:
            self.counters["slcan_bad"] += 1
            self._buf = b""
        out = []
        for line in lines:
            frame = self._line(line.strip(b"\x07 "))
            if frame is not None:
                out.append(frame)
        return out

    def _line(self, line: bytes) -> tuple[int, bytes, bool] | None:
        if not line:
            return None
        kind = line[:1]
        if kind not in (b"t", b"T", b"d", b"D", b"b", b"B", b"r", b"R"):
            self.counters["slcan_other"] += 1
            return None
        extended = kind.isupper()
        n = 8 if extended else 3
        fd = kind in (b"d", b"D", b"b", b"B")
        try:
            text = line.decode("ascii")
            address = int(text[1:1 + n], 16)
            code = int(text[1 + n], 16)
            length = FD_LENGTHS[code] if fd else code
            if kind in (b"r", b"R"):  # a remote frame carries no data
                self.counters["slcan_other"] += 1
                return None
            hexdata = text[2 + n:]
            if len(text) < 2 + n or (not fd and code > 8) or len(hexdata) != 2 * length:
                raise ValueError("length")
            data = bytes.fromhex(hexdata)
        except (ValueError, IndexError, UnicodeDecodeError):
            self.counters["slcan_bad"] += 1
            return None
        if address > (0x1FFFFFFF if extended else 0x7FF):
            self.counters["slcan_bad"] += 1
            return None
        self.counters["slcan_frames"] += 1
        return address, data, fd
