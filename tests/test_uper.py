"""The hand-written UPER codec against asn1tools (compiled from our bsm.asn) and against
arbitrary bytes."""

from __future__ import annotations

import binascii
import contextlib
from importlib import resources

import asn1tools
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from catc.bsm import BSM, BrakeStatus, PathHistory, PathHistoryPoint, PathPrediction
from catc.errors import DecodeError, EncodeError
from catc.j2735 import decode_bsm, decode_frame, encode_bsm, encode_frame, frame_message_id

ORACLE = asn1tools.compile_string(
    resources.files("catc.j2735").joinpath("bsm.asn").read_text(), "uper")

# A real frame from a deployed OBU (the ODE's decoder-output-bsm.xml), with Part II.
REAL = binascii.unhexlify(
    "001480B8494C4C950CD8CDE6E9651116579F22A424DD78FFFFF00761E4FD7EB7D07F7FFF80005F11D1020214"
    "C1C0FFC7C016AFF4017A0FF65403B0FD204C20FFCCC04F8FE40C420FFE6404CEFE60E9A10133408FCFDE1438"
    "103AB4138F00E1EEC1048EC160103E237410445C171104E26BC103DC4154305C2C84103B1C1C8F0A82F42103"
    "F34262D1123198103DAC25FB12034CE10381C259F12038CA103574251B10E3B2210324C23AD0F23D8EFFFE00"
    "00209340D10000004264BF00")


def ints(lo: int, hi: int, unavailable: int | None = None) -> st.SearchStrategy[int]:
    """Legal raw values, excluding the field's 'unavailable' code when it is OPTIONAL."""
    s = st.integers(lo, hi)
    return s.filter(lambda v: v != unavailable) if unavailable is not None else s


def accuracy(optional: bool = False):
    return st.fixed_dictionaries({"semiMajor": st.integers(0, 255),
                                  "semiMinor": st.integers(0, 255),
                                  "orientation": st.integers(0, 65535)})


ENUM_CS = st.sampled_from(["unavailable", "off", "on", "engaged"])
TRANSMISSIONS = st.sampled_from(["neutral", "park", "forwardGears", "reverseGears", "reserved1",
                                 "reserved2", "reserved3", "unavailable"])

CORE = st.fixed_dictionaries({
    "msgCnt": st.integers(0, 127),
    "id": st.binary(min_size=4, max_size=4),
    "secMark": st.integers(0, 65535),
    "lat": st.integers(-900000000, 900000001),
    "long": st.integers(-1799999999, 1800000001),
    "elev": st.integers(-4096, 61439),
    "accuracy": accuracy(),
    "transmission": TRANSMISSIONS,
    "speed": st.integers(0, 8191),
    "heading": st.integers(0, 28800),
    "angle": st.integers(-126, 127),
    "accelSet": st.fixed_dictionaries({"long": st.integers(-2000, 2001),
                                       "lat": st.integers(-2000, 2001),
                                       "vert": st.integers(-127, 127),
                                       "yaw": st.integers(-32767, 32767)}),
    "brakes": st.fixed_dictionaries({
        "wheelBrakes": st.integers(0, 31).map(lambda v: (bytes([v << 3]), 5)),
        "traction": ENUM_CS, "abs": ENUM_CS, "scs": ENUM_CS,
        "brakeBoost": st.sampled_from(["unavailable", "off", "on"]),
        "auxBrakes": st.sampled_from(["unavailable", "off", "on", "reserved"])}),
    "size": st.fixed_dictionaries({"width": st.integers(0, 1023),
                                   "length": st.integers(0, 4095)}),
})

POINT = st.fixed_dictionaries(
    {"latOffset": st.integers(-131072, 131071), "lonOffset": st.integers(-131072, 131071),
     "elevationOffset": st.integers(-2048, 2047), "timeOffset": st.integers(1, 65535)},
    optional={"speed": ints(0, 8191, 8191), "posAccuracy": accuracy(),
              "heading": ints(0, 240, 240)})

DDATETIME = st.fixed_dictionaries({}, optional={
    "year": st.integers(0, 4095), "month": st.integers(0, 12), "day": st.integers(0, 31),
    "hour": st.integers(0, 31), "minute": st.integers(0, 60), "second": st.integers(0, 65535),
    "offset": st.integers(-840, 840)})

