"""IEEE 1609.2 signing and verification (catc.security), cross-checked with OpenSSL and tshark.

The independent checks recompute what they check from the wire octets: the OpenSSL test
slices the ToBeSignedData and the certificates' toBeSigned out of the COER by the lengths
of what follows them, hashes with hashlib and verifies with ``openssl dgst``; the tshark
test has Wireshark's own 1609.3 / 1609.2 dissectors read a capture.
"""

from __future__ import annotations

import hashlib
import re
import shutil
import struct
import subprocess
import time
from datetime import UTC, datetime, timedelta
from functools import cache
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.utils import encode_dss_signature
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from catc.bsm import BSM
from catc.errors import DecodeError
from catc.j2735 import open_envelope
from catc.j2735.ieee1609 import (
    build_signed,
    parse_certificate,
    tbs_data,
    unwrap,
    wrap_unsecured,
    wrap_wsmp,
)
from catc.j2735.uper import encode_frame
from catc.security import (
    P256_ORDER,
    VERDICT_REASONS,
    Identity,
    Pki,
    Verdict,
    Verifier,
    hash_input,
    issue_certificate,
    load_private_pem,
    make_pki,
    sign_bsm,
    sign_data,
    time64_to_unix,
    unix_to_time32,
    unix_to_time64,
)

FRAME = encode_frame(BSM(msg_cnt=7, temp_id=0x12345678, sec_mark=1000, lat=42.3, lon=-83.7,
                         elev=200.0, speed=13.4, heading=90.0))
NOW = 636_913_807_899_000  # Time64 of the ODE's real signed record: 2024-03-07 TAI
DAY, WEEK = 86400, 7 * 86400
START = NOW // 1_000_000 - DAY  # Time32: the certificates became valid a day ago


@cache
def _pki() -> Pki:
    return make_pki(3, start_time32=START, duration_s=WEEK, seed=b"catc-test")


@cache
def _other_pki() -> Pki:
    return make_pki(1, start_time32=START, duration_s=WEEK, seed=b"someone else")


def _verifier(**kw: int) -> Verifier:
    """Trusts the root; knows the AA in advance, as the SCMS local certificate chain does."""
    return Verifier([_pki().root.raw], certificates=[_pki().aa.raw], **kw)


def _msg(i: int = 0, *, include_cert: bool = True, gen: int = NOW, frame: bytes = FRAME) -> bytes:
    p = _pki().pseudonyms[i]
    return sign_bsm(frame, p.key, p.raw, gen, include_cert=include_cert)


# --- time ---------------------------------------------------------------------------------


def test_time_helpers() -> None:
    assert unix_to_time64(1_072_915_200) == 0  # 2004-01-01 00:00:00 UTC: the epoch
    assert unix_to_time64(1_136_073_599) == (1_136_073_599 - 1_072_915_200) * 10**6  # 2005
    # leap seconds at the ends of 2005, 2008, 2012-06, 2015-06 and 2016 (TAI-UTC 32 -> 37 s)
    assert unix_to_time64(1_483_228_800) == (1_483_228_800 - 1_072_915_200 + 5) * 10**6
    assert unix_to_time64(1_483_228_799.5) == (1_483_228_799 - 1_072_915_200 + 4) * 10**6 + 5e5
    for unix_s in (1_072_915_200, 1_200_000_000.25, 1_483_228_800, 1_709_829_002.899):
        assert time64_to_unix(unix_to_time64(unix_s)) == pytest.approx(unix_s, abs=1e-6)
    # the ODE's signed record: Wireshark shows 2024-03-07 16:30:02.899 UTC for it as well
    assert time64_to_unix(NOW) == pytest.approx(1_709_829_002.899, abs=1e-6)
    assert unix_to_time32(1_709_829_002.899) == NOW // 10**6


# --- PKI ----------------------------------------------------------------------------------


