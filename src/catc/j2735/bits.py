"""Bit-level reader and writer for unaligned PER (ITU-T X.691, UPER).

Only what a BasicSafetyMessage needs: constrained whole numbers, bit fields,
the general length determinant (X.691 §11.9, unaligned variant), the normally
small length used by extension bitmaps (§11.9.3.4), enumeration indices (§14)
and open types (§11.2).

Both classes keep the bit string in one Python ``int``.  Reading a field is a
shift and a mask; writing is a shift and an or.  This is several times faster
than a list of bits or ``bytearray`` arithmetic in CPython.
"""

from __future__ import annotations

from catc.errors import DecodeError, EncodeError


class BitReader:
    """Reads big-endian bit fields from ``data``, starting at bit ``0``."""

    __slots__ = ("_end", "_value", "pos")

    def __init__(self, data: bytes) -> None:
        self._value = int.from_bytes(data, "big")
        self._end = len(data) * 8
        self.pos = 0

    @property
    def remaining(self) -> int:
        return self._end - self.pos

    def read(self, nbits: int, what: str = "field") -> int:
        """The next ``nbits`` bits as an unsigned integer."""
        end = self.pos + nbits
        if end > self._end:
            raise DecodeError("truncated", f"{what}: needs {nbits} bits, {self.remaining} left")
        self.pos = end
        return (self._value >> (self._end - end)) & ((1 << nbits) - 1)

    def constrained(self, lo: int, hi: int, nbits: int, what: str) -> int:
        """A constrained whole number lo..hi in ``nbits`` bits (X.691 §11.5.6).

        Raw offsets beyond ``hi`` cannot be produced by a conforming encoder; they
        are reported as out-of-range rather than silently accepted.
        """
        value = lo + self.read(nbits, what)
        if value > hi:
            raise DecodeError("out-of-range", f"{what}={value} outside {lo}..{hi}")
        return value

    def enumerated(self, count: int, extensible: bool, what: str) -> int:
        """The index of an ENUMERATED value with ``count`` root values (X.691 §14).

        A constrained whole number 0..count-1, after an extension bit when the type has
        an extension marker.  A value added in an extension (extension bit 1) is a
        normally small number (§11.6); it is returned as ``count`` plus that number.
        """
        if extensible and self.read(1, what):
            return count + self.normally_small_number(what)
        return self.constrained(0, count - 1, (count - 1).bit_length(), what)

    def normally_small_number(self, what: str) -> int:
        """A normally small non-negative whole number (X.691 §11.6)."""
        if self.read(1, what) == 0:
            return self.read(6, what)
        count = self.length(what)
        return self.read(8 * count, what) if count else 0

    def length(self, what: str) -> int:
        """An unconstrained length determinant (X.691 §11.9.3.5-8, unaligned)."""
        first = self.read(8, what)
        if first & 0x80 == 0:
            return first
        if first & 0x40 == 0:
            return ((first & 0x3F) << 8) | self.read(8, what)
        raise DecodeError("unsupported", f"{what}: fragmented length (>= 16K) is not supported")

    def small_length(self, what: str) -> int:
        """A normally small length (X.691 §11.9.3.4), as used for extension bitmaps."""
        if self.read(1, what) == 0:
            return self.read(6, what) + 1
        return self.length(what)

    def octets(self, count: int, what: str) -> bytes:
        if count == 0:
            return b""
        return self.read(8 * count, what).to_bytes(count, "big")

    def open_type(self, what: str) -> bytes:
        """The octets of an open type (X.691 §11.2): a length, then that many octets."""
        return self.octets(self.length(what), what)


class BitWriter:
    """Accumulates big-endian bit fields; :meth:`to_bytes` pads the last octet with 0s."""

    __slots__ = ("_value", "nbits")

    def __init__(self) -> None:
        self._value = 0
        self.nbits = 0

    def write(self, value: int, nbits: int) -> None:
        self._value = (self._value << nbits) | value
        self.nbits += nbits

    def constrained(self, value: int, lo: int, hi: int, nbits: int, what: str) -> None:
        if not lo <= value <= hi:
            raise EncodeError(f"{what}={value!r} outside {lo}..{hi}")
        self.write(value - lo, nbits)

    def length(self, count: int, what: str) -> None:
        if count < 0x80:
            self.write(count, 8)
        elif count < 0x4000:
            self.write(0x8000 | count, 16)
        else:
            raise EncodeError(f"{what}: {count} octets needs a fragmented length (>= 16K)")

    def octets(self, data: bytes) -> None:
        if data:
            self.write(int.from_bytes(data, "big"), 8 * len(data))

    def open_type(self, data: bytes, what: str) -> None:
        self.length(len(data), what)
        self.octets(data)

    def to_bytes(self) -> bytes:
        """The complete encoding, padded to whole octets (X.691 §11.1 for a PDU).

        An empty encoding is one zero octet, as X.691 §11.1.3 requires.
        """
        pad = -self.nbits % 8
        nbytes = (self.nbits + pad) // 8 or 1
        return (self._value << pad).to_bytes(nbytes, "big")
