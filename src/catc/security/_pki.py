"""Keys, certificates and a test PKI for :mod:`catc.security`: explicit P-256
certificates (§6.4) issued by a root CA and an authorization CA."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from catc.j2735.ieee1609 import (
    ISSUE_ALL,
    PSID_BSM,
    Certificate,
    build_certificate,
    build_tbs_certificate,
    parse_certificate,
)
from catc.security._crypto import EMPTY_HASH, P256_ORDER, sha256, sign_digest


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
        signature = sign_digest(key, sha256(sha256(tbs) + EMPTY_HASH))
        raw = build_certificate(tbs, issuer_digest=None, signature=signature)
    else:
        signature = sign_digest(issuer.key, sha256(sha256(tbs)
                                                     + sha256(issuer.cert.canonical)))
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
            h = sha256(b"catc-pki\x00" + seed_octets + b"\x00" + label.encode())
            return ec.derive_private_key(int.from_bytes(h, "big") % (P256_ORDER - 1) + 1,
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


