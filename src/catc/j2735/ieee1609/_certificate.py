"""IEEE 1609.2-2016 §6.4 ``Certificate`` in canonical OER: parse one, build an explicit one.

``CertificateBase`` (§6.4.3) is a preamble octet (bit 7: ``signature`` present),
``version`` 3, ``type`` (explicit 0 / implicit 1), ``issuer`` (``sha256AndDigest``
HashedId8 | ``self`` HashAlgorithm | ``sha384AndDigest``), ``toBeSigned``
(``ToBeSignedCertificate``, §6.4.8), ``signature``.

A certificate is hashed in its canonical form (§6.4.3); the only hash computed here is its
HashedId8, an identifier.  The issuer's signature is verified by :mod:`catc.security`.
Forms decoded structurally but not verifiable (implicit certificates, brainpool or P-384
keys and signatures, SHA-384) are reported in :attr:`Certificate.unsupported`;
:func:`parse_certificate` on its own rejects them as ``unsupported``.
"""

from __future__ import annotations

import hashlib
import io
from collections.abc import Sequence
from dataclasses import dataclass

from catc.errors import DecodeError, EncodeError
from catc.j2735.ieee1609._basetypes import (
    HASHES,
    Splices,
    compressed_key,
    read_public_point,
    read_signature,
    signature_octets,
    skip_region,
)
from catc.j2735.ieee1609._oer import (
    enc_octets,
    enc_psid,
    enc_quantity,
    enc_signed_int,
    read_enumerated,
    read_octets,
    read_preamble,
    read_psid,
    read_quantity,
    read_signed_int,
    read_tag,
    read_uint,
    skip_extensions,
    take,
)

ISSUE_ALL = "all"  # ``issue_psids`` of a certificate that may issue for every PSID

# Duration CHOICE: microseconds, milliseconds, then seconds per unit of
# seconds, minutes, hours, sixtyHours, years (a year is 31 556 952 s there).
_UNIT_SECONDS = (None, None, 1, 60, 3600, 216_000, 31_556_952)


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


def _psid_ssp_ranges(stream: io.BytesIO, what: str) -> list[int]:
    """``SequenceOfPsidSspRange``: the PSIDs (SSP ranges are skipped)."""
    psids = []
    for _ in range(read_quantity(stream, what)):
        has_range = read_preamble(stream, 1, what) & 0x80
        psids.append(read_psid(stream, f"{what} psid"))
        if has_range:
            index = read_tag(stream, f"{what} sspRange")
            if index == 0:  # opaque SequenceOfOctetString
                for _ in range(read_quantity(stream, f"{what} sspRange")):
                    read_octets(stream, f"{what} sspRange")
            elif index >= 2:  # bitmapSspRange and later: open types
                read_octets(stream, f"{what} sspRange")
    return psids


def _group_permissions(
    stream: io.BytesIO, what: str
) -> tuple[list[int], bool, tuple[int, int] | None]:
    """``SequenceOfPsidGroupPermissions``: (explicit PSIDs, any "all", chain)."""
    psids: list[int] = []
    everything = False
    chain = None
    for _ in range(read_quantity(stream, what)):
        preamble = read_preamble(stream, 3, what)
        index = read_tag(stream, f"{what} subjectPermissions")
        if index == 0:
            psids += _psid_ssp_ranges(stream, f"{what} explicit")
        elif index == 1:
            everything = True
        else:
            read_octets(stream, f"{what} subjectPermissions")
        min_length = read_signed_int(stream, f"{what} minChainLength") if preamble & 0x80 else 1
        length_range = read_signed_int(stream, f"{what} chainLengthRange") if preamble & 0x40 else 0
        if preamble & 0x20:
            take(stream, 1, f"{what} eeType")
        chain = chain or (min_length, length_range)
    return psids, everything, chain


