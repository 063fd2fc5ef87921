"""IEEE 1609.2 COER unwrap/wrap against the ODE's real records and synthetic edge cases."""

from __future__ import annotations

import json
import re
import struct
from functools import cache

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catc.errors import DecodeError
from catc.j2735.ieee1609 import Unwrapped, looks_like_1609, unwrap, wrap_unsecured
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
    # signed inside signed: the header of the layer that signs the frame is reported
    u = unwrap(_signed(_signed(wrap_unsecured(frame), psid=0x20, gen_time=7), psid=0x8F))
    assert (u.frame, u.psid, u.generation_time_us) == (frame, 0x20, 7)


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
