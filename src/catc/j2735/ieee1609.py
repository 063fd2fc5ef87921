"""IEEE 1609.2 ``Ieee1609Dot2Data`` and certificates in canonical OER, and the WSMP envelope.

Deployed OBUs and RSUs send a J2735 UPER MessageFrame inside an IEEE 1609.2 secured
data structure, encoded with COER (ITU-T X.696 canonical OER), usually carried in a
WAVE Short Message (IEEE 1609.3).  The types come from IEEE Std 1609.2-2016 §6.3 and
§6.4 (ASN.1 modules ``Ieee1609Dot2`` and ``Ieee1609Dot2BaseTypes``, as published e.g. in
the usdot-jpo-ode/asn1_codec repository); the octet layout from X.696:

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
  and ``self``; ``Signature`` an extensible CHOICE whose root alternatives
  are ``EcdsaP256Signature`` ``{rSig EccP256CurvePoint, sSig OCTET STRING (32)}``.
- ``CertificateBase`` (§6.4.3): a preamble octet (bit 7: ``signature`` present),
  ``version`` 3, ``type`` (explicit 0 / implicit 1), ``issuer`` (``sha256AndDigest``
  HashedId8 | ``self`` HashAlgorithm | ``sha384AndDigest``), ``toBeSigned``
  (``ToBeSignedCertificate``, §6.4.8), ``signature``.

Signed data is followed down its ``payload.data`` to the innermost ``unsecuredData``;
every layer is parsed completely (header, signer, certificates, signature).  What is
reported (:class:`Unwrapped`) is the innermost signed layer, the one that signs the
frame: its headerInfo, the exact octets of its ``ToBeSignedData`` (the data input of
the signature, §5.3.1 / §6.3.4), its signer and its signature.  Nothing here does
cryptography: the signature is verified by :mod:`catc.security`.  The only hash computed
is the HashedId8 of a certificate (§6.4.3), an identifier.

Forms this codec decodes structurally but cannot *verify* (implicit certificates,
brainpool or P-384 keys and signatures, SHA-384) do not stop :func:`unwrap`: the frame
is delivered and :attr:`Unwrapped.unsupported` says why the signature cannot be checked
(deployed SCMS pseudonym certificates are implicit, and an OBU still wants the BSM).
:func:`parse_certificate` on its own rejects them as ``unsupported``.

Every count, length and nesting depth is bounded, so hostile input costs time and
memory proportional to its length at most.  Errors are :class:`DecodeError` with the
reasons of :mod:`catc.errors`: input that ends early is ``truncated``, a form this codec
does not handle is ``unsupported``, anything else malformed is ``garbage``.

The WAVE Short Message (IEEE 1609.3-2016 §8.3) that carries the data over the air, or
over Ethernet with ethertype 0x88DC, is handled by :func:`wrap_wsmp` and
:func:`unwrap_wsmp`.
"""

from __future__ import annotations

import hashlib
import io
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from catc.errors import DecodeError, EncodeError

PROTOCOL_VERSION = 3
PSID_BSM = 0x20  # IEEE 1609.12: vehicle-to-vehicle safety and awareness (J2735 BSM)
ISSUE_ALL = "all"  # ``issue_psids`` of a certificate that may issue for every PSID

_UNSECURED, _SIGNED = 0x80, 0x81
_UNSUPPORTED = {
    0x82: "encryptedData",
    0x83: "signedCertificateRequest",
    0x84: "signedX509CertificateRequest",
}
_MAX_DEPTH = 8  # signed-inside-signed nesting accepted before giving up
_MAX_ENTRIES = 64  # entries in one SEQUENCE OF (1609.2 requires support for >= 8)
_MAX_CERTS = 8  # certificates in one SignerIdentifier
_HASHES = {0: "sha256", 1: "sha384", 2: "sm3"}  # HashAlgorithm (§6.3.5; sm3 from 1609.2-2022)
_POINT_FORMS = ("x-only", "fill", "compressed-y-0", "compressed-y-1", "uncompressed")
# Duration CHOICE: microseconds, milliseconds, then seconds per unit of
# seconds, minutes, hours, sixtyHours, years (a year is 31 556 952 s there).
_UNIT_SECONDS = (None, None, 1, 60, 3600, 216_000, 31_556_952)
_UNSECURED_HEAD = bytes([PROTOCOL_VERSION, _UNSECURED])
# What an unknown HashedData alternative is reported with (the message of the
# construct-based parser this replaced, kept octet for octet).
_NO_ALTERNATIVE = "Error in path (parsing) -> value\nError field was activated during parsing"


