"""The BasicSafetyMessage record in SI units, per message and as numpy arrays.

:class:`BSM` is what the rest of the system works with: the RVE builds them from
mobility tables, the OBU gets them from :func:`catc.j2735.decode_frame`, and the
offline simulator passes them straight to the CA-TC.  Units:

=====================  ===============================================================
field                  unit / meaning (``None`` = unavailable or absent)
=====================  ===============================================================
``msg_cnt``            0..127, wraps
``temp_id``            TemporaryID as an unsigned 32-bit integer (the 4 octets, big-endian)
``sec_mark``           milliseconds within the UTC minute (0..60999), an ``int``
``lat``, ``lon``       degrees, WGS-84
``elev``               metres
``accuracy``           :class:`PositionalAccuracy` (semi-axes in m, orientation in deg)
``transmission``       :class:`TransmissionState`
``speed``              m/s
``heading``            degrees clockwise from north, 0..360
``steering_angle``     degrees, positive to the right (J2735 SteeringWheelAngle)
``accel_long/lat``     m/s²
``accel_vert``         m/s² (sent as units of 0.02 G)
``yaw_rate``           deg/s, positive clockwise (J2735 YawRate); J2735 has no "unavailable"
``brakes``             :class:`BrakeStatus`
``width``, ``length``  metres
``path_history``       :class:`PathHistory` (Part II, VehicleSafetyExtensions)
``path_prediction``    :class:`PathPrediction` (Part II, VehicleSafetyExtensions)
``events``             :class:`BitString` VehicleEventFlags (Part II, as above)
``lights``             :class:`BitString` ExteriorLights (Part II, as above)
``part2_other``        other Part II items as (partII-Id, octets of the value)
``vse_position``       index of the VehicleSafetyExtensions among the Part II items
                       (``None``: first, and sent only when one of its fields is set)
=====================  ===============================================================

The exact conversions, rounding and saturation rules are in :mod:`catc.units`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import NamedTuple

import numpy as np

from catc import units as u


class TransmissionState(IntEnum):
    NEUTRAL = 0
    PARK = 1
    FORWARD_GEARS = 2
    REVERSE_GEARS = 3
    RESERVED1 = 4
    RESERVED2 = 5
    RESERVED3 = 6


class ControlStatus(IntEnum):
    """TractionControlStatus, AntiLockBrakeStatus and StabilityControlStatus."""

    UNAVAILABLE = 0
    OFF = 1
    ON = 2
    ENGAGED = 3


class BrakeBoost(IntEnum):
    UNAVAILABLE = 0
    OFF = 1
    ON = 2


class AuxBrakes(IntEnum):
    UNAVAILABLE = 0
    OFF = 1
    ON = 2
    RESERVED = 3


#: BrakeAppliedStatus bits as an integer, bit 0 of the ASN.1 BIT STRING being the MSB.
WHEELS_UNAVAILABLE = 0b10000
LEFT_FRONT = 0b01000
LEFT_REAR = 0b00100
RIGHT_FRONT = 0b00010
RIGHT_REAR = 0b00001


@dataclass(frozen=True, slots=True)
class BrakeStatus:
    wheel_brakes: int = WHEELS_UNAVAILABLE
    traction: ControlStatus = ControlStatus.UNAVAILABLE
    abs: ControlStatus = ControlStatus.UNAVAILABLE
    scs: ControlStatus = ControlStatus.UNAVAILABLE
    brake_boost: BrakeBoost = BrakeBoost.UNAVAILABLE
    aux_brakes: AuxBrakes = AuxBrakes.UNAVAILABLE

    @property
    def applied(self) -> bool:
        """True when any wheel brake is reported applied."""
        return bool(self.wheel_brakes & 0b01111)


@dataclass(frozen=True, slots=True)
class PositionalAccuracy:
    semi_major: float | None = None
    semi_minor: float | None = None
    orientation: float | None = None


class BitString(NamedTuple):
    """An ASN.1 BIT STRING: ``value`` holds ``size`` bits, named bit 0 as the MSB."""

    value: int
    size: int

    def bit(self, index: int) -> bool:
        return bool((self.value >> (self.size - 1 - index)) & 1)


@dataclass(frozen=True, slots=True)
class DDateTime:
    """J2735 DDateTime, in its own units (``second`` is milliseconds, ``offset`` minutes)."""

    year: int | None = None
    month: int | None = None
    day: int | None = None
    hour: int | None = None
    minute: int | None = None
    second: int | None = None
    offset: int | None = None


@dataclass(frozen=True, slots=True)
class FullPositionVector:
    """PathHistory.initialPosition.  Confidence sets are kept as their enumeration indices."""

    lat: float | None
    lon: float | None
    elevation: float | None = None
    heading: float | None = None
    transmission: TransmissionState | None = None
    speed: float | None = None
    accuracy: PositionalAccuracy | None = None
    utc_time: DDateTime | None = None
    time_confidence: int | None = None
    pos_confidence: tuple[int, int] | None = None
    speed_confidence: tuple[int, int, int] | None = None


@dataclass(frozen=True, slots=True)
class PathHistoryPoint:
    """One crumb: offsets from the current position, ``time_offset`` seconds back in time."""

    lat_offset: float | None
    lon_offset: float | None
    elev_offset: float | None
    time_offset: float | None
    speed: float | None = None
    accuracy: PositionalAccuracy | None = None
    heading: float | None = None


@dataclass(frozen=True, slots=True)
class PathHistory:
    points: tuple[PathHistoryPoint, ...]
    initial_position: FullPositionVector | None = None
    gnss_status: BitString | None = None


@dataclass(frozen=True, slots=True)
class PathPrediction:
    """``radius_of_curve`` in metres (``inf`` = straight); ``confidence`` in percent."""

    radius_of_curve: float
    confidence: float


#: secMark wraps here: J2735 DSecond is milliseconds within the UTC minute.
MINUTE_MS = 60_000
#: msgCnt wraps here: J2735 MsgCount is 0..127.
MSG_COUNT_MODULUS = 128


def sec_mark(t: float) -> int:
    """The secMark of a message generated at time ``t`` (s): its milliseconds within the
    minute, ``round(t * 1000) mod 60000``.  The RVE stamps its BSMs with it and the
    capture files join their records on it (:mod:`hil.capture.schema`)."""
    return round(t * 1000.0) % MINUTE_MS


def msg_cnt(seq: int) -> int:
    """The msgCnt of a vehicle's ``seq``-th message (counted from 0): ``seq mod 128``."""
    return seq % MSG_COUNT_MODULUS


