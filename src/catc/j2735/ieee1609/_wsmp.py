"""The WAVE Short Message (IEEE 1609.3-2016 §8.3) that carries an ``Ieee1609Dot2Data`` over
the air, or over Ethernet with ethertype 0x88DC.

The N-header is one octet (subtype, option indicator, version 3) and optional WAVE
information elements; the T-header the TPID, the PSID p-encoded (IEEE 1609.12) and the WSM
length.  Counts and lengths are 1609.3 §8.1.3 counts (one octet below 128, else two).
"""

from __future__ import annotations

import io

from catc.errors import DecodeError, EncodeError
from catc.j2735.ieee1609._basetypes import PSID_BSM
from catc.j2735.ieee1609._oer import take

WSMP_VERSION = 3
ETHERTYPE_WSMP = 0x88DC  # WSMP directly over an IEEE 802 LLC/Ethernet header
_P_ENCODING = (  # IEEE 1609.3-2016 / 1609.12 p-encoding: (first PSID, prefix, octets)
    (0x204080, 0xE0000000, 4),
    (0x4080, 0xC00000, 3),
    (0x80, 0x8000, 2),
    (0, 0, 1),
)
_P_MAX = 0x204080 + 0x0FFFFFFF


def _wsmp_count(n: int, what: str) -> bytes:
    """1609.3 §8.1.3 length/count: one octet below 128, two octets ``0b10`` + 14 bits."""
    if n < 0x80:
        return bytes([n])
    if n < 0x4000:
        return (0x8000 | n).to_bytes(2, "big")
    raise EncodeError(f"WSMP {what} {n} does not fit 14 bits")


def _read_wsmp_count(stream: io.BytesIO, what: str) -> int:
    first = take(stream, 1, f"WSMP {what}")[0]
    if first < 0x80:
        return first
    if first & 0xC0 != 0x80:
        raise DecodeError("garbage", f"WSMP {what}: 0x{first:02x} is neither 1 nor 2 octets")
    return (first & 0x3F) << 8 | take(stream, 1, f"WSMP {what}")[0]


def _skip_wave_elements(stream: io.BytesIO, what: str) -> None:
    """A WAVE Information Element Extension: count, then ID, length, contents."""
    for _ in range(_read_wsmp_count(stream, what)):  # at most 16383, each >= 2 octets
        take(stream, 1, f"WSMP {what}")
        take(stream, _read_wsmp_count(stream, what), f"WSMP {what}")


def wrap_wsmp(payload: bytes, psid: int = PSID_BSM) -> bytes:
    """A WAVE Short Message (1609.3-2016 §8.3) carrying ``payload`` for ``psid``.

    N-header without options: subtype 0 (null networking), option indicator 0, version 3
    (one octet 0x03), TPID 0; T-header: the PSID p-encoded (0x20 is one octet 0x20), the
    WSM length as a 1609.3 count; then the payload (usually an ``Ieee1609Dot2Data``).
    """
    if not isinstance(psid, int) or not 0 <= psid <= _P_MAX:
        raise EncodeError(f"PSID {psid!r} cannot be p-encoded")
    first, prefix, size = next(row for row in _P_ENCODING if psid >= row[0])
    p_encoded = (prefix | (psid - first)).to_bytes(size, "big")
    return b"\x03\x00" + p_encoded + _wsmp_count(len(payload), "length") + bytes(payload)


def unwrap_wsmp(data: bytes) -> tuple[bytes, int]:
    """Parse a WAVE Short Message: (payload, PSID).  Octets after the WSM data (Ethernet
    padding) are ignored.  N-header and T-header information elements are skipped."""
    stream = io.BytesIO(bytes(data))
    n_header = take(stream, 1, "WSMP N-header")[0]
    if n_header & 0x07 != WSMP_VERSION:
        raise DecodeError("unsupported", f"WSMP version {n_header & 0x07}, not 3")
    if n_header >> 4:
        raise DecodeError("unsupported", f"WSMP subtype {n_header >> 4} (only null networking)")
    if n_header & 0x08:
        _skip_wave_elements(stream, "N-header extension")
    tpid = take(stream, 1, "WSMP TPID")[0]
    if tpid > 1:
        raise DecodeError("unsupported", f"WSMP TPID {tpid} (only PSID addressing)")
    first = take(stream, 1, "WSMP PSID")[0]
    size = next((n for n, mask in ((1, 0x80), (2, 0xC0), (3, 0xE0), (4, 0xF0))
                 if first & mask == (mask << 1) & 0xFF), None)
    if size is None:
        raise DecodeError("garbage", f"WSMP PSID p-encoding prefix 0x{first:02x}")
    value = int.from_bytes(bytes([first]) + take(stream, size - 1, "WSMP PSID"), "big")
    offset, prefix, _ = next(row for row in _P_ENCODING if row[2] == size)
    psid = (value ^ prefix) + offset
    if tpid == 1:
        _skip_wave_elements(stream, "T-header extension")
    length = _read_wsmp_count(stream, "length")
    return take(stream, length, "WSMP data"), psid


def looks_like_wsmp(data: bytes) -> bool:
    """Cheap sniff: a version-3 null-networking N-header followed by TPID 0 or 1 (an
    ``Ieee1609Dot2Data`` also starts with 0x03 but continues with a 0x8x CHOICE tag)."""
    if len(data) < 4 or data[0] & 0xF7 != WSMP_VERSION:
        return False
    return data[0] & 0x08 != 0 or data[1] in (0, 1)
