"""IEEE 1609.2-2016 §6.3 ``Ieee1609Dot2Data`` in canonical OER: unwrap to the innermost
unsecured octets, and build unsecured or signed data.

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
  octet bit 7 extensions, bit 6 ``generationTime``, bits 5..1 ``expiryTime``,
  ``generationLocation``, ``p2pcdLearningRequest``, ``missingCrlIdentifier``,
  ``encryptionKey``.  ``psid`` is an INTEGER (0..MAX), so a length determinant then
  unsigned big-endian octets; ``generationTime`` is a ``Time64`` (8 octets,
  microseconds since 2004-01-01 00:00:00 UTC, counted in TAI).  Extension additions
  (X.696 §16.4) are skipped as open types.
- ``SignerIdentifier`` is a CHOICE of ``digest`` (HashedId8),
  ``certificate`` (SEQUENCE OF Certificate: a quantity field then the certificates)
  and ``self``.

Signed data is followed down its ``payload.data`` to the innermost ``unsecuredData``;
every layer is parsed completely (header, signer, certificates, signature).  What is
reported (:class:`Unwrapped`) is the innermost signed layer, the one that signs the
frame: its headerInfo, the exact octets of its ``ToBeSignedData`` (the data input of
the signature, §5.3.1 / §6.3.4), its signer and its signature.  Nothing here does
cryptography: the signature is verified by :mod:`catc.security`.  Forms this codec
decodes structurally but cannot *verify* do not stop :func:`unwrap`: the frame is
delivered and :attr:`Unwrapped.unsupported` says why the signature cannot be checked
(deployed SCMS pseudonym certificates are implicit, and an OBU still wants the BSM).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Any

from catc.errors import DecodeError, EncodeError
from catc.j2735.ieee1609._basetypes import (
    HASHES,
    PSID_BSM,
    read_point,
    read_signature,
    signature_octets,
)
from catc.j2735.ieee1609._certificate import Certificate, read_certificate
from catc.j2735.ieee1609._oer import (
    enc_octets,
    enc_psid,
    enc_quantity,
    read_enumerated,
    read_octets,
    read_preamble,
    read_psid,
    read_quantity,
    read_tag,
    read_uint,
    skip_extensions,
    take,
)

PROTOCOL_VERSION = 3

_UNSECURED, _SIGNED = 0x80, 0x81
_UNSUPPORTED = {
    0x82: "encryptedData",
    0x83: "signedCertificateRequest",
    0x84: "signedX509CertificateRequest",
}
_MAX_DEPTH = 8  # signed-inside-signed nesting accepted before giving up
_MAX_CERTS = 8  # certificates in one SignerIdentifier
_UNSECURED_HEAD = bytes([PROTOCOL_VERSION, _UNSECURED])
# What an unknown HashedData alternative is reported with (the message of the
# construct-based parser this replaced, kept octet for octet).
_NO_ALTERNATIVE = "Error in path (parsing) -> value\nError field was activated during parsing"


@dataclass(frozen=True)
class Unwrapped:
    """The innermost unsecured octets of an ``Ieee1609Dot2Data`` and what wrapped them.

    For signed data, the fields after ``generation_time_us`` describe the innermost
    ``SignedData`` (§6.3.4): ``tbs_data`` is the exact COER of its ``ToBeSignedData``;
    ``signer_digest`` is the HashedId8 of the signing certificate (the ``digest`` sent, or
    the HashedId8 of the first certificate sent); ``signature`` is r || s (64 octets).
    ``signed_layers`` counts the ``SignedData`` layers around the frame (a BSM has one);
    ``wsmp_psid`` is the PSID of the WAVE Short Message that carried the data, when it
    came in one (set by :func:`catc.j2735.open_envelope`, not by :func:`unwrap`).
    """

    frame: bytes  # normally a UPER MessageFrame
    security: str  # "unsecured" | "signed"
    psid: int | None = None
    generation_time_us: int | None = None  # Time64: µs since 2004-01-01 00:00:00 UTC, TAI
    hash_id: str | None = None  # "sha256" (or "sha384", "sm3", "unknown(n)")
    tbs_data: bytes | None = None
    signer_kind: str | None = None  # "digest" | "certificate" | "self" | "unknown(n)"
    signer_digest: bytes | None = None
    signer_certs: tuple[Certificate, ...] = ()
    signature: bytes | None = None
    signature_r_form: str | None = None
    expiry_time_us: int | None = None
    unsupported: str | None = None  # why the signature cannot be verified by catc, if so
    signed_layers: int = 0
    wsmp_psid: int | None = None


def _skip_hashed_data(stream: io.BytesIO) -> None:
    """``extDataHash``: ``HashedData``, an extensible CHOICE with ``sha256HashedData``
    (32 octets) in the root; the later alternatives are open types."""
    what = "extDataHash"
    tag = take(stream, 1, what)[0]
    if tag == 0x80:
        take(stream, 32, what)
    elif tag in (0x81, 0x82):
        read_octets(stream, what)
    else:
        raise DecodeError("garbage", f"1609.2 {what}: {_NO_ALTERNATIVE}")


def _header_info(stream: io.BytesIO) -> tuple[int, int | None, int | None]:
    """``HeaderInfo`` (§6.3.9): (psid, generationTime, expiryTime); the rest is skipped."""
    what = "headerInfo"
    preamble = take(stream, 1, what)[0]
    if preamble & 0x01:
        raise DecodeError("garbage", "1609.2 headerInfo: preamble padding bit set")
    psid = read_psid(stream, "psid")
    generation = read_uint(stream, 8, "generationTime") if preamble & 0x40 else None
    expiry = read_uint(stream, 8, "expiryTime") if preamble & 0x20 else None
    if preamble & 0x10:
        take(stream, 10, "generationLocation")  # ThreeDLocation: 4 + 4 + 2 octets
    if preamble & 0x08:
        take(stream, 3, "p2pcdLearningRequest")
    if preamble & 0x04:  # MissingCrlIdentifier, extensible: preamble, cracaId, crlSeries
        extended = read_preamble(stream, 1, "missingCrlIdentifier") & 0x80
        take(stream, 5, "missingCrlIdentifier")
        if extended:
            skip_extensions(stream, "missingCrlIdentifier")
    if preamble & 0x02:  # EncryptionKey CHOICE {public, symmetric}
        index = read_tag(stream, "encryptionKey")
        if index == 0:
            read_enumerated(stream, "supportedSymmAlg")
            if read_tag(stream, "BasePublicEncryptionKey") <= 1:
                read_point(stream, "encryptionKey")
            else:
                read_octets(stream, "BasePublicEncryptionKey")
        elif index == 1:
            if read_tag(stream, "SymmetricEncryptionKey") == 0:
                take(stream, 16, "aes128Ccm")
            else:
                read_octets(stream, "SymmetricEncryptionKey")
        else:
            raise DecodeError("garbage", f"1609.2 encryptionKey alternative {index}")
    if preamble & 0x80:
        skip_extensions(stream, what)
    return psid, generation, expiry


def _signer(
    stream: io.BytesIO, buf: bytes
) -> tuple[str, bytes | None, tuple[Certificate, ...], str | None]:
    """``SignerIdentifier``: (kind, HashedId8, certificates, unsupported note)."""
    index = read_tag(stream, "signer")
    if index == 0:
        return "digest", take(stream, 8, "signer digest"), (), None
    if index == 1:
        count = read_quantity(stream, "signer certificates", _MAX_CERTS)
        if count == 0:
            raise DecodeError("garbage", "1609.2 signer: empty certificate sequence")
        certs = tuple(read_certificate(stream, buf) for _ in range(count))
        note = certs[0].unsupported and f"signer {certs[0].unsupported}"
        return "certificate", certs[0].hashed_id8, certs, note
    if index == 2:
        return "self", None, (), None
    read_octets(stream, "signer")
    return f"unknown({index})", None, (), f"signer alternative {index}"


def unwrap(data: bytes) -> Unwrapped:
    """Parse a COER ``Ieee1609Dot2Data`` and return its innermost unsecured payload.

    Signed layers are parsed completely (§6.3.4-§6.3.9, §6.4); octets after a signed
    ``Ieee1609Dot2Data`` are ignored (some ODE records carry one), after unsecured data
    they are ``garbage``.
    """
    buf = bytes(data)
    stream = io.BytesIO(buf)
    layers: list[tuple[int, int, int]] = []  # (hashId, ToBeSignedData offset, payload preamble)
    for _depth in range(_MAX_DEPTH):
        version, tag = take(stream, 2, "Ieee1609Dot2Data")  # protocolVersion, content tag
        if version != PROTOCOL_VERSION:
            raise DecodeError("garbage", f"1609.2 protocolVersion {version}, not 3")
        if tag == _UNSECURED:
            frame = read_octets(stream, "unsecuredData")
            break
        if tag in _UNSUPPORTED:
            raise DecodeError("unsupported", f"1609.2 content {_UNSUPPORTED[tag]}")
        if tag != _SIGNED:
            raise DecodeError("garbage", f"1609.2 content tag 0x{tag:02x}")
        hash_id, payload_preamble = take(stream, 2, "signedData")
        if hash_id >= 0x80 or payload_preamble & 0x1F:
            raise DecodeError("garbage", "1609.2 signedData: bad hashId or payload preamble")
        if not payload_preamble & 0x40:
            raise DecodeError("unsupported", "1609.2 signedData without embedded data")
        layers.append((hash_id, stream.tell() - 1, payload_preamble))
    else:
        raise DecodeError("unsupported", f"1609.2 signedData nested deeper than {_MAX_DEPTH}")

    if not layers:
        trailing = len(buf) - stream.tell()
        if trailing:
            raise DecodeError("garbage", f"1609.2 unsecuredData followed by {trailing} octets")
        return Unwrapped(frame=frame, security="unsecured")

    inner: Unwrapped | None = None
    for hash_index, tbs_start, preamble in reversed(layers):  # innermost layer first
        if preamble & 0x20:
            _skip_hashed_data(stream)
        if preamble & 0x80:
            skip_extensions(stream, "SignedDataPayload")
        psid, generation, expiry = _header_info(stream)
        tbs = buf[tbs_start : stream.tell()]
        kind, digest, certs, signer_note = _signer(stream, buf)
        signature, r_form, signature_note = read_signature(stream, "signature")
        if inner is None:
            hash_id = HASHES.get(hash_index, f"unknown({hash_index})")
            hash_note = None if hash_id == "sha256" else f"hashId {hash_id}"
            notes = [n for n in (hash_note, signer_note, signature_note) if n]
            inner = Unwrapped(
                frame, "signed", psid, generation, hash_id=hash_id, tbs_data=tbs,
                signer_kind=kind, signer_digest=digest, signer_certs=certs,
                signature=signature, signature_r_form=r_form, expiry_time_us=expiry,
                unsupported="; ".join(notes) or None, signed_layers=len(layers),
            )
    assert inner is not None
    return inner


def wrap_unsecured(frame: bytes) -> bytes:
    """Wrap ``frame`` in an unsecured ``Ieee1609Dot2Data`` (version 3, ``unsecuredData``)."""
    return _UNSECURED_HEAD + enc_octets(bytes(frame))


def tbs_data(frame: bytes, psid: int, generation_time_us: int) -> bytes:
    """COER ``ToBeSignedData`` (§6.3.6) carrying ``frame`` as unsecured ``payload.data``
    (§6.3.7) with a ``headerInfo`` of ``psid`` and ``generationTime`` only (§6.3.9).

    These are the octets that are hashed for the signature (the data input of §5.3.1).
    """
    if not 0 <= generation_time_us < 1 << 64:
        raise EncodeError(f"generationTime {generation_time_us} is not a Time64")
    header = b"\x40" + enc_psid(psid) + generation_time_us.to_bytes(8, "big")
    return b"\x40" + wrap_unsecured(frame) + header


def build_signed(
    frame: bytes,
    *,
    psid: int = PSID_BSM,
    generation_time_us: int,
    signer: tuple[str, Any],
    signature: bytes,
) -> bytes:
    """COER ``Ieee1609Dot2Data`` with ``signedData`` (§6.3.4), hashId sha256.

    ``signer`` is ``("digest", hashed_id8)``, ``("certificate", cert_raw)`` (or a list of
    certificates, the signer's first, each followed by its issuer) or ``("self", None)``;
    ``signature`` is r || s (64 octets), sent with rSig x-only.  Sign
    :func:`tbs_data` of the same arguments (see :func:`catc.security.sign_bsm`).
    """
    kind, value = signer
    if kind == "digest":
        if len(value) != 8:
            raise EncodeError("a digest signer is a HashedId8, 8 octets")
        signer_octets = b"\x80" + bytes(value)
    elif kind == "certificate":
        certs = [bytes(value)] if isinstance(value, (bytes, bytearray)) else list(value)
        if not 1 <= len(certs) <= _MAX_CERTS:
            raise EncodeError(f"1 to {_MAX_CERTS} signer certificates")
        signer_octets = b"\x81" + enc_quantity(len(certs)) + b"".join(map(bytes, certs))
    elif kind == "self":
        signer_octets = b"\x82"
    else:
        raise EncodeError(f"unknown signer kind {kind!r}")
    tbs = tbs_data(frame, psid, generation_time_us)
    return b"\x03\x81\x00" + tbs + signer_octets + signature_octets(signature)


def looks_like_1609(data: bytes) -> bool:
    """Cheap sniff: protocolVersion 3 followed by a known ``content`` CHOICE tag."""
    return len(data) >= 2 and data[0] == PROTOCOL_VERSION and 0x80 <= data[1] <= 0x84

