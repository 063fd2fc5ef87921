"""The codec against real BSMs from deployed OBUs (../shared/data/jpo-ode-bsm-vectors).

Every BSM in every file is checked: frames decode to the values the ODE decoded,
and frames re-encode bit for bit.
"""

from __future__ import annotations

import binascii
import json
import xml.etree.ElementTree as ET
from dataclasses import replace
from importlib import resources

import asn1tools
import pytest

from captures.decode import is_message_frame
from catc.bsm import (
    BSM,
    BrakeStatus,
    PathHistory,
    PathHistoryPoint,
    PathPrediction,
    PositionalAccuracy,
)
from catc.errors import DecodeError
from catc.j2735 import decode_bsm, decode_frame, encode_bsm, encode_frame
from catc.j2735.obulog import iter_records
from catc.j2735.ode import bsm_from_ode
from catc.j2735.sniff import extract_frames
from tests.bsm_compare import (
    assert_close,
    assert_matches_xer,
    assert_same_except_extras,
    expected_from_xer,
)
from tests.conftest import shared_path

VEC = "jpo-ode-bsm-vectors"

#: Part II values with every OPTIONAL absent: SpecialVehicleExtensions (extension bit and
#: 3 presence bits) and SupplementalVehicleExtensions (extension bit and 10 presence bits).
EMPTY_PART2 = {1: b"\x00", 2: b"\x00\x00"}


def frame_length(frame: bytes) -> int:
    """Octets the MessageFrame occupies (header + open type), ignoring padding after it."""
    n = frame[2]
    return 3 + n if n < 0x80 else 4 + (((n & 0x3F) << 8) | frame[3])


def assert_reencodes(frame: bytes) -> None:
    assert encode_frame(decode_frame(frame)) == frame[:frame_length(frame)]


def test_obu_log_during_event_matches_ode_record_by_record():
    records = list(iter_records(shared_path(VEC, "bsmLogDuringEvent.bin").read_bytes()))
    lines = shared_path(VEC, "bsmLogDuringEvent.json").read_text().splitlines()
    # The ODE's JSON lines are not in file order; serialId.recordId is the record index.
    by_record = {rec["metadata"]["serialId"]["recordId"]: rec["payload"]["data"]
                 for rec in map(json.loads, filter(str.strip, lines))}
    ode = [by_record[i] for i in sorted(by_record)]
    assert len(records) == len(ode) == 222
    for rec, expected in zip(records, ode, strict=True):
        bsm = decode_frame(rec.frame)
        # The 2019 ODE (schemaVersion 6) printed TransmissionState 7 ("unavailable") as
        # "NEUTRAL".  The frames hold 7: asn1tools reads it so (test below) and the 2024
        # ODE prints the same device's 7 as "UNAVAILABLE" (expected-bsm.json).
        assert expected["coreData"]["transmission"] == "NEUTRAL"
        assert bsm.transmission is None
        assert_same_except_extras(bsm, replace(bsm_from_ode(expected), transmission=None))
        assert_reencodes(rec.frame)


def test_obu_log_transmission_is_unavailable_per_reference_decoder():
    oracle = asn1tools.compile_string(
        resources.files("catc.j2735").joinpath("bsm.asn").read_text(), "uper")
    for rec in iter_records(shared_path(VEC, "bsmLogDuringEvent.bin").read_bytes()):
        value = oracle.decode("MessageFrame", rec.frame)["value"]
        assert oracle.decode("BasicSafetyMessage", value)["coreData"]["transmission"] == \
            "unavailable"


def test_xer_only_record_survives_our_encoder():
    """bsmLogDuringEvent_Asn1DecoderOutput.xml holds the ODE's XER of a 2018 record with
    no hex beside it: build the BSM from its integers, encode, decode, compare with XER."""
    root = ET.parse(shared_path(VEC, "bsmLogDuringEvent_Asn1DecoderOutput.xml")).getroot()
    xer = root.find(".//BasicSafetyMessage")
    e = expected_from_xer(xer)
    points = tuple(PathHistoryPoint(*p) for p in e["points"])
    bsm = BSM(msg_cnt=e["msg_cnt"], temp_id=int(e["id_hex"], 16), sec_mark=e["sec_mark"],
              lat=e["lat"], lon=e["lon"], elev=e["elev"], speed=e["speed"],
              heading=e["heading"],
              accuracy=PositionalAccuracy(e["semi_major"], e["semi_minor"], e["orientation"]),
              steering_angle=e["steering_angle"], accel_long=e["accel_long"],
              accel_lat=e["accel_lat"], accel_vert=e["accel_vert"], yaw_rate=e["yaw_rate"],
              brakes=BrakeStatus(wheel_brakes=e["wheel_brakes"]), width=e["width"],
              length=e["length"],
              path_history=PathHistory(points) if points else None,
              path_prediction=PathPrediction(*e["radius"]) if e["radius"] else None,
              part2_other=tuple((pid, EMPTY_PART2[pid]) for pid in e["part2_ids"] if pid != 0))
    assert e["transmission"] == "unavailable"
    assert_matches_xer(decode_frame(encode_frame(bsm)), xer)


