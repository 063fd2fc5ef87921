"""Conversion between SI values and J2735 integer units, one :class:`Quantity` per field.

Rules, the same for every field (scalar and numpy forms agree exactly):

* **Unavailable.** The field's "unavailable" code decodes to ``None`` (``NaN`` in
  the array form), and ``None``/``NaN`` encodes to that code.  A field without an
  unavailable code (yaw rate, path prediction confidence) refuses ``None``.
* **Rounding.** ``raw = round(x / lsb)``: to the nearest LSB, ties to even
  (Python ``round`` and ``numpy.rint`` both do this).
* **Saturation.** A value beyond the field's range encodes to the end code that
  J2735 defines as "this value or more" (for example speed 8190 = 163.8 m/s or
  greater, acceleration ±2000 = ±20 m/s² or more, elevation −4095 = −409.5 m or
  below).  Decoding an end code gives the end value, not the original.
* **Angles wrap.** Heading, coarse heading, longitude and the accuracy ellipse
  orientation are reduced to their period before saturation, so 360° encodes as 0°
  and −180° as +180°.
* **Exactness.** For every legal raw value ``r``, ``to_raw(from_raw(r)) == r``.
  This is what makes a decoded frame re-encode bit for bit.

Units on the SI side: metres, seconds, m/s, m/s², degrees (headings clockwise from
north, as on the wire), deg/s for yaw rate, percent for confidence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from catc.errors import EncodeError

#: Bound applied before casting scaled floats to int64 (far beyond any J2735 range).
_CAST_LIMIT = 2.0**53

#: Standard gravity, for VerticalAcceleration (units of 0.02 G).
G0 = 9.80665


@dataclass(frozen=True, slots=True)
class Quantity:
    """One J2735 integer field and its SI meaning.

    ``lo..hi`` is the raw range that real values saturate into; ``unavailable`` is
    the raw code for "unavailable" (or ``None``); ``period`` is the number of raw
    LSBs in a full turn for angles that wrap (raw values wrap into ``lo..lo+period-1``).
    """

    name: str
    lsb: float
    lo: int
    hi: int
    unavailable: int | None = None
    period: int | None = None

    def to_raw(self, x: float | None) -> int:
        if x is None or x != x:
            if self.unavailable is None:
                raise EncodeError(f"{self.name} has no 'unavailable' value and cannot be None/NaN")
            return self.unavailable
        if math.isinf(x):
            return self.lo if x < 0 else self.hi
        scaled = x / self.lsb
        if not -_CAST_LIMIT <= scaled <= _CAST_LIMIT:  # as the array form does
            scaled = _CAST_LIMIT if scaled > 0 else -_CAST_LIMIT
        raw = round(scaled)
        if self.period is not None:
            raw = (raw - self.lo) % self.period + self.lo
        return self.lo if raw < self.lo else self.hi if raw > self.hi else raw

    def from_raw(self, raw: int) -> float | None:
        if raw == self.unavailable:
            return None
        return raw * self.lsb

    def to_raw_array(self, x: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`to_raw`: ``NaN`` → unavailable; returns int64."""
        x = np.asarray(x, dtype=np.float64)
        missing = np.isnan(x)
        if missing.any() and self.unavailable is None:
            raise EncodeError(f"{self.name} has no 'unavailable' value and cannot be NaN")
        scaled = np.rint(np.where(missing, 0.0, x) / self.lsb)
        # Clip before the integer cast so that inf and huge values cannot overflow.
        raw = np.clip(scaled, -_CAST_LIMIT, _CAST_LIMIT).astype(np.int64)
        if self.period is not None:
            raw = (raw - self.lo) % self.period + self.lo
        raw = np.clip(raw, self.lo, self.hi)
        raw = np.where(np.isposinf(x), self.hi, np.where(np.isneginf(x), self.lo, raw))
        if self.unavailable is not None:
            raw = np.where(missing, self.unavailable, raw)
        return raw

    def from_raw_array(self, raw: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`from_raw`: unavailable → ``NaN``; returns float64."""
        raw = np.asarray(raw, dtype=np.int64)
        out = raw * self.lsb
        if self.unavailable is not None:
            out = np.where(raw == self.unavailable, np.nan, out)
        return out


# --- BSMcoreData -------------------------------------------------------------------------
LATITUDE = Quantity("lat", 1e-7, -900_000_000, 900_000_000, unavailable=900_000_001)
LONGITUDE = Quantity("lon", 1e-7, -1_799_999_999, 1_800_000_000, unavailable=1_800_000_001,
                     period=3_600_000_000)
ELEVATION = Quantity("elev", 0.1, -4095, 61439, unavailable=-4096)
SEMI_AXIS = Quantity("semi_axis", 0.05, 0, 254, unavailable=255)
ORIENTATION = Quantity("orientation", 360.0 / 65535, 0, 65534, unavailable=65535, period=65535)
SPEED = Quantity("speed", 0.02, 0, 8190, unavailable=8191)
HEADING = Quantity("heading", 0.0125, 0, 28799, unavailable=28800, period=28800)
STEERING = Quantity("steering_angle", 1.5, -126, 126, unavailable=127)
ACCEL = Quantity("accel", 0.01, -2000, 2000, unavailable=2001)
ACCEL_VERT = Quantity("accel_vert", 0.02 * G0, -126, 127, unavailable=-127)
YAW_RATE = Quantity("yaw_rate", 0.01, -32767, 32767)
# J2735 gives VehicleWidth/Length no unavailable code; deployments send 0 for
# "not known" and the ODE decodes 0 as null, so 0 is treated as unavailable and a
# real value never rounds to it (it saturates to 1 cm).
WIDTH = Quantity("width", 0.01, 1, 1023, unavailable=0)
LENGTH = Quantity("length", 0.01, 1, 4095, unavailable=0)

# --- Part II -----------------------------------------------------------------------------
OFFSET_LL = Quantity("offset_ll", 1e-7, -131_071, 131_071, unavailable=-131_072)
VERT_OFFSET = Quantity("vert_offset", 0.1, -2047, 2047, unavailable=-2048)
TIME_OFFSET = Quantity("time_offset", 0.01, 1, 65534, unavailable=65535)
COARSE_HEADING = Quantity("coarse_heading", 1.5, 0, 239, unavailable=240, period=240)
CONFIDENCE = Quantity("confidence", 0.5, 0, 200)

#: RadiusOfCurvature: 10 cm LSB, 32767 = straight, which is ``inf`` on the SI side.
RADIUS_STRAIGHT = 32767
RADIUS_LSB = 0.1
RADIUS_MIN = -32767
RADIUS_MAX = 32766


def radius_to_raw(radius_m: float) -> int:
    """Radius of curvature (m, as J2735 signs it) to raw.

    ``±inf``, ``NaN`` and radii that do not fit the field (beyond −3276.7 m or
    +3276.6 m) are sent as "straight path" (32767): within a path prediction
    horizon such a curve is indistinguishable from a straight line.
    """
    if radius_m != radius_m or math.isinf(radius_m):
        return RADIUS_STRAIGHT
    raw = round(radius_m / RADIUS_LSB)
    return raw if RADIUS_MIN <= raw <= RADIUS_MAX else RADIUS_STRAIGHT


def radius_from_raw(raw: int) -> float:
    return math.inf if raw == RADIUS_STRAIGHT else raw * RADIUS_LSB
