"""IEEE 1609.2 ``Ieee1609Dot2Data`` in canonical OER: unwrap to the carried MessageFrame.

Deployed OBUs and RSUs send a J2735 UPER MessageFrame inside an IEEE 1609.2 secured
data structure, encoded with COER (ITU-T X.696 canonical OER).  The types come from
IEEE Std 1609.2-2016 §6.3 (ASN.1 module ``Ieee1609Dot2``, as published e.g. in the
usdot-jpo-ode/asn1_codec repository); the octet layout from X.696:

- ``Ieee1609Dot2Data`` (§6.3.1) is a plain SEQUENCE: ``protocolVersion`` (one octet,
  must be 3), then ``content``, an extensible CHOICE whose tag octet is
  ``0x80 | index``: 0 ``unsecuredData``, 1 ``signedData``, 2 ``encryptedData``,
  3 ``signedCertificateRequest``, 4 ``signedX509CertificateRequest`` (extension).
- ``unsecuredData`` is an ``Opaque`` OCTET STRING: a length determinant (one octet
  below 128, else ``0x80 | n`` and n big-endian length octets), then the octets.
- ``SignedData`` (§6.3.4) is ``hashId`` (ENUMERATED, one octet), ``tbsData``,
  ``signer``, ``signature``; ``ToBeSignedData`` (§6.3.6) is ``payload`` then
  ``headerInfo``.
- ``SignedDataPayload`` (§6.3.7) is extensible with two OPTIONAL fields, so it opens
  with a preamble octet: bit 7 extensions present, bit 6 ``data``, bit 5
  ``extDataHash``.  ``data`` is again an ``Ieee1609Dot2Data``.
- ``HeaderInfo`` (§6.3.9) is extensible with six OPTIONAL root fields: preamble
  octet bit 7 extensions, bit 6 ``generationTime``, bits 5..1 the others.  ``psid``
  is an INTEGER (0..MAX), so a length determinant then unsigned big-endian octets;
  ``generationTime`` is a ``Time64`` (8 octets, microseconds since 2004-01-01 TAI).

Signed data is followed down its ``payload.data`` to the innermost ``unsecuredData``.
The ``headerInfo`` read is the one of the innermost signed layer (it follows directly
after the unsecured octets); ``signer`` and ``signature`` are neither parsed nor
verified.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Any

from construct import (
    Array,
    Byte,
    Bytes,
    Computed,
    Const,
    Construct,
    ConstructError,
    Error,
    GreedyBytes,
    If,
    Int64ub,
    Prefixed,
    StreamError,
    Struct,
    Switch,
    this,
)
from construct.core import stream_read, stream_write

from catc.errors import DecodeError

PROTOCOL_VERSION = 3
_UNSECURED, _SIGNED = 0x80, 0x81
_UNSUPPORTED = {
    0x82: "encryptedData",
    0x83: "signedCertificateRequest",
    0x84: "signedX509CertificateRequest",
}
_MAX_DEPTH = 8  # signed-inside-signed nesting accepted before giving up


class _OerLength(Construct):
    """X.696 §8.6 length determinant (short form below 128, else ``0x80 | n`` + n octets)."""

    def _parse(self, stream, context, path):  # type: ignore[no-untyped-def]
        first = stream_read(stream, 1, path)[0]
        if first < 0x80:
            return first
        n = first & 0x7F
        if not 1 <= n <= 4:
            raise DecodeError("garbage", f"1609.2 length determinant with {n} length octets")
        return int.from_bytes(stream_read(stream, n, path), "big")

    def _build(self, obj, stream, context, path):  # type: ignore[no-untyped-def]
        if obj < 0x80:
            octets = bytes([obj])
        else:
            body = obj.to_bytes((obj.bit_length() + 7) // 8, "big")
            octets = bytes([0x80 | len(body)]) + body
        stream_write(stream, octets, len(octets), path)
        return obj


_OPAQUE = Prefixed(_OerLength(), GreedyBytes)
_CONTENT_HEAD = Struct("protocolVersion" / Byte, "tag" / Byte)
_SIGNED_HEAD = Struct("hashId" / Byte, "payloadPreamble" / Byte)
_HASHED_DATA = Struct(  # CHOICE: sha256 in the root, the rest are extensions (open types)
    "tag" / Byte,
    "value" / Switch(this.tag, {0x80: Bytes(32), 0x81: _OPAQUE, 0x82: _OPAQUE}, default=Error),
)
_EXTENSION_ADDITIONS = Struct(  # X.696 §16.4: presence bitmap, then one open type per bit set
    "bitmap" / _OPAQUE,
    "count" / Computed(lambda ctx: sum(bin(b).count("1") for b in ctx.bitmap[1:])),
    "values" / Array(this.count, _OPAQUE),
)
_HEADER_INFO_HEAD = Struct(
    "preamble" / Byte,
    "psid" / _OPAQUE,
    "generationTime" / If(this.preamble & 0x40, Int64ub),
)
_UNSECURED_DATA = Struct(Const(bytes([PROTOCOL_VERSION, _UNSECURED])), "data" / _OPAQUE)


@dataclass(frozen=True)
class Unwrapped:
    """The innermost unsecured octets of an ``Ieee1609Dot2Data`` and what wrapped them."""

    frame: bytes  # normally a UPER MessageFrame
    security: str  # "unsecured" | "signed"
    psid: int | None = None
    generation_time_us: int | None = None  # Time64: µs since 2004-01-01 00:00:00 TAI


def _read(con: Construct, stream: io.BytesIO, what: str) -> Any:
    try:
        return con.parse_stream(stream)
    except StreamError:
        raise DecodeError("truncated", f"1609.2 {what}: input ends early") from None
    except ConstructError as err:
        raise DecodeError("garbage", f"1609.2 {what}: {err}") from None


def _finish_signed(stream: io.BytesIO, preamble: int) -> tuple[int, int | None]:
    """Skip the rest of a SignedDataPayload and read (psid, generationTime) of its headerInfo."""
    if preamble & 0x20:
        _read(_HASHED_DATA, stream, "extDataHash")
    if preamble & 0x80:
        _read(_EXTENSION_ADDITIONS, stream, "SignedDataPayload extensions")
    header = _read(_HEADER_INFO_HEAD, stream, "headerInfo")
    if header.preamble & 0x01:
        raise DecodeError("garbage", "1609.2 headerInfo: preamble padding bit set")
    if not 1 <= len(header.psid) <= 8:
        raise DecodeError("out-of-range", f"1609.2 psid: {len(header.psid)} octets")
    return int.from_bytes(header.psid, "big"), header.generationTime


def unwrap(data: bytes) -> Unwrapped:
    """Parse a COER ``Ieee1609Dot2Data`` and return its innermost unsecured payload."""
    stream = io.BytesIO(bytes(data))
    signed_preamble: int | None = None
    for _depth in range(_MAX_DEPTH):
        head = _read(_CONTENT_HEAD, stream, "Ieee1609Dot2Data")
        if head.protocolVersion != PROTOCOL_VERSION:
            raise DecodeError("garbage", f"1609.2 protocolVersion {head.protocolVersion}, not 3")
        if head.tag == _UNSECURED:
            frame = _read(_OPAQUE, stream, "unsecuredData")
            break
        if head.tag in _UNSUPPORTED:
            raise DecodeError("unsupported", f"1609.2 content {_UNSUPPORTED[head.tag]}")
        if head.tag != _SIGNED:
            raise DecodeError("garbage", f"1609.2 content tag 0x{head.tag:02x}")
        signed = _read(_SIGNED_HEAD, stream, "signedData")
        if signed.hashId >= 0x80 or signed.payloadPreamble & 0x1F:
            raise DecodeError("garbage", "1609.2 signedData: bad hashId or payload preamble")
        if not signed.payloadPreamble & 0x40:
            raise DecodeError("unsupported", "1609.2 signedData without embedded data")
        signed_preamble = signed.payloadPreamble
    else:
        raise DecodeError("unsupported", f"1609.2 signedData nested deeper than {_MAX_DEPTH}")

    if signed_preamble is None:
        trailing = len(stream.getbuffer()) - stream.tell()
        if trailing:
            raise DecodeError("garbage", f"1609.2 unsecuredData followed by {trailing} octets")
        return Unwrapped(frame=frame, security="unsecured")
    psid, generation_time = _finish_signed(stream, signed_preamble)
    return Unwrapped(frame, "signed", psid, generation_time)


def wrap_unsecured(frame: bytes) -> bytes:
    """Wrap ``frame`` in an unsecured ``Ieee1609Dot2Data`` (version 3, ``unsecuredData``)."""
    return _UNSECURED_DATA.build({"data": bytes(frame)})


def looks_like_1609(data: bytes) -> bool:
    """Cheap sniff: protocolVersion 3 followed by a known ``content`` CHOICE tag."""
    return len(data) >= 2 and data[0] == PROTOCOL_VERSION and 0x80 <= data[1] <= 0x84