@dataclass(frozen=True, slots=True)
class BSM:
    """A BasicSafetyMessage in SI units (see the module docstring for every unit)."""

    msg_cnt: int
    temp_id: int
    sec_mark: int | None
    lat: float | None
    lon: float | None
    elev: float | None = None
    speed: float | None = None
    heading: float | None = None
    accuracy: PositionalAccuracy = PositionalAccuracy()
    transmission: TransmissionState | None = None
    steering_angle: float | None = None
    accel_long: float | None = None
    accel_lat: float | None = None
    accel_vert: float | None = None
    yaw_rate: float = 0.0
    brakes: BrakeStatus = BrakeStatus()
    width: float | None = None
    length: float | None = None
    # Part II, VehicleSafetyExtensions
    path_history: PathHistory | None = None
    path_prediction: PathPrediction | None = None
    events: BitString | None = None
    lights: BitString | None = None
    #: Other Part II content, kept as (partII-Id, open type octets) so it is re-sent
    #: unchanged (SpecialVehicleExtensions, SupplementalVehicleExtensions, ...), in the
    #: order received.
    part2_other: tuple[tuple[int, bytes], ...] = field(default=())
    #: Regional extensions as (regionId, open type octets), likewise kept unchanged.
    regional: tuple[tuple[int, bytes], ...] = field(default=())
    #: Index of the VehicleSafetyExtensions among the Part II items, counting the items
    #: of ``part2_other`` before it.  ``None`` (the default) puts it first and sends it
    #: only when one of its four fields is set.  The decoder sets it only when that
    #: default would not give back what was received: a VehicleSafetyExtensions after
    #: another item, or one with none of its fields (which is then sent empty).
    vse_position: int | None = None

    @property
    def id_hex(self) -> str:
        """The TemporaryID as 8 upper-case hex digits, as logs and the ODE print it."""
        return f"{self.temp_id:08X}"

    @property
    def vse_index(self) -> int | None:
        """Where the encoder puts the VehicleSafetyExtensions among the Part II items
        (``None``: not sent).  A ``vse_position`` past the other items means last."""
        if self.vse_position is not None:
            return min(self.vse_position, len(self.part2_other))
        if (self.events is None and self.path_history is None
                and self.path_prediction is None and self.lights is None):
            return None
        return 0

    @property
    def part2_ids(self) -> tuple[int, ...]:
        """The partII-Id of every Part II item, in the order they are sent (0 is the
        VehicleSafetyExtensions built from the fields above)."""
        ids = [part_id for part_id, _ in self.part2_other]
        at = self.vse_index
        if at is not None:
            ids.insert(at, 0)
        return tuple(ids)


