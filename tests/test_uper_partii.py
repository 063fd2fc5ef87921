"""BSM Part II against the J2735 ASN.1: PathHistoryPoint.timeOffset range, the order of
Part II items, the empty VehicleSafetyExtensions, and validation of Part II ids 1
(SpecialVehicleExtensions) and 2 (SupplementalVehicleExtensions).

The reference is asn1tools compiled from ``bsm.asn``, which holds the J2735 2020 form
of both extensions.
"""

from __future__ import annotations

from importlib import resources

import asn1tools
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from catc.bsm import BSM, PathHistory, PathHistoryPoint
from catc.errors import DecodeError, EncodeError
from catc.j2735 import decode_bsm, decode_frame, encode_bsm, encode_frame
from catc.j2735.bits import BitWriter

ORACLE = asn1tools.compile_string(
    resources.files("catc.j2735").joinpath("bsm.asn").read_text(), "uper")

CORE = {
    "msgCnt": 7, "id": bytes.fromhex("31325433"), "secMark": 41000,
    "lat": 405741234, "long": -1050312345, "elev": 14409,
    "accuracy": {"semiMajor": 40, "semiMinor": 30, "orientation": 65535},
    "transmission": "forwardGears", "speed": 700, "heading": 7200, "angle": 127,
    "accelSet": {"long": 10, "lat": 0, "vert": 0, "yaw": 0},
    "brakes": {"wheelBrakes": (b"\x00", 5), "traction": "unavailable", "abs": "off",
               "scs": "unavailable", "brakeBoost": "unavailable", "auxBrakes": "unavailable"},
    "size": {"width": 190, "length": 570},
}

POINT = {"latOffset": -141, "lonOffset": 65, "elevationOffset": -3, "timeOffset": 670}
VSE = ORACLE.encode("VehicleSafetyExtensions", {
    "pathHistory": {"crumbData": [POINT]},
    "pathPrediction": {"radiusOfCurve": 32767, "confidence": 0}})
EMPTY_VSE = ORACLE.encode("VehicleSafetyExtensions", {})
# SupplementalVehicleExtensions as the deployed OBUs of the jpo-ode vectors send it:
# classDetails, vehicleData.height 38 and weatherProbe.airTemp 191.
SUPPLEMENTAL = bytes.fromhex("340d10000004264bf0")
# SpecialVehicleExtensions with one trailer, the values of the ODE's J2735 2024 XER test
# vector (BSM_XML_J2735_2024_ToTranslate.xml, where the field is renamed doNotUse).
SPECIAL = ORACLE.encode("SpecialVehicleExtensions", {"trailers": {
    "notUsed": 0,
    "connection": {"pivotOffset": 100, "pivotAngle": 28800, "pivots": True},
    "units": [{"isDolly": False, "width": 200, "length": 600, "height": 40, "mass": 128,
               "frontPivot": {"pivotOffset": 100, "pivotAngle": 0, "pivots": False},
               "positionOffset": {"x": 0, "y": 0}}]}})


def bsm_with_part2(items: list[tuple[int, bytes]]) -> bytes:
    """A reference UPER BasicSafetyMessage carrying ``items`` as its Part II, in order."""
    return ORACLE.encode("BasicSafetyMessage", {
        "coreData": CORE,
        "partII": [{"partII-Id": i, "partII-Value": v} for i, v in items]})


def assert_reencodes(data: bytes) -> BSM:
    bsm = decode_bsm(data)
    assert encode_bsm(bsm) == data
    frame = ORACLE.encode("MessageFrame", {"messageId": 20, "value": data})
    assert encode_frame(decode_frame(frame)) == frame
    return bsm


def decode_error(data: bytes) -> DecodeError:
    with pytest.raises(DecodeError) as err:
        decode_bsm(data)
    return err.value


# --- 1. PathHistoryPoint.timeOffset is INTEGER (1..65535) --------------------------------

def _vse_with_time_offset_raw(raw: int) -> bytes:
    """One-point VehicleSafetyExtensions whose timeOffset field holds ``raw`` (value - 1)."""
    good = ORACLE.encode("VehicleSafetyExtensions",
                         {"pathHistory": {"crumbData": [{**POINT, "timeOffset": 65535}]}})
    # Bits before timeOffset: VSE extension bit and 4 presence bits, PathHistory extension
    # bit and 2 presence bits, the 5-bit crumbData count, the point's extension bit and 3
    # presence bits, then latOffset 18, lonOffset 18 and elevationOffset 12.
    start = 5 + 3 + 5 + 4 + 18 + 18 + 12
    value = int.from_bytes(good, "big")
    shift = len(good) * 8 - start - 16
    assert (value >> shift) & 0xFFFF == 65534  # 65535 "unavailable" is sent as 65535 - 1
    value = (value & ~(0xFFFF << shift)) | (raw << shift)
    return value.to_bytes(len(good), "big")