def _compressed(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.public_key().public_bytes(serialization.Encoding.X962,
                                         serialization.PublicFormat.CompressedPoint)


def test_make_pki_structure() -> None:
    pki = _pki()
    root, aa = pki.root, pki.aa
    assert (root.cert.issuer_kind, root.cert.issue_all, root.cert.app_psids) == ("self", True, ())
    assert (aa.cert.issuer_digest, aa.cert.issue_psids, aa.cert.issue_all) == (
        root.hashed_id8, (0x20,), False)
    assert len(pki.pseudonyms) == 3
    for p in pki.pseudonyms:
        assert (p.cert.issuer_digest, p.cert.app_psids, p.cert.cert_type) == (
            aa.hashed_id8, (0x20,), "explicit")
        assert (p.cert.start_time32, p.cert.duration_s) == (START, WEEK)
        assert p.cert.verify_key == _compressed(p.key)
        assert parse_certificate(p.raw)[0] == p.cert and p.hashed_id8 == p.cert.hashed_id8
    keys = {_compressed(i.key) for i in pki.identities().values()}
    assert len(keys) == 5 and set(pki.identities()) == {
        "root", "aa", "pseudonym-0", "pseudonym-1", "pseudonym-2"}
    # keys serialise to PEM for a CLI to write, and read back
    pem = pki.private_pem("pseudonym-1")
    assert pem.startswith(b"-----BEGIN PRIVATE KEY-----")
    assert load_private_pem(pem).private_numbers() == pki.pseudonyms[1].key.private_numbers()
    # a seed makes the whole PKI reproducible (RFC 6979 signatures), no seed does not
    again = make_pki(3, start_time32=START, duration_s=WEEK, seed=b"catc-test")
    assert [i.raw for i in again.identities().values()] == [
        i.raw for i in pki.identities().values()]
    fresh = make_pki(1, start_time32=START, duration_s=WEEK)
    assert fresh.root.raw != pki.root.raw


# --- OpenSSL: independent signature check ----------------------------------------------------


def _openssl_verify(tmp: Path, pub: ec.EllipticCurvePublicKey, signature: bytes,
                    hashed: bytes) -> str:
    """``openssl dgst -sha256 -verify`` of r || s over ``hashed`` (the 64-octet input)."""
    (tmp / "pub.pem").write_bytes(pub.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
    r, s = int.from_bytes(signature[:32], "big"), int.from_bytes(signature[32:], "big")
    (tmp / "sig.der").write_bytes(encode_dss_signature(r, s))
    (tmp / "input.bin").write_bytes(hashed)
    out = subprocess.run(["openssl", "dgst", "-sha256", "-verify", str(tmp / "pub.pem"),
                          "-signature", str(tmp / "sig.der"), str(tmp / "input.bin")],
                         capture_output=True, text=True, timeout=60, check=False)
    return out.stdout.strip()


def _h(octets: bytes) -> bytes:
    return hashlib.sha256(octets).digest()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl CLI not installed")
@pytest.mark.parametrize("include_cert", [False, True])
def test_openssl_verifies_bsm_signature(tmp_path: Path, include_cert: bool) -> None:
    p = _pki().pseudonyms[0]
    data = _msg(include_cert=include_cert)
    # Slice by lengths: 03 81 00 | ToBeSignedData | signer | 80 80 r(32) s(32)
    signer_len = 3 + len(p.raw) if include_cert else 9
    tbs = data[3 : len(data) - 66 - signer_len]
    signer = data[len(data) - 66 - signer_len : len(data) - 66]
    assert signer == (b"\x81\x01\x01" + p.raw if include_cert else b"\x80" + p.hashed_id8)
    assert data[-66:-64] == b"\x80\x80"
    assert tbs == unwrap(data).tbs_data  # the codec agrees with the slicing
    assert p.hashed_id8 == _h(p.raw)[-8:]
    signature = data[-64:]
    # IEEE 1609.2 §5.3.1: ECDSA over SHA-256( SHA-256(tbs) || SHA-256(signer certificate) )
    assert _openssl_verify(tmp_path, p.key.public_key(), signature,
                           _h(tbs) + _h(p.raw)) == "Verified OK"
    flipped = bytearray(tbs)
    flipped[len(tbs) // 2] ^= 0x01
    assert _openssl_verify(tmp_path, p.key.public_key(), signature,
                           _h(bytes(flipped)) + _h(p.raw)) == "Verification failure"
    assert hash_input(tbs, p.raw) == _h(tbs) + _h(p.raw)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl CLI not installed")
def test_openssl_verifies_certificate_chain(tmp_path: Path) -> None:
    pki = _pki()
    root, aa, p = pki.root, pki.aa, pki.pseudonyms[2]
    # CertificateBase: preamble, version, type, issuer (9 octets digest / 2 octets self),
    # toBeSigned, then the 66-octet signature 80 80 r s
    checks = [  # (certificate, offset of toBeSigned, issuer certificate octets, issuer key)
        (p.raw, 12, aa.raw, aa.key),
        (aa.raw, 12, root.raw, root.key),
        (root.raw, 5, b"", root.key),  # self-signed: the hash of the empty string (§5.3.1)
    ]
    for raw, tbs_at, issuer_raw, issuer_key in checks:
        tbs, signature = raw[tbs_at:-66], raw[-64:]
        assert raw[-66:-64] == b"\x80\x80"
        assert _openssl_verify(tmp_path, issuer_key.public_key(), signature,
                               _h(tbs) + _h(issuer_raw)) == "Verified OK"
    assert _openssl_verify(tmp_path, aa.key.public_key(), p.raw[-64:],
                           _h(p.raw[12:-66]) + _h(root.raw)) == "Verification failure"


# --- tshark: independent dissection ----------------------------------------------------------


def _pcap(path: Path, payloads: list[bytes]) -> None:
    """A classic libpcap file, LINKTYPE_ETHERNET: broadcast, ethertype 0x88DC (WSMP)."""
    out = [struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)]
    for i, payload in enumerate(payloads):
        eth = b"\xff" * 6 + b"\x02\x00\x00\x00\x00\x01" + b"\x88\xdc" + payload
        out.append(struct.pack("<IIII", 1_709_829_003 + i, 0, len(eth), len(eth)) + eth)
    path.write_bytes(b"".join(out))


def test_tshark_dissects_signed_wsmp(tmp_path: Path) -> None:
    tshark = shutil.which("tshark")
    if tshark is None:
        pytest.skip("tshark not installed (make test installs it)")
    pki = _pki()
    p = pki.pseudonyms[0]
    messages = [_msg(include_cert=True), _msg(include_cert=False)]
    _pcap(tmp_path / "bsm.pcap", [wrap_wsmp(m) for m in messages])
    run = subprocess.run([tshark, "-r", str(tmp_path / "bsm.pcap"), "-V"], capture_output=True,
                         text=True, timeout=120, check=True)
    frames = re.split(r"^Frame \d+:", run.stdout, flags=re.M)[1:]
    assert len(frames) == 2
    # generationTime as Wireshark shows it in UTC: Time64 - 5 leap seconds (2006-2017)
    gen = datetime(2004, 1, 1, tzinfo=UTC) + timedelta(seconds=NOW // 10**6 - 5,
                                                       microseconds=NOW % 10**6)
    for text, data, kind in zip(frames, messages, ("certificate (1)", "digest (0)"), strict=True):
        assert "Protocols in frame: eth:ethertype:wsmp:ieee1609dot2" in text
        assert re.search(r"PSID: psid-vehicle-to-vehicle-safety-and-awarenesss\s*\(32\)", text)
        assert "Ieee1609Dot2Data" in text and "content: signedData (1)" in text
        assert "hashId: sha256 (0)" in text
        assert f"unsecuredData: {FRAME.hex()[:60]}" in text
        assert f"generationTime: {gen:%Y-%m-%d %H:%M:%S.%f} ({NOW})" in text
        assert f"signer: {kind}" in text
        assert "signature: ecdsaNistP256Signature (0)" in text
        assert f"x-only: {data[-64:-32].hex()}" in text and f"sSig: {data[-32:].hex()}" in text
        assert "Malformed" not in text and "Expert Info" not in text
    cert_frame, digest_frame = frames
    assert f"digest: {p.hashed_id8.hex()}" in digest_frame
    assert f"sha256AndDigest: {pki.aa.hashed_id8.hex()}" in cert_frame
    assert "type: explicit (0)" in cert_frame
    assert f"compressed-y-{p.cert.verify_key[0] - 2}: {p.cert.verify_key[1:].hex()}" in cert_frame
    assert re.search(r"appPermissions: 1 item.*?psid: psid-vehicle-to-vehicle", cert_frame, re.S)
    expert = subprocess.run([tshark, "-r", str(tmp_path / "bsm.pcap"), "-q", "-z", "expert"],
                            capture_output=True, text=True, timeout=120, check=True)
    assert not re.search(r"^(Errors|Warnings|Notes)\b", expert.stdout, flags=re.M)


# --- Verifier ---------------------------------------------------------------------------------


def test_legit_chain_verifies_and_certificates_are_checked_once() -> None:
    v = _verifier()
    p = _pki().pseudonyms[0]
    verdict = v.verify(_msg(), NOW + 20_000)
    assert verdict == Verdict(True, "ok", FRAME, p.hashed_id8)
    assert v.cert_checks == 2  # the AA under the root, the pseudonym under the AA
    # (each message once: the same ToBeSignedData again, whoever signs it, is a replay)
    assert v.verify(_msg(include_cert=False, gen=NOW + 1), NOW).ok
    assert v.verify(_msg(gen=NOW + 2), NOW).ok and v.cert_checks == 2  # cached: not again
    assert v.verify(_msg(1, gen=NOW + 3), NOW).ok and v.cert_checks == 3  # the AA stays cached
    assert v.verify(unwrap(_msg(1, include_cert=False, gen=NOW + 4)), NOW).ok  # Unwrapped too
    assert v.cache_size == 3 and p.hashed_id8 in v


def test_digest_before_certificate_is_unknown_then_known() -> None:
    v = _verifier()
    digest_msg = _msg(2, include_cert=False)
    assert v.verify(digest_msg, NOW).reason == "unknown-signer"
    assert v.verify(_msg(2, gen=NOW - 1), NOW).reason == "ok"
    assert v.verify(digest_msg, NOW).reason == "ok"


def test_tampered_message_is_bad_signature() -> None:
    v = _verifier()
    good = _msg()
    frame_at = good.index(FRAME)
    for pos in (frame_at + 5, len(good) - 1, len(good) - 40):  # frame, sSig, rSig
        bad = bytearray(good)
        bad[pos] ^= 0x10
        assert v.verify(bytes(bad), NOW).reason == "bad-signature", pos
    # signed by another pseudonym's key, claiming pseudonym 0's certificate
    p0, p1 = _pki().pseudonyms[:2]
    forged = sign_bsm(FRAME, p1.key, p0.raw, NOW, include_cert=False)
    assert v.verify(forged, NOW).reason == "bad-signature"
    assert v.verify(good, NOW).reason == "ok"


def _chain_msg(key: ec.EllipticCurvePrivateKey, chain: list[bytes], gen: int = NOW,
               psid: int = 0x20) -> bytes:
    signature = sign_data(tbs_data(FRAME, psid, gen), key, chain[0])
    return build_signed(FRAME, psid=psid, generation_time_us=gen,
                        signer=("certificate", chain), signature=signature)


def test_foreign_root_is_chain() -> None:
    v = _verifier()
    other = _other_pki()
    q = other.pseudonyms[0]
    assert v.verify(sign_bsm(FRAME, q.key, q.raw, NOW, include_cert=True), NOW).reason == "chain"
    full = _chain_msg(q.key, [q.raw, other.aa.raw, other.root.raw])
    assert v.verify(full, NOW).reason == "chain"
    assert v.cache_size == 0
    # the same full chain from the trusted PKI (root included) is fine
    pki = _pki()
    p = pki.pseudonyms[0]
    assert v.verify(_chain_msg(p.key, [p.raw, pki.aa.raw, pki.root.raw]), NOW).ok
    # an AA that the trusted root did not sign
    assert Verifier([other.root.raw]).verify(_chain_msg(p.key, [p.raw, pki.aa.raw]),
                                             NOW).reason == "chain"


def test_wrong_psid() -> None:
    pki = make_pki(1, start_time32=START, duration_s=WEEK, psids=(0x20, 0x8F), seed=b"psid")
    v = Verifier([pki.root.raw], certificates=[pki.aa.raw])
    not_bsm = issue_certificate(pki.aa, start_time32=START, duration_s=WEEK, app_psids=(0x8F,))
    msg = sign_bsm(FRAME, not_bsm.key, not_bsm.raw, NOW, include_cert=True)
    assert v.verify(msg, NOW).reason == "wrong-psid"
    p = pki.pseudonyms[0]  # may sign 0x20 and 0x8F: a header psid 0x8F is not a BSM
    assert v.verify(sign_bsm(FRAME, p.key, p.raw, NOW, include_cert=True, psid=0x8F),
                    NOW).reason == "wrong-psid"
    assert v.verify(sign_bsm(FRAME, p.key, p.raw, NOW, include_cert=True), NOW).ok
    # the AA may issue only what the root allowed it; a pseudonym beyond that breaks the chain
    greedy = issue_certificate(_pki().aa, start_time32=START, duration_s=WEEK,
                               app_psids=(0x20, 0x8F))
    assert _verifier().verify(sign_bsm(FRAME, greedy.key, greedy.raw, NOW, include_cert=True),
                              NOW).reason == "chain"


def test_expired() -> None:
    pki = _pki()
    v = _verifier()
    old = issue_certificate(pki.aa, start_time32=START - 3 * WEEK, duration_s=WEEK,
                            app_psids=(0x20,))
    assert v.verify(sign_bsm(FRAME, old.key, old.raw, NOW, include_cert=True),
                    NOW).reason == "expired"
    future = issue_certificate(pki.aa, start_time32=START + 2 * DAY, duration_s=WEEK,
                               app_psids=(0x20,))
    assert v.verify(sign_bsm(FRAME, future.key, future.raw, NOW, include_cert=True),
                    NOW).reason == "expired"
    # the pseudonym's own period is fine but its AA's has ended: the chain's period counts
    short_aa = issue_certificate(pki.root, start_time32=START - WEEK, duration_s=WEEK + 3600,
                                 issue_psids=(0x20,))
    p = issue_certificate(short_aa, start_time32=START, duration_s=WEEK, app_psids=(0x20,))
    assert v.verify(_chain_msg(p.key, [p.raw, short_aa.raw]), NOW).reason == "expired"
    # the same messages a week later: everything of this PKI has expired
    later = NOW + 8 * DAY * 10**6
    assert v.verify(_msg(gen=later), later).reason == "expired"


def test_stale_generation_time() -> None:
    v = _verifier()
    assert v.verify(_msg(gen=NOW - 1_500_000), NOW).reason == "ok"
    assert v.verify(_msg(gen=NOW - 5_000_000), NOW).reason == "stale"
    assert v.verify(_msg(gen=NOW + 5_000_000), NOW).reason == "stale"
    assert v.verify(_msg(gen=NOW + 500_000), NOW).reason == "ok"
    lenient = _verifier(max_age_us=10_000_000)
    assert lenient.verify(_msg(gen=NOW - 5_000_000), NOW).reason == "ok"


def test_unsigned_and_unsupported() -> None:
    v = _verifier()
    assert v.verify(wrap_unsecured(FRAME), NOW) == Verdict(False, "unsigned", FRAME, None)
    # a signer whose certificate is implicit (as SCMS pseudonyms are): cannot be verified
    p = _pki().pseudonyms[0]
    implicit = (b"\x00\x03\x01\x80" + _pki().aa.hashed_id8 + p.cert.tbs[:-35]
                + b"\x81\x82" + bytes(range(32)))
    msg = build_signed(FRAME, generation_time_us=NOW, signer=("certificate", implicit),
                       signature=bytes(64))
    verdict = v.verify(msg, NOW)
    assert (verdict.ok, verdict.reason, verdict.frame) == (False, "unsupported", FRAME)
    # a signer certificate with an ecdsaNistP384 key (an open type in the extension)
    p384 = (b"\x80\x03\x00\x80" + _pki().aa.hashed_id8 + p.cert.tbs[:-35]
            + b"\x80\x83\x31\x82" + bytes(48) + p.raw[-66:])
    msg = build_signed(FRAME, generation_time_us=NOW, signer=("certificate", p384),
                       signature=bytes(64))
    assert v.verify(msg, NOW).reason == "unsupported"
    assert set(VERDICT_REASONS) >= {"ok", "unsigned", "bad-signature", "unknown-signer",
                                    "expired", "wrong-psid", "stale", "chain", "unsupported"}


def test_signature_r_forms() -> None:
    """rSig may be sent x-only or as the compressed point R (its x is r): both verify
    where non-canonical encodings are allowed, only x-only where they are not (the
    default); ``fill`` is no 32-octet r at all and does not decode."""
    msg = _msg()
    assert msg[-66:-64] == b"\x80\x80"
    compressed = msg[:-65] + b"\x82" + msg[-64:]
    assert _verifier(canonical_only=False).verify(compressed, NOW).reason == "ok"
    v = _verifier()
    assert v.verify(compressed, NOW).reason == "non-canonical"
    assert v.verify(msg, NOW).reason == "ok"
    with pytest.raises(DecodeError) as err:
        v.verify(msg[:-65] + b"\x81" + msg[-32:], NOW)
    assert err.value.reason == "garbage"


def test_chain_longer_than_allowed() -> None:
    pki = _pki()
    aa1 = issue_certificate(pki.root, start_time32=START, duration_s=WEEK, issue_psids=(0x20,),
                            issue_chain=(2, 0))
    aa2 = issue_certificate(aa1, start_time32=START, duration_s=WEEK, issue_psids=(0x20,))
    p = issue_certificate(aa2, start_time32=START, duration_s=WEEK, app_psids=(0x20,))
    msg = _chain_msg(p.key, [p.raw, aa2.raw, aa1.raw])
    v = _verifier()
    assert v.verify(msg, NOW).reason == "chain" and v.cache_size == 0
    assert _verifier(max_chain=4).verify(msg, NOW).ok
    # an AA whose signature by the root is broken, and a pseudonym it issued
    broken_raw = pki.aa.raw[:-1] + bytes([pki.aa.raw[-1] ^ 1])
    broken_aa = Identity("broken", broken_raw, parse_certificate(broken_raw)[0], pki.aa.key)
    r = issue_certificate(broken_aa, start_time32=START, duration_s=WEEK, app_psids=(0x20,))
    checks = v.cert_checks
    assert v.verify(_chain_msg(r.key, [r.raw, broken_raw]), NOW).reason == "chain"
    assert v.cert_checks == checks + 1 and v.cache_size == 0
    # the same forged certificate again: rejected without another ECDSA; a real one
    # after it still verifies
    assert v.verify(_chain_msg(r.key, [r.raw, broken_raw]), NOW).reason == "chain"
    assert v.cert_checks == checks + 1
    good = issue_certificate(pki.aa, start_time32=START, duration_s=WEEK, app_psids=(0x20,))
    assert v.verify(_chain_msg(good.key, [good.raw, pki.aa.raw], gen=NOW + 1), NOW).ok
    assert v.cert_checks == checks + 3  # the AA under the root, the pseudonym under the AA
    q = pki.pseudonyms[1]
    # certificates that do not chain (the second is not the issuer of the first), to a
    # verifier that does not know the AA in advance; one that knows it needs no more
    stranger = Verifier([pki.root.raw])
    assert stranger.verify(_chain_msg(q.key, [q.raw, pki.root.raw]), NOW).reason == "chain"
    assert v.verify(_chain_msg(q.key, [q.raw, pki.root.raw]), NOW).ok


def test_cache_is_lru_and_bounded() -> None:
    pki = make_pki(20, start_time32=START, duration_s=WEEK, seed=b"many")
    v = Verifier([pki.root.raw], certificates=[pki.aa.raw], max_certs=8)
    for i, p in enumerate(pki.pseudonyms):
        assert v.verify(sign_bsm(FRAME, p.key, p.raw, NOW + i, include_cert=True), NOW).ok
        assert v.cache_size <= 8
    first, last = pki.pseudonyms[0], pki.pseudonyms[-1]
    assert v.verify(sign_bsm(FRAME, first.key, first.raw, NOW + 98, include_cert=False),
                    NOW).reason == "unknown-signer"  # evicted
    assert v.verify(sign_bsm(FRAME, last.key, last.raw, NOW + 99, include_cert=False), NOW).ok


def test_ten_thousand_unknown_digests_stay_bounded() -> None:
    v = _verifier(max_certs=64)
    assert v.verify(_msg(), NOW).ok
    template = _msg(include_cert=False, gen=NOW + 1)  # not the message that verified
    digest_at = len(template) - 66 - 8
    reasons = set()
    for i in range(10_000):
        msg = template[:digest_at] + i.to_bytes(8, "big") + template[digest_at + 8:]
        reasons.add(v.verify(msg, NOW).reason)
    assert reasons == {"unknown-signer"}
    assert v.cache_size <= 64


def test_verify_many() -> None:
    v = _verifier()
    items: list[bytes] = [_msg(include_cert=False), _msg(), _msg(include_cert=False, gen=NOW + 1),
                          b"\x03\x81", wrap_unsecured(FRAME), _msg(include_cert=False)]
    out = v.verify_many(items, NOW)
    assert [o.reason for o in out] == ["unknown-signer", "ok", "ok", "truncated", "unsigned",
                                       "replay"]
    assert isinstance(out[3], DecodeError) and v.cert_checks == 2


def test_verifier_rejects_a_bad_trusted_root() -> None:
    root = _pki().root.raw
    with pytest.raises(ValueError, match="self-signature"):
        Verifier([root[:-1] + bytes([root[-1] ^ 1])])
    with pytest.raises(ValueError, match="self-signed"):
        Verifier([_pki().aa.raw])
    with pytest.raises(DecodeError):
        Verifier([root[:40]])


# --- hostile input ------------------------------------------------------------------------------


def _only_decode_error_or_verdict(v: Verifier, data: bytes) -> Verdict | None:
    try:
        verdict = v.verify(data, NOW)
    except DecodeError:
        return None
    assert isinstance(verdict, Verdict) and verdict.reason in VERDICT_REASONS
    assert verdict.ok == (verdict.reason == "ok")
    return verdict


@given(st.binary(max_size=400))
def test_random_bytes_into_verify(data: bytes) -> None:
    _only_decode_error_or_verdict(_VERIFIER, data)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_mutated_signed_messages_into_verify(data: st.DataObject) -> None:
    msg = bytearray(data.draw(st.sampled_from(_MESSAGES)))
    for _ in range(data.draw(st.integers(1, 3))):
        msg[data.draw(st.integers(0, len(msg) - 1))] = data.draw(st.integers(0, 255))
    _only_decode_error_or_verdict(_VERIFIER, bytes(msg))
    assert _VERIFIER.cache_size <= 16


@given(st.integers(0, 300))
def test_truncated_signed_messages_into_verify(n: int) -> None:
    msg = _MESSAGES[0]
    if n < len(msg):
        with pytest.raises(DecodeError) as err:
            _VERIFIER.verify(msg[:n], NOW)
        assert err.value.reason == "truncated"


_VERIFIER = Verifier([_pki().root.raw], certificates=[_pki().aa.raw], max_certs=16)
_MESSAGES = [_msg(include_cert=True), _msg(1, include_cert=False)]


# --- performance --------------------------------------------------------------------------------


def test_sign_and_verify_cost(capsys: pytest.CaptureFixture[str]) -> None:
    p = _pki().pseudonyms[0]
    v = _verifier()
    assert v.verify(_msg(), NOW).ok
    n = 300
    t0 = time.perf_counter()
    msgs = [sign_bsm(FRAME, p.key, p.raw, NOW + 1 + i, include_cert=False) for i in range(n)]
    t1 = time.perf_counter()
    verdicts = [v.verify(m, NOW) for m in msgs]
    t2 = time.perf_counter()
    assert all(x.ok for x in verdicts) and v.cert_checks == 2
    sign_us, verify_us = (t1 - t0) / n * 1e6, (t2 - t1) / n * 1e6
    with capsys.disabled():
        print(f"\n1609.2 per BSM: sign {sign_us:.0f} µs, verify (cached cert) {verify_us:.0f} µs")
    assert verify_us < 3000 and sign_us < 3000  # generous: a loaded 2-core machine


# --- issue 28: the envelope and the signature's encoding ------------------------------------


N = P256_ORDER


def _with_header(header: bytes, i: int = 0) -> bytes:
    """A message of pseudonym ``i`` (certificate signer) whose headerInfo is ``header``
    (psid 0x20 first), signed as sign_bsm signs."""
    p = _pki().pseudonyms[i]
    tbs = b"\x40" + wrap_unsecured(FRAME) + header
    signature = sign_data(tbs, p.key, p.raw)
    return b"\x03\x81\x00" + tbs + b"\x81\x01\x01" + p.raw + b"\x80\x80" + signature


def _header(gen: int, expiry: int | None = None) -> bytes:
    if expiry is None:
        return b"\x40\x01\x20" + gen.to_bytes(8, "big")
    return b"\x60\x01\x20" + gen.to_bytes(8, "big") + expiry.to_bytes(8, "big")


def test_header_expiry_time_in_the_past_is_message_expired() -> None:
    assert _with_header(_header(NOW)) == _msg()  # the hand-made header is sign_bsm's
    v = _verifier()
    assert v.verify(_with_header(_header(NOW, NOW - 1)), NOW).reason == "message-expired"
    assert v.verify(_with_header(_header(NOW - 500_000, NOW - 100_000)),
                    NOW).reason == "message-expired"  # fresh, but expired 0.1 s ago
    # expiring before it was generated: no time at which it was ever valid
    assert v.verify(_with_header(_header(NOW + 500_000, NOW + 200_000)),
                    NOW).reason == "message-expired"
    assert v.verify(_with_header(_header(NOW, NOW + 100_000)), NOW).reason == "ok"
    assert v.verify(_with_header(_header(NOW - 1, NOW)), NOW).reason == "ok"  # to the µs


def test_signed_data_inside_signed_data_is_nested() -> None:
    """An outer SignedData around a valid message: the verifier would check only the
    inner one, so the outer layer (here signed by nobody it trusts) is refused."""
    inner = _msg()
    q = _other_pki().pseudonyms[0]
    tbs = b"\x40" + inner + _header(NOW)
    outer = (b"\x03\x81\x00" + tbs + b"\x81\x01\x01" + q.raw + b"\x80\x80"
             + sign_data(tbs, q.key, q.raw))
    v = _verifier()
    assert v.verify(outer, NOW).reason == "nested"
    assert v.verify(inner, NOW).reason == "ok"
    assert unwrap(outer).frame == FRAME and unwrap(outer).signed_layers == 2


def test_a_wsm_for_another_psid_is_wsmp_psid() -> None:
    v = _verifier()
    frame, envelope = open_envelope(wrap_wsmp(_msg(), psid=0x87))
    assert frame == FRAME and v.verify(envelope, NOW).reason == "wsmp-psid"
    frame, envelope = open_envelope(wrap_wsmp(_msg(1), psid=0x20))
    assert frame == FRAME and v.verify(envelope, NOW).reason == "ok"


def _resign(msg: bytes, r_octets: bytes, s: int) -> bytes:
    """``msg`` with its signature replaced: rSig as given (choice and octets), s."""
    return msg[:-65] + r_octets + s.to_bytes(32, "big")


def test_sign_bsm_signs_low_s() -> None:
    p = _pki().pseudonyms[0]
    sigs = [sign_bsm(FRAME, p.key, p.raw, NOW + i, include_cert=False)[-32:] for i in range(64)]
    assert all(int.from_bytes(s, "big") <= N // 2 for s in sigs)


def test_malleated_signatures_are_non_canonical() -> None:
    """Encodings anyone can make from a valid signature without the key: the high-S twin
    (r, n - s), and rSig sent as the point R with either y bit or any y.  ECDSA accepts
    them all (the lenient verifier says ok); the default verifier only the original."""
    msg = _msg()
    r, s = msg[-64:-32], int.from_bytes(msg[-32:], "big")
    twins = {
        "high-S": _resign(msg, b"\x80" + r, N - s),
        "compressed-y-0": _resign(msg, b"\x82" + r, s),
        "compressed-y-1": _resign(msg, b"\x83" + r, s),
        "uncompressed, any y": _resign(msg, b"\x84" + r + bytes(range(32)), s),
        "compressed, high-S": _resign(msg, b"\x83" + r, N - s),
    }
    for name, twin in twins.items():
        assert _verifier(canonical_only=False).verify(twin, NOW).ok, name
        assert _verifier().verify(twin, NOW).reason == "non-canonical", name
    # out of range: r or s of 0, r of n or more (no x-only r is), s of n
    r0 = int.from_bytes(r, "big")
    for r_int, s_int in ((0, s), (r0, 0), (N, s), (2**256 - 1, s), (r0, N)):
        bad = _resign(msg, b"\x80" + r_int.to_bytes(32, "big"), s_int)
        assert _verifier().verify(bad, NOW).reason == "non-canonical", (r_int, s_int)
    assert _verifier().verify(msg, NOW).ok
