"""Canonical OER (ITU-T X.696) primitives of IEEE 1609.2: read from a stream, build octets.

Readers take an :class:`io.BytesIO` positioned at the value and a ``what`` that names it in
error messages: input that ends early is ``DecodeError("truncated")``, a malformed
primitive ``garbage``.  Builders return the COER octets.  The types of IEEE 1609.2 that
are built from these live in :mod:`._basetypes`, :mod:`._certificate` and :mod:`._data`.
"""

from __future__ import annotations

import io

from catc.errors import DecodeError, EncodeError

MAX_ENTRIES = 64  # entries in one SEQUENCE OF (1609.2 requires support for >= 8)


def take(stream: io.BytesIO, n: int, what: str) -> bytes:
    """The next ``n`` octets, or ``truncated``."""
    octets = stream.read(n)  # BytesIO.read never allocates more than what is left
    if len(octets) != n:
        raise DecodeError("truncated", f"1609.2 {what}: input ends early")
    return octets


def read_uint(stream: io.BytesIO, n: int, what: str) -> int:
    """A fixed-size unsigned integer of ``n`` octets, big-endian."""
    return int.from_bytes(take(stream, n, what), "big")


def read_preamble(stream: io.BytesIO, used: int, what: str) -> int:
    """A one-octet SEQUENCE preamble (X.696 §16.2) whose low ``8 - used`` bits must be 0."""
    octet = take(stream, 1, what)[0]
    if octet & (0xFF >> used):
        raise DecodeError("garbage", f"1609.2 {what}: preamble 0x{octet:02x}, padding bits set")
    return octet


def read_tag(stream: io.BytesIO, what: str) -> int:
    """A CHOICE tag octet (X.696 §20, context class, tag number below 63): the index."""
    octet = take(stream, 1, what)[0]
    if octet & 0xC0 != 0x80 or octet == 0xBF:
        raise DecodeError("garbage", f"1609.2 {what}: 0x{octet:02x} is not a CHOICE tag")
    return octet & 0x3F


def read_enumerated(stream: io.BytesIO, what: str) -> int:
    """An ENUMERATED with fewer than 128 values (X.696 §11: one octet, short form)."""
    octet = take(stream, 1, what)[0]
    if octet & 0x80:
        raise DecodeError("garbage", f"1609.2 {what}: enumerated value in long form")
    return octet


def read_length(stream: io.BytesIO, what: str) -> int:
    """X.696 §8.6 length determinant (short form below 128, else ``0x80 | n`` + n octets)."""
    first = take(stream, 1, what)[0]
    if first < 0x80:
        return first
    n = first & 0x7F
    if not 1 <= n <= 4:
        raise DecodeError("garbage", f"1609.2 length determinant with {n} length octets")
    return read_uint(stream, n, what)


def read_octets(stream: io.BytesIO, what: str) -> bytes:
    """A variable-size OCTET STRING or an open type: length determinant, then the octets."""
    return take(stream, read_length(stream, what), what)


def read_quantity(stream: io.BytesIO, what: str, limit: int = MAX_ENTRIES) -> int:
    """The quantity field of a SEQUENCE OF (X.696 §17): the entry count."""
    n = take(stream, 1, what)[0]
    if not 1 <= n <= 4:
        raise DecodeError("garbage", f"1609.2 {what}: quantity field of {n} octets")
    count = read_uint(stream, n, what)
    if count > limit:
        raise DecodeError("unsupported", f"1609.2 {what}: {count} entries (at most {limit})")
    return count


def read_psid(stream: io.BytesIO, what: str) -> int:
    """``Psid ::= INTEGER (0..MAX)``: length determinant, unsigned octets (at most 8)."""
    octets = read_octets(stream, what)
    if not 1 <= len(octets) <= 8:
        raise DecodeError("out-of-range", f"1609.2 {what}: {len(octets)} octets")
    return int.from_bytes(octets, "big")


def read_signed_int(stream: io.BytesIO, what: str) -> int:
    """An unconstrained INTEGER: length determinant, two's complement (at most 8 octets)."""
    octets = read_octets(stream, what)
    if not 1 <= len(octets) <= 8:
        raise DecodeError("garbage", f"1609.2 {what}: integer of {len(octets)} octets")
    return int.from_bytes(octets, "big", signed=True)


def skip_extensions(stream: io.BytesIO, what: str) -> None:
    """The extension additions of an extensible SEQUENCE (X.696 §16.4): a presence bitmap
    (an OCTET STRING whose first octet counts the unused bits), then one open type per
    bit set, all skipped."""
    what = f"{what} extensions"
    bitmap = read_octets(stream, what)
    for _ in range(sum(bin(b).count("1") for b in bitmap[1:])):
        read_octets(stream, what)


def length_octets(n: int) -> bytes:
    """The X.696 §8.6 length determinant of ``n``."""
    if n < 0x80:
        return bytes([n])
    body = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes([0x80 | len(body)]) + body


def enc_octets(octets: bytes) -> bytes:
    """A variable-size OCTET STRING: length determinant, then the octets."""
    return length_octets(len(octets)) + octets


def enc_quantity(n: int) -> bytes:
    """The quantity field of a SEQUENCE OF ``n`` entries (X.696 §17)."""
    body = n.to_bytes(max(1, (n.bit_length() + 7) // 8), "big")
    return bytes([len(body)]) + body


def enc_psid(psid: int) -> bytes:
    """``Psid``: length determinant, then the fewest unsigned octets."""
    if not isinstance(psid, int) or not 0 <= psid < 1 << 64:
        raise EncodeError(f"psid {psid!r} is not an integer in 0..2**64-1")
    return enc_octets(psid.to_bytes(max(1, (psid.bit_length() + 7) // 8), "big"))


def enc_signed_int(n: int) -> bytes:
    """An unconstrained INTEGER in the fewest two's complement octets."""
    size = ((n if n >= 0 else ~n).bit_length() + 8) // 8  # minimal two's complement
    return enc_octets(n.to_bytes(size, "big", signed=True))
