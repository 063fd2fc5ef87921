"""IEEE 1609.2-2016 security for BSMs: a test PKI, signing, and a bounded verifier.

Pure: keys are ``cryptography`` objects, certificates and messages are octets; nothing
here touches files or the network (:meth:`Pki.private_pem` gives PEM octets for a CLI to
write, :func:`load_private_pem` reads them back).  The wire formats are in
:mod:`catc.j2735.ieee1609`; this module adds the cryptography (ECDSA over NIST P-256 with
SHA-256, the only algorithms it supports).

Signatures (§5.3.1)
    The data to sign is hashed as ``H = SHA-256( SHA-256(data input) ||
    SHA-256(signer identifier input) )``.  The data input is the COER
    ``ToBeSignedData`` for signed messages (§6.3.4) and the COER ``ToBeSignedCertificate``
    for certificates (§6.4.8).  The signer identifier input is the canonical COER of the
    signer's certificate, or the empty string when self-signed.  ECDSA is applied to
    ``H``: here the outer SHA-256 is computed in Python and handed to ``cryptography`` as
    ``ECDSA(Prehashed(SHA256()))``.  That equals ``ECDSA(SHA256())`` over the 64-octet
    concatenation, and ``openssl dgst -sha256`` over it.  Signatures are sent as r || s
    with rSig x-only.  When the installed OpenSSL supports it, signing is deterministic
    (RFC 6979), so a seeded PKI and its signed messages are reproducible octet for octet.

Time (base types Time32, Time64)
    Time32 and Time64 count TAI seconds and microseconds since 2004-01-01 00:00:00 UTC.
    TAI−UTC was 32 s at that epoch and has been 37 s since 2017-01-01.  So a UTC instant
    after 2016 is ``unix − 1 072 915 200 + 5`` s in these units.  :func:`unix_to_time64`
    and :func:`time64_to_unix` apply the five leap seconds inserted since 2004 at their
    true dates (end of 2005, 2008, June 2012, June 2015, 2016).  No leap second has been
    announced after 2016; a new one would need a new table entry.  Wireshark's 1609.2
    dissector converts the same way (a test checks this).

Verification (:class:`Verifier`)
    The verifier trusts the roots it is given.  It verifies a certificate chain once and
    then keeps every verified certificate by HashedId8 in a bounded LRU cache, so a BSM
    with a cached signer costs one ECDSA verification.  A ``digest`` signer that is not
    cached yet is ``unknown-signer``: that is normal, since vehicles attach the
    certificate only now and then.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, utils

from catc.errors import DecodeError
from catc.j2735.ieee1609 import (
    ISSUE_ALL,
    PSID_BSM,
    Certificate,
    Unwrapped,
    build_certificate,
    build_signed,
    build_tbs_certificate,
    parse_certificate,
    tbs_data,
    unwrap,
)

#: Every :attr:`Verdict.reason`.  Beyond "ok": no signature at all; a signature this
#: module cannot check (implicit certificate, other curve or hash); a digest signer not
#: in the cache; a certificate chain that is broken, too long or not under a trusted
#: root; a signer not permitted for the PSID; outside the validity period; a
#: generationTime too old or too far ahead; an ECDSA signature that does not verify.
VERDICT_REASONS = ("ok", "unsigned", "unsupported", "unknown-signer", "chain", "wrong-psid",
                   "expired", "stale", "bad-signature")

_P256_ORDER = 0xFFFFFFFF00000000FFFFFFFFFFFFFFFFBCE6FAADA7179E84F3B9CAC2FC632551
_EPOCH_UNIX = 1_072_915_200  # 2004-01-01 00:00:00 UTC
_LEAPS_UNIX = (1_136_073_600, 1_230_768_000, 1_341_100_800, 1_435_708_800, 1_483_228_800)
_EMPTY_HASH = hashlib.sha256(b"").digest()
_VERIFY = ec.ECDSA(utils.Prehashed(hashes.SHA256()))


def _signing_algorithm() -> ec.ECDSA:
    try:  # RFC 6979: cryptography >= 44 with OpenSSL >= 3.2
        algorithm = ec.ECDSA(utils.Prehashed(hashes.SHA256()), deterministic_signing=True)
        ec.derive_private_key(1, ec.SECP256R1()).sign(bytes(32), algorithm)
        return algorithm
    except (TypeError, UnsupportedAlgorithm):
        return _VERIFY


_SIGN = _signing_algorithm()


# --- time ---------------------------------------------------------------------------------


def unix_to_time64(unix_s: float) -> int:
    """Time64 (TAI µs since 2004-01-01 00:00:00 UTC) of a POSIX (UTC) timestamp."""
    leaps = sum(1 for t in _LEAPS_UNIX if unix_s >= t)
    return round((unix_s - _EPOCH_UNIX) * 1_000_000) + leaps * 1_000_000


def time64_to_unix(time64_us: int) -> float:
    """POSIX (UTC) timestamp of a Time64."""
    leaps = sum(1 for i, t in enumerate(_LEAPS_UNIX)
                if time64_us >= (t - _EPOCH_UNIX + i + 1) * 1_000_000)
    return _EPOCH_UNIX + time64_us / 1_000_000 - leaps


def unix_to_time32(unix_s: float) -> int:
    """Time32 (TAI seconds since 2004-01-01 00:00:00 UTC) of a POSIX timestamp."""
    return unix_to_time64(unix_s) // 1_000_000


# --- signing ---------------------------------------------------------------------------------


def _sha256(octets: bytes) -> bytes:
    return hashlib.sha256(octets).digest()


def hash_input(tbs: bytes, signer_cert: bytes | None) -> bytes:
    """The 64 octets whose SHA-256 is signed (§5.3.1): ``SHA-256(tbs) || SHA-256(signer)``,
    with ``signer`` the canonical COER certificate, or empty when self-signed."""
    return _sha256(tbs) + _sha256(signer_cert or b"")


def _sign_digest(key: ec.EllipticCurvePrivateKey, digest: bytes) -> bytes:
    r, s = utils.decode_dss_signature(key.sign(digest, _SIGN))
    return r.to_bytes(32, "big") + s.to_bytes(32, "big")


def _verify_digest(key: ec.EllipticCurvePublicKey, signature: bytes | None,
                   digest: bytes) -> bool:
    if signature is None or len(signature) != 64:
        return False
    r, s = int.from_bytes(signature[:32], "big"), int.from_bytes(signature[32:], "big")
    try:
        key.verify(utils.encode_dss_signature(r, s), digest, _VERIFY)
    except InvalidSignature:
        return False
    return True


@lru_cache(maxsize=4096)  # a signer per RV: an RVE with 500 RVs signs in turn
def _cert_hashes(cert_raw: bytes) -> tuple[bytes, bytes]:
    """(SHA-256 of the canonical certificate, its HashedId8) for a signer certificate."""
    cert, _ = parse_certificate(cert_raw)
    return _sha256(cert.canonical), cert.hashed_id8


def sign_data(tbs: bytes, key: ec.EllipticCurvePrivateKey, signer_cert: bytes | None) -> bytes:
    """r || s (64 octets) over ``tbs`` for the certificate ``signer_cert`` (COER), or
    self-signed when None (§5.3.1)."""
    signer_hash = _cert_hashes(bytes(signer_cert))[0] if signer_cert else _EMPTY_HASH
    return _sign_digest(key, _sha256(_sha256(tbs) + signer_hash))


def sign_bsm(
    frame: bytes,
    key: ec.EllipticCurvePrivateKey,
    cert_raw: bytes,
    generation_time_us: int,
    *,
    include_cert: bool,
    psid: int = PSID_BSM,
) -> bytes:
    """A COER ``Ieee1609Dot2Data`` signing ``frame`` (§6.3.4): headerInfo psid and
    generationTime (a Time64), signer the whole certificate ``cert_raw`` when
    ``include_cert`` else its HashedId8 ``digest``, ECDSA P-256 with ``key``."""
    cert_hash, hashed_id8 = _cert_hashes(bytes(cert_raw))
    tbs = tbs_data(frame, psid, generation_time_us)
    signature = _sign_digest(key, _sha256(_sha256(tbs) + cert_hash))
    signer = ("certificate", bytes(cert_raw)) if include_cert else ("digest", hashed_id8)
    return build_signed(frame, psid=psid, generation_time_us=generation_time_us, signer=signer,
                        signature=signature)


# --- keys and a PKI -----------------------------------------------------------------------


def _compressed(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.public_key().public_bytes(serialization.Encoding.X962,
                                         serialization.PublicFormat.CompressedPoint)


def private_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    """An unencrypted PKCS#8 PEM of ``key``."""
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def load_private_pem(data: bytes) -> ec.EllipticCurvePrivateKey:
    """A P-256 private key from PEM octets (as :func:`private_pem` writes them)."""
    key = serialization.load_pem_private_key(bytes(data), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.curve.name != "secp256r1":
        raise ValueError("not a NIST P-256 private key")
    return key


@dataclass(frozen=True)
class Identity:
    """A certificate (COER and parsed) with its private key."""

    label: str
    raw: bytes
    cert: Certificate
    key: ec.EllipticCurvePrivateKey = field(repr=False)

    @property
    def hashed_id8(self) -> bytes:
        return self.cert.hashed_id8

    def private_pem(self) -> bytes:
        return private_pem(self.key)


def issue_certificate(
    issuer: Identity | None,
    *,
    start_time32: int,
    duration_s: int,
    name: str | None = None,
    app_psids: Sequence[int] = (),
    issue_psids: Sequence[int] | str = (),
    issue_chain: tuple[int, int] = (1, 0),
    key: ec.EllipticCurvePrivateKey | None = None,
    label: str | None = None,
) -> Identity:
    """An explicit certificate for ``key`` (a new P-256 key if None), signed by ``issuer``
    (IssuerIdentifier ``sha256AndDigest``, §6.4.7), or self-signed when ``issuer`` is None.

    ``issue_chain`` is the (minChainLength, chainLengthRange) of certIssuePermissions
    (PsidGroupPermissions).  It is recorded in the certificate but not enforced by
    :class:`Verifier`.
    """
    key = key or ec.generate_private_key(ec.SECP256R1())
    tbs = build_tbs_certificate(verify_key=_compressed(key), start_time32=start_time32,
                                duration_s=duration_s, name=name, app_psids=tuple(app_psids),
                                issue_psids=issue_psids, issue_chain=issue_chain)
    if issuer is None:
        signature = _sign_digest(key, _sha256(_sha256(tbs) + _EMPTY_HASH))
        raw = build_certificate(tbs, issuer_digest=None, signature=signature)
    else:
        signature = _sign_digest(issuer.key, _sha256(_sha256(tbs)
                                                     + _sha256(issuer.cert.canonical)))
        raw = build_certificate(tbs, issuer_digest=issuer.hashed_id8, signature=signature)
    cert, _ = parse_certificate(raw)
    return Identity(label or name or cert.hashed_id8.hex(), raw, cert, key)


@dataclass(frozen=True)
class Pki:
    """A three-level test PKI: a self-signed root CA, an authorization CA and pseudonyms."""

    root: Identity
    aa: Identity
    pseudonyms: tuple[Identity, ...]

    def identities(self) -> dict[str, Identity]:
        """Every identity by label: "root", "aa", "pseudonym-0", ..."""
        return {i.label: i for i in (self.root, self.aa, *self.pseudonyms)}

    def private_pem(self, label: str) -> bytes:
        """The PKCS#8 PEM of the private key of the identity ``label``."""
        return self.identities()[label].private_pem()


def make_pki(
    n_pseudonyms: int,
    *,
    start_time32: int,
    duration_s: int,
    psids: Sequence[int] = (PSID_BSM,),
    seed: bytes | str | int | None = None,
) -> Pki:
    """A root CA (certIssuePermissions all), an AA signed by it that may issue ``psids``,
    and ``n_pseudonyms`` pseudonym certificates (appPermissions ``psids``, id none) signed
    by the AA, all explicit with P-256 keys and the validity period
    [``start_time32``, ``start_time32 + duration_s``).

    With a ``seed`` the private keys are derived from it and the certificates reproduce
    octet for octet (when signing is deterministic); without, keys are random.
    """
    if seed is None:
        def key_for(_label: str) -> ec.EllipticCurvePrivateKey:
            return ec.generate_private_key(ec.SECP256R1())
    else:
        seed_octets = seed if isinstance(seed, bytes) else str(seed).encode()

        def key_for(label: str) -> ec.EllipticCurvePrivateKey:
            h = _sha256(b"catc-pki\x00" + seed_octets + b"\x00" + label.encode())
            return ec.derive_private_key(int.from_bytes(h, "big") % (_P256_ORDER - 1) + 1,
                                         ec.SECP256R1())

    validity = {"start_time32": start_time32, "duration_s": duration_s}
    root = issue_certificate(None, name="catc-root-ca", issue_psids=ISSUE_ALL,
                             issue_chain=(2, 0), key=key_for("root"), label="root", **validity)
    aa = issue_certificate(root, name="catc-aa", issue_psids=tuple(psids), key=key_for("aa"),
                           label="aa", **validity)
    pseudonyms = tuple(
        issue_certificate(aa, app_psids=tuple(psids), key=key_for(f"pseudonym-{i}"),
                          label=f"pseudonym-{i}", **validity)
        for i in range(n_pseudonyms)
    )
    return Pki(root, aa, pseudonyms)


# --- verification ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Verdict:
    """The outcome of :meth:`Verifier.verify`: ``reason`` is one of
    :data:`VERDICT_REASONS`, ``frame`` the carried MessageFrame, ``signer_digest`` the
    HashedId8 of the signing certificate (when the message names one)."""

    ok: bool
    reason: str
    frame: bytes | None = None
    signer_digest: bytes | None = None


@dataclass(frozen=True)
class _Trusted:
    """A verified certificate: its key, the hash of its canonical COER (the signer
    identifier input of what it signs), its depth (root = 1) and the validity period of
    its whole chain (Time32)."""

    cert: Certificate
    key: ec.EllipticCurvePublicKey
    cert_hash: bytes
    depth: int
    not_before: int
    not_after: int


def _whole_certificate(raw: bytes) -> Certificate:
    cert, used = parse_certificate(raw)
    if used != len(raw):
        raise DecodeError("garbage", f"certificate followed by {len(raw) - used} octets")
    return cert


def _public_key(cert: Certificate) -> ec.EllipticCurvePublicKey | None:
    if cert.verify_key is None or cert.unsupported:
        return None
    try:
        return ec.EllipticCurvePublicKey.from_encoded_point(ec.SECP256R1(), cert.verify_key)
    except ValueError:  # not a point on the curve
        return None


class Verifier:
    """Verifies signed BSMs against trusted root certificates; stateful and bounded.

    ``roots`` are COER self-signed root certificates (their self-signatures are checked
    here; ValueError if one does not verify).  ``certificates`` are CA certificates known
    in advance, such as the AA of the local certificate chain that an SCMS distributes
    with the root.  Messages name such CAs only by HashedId8, so they are kept unverified
    and verified against their issuer on first use.  At most ``max_certs`` verified
    certificates are cached (least recently used evicted first) and at most as many
    unverified ones kept.  Chains may hold at most ``max_chain`` certificates including
    the root.

    Freshness (IEEE 1609.2-2016 §5.2, relevance checks on generationTime): the
    security profile of the application sets how far generationTime may lie in the past
    and in the future.  The defaults here, ``max_age_us`` 2 s and ``max_future_us`` 1 s,
    are this testbench's choice for 10 Hz BSMs, not figures taken from SAE J2945/1.
    """

    def __init__(
        self,
        roots: Iterable[bytes],
        *,
        certificates: Iterable[bytes] = (),
        max_certs: int = 4096,
        max_chain: int = 3,
        psid: int = PSID_BSM,
        max_age_us: int = 2_000_000,
        max_future_us: int = 1_000_000,
    ) -> None:
        if max_certs < 1 or max_chain < 1:
            raise ValueError("max_certs and max_chain must be positive")
        self.max_certs, self.max_chain, self.psid = max_certs, max_chain, psid
        self.max_age_us, self.max_future_us = max_age_us, max_future_us
        self.cert_checks = 0  # certificate signatures verified so far (roots excluded)
        self._roots: dict[bytes, _Trusted] = {}
        self._cache: OrderedDict[bytes, _Trusted] = OrderedDict()
        self._known: OrderedDict[bytes, Certificate] = OrderedDict()  # not yet verified
        for raw in roots:
            cert = _whole_certificate(raw)
            key = _public_key(cert)
            if cert.issuer_kind != "self" or key is None:
                raise ValueError("a trusted root must be self-signed with a P-256 key")
            if not _verify_digest(key, cert.signature, _sha256(_sha256(cert.tbs) + _EMPTY_HASH)):
                raise ValueError("trusted root self-signature does not verify")
            self._roots[cert.hashed_id8] = _Trusted(cert, key, _sha256(cert.canonical), 1,
                                                    cert.start_time32, cert.end_time32)
        self.add_certificates(certificates)

    def add_certificates(self, certificates: Iterable[bytes]) -> None:
        """Learn CA certificates (COER) to be verified when a chain first needs them."""
        for raw in certificates:
            cert = _whole_certificate(raw)
            self._known[cert.hashed_id8] = cert
            self._known.move_to_end(cert.hashed_id8)
            while len(self._known) > self.max_certs:
                self._known.popitem(last=False)

    @property
    def cache_size(self) -> int:
        """Certificates cached (trusted roots not counted)."""
        return len(self._cache)

    def __contains__(self, hashed_id8: object) -> bool:
        return hashed_id8 in self._roots or hashed_id8 in self._cache

    def _lookup(self, hashed_id8: bytes | None) -> _Trusted | None:
        if hashed_id8 is None:
            return None
        trusted = self._roots.get(hashed_id8)
        if trusted is None:
            trusted = self._cache.get(hashed_id8)
            if trusted is not None:
                self._cache.move_to_end(hashed_id8)
        return trusted

    def _admit(self, cert: Certificate, issuer: _Trusted) -> _Trusted | None:
        """Verify ``cert`` under an already trusted ``issuer`` and cache it (§6.4)."""
        key = _public_key(cert)
        if key is None or cert.cert_type != "explicit":
            return None
        granted = issuer.cert
        if not granted.issue_all and (
            cert.issue_all or not {*cert.app_psids, *cert.issue_psids} <= {*granted.issue_psids}
        ):
            return None  # the issuer may not grant these permissions
        self.cert_checks += 1
        digest = _sha256(_sha256(cert.tbs) + issuer.cert_hash)
        if not _verify_digest(issuer.key, cert.signature, digest):
            return None
        trusted = _Trusted(cert, key, _sha256(cert.canonical), issuer.depth + 1,
                           max(issuer.not_before, cert.start_time32),
                           min(issuer.not_after, cert.end_time32))
        self._cache[cert.hashed_id8] = trusted
        while len(self._cache) > self.max_certs:
            self._cache.popitem(last=False)
        return trusted

    def _chain(self, certs: tuple[Certificate, ...]) -> _Trusted | None:
        """The signer of a ``certificate`` SignerIdentifier (the signer first,
        each followed by its issuer), verified up to a cached or trusted certificate."""
        known = self._lookup(certs[0].hashed_id8)
        if known is not None:
            return known
        pending: list[Certificate] = []
        cert = certs[0]
        while True:
            pending.append(cert)
            if len(pending) + 1 > self.max_chain or cert.issuer_kind != "sha256AndDigest":
                return None  # too long, or a self-signed certificate we do not trust
            anchor = self._lookup(cert.issuer_digest)
            if anchor is not None:
                break
            position = len(pending)
            if position < len(certs) and certs[position].hashed_id8 == cert.issuer_digest:
                cert = certs[position]
            elif cert.issuer_digest in self._known:
                cert = self._known[cert.issuer_digest]
            else:
                return None  # the issuer is neither trusted, nor known, nor sent
        if anchor.depth + len(pending) > self.max_chain:
            return None
        for cert in reversed(pending):
            anchor = self._admit(cert, anchor)
            if anchor is None:
                return None
        return anchor

    def verify(self, data: bytes | Unwrapped, now_us: int) -> Verdict:
        """Check one message at ``now_us`` (Time64).  Raises :class:`DecodeError` for
        octets that are not an ``Ieee1609Dot2Data`` at all (as :func:`unwrap` does)."""
        u = data if isinstance(data, Unwrapped) else unwrap(data)
        if u.security != "signed":
            return Verdict(False, "unsigned", u.frame)
        if u.unsupported:
            return Verdict(False, "unsupported", u.frame, u.signer_digest)
        if u.signer_kind == "digest":
            signer = self._lookup(u.signer_digest)
            if signer is None:
                return Verdict(False, "unknown-signer", u.frame, u.signer_digest)
        elif u.signer_kind == "certificate":
            signer = self._chain(u.signer_certs)
            if signer is None:
                return Verdict(False, "chain", u.frame, u.signer_digest)
        else:  # "self": self-signed data carries no key to verify it with
            return Verdict(False, "unknown-signer", u.frame, None)

        def fail(reason: str) -> Verdict:
            return Verdict(False, reason, u.frame, u.signer_digest)

        if u.psid != self.psid or self.psid not in signer.cert.app_psids:
            return fail("wrong-psid")
        generation = u.generation_time_us
        for instant in (now_us, generation):
            if instant is not None and not (
                signer.not_before <= instant // 1_000_000 < signer.not_after
            ):
                return fail("expired")
        if (generation is None or now_us - generation > self.max_age_us
                or generation - now_us > self.max_future_us):
            return fail("stale")
        assert u.tbs_data is not None
        if not _verify_digest(signer.key, u.signature,
                              _sha256(_sha256(u.tbs_data) + signer.cert_hash)):
            return fail("bad-signature")
        return Verdict(True, "ok", u.frame, u.signer_digest)

    def verify_many(
        self, items: Iterable[bytes | Unwrapped], now_us: int
    ) -> list[Verdict | DecodeError]:
        """:meth:`verify` each item in order; an item that does not decode yields its
        :class:`DecodeError` in its place instead of stopping the batch.  Certificates
        verified for one item are cached for the next ones."""
        out: list[Verdict | DecodeError] = []
        for item in items:
            try:
                out.append(self.verify(item, now_us))
            except DecodeError as err:
                out.append(err)
        return out
