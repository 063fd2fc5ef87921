"""OBU log records against the ODE's own decoding of the same files."""

from __future__ import annotations

import json
import re
import struct
from datetime import datetime
from functools import cache

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catc.errors import DecodeError
from catc.j2735.ieee1609 import wrap_unsecured
from catc.j2735.obulog import LogRecord, iter_records, looks_like_obulog
from tests.conftest import shared_path

FRAME = bytes.fromhex("001480ad") + bytes(20)


@cache
def _vector(name: str) -> bytes:
    return shared_path("jpo-ode-bsm-vectors", name).read_bytes()


def _ms(iso: str) -> int:
    """ODE recordGeneratedAt ("2018-05-01T16:04:23.694Z", maybe "[UTC]") as Unix ms."""
    return round(
        datetime.fromisoformat(iso.removesuffix("[UTC]").replace("Z", "+00:00")).timestamp() * 1000
    )


def _value(text: str) -> float | None:
    return None if text == "unavailable" else float(text)


def _location(rec: LogRecord) -> tuple:
    return (rec.lat, rec.lon, rec.elevation_m, rec.speed_mps, rec.heading_deg)


def _location_pack(lat: int, lon: int, elev: int, speed: int, heading: int) -> bytes:
    return struct.pack("<iiiHH", lat, lon, elev, speed, heading)


def test_bsm_log_during_event_matches_ode_json() -> None:
    records = list(iter_records(_vector("bsmLogDuringEvent.bin")))
    lines = _vector("bsmLogDuringEvent.json").decode().splitlines()
    assert len(records) == len(lines) == 222
    # The ODE wrote its JSON lines newest first; serialId.recordId is the record's
    # position in the .bin, so that is how lines and records are paired.
    by_id = {}
    for line in lines:
        meta = json.loads(line)["metadata"]
        by_id[meta["serialId"]["recordId"]] = meta
    assert sorted(by_id) == list(range(222))
    for i, rec in enumerate(records):
        meta = by_id[i]
        loc = meta["receivedMessageDetails"]["locationData"]
        expected = tuple(
            _value(loc[k]) for k in ("latitude", "longitude", "elevation", "speed", "heading")
        )
        assert _location(rec) == expected, i
        assert rec.direction == meta["bsmSource"]
        assert rec.kind == meta["recordType"] == "bsmLogDuringEvent"
        assert rec.security_result == meta["securityResultCode"]
        assert rec.rx_source is None
        assert round(rec.utc_time * 1000) == _ms(meta["recordGeneratedAt"]), i
        assert rec.frame[:2] == b"\x00\x14"
        assert rec.payload[:2] == b"\x03\x80"


def test_rx_msg_2017_layout_and_ode_decoder_input() -> None:
    records = list(iter_records(_vector("rxMsg_BSM.bin")))
    assert len(records) == 228
    assert {r.kind for r in records} == {"rxMsg"}
    assert {r.rx_source for r in records} == {"RV", "SNMP"}
    assert sum(r.frame[:2] == b"\x00\x14" for r in records) == 227
    xml = _vector("rxMsg_BSM_Asn1DecoderInput.xml").decode()
    frame = bytes.fromhex(re.search(r"<bytes>(\w+)</bytes>", xml).group(1))
    (match,) = [r for r in records if r.frame == frame]
    fields = dict(
        re.findall(r"<(latitude|longitude|elevation|speed|heading|rxSource)>([^<]+)<", xml)
    )
    expected = tuple(
        float(fields[k]) for k in ("latitude", "longitude", "elevation", "speed", "heading")
    )
    assert _location(match) == expected
    assert match.rx_source == fields["rxSource"] == "SNMP"
    generated_at = re.search(r"<recordGeneratedAt>([^<]+)<", xml).group(1)
    assert round(match.utc_time * 1000) == _ms(generated_at)
    assert match.security_result == 0  # verificationStatus: the ODE says validSignature false
    assert match.payload == frame  # this one was logged without a 1609.2 wrapper


def test_explicit_kinds() -> None:
    data = _vector("bsmLogDuringEvent.bin")
    assert [r.kind for r in iter_records(data, "bsmTx")] == ["bsmTx"] * 222
    assert len(list(iter_records(_vector("rxMsg_BSM.bin"), "rxMsg"))) == 228
    with pytest.raises(DecodeError) as err:
        list(iter_records(data, "spatTx"))
    assert err.value.reason == "unsupported"