# --- Array form ----------------------------------------------------------------------------

#: Core fields for bulk work: one row a message, float64 with NaN for unavailable.
#: Integer fields use int64; ``sec_mark`` uses -1 for unavailable.
CORE_DTYPE = np.dtype([
    ("msg_cnt", np.int64), ("temp_id", np.int64), ("sec_mark", np.int64),
    ("lat", np.float64), ("lon", np.float64), ("elev", np.float64),
    ("speed", np.float64), ("heading", np.float64),
    ("semi_major", np.float64), ("semi_minor", np.float64), ("orientation", np.float64),
    ("transmission", np.int64), ("steering_angle", np.float64),
    ("accel_long", np.float64), ("accel_lat", np.float64), ("accel_vert", np.float64),
    ("yaw_rate", np.float64), ("wheel_brakes", np.int64),
    ("width", np.float64), ("length", np.float64),
])

#: The Quantity behind each float column of :data:`CORE_DTYPE`.
CORE_QUANTITIES: dict[str, u.Quantity] = {
    "lat": u.LATITUDE, "lon": u.LONGITUDE, "elev": u.ELEVATION,
    "speed": u.SPEED, "heading": u.HEADING,
    "semi_major": u.SEMI_AXIS, "semi_minor": u.SEMI_AXIS, "orientation": u.ORIENTATION,
    "steering_angle": u.STEERING, "accel_long": u.ACCEL, "accel_lat": u.ACCEL,
    "accel_vert": u.ACCEL_VERT, "yaw_rate": u.YAW_RATE, "width": u.WIDTH, "length": u.LENGTH,
}

_TRANSMISSION_UNAVAILABLE = 7
_SEC_MARK_UNAVAILABLE = 65535


def _nan(x: float | None) -> float:
    return np.nan if x is None else x


def to_array(messages: Iterable[BSM]) -> np.ndarray:
    """Core fields of ``messages`` as a structured array of :data:`CORE_DTYPE`."""
    rows = [
        (m.msg_cnt, m.temp_id, -1 if m.sec_mark is None else m.sec_mark,
         _nan(m.lat), _nan(m.lon), _nan(m.elev), _nan(m.speed), _nan(m.heading),
         _nan(m.accuracy.semi_major), _nan(m.accuracy.semi_minor),
         _nan(m.accuracy.orientation),
         _TRANSMISSION_UNAVAILABLE if m.transmission is None else int(m.transmission),
         _nan(m.steering_angle), _nan(m.accel_long), _nan(m.accel_lat), _nan(m.accel_vert),
         m.yaw_rate, m.brakes.wheel_brakes, _nan(m.width), _nan(m.length))
        for m in messages
    ]
    return np.array(rows, dtype=CORE_DTYPE)


def from_array(arr: np.ndarray) -> list[BSM]:
    """Per-message records from a :data:`CORE_DTYPE` array (Part II is empty)."""

    def opt(x: float) -> float | None:
        return None if x != x else float(x)

    out = []
    for r in arr.tolist():
        (msg_cnt, temp_id, sec_mark, lat, lon, elev, speed, heading, smaj, smin, orient,
         trans, steer, along, alat, avert, yaw, wheels, width, length) = r
        out.append(BSM(
            msg_cnt=msg_cnt, temp_id=temp_id, sec_mark=None if sec_mark < 0 else sec_mark,
            lat=opt(lat), lon=opt(lon), elev=opt(elev), speed=opt(speed), heading=opt(heading),
            accuracy=PositionalAccuracy(opt(smaj), opt(smin), opt(orient)),
            transmission=None if trans == _TRANSMISSION_UNAVAILABLE else TransmissionState(trans),
            steering_angle=opt(steer), accel_long=opt(along), accel_lat=opt(alat),
            accel_vert=opt(avert), yaw_rate=yaw, brakes=BrakeStatus(wheel_brakes=wheels),
            width=opt(width), length=opt(length)))
    return out


def quantize(arr: np.ndarray) -> np.ndarray:
    """The values ``arr`` would have after a trip through J2735 units (vectorised).

    Every float column is rounded and saturated exactly as the encoder does it and
    converted back, so ``quantize(to_array(msgs))`` equals ``to_array`` of the decoded
    messages.  Use it to give a simulation the values an OBU would receive.
    """
    out = arr.copy()
    for name, q in CORE_QUANTITIES.items():
        out[name] = q.from_raw_array(q.to_raw_array(arr[name]))
    return out