def test_time_offset_unavailable_is_legal_and_reencodes():
    data = bsm_with_part2([(0, _vse_with_time_offset_raw(0xFFFE))])
    bsm = assert_reencodes(data)
    assert bsm.path_history.points[0].time_offset is None


def test_time_offset_raw_ffff_is_out_of_range():
    """Raw 0xFFFF is 65536, outside 1..65535: before the fix it decoded as 655.36 s."""
    err = decode_error(bsm_with_part2([(0, _vse_with_time_offset_raw(0xFFFF))]))
    assert err.reason == "out-of-range"
    assert "timeOffset" in str(err)


def test_time_offset_largest_value_reencodes():
    data = bsm_with_part2([(0, _vse_with_time_offset_raw(65533))])  # 65534 = 655.34 s
    assert assert_reencodes(data).path_history.points[0].time_offset == pytest.approx(655.34)


# --- 2. Part II order and the empty VehicleSafetyExtensions -------------------------------

@pytest.mark.parametrize("order", [(2, 0), (1, 0), (2, 0, 1), (1, 2, 0), (0, 2), (0, 1, 2),
                                   (2, 1), (2,)])
def test_part2_items_reencode_in_the_order_received(order):
    values = {0: VSE, 1: SPECIAL, 2: SUPPLEMENTAL}
    bsm = assert_reencodes(bsm_with_part2([(i, values[i]) for i in order]))
    assert bsm.part2_ids == order
    assert [pid for pid, _ in bsm.part2_other] == [i for i in order if i != 0]
    assert bsm.path_history is not None or 0 not in order


def test_usual_order_needs_no_recorded_position():
    """VehicleSafetyExtensions first is the default; such a BSM equals one built by hand."""
    bsm = decode_bsm(bsm_with_part2([(0, VSE), (2, SUPPLEMENTAL)]))
    assert bsm.vse_position is None
    built = BSM(*(getattr(bsm, f) for f in ("msg_cnt", "temp_id", "sec_mark", "lat", "lon")),
                **{f: getattr(bsm, f) for f in (
                    "elev", "speed", "heading", "accuracy", "transmission", "steering_angle",
                    "accel_long", "accel_lat", "accel_vert", "yaw_rate", "brakes", "width",
                    "length", "path_history", "path_prediction", "part2_other")})
    assert built == bsm
    assert encode_bsm(built) == encode_bsm(bsm)


@pytest.mark.parametrize("items", [
    [(0, EMPTY_VSE)],
    [(0, EMPTY_VSE), (2, SUPPLEMENTAL)],
    [(2, SUPPLEMENTAL), (0, EMPTY_VSE)],
    [(1, SPECIAL), (0, EMPTY_VSE), (2, SUPPLEMENTAL)],
])
def test_empty_vehicle_safety_extensions_survives_a_round_trip(items):
    bsm = assert_reencodes(bsm_with_part2(items))
    assert (bsm.events, bsm.path_history, bsm.path_prediction, bsm.lights) == (None,) * 4
    assert 0 in bsm.part2_ids


def test_second_vehicle_safety_extensions_is_kept_as_octets():
    bsm = assert_reencodes(bsm_with_part2([(2, SUPPLEMENTAL), (0, VSE), (0, EMPTY_VSE)]))
    assert bsm.part2_ids == (2, 0, 0)
    assert bsm.part2_other == ((2, SUPPLEMENTAL), (0, EMPTY_VSE))