FPV = st.fixed_dictionaries(
    {"long": st.integers(-1799999999, 1800000001), "lat": st.integers(-900000000, 900000001)},
    optional={
        "utcTime": DDATETIME, "elevation": ints(-4096, 61439, -4096),
        "heading": ints(0, 28800, 28800),
        "speed": st.fixed_dictionaries({"transmisson": TRANSMISSIONS,
                                        "speed": st.integers(0, 8191)}),
        "posAccuracy": accuracy(), "timeConfidence": st.integers(0, 39),
        "posConfidence": st.fixed_dictionaries({"pos": st.integers(0, 15),
                                                "elevation": st.integers(0, 15)}),
        "speedConfidence": st.fixed_dictionaries({"heading": st.integers(0, 7),
                                                  "speed": st.integers(0, 7),
                                                  "throttle": st.integers(0, 3)})})


def bits(size: int):
    return st.integers(0, (1 << size) - 1).map(
        lambda v: ((v << (-size % 8)).to_bytes((size + 7) // 8, "big"), size))


VSE = st.fixed_dictionaries({}, optional={
    "events": bits(13),
    "pathHistory": st.fixed_dictionaries(
        {"crumbData": st.lists(POINT, min_size=1, max_size=23)},
        optional={"initialPosition": FPV, "currGNSSstatus": bits(8)}),
    "pathPrediction": st.fixed_dictionaries({"radiusOfCurve": st.integers(-32767, 32767),
                                             "confidence": st.integers(0, 200)}),
    "lights": bits(9),
})

# Ids 1 and 2 must hold their J2735 types (tests/test_uper_partii.py); others are opaque.
OTHER_PART2 = st.tuples(st.integers(3, 63), st.binary(min_size=1, max_size=40))


@st.composite
def oracle_bsm(draw) -> dict:
    bsm = {"coreData": draw(CORE)}
    part2 = []
    vse = draw(st.none() | VSE)
    if vse is not None:
        fpv = vse.get("pathHistory", {}).get("initialPosition", {})
        speed = fpv.get("speed")
        if speed is not None and speed == {"transmisson": "unavailable", "speed": 8191}:
            del fpv["speed"]  # present-but-unavailable re-encodes as absent
        part2.append({"partII-Id": 0,
                      "partII-Value": ORACLE.encode("VehicleSafetyExtensions", vse)})
    part2 += [{"partII-Id": i, "partII-Value": v} for i, v in draw(st.lists(OTHER_PART2,
                                                                            max_size=3))]
    if part2:
        bsm["partII"] = draw(st.permutations(part2))  # re-encoded in the order received
    regional = draw(st.lists(st.tuples(st.integers(0, 255), st.binary(min_size=1, max_size=20)),
                             max_size=4))
    if regional:
        bsm["regional"] = [{"regionId": r, "regExtValue": v} for r, v in regional]
    return bsm


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(oracle_bsm())
def test_reencoding_equals_the_reference_codec_bit_for_bit(value):
    reference = ORACLE.encode("BasicSafetyMessage", value)
    assert encode_bsm(decode_bsm(reference)) == reference
    frame = ORACLE.encode("MessageFrame", {"messageId": 20, "value": reference})
    assert encode_frame(decode_frame(frame)) == frame


@settings(max_examples=200, deadline=None)
@given(st.builds(
    BSM,
    msg_cnt=st.integers(0, 127), temp_id=st.integers(0, 2**32 - 1),
    sec_mark=st.none() | st.integers(0, 60999),
    lat=st.none() | st.floats(-90, 90), lon=st.none() | st.floats(-180, 180),
    elev=st.none() | st.floats(-1000, 9000), speed=st.none() | st.floats(0, 300),
    heading=st.none() | st.floats(-720, 720), steering_angle=st.none() | st.floats(-400, 400),
    accel_long=st.none() | st.floats(-50, 50), yaw_rate=st.floats(-500, 500),
    width=st.none() | st.floats(0.01, 12), length=st.none() | st.floats(0.01, 45),
))
def test_our_encoding_is_what_the_reference_codec_reads(bsm):
    """SI values go in; the reference decoder reads the J2735 integers we promised."""
    decoded = ORACLE.decode("BasicSafetyMessage", encode_bsm(bsm))["coreData"]
    assert decoded["msgCnt"] == bsm.msg_cnt
    assert int.from_bytes(decoded["id"], "big") == bsm.temp_id
    assert decoded["secMark"] == (65535 if bsm.sec_mark is None else bsm.sec_mark)
    if bsm.lat is None:
        assert decoded["lat"] == 900000001
    else:
        assert abs(decoded["lat"] * 1e-7 - bsm.lat) <= 0.5e-7 + 1e-12
    if bsm.speed is None:
        assert decoded["speed"] == 8191
    else:
        assert decoded["speed"] == min(round(bsm.speed / 0.02), 8190)
    if bsm.heading is not None:
        assert decoded["heading"] == round((bsm.heading % 360) / 0.0125) % 28800
    assert decoded["accelSet"]["yaw"] == max(-32767, min(32767, round(bsm.yaw_rate / 0.01)))


def test_hand_computed_core_values():
    """A BSM worked out by hand: 25 m/s heading 90°, braking at 3.5 m/s²."""
    bsm = BSM(msg_cnt=5, temp_id=0xDEADBEEF, sec_mark=12345, lat=28.6024, lon=-81.2001,
              elev=30.0, speed=25.0, heading=90.0, accel_long=-3.5, yaw_rate=-1.25,
              brakes=BrakeStatus(wheel_brakes=0b01111), width=1.8, length=4.6,
              path_prediction=PathPrediction(radius_of_curve=-250.0, confidence=90.0),
              path_history=PathHistory(points=(PathHistoryPoint(1e-5, -2e-5, 0.5, 1.0),)))
    frame = encode_frame(bsm)
    assert frame[:2] == b"\x00\x14"
    value = ORACLE.decode("BasicSafetyMessage", ORACLE.decode("MessageFrame", frame)["value"])
    core = value["coreData"]
    assert (core["id"], core["lat"], core["long"], core["elev"]) == (
        bytes.fromhex("DEADBEEF"), 286024000, -812001000, 300)
    assert (core["speed"], core["heading"], core["accelSet"]["long"], core["accelSet"]["yaw"]) \
        == (1250, 7200, -350, -125)
    assert core["brakes"]["wheelBrakes"] == (bytes([0b01111000]), 5)
    assert (core["size"]["width"], core["size"]["length"]) == (180, 460)
    vse = ORACLE.decode("VehicleSafetyExtensions", value["partII"][0]["partII-Value"])
    assert vse["pathPrediction"] == {"radiusOfCurve": -2500, "confidence": 180}
    assert vse["pathHistory"]["crumbData"] == [
        {"latOffset": 100, "lonOffset": -200, "elevationOffset": 5, "timeOffset": 100}]


def test_encode_rejects_values_that_cannot_be_sent():
    base = BSM(msg_cnt=0, temp_id=0, sec_mark=0, lat=0.0, lon=0.0)
    for bad in (BSM(msg_cnt=0, temp_id=2**32, sec_mark=0, lat=0.0, lon=0.0),
                BSM(msg_cnt=0, temp_id=0, sec_mark=70000, lat=0.0, lon=0.0),
                BSM(msg_cnt=0, temp_id=0, sec_mark=0, lat=0.0, lon=0.0,
                    path_history=PathHistory(points=()))):
        with pytest.raises(EncodeError):
            encode_frame(bad)
    assert decode_frame(encode_frame(base)).lat == 0.0


# --- Bad input: only DecodeError, with a reason ---------------------------------------------

@settings(max_examples=1000, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_raise_only_decode_error(data):
    for decode in (decode_frame, decode_bsm):
        try:
            decode(data)
        except DecodeError as err:
            assert err.reason in {"truncated", "garbage", "wrong-message-id", "out-of-range",
                                  "unsupported"}


@settings(max_examples=1000, deadline=None)
@given(st.lists(st.tuples(st.integers(0, len(REAL) - 1), st.integers(0, 255)), min_size=1,
                max_size=8),
       st.integers(0, len(REAL)))
def test_mutated_real_frames_raise_only_decode_error(edits, cut):
    data = bytearray(REAL)
    for index, value in edits:
        data[index] = value
    with contextlib.suppress(DecodeError):
        decode_frame(bytes(data[:cut]))


def test_every_truncation_of_a_real_frame_is_reported_as_truncated():
    for cut in range(len(REAL)):
        with pytest.raises(DecodeError) as err:
            decode_frame(REAL[:cut])
        assert err.value.reason == "truncated", cut


def test_reasons_for_specific_bad_frames():
    with pytest.raises(DecodeError, match="messageId 18") as err:
        decode_frame(b"\x00\x12\x05abcde")
    assert err.value.reason == "wrong-message-id"
    assert frame_message_id(b"\x00\x12\x05abcde") == 18
    # heading field set to 32767 (above 28800) inside an otherwise valid frame
    bsm = decode_frame(REAL)
    raw = bytearray(encode_frame(BSM(msg_cnt=bsm.msg_cnt, temp_id=bsm.temp_id, sec_mark=0,
                                     lat=bsm.lat, lon=bsm.lon)))
    heading_bit = 3 * 8 + 3 + 7 + 32 + 16 + 31 + 32 + 16 + 32 + 3 + 13
    for i in range(15):
        bit = heading_bit + i
        raw[bit // 8] |= 0x80 >> (bit % 8)
    with pytest.raises(DecodeError, match="heading") as err:
        decode_frame(bytes(raw))
    assert err.value.reason == "out-of-range"