@dataclass(frozen=True)
class Certificate:
    """A parsed COER ``Certificate`` (IEEE 1609.2-2016 §6.4.1-§6.4.8).

    ``raw`` is the certificate as received; ``canonical`` its canonical form (§6.4.3:
    public keys compressed, the signature's r as x-only; equal to ``raw`` for everything
    :func:`build_certificate` makes), which is what is hashed: ``hashed_id8`` is the
    low-order 8 octets of SHA-256 over it, and ``tbs`` is its ``toBeSigned`` part, the
    data input of the issuer's signature (§6.4.8, §5.3.1).  Times are ``Time32``: TAI
    seconds since 2004-01-01 00:00:00 UTC.
    """

    raw: bytes
    tbs: bytes
    canonical: bytes
    hashed_id8: bytes
    cert_type: str  # "explicit" | "implicit" | "unknown(n)"
    issuer_kind: str  # "self" | "sha256AndDigest" | "sha384AndDigest" | "unknown(n)"
    issuer_digest: bytes | None  # HashedId8 of the issuing certificate, None if self-signed
    id_kind: str  # CertificateId: "linkageData" | "name" | "binaryId" | "none" | "unknown(n)"
    name: str | None
    craca_id: bytes
    crl_series: int
    start_time32: int
    duration_s: int
    app_psids: tuple[int, ...]  # appPermissions
    issue_psids: tuple[int, ...]  # certIssuePermissions, explicit PSIDs
    issue_all: bool  # certIssuePermissions has a group for all PSIDs
    issue_chain: tuple[int, int] | None  # (minChainLength, chainLengthRange) of the 1st group
    verify_key: bytes | None  # ecdsaNistP256 verification key, compressed SEC1 (33 octets)
    signature: bytes | None  # r || s, 64 octets
    signature_r_form: str | None  # how rSig was sent: "x-only", "compressed-y-0", ...
    unsupported: str | None = None  # why this certificate cannot be used to verify, if so

    @property
    def end_time32(self) -> int:
        """First Time32 second after the validity period (ValidityPeriod: start + duration)."""
        return self.start_time32 + self.duration_s


@dataclass(frozen=True)
class Unwrapped:
    """The innermost unsecured octets of an ``Ieee1609Dot2Data`` and what wrapped them.

    For signed data, the fields after ``generation_time_us`` describe the innermost
    ``SignedData`` (§6.3.4): ``tbs_data`` is the exact COER of its ``ToBeSignedData``;
    ``signer_digest`` is the HashedId8 of the signing certificate (the ``digest`` sent, or
    the HashedId8 of the first certificate sent); ``signature`` is r || s (64 octets).
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


# ------------------------------------------------------------------------------------------
# COER primitives (X.696)
# ------------------------------------------------------------------------------------------


def _take(stream: io.BytesIO, n: int, what: str) -> bytes:
    octets = stream.read(n)  # BytesIO.read never allocates more than what is left
    if len(octets) != n:
        raise DecodeError("truncated", f"1609.2 {what}: input ends early")
    return octets


def _uint(stream: io.BytesIO, n: int, what: str) -> int:
    return int.from_bytes(_take(stream, n, what), "big")


def _preamble(stream: io.BytesIO, used: int, what: str) -> int:
    """A one-octet SEQUENCE preamble (X.696 §16.2) whose low ``8 - used`` bits must be 0."""
    octet = _take(stream, 1, what)[0]
    if octet & (0xFF >> used):
        raise DecodeError("garbage", f"1609.2 {what}: preamble 0x{octet:02x}, padding bits set")
    return octet


def _tag(stream: io.BytesIO, what: str) -> int:
    """A CHOICE tag octet (X.696 §20, context class, tag number below 63): the index."""
    octet = _take(stream, 1, what)[0]
    if octet & 0xC0 != 0x80 or octet == 0xBF:
        raise DecodeError("garbage", f"1609.2 {what}: 0x{octet:02x} is not a CHOICE tag")
    return octet & 0x3F


def _enum(stream: io.BytesIO, what: str) -> int:
    """An ENUMERATED with fewer than 128 values (X.696 §11: one octet, short form)."""
    octet = _take(stream, 1, what)[0]
    if octet & 0x80:
        raise DecodeError("garbage", f"1609.2 {what}: enumerated value in long form")
    return octet


def _length(stream: io.BytesIO, what: str) -> int:
    """X.696 §8.6 length determinant (short form below 128, else ``0x80 | n`` + n octets)."""
    first = _take(stream, 1, what)[0]
    if first < 0x80:
        return first
    n = first & 0x7F
    if not 1 <= n <= 4:
        raise DecodeError("garbage", f"1609.2 length determinant with {n} length octets")
    return _uint(stream, n, what)


def _octets(stream: io.BytesIO, what: str) -> bytes:
    """A variable-size OCTET STRING or an open type: length determinant, then the octets."""
    return _take(stream, _length(stream, what), what)


def _quantity(stream: io.BytesIO, what: str, limit: int = _MAX_ENTRIES) -> int:
    """The quantity field of a SEQUENCE OF (X.696 §17): the entry count."""
    n = _take(stream, 1, what)[0]
    if not 1 <= n <= 4:
        raise DecodeError("garbage", f"1609.2 {what}: quantity field of {n} octets")
    count = _uint(stream, n, what)
    if count > limit:
        raise DecodeError("unsupported", f"1609.2 {what}: {count} entries (at most {limit})")
    return count


def _psid(stream: io.BytesIO, what: str) -> int:
    """``Psid ::= INTEGER (0..MAX)``: length determinant, unsigned octets (at most 8)."""
    octets = _octets(stream, what)
    if not 1 <= len(octets) <= 8:
        raise DecodeError("out-of-range", f"1609.2 {what}: {len(octets)} octets")
    return int.from_bytes(octets, "big")


def _signed_int(stream: io.BytesIO, what: str) -> int:
    """An unconstrained INTEGER: length determinant, two's complement (at most 8 octets)."""
    octets = _octets(stream, what)
    if not 1 <= len(octets) <= 8:
        raise DecodeError("garbage", f"1609.2 {what}: integer of {len(octets)} octets")
    return int.from_bytes(octets, "big", signed=True)


