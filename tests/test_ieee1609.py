"""IEEE 1609.2 COER unwrap/wrap against the ODE's real records and synthetic edge cases."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import struct
import subprocess
import sys
from functools import cache
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catc.errors import DecodeError, EncodeError
from catc.j2735 import open_envelope
from catc.j2735.ieee1609 import (
    ISSUE_ALL,
    Certificate,
    Unwrapped,
    build_certificate,
    build_signed,
    build_tbs_certificate,
    looks_like_1609,
    looks_like_wsmp,
    parse_certificate,
    tbs_data,
    unwrap,
    unwrap_wsmp,
    wrap_unsecured,
    wrap_wsmp,
)
from tests.conftest import shared_path

PSID_BSM = 0x20


@cache
def _bin_payloads(name: str) -> tuple[bytes, ...]:
    """Payloads of an OBU log, framed independently of catc.j2735.obulog."""
    data = shared_path("jpo-ode-bsm-vectors", name).read_bytes()
    header, len_at = {"bsmLogDuringEvent.bin": (26, 24), "rxMsg_BSM.bin": (29, 27)}[name]
    out, pos = [], 0
    while pos < len(data):
        (length,) = struct.unpack_from("<H", data, pos + len_at)
        out.append(data[pos + header : pos + header + length])
        pos += header + length
    return tuple(out)


def _unsecured_records() -> list[bytes]:
    records = _bin_payloads("bsmLogDuringEvent.bin") + _bin_payloads("rxMsg_BSM.bin")
    return [r for r in records if looks_like_1609(r)]


@cache
def _signed_record() -> bytes:
    doc = json.loads(shared_path("jpo-ode-bsm-vectors", "decoder-input-bsm.json").read_text())
    return bytes.fromhex(doc["payload"]["data"]["bytes"])


def _signed(inner: bytes, psid: int, gen_time: int | None = None, ext_hash: bool = False) -> bytes:
    """A SignedData around ``inner`` with a digest signer and a dummy P-256 signature."""
    preamble = 0x40 | (0x20 if ext_hash else 0)
    psid_octets = psid.to_bytes(max(1, (psid.bit_length() + 7) // 8), "big")
    header = bytes([0x40 if gen_time is not None else 0, len(psid_octets)]) + psid_octets
    if gen_time is not None:
        header += gen_time.to_bytes(8, "big")
    ext = b"\x80" + bytes(32) if ext_hash else b""
    tail = b"\x80" + bytes(8) + b"\x80\x80" + bytes(64)  # signer digest, signature x-only
    return b"\x03\x81\x00" + bytes([preamble]) + inner + ext + header + tail


def test_real_unsecured_records_unwrap_to_message_frames() -> None:
    records = _unsecured_records()
    assert len(records) >= 222 + 227
    for record in records:
        u = unwrap(record)
        assert u == Unwrapped(frame=u.frame, security="unsecured")
        assert u.frame[:2] == b"\x00\x14"
        assert wrap_unsecured(u.frame) == record  # the logs are canonical OER


def test_real_signed_record() -> None:
    u = unwrap(_signed_record())
    assert u.security == "signed"
    assert u.psid == PSID_BSM
    assert u.frame[:2] == b"\x00\x14" and len(u.frame) == 0xB1
    # 2024-03-07 (TAI), a week before the record's odeReceivedAt of 2024-03-15
    assert u.generation_time_us == 636_913_807_899_000
    # the ODE's expected decoder input is this frame followed by the rest of the record
    xml = shared_path("jpo-ode-bsm-vectors", "expected-bsm.xml").read_text()
    expected = bytes.fromhex(re.search(r"<bytes>([0-9A-F]+)</bytes>", xml).group(1))
    assert expected.startswith(u.frame)


@pytest.mark.parametrize("size", [0, 1, 127, 128, 255, 256, 65535, 65536, 70000])
def test_wrap_lengths(size: int) -> None:
    frame = bytes(i % 251 for i in range(size))
    wrapped = wrap_unsecured(frame)
    assert wrapped[:2] == b"\x03\x80"
    assert len(wrapped) == 2 + (1 if size < 128 else 2 + (size > 255) + (size > 65535)) + size
    assert unwrap(wrapped).frame == frame


@given(st.binary(max_size=600))
def test_wrap_unwrap_round_trip(frame: bytes) -> None:
    assert unwrap(wrap_unsecured(frame)) == Unwrapped(frame, "unsecured")


def test_signed_synthetic_variants() -> None:
    frame = bytes.fromhex("001480ad") + bytes(40)
    u = unwrap(_signed(wrap_unsecured(frame), psid=0x20, gen_time=12345))
    assert (u.frame, u.security, u.psid, u.generation_time_us) == (frame, "signed", 0x20, 12345)
    u = unwrap(_signed(wrap_unsecured(frame), psid=0x204097, ext_hash=True))
    assert (u.psid, u.generation_time_us) == (0x204097, None)
    assert u.signed_layers == 1 and u.wsmp_psid is None
    # signed inside signed: the header of the layer that signs the frame is reported, and
    # the number of layers (the verifier refuses more than one)
    u = unwrap(_signed(_signed(wrap_unsecured(frame), psid=0x20, gen_time=7), psid=0x8F))
    assert (u.frame, u.psid, u.generation_time_us) == (frame, 0x20, 7)
    assert u.signed_layers == 2


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"", "truncated"),
        (b"\x03", "truncated"),
        (b"\x03\x80\x05abc", "truncated"),
        (b"\x03\x80\x82\x01", "truncated"),
        (b"\x02\x80\x01a", "garbage"),  # protocolVersion 2
        (b"\x03\x85\x01a", "garbage"),  # no such content
        (b"\x03\x40\x01a", "garbage"),  # not a context tag
        (b"\x03\x80\x80", "garbage"),  # indefinite length form
        (b"\x03\x80\x01ab", "garbage"),  # trailing octets
        (b"\x03\x82\x00", "unsupported"),  # encryptedData
        (b"\x03\x83\x01a", "unsupported"),  # signedCertificateRequest
        (b"\x03\x81\x00\x20\x80" + bytes(32), "unsupported"),  # extDataHash only
        (b"\x03\x81\x00\x40" * 9 + b"\x03\x80\x00", "unsupported"),  # nested too deep
        (b"\x03\x81\x00\x40\x03\x80\x00\x00\x00", "out-of-range"),  # empty psid
    ],
)
def test_bad_input_reasons(data: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as err:
        unwrap(data)
    assert err.value.reason == reason


def test_every_truncation_of_real_records_is_truncated() -> None:
    for record in _unsecured_records():
        for n in range(len(record)):
            with pytest.raises(DecodeError) as err:
                unwrap(record[:n])
            assert err.value.reason == "truncated"
    signed = _signed_record()
    frame = unwrap(signed).frame
    for n in range(len(signed)):
        try:  # signer and signature are not parsed: a cut there still yields the frame
            assert unwrap(signed[:n]).frame == frame
        except DecodeError as err:
            assert err.reason == "truncated"


def test_looks_like_1609() -> None:
    assert looks_like_1609(_signed_record())
    assert all(looks_like_1609(r) for r in _unsecured_records())
    assert not looks_like_1609(b"")
    assert not looks_like_1609(b"\x03")
    assert not looks_like_1609(b"\x00\x14\x80")
    assert not looks_like_1609(b"\x03\x85\x00")


def _only_decode_errors(data: bytes) -> None:
    try:
        u = unwrap(data)
    except DecodeError:
        return
    assert isinstance(u.frame, bytes)


@given(st.binary(max_size=300))
def test_random_bytes_raise_only_decode_error(data: bytes) -> None:
    _only_decode_errors(data)


@given(st.binary(max_size=60).map(lambda tail: b"\x03" + bytes([0x80 + len(tail) % 5]) + tail))
def test_random_bytes_after_a_valid_head_raise_only_decode_error(data: bytes) -> None:
    _only_decode_errors(data)


@settings(max_examples=200)
@given(st.data())
def test_mutated_real_records_raise_only_decode_error(data: st.DataObject) -> None:
    record = bytearray(data.draw(st.sampled_from([_signed_record(), *_unsecured_records()[:5]])))
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(record) - 1))
        record[pos] = data.draw(st.integers(0, 255))
    _only_decode_errors(bytes(record))


# --------------------------------------------------------------------------------------------
# Certificates (IEEE 1609.2-2016 §6.4), SignedData signer/signature (§6.3.4-§6.3.9), WSMP
# --------------------------------------------------------------------------------------------
# Expected octets below are written by hand from the ASN.1 and X.696 (COER), not produced by
# the codec under test.

KEY_X = bytes(range(1, 33))
KEY = b"\x03" + KEY_X  # compressed SEC1, y odd (the codec does no curve arithmetic)
SIG = bytes(range(100, 164))  # r || s
DIGEST8 = bytes.fromhex("0102030405060708")
FRAME = bytes.fromhex("001480ad") + bytes(40)


def _psid(p: int) -> bytes:
    body = p.to_bytes(max(1, (p.bit_length() + 7) // 8), "big")
    return bytes([len(body)]) + body


APP_0x20 = b"\x01\x01" + b"\x00" + _psid(0x20)  # SEQUENCE OF count 1, PsidSsp without ssp


def _hand_tbs(*, extra_preamble: int = 0, region: bytes = b"", assurance: bytes = b"",
              enc: bytes = b"", key: bytes = b"\x80\x80\x83" + KEY_X, ident: bytes = b"\x83",
              ext: bytes = b"", perms: bytes = APP_0x20, perm_bits: int = 0x10) -> bytes:
    """ToBeSignedCertificate (by default appPermissions {0x20}, verificationKey ecdsaNistP256
    compressed-y-1), built octet by octet."""
    preamble = perm_bits | extra_preamble  # bit 4: appPermissions
    return (bytes([preamble]) + ident + b"\xab\xcd\xef" + b"\x00\x07"  # id, cracaId, crlSeries
            + b"\x1c\x2d\x3e\x4f" + b"\x84\x00\xa8"  # start, duration hours(168)
            + region + assurance
            + perms + enc + key + ext)


def _hand_cert(tbs: bytes, *, issuer: bytes = b"\x80" + DIGEST8, sig: bytes | None = None,
               ctype: int = 0) -> bytes:
    sig = b"\x80\x80" + SIG if sig is None else sig
    return (b"\x80" if sig else b"\x00") + bytes([3, ctype]) + issuer + tbs + sig


def test_certificate_build_matches_hand_encoding() -> None:
    tbs = build_tbs_certificate(verify_key=KEY, start_time32=0x1C2D3E4F, duration_s=168 * 3600,
                                app_psids=(0x20,), craca_id=b"\xab\xcd\xef", crl_series=7)
    # 168 h: the builder picks the finest unit that holds it exactly, 10080 minutes
    assert tbs == _hand_tbs().replace(b"\x84\x00\xa8", b"\x83\x27\x60")
    raw = build_certificate(tbs, issuer_digest=DIGEST8, signature=SIG)
    assert raw == _hand_cert(tbs)


def test_certificate_round_trip() -> None:
    tbs = build_tbs_certificate(verify_key=KEY, start_time32=600_000_000, duration_s=7 * 86400,
                                name="aa.catc.example", issue_psids=(0x20, 0x204097))
    raw = build_certificate(tbs, issuer_digest=DIGEST8, signature=SIG)
    cert, used = parse_certificate(raw + b"tail")
    assert used == len(raw)
    assert isinstance(cert, Certificate)
    assert (cert.raw, cert.tbs, cert.canonical) == (raw, tbs, raw)
    assert (cert.cert_type, cert.issuer_kind, cert.issuer_digest) == (
        "explicit", "sha256AndDigest", DIGEST8)
    assert (cert.name, cert.start_time32, cert.duration_s) == (
        "aa.catc.example", 600_000_000, 7 * 86400)
    assert cert.end_time32 == 600_000_000 + 7 * 86400
    assert (cert.app_psids, cert.issue_psids, cert.issue_all) == ((), (0x20, 0x204097), False)
    assert (cert.verify_key, cert.signature, cert.signature_r_form) == (KEY, SIG, "x-only")
    assert cert.unsupported is None
    assert cert.hashed_id8 == hashlib.sha256(raw).digest()[-8:]
    # rebuilding from the parsed fields reproduces the octets
    again = build_tbs_certificate(verify_key=cert.verify_key, start_time32=cert.start_time32,
                                  duration_s=cert.duration_s, name=cert.name,
                                  issue_psids=cert.issue_psids)
    assert build_certificate(again, issuer_digest=cert.issuer_digest,
                             signature=cert.signature) == raw


def test_self_signed_issue_all_certificate() -> None:
    tbs = build_tbs_certificate(verify_key=b"\x02" + KEY_X, start_time32=1, duration_s=65535,
                                name="root", issue_psids=ISSUE_ALL, issue_chain=(2, 0))
    raw = build_certificate(tbs, issuer_digest=None, signature=SIG)
    assert raw[:5] == b"\x80\x03\x00\x81\x00"  # signature present, v3, explicit, self sha256
    cert, _ = parse_certificate(raw)
    assert (cert.issuer_kind, cert.issuer_digest, cert.issue_all, cert.issue_psids) == (
        "self", None, True, ())
    assert cert.issue_chain == (2, 0)
    assert cert.duration_s == 65535 and cert.verify_key == b"\x02" + KEY_X


@pytest.mark.parametrize(("seconds", "tag"), [
    (1, 0x82), (65535, 0x82), (65535 * 60, 0x83), (3600 * 65535, 0x84), (216000 * 1093, 0x85),
    (31556952 * 2, 0x86),
])
def test_duration_units(seconds: int, tag: int) -> None:
    tbs = build_tbs_certificate(verify_key=KEY, start_time32=0, duration_s=seconds,
                                app_psids=(0x20,))
    assert tbs[11] == tag  # preamble, id none, cracaId, crlSeries, start
    cert, _ = parse_certificate(build_certificate(tbs, issuer_digest=DIGEST8, signature=SIG))
    assert cert.duration_s == seconds


def test_unencodable_certificate_fields() -> None:
    with pytest.raises(EncodeError):
        build_tbs_certificate(verify_key=KEY, start_time32=0, duration_s=65537, app_psids=(1,))
    with pytest.raises(EncodeError):
        build_tbs_certificate(verify_key=KEY[:20], start_time32=0, duration_s=60, app_psids=(1,))
    with pytest.raises(EncodeError):  # no permissions at all: forbidden by §6.4.8
        build_tbs_certificate(verify_key=KEY, start_time32=0, duration_s=60)
    with pytest.raises(EncodeError):
        build_certificate(b"\x10", issuer_digest=b"short", signature=SIG)


def test_parse_all_optional_certificate_fields() -> None:
    """region (every GeographicRegion form), assuranceLevel, linkageData, encryptionKey,
    canRequestRollover, an extension addition, an uncompressed key and a compressed r."""
    regions = [
        b"\x80" + bytes(8) + b"\x01\x00",  # circularRegion
        b"\x81\x01\x02" + bytes(32),  # rectangularRegion x2
        b"\x82\x01\x03" + bytes(24),  # polygonalRegion, 3 points
        b"\x83\x01\x03" + b"\x80\x03\x48"  # identifiedRegion: countryOnly 840,
        + b"\x81\x03\x48\x01\x02\x06\x30"  # countryAndRegions 840 {6, 48},
        + b"\x82\x03\x48\x01\x01\x06\x01\x01\x00\x01",  # countryAndSubregions 840 {6:{1}}
        b"\x84\x03abc",  # an extension alternative: skipped as an open type
    ]
    linkage = b"\x80\x80\x00\x05" + bytes(9) + bytes(4) + bytes(9)  # with group-linkage-value
    enc = b"\x00\x80\x82" + KEY_X  # aes128Ccm, eciesNistP256 compressed-y-0
    uncompressed = b"\x80\x80\x84" + KEY_X + bytes(31) + b"\x01"  # y odd -> compressed-y-1
    for region in regions:
        tbs = _hand_tbs(extra_preamble=0x80 | 0x40 | 0x20 | 0x02 | 0x01, region=region,
                        assurance=b"\xe0", enc=enc, key=uncompressed, ident=linkage,
                        ext=b"\x02\x07\x80\x01\x00")  # extension bitmap 1 bit set: flags
        raw = _hand_cert(tbs, sig=b"\x80\x83" + SIG)  # r as compressed-y-1
        cert, used = parse_certificate(raw)
        assert used == len(raw)
        assert cert.verify_key == KEY and cert.signature == SIG
        assert (cert.signature_r_form, cert.app_psids, cert.name) == ("compressed-y-1", (0x20,),
                                                                      None)
        # §6.4.3 canonical form: key compressed, r x-only; HashedId8 over that form
        canonical = _hand_cert(_hand_tbs(
            extra_preamble=0xE3, region=region, assurance=b"\xe0", enc=enc, ident=linkage,
            ext=b"\x02\x07\x80\x01\x00"))
        assert cert.canonical == canonical and cert.raw == raw
        assert cert.tbs == canonical[12:-66]
        assert cert.hashed_id8 == hashlib.sha256(canonical).digest()[-8:]


@pytest.mark.parametrize(("raw", "reason"), [
    (_hand_cert(_hand_tbs(key=b"\x80\x81\x83" + KEY_X)), "unsupported"),  # brainpool key
    (_hand_cert(_hand_tbs(key=b"\x80\x83\x21\x03" + KEY_X)), "unsupported"),  # ecdsaNistP384
    (_hand_cert(_hand_tbs(key=b"\x81\x82" + KEY_X), sig=b"", ctype=1), "unsupported"),  # implicit
    (_hand_cert(_hand_tbs(), ctype=2), "unsupported"),  # unknown CertificateType
    (_hand_cert(_hand_tbs(), issuer=b"\x82\x08" + DIGEST8), "unsupported"),  # sha384AndDigest
    (_hand_cert(_hand_tbs(), sig=b"\x81\x80" + SIG), "unsupported"),  # brainpool signature
    (_hand_cert(_hand_tbs(key=b"\x80\x80\x80" + KEY_X)), "garbage"),  # x-only public key
    (_hand_cert(_hand_tbs(key=b"\x80\x80\x85" + KEY_X)), "garbage"),  # no such point form
    (_hand_cert(_hand_tbs(), sig=b"\x80\x81" + SIG[32:]), "garbage"),  # r is "fill"
    (_hand_cert(_hand_tbs(key=b"\x81\x82" + KEY_X)), "garbage"),  # explicit, but implicit key
    (_hand_cert(_hand_tbs(), sig=b""), "garbage"),  # explicit without signature
    (b"\x80\x02" + _hand_cert(_hand_tbs())[2:], "garbage"),  # version 2
    (b"\xc0" + _hand_cert(_hand_tbs())[1:], "garbage"),  # preamble padding bit
    (_hand_cert(_hand_tbs(perms=b"", perm_bits=0)), "garbage"),  # no permissions at all
    (_hand_cert(_hand_tbs().replace(b"\x84\x00\xa8", b"\x87\x00\xa8")), "garbage"),  # duration
    (_hand_cert(_hand_tbs(ident=b"\x81\x02\xff\xfe")), "garbage"),  # name not UTF-8
    (_hand_cert(_hand_tbs(ident=b"\x82\x00")), "garbage"),  # empty binaryId
    (_hand_cert(_hand_tbs().replace(b"\x01\x01\x00\x01\x20", b"\x01\x01\x00\x00")),
     "out-of-range"),  # empty psid
    (_hand_cert(_hand_tbs().replace(b"\x01\x01\x00\x01\x20", b"\x02\x10\x00")),
     "unsupported"),  # 4096 appPermissions entries
])
def test_bad_certificates(raw: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as err:
        parse_certificate(raw)
    assert err.value.reason == reason


def test_every_truncated_certificate_is_truncated() -> None:
    tbs = build_tbs_certificate(verify_key=KEY, start_time32=5, duration_s=60, name="x" * 200,
                                app_psids=(0x20, 0x80), issue_psids=(0x20,))
    raw = build_certificate(tbs, issuer_digest=DIGEST8, signature=SIG)
    for n in range(len(raw)):
        with pytest.raises(DecodeError) as err:
            parse_certificate(raw[:n])
        assert err.value.reason == "truncated", n


def _cert(**kw: Any) -> bytes:
    fields = {"verify_key": KEY, "start_time32": 5, "duration_s": 60, "app_psids": (0x20,)}
    return build_certificate(build_tbs_certificate(**{**fields, **kw}), issuer_digest=DIGEST8,
                             signature=SIG)


def test_signed_data_hand_encoding() -> None:
    tbs = tbs_data(FRAME, 0x20, 0x0102030405060708)
    assert tbs == (b"\x40" + b"\x03\x80" + bytes([len(FRAME)]) + FRAME  # payload.data
                   + b"\x40\x01\x20" + bytes.fromhex("0102030405060708"))  # headerInfo
    data = build_signed(FRAME, generation_time_us=0x0102030405060708,
                        signer=("digest", DIGEST8), signature=SIG)
    assert data == b"\x03\x81\x00" + tbs + b"\x80" + DIGEST8 + b"\x80\x80" + SIG


def test_signed_data_round_trip_digest_signer() -> None:
    data = build_signed(FRAME, psid=0x20, generation_time_us=123_456,
                        signer=("digest", DIGEST8), signature=SIG)
    u = unwrap(data)
    assert (u.frame, u.security, u.psid, u.generation_time_us) == (FRAME, "signed", 0x20, 123_456)
    assert (u.hash_id, u.signer_kind, u.signer_digest, u.signer_certs) == (
        "sha256", "digest", DIGEST8, ())
    assert (u.signature, u.signature_r_form, u.unsupported) == (SIG, "x-only", None)
    assert u.tbs_data == tbs_data(FRAME, 0x20, 123_456) == data[3:-75]


def test_signed_data_round_trip_certificate_signer() -> None:
    cert_raw = _cert(name="pseudonym")
    data = build_signed(FRAME, psid=0x20, generation_time_us=7,
                        signer=("certificate", cert_raw), signature=SIG)
    u = unwrap(data)
    cert, _ = parse_certificate(cert_raw)
    assert u.signer_kind == "certificate" and u.signer_certs == (cert,)
    assert u.signer_digest == cert.hashed_id8
    assert u.tbs_data == data[3 : 3 + len(u.tbs_data)]
    assert data[3 + len(u.tbs_data):] == b"\x81\x01\x01" + cert_raw + b"\x80\x80" + SIG
    chain = build_signed(FRAME, generation_time_us=7, signer=("certificate", [cert_raw, cert_raw]),
                         signature=SIG)
    assert unwrap(chain).signer_certs == (cert, cert)
    selfsigned = unwrap(build_signed(FRAME, generation_time_us=7, signer=("self", None),
                                     signature=SIG))
    assert (selfsigned.signer_kind, selfsigned.signer_digest) == ("self", None)


@pytest.mark.parametrize(("rsig", "form"), [
    (b"\x80" + SIG[:32], "x-only"),
    (b"\x82" + SIG[:32], "compressed-y-0"),
    (b"\x83" + SIG[:32], "compressed-y-1"),
    (b"\x84" + SIG[:32] + bytes(32), "uncompressed"),
])
def test_signature_r_forms(rsig: bytes, form: str) -> None:
    data = b"\x03\x81\x00" + tbs_data(FRAME, 0x20, 1) + b"\x80" + DIGEST8 + b"\x80" + rsig
    u = unwrap(data + SIG[32:])
    assert (u.signature, u.signature_r_form) == (SIG, form)


def test_header_info_with_every_optional_field() -> None:
    header = (b"\x7e" + _psid(0x20) + (5).to_bytes(8, "big")  # generationTime
              + (9).to_bytes(8, "big")  # expiryTime
              + bytes(10)  # generationLocation
              + b"abc"  # p2pcdLearningRequest
              + b"\x00abc\x00\x01"  # missingCrlIdentifier
              + b"\x80\x00\x80\x84" + KEY_X + bytes(32))  # encryptionKey public, uncompressed
    header_ext = b"\xfe" + header[1:] + b"\x02\x06\xc0\x02\x01\x02\x01\x00"  # 2 ext additions
    symmetric = b"\x42" + _psid(0x20) + (5).to_bytes(8, "big") + b"\x81\x80" + bytes(16)
    for hdr in (header, header_ext, symmetric):
        tbs = b"\x40" + wrap_unsecured(FRAME) + hdr
        u = unwrap(b"\x03\x81\x00" + tbs + b"\x80" + DIGEST8 + b"\x80\x80" + SIG)
        assert (u.frame, u.psid, u.generation_time_us, u.tbs_data, u.signature) == (
            FRAME, 0x20, 5, tbs, SIG)
    assert unwrap(b"\x03\x81\x00\x40" + wrap_unsecured(FRAME) + header
                  + b"\x80" + DIGEST8 + b"\x80\x80" + SIG).expiry_time_us == 9


@pytest.mark.parametrize(("tail", "note"), [
    (b"\x80" + DIGEST8 + b"\x81\x80" + SIG, "ecdsaBrainpoolP256r1"),  # brainpool signature
    (b"\x80" + DIGEST8 + b"\x83\x61" + b"\x80" + bytes(96), "ecdsaNistP384"),  # open type
    (b"\x81\x01\x01" + _hand_cert(_hand_tbs(key=b"\x81\x82" + KEY_X), sig=b"", ctype=1)
     + b"\x80\x80" + SIG, "implicit"),
])
def test_unsupported_crypto_still_unwraps(tail: bytes, note: str) -> None:
    """A signer or signature this codec cannot verify is noted, not fatal: the frame is
    still delivered (OBUs sniffing deployed traffic see implicit certificates)."""
    u = unwrap(b"\x03\x81\x00" + tbs_data(FRAME, 0x20, 1) + tail)
    assert u.frame == FRAME and u.unsupported is not None and note in u.unsupported


@pytest.mark.parametrize(("tail", "reason"), [
    (b"\x80" + DIGEST8 + b"\x80\x81" + SIG[32:], "garbage"),  # r is "fill"
    (b"\x80" + DIGEST8 + b"\x80\x85" + SIG, "garbage"),  # no such EccP256CurvePoint
    (b"\x80" + DIGEST8 + b"\x80\x80" + SIG[:40], "truncated"),  # short signature
    (b"\x81\x01\x00" + b"\x80\x80" + SIG, "garbage"),  # empty certificate sequence
    (b"\x81\x01\x09" + b"\x80\x80" + SIG, "unsupported"),  # nine certificates
    (b"\x81\x01\x01" + _hand_cert(_hand_tbs())[:50], "truncated"),
    (b"\x20" + DIGEST8, "garbage"),  # not a CHOICE tag
])
def test_bad_signer_or_signature(tail: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as err:
        unwrap(b"\x03\x81\x00" + tbs_data(FRAME, 0x20, 1) + tail)
    assert err.value.reason == reason


def test_every_truncation_of_a_certificate_signed_message() -> None:
    data = build_signed(FRAME, generation_time_us=1, signer=("certificate", _cert(name="n")),
                        signature=SIG)
    for n in range(len(data)):
        with pytest.raises(DecodeError) as err:
            unwrap(data[:n])
        assert err.value.reason == "truncated", n


@given(st.binary(max_size=400))
def test_random_bytes_into_parse_certificate(data: bytes) -> None:
    try:
        cert, used = parse_certificate(data)
    except DecodeError:
        return
    assert 0 < used <= len(data) and cert.raw == data[:used]


@settings(max_examples=300)
@given(st.data())
def test_mutated_certificate_messages_raise_only_decode_error(data: st.DataObject) -> None:
    msg = bytearray(build_signed(FRAME, generation_time_us=1,
                                 signer=("certificate", _cert(name="n", issue_psids=(1,))),
                                 signature=SIG))
    for _ in range(data.draw(st.integers(1, 4))):
        msg[data.draw(st.integers(0, len(msg) - 1))] = data.draw(st.integers(0, 255))
    _only_decode_errors(bytes(msg))


# WSMP (IEEE 1609.3-2016 §8.3) ---------------------------------------------------------------


@pytest.mark.parametrize(("psid", "p_encoded"), [
    (0x20, b"\x20"), (0x7F, b"\x7f"), (0x80, b"\x80\x00"), (0x4070, b"\xbf\xf0"),
    (0x407F, b"\xbf\xff"), (0x4080, b"\xc0\x00\x00"), (0x204080, b"\xe0\x00\x00\x00"),
])
def test_wsmp_psid_p_encoding(psid: int, p_encoded: bytes) -> None:
    wsm = wrap_wsmp(b"xyz", psid=psid)
    assert wsm == b"\x03\x00" + p_encoded + b"\x03xyz"
    assert unwrap_wsmp(wsm) == (b"xyz", psid)


@pytest.mark.parametrize("size", [0, 1, 127, 128, 300, 16383])
def test_wsmp_lengths(size: int) -> None:
    payload = bytes(i % 7 for i in range(size))
    wsm = wrap_wsmp(payload)
    length = bytes([size]) if size < 128 else (0x8000 | size).to_bytes(2, "big")
    assert wsm == b"\x03\x00\x20" + length + payload
    assert unwrap_wsmp(wsm + bytes(20)) == (payload, 0x20)  # Ethernet padding is ignored
    assert looks_like_wsmp(wsm)


def test_wsmp_with_information_elements() -> None:
    # N-header option indicator set: count 2 (channel 172, data rate 12), TPID 1 with a
    # T-header extension (channel load) after the PSID.
    wsm = (b"\x0b" + b"\x02" + b"\x0f\x01\xac" + b"\x10\x01\x0c" + b"\x01" + b"\x20"
           + b"\x01\x17\x01\x05" + b"\x02ab")
    assert unwrap_wsmp(wsm) == (b"ab", 0x20)
    assert looks_like_wsmp(wsm)


@pytest.mark.parametrize(("data", "reason"), [
    (b"", "truncated"),
    (b"\x03\x00\x20\x05ab", "truncated"),
    (b"\x03\x00\x20\xc0\x01", "garbage"),  # length with 0b11 prefix
    (b"\x03\x00\xf0\x01a", "garbage"),  # psid prefix 1111
    (b"\x02\x00\x20\x01a", "unsupported"),  # WSMP version 2
    (b"\x13\x00\x20\x01a", "unsupported"),  # subtype 1
    (b"\x03\x02\x20\x01a", "unsupported"),  # TPID 2 (ITS port numbers)
])
def test_wsmp_errors(data: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as err:
        unwrap_wsmp(data)
    assert err.value.reason == reason


def test_wsmp_encode_limits_and_sniff() -> None:
    with pytest.raises(EncodeError):
        wrap_wsmp(bytes(16384))
    with pytest.raises(EncodeError):
        wrap_wsmp(b"", psid=0x1020407F + 1)
    assert not looks_like_wsmp(b"\x03\x81\x00\x40")  # an Ieee1609Dot2Data is not a WSM
    assert not looks_like_wsmp(b"\x00\x14")
    signed = build_signed(FRAME, generation_time_us=1, signer=("digest", DIGEST8), signature=SIG)
    assert unwrap(unwrap_wsmp(wrap_wsmp(signed))[0]).frame == FRAME


def test_open_envelope_keeps_the_wsmp_psid() -> None:
    signed = build_signed(FRAME, generation_time_us=1, signer=("digest", DIGEST8), signature=SIG)
    for psid in (0x20, 0x87, 0x204097):
        frame, u = open_envelope(wrap_wsmp(signed, psid=psid))
        assert frame == FRAME and u is not None and u.wsmp_psid == psid
        assert u == dataclasses.replace(unwrap(signed), wsmp_psid=psid)
    frame, u = open_envelope(signed)  # no WSM: no WSMP PSID
    assert frame == FRAME and u is not None and u.wsmp_psid is None
    assert open_envelope(FRAME) == (FRAME, None)  # a bare UPER frame
    assert open_envelope(wrap_wsmp(FRAME)) == (FRAME, None)


@pytest.mark.parametrize("data", [
    b"\x02\x00\x20\x05" + b"\x03\x80\x02ab",  # a WSM of version 2 around unsecured data
    b"\x00\x01\x20\x01a",  # version 0, TPID 1
    b"\x02\x80\x02ab",  # an Ieee1609Dot2Data of protocolVersion 2
    b"\x04\x81\x00\x40",  # protocolVersion 4, signedData
    wrap_wsmp(b"\x02\x80\x02ab"),  # version 3 WSM, protocolVersion 2 inside
])
def test_open_envelope_refuses_other_versions(data: bytes) -> None:
    """A WSMP header or an ``Ieee1609Dot2Data`` of another version than 3 is refused
    (``unsupported``), not taken for a bare UPER frame."""
    with pytest.raises(DecodeError) as err:
        open_envelope(data)
    assert err.value.reason == "unsupported"
    assert "version" in str(err.value).lower()


@given(st.binary(max_size=80))
def test_random_bytes_into_open_envelope(data: bytes) -> None:
    try:
        frame, u = open_envelope(data)
    except DecodeError:
        return
    assert isinstance(frame, bytes) and (u is None or u.frame == frame)


@given(st.binary(max_size=80))
def test_random_bytes_into_unwrap_wsmp(data: bytes) -> None:
    try:
        payload, psid = unwrap_wsmp(data)
    except DecodeError:
        return
    assert isinstance(payload, bytes) and psid >= 0


# --------------------------------------------------------------------------------------------
# Open types and extension additions (X.696 §16.4), and the codec/service split
# --------------------------------------------------------------------------------------------


def _with_payload_tail(preamble: int, tail: bytes) -> bytes:
    """SignedData whose SignedDataPayload has ``preamble`` and ``tail`` after its data."""
    return (b"\x03\x81\x00" + bytes([preamble]) + wrap_unsecured(FRAME) + tail
            + b"\x00\x01\x20" + b"\x80" + DIGEST8 + b"\x80\x80" + SIG)


@pytest.mark.parametrize("ext_hash", [b"\x80" + bytes(32), b"\x81\x03abc", b"\x82\x00"])
def test_ext_data_hash_alternatives_are_skipped(ext_hash: bytes) -> None:
    u = unwrap(_with_payload_tail(0x60, ext_hash))
    assert (u.frame, u.psid) == (FRAME, 0x20)


@pytest.mark.parametrize(("ext_hash", "message"), [
    (b"\x83", "garbage: 1609.2 extDataHash: Error in path (parsing) -> value\n"
              "Error field was activated during parsing"),
    (b"\x81\x85", "garbage: 1609.2 length determinant with 5 length octets"),
])
def test_ext_data_hash_errors(ext_hash: bytes, message: str) -> None:
    with pytest.raises(DecodeError) as err:
        unwrap(_with_payload_tail(0x60, ext_hash))
    assert str(err.value) == message


def test_ext_data_hash_cut_short() -> None:
    data = _with_payload_tail(0x60, b"")[:-78]  # ends where the extDataHash starts
    with pytest.raises(DecodeError) as err:
        unwrap(data)
    assert str(err.value) == "truncated: 1609.2 extDataHash: input ends early"


def test_extension_additions_are_skipped_as_open_types() -> None:
    additions = b"\x02\x06\xc0" + b"\x01a" + b"\x02bc"  # bitmap: 2 bits used, both set
    u = unwrap(_with_payload_tail(0xC0, additions))
    assert (u.frame, u.psid) == (FRAME, 0x20)
    data = b"\x03\x81\x00\xc0" + wrap_unsecured(FRAME) + additions[:-3]
    with pytest.raises(DecodeError) as err:
        unwrap(data)
    assert str(err.value) == "truncated: 1609.2 SignedDataPayload extensions: input ends early"


def test_the_codec_loads_no_cryptography() -> None:
    """Parsing and building 1609.2 needs no crypto library: signing and verifying are
    catc.security's, apart from the codec."""
    code = ("import sys, catc.j2735, catc.j2735.ieee1609, catc.j2735.obulog, catc.j2735.sniff; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'cryptography'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"