@pytest.mark.parametrize(
    ("name", "kind"),
    [
        ("bsmLogDuringEvent.bin", None),
        ("bsmLogDuringEvent.bin", "bsmLogDuringEvent"),
        ("rxMsg_BSM.bin", None),
        ("rxMsg_BSM.bin", "rxMsg"),
    ],
)
def test_truncated_file_yields_complete_records_then_raises(name: str, kind: str | None) -> None:
    data = _vector(name)
    complete = list(iter_records(data, kind))
    for cut in (1, 5, 100):
        got = []
        with pytest.raises(DecodeError) as err:
            for rec in iter_records(data[:-cut], kind):
                got.append(rec)
        assert err.value.reason == "truncated"
        assert got == complete[:-1]


def test_bsm_receiver_datagram_is_one_bsm_tx_record() -> None:
    data = bytes.fromhex(_vector("BsmReceiverTest_ValidBSM.txt").decode().strip())
    assert looks_like_obulog(data)
    (rec,) = iter_records(data, "bsmTx")
    expected = json.loads(_vector("BsmReceiverTest_ValidBSM_expected.json"))["metadata"]["asn1"]
    assert rec.frame == bytes.fromhex(expected)
    assert (rec.direction, rec.security_result) == ("EV", "success")
    assert rec.lat == pytest.approx(40.5659938) and rec.lon == pytest.approx(-105.0317754)


def test_current_rx_msg_and_dn_msg_layouts_are_detected() -> None:
    payload = wrap_unsecured(FRAME)
    loc = _location_pack(405_000_000, -1_050_000_000, 15000, 8191, 28800)
    time = struct.pack("<IH", 1_600_000_000, 250)
    length = struct.pack("<H", len(payload))
    rx = (b"\x02" + loc + time + b"\x00" + length + payload) * 3
    recs = list(iter_records(rx))
    assert [(r.kind, r.rx_source, r.direction) for r in recs] == [("rxMsg", "RV", None)] * 3
    assert (recs[0].speed_mps, recs[0].heading_deg) == (None, None)
    assert recs[0].utc_time == 1_600_000_000.25
    dn = (loc + time + b"\x01" + length + payload) * 2
    recs = list(iter_records(dn))
    assert [(r.kind, r.security_result, r.frame) for r in recs] == [("dnMsg", "unknown", FRAME)] * 2


def test_unavailable_and_out_of_range_header_fields() -> None:
    payload = wrap_unsecured(FRAME)
    tail = struct.pack("<IHBH", 1_600_000_000, 0, 0, len(payload)) + payload
    unavailable = _location_pack(900000001, 1800000001, -4096, 8191, 28800)
    (rec,) = iter_records(b"\x01" + unavailable + tail, "bsmLogDuringEvent")
    assert _location(rec) == (None,) * 5 and rec.direction == "RV"
    for bad in (
        b"\x02" + unavailable + tail,  # direction
        b"\x00" + _location_pack(900000002, 0, 0, 0, 0) + tail,
        b"\x00" + _location_pack(0, 0, 0, 8192, 0) + tail,
        b"\x00" + unavailable + struct.pack("<IHBH", 0, 1000, 0, len(payload)) + payload,
        b"\x00" + unavailable + struct.pack("<IHBH", 0, 0, 99, len(payload)) + payload,
    ):
        with pytest.raises(DecodeError) as err:
            list(iter_records(bad, "bsmLogDuringEvent"))
        assert err.value.reason == "out-of-range"


def test_not_a_log() -> None:
    assert list(iter_records(b"")) == []
    for data in (b"\xff" * 64, bytes(range(256)), wrap_unsecured(FRAME), _vector("bsm.uper")):
        assert not looks_like_obulog(data)
        with pytest.raises(DecodeError) as err:
            list(iter_records(data))
        assert err.value.reason == "garbage"
    assert looks_like_obulog(_vector("bsmLogDuringEvent.bin"))
    assert looks_like_obulog(_vector("rxMsg_BSM.bin"))


def _only_decode_errors(data: bytes, kind: str | None = None) -> None:
    try:
        for rec in iter_records(data, kind):
            assert isinstance(rec.frame, bytes)
    except DecodeError:
        pass
    assert isinstance(looks_like_obulog(data), bool)


@given(st.binary(max_size=200), st.sampled_from([None, "bsmTx", "rxMsg", "dnMsg"]))
def test_random_bytes_raise_only_decode_error(data: bytes, kind: str | None) -> None:
    _only_decode_errors(data, kind)


@settings(max_examples=150)
@given(st.data())
def test_mutated_logs_raise_only_decode_error(data: st.DataObject) -> None:
    name = data.draw(st.sampled_from(["bsmLogDuringEvent.bin", "rxMsg_BSM.bin"]))
    log = bytearray(_vector(name)[:700])
    for _ in range(data.draw(st.integers(1, 4))):
        log[data.draw(st.integers(0, len(log) - 1))] = data.draw(st.integers(0, 255))
    _only_decode_errors(bytes(log))