def _extensions(stream: io.BytesIO, what: str) -> None:
    """The extension additions of an extensible SEQUENCE (X.696 §16.4): a presence bitmap
    (an OCTET STRING whose first octet counts the unused bits), then one open type per
    bit set, all skipped."""
    what = f"{what} extensions"
    bitmap = _octets(stream, what)
    for _ in range(sum(bin(b).count("1") for b in bitmap[1:])):
        _octets(stream, what)


def _length_octets(n: int) -> bytes:
    if n < 0x80:
        return bytes([n])
    body = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes([0x80 | len(body)]) + body


def _enc_octets(octets: bytes) -> bytes:
    return _length_octets(len(octets)) + octets


def _enc_quantity(n: int) -> bytes:
    body = n.to_bytes(max(1, (n.bit_length() + 7) // 8), "big")
    return bytes([len(body)]) + body


def _enc_psid(psid: int) -> bytes:
    if not isinstance(psid, int) or not 0 <= psid < 1 << 64:
        raise EncodeError(f"psid {psid!r} is not an integer in 0..2**64-1")
    return _enc_octets(psid.to_bytes(max(1, (psid.bit_length() + 7) // 8), "big"))


def _enc_signed_int(n: int) -> bytes:
    size = ((n if n >= 0 else ~n).bit_length() + 8) // 8  # minimal two's complement
    return _enc_octets(n.to_bytes(size, "big", signed=True))


# ------------------------------------------------------------------------------------------
# Certificates (§6.4)
# ------------------------------------------------------------------------------------------


class _Splices:
    """Replacements that turn the received octets into the canonical form (§6.4.3)."""

    def __init__(self) -> None:
        self.items: list[tuple[int, int, bytes]] = []

    def add(self, start: int, end: int, octets: bytes) -> None:
        self.items.append((start, end, octets))

    def apply(self, buf: bytes, start: int, end: int) -> bytes:
        out, pos = [], start
        for a, b, octets in self.items:
            if start <= a and b <= end:
                out += [buf[pos:a], octets]
                pos = b
        out.append(buf[pos:end])
        return b"".join(out)


def _point(stream: io.BytesIO, what: str) -> tuple[str, bytes]:
    """``EccP256CurvePoint`` (not extensible): (form, x or x || y)."""
    index = _tag(stream, what)
    if index in (0, 2, 3):
        return _POINT_FORMS[index], _take(stream, 32, what)
    if index == 1:
        return "fill", b""
    if index == 4:
        return "uncompressed", _take(stream, 64, what)
    raise DecodeError("garbage", f"1609.2 {what}: EccP256CurvePoint alternative {index}")


def _public_point(stream: io.BytesIO, what: str, splices: _Splices) -> bytes:
    """A public key or reconstruction value: returned as compressed SEC1 (33 octets); an
    uncompressed point is recorded for canonicalisation (§6.4.3: compressed form)."""
    start = stream.tell()
    form, value = _point(stream, what)
    if form in ("x-only", "fill"):
        raise DecodeError("garbage", f"1609.2 {what}: a public key cannot be {form}")
    if form == "uncompressed":
        odd = value[63] & 1
        splices.add(start, stream.tell(), bytes([0x82 | odd]) + value[:32])
        return bytes([2 | odd]) + value[:32]
    return bytes([2 if form == "compressed-y-0" else 3]) + value


def _signature(
    stream: io.BytesIO, what: str, splices: _Splices | None = None
) -> tuple[bytes | None, str | None, str | None]:
    """``Signature``: (r || s, form of rSig, why it cannot be verified or None)."""
    index = _tag(stream, what)
    if index >= 2:  # extension alternatives (P-384 and later): open types
        _octets(stream, what)
        names = {2: "ecdsaBrainpoolP384r1Signature", 3: "ecdsaNistP384Signature"}
        return None, None, f"signature {names.get(index, f'alternative {index}')}"
    start = stream.tell()
    form, r = _point(stream, f"{what} rSig")
    if form == "fill":
        raise DecodeError("garbage", f"1609.2 {what}: rSig is fill, not a 32-octet value")
    if splices is not None and form != "x-only":  # §6.4.3: r taken as x-only for hashing
        splices.add(start, stream.tell(), b"\x80" + r[:32])
    s = _take(stream, 32, f"{what} sSig")
    note = None if index == 0 else "signature ecdsaBrainpoolP256r1Signature"
    return r[:32] + s, form, note


def _psid_ssp_ranges(stream: io.BytesIO, what: str) -> list[int]:
    """``SequenceOfPsidSspRange``: the PSIDs (SSP ranges are skipped)."""
    psids = []
    for _ in range(_quantity(stream, what)):
        has_range = _preamble(stream, 1, what) & 0x80
        psids.append(_psid(stream, f"{what} psid"))
        if has_range:
            index = _tag(stream, f"{what} sspRange")
            if index == 0:  # opaque SequenceOfOctetString
                for _ in range(_quantity(stream, f"{what} sspRange")):
                    _octets(stream, f"{what} sspRange")
            elif index >= 2:  # bitmapSspRange and later: open types
                _octets(stream, f"{what} sspRange")
    return psids


def _group_permissions(
    stream: io.BytesIO, what: str
) -> tuple[list[int], bool, tuple[int, int] | None]:
    """``SequenceOfPsidGroupPermissions``: (explicit PSIDs, any "all", chain)."""
    psids: list[int] = []
    everything = False
    chain = None
    for _ in range(_quantity(stream, what)):
        preamble = _preamble(stream, 3, what)
        index = _tag(stream, f"{what} subjectPermissions")
        if index == 0:
            psids += _psid_ssp_ranges(stream, f"{what} explicit")
        elif index == 1:
            everything = True
        else:
            _octets(stream, f"{what} subjectPermissions")
        min_length = _signed_int(stream, f"{what} minChainLength") if preamble & 0x80 else 1
        length_range = _signed_int(stream, f"{what} chainLengthRange") if preamble & 0x40 else 0
        if preamble & 0x20:
            _take(stream, 1, f"{what} eeType")
        chain = chain or (min_length, length_range)
    return psids, everything, chain


def _skip_region(stream: io.BytesIO) -> None:
    """``GeographicRegion``: structurally skipped, not interpreted."""
    what = "GeographicRegion"
    index = _tag(stream, what)
    if index == 0:  # circularRegion: TwoDLocation (2 x 4 octets), radius Uint16
        _take(stream, 10, what)
    elif index == 1:  # rectangularRegion: SEQUENCE OF two TwoDLocation
        _take(stream, 16 * _quantity(stream, what), what)
    elif index == 2:  # polygonalRegion: SEQUENCE OF TwoDLocation
        _take(stream, 8 * _quantity(stream, what), what)
    elif index == 3:  # identifiedRegion: SEQUENCE OF IdentifiedRegion
        for _ in range(_quantity(stream, what)):
            kind = _tag(stream, what)
            if kind == 0:  # countryOnly
                _take(stream, 2, what)
            elif kind == 1:  # countryAndRegions: country, SequenceOfUint8
                _take(stream, 2, what)
                _take(stream, _quantity(stream, what), what)
            elif kind == 2:  # countryAndSubregions: country, SEQUENCE OF RegionAndSubregions
                _take(stream, 2, what)
                for _ in range(_quantity(stream, what)):
                    _take(stream, 1, what)
                    _take(stream, 2 * _quantity(stream, what), what)
            else:
                _octets(stream, what)
    else:
        _octets(stream, what)


def _certificate(stream: io.BytesIO, buf: bytes) -> Certificate:
    """Parse one ``CertificateBase`` (§6.4.3) at the stream position of ``buf``."""
    start = stream.tell()
    splices = _Splices()
    notes: list[str] = []
    what = "Certificate"
    has_signature = _preamble(stream, 1, what) & 0x80
    if _uint(stream, 1, f"{what} version") != 3:
        raise DecodeError("garbage", f"1609.2 {what}: version is not 3")
    type_index = _enum(stream, f"{what} type")
    cert_type = {0: "explicit", 1: "implicit"}.get(type_index, f"unknown({type_index})")
    if type_index not in (0, 1):
        notes.append(f"certificate type {cert_type}")

    issuer_index = _tag(stream, f"{what} issuer")
    issuer_digest: bytes | None = None
    if issuer_index == 0:
        issuer_kind, issuer_digest = "sha256AndDigest", _take(stream, 8, "issuer")
    elif issuer_index == 1:
        issuer_kind = "self"
        algorithm = _enum(stream, "issuer self")
        if algorithm != 0:
            notes.append(f"self-signed with {_HASHES.get(algorithm, algorithm)}")
    else:
        value = _octets(stream, "issuer")
        if issuer_index == 2 and len(value) == 8:
            issuer_kind, issuer_digest = "sha384AndDigest", value
        else:
            issuer_kind = f"unknown({issuer_index})"
        notes.append(f"issuer {issuer_kind}")

    tbs_start = stream.tell()
    what = "ToBeSignedCertificate"
    optional = _preamble(stream, 8, what)
    id_index = _tag(stream, f"{what} id")
    name = None
    if id_index == 0:  # linkageData
        has_group = _preamble(stream, 1, "linkageData") & 0x80
        _take(stream, 2 + 9 + (13 if has_group else 0), "linkageData")
    elif id_index == 1:
        octets = _octets(stream, "name")
        try:
            name = octets.decode("utf-8")
        except UnicodeDecodeError:
            raise DecodeError("garbage", "1609.2 certificate name is not UTF-8") from None
        if len(name) > 255:  # Hostname ::= UTF8String (SIZE(0..255))
            raise DecodeError("garbage", "1609.2 certificate name longer than 255 characters")
    elif id_index == 2:
        if not 1 <= len(_octets(stream, "binaryId")) <= 64:
            raise DecodeError("garbage", "1609.2 certificate binaryId not of 1..64 octets")
    elif id_index >= 4:
        _octets(stream, f"{what} id")
        notes.append(f"certificate id alternative {id_index}")
    id_kind = ("linkageData", "name", "binaryId", "none")[id_index] if id_index < 4 else (
        f"unknown({id_index})")
    craca_id = _take(stream, 3, "cracaId")
    crl_series = _uint(stream, 2, "crlSeries")
    start_time32 = _uint(stream, 4, "validityPeriod start")
    unit = _tag(stream, "validityPeriod duration")
    if unit > 6:
        raise DecodeError("garbage", f"1609.2 Duration alternative {unit}")
    count = _uint(stream, 2, "validityPeriod duration")
    per_unit = _UNIT_SECONDS[unit]
    duration_s = count * per_unit if per_unit else count // (1_000_000 if unit == 0 else 1000)
    if optional & 0x40:
        _skip_region(stream)
    if optional & 0x20:
        _take(stream, 1, "assuranceLevel")
    app_psids: list[int] = []
    if optional & 0x10:
        for _ in range(_quantity(stream, "appPermissions")):
            has_ssp = _preamble(stream, 1, "PsidSsp") & 0x80
            app_psids.append(_psid(stream, "appPermissions psid"))
            if has_ssp:
                _tag(stream, "ServiceSpecificPermissions")
                _octets(stream, "ServiceSpecificPermissions")  # opaque or an open type
    issue_psids: list[int] = []
    issue_all, issue_chain = False, None
    if optional & 0x08:
        issue_psids, issue_all, issue_chain = _group_permissions(stream, "certIssuePermissions")
    if optional & 0x04:
        _group_permissions(stream, "certRequestPermissions")
    if not optional & 0x1C:
        raise DecodeError("garbage", "1609.2 certificate without any permissions (§6.4.8)")
    if optional & 0x01:  # encryptionKey: PublicEncryptionKey
        _enum(stream, "supportedSymmAlg")
        index = _tag(stream, "BasePublicEncryptionKey")
        if index <= 1:
            _public_point(stream, "encryptionKey", splices)
        else:
            _octets(stream, "BasePublicEncryptionKey")
    verify_key = None
    indicator = _tag(stream, "verifyKeyIndicator")
    if indicator == 0:
        curve = _tag(stream, "PublicVerificationKey")
        if curve <= 1:
            point = _public_point(stream, "verificationKey", splices)
            if curve == 0:
                verify_key = point
            else:
                notes.append("verification key ecdsaBrainpoolP256r1")
        else:
            _octets(stream, "PublicVerificationKey")
            names = {2: "ecdsaBrainpoolP384r1", 3: "ecdsaNistP384"}
            notes.append(f"verification key {names.get(curve, f'alternative {curve}')}")
    elif indicator == 1:
        _public_point(stream, "reconstructionValue", splices)
    else:
        _octets(stream, "verifyKeyIndicator")
        notes.append(f"verifyKeyIndicator alternative {indicator}")
    if optional & 0x80:
        _extensions(stream, what)
    tbs_end = stream.tell()

    signature = r_form = None
    if has_signature:
        signature, r_form, note = _signature(stream, "certificate signature", splices)
        if note:
            notes.append(note)
    end = stream.tell()

    if cert_type == "explicit" and (indicator != 0 or not has_signature):
        raise DecodeError("garbage", "1609.2 explicit certificate without key or signature")
    if cert_type == "implicit":
        if indicator != 1 or has_signature:
            raise DecodeError("garbage", "1609.2 implicit certificate with key or signature")
        notes.append("implicit certificate")
    canonical = splices.apply(buf, start, end)
    return Certificate(
        raw=buf[start:end],
        tbs=splices.apply(buf, tbs_start, tbs_end),
        canonical=canonical,
        hashed_id8=hashlib.sha256(canonical).digest()[-8:],
        cert_type=cert_type,
        issuer_kind=issuer_kind,
        issuer_digest=issuer_digest,
        id_kind=id_kind,
        name=name,
        craca_id=craca_id,
        crl_series=crl_series,
        start_time32=start_time32,
        duration_s=duration_s,
        app_psids=tuple(app_psids),
        issue_psids=tuple(issue_psids),
        issue_all=issue_all,
        issue_chain=issue_chain,
        verify_key=verify_key,
        signature=signature,
        signature_r_form=r_form,
        unsupported="; ".join(notes) or None,
    )


def parse_certificate(data: bytes) -> tuple[Certificate, int]:
    """Parse the COER ``Certificate`` at the start of ``data``: (certificate, octets used).

    Only explicit certificates with an ecdsaNistP256 key and signature are accepted; other
    well-formed certificates (implicit, other curves) raise ``DecodeError("unsupported")``.
    """
    buf = bytes(data)
    stream = io.BytesIO(buf)
    cert = _certificate(stream, buf)
    if cert.unsupported:
        raise DecodeError("unsupported", f"1609.2 {cert.unsupported}")
    return cert, stream.tell()


def _duration(seconds: int) -> bytes:
    """The exact ``Duration`` with the finest unit that holds ``seconds``."""
    for index, unit in enumerate(_UNIT_SECONDS):
        if unit and seconds % unit == 0 and 0 <= seconds // unit <= 0xFFFF:
            return bytes([0x80 | index]) + (seconds // unit).to_bytes(2, "big")
    raise EncodeError(f"certificate duration of {seconds} s is not a whole Uint16 of a unit")


def _compressed_key(key: bytes) -> bytes:
    """A SEC1 P-256 point (33 compressed or 65 uncompressed octets) as EccP256CurvePoint."""
    key = bytes(key)
    if len(key) == 33 and key[0] in (2, 3):
        return bytes([0x80 | key[0]]) + key[1:]
    if len(key) == 65 and key[0] == 4:
        return bytes([0x82 | key[64] & 1]) + key[1:33]
    raise EncodeError("verification key is not a 33- or 65-octet SEC1 point")


def _psid_group(psids: Sequence[int] | str, chain: tuple[int, int]) -> bytes:
    """One ``PsidGroupPermissions``; DEFAULT components are omitted (COER)."""
    if psids == ISSUE_ALL:
        subject = b"\x81"
    else:
        subject = b"\x80" + _enc_quantity(len(psids))
        subject += b"".join(b"\x00" + _enc_psid(p) for p in psids)  # PsidSspRange, no range
    min_length, length_range = chain
    preamble = (0x80 if min_length != 1 else 0) | (0x40 if length_range != 0 else 0)
    out = bytes([preamble]) + subject
    if min_length != 1:
        out += _enc_signed_int(min_length)
    if length_range != 0:
        out += _enc_signed_int(length_range)
    return out


def build_tbs_certificate(
    *,
    verify_key: bytes,
    start_time32: int,
    duration_s: int,
    name: str | None = None,
    app_psids: Sequence[int] = (),
    issue_psids: Sequence[int] | str = (),
    issue_chain: tuple[int, int] = (1, 0),
    craca_id: bytes = bytes(3),
    crl_series: int = 0,
) -> bytes:
    """COER ``ToBeSignedCertificate`` (§6.4.8) of an explicit certificate.

    ``verify_key`` is the ecdsaNistP256 key as SEC1 octets (sent compressed, §6.4.3);
    ``name`` selects ``CertificateId`` name (else ``none``); ``app_psids`` becomes
    appPermissions (without SSPs); ``issue_psids`` (a PSID list or :data:`ISSUE_ALL`) one
    certIssuePermissions group with ``issue_chain`` = (minChainLength, chainLengthRange).
    The duration is encoded exactly in the finest unit that fits.
    """
    if not app_psids and not issue_psids:
        raise EncodeError("a certificate needs appPermissions or certIssuePermissions")
    if len(craca_id) != 3 or not 0 <= crl_series <= 0xFFFF or not 0 <= start_time32 < 1 << 32:
        raise EncodeError("cracaId, crlSeries or start time out of range")
    if name is None:
        ident = b"\x83"
    else:
        if len(name) > 255:
            raise EncodeError("certificate name longer than 255 characters")
        ident = b"\x81" + _enc_octets(name.encode("utf-8"))
    preamble = (0x10 if app_psids else 0) | (0x08 if issue_psids else 0)
    out = bytes([preamble]) + ident + bytes(craca_id) + crl_series.to_bytes(2, "big")
    out += start_time32.to_bytes(4, "big") + _duration(duration_s)
    if app_psids:
        out += _enc_quantity(len(app_psids)) + b"".join(b"\x00" + _enc_psid(p) for p in app_psids)
    if issue_psids:
        out += b"\x01\x01" + _psid_group(issue_psids, issue_chain)
    return out + b"\x80\x80" + _compressed_key(verify_key)  # verificationKey ecdsaNistP256


def _signature_octets(signature: bytes) -> bytes:
    if len(signature) != 64:
        raise EncodeError("an ECDSA P-256 signature is 64 octets, r || s")
    return b"\x80\x80" + bytes(signature)  # ecdsaNistP256Signature, rSig x-only


def build_certificate(tbs: bytes, *, issuer_digest: bytes | None, signature: bytes) -> bytes:
    """COER explicit ``Certificate`` (§6.4.2-§6.4.7) around the ``tbs`` octets.

    ``issuer_digest`` is the issuer's HashedId8 (``sha256AndDigest``), or None for a
    self-signed certificate (``self``: sha256).  ``signature`` is r || s (64 octets).
    """
    if issuer_digest is None:
        issuer = b"\x81\x00"
    elif len(issuer_digest) == 8:
        issuer = b"\x80" + bytes(issuer_digest)
    else:
        raise EncodeError("issuer digest is a HashedId8, 8 octets")
    return b"\x80\x03\x00" + issuer + bytes(tbs) + _signature_octets(signature)


# ------------------------------------------------------------------------------------------
# Ieee1609Dot2Data (§6.3)
# ------------------------------------------------------------------------------------------


def _skip_hashed_data(stream: io.BytesIO) -> None:
    """``extDataHash``: ``HashedData``, an extensible CHOICE with ``sha256HashedData``
    (32 octets) in the root; the later alternatives are open types."""
    what = "extDataHash"
    tag = _take(stream, 1, what)[0]
    if tag == 0x80:
        _take(stream, 32, what)
    elif tag in (0x81, 0x82):
        _octets(stream, what)
    else:
        raise DecodeError("garbage", f"1609.2 {what}: {_NO_ALTERNATIVE}")


def _header_info(stream: io.BytesIO) -> tuple[int, int | None, int | None]:
    """``HeaderInfo`` (§6.3.9): (psid, generationTime, expiryTime); the rest is skipped."""
    what = "headerInfo"
    preamble = _take(stream, 1, what)[0]
    if preamble & 0x01:
        raise DecodeError("garbage", "1609.2 headerInfo: preamble padding bit set")
    psid = _psid(stream, "psid")
    generation = _uint(stream, 8, "generationTime") if preamble & 0x40 else None
    expiry = _uint(stream, 8, "expiryTime") if preamble & 0x20 else None
    if preamble & 0x10:
        _take(stream, 10, "generationLocation")  # ThreeDLocation: 4 + 4 + 2 octets
    if preamble & 0x08:
        _take(stream, 3, "p2pcdLearningRequest")
    if preamble & 0x04:  # MissingCrlIdentifier, extensible: preamble, cracaId, crlSeries
        extended = _preamble(stream, 1, "missingCrlIdentifier") & 0x80
        _take(stream, 5, "missingCrlIdentifier")
        if extended:
            _extensions(stream, "missingCrlIdentifier")
    if preamble & 0x02:  # EncryptionKey CHOICE {public, symmetric}
        index = _tag(stream, "encryptionKey")
        if index == 0:
            _enum(stream, "supportedSymmAlg")
            if _tag(stream, "BasePublicEncryptionKey") <= 1:
                _point(stream, "encryptionKey")
            else:
                _octets(stream, "BasePublicEncryptionKey")
        elif index == 1:
            if _tag(stream, "SymmetricEncryptionKey") == 0:
                _take(stream, 16, "aes128Ccm")
            else:
                _octets(stream, "SymmetricEncryptionKey")
        else:
            raise DecodeError("garbage", f"1609.2 encryptionKey alternative {index}")
    if preamble & 0x80:
        _extensions(stream, what)
    return psid, generation, expiry


def _signer(
    stream: io.BytesIO, buf: bytes
) -> tuple[str, bytes | None, tuple[Certificate, ...], str | None]:
    """``SignerIdentifier``: (kind, HashedId8, certificates, unsupported note)."""
    index = _tag(stream, "signer")
    if index == 0:
        return "digest", _take(stream, 8, "signer digest"), (), None
    if index == 1:
        count = _quantity(stream, "signer certificates", _MAX_CERTS)
        if count == 0:
            raise DecodeError("garbage", "1609.2 signer: empty certificate sequence")
        certs = tuple(_certificate(stream, buf) for _ in range(count))
        note = certs[0].unsupported and f"signer {certs[0].unsupported}"
        return "certificate", certs[0].hashed_id8, certs, note
    if index == 2:
        return "self", None, (), None
    _octets(stream, "signer")
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
        version, tag = _take(stream, 2, "Ieee1609Dot2Data")  # protocolVersion, content tag
        if version != PROTOCOL_VERSION:
            raise DecodeError("garbage", f"1609.2 protocolVersion {version}, not 3")
        if tag == _UNSECURED:
            frame = _octets(stream, "unsecuredData")
            break
        if tag in _UNSUPPORTED:
            raise DecodeError("unsupported", f"1609.2 content {_UNSUPPORTED[tag]}")
        if tag != _SIGNED:
            raise DecodeError("garbage", f"1609.2 content tag 0x{tag:02x}")
        hash_id, payload_preamble = _take(stream, 2, "signedData")
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
            _extensions(stream, "SignedDataPayload")
        psid, generation, expiry = _header_info(stream)
        tbs = buf[tbs_start : stream.tell()]
        kind, digest, certs, signer_note = _signer(stream, buf)
        signature, r_form, signature_note = _signature(stream, "signature")
        if inner is None:
            hash_id = _HASHES.get(hash_index, f"unknown({hash_index})")
            hash_note = None if hash_id == "sha256" else f"hashId {hash_id}"
            notes = [n for n in (hash_note, signer_note, signature_note) if n]
            inner = Unwrapped(
                frame, "signed", psid, generation, hash_id=hash_id, tbs_data=tbs,
                signer_kind=kind, signer_digest=digest, signer_certs=certs,
                signature=signature, signature_r_form=r_form, expiry_time_us=expiry,
                unsupported="; ".join(notes) or None,
            )
    assert inner is not None
    return inner


def wrap_unsecured(frame: bytes) -> bytes:
    """Wrap ``frame`` in an unsecured ``Ieee1609Dot2Data`` (version 3, ``unsecuredData``)."""
    return _UNSECURED_HEAD + _enc_octets(bytes(frame))


def tbs_data(frame: bytes, psid: int, generation_time_us: int) -> bytes:
    """COER ``ToBeSignedData`` (§6.3.6) carrying ``frame`` as unsecured ``payload.data``
    (§6.3.7) with a ``headerInfo`` of ``psid`` and ``generationTime`` only (§6.3.9).

    These are the octets that are hashed for the signature (the data input of §5.3.1).
    """
    if not 0 <= generation_time_us < 1 << 64:
        raise EncodeError(f"generationTime {generation_time_us} is not a Time64")
    header = b"\x40" + _enc_psid(psid) + generation_time_us.to_bytes(8, "big")
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
        signer_octets = b"\x81" + _enc_quantity(len(certs)) + b"".join(map(bytes, certs))
    elif kind == "self":
        signer_octets = b"\x82"
    else:
        raise EncodeError(f"unknown signer kind {kind!r}")
    tbs = tbs_data(frame, psid, generation_time_us)
    return b"\x03\x81\x00" + tbs + signer_octets + _signature_octets(signature)


def looks_like_1609(data: bytes) -> bool:
    """Cheap sniff: protocolVersion 3 followed by a known ``content`` CHOICE tag."""
    return len(data) >= 2 and data[0] == PROTOCOL_VERSION and 0x80 <= data[1] <= 0x84


# ------------------------------------------------------------------------------------------
# WAVE Short Message (IEEE 1609.3-2016 §8.3)
# ------------------------------------------------------------------------------------------

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
    first = _take(stream, 1, f"WSMP {what}")[0]
    if first < 0x80:
        return first
    if first & 0xC0 != 0x80:
        raise DecodeError("garbage", f"WSMP {what}: 0x{first:02x} is neither 1 nor 2 octets")
    return (first & 0x3F) << 8 | _take(stream, 1, f"WSMP {what}")[0]


def _skip_wave_elements(stream: io.BytesIO, what: str) -> None:
    """A WAVE Information Element Extension: count, then ID, length, contents."""
    for _ in range(_read_wsmp_count(stream, what)):  # at most 16383, each >= 2 octets
        _take(stream, 1, f"WSMP {what}")
        _take(stream, _read_wsmp_count(stream, what), f"WSMP {what}")


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
    n_header = _take(stream, 1, "WSMP N-header")[0]
    if n_header & 0x07 != WSMP_VERSION:
        raise DecodeError("unsupported", f"WSMP version {n_header & 0x07}, not 3")
    if n_header >> 4:
        raise DecodeError("unsupported", f"WSMP subtype {n_header >> 4} (only null networking)")
    if n_header & 0x08:
        _skip_wave_elements(stream, "N-header extension")
    tpid = _take(stream, 1, "WSMP TPID")[0]
    if tpid > 1:
        raise DecodeError("unsupported", f"WSMP TPID {tpid} (only PSID addressing)")
    first = _take(stream, 1, "WSMP PSID")[0]
    size = next((n for n, mask in ((1, 0x80), (2, 0xC0), (3, 0xE0), (4, 0xF0))
                 if first & mask == (mask << 1) & 0xFF), None)
    if size is None:
        raise DecodeError("garbage", f"WSMP PSID p-encoding prefix 0x{first:02x}")
    value = int.from_bytes(bytes([first]) + _take(stream, size - 1, "WSMP PSID"), "big")
    offset, prefix, _ = next(row for row in _P_ENCODING if row[2] == size)
    psid = (value ^ prefix) + offset
    if tpid == 1:
        _skip_wave_elements(stream, "T-header extension")
    length = _read_wsmp_count(stream, "length")
    return _take(stream, length, "WSMP data"), psid


def looks_like_wsmp(data: bytes) -> bool:
    """Cheap sniff: a version-3 null-networking N-header followed by TPID 0 or 1 (an
    ``Ieee1609Dot2Data`` also starts with 0x03 but continues with a 0x8x CHOICE tag)."""
    if len(data) < 4 or data[0] & 0xF7 != WSMP_VERSION:
        return False
    return data[0] & 0x08 != 0 or data[1] in (0, 1)
