"""The cryptography of :mod:`catc.security`: 1609.2 time, the hash input of §5.3.1, and
ECDSA P-256 signing and verification of a digest (``cryptography``).

Signatures are made low-S (``s <= (n - 1) / 2``): ECDSA accepts (r, n - s) as readily
as (r, s), and the verifier takes only the low one (see :mod:`catc.security`).
"""

from __future__ import annotations

import hashlib
from functools import lru_cache

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import ec, utils

from catc.j2735.ieee1609 import PSID_BSM, build_signed, parse_certificate, tbs_data

P256_ORDER = 0xFFFFFFFF00000000FFFFFFFFFFFFFFFFBCE6FAADA7179E84F3B9CAC2FC632551
_EPOCH_UNIX = 1_072_915_200  # 2004-01-01 00:00:00 UTC
_LEAPS_UNIX = (1_136_073_600, 1_230_768_000, 1_341_100_800, 1_435_708_800, 1_483_228_800)
EMPTY_HASH = hashlib.sha256(b"").digest()
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


def sha256(octets: bytes) -> bytes:
    """SHA-256 of ``octets``."""
    return hashlib.sha256(octets).digest()


def hash_input(tbs: bytes, signer_cert: bytes | None) -> bytes:
    """The 64 octets whose SHA-256 is signed (§5.3.1): ``SHA-256(tbs) || SHA-256(signer)``,
    with ``signer`` the canonical COER certificate, or empty when self-signed."""
    return sha256(tbs) + sha256(signer_cert or b"")


def sign_digest(key: ec.EllipticCurvePrivateKey, digest: bytes) -> bytes:
    """r || s (64 octets) over a 32-octet ``digest``, with s low (``s <= (n - 1) / 2``)."""
    r, s = utils.decode_dss_signature(key.sign(digest, _SIGN))
    s = min(s, P256_ORDER - s)
    return r.to_bytes(32, "big") + s.to_bytes(32, "big")


def verify_digest(key: ec.EllipticCurvePublicKey, signature: bytes | None,
                  digest: bytes) -> bool:
    """Whether r || s ``signature`` is ``key``'s ECDSA signature over ``digest`` (either
    s: the verifier checks the encoding apart)."""
    if signature is None or len(signature) != 64:
        return False
    r, s = int.from_bytes(signature[:32], "big"), int.from_bytes(signature[32:], "big")
    try:
        key.verify(utils.encode_dss_signature(r, s), digest, _VERIFY)
    except InvalidSignature:
        return False
    return True


@lru_cache(maxsize=4096)  # a signer per RV: an RVE with 500 RVs signs in turn
def cert_hashes(cert_raw: bytes) -> tuple[bytes, bytes]:
    """(SHA-256 of the canonical certificate, its HashedId8) for a signer certificate."""
    cert, _ = parse_certificate(cert_raw)
    return sha256(cert.canonical), cert.hashed_id8


def sign_data(tbs: bytes, key: ec.EllipticCurvePrivateKey, signer_cert: bytes | None) -> bytes:
    """r || s (64 octets) over ``tbs`` for the certificate ``signer_cert`` (COER), or
    self-signed when None (§5.3.1)."""
    signer_hash = cert_hashes(bytes(signer_cert))[0] if signer_cert else EMPTY_HASH
    return sign_digest(key, sha256(sha256(tbs) + signer_hash))


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
    cert_hash, hashed_id8 = cert_hashes(bytes(cert_raw))
    tbs = tbs_data(frame, psid, generation_time_us)
    signature = sign_digest(key, sha256(sha256(tbs) + cert_hash))
    signer = ("certificate", bytes(cert_raw)) if include_cert else ("digest", hashed_id8)
    return build_signed(frame, psid=psid, generation_time_us=generation_time_us, signer=signer,
                        signature=signature)


