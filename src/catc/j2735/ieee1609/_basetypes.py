"""IEEE 1609.2-2016 base types (ASN.1 module ``Ieee1609Dot2BaseTypes``) that both
certificates (§6.4) and signed data (§6.3) carry: curve points, public keys, signatures,
hash algorithms and geographic regions, in canonical OER.

- ``EccP256CurvePoint`` is a CHOICE (not extensible) of ``x-only``, ``fill``,
  ``compressed-y-0``, ``compressed-y-1`` and ``uncompressed``.
- ``Signature`` is an extensible CHOICE whose root alternatives are
  ``EcdsaP256Signature`` ``{rSig EccP256CurvePoint, sSig OCTET STRING (32)}``.

A certificate is hashed in its canonical form (§6.4.3: public keys compressed, the
signature's r as x-only); :class:`Splices` records the replacements that turn the received
octets into it.  Nothing here does cryptography.
"""

from __future__ import annotations

import io

from catc.errors import DecodeError, EncodeError
from catc.j2735.ieee1609._oer import read_octets, read_quantity, read_tag, take

PSID_BSM = 0x20  # IEEE 1609.12: vehicle-to-vehicle safety and awareness (J2735 BSM)

HASHES = {0: "sha256", 1: "sha384", 2: "sm3"}  # HashAlgorithm (§6.3.5; sm3 from 1609.2-2022)
_POINT_FORMS = ("x-only", "fill", "compressed-y-0", "compressed-y-1", "uncompressed")


class Splices:
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


def read_point(stream: io.BytesIO, what: str) -> tuple[str, bytes]:
    """``EccP256CurvePoint`` (not extensible): (form, x or x || y)."""
    index = read_tag(stream, what)
    if index in (0, 2, 3):
        return _POINT_FORMS[index], take(stream, 32, what)
    if index == 1:
        return "fill", b""
    if index == 4:
        return "uncompressed", take(stream, 64, what)
    raise DecodeError("garbage", f"1609.2 {what}: EccP256CurvePoint alternative {index}")


def read_public_point(stream: io.BytesIO, what: str, splices: Splices) -> bytes:
    """A public key or reconstruction value: returned as compressed SEC1 (33 octets); an
    uncompressed point is recorded for canonicalisation (§6.4.3: compressed form)."""
    start = stream.tell()
    form, value = read_point(stream, what)
    if form in ("x-only", "fill"):
        raise DecodeError("garbage", f"1609.2 {what}: a public key cannot be {form}")
    if form == "uncompressed":
        odd = value[63] & 1
        splices.add(start, stream.tell(), bytes([0x82 | odd]) + value[:32])
        return bytes([2 | odd]) + value[:32]
    return bytes([2 if form == "compressed-y-0" else 3]) + value


def read_signature(
    stream: io.BytesIO, what: str, splices: Splices | None = None
) -> tuple[bytes | None, str | None, str | None]:
    """``Signature``: (r || s, form of rSig, why it cannot be verified or None)."""
    index = read_tag(stream, what)
    if index >= 2:  # extension alternatives (P-384 and later): open types
        read_octets(stream, what)
        names = {2: "ecdsaBrainpoolP384r1Signature", 3: "ecdsaNistP384Signature"}
        return None, None, f"signature {names.get(index, f'alternative {index}')}"
    start = stream.tell()
    form, r = read_point(stream, f"{what} rSig")
    if form == "fill":
        raise DecodeError("garbage", f"1609.2 {what}: rSig is fill, not a 32-octet value")
    if splices is not None and form != "x-only":  # §6.4.3: r taken as x-only for hashing
        splices.add(start, stream.tell(), b"\x80" + r[:32])
    s = take(stream, 32, f"{what} sSig")
    note = None if index == 0 else "signature ecdsaBrainpoolP256r1Signature"
    return r[:32] + s, form, note


def signature_octets(signature: bytes) -> bytes:
    """``Signature`` ecdsaNistP256Signature of r || s (64 octets), rSig sent x-only."""
    if len(signature) != 64:
        raise EncodeError("an ECDSA P-256 signature is 64 octets, r || s")
    return b"\x80\x80" + bytes(signature)  # ecdsaNistP256Signature, rSig x-only


def compressed_key(key: bytes) -> bytes:
    """A SEC1 P-256 point (33 compressed or 65 uncompressed octets) as EccP256CurvePoint."""
    key = bytes(key)
    if len(key) == 33 and key[0] in (2, 3):
        return bytes([0x80 | key[0]]) + key[1:]
    if len(key) == 65 and key[0] == 4:
        return bytes([0x82 | key[64] & 1]) + key[1:33]
    raise EncodeError("verification key is not a 33- or 65-octet SEC1 point")


def skip_region(stream: io.BytesIO) -> None:
    """``GeographicRegion``: structurally skipped, not interpreted."""
    what = "GeographicRegion"
    index = read_tag(stream, what)
    if index == 0:  # circularRegion: TwoDLocation (2 x 4 octets), radius Uint16
        take(stream, 10, what)
    elif index == 1:  # rectangularRegion: SEQUENCE OF two TwoDLocation
        take(stream, 16 * read_quantity(stream, what), what)
    elif index == 2:  # polygonalRegion: SEQUENCE OF TwoDLocation
        take(stream, 8 * read_quantity(stream, what), what)
    elif index == 3:  # identifiedRegion: SEQUENCE OF IdentifiedRegion
        for _ in range(read_quantity(stream, what)):
            kind = read_tag(stream, what)
            if kind == 0:  # countryOnly
                take(stream, 2, what)
            elif kind == 1:  # countryAndRegions: country, SequenceOfUint8
                take(stream, 2, what)
                take(stream, read_quantity(stream, what), what)
            elif kind == 2:  # countryAndSubregions: country, SEQUENCE OF RegionAndSubregions
                take(stream, 2, what)
                for _ in range(read_quantity(stream, what)):
                    take(stream, 1, what)
                    take(stream, 2 * read_quantity(stream, what), what)
            else:
                read_octets(stream, what)
    else:
        read_octets(stream, what)