def test_built_bsm_without_position_sends_vse_first_and_only_with_content():
    point = PathHistoryPoint(1e-5, -2e-5, 0.5, 1.0)
    bare = BSM(msg_cnt=1, temp_id=2, sec_mark=3, lat=40.0, lon=-105.0,
               part2_other=((2, SUPPLEMENTAL),))
    assert bare.part2_ids == (2,)
    assert [p["partII-Id"] for p in ORACLE.decode("BasicSafetyMessage",
                                                  encode_bsm(bare))["partII"]] == [2]
    with_ph = BSM(msg_cnt=1, temp_id=2, sec_mark=3, lat=40.0, lon=-105.0,
                  path_history=PathHistory(points=(point,)), part2_other=((2, SUPPLEMENTAL),))
    assert with_ph.part2_ids == (0, 2)
    # An explicit position past the other items puts it last; an empty one is still sent.
    last = BSM(msg_cnt=1, temp_id=2, sec_mark=3, lat=40.0, lon=-105.0,
               part2_other=((2, SUPPLEMENTAL),), vse_position=5)
    assert last.part2_ids == (2, 0)
    sent = ORACLE.decode("BasicSafetyMessage", encode_bsm(last))["partII"]
    assert [(p["partII-Id"], p["partII-Value"]) for p in sent] == [(2, SUPPLEMENTAL),
                                                                  (0, EMPTY_VSE)]
    with pytest.raises(EncodeError):
        encode_bsm(BSM(msg_cnt=1, temp_id=2, sec_mark=3, lat=40.0, lon=-105.0,
                       vse_position=-1))


# --- 3. Part II ids 1 and 2 are checked against their ASN.1 -------------------------------

def test_real_and_reference_extensions_are_accepted():
    bsm = assert_reencodes(bsm_with_part2([(0, VSE), (1, SPECIAL), (2, SUPPLEMENTAL)]))
    assert bsm.part2_other == ((1, SPECIAL), (2, SUPPLEMENTAL))
    for pid, empty in ((1, ORACLE.encode("SpecialVehicleExtensions", {})),
                       (2, ORACLE.encode("SupplementalVehicleExtensions", {}))):
        assert_reencodes(bsm_with_part2([(pid, empty)]))


def bits(*fields: tuple[int, int]) -> bytes:
    """Hand-built UPER: (value, nbits) pairs, padded with zeros to whole octets."""
    w = BitWriter()
    for value, nbits in fields:
        w.write(value, nbits)
    return w.to_bytes()


# Each case: (partII-Id, value, expected reason).  Field layouts are in the comments.
BAD_CONTENT = {
    "special: too short for its presence bits": (1, b"\xf0", "garbage"),
    "special: random octets": (1, b"\xff\xff", "garbage"),
    "special: octets left after the value": (1, SPECIAL + b"\x00", "garbage"),
    "special: last octet missing": (1, SPECIAL[:-1], "garbage"),
    # ext 0, vehicleAlerts only; EmergencyDetails ext 0, responseType only, notUsed,
    # sirenUse, lightsUse, multi, responseType (ext 0, index 7 of 7 values).
    "special: responseType index 7": (
        1, bits((0, 1), (0b100, 3), (0, 1), (0b01, 2), (0, 5), (0, 2), (0, 3), (0, 2),
                (0, 1), (7, 3)), "out-of-range"),
    # ext 0, trailers only; TrailerData ext 0, notUsed, connection (ext 0, pivotOffset,
    # pivotAngle 28801 > 28800, ...).
    "special: pivotAngle above 28800": (
        1, bits((0, 1), (0b001, 3), (0, 1), (0, 5), (0, 1), (0, 11), (28801, 15), (0, 1),
                (0, 16)), "out-of-range"),
    "supplemental: too short for its presence bits": (2, b"\x00", "garbage"),
    "supplemental: octets left after the value": (2, SUPPLEMENTAL + b"\x00", "garbage"),
    "supplemental: last octet missing": (2, SUPPLEMENTAL[:-1], "garbage"),
    # ext 0, weatherReport only; WeatherReport ext 0, nothing optional, isRaining index 3.
    "supplemental: isRaining index 3 of 3": (
        2, bits((0, 1), (0b0001000000, 10), (0, 1), (0, 5), (3, 2)), "out-of-range"),
    # ext 0, vehicleData only; VehicleData ext 0, trailerWeight only, 64256 > 64255.
    "supplemental: trailerWeight above 64255": (
        2, bits((0, 1), (0b0010000000, 10), (0, 1), (0b0001, 4), (64256, 16)),
        "out-of-range"),
    # ext 0, speedProfile only; SpeedProfile ext 0, 21 speed reports (at most 20).
    "supplemental: 21 speed reports": (
        2, bits((0, 1), (0b0000000100, 10), (0, 1), (20, 5), *[(0, 5)] * 21),
        "out-of-range"),
    # ext 0, status only; DisabledVehicle ext 0, no locationDetails, statusDetails 523 + 19.
    "supplemental: statusDetails 542": (
        2, bits((0, 1), (0b0000001000, 10), (0, 1), (0, 1), (19, 5)), "out-of-range"),
    # ext 0, classDetails only; VehicleClassification ext 0, role only, ext 0, index 23.
    "supplemental: role index 23 of 23": (
        2, bits((0, 1), (0b0100000000, 10), (0, 1), (0b010000000, 9), (0, 1), (23, 5)),
        "out-of-range"),
    # ext 0, theRTCM only; RTCMPackage ext 0, no header, 6 messages (at most 5).
    "supplemental: RTCM message count 6": (
        2, bits((0, 1), (0b0000000010, 10), (0, 1), (0, 1), (5, 3)), "out-of-range"),
}