def read_certificate(stream: io.BytesIO, buf: bytes) -> Certificate:
    """Parse one ``CertificateBase`` (§6.4.3) at the stream position of ``buf``."""
    start = stream.tell()
    splices = Splices()
    notes: list[str] = []
    what = "Certificate"
    has_signature = read_preamble(stream, 1, what) & 0x80
    if read_uint(stream, 1, f"{what} version") != 3:
        raise DecodeError("garbage", f"1609.2 {what}: version is not 3")
    type_index = read_enumerated(stream, f"{what} type")
    cert_type = {0: "explicit", 1: "implicit"}.get(type_index, f"unknown({type_index})")
    if type_index not in (0, 1):
        notes.append(f"certificate type {cert_type}")

    issuer_index = read_tag(stream, f"{what} issuer")
    issuer_digest: bytes | None = None
    if issuer_index == 0:
        issuer_kind, issuer_digest = "sha256AndDigest", take(stream, 8, "issuer")
    elif issuer_index == 1:
        issuer_kind = "self"
        algorithm = read_enumerated(stream, "issuer self")
        if algorithm != 0:
            notes.append(f"self-signed with {HASHES.get(algorithm, algorithm)}")
    else:
        value = read_octets(stream, "issuer")
        if issuer_index == 2 and len(value) == 8:
            issuer_kind, issuer_digest = "sha384AndDigest", value
        else:
            issuer_kind = f"unknown({issuer_index})"
        notes.append(f"issuer {issuer_kind}")

    tbs_start = stream.tell()
    what = "ToBeSignedCertificate"
    optional = read_preamble(stream, 8, what)
    id_index = read_tag(stream, f"{what} id")
    name = None
    if id_index == 0:  # linkageData
        has_group = read_preamble(stream, 1, "linkageData") & 0x80
        take(stream, 2 + 9 + (13 if has_group else 0), "linkageData")
    elif id_index == 1:
        octets = read_octets(stream, "name")
        try:
            name = octets.decode("utf-8")
        except UnicodeDecodeError:
            raise DecodeError("garbage", "1609.2 certificate name is not UTF-8") from None
        if len(name) > 255:  # Hostname ::= UTF8String (SIZE(0..255))
            raise DecodeError("garbage", "1609.2 certificate name longer than 255 characters")
    elif id_index == 2:
        if not 1 <= len(read_octets(stream, "binaryId")) <= 64:
            raise DecodeError("garbage", "1609.2 certificate binaryId not of 1..64 octets")
    elif id_index >= 4:
        read_octets(stream, f"{what} id")
        notes.append(f"certificate id alternative {id_index}")
    id_kind = ("linkageData", "name", "binaryId", "none")[id_index] if id_index < 4 else (
        f"unknown({id_index})")
    craca_id = take(stream, 3, "cracaId")
    crl_series = read_uint(stream, 2, "crlSeries")
    start_time32 = read_uint(stream, 4, "validityPeriod start")
    unit = read_tag(stream, "validityPeriod duration")
    if unit > 6:
        raise DecodeError("garbage", f"1609.2 Duration alternative {unit}")
    count = read_uint(stream, 2, "validityPeriod duration")
    per_unit = _UNIT_SECONDS[unit]
    duration_s = count * per_unit if per_unit else count // (1_000_000 if unit == 0 else 1000)
    if optional & 0x40:
        skip_region(stream)
    if optional & 0x20:
        take(stream, 1, "assuranceLevel")
    app_psids: list[int] = []
    if optional & 0x10:
        for _ in range(read_quantity(stream, "appPermissions")):
            has_ssp = read_preamble(stream, 1, "PsidSsp") & 0x80
            app_psids.append(read_psid(stream, "appPermissions psid"))
            if has_ssp:
                read_tag(stream, "ServiceSpecificPermissions")
                read_octets(stream, "ServiceSpecificPermissions")  # opaque or an open type
    issue_psids: list[int] = []
    issue_all, issue_chain = False, None
    if optional & 0x08:
        issue_psids, issue_all, issue_chain = _group_permissions(stream, "certIssuePermissions")
    if optional & 0x04:
        _group_permissions(stream, "certRequestPermissions")
    if not optional & 0x1C:
        raise DecodeError("garbage", "1609.2 certificate without any permissions (§6.4.8)")
    if optional & 0x01:  # encryptionKey: PublicEncryptionKey
        read_enumerated(stream, "supportedSymmAlg")
        index = read_tag(stream, "BasePublicEncryptionKey")
        if index <= 1:
            read_public_point(stream, "encryptionKey", splices)
        else:
            read_octets(stream, "BasePublicEncryptionKey")
    verify_key = None
    indicator = read_tag(stream, "verifyKeyIndicator")
    if indicator == 0:
        curve = read_tag(stream, "PublicVerificationKey")
        if curve <= 1:
            point = read_public_point(stream, "verificationKey", splices)
            if curve == 0:
                verify_key = point
            else:
                notes.append("verification key ecdsaBrainpoolP256r1")
        else:
            read_octets(stream, "PublicVerificationKey")
            names = {2: "ecdsaBrainpoolP384r1", 3: "ecdsaNistP384"}
            notes.append(f"verification key {names.get(curve, f'alternative {curve}')}")
    elif indicator == 1:
        read_public_point(stream, "reconstructionValue", splices)
    else:
        read_octets(stream, "verifyKeyIndicator")
        notes.append(f"verifyKeyIndicator alternative {indicator}")
    if optional & 0x80:
        skip_extensions(stream, what)
    tbs_end = stream.tell()

    signature = r_form = None
    if has_signature:
        signature, r_form, note = read_signature(stream, "certificate signature", splices)
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
    cert = read_certificate(stream, buf)
    if cert.unsupported:
        raise DecodeError("unsupported", f"1609.2 {cert.unsupported}")
    return cert, stream.tell()


