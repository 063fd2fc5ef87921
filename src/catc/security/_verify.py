"""The verifier of :mod:`catc.security` (:class:`Verifier`, :class:`Verdict`): the chain
of certificates to a trusted root, the header's relevance checks, the envelope's outer
layers, the signature's encoding, replays, and ECDSA; the module docstring of
:mod:`catc.security` says what each verdict means and why."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass

from cryptography.hazmat.primitives.asymmetric import ec

from catc.errors import DecodeError
from catc.j2735.ieee1609 import PSID_BSM, Certificate, Unwrapped, parse_certificate, unwrap
from catc.security._crypto import EMPTY_HASH, P256_ORDER, sha256, verify_digest
from catc.security._replay import ReplayCache

#: Every :attr:`Verdict.reason`.  Beyond "ok": no signature at all; a copy of a message
#: already accepted; a signature this module cannot check (implicit certificate, other
#: curve or hash); signed data nested in signed data; a WSMP header for another PSID; a
#: signature not in its canonical encoding (rSig not x-only, s high); a digest signer
#: not in the cache; a certificate chain that is broken, too long or not under a trusted
#: root; a signer not permitted for the PSID; outside the validity period; a
#: generationTime too old or too far ahead; a headerInfo expiryTime passed; an ECDSA
#: signature that does not verify.
VERDICT_REASONS = ("ok", "unsigned", "replay", "unsupported", "nested", "wsmp-psid",
                   "non-canonical", "unknown-signer", "chain", "wrong-psid", "expired",
                   "stale", "message-expired", "bad-signature")

_HALF_ORDER = P256_ORDER // 2  # (n - 1) / 2: the largest low s
_ZERO = bytes(32)
_ORDER_OCTETS = P256_ORDER.to_bytes(32, "big")
_HALF_OCTETS = _HALF_ORDER.to_bytes(32, "big")
_new = object.__new__

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


@dataclass(frozen=True)
class Checked:
    """A message that passed every check of :meth:`Verifier.check`: what
    :meth:`Verifier.finish` needs for its ECDSA verification (the signer's key is kept,
    so a certificate evicted from the cache meanwhile does not matter)."""

    unwrapped: Unwrapped
    tbs_hash: bytes
    signer: _Trusted
    now_us: int
    generation_us: int

    @property
    def frame(self) -> bytes | None:
        return self.unwrapped.frame

    @property
    def signer_digest(self) -> bytes | None:
        return self.unwrapped.signer_digest

    def ecdsa_input(self) -> tuple[ec.EllipticCurvePublicKey, bytes | None, bytes]:
        """What the message's ECDSA verification takes: the signer's key, the r || s
        signature and the digest (for a verification elsewhere: another process)."""
        return (self.signer.key, self.unwrapped.signature,
                sha256(self.tbs_hash + self.signer.cert_hash))


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


def canonical(u: Unwrapped) -> bool:
    """Whether the signature of ``u`` is in the one encoding this verifier accepts: rSig
    x-only, 1 <= r < n and 1 <= s <= (n - 1) / 2 (see :mod:`catc.security`)."""
    sig = u.signature
    if u.signature_r_form != "x-only" or sig is None or len(sig) != 64:
        return False
    # 32-octet big-endian numbers compare as octet strings compare
    r, s = bytes(sig[:32]), bytes(sig[32:])
    return _ZERO < r < _ORDER_OCTETS and _ZERO < s <= _HALF_OCTETS


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

    Replays: the SHA-256 of the ToBeSignedData of every message accepted is kept until
    the message would be ``stale`` (at most ``max_replays`` of them, oldest evicted
    first; :attr:`replays`); a message with the same ToBeSignedData is then ``replay``.
    ``max_replays=0`` turns that off.  ``canonical_only=False`` accepts the signature
    encodings that 1609.2 allows and that anyone can derive from a valid signature (rSig
    as a point, high s); see :mod:`catc.security`.
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
        max_replays: int = 200_000,
        canonical_only: bool = True,
    ) -> None:
        if max_certs < 1 or max_chain < 1 or max_replays < 0:
            raise ValueError("max_certs and max_chain must be positive, max_replays not "
                             "negative")
        self.max_certs, self.max_chain, self.psid = max_certs, max_chain, psid
        self.max_age_us, self.max_future_us = max_age_us, max_future_us
        self.canonical_only = canonical_only
        #: the messages accepted within the freshness window (None: no replay check)
        self.replays = ReplayCache(max_replays) if max_replays else None
        self.cert_checks = 0  # certificate signatures verified so far (roots excluded)
        self._roots: dict[bytes, _Trusted] = {}
        self._cache: OrderedDict[bytes, _Trusted] = OrderedDict()
        self._known: OrderedDict[bytes, Certificate] = OrderedDict()  # not yet verified
        #: certificates whose signature did not verify (SHA-256 of their octets), so that
        #: a sender repeating a forged one costs one ECDSA, not one per frame
        self._forged: OrderedDict[bytes, None] = OrderedDict()
        for raw in roots:
            cert = _whole_certificate(raw)
            key = _public_key(cert)
            if cert.issuer_kind != "self" or key is None:
                raise ValueError("a trusted root must be self-signed with a P-256 key")
            if not verify_digest(key, cert.signature, sha256(sha256(cert.tbs) + EMPTY_HASH)):
                raise ValueError("trusted root self-signature does not verify")
            self._roots[cert.hashed_id8] = _Trusted(cert, key, sha256(cert.canonical), 1,
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
        whole = sha256(cert.canonical)
        if whole in self._forged:
            return None
        self.cert_checks += 1
        digest = sha256(sha256(cert.tbs) + issuer.cert_hash)
        if not verify_digest(issuer.key, cert.signature, digest):
            self._forged[whole] = None
            while len(self._forged) > self.max_certs:
                self._forged.popitem(last=False)
            return None
        trusted = _Trusted(cert, key, whole, issuer.depth + 1,
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
        octets that are not an ``Ieee1609Dot2Data`` at all (as :func:`unwrap` does).

        The checks run cheapest first and the first that fails is the verdict; a copy of
        a message already accepted is ``replay`` before anything else is looked at.  It is
        :meth:`check` (every check but the message's ECDSA) then :meth:`finish`."""
        checked = self.check(data, now_us)
        return checked if isinstance(checked, Verdict) else self.finish(checked)

    def check(self, data: bytes | Unwrapped, now_us: int) -> Verdict | Checked:
        """Every check of :meth:`verify` but the message's own ECDSA verification: the
        failed :class:`Verdict`, or a :class:`Checked` for :meth:`finish`.  Cheap when
        the signer is cached (a digest, or a certificate verified before); a certificate
        not seen yet costs its own ECDSA verification here, once (verify on demand,
        :mod:`catc.security.ondemand`)."""
        u = data if isinstance(data, Unwrapped) else unwrap(data)
        if u.security != "signed":
            return Verdict(False, "unsigned", u.frame)
        assert u.tbs_data is not None
        # the checks in their order, each failure a Verdict(False, reason, frame, digest);
        # written out flat (no closure, attributes read once): this runs for every frame
        tbs_hash = sha256(u.tbs_data)
        replays, psid = self.replays, self.psid
        if replays is not None and replays.seen(tbs_hash, now_us):
            return Verdict(False, "replay", u.frame, u.signer_digest)
        reason = None
        if u.unsupported:
            reason = "unsupported"
        elif u.signed_layers > 1:
            reason = "nested"
        elif u.wsmp_psid is not None and u.wsmp_psid != psid:
            reason = "wsmp-psid"
        else:
            kind = u.signer_kind
            if kind == "digest":
                signer = self._lookup(u.signer_digest)
                if signer is None:
                    reason = "unknown-signer"
            elif kind == "certificate":
                signer = self._chain(u.signer_certs)
                if signer is None:
                    reason = "chain"
            else:  # "self": self-signed data carries no key to verify it with
                return Verdict(False, "unknown-signer", u.frame, None)
        if reason is not None:
            return Verdict(False, reason, u.frame, u.signer_digest)
        generation, expiry = u.generation_time_us, u.expiry_time_us
        nb, na = signer.not_before, signer.not_after
        if u.psid != psid or psid not in signer.cert.app_psids:
            reason = "wrong-psid"
        elif (now_us is not None and not nb <= now_us // 1_000_000 < na) or (
                generation is not None and not nb <= generation // 1_000_000 < na):
            reason = "expired"
        elif (generation is None or now_us - generation > self.max_age_us
                or generation - now_us > self.max_future_us):
            reason = "stale"
        elif expiry is not None and (expiry < now_us or expiry < generation):
            reason = "message-expired"
        elif self.canonical_only and not canonical(u):
            reason = "non-canonical"
        else:
            checked = _new(Checked)  # Checked(u, tbs_hash, ...) without its frozen __init__
            checked.__dict__.update(unwrapped=u, tbs_hash=tbs_hash, signer=signer,
                                    now_us=now_us, generation_us=generation)
            return checked
        return Verdict(False, reason, u.frame, u.signer_digest)

    def finish(self, checked: Checked) -> Verdict:
        """The message's ECDSA verification, after :meth:`check` (at once, or later: the
        checks stay those of its receive time).  A copy accepted since its check is a
        ``replay``: two copies may wait at once, and only the first is the message."""
        u = checked.unwrapped
        if self.replays is not None and self.replays.seen(checked.tbs_hash, checked.now_us):
            return Verdict(False, "replay", u.frame, u.signer_digest)
        return self.settle(checked, verify_digest(*checked.ecdsa_input()))

    def settle(self, checked: Checked, ecdsa_ok: bool) -> Verdict:
        """:meth:`finish` with the ECDSA verification's outcome ``ecdsa_ok`` made
        elsewhere (:meth:`Checked.ecdsa_input`): the replay check again, then the verdict,
        and an accepted message into the replay cache."""
        u, tbs_hash = checked.unwrapped, checked.tbs_hash
        if self.replays is not None and self.replays.seen(tbs_hash, checked.now_us):
            return Verdict(False, "replay", u.frame, u.signer_digest)
        if not ecdsa_ok:
            return Verdict(False, "bad-signature", u.frame, u.signer_digest)
        if self.replays is not None:  # only now: a forgery must not make the real one a replay
            self.replays.add(tbs_hash, checked.generation_us + self.max_age_us,
                             checked.now_us)
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