def test_rx_msg_log_decodes_and_reencodes():
    """228 received messages: 227 BSMs and one TravelerInformation (messageId 31) that
    the ODE itself failed on (rxMsg_BSM_Asn1DecoderOutput.xml)."""
    records = list(iter_records(shared_path(VEC, "rxMsg_BSM.bin").read_bytes()))
    bsms, rejected = 0, []
    for rec in records:
        try:
            bsm = decode_frame(rec.frame)
        except DecodeError as err:
            rejected.append(err.reason)
            continue
        bsms += 1
        assert bsm.lat is not None and 40 < bsm.lat < 41.5
        assert_reencodes(rec.frame)
    assert (bsms, rejected) == (227, ["wrong-message-id"])


def test_decoder_output_xer_and_ode_json_agree_with_our_decode():
    root = ET.parse(shared_path(VEC, "decoder-output-bsm.xml")).getroot()
    frame = binascii.unhexlify("".join(root.find(".//asn1").text.split()))
    bsm = decode_frame(frame)
    assert_matches_xer(bsm, root.find(".//BasicSafetyMessage"))
    expected = json.loads(shared_path(VEC, "expected-bsm.json").read_text())["payload"]["data"]
    assert_same_except_extras(bsm, bsm_from_ode(expected))
    assert [pid for pid, _ in bsm.part2_other] == [2]  # SupplementalVehicleExtensions, kept
    assert_reencodes(frame)


def test_bare_bsm_uper_matches_ode_json():
    data = shared_path(VEC, "bsm.uper").read_bytes()
    bsm = decode_bsm(data)
    assert_same_except_extras(bsm, bsm_from_ode(json.loads(
        shared_path(VEC, "bsm.json").read_text())))
    encoded = encode_bsm(bsm)
    assert encoded == data[:len(encoded)]
    assert not data[len(encoded):].strip(b"\x00"), "only zero padding follows the BSM"


def test_every_optional_present_vector():
    """bsm_uper.hex: every OPTIONAL present, most fields at their minimum."""
    data = binascii.unhexlify(shared_path(VEC, "bsm_uper.hex").read_text().strip())
    bsm = decode_bsm(data)
    assert (bsm.lat, bsm.lon, bsm.steering_angle, bsm.accel_long) == (-90.0, -179.9999999,
                                                                     -189.0, -20.0)
    assert bsm.path_history.initial_position is not None
    assert bsm.events.size == 13 and bsm.lights.size == 9
    # Present-but-unavailable OPTIONAL fields (initialPosition.elevation = -4096) decode to
    # None and re-encode as absent, so this one is equal in value, not in bits.
    again = decode_bsm(encode_bsm(bsm))
    assert_close(again, bsm)


def test_frame_header_claiming_more_than_present_is_truncated():
    """bsm_uper1.hex: a MessageFrame header announcing 173 octets in front of 93."""
    data = binascii.unhexlify(shared_path(VEC, "bsm_uper1.hex").read_text().strip())
    with pytest.raises(DecodeError) as err:
        decode_frame(data)
    assert err.value.reason == "truncated"


def test_non_bsm_frame_is_wrong_message_id():
    """rxMsg_BSM_Asn1DecoderInput.xml carries a TravelerInformation frame (messageId 31)."""
    root = ET.parse(shared_path(VEC, "rxMsg_BSM_Asn1DecoderInput.xml")).getroot()
    frame = binascii.unhexlify(root.find(".//bytes").text.strip())
    with pytest.raises(DecodeError) as err:
        decode_frame(frame)
    assert err.value.reason == "wrong-message-id"


def test_ode_json_128_bsms_survive_encode_decode():
    """128 ODE-decoded BSMs: build, encode, decode, and get the ODE's values back."""
    lines = shared_path(VEC, "128_bsms.json").read_text().splitlines()
    bsms = [bsm_from_ode(json.loads(line)) for line in lines if line.strip()]
    assert len(bsms) == 128
    for bsm in bsms:
        assert_close(decode_frame(encode_frame(bsm)), bsm)


def _frame_files():
    vectors = shared_path(VEC)
    return sorted(p for p in vectors.iterdir() if p.suffix != ".md")


def test_every_frame_in_every_file_decodes_or_is_rejected_for_a_reason():
    """Every frame that the container layer finds in any vector file is a BSM that
    re-encodes bit-exactly, except the known non-BSM and truncated vectors."""
    expected_errors = {"rxMsg_BSM_Asn1DecoderInput.xml": ["wrong-message-id"],
                       "rxMsg_BSM.bin": ["wrong-message-id"],
                       "bsm_uper1.hex": ["truncated"]}
    frames_seen = 0
    for path in _frame_files():
        errors = []
        for item in extract_frames(path.read_bytes()):
            frames_seen += 1
            try:
                if is_message_frame(item.frame):
                    assert_reencodes(item.frame)
                else:  # a bare BasicSafetyMessage (bsm.uper, bsm_uper.hex)
                    decode_bsm(item.frame)
            except DecodeError as err:
                errors.append(err.reason)
        assert errors == expected_errors.get(path.name, []), path.name
    assert frames_seen >= 222 + 228 + 5
