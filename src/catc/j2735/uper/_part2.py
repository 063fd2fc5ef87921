"""J2735 Part II content other than VehicleSafetyExtensions, checked and kept as octets.

SpecialVehicleExtensions (partII-Id 1) and SupplementalVehicleExtensions (partII-Id 2)
are checked against their J2735 2020 ASN.1 (written out in ``catc/j2735/bsm.asn``) and
kept as their octets; other Part II ids pass unchecked.  Every Part II value must fill
its open type (X.691 §11.2): :func:`read_open_type` rejects octets left over after the
value, and a value that runs past its octets.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from catc.errors import DecodeError
from catc.j2735.bits import BitReader
from catc.j2735.uper._elements import read_ddatetime, skip_extensions

_T = TypeVar("_T")

# Each walker reads one type and keeps nothing; a field that fills its bit width (every
# raw value legal) is read as bits, a field with a narrower range is checked.


def _int(r: BitReader, lo: int, hi: int, what: str) -> int:
    """INTEGER (lo..hi): a constrained whole number in the fewest bits (X.691 §11.5.6)."""
    return r.constrained(lo, hi, (hi - lo).bit_length(), what)


def _size(r: BitReader, lo: int, hi: int, what: str) -> int:
    """The number of elements of a SEQUENCE (SIZE(lo..hi)) OF (X.691 §20.6)."""
    return _int(r, lo, hi, f"{what} count")


def _bits(nbits: int, what: str):
    """A walker for a field whose every ``nbits`` value is legal."""
    return lambda r: r.read(nbits, what)


def _range(lo: int, hi: int, what: str):
    """A walker for INTEGER (lo..hi)."""
    return lambda r: _int(r, lo, hi, what)


def _enum(count: int, what: str):
    """A walker for an ENUMERATED of ``count`` root values and an extension marker."""
    return lambda r: r.enumerated(count, True, what)


def _preamble(r: BitReader, n_optional: int, what: str) -> tuple[int, int]:
    """The extension bit and the presence bitmap of an extensible SEQUENCE (X.691 §19)."""
    head = r.read(1 + n_optional, f"{what} preamble")
    return head >> n_optional, head & ((1 << n_optional) - 1)


def _walk_optionals(r: BitReader, what: str, walkers: tuple) -> None:
    """An extensible SEQUENCE whose components are all OPTIONAL, one walker each."""
    n = len(walkers)
    ext, present = _preamble(r, n, what)
    for i, walk in enumerate(walkers):
        if present >> (n - 1 - i) & 1:
            walk(r)
    if ext:
        skip_extensions(r, what)


def _walk_regional(r: BitReader) -> None:
    """SEQUENCE (SIZE(1..4)) OF RegionalExtension: regionId INTEGER (0..255) and an open
    type, whose content is not checked (the REGION content sets are extensible)."""
    for _ in range(_size(r, 1, 4, "regional")):
        r.read(8, "regionId")
        r.open_type("regExtValue")


def _walk_pivot(r: BitReader) -> None:
    """PivotPointDescription ::= SEQUENCE { pivotOffset Offset-B11, pivotAngle Angle,
    pivots PivotingAllowed (BOOLEAN), ... }"""
    ext = r.read(1, "PivotPointDescription")
    r.read(11, "PivotPointDescription.pivotOffset")  # -1024..1023
    _int(r, 0, 28800, "PivotPointDescription.pivotAngle")
    r.read(1, "PivotPointDescription.pivots")
    if ext:
        skip_extensions(r, "PivotPointDescription")


def _walk_trailer_point(r: BitReader) -> None:
    """TrailerHistoryPoint ::= SEQUENCE { pivotAngle Angle, timeOffset TimeOffset,
    positionOffset Node-XY-24b, elevationOffset VertOffset-B07 OPTIONAL,
    heading CoarseHeading OPTIONAL, ... }"""
    ext, present = _preamble(r, 2, "TrailerHistoryPoint")
    _int(r, 0, 28800, "TrailerHistoryPoint.pivotAngle")
    _int(r, 1, 65535, "TrailerHistoryPoint.timeOffset")
    r.read(24, "TrailerHistoryPoint.positionOffset")  # x, y: Offset-B12 -2048..2047
    if present & 2:
        r.read(7, "TrailerHistoryPoint.elevationOffset")  # -64..63
    if present & 1:
        _int(r, 0, 240, "TrailerHistoryPoint.heading")
    if ext:
        skip_extensions(r, "TrailerHistoryPoint")


def _walk_trailer_unit(r: BitReader) -> None:
    """TrailerUnitDescription ::= SEQUENCE { isDolly IsDolly, width VehicleWidth,
    length VehicleLength, height VehicleHeight OPTIONAL, mass TrailerMass OPTIONAL,
    bumperHeights BumperHeights OPTIONAL, centerOfGravity VehicleHeight OPTIONAL,
    frontPivot PivotPointDescription, rearPivot PivotPointDescription OPTIONAL,
    rearWheelOffset Offset-B12 OPTIONAL, positionOffset Node-XY-24b,
    elevationOffset VertOffset-B07 OPTIONAL, crumbData TrailerHistoryPointList OPTIONAL,
    ... }"""
    ext, present = _preamble(r, 8, "TrailerUnitDescription")
    r.read(1 + 10 + 12, "TrailerUnitDescription")  # isDolly, width 0..1023, length 0..4095
    if present & 0x80:
        r.read(7, "TrailerUnitDescription.height")  # 0..127
    if present & 0x40:
        r.read(8, "TrailerUnitDescription.mass")  # 0..255
    if present & 0x20:
        r.read(14, "TrailerUnitDescription.bumperHeights")  # front, rear: 0..127
    if present & 0x10:
        r.read(7, "TrailerUnitDescription.centerOfGravity")
    _walk_pivot(r)
    if present & 8:
        _walk_pivot(r)
    if present & 4:
        r.read(12, "TrailerUnitDescription.rearWheelOffset")  # -2048..2047
    r.read(24, "TrailerUnitDescription.positionOffset")
    if present & 2:
        r.read(7, "TrailerUnitDescription.elevationOffset")
    if present & 1:
        for _ in range(_size(r, 1, 23, "TrailerUnitDescription.crumbData")):
            _walk_trailer_point(r)
    if ext:
        skip_extensions(r, "TrailerUnitDescription")


def _walk_trailer_data(r: BitReader) -> None:
    """TrailerData ::= SEQUENCE { notUsed SSPindex, connection PivotPointDescription,
    units SEQUENCE (SIZE(1..8)) OF TrailerUnitDescription, ... }"""
    ext = r.read(1, "TrailerData")
    r.read(5, "TrailerData.notUsed")  # 0..31
    _walk_pivot(r)
    for _ in range(_size(r, 1, 8, "TrailerData.units")):
        _walk_trailer_unit(r)
    if ext:
        skip_extensions(r, "TrailerData")


def _walk_privileged_events(r: BitReader) -> None:
    """PrivilegedEvents ::= SEQUENCE { notUsed SSPindex, event PrivilegedEventFlags, ... }"""
    ext = r.read(1, "PrivilegedEvents")
    r.read(5 + 16, "PrivilegedEvents")  # 0..31, BIT STRING (SIZE(16))
    if ext:
        skip_extensions(r, "PrivilegedEvents")


def _walk_emergency_details(r: BitReader) -> None:
    """EmergencyDetails ::= SEQUENCE { notUsed SSPindex, sirenUse SirenInUse,
    lightsUse LightbarInUse, multi MultiVehicleResponse, events PrivilegedEvents OPTIONAL,
    responseType ResponseType OPTIONAL, ... }"""
    ext, present = _preamble(r, 2, "EmergencyDetails")
    r.read(5 + 2 + 3 + 2, "EmergencyDetails")  # 0..31, then enumerations of 4, 8 and 4
    if present & 2:
        _walk_privileged_events(r)
    if present & 1:
        r.enumerated(7, True, "EmergencyDetails.responseType")
    if ext:
        skip_extensions(r, "EmergencyDetails")


def _walk_event_description(r: BitReader) -> None:
    """EventDescription ::= SEQUENCE { typeEvent ITIScodes, description SEQUENCE
    (SIZE(1..8)) OF ITIScodes OPTIONAL, priority Priority OPTIONAL, heading HeadingSlice
    OPTIONAL, extent Extent OPTIONAL, regional ... OPTIONAL, ... }"""
    ext, present = _preamble(r, 5, "EventDescription")
    r.read(16, "EventDescription.typeEvent")  # ITIScodes 0..65535
    if present & 16:
        r.read(16 * _size(r, 1, 8, "EventDescription.description"), "EventDescription")
    if present & 8:
        r.read(8, "EventDescription.priority")  # OCTET STRING (SIZE(1))
    if present & 4:
        r.read(16, "EventDescription.heading")  # BIT STRING (SIZE(16))
    if present & 2:
        r.read(4, "EventDescription.extent")  # 16 values
    if present & 1:
        _walk_regional(r)
    if ext:
        skip_extensions(r, "EventDescription")


def _walk_special(r: BitReader) -> None:
    """SpecialVehicleExtensions ::= SEQUENCE { vehicleAlerts EmergencyDetails OPTIONAL,
    description EventDescription OPTIONAL, trailers TrailerData OPTIONAL, ... }"""
    _walk_optionals(r, "SpecialVehicleExtensions",
                    (_walk_emergency_details, _walk_event_description, _walk_trailer_data))


def _walk_wiper_set(r: BitReader) -> None:
    """WiperSet ::= SEQUENCE { statusFront WiperStatus, rateFront WiperRate,
    statusRear WiperStatus OPTIONAL, rateRear WiperRate OPTIONAL } (no extension marker)"""
    present = r.read(2, "WiperSet preamble")
    r.enumerated(7, True, "WiperSet.statusFront")
    r.read(7, "WiperSet.rateFront")  # 0..127
    if present & 2:
        r.enumerated(7, True, "WiperSet.statusRear")
    if present & 1:
        r.read(7, "WiperSet.rateRear")


def _walk_weather_report(r: BitReader) -> None:
    """WeatherReport ::= SEQUENCE { isRaining EssPrecipYesNo, rainRate EssPrecipRate
    OPTIONAL, precipSituation EssPrecipSituation OPTIONAL, solarRadiation
    EssSolarRadiation OPTIONAL, friction EssMobileFriction OPTIONAL,
    roadFriction CoefficientOfFriction OPTIONAL, ... }"""
    ext, present = _preamble(r, 5, "WeatherReport")
    r.enumerated(3, False, "WeatherReport.isRaining")
    if present & 16:
        r.read(16, "WeatherReport.rainRate")  # 0..65535
    if present & 8:
        r.enumerated(15, False, "WeatherReport.precipSituation")
    if present & 4:
        r.read(16, "WeatherReport.solarRadiation")  # 0..65535
    if present & 2:
        _int(r, 0, 101, "WeatherReport.friction")
    if present & 1:
        _int(r, 0, 50, "WeatherReport.roadFriction")
    if ext:
        skip_extensions(r, "WeatherReport")


def _walk_obstacle(r: BitReader) -> None:
    """ObstacleDetection ::= SEQUENCE { obDist ObstacleDistance, obDirect ObstacleDirection,
    description ITIScodes(523..541) OPTIONAL, locationDetails GenericLocations OPTIONAL,
    dateTime DDateTime, vertEvent VerticalAccelerationThreshold OPTIONAL, ... }"""
    ext, present = _preamble(r, 3, "ObstacleDetection")
    r.read(15, "ObstacleDetection.obDist")  # 0..32767
    _int(r, 0, 28800, "ObstacleDetection.obDirect")
    if present & 4:
        _int(r, 523, 541, "ObstacleDetection.description")
    if present & 2:
        r.enumerated(96, True, "ObstacleDetection.locationDetails")
    read_ddatetime(r)
    if present & 1:
        r.read(5, "ObstacleDetection.vertEvent")  # BIT STRING (SIZE(5))
    if ext:
        skip_extensions(r, "ObstacleDetection")


def _walk_disabled_vehicle(r: BitReader) -> None:
    """DisabledVehicle ::= SEQUENCE { statusDetails ITIScodes(523..541),
    locationDetails GenericLocations OPTIONAL, ... }"""
    ext, present = _preamble(r, 1, "DisabledVehicle")
    _int(r, 523, 541, "DisabledVehicle.statusDetails")
    if present:
        r.enumerated(96, True, "DisabledVehicle.locationDetails")
    if ext:
        skip_extensions(r, "DisabledVehicle")


def _walk_speed_profile(r: BitReader) -> None:
    """SpeedProfile ::= SEQUENCE { speedReports SEQUENCE (SIZE(1..20)) OF GrossSpeed, ... }"""
    ext = r.read(1, "SpeedProfile")
    r.read(5 * _size(r, 1, 20, "SpeedProfile.speedReports"), "speedReports")  # 0..31 each
    if ext:
        skip_extensions(r, "SpeedProfile")


def _walk_rtcm(r: BitReader) -> None:
    """RTCMPackage ::= SEQUENCE { rtcmHeader RTCMheader OPTIONAL, msgs SEQUENCE (SIZE(1..5))
    OF RTCMmessage, ... }; RTCMmessage ::= OCTET STRING (SIZE(1..1023))"""
    ext, present = _preamble(r, 1, "RTCMPackage")
    if present:  # RTCMheader: GNSSstatus (8 bits), AntennaOffsetSet (Offset-B12, B09, B10)
        r.read(8 + 12 + 9 + 10, "RTCMPackage.rtcmHeader")
    for _ in range(_size(r, 1, 5, "RTCMPackage.msgs")):
        r.octets(_int(r, 1, 1023, "RTCMmessage length"), "RTCMmessage")
    if ext:
        skip_extensions(r, "RTCMPackage")


def _walk_supplemental(r: BitReader) -> None:
    """SupplementalVehicleExtensions ::= SEQUENCE { classification BasicVehicleClass,
    classDetails VehicleClassification, vehicleData VehicleData, weatherReport
    WeatherReport, weatherProbe WeatherProbe, obstacle ObstacleDetection, status
    DisabledVehicle, speedProfile SpeedProfile, theRTCM RTCMPackage, regional SEQUENCE
    (SIZE(1..4)) OF RegionalExtension, ... }, every component OPTIONAL"""
    _walk_optionals(r, "SupplementalVehicleExtensions", _SUPPLEMENTAL)


#: VehicleClassification ::= SEQUENCE { keyType BasicVehicleClass, role BasicVehicleRole,
#: iso3883 Iso3833VehicleType, hpmsType VehicleType, vehicleType VehicleGroupAffected,
#: responseEquip IncidentResponseEquipment, responderType ResponderGroupAffected,
#: fuelType FuelType, regional ..., ... }, every component OPTIONAL.  The ITIS
#: enumerations have 35, 72 and 14 root values, and an extension marker.
_VEHICLE_CLASSIFICATION = (
    _bits(8, "VehicleClassification.keyType"), _enum(23, "VehicleClassification.role"),
    _range(0, 100, "VehicleClassification.iso3883"),
    _enum(16, "VehicleClassification.hpmsType"),
    _enum(35, "VehicleClassification.vehicleType"),
    _enum(72, "VehicleClassification.responseEquip"),
    _enum(14, "VehicleClassification.responderType"),
    _bits(4, "VehicleClassification.fuelType"), _walk_regional)

#: VehicleData ::= SEQUENCE { height VehicleHeight, bumpers BumperHeights, mass VehicleMass,
#: trailerWeight TrailerWeight (0..64255), ... }, every component OPTIONAL.
_VEHICLE_DATA = (_bits(7, "VehicleData.height"), _bits(14, "VehicleData.bumpers"),
                 _bits(8, "VehicleData.mass"), _range(0, 64255, "VehicleData.trailerWeight"))

#: WeatherProbe ::= SEQUENCE { airTemp AmbientAirTemperature (0..191), airPressure
#: AmbientAirPressure, rainRates WiperSet, ... }, every component OPTIONAL.
_WEATHER_PROBE = (_range(0, 191, "WeatherProbe.airTemp"), _bits(8, "WeatherProbe.airPressure"),
                  _walk_wiper_set)

#: The components of SupplementalVehicleExtensions, in order (see _walk_supplemental).
_SUPPLEMENTAL = (
    _bits(8, "SupplementalVehicleExtensions.classification"),  # BasicVehicleClass 0..255
    lambda r: _walk_optionals(r, "VehicleClassification", _VEHICLE_CLASSIFICATION),
    lambda r: _walk_optionals(r, "VehicleData", _VEHICLE_DATA),
    _walk_weather_report,
    lambda r: _walk_optionals(r, "WeatherProbe", _WEATHER_PROBE),
    _walk_obstacle, _walk_disabled_vehicle, _walk_speed_profile, _walk_rtcm, _walk_regional)

#: Part II content checked here, by partII-Id: the type's name and its walker.
_PART2_TYPES = {1: ("SpecialVehicleExtensions", _walk_special),
                2: ("SupplementalVehicleExtensions", _walk_supplemental)}
#: (partII-Id, value) pairs already found valid: a vehicle repeats the same content.
_valid_part2: set[tuple[int, bytes]] = set()
_VALID_PART2_MAX = 1024


def read_open_type(value: bytes, read: Callable[[BitReader], _T], name: str) -> _T:
    """``read`` applied to the inner encoding of an open type (X.691 §11.2).

    The value must end within its octets and leave at most the 7 bits that pad it to a
    whole octet.  Running past the octets or leaving more is garbage, not truncation:
    the frame around the open type is complete, its content is not of the type.
    Errors name the type: ``"{name}: {what went wrong}"``.
    """
    r = BitReader(value)
    try:
        result = read(r)
    except DecodeError as err:
        detail = str(err).partition(": ")[2]
        if err.reason == "truncated":
            raise DecodeError("garbage", f"{name}: the value runs past its {len(value)} "
                                         f"octets ({detail})") from None
        raise DecodeError(err.reason, f"{name}: {detail}") from None
    if r.remaining >= 8:
        raise DecodeError("garbage", f"{name}: {r.remaining // 8} octets left after the value")
    return result


def check_part2(part_id: int, value: bytes) -> None:
    """Reject a Part II value of id 1 or 2 that is not of its type; other ids pass."""
    checked = _PART2_TYPES.get(part_id)
    if checked is None or (part_id, value) in _valid_part2:
        return
    read_open_type(value, checked[1], checked[0])
    if len(_valid_part2) >= _VALID_PART2_MAX:
        _valid_part2.clear()
    _valid_part2.add((part_id, value))