@pytest.mark.parametrize("case", sorted(BAD_CONTENT))
def test_extension_content_that_does_not_fit_its_type_is_rejected(case):
    pid, value, reason = BAD_CONTENT[case]
    err = decode_error(bsm_with_part2([(0, VSE), (pid, value)]))
    assert err.reason == reason, str(err)
    name = "SpecialVehicleExtensions" if pid == 1 else "SupplementalVehicleExtensions"
    assert name in str(err)


def test_extension_additions_and_extension_enumerations_are_accepted_and_kept():
    """Content from a later J2735: an ENUMERATED value beyond the root (role, extension
    bit 1 and a normally small number) and an extension addition of the SEQUENCE."""
    value = bits((1, 1), (0b0100000000, 10),  # extension bit set, classDetails present
                 (0, 1), (0b010000000, 9),  # VehicleClassification: role present
                 (1, 1), (0, 1), (5, 6),  # role: extension value 5
                 (0, 1), (0, 6), (1, 1),  # extension bitmap: 1 bit, set
                 (1, 8), (0x2A, 8))  # the addition: an open type of one octet
    bsm = assert_reencodes(bsm_with_part2([(0, VSE), (2, value)]))
    assert bsm.part2_other == ((2, value),)


def test_vehicle_safety_extensions_with_octets_left_over_is_rejected():
    err = decode_error(bsm_with_part2([(0, VSE + b"\x00")]))
    assert err.reason == "garbage"


def test_other_part2_ids_stay_opaque():
    assert assert_reencodes(bsm_with_part2([(3, b"\xff"), (63, b"")])).part2_other == (
        (3, b"\xff"), (63, b""))


# --- Property tests against the reference codec -------------------------------------------

def opt(**fields) -> st.SearchStrategy[dict]:
    return st.fixed_dictionaries({}, optional=fields)