def _duration(seconds: int) -> bytes:
    """The exact ``Duration`` with the finest unit that holds ``seconds``."""
    for index, unit in enumerate(_UNIT_SECONDS):
        if unit and seconds % unit == 0 and 0 <= seconds // unit <= 0xFFFF:
            return bytes([0x80 | index]) + (seconds // unit).to_bytes(2, "big")
    raise EncodeError(f"certificate duration of {seconds} s is not a whole Uint16 of a unit")


def _psid_group(psids: Sequence[int] | str, chain: tuple[int, int]) -> bytes:
    """One ``PsidGroupPermissions``; DEFAULT components are omitted (COER)."""
    if psids == ISSUE_ALL:
        subject = b"\x81"
    else:
        subject = b"\x80" + enc_quantity(len(psids))
        subject += b"".join(b"\x00" + enc_psid(p) for p in psids)  # PsidSspRange, no range
    min_length, length_range = chain
    preamble = (0x80 if min_length != 1 else 0) | (0x40 if length_range != 0 else 0)
    out = bytes([preamble]) + subject
    if min_length != 1:
        out += enc_signed_int(min_length)
    if length_range != 0:
        out += enc_signed_int(length_range)
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
        ident = b"\x81" + enc_octets(name.encode("utf-8"))
    preamble = (0x10 if app_psids else 0) | (0x08 if issue_psids else 0)
    out = bytes([preamble]) + ident + bytes(craca_id) + crl_series.to_bytes(2, "big")
    out += start_time32.to_bytes(4, "big") + _duration(duration_s)
    if app_psids:
        out += enc_quantity(len(app_psids)) + b"".join(b"\x00" + enc_psid(p) for p in app_psids)
    if issue_psids:
        out += b"\x01\x01" + _psid_group(issue_psids, issue_chain)
    return out + b"\x80\x80" + compressed_key(verify_key)  # verificationKey ecdsaNistP256


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
    return b"\x80\x03\x00" + issuer + bytes(tbs) + signature_octets(signature)

