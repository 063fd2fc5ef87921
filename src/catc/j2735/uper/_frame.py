"""J2735 ``MessageFrame`` and ``BasicSafetyMessage`` in UPER: the public codec.

``BasicSafetyMessage ::= SEQUENCE { coreData BSMcoreData, partII SEQUENCE (SIZE(1..8)) OF
PartIIcontent OPTIONAL, regional SEQUENCE (SIZE(1..4)) OF RegionalExtension OPTIONAL,
... }`` inside ``MessageFrame ::= SEQUENCE { messageId, value }`` (messageId 20, the value
an open type).  The parts are in :mod:`._core`, :mod:`._vse` and :mod:`._part2`.
"""

from __future__ import annotations

from catc.bsm import BSM
from catc.errors import DecodeError, EncodeError
from catc.j2735.bits import BitReader, BitWriter
from catc.j2735.uper._core import CORE_BITS, core_bsm, core_raw, decode_core
from catc.j2735.uper._elements import skip_extensions
from catc.j2735.uper._part2 import check_part2, read_open_type
from catc.j2735.uper._vse import VEHICLE_SAFETY_EXT, encode_vse, read_vse

#: DSRCmsgID of a BasicSafetyMessage.
BSM_MESSAGE_ID = 20
_CORE_MASK = (1 << CORE_BITS) - 1
#: The octets that hold a BSM's first three bits (extension, partII and regional
#: present) and its BSMcoreData.
_HEAD_OCTETS = (3 + CORE_BITS + 7) // 8
_HEAD_SHIFT = 8 * _HEAD_OCTETS - 3 - CORE_BITS


def _read_bsm(r: BitReader) -> BSM:
    head = r.read(3 + CORE_BITS, "BasicSafetyMessage")
    core = decode_core(head & ((1 << CORE_BITS) - 1))
    ext = head >> (CORE_BITS + 2)
    present = (head >> CORE_BITS) & 3
    if not (ext or present):
        return BSM(*core)
    fields: dict = {}
    if present & 2:
        count = r.read(3, "partII count") + 1
        other = []
        have_vse = False
        for index in range(count):
            part_id = r.read(6, "partII-Id")
            value = r.open_type("partII-Value")
            if part_id == VEHICLE_SAFETY_EXT and not have_vse:
                have_vse = True
                vse = read_open_type(value, read_vse, "VehicleSafetyExtensions")
                fields.update(vse)
                if index or not vse:  # where the default (first, if not empty) is wrong
                    fields["vse_position"] = index
                continue
            check_part2(part_id, value)
            other.append((part_id, value))
        fields["part2_other"] = tuple(other)
    if present & 1:
        count = r.read(2, "regional count") + 1
        fields["regional"] = tuple((r.read(8, "regionId"), r.open_type("regExtValue"))
                                   for _ in range(count))
    if ext:
        skip_extensions(r, "BasicSafetyMessage")
    return BSM(*core, **fields)


def _write_bsm(w: BitWriter, m: BSM) -> None:
    if m.vse_position is not None and m.vse_position < 0:
        raise EncodeError(f"vse_position={m.vse_position!r} is negative")
    part2 = list(m.part2_other)
    vse_at = m.vse_index
    if vse_at is not None:  # in the order received, see BSM.vse_position
        part2.insert(vse_at, (VEHICLE_SAFETY_EXT, encode_vse(m)))
    if len(part2) > 8:
        raise EncodeError(f"at most 8 Part II items, got {len(part2)}")
    if len(m.regional) > 4:
        raise EncodeError(f"at most 4 regional extensions, got {len(m.regional)}")
    w.write((2 if part2 else 0) | (1 if m.regional else 0), 3)
    w.write(core_raw(m), CORE_BITS)
    if part2:
        w.write(len(part2) - 1, 3)
        for part_id, value in part2:
            w.constrained(part_id, 0, 63, 6, "partII-Id")
            w.open_type(value, "partII-Value")
    if m.regional:
        w.write(len(m.regional) - 1, 2)
        for region_id, value in m.regional:
            w.constrained(region_id, 0, 255, 8, "regionId")
            w.open_type(value, "regExtValue")


def encode_bsm(m: BSM) -> bytes:
    """A bare UPER BasicSafetyMessage (no MessageFrame)."""
    w = BitWriter()
    _write_bsm(w, m)
    return w.to_bytes()


def decode_bsm(data: bytes) -> BSM:
    """Decode a bare UPER BasicSafetyMessage.  Trailing octets are ignored."""
    try:
        if len(data) >= _HEAD_OCTETS and data[0] < 0x20:  # BSMcoreData only, no BitReader
            v = int.from_bytes(data[:_HEAD_OCTETS], "big") >> _HEAD_SHIFT
            return core_bsm(decode_core(v & _CORE_MASK))
        return _read_bsm(BitReader(data))
    except (ValueError, TypeError) as exc:  # enum construction inside a malformed frame
        if isinstance(exc, DecodeError):
            raise
        raise DecodeError("garbage", f"BasicSafetyMessage: {exc}") from None


def encode_frame(m: BSM) -> bytes:
    """A UPER MessageFrame (messageId 20) carrying ``m``: what goes on the air."""
    body = encode_bsm(m)
    n = len(body)
    if n < 0x80:
        return b"\x00\x14" + bytes((n,)) + body
    if n < 0x4000:
        return b"\x00\x14" + (0x8000 | n).to_bytes(2, "big") + body
    raise EncodeError(f"BSM of {n} octets needs a fragmented length")


def frame_message_id(data: bytes) -> int:
    """The messageId of a UPER MessageFrame, without decoding the rest."""
    if len(data) < 2:
        raise DecodeError("truncated",
                          f"MessageFrame needs 2 octets for messageId, got {len(data)}")
    return int.from_bytes(data[:2], "big") & 0x7FFF


def decode_frame(data: bytes) -> BSM:
    """Decode a UPER MessageFrame carrying a BasicSafetyMessage.

    Raises :class:`DecodeError` with reason ``wrong-message-id`` for any other
    message, ``truncated`` when the frame is cut short, and ``garbage`` or
    ``out-of-range`` when the bits cannot be a BSM.  Octets after the frame are
    ignored (deployed logs pad frames).
    """
    n = len(data)
    if n < 3:
        raise DecodeError("truncated", f"MessageFrame needs at least 3 octets, got {n}")
    # Octet-aligned header: extension bit + 15-bit messageId, then the open type's
    # length determinant (X.691 §11.9.3.5-8).  Extension additions after the value
    # (extension bit set) are ignored.
    message_id = ((data[0] << 8) | data[1]) & 0x7FFF
    if message_id != BSM_MESSAGE_ID:
        raise DecodeError("wrong-message-id",
                          f"messageId {message_id} is not a BasicSafetyMessage (20)")
    length = data[2]
    start = 3
    if length & 0x80:
        if length & 0x40:
            raise DecodeError("unsupported", "MessageFrame.value: fragmented length (>= 16K)")
        if n < 4:
            raise DecodeError("truncated", "MessageFrame.value: length determinant cut short")
        length = ((length & 0x3F) << 8) | data[3]
        start = 4
    if n - start < length:
        raise DecodeError("truncated",
                          f"MessageFrame.value: needs {length} octets, {n - start} left")
    return decode_bsm(data[start:start + length])