def bitstring(size: int) -> st.SearchStrategy[tuple[bytes, int]]:
    return st.integers(0, (1 << size) - 1).map(
        lambda v: ((v << (-size % 8)).to_bytes((size + 7) // 8, "big"), size))


Z = st.integers  # short: the strategies below are mostly integer ranges
REGIONAL = st.lists(st.fixed_dictionaries({"regionId": Z(0, 255),
                                           "regExtValue": st.binary(min_size=1, max_size=6)}),
                    min_size=1, max_size=4)
PIVOT = st.fixed_dictionaries({"pivotOffset": Z(-1024, 1023), "pivotAngle": Z(0, 28800),
                               "pivots": st.booleans()})
NODE = st.fixed_dictionaries({"x": Z(-2048, 2047), "y": Z(-2048, 2047)})
BUMPERS = st.fixed_dictionaries({"front": Z(0, 127), "rear": Z(0, 127)})
TRAILER_POINT = st.fixed_dictionaries(
    {"pivotAngle": Z(0, 28800), "timeOffset": Z(1, 65535), "positionOffset": NODE},
    optional={"elevationOffset": Z(-64, 63), "heading": Z(0, 240)})
TRAILER_UNIT = st.fixed_dictionaries(
    {"isDolly": st.booleans(), "width": Z(0, 1023), "length": Z(0, 4095),
     "frontPivot": PIVOT, "positionOffset": NODE},
    optional={"height": Z(0, 127), "mass": Z(0, 255), "bumperHeights": BUMPERS,
              "centerOfGravity": Z(0, 127), "rearPivot": PIVOT,
              "rearWheelOffset": Z(-2048, 2047), "elevationOffset": Z(-64, 63),
              "crumbData": st.lists(TRAILER_POINT, min_size=1, max_size=23)})
SPECIAL_VALUES = opt(
    vehicleAlerts=st.fixed_dictionaries(
        {"notUsed": Z(0, 31), "sirenUse": Z(0, 3), "lightsUse": Z(0, 7), "multi": Z(0, 3)},
        optional={"events": st.fixed_dictionaries({"notUsed": Z(0, 31),
                                                   "event": bitstring(16)}),
                  "responseType": Z(0, 6)}),
    description=st.fixed_dictionaries(
        {"typeEvent": Z(0, 65535)},
        optional={"description": st.lists(Z(0, 65535), min_size=1, max_size=8),
                  "priority": st.binary(min_size=1, max_size=1), "heading": bitstring(16),
                  "extent": Z(0, 15), "regional": REGIONAL}),
    trailers=st.fixed_dictionaries({"notUsed": Z(0, 31), "connection": PIVOT,
                                    "units": st.lists(TRAILER_UNIT, min_size=1, max_size=3)}))
DDATETIME = opt(year=Z(0, 4095), month=Z(0, 12), day=Z(0, 31), hour=Z(0, 31),
                minute=Z(0, 60), second=Z(0, 65535), offset=Z(-840, 840))
SUPPLEMENTAL_VALUES = opt(
    classification=Z(0, 255),
    classDetails=opt(keyType=Z(0, 255), role=Z(0, 22), iso3883=Z(0, 100), hpmsType=Z(0, 15),
                     vehicleType=Z(0, 34), responseEquip=Z(0, 71), responderType=Z(0, 13),
                     fuelType=Z(0, 15), regional=REGIONAL),
    vehicleData=opt(height=Z(0, 127), bumpers=BUMPERS, mass=Z(0, 255),
                    trailerWeight=Z(0, 64255)),
    weatherReport=st.fixed_dictionaries(
        {"isRaining": Z(0, 2)},
        optional={"rainRate": Z(0, 65535), "precipSituation": Z(0, 14),
                  "solarRadiation": Z(0, 65535), "friction": Z(0, 101),
                  "roadFriction": Z(0, 50)}),
    weatherProbe=opt(airTemp=Z(0, 191), airPressure=Z(0, 255),
                     rainRates=st.fixed_dictionaries(
                         {"statusFront": Z(0, 6), "rateFront": Z(0, 127)},
                         optional={"statusRear": Z(0, 6), "rateRear": Z(0, 127)})),
    obstacle=st.fixed_dictionaries(
        {"obDist": Z(0, 32767), "obDirect": Z(0, 28800), "dateTime": DDATETIME},
        optional={"description": Z(523, 541), "locationDetails": Z(0, 95),
                  "vertEvent": bitstring(5)}),
    status=st.fixed_dictionaries({"statusDetails": Z(523, 541)},
                                 optional={"locationDetails": Z(0, 95)}),
    speedProfile=st.fixed_dictionaries(
        {"speedReports": st.lists(Z(0, 31), min_size=1, max_size=20)}),
    theRTCM=st.fixed_dictionaries(
        {"msgs": st.lists(st.binary(min_size=1, max_size=40), min_size=1, max_size=5)},
        optional={"rtcmHeader": st.fixed_dictionaries({
            "status": bitstring(8),
            "offsetSet": st.fixed_dictionaries({"antOffsetX": Z(-2048, 2047),
                                                "antOffsetY": Z(-256, 255),
                                                "antOffsetZ": Z(-512, 511)})})}),
    regional=REGIONAL)

PART2_ITEM = st.one_of(
    SPECIAL_VALUES.map(lambda v: (1, ORACLE.encode("SpecialVehicleExtensions", v))),
    SUPPLEMENTAL_VALUES.map(lambda v: (2, ORACLE.encode("SupplementalVehicleExtensions", v))),
    st.tuples(Z(3, 63), st.binary(max_size=8)),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(PART2_ITEM, max_size=7), st.none() | st.sampled_from([VSE, EMPTY_VSE]),
       st.integers(0, 7))
def test_any_valid_part2_in_any_order_reencodes_bit_for_bit(items, vse, at):
    if vse is not None:
        items.insert(at, (0, vse))
    if items:
        assert_reencodes(bsm_with_part2(items))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(PART2_ITEM.filter(lambda item: item[0] in (1, 2)))
def test_valid_extension_with_an_octet_more_or_less_is_rejected(item):
    pid, value = item
    for wrong in (value + b"\x00", value[:-1]):
        assert decode_error(bsm_with_part2([(pid, wrong)])).reason == "garbage"
