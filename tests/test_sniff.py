"""Content detection for ``captures decode FILE`` over every ODE test vector."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from catc.errors import DecodeError
from catc.j2735.ieee1609 import wrap_unsecured
from catc.j2735.sniff import extract_frames
from tests.conftest import shared_path

FRAME = bytes.fromhex("001480ad") + bytes(range(30))

#: file -> (container, number of frames, first frame starts with); None: not a capture
VECTORS: dict[str, tuple[str, int, str] | None] = {
    "128_bsms.json": ("ode-json", 0, ""),  # decoded values only
    "BSM_JSON_J2735_2024_ExpectedTranslation.json": ("ode-json", 0, ""),
    "BSM_XML_J2735_2024_ToTranslate.xml": ("ode-xml", 0, ""),
    "BsmReceiverTest_ValidBSM.txt": ("hex", 1, "001480b8"),
    "BsmReceiverTest_ValidBSM_expected.json": ("ode-json", 1, "001480b8"),
    "PROVENANCE.md": None,
    "bsm.json": ("ode-json", 0, ""),
    "bsm.uper": ("uper", 1, "59af"),  # bare BasicSafetyMessage, no MessageFrame
    "bsmLogDuringEvent.bin": ("obulog", 222, "0014"),
    "bsmLogDuringEvent.json": ("ode-json", 0, ""),
    "bsmLogDuringEvent_Asn1DecoderOutput.xml": ("ode-xml", 0, ""),
    "bsm_uper.hex": ("hex", 1, "4014"),
    "bsm_uper1.hex": ("hex", 1, "001480ad"),
    "decoder-input-bsm.json": ("ode-json", 1, "001480ad"),
    "decoder-output-bsm.xml": ("ode-xml", 1, "001480b8"),
    "expected-bsm.json": ("ode-json", 1, "001480b8"),
    "expected-bsm.xml": ("ode-xml", 1, "001480ad"),
    "rxMsg_BSM.bin": ("obulog", 228, "00"),  # 227 BSMs and a TIM
    "rxMsg_BSM_Asn1DecoderInput.xml": ("ode-xml", 1, "001f"),  # a TIM
    "rxMsg_BSM_Asn1DecoderOutput.xml": ("ode-xml", 0, ""),
}


def test_the_table_covers_every_vector(vectors_dir) -> None:  # type: ignore[no-untyped-def]
    assert sorted(p.name for p in vectors_dir.iterdir()) == sorted(VECTORS)


@pytest.mark.parametrize("name", sorted(VECTORS))
def test_every_vector_is_classified(name: str) -> None:
    data = shared_path("jpo-ode-bsm-vectors", name).read_bytes()
    if VECTORS[name] is None:
        with pytest.raises(DecodeError) as err:
            extract_frames(data)
        assert err.value.reason == "garbage"
        return
    container, count, start = VECTORS[name]
    found = extract_frames(data)
    assert len(found) == count
    for i, x in enumerate(found):
        assert x.container == container
        assert x.meta["index"] == i and x.meta["layers"][0] == container
        assert x.frame.hex().startswith(start)


def test_bsm_receiver_datagram_frame_is_the_odes() -> None:
    data = shared_path("jpo-ode-bsm-vectors", "BsmReceiverTest_ValidBSM.txt").read_bytes()
    (x,) = extract_frames(data)
    expected = shared_path("jpo-ode-bsm-vectors", "BsmReceiverTest_ValidBSM_expected.json")
    assert x.frame == bytes.fromhex(json.loads(expected.read_text())["metadata"]["asn1"])
    assert x.meta["layers"] == ["hex", "obulog", "ieee1609"]
    assert (x.meta["direction"], x.meta["record"]) == ("EV", 0)


def test_signed_json_record_meta() -> None:
    (x,) = extract_frames(shared_path("jpo-ode-bsm-vectors", "decoder-input-bsm.json").read_bytes())
    assert x.meta["layers"] == ["ode-json", "ieee1609"]
    assert (x.meta["security"], x.meta["psid"]) == ("signed", 0x20)


def test_obulog_meta_carries_the_record_header() -> None:
    found = extract_frames(shared_path("jpo-ode-bsm-vectors", "rxMsg_BSM.bin").read_bytes())
    last = found[-1]
    assert last.meta["record"] == 227 and last.meta["rx_source"] == "SNMP"
    assert last.meta["layers"] == ["obulog"]
    assert found[0].meta["layers"] == ["obulog", "ieee1609"]
    assert found[0].meta["security"] == "unsecured"


def test_binary_and_hex_forms_of_a_frame() -> None:
    wrapped = wrap_unsecured(FRAME)
    assert [(x.frame, x.container) for x in extract_frames(FRAME)] == [(FRAME, "uper")]
    assert [(x.frame, x.container) for x in extract_frames(wrapped)] == [(FRAME, "ieee1609")]
    (x,) = extract_frames(wrapped.hex().upper().encode())
    assert (x.frame, x.container, x.meta["layers"]) == (FRAME, "hex", ["hex", "ieee1609"])


def test_hex_lines() -> None:
    other = bytes.fromhex("0014") + bytes(10)
    lines = f"{FRAME.hex()}\n\n  {wrap_unsecured(other).hex()}  \r\n".encode()
    found = extract_frames(lines)
    assert [(x.frame, x.meta["line"]) for x in found] == [(FRAME, 0), (other, 1)]
    wrapped_dump = "\n".join(FRAME.hex()[i : i + 16] for i in range(0, 68, 16)).encode()
    assert [x.frame for x in extract_frames(wrapped_dump)] == [FRAME]


def test_json_lines_and_arrays_with_hex() -> None:
    records = [
        {"payload": {"data": {"bytes": FRAME.hex()}}},
        {"metadata": {"asn1": wrap_unsecured(FRAME).hex()}},
        {"metadata": {"recordType": "bsmTx"}},
    ]
    lines = "\n".join(json.dumps(r) for r in records).encode()
    for data in (lines, json.dumps(records).encode()):
        found = extract_frames(data)
        assert [(x.frame, x.meta["line"], x.meta["field"]) for x in found] == [
            (FRAME, 0, "payload.data.bytes"),
            (FRAME, 1, "metadata.asn1"),
        ]


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"  \n\t ",
        b"hello world",
        b"\xff" * 40,
        b"\x80\x01\x02",
        b"abc",  # odd number of hex digits
        b"{not json",
        b'{"foo": 1}',
        b"[1, 2]",
        b"<html><body>hi</body></html>",
        b"<OdeAsn1Data><bytes>XYZ</bytes></OdeAsn1Data>",
        b'{"payload": {"data": {"bytes": "12G4"}}}',
        b"[" * 100_000,
    ],
)
def test_garbage(data: bytes) -> None:
    with pytest.raises(DecodeError) as err:
        extract_frames(data)
    assert err.value.reason == "garbage"


@given(st.binary(max_size=200))
def test_random_bytes_raise_only_decode_error(data: bytes) -> None:
    try:
        found = extract_frames(data)
    except DecodeError:
        return
    assert all(isinstance(x.frame, bytes) for x in found)


@given(st.text(max_size=200))
def test_random_text_raises_only_decode_error(text: str) -> None:
    try:
        found = extract_frames(text.encode())
    except DecodeError:
        return
    assert all(isinstance(x.frame, bytes) for x in found)
