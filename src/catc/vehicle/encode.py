"""The host vehicle's side of a replay, made from its trajectory (no I/O): the frames its
CAN bus carries and the fixes its GNSS receiver sends.

* :class:`CanEncoder` is the inverse of :class:`catc.vehicle.CanDecoder`: a host-state
  field's value becomes its signals through the profile's :class:`FieldRule` (``(value -
  offset) / scale``; ``mean``: every signal gets it; ``sum``: the first signal gets it
  quantized to its DBC scale, the second the remainder; a named choice such as gear
  ``"D"`` its DBC value), the message's other signals are 0, :mod:`cantools` packs the
  frame, and the profile's checksum rule fills the ``CHECKSUM`` byte.  Decoded back, every
  field is within one DBC scale step of the value given (tests/test_rve_hostbus.py).
* :func:`host_frames`: every message the profile reads, at the profile's rate
  (``rates_hz``), its fields taken from the track at the frame's time (:func:`host_values`
  says where each comes from).
* :func:`gnss_epochs` / :func:`gnss_fixes`: one fix per 0.1 s of UTC, the true position
  plus a slow, seeded Gauss-Markov error, sent ``latency_s`` after its epoch, some lost
  (``loss``) and none during an outage.

Where a host's state is not in its track, these rules stand in (:func:`host_values`):

* steering wheel angle: a kinematic bicycle model, ``ratio * atan(wheelbase * yaw rate /
  speed)`` with :data:`WHEELBASE_M` 2.66 m and :data:`STEERING_RATIO` 14.3 (a 2017 RAV4),
  positive to the right like the J2735 yaw rate it comes from, 0 below 0.5 m/s;
* brake pedal pressed: longitudinal acceleration below :data:`BRAKE_ACCEL_MPS2` (-1.0
  m/s²), a firm deceleration (coasting and engine braking stay above it);
* gear ``"D"``, or ``"P"`` once the speed has stayed below 0.1 m/s for more than 1 s;
* lights: no turn signal, no hazard lights, beams off.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from catc.gnss import Fix
from catc.mobility import Track
from catc.vehicle import CHECKSUMS, FieldRule, VehicleProfile

__all__ = [
    "BRAKE_ACCEL_MPS2", "FRAME_DTYPE", "GNSS_PERIOD_S", "NOISE_TAU_S", "STEERING_RATIO",
    "WHEELBASE_M", "CanEncoder", "GnssEpoch", "gnss_epochs", "gnss_fixes", "host_frames",
    "host_values",
]

#: A kinematic bicycle model's wheelbase (m) and steering ratio: a 2017 Toyota RAV4.
WHEELBASE_M = 2.66
STEERING_RATIO = 14.3
#: The brake pedal counts as pressed below this longitudinal acceleration (m/s²).
BRAKE_ACCEL_MPS2 = -1.0
#: Standing still: below this speed (m/s) for longer than PARK_AFTER_S the gear is "P".
PARK_SPEED_MPS = 0.1
PARK_AFTER_S = 1.0
#: Below this speed (m/s) the bicycle model gives no steering angle (yaw rate / speed).
STEER_MIN_SPEED_MPS = 0.5

#: GNSS epochs are this far apart in UTC (s): 10 Hz.
GNSS_PERIOD_S = 0.1
#: Correlation time of the GNSS position error (s): first-order Gauss-Markov.
NOISE_TAU_S = 10.0
#: White noise on the course (deg) and speed (m/s) over ground, per metre of noise_m.
COURSE_STD_DEG_PER_M = 0.4
SPEED_STD_MPS_PER_M = 0.04
#: What the GGA says: fix quality (1 = GPS fix), satellites used, HDOP.
QUALITY, NUM_SV, HDOP = 1, 12, 0.8

#: One frame: time (s, the table's clock), bus, arbitration id, length, data (zero-padded;
#: NumPy drops trailing zero bytes on reading, ``length`` restores them).  The recorded
#: ``vehicle_can`` of a dataset has the same columns.
FRAME_DTYPE = np.dtype([("t", "f8"), ("bus", "u1"), ("address", "u4"), ("length", "u1"),
                        ("data", "S64")])

# WGS-84, for metres of error to degrees at a latitude.
_A, _E2 = 6378137.0, 6.69437999014e-3


def _raw_limits(sig: Any) -> tuple[float, float]:
    """The physical values a signal's bits can carry (its DBC minimum and maximum are
    not trusted: opendbc writes [0|65535] or [0|0] on signed and offset signals)."""
    n = int(sig.length)
    lo, hi = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if sig.is_signed else (0, (1 << n) - 1)
    a, b = lo * sig.scale + sig.offset, hi * sig.scale + sig.offset
    return (a, b) if a <= b else (b, a)


def _choice(sig: Any, name: str) -> int:
    for value, label in (sig.choices or {}).items():
        if str(label) == name:
            return int(value)
    raise ValueError(f"signal {sig.name} has no choice {name!r}")


class CanEncoder:
    """Frames of the car's bus from host-state fields: the inverse of
    :class:`catc.vehicle.CanDecoder` for ``profile`` through ``db`` (module docstring)."""

    def __init__(self, profile: VehicleProfile, db: Any) -> None:
        profile.check(db)
        self.profile = profile
        self.db = db
        self._rule = CHECKSUMS[profile.checksum]
        self._msgs: dict[str, Any] = {}
        self._checksummed: dict[str, bool] = {}
        for name in {*profile.messages(), *profile.rates_hz}:
            msg = db.get_message_by_name(name)
            self._msgs[name] = msg
            self._checksummed[name] = any(s.name == "CHECKSUM" and s.length == 8
                                          for s in msg.signals)

    def message(self, name: str) -> Any:
        """The cantools message ``name``."""
        msg = self._msgs.get(name)
        if msg is None:
            msg = self._msgs[name] = self.db.get_message_by_name(name)
            self._checksummed[name] = any(s.name == "CHECKSUM" and s.length == 8
                                          for s in msg.signals)
        return msg

    def signals(self, field_name: str, value: Any) -> dict[str, float]:
        """The physical signal values that carry ``value`` of field ``field_name``."""
        rule: FieldRule = self.profile.fields[field_name]
        msg = self.message(rule.message)
        sigs = [msg.get_signal_by_name(s) for s in rule.signals]
        if isinstance(value, str):  # a named choice: its DBC value, on every signal
            raw = _choice(sigs[0], value) * sigs[0].scale + sigs[0].offset
            return {s.name: raw for s in sigs}
        v = (float(value) - rule.offset) / rule.scale
        if rule.combine != "sum" or len(sigs) == 1:
            return {s.name: v for s in sigs}
        first, second = sigs[0], sigs[1]
        lo, hi = _raw_limits(second)
        steps = v / first.scale
        best = None
        for k in (round(steps), math.floor(steps), math.ceil(steps)):
            head = k * first.scale
            rest = round((v - head) / second.scale) * second.scale
            if lo - 1e-9 <= rest <= hi + 1e-9:
                best = (head, rest)
                break
        if best is None:  # out of the first signal's reach: saturates at encoding
            best = (round(steps) * first.scale, 0.0)
        out = {s.name: 0.0 for s in sigs}
        out[first.name], out[second.name] = best
        return out

    def encode(self, message: str, values: Mapping[str, Any]) -> tuple[int, bytes]:
        """``(arbitration id, data)`` of ``message`` carrying the fields of ``values``
        (field name -> value) that it carries; its other signals are 0, every value is
        saturated to what its bits can hold, and the checksum is set."""
        msg = self.message(message)
        phys: dict[str, float] = {s.name: 0.0 for s in msg.signals}
        for name, rule in self.profile.fields.items():
            if rule.message == message and name in values and values[name] is not None:
                phys.update(self.signals(name, values[name]))
        for s in msg.signals:
            if not s.is_float:
                lo, hi = _raw_limits(s)
                phys[s.name] = min(max(phys[s.name], lo), hi)
        data = bytearray(msg.encode(phys, scaling=True, strict=False))
        if self._checksummed[message]:
            data[-1] = self._rule(msg.frame_id, bytes(data))
        return msg.frame_id, bytes(data)


# --- the host's state along its track ------------------------------------------------------

def _interp(t: np.ndarray, track: Track, column: str) -> np.ndarray:
    return np.interp(t, track.t, np.asarray(getattr(track, column), dtype=np.float64))


def _heading(t: np.ndarray, track: Track) -> np.ndarray:
    unwrapped = np.degrees(np.unwrap(np.radians(np.asarray(track.heading, dtype=float))))
    return np.interp(t, track.t, unwrapped) % 360.0


def _parked(t: np.ndarray, track: Track) -> np.ndarray:
    """Whether the car has stood still (speed below PARK_SPEED_MPS) for longer than
    PARK_AFTER_S at each time of ``t`` (judged on the track's own samples)."""
    still = np.asarray(track.speed, dtype=float) < PARK_SPEED_MPS
    since = np.full(len(still), np.inf)
    start = None
    for i, s in enumerate(still.tolist()):
        start = (start if start is not None else float(track.t[i])) if s else None
        if start is not None:
            since[i] = start
    i = np.clip(np.searchsorted(track.t, t, side="right") - 1, 0, len(still) - 1)
    return still[i] & (t - since[i] > PARK_AFTER_S)


def host_values(track: Track, t: np.ndarray) -> dict[str, np.ndarray]:
    """The host-state fields at the times ``t`` (s), interpolated from ``track``:
    ``speed_mps`` and ``dashboard_speed_mps`` (speed), ``yaw_rate_dps`` (yaw rate, J2735:
    clockwise), ``accel_long_mps2`` (accel), ``accel_lat_mps2`` (speed times yaw rate in
    rad/s: positive to the right), ``steering_wheel_angle_deg`` (bicycle model), and
    ``brake_pressed``, ``gear`` and the lights by the module docstring's rules."""
    t = np.asarray(t, dtype=np.float64)
    speed = _interp(t, track, "speed")
    yaw = _interp(t, track, "yaw_rate")
    accel = _interp(t, track, "accel")
    yaw_rad = np.radians(yaw)
    curvature = np.divide(yaw_rad, speed, out=np.zeros_like(speed),
                          where=speed >= STEER_MIN_SPEED_MPS)
    steer = STEERING_RATIO * np.degrees(np.arctan(WHEELBASE_M * curvature))
    n = len(t)
    return {
        "speed_mps": speed, "dashboard_speed_mps": speed, "yaw_rate_dps": yaw,
        "accel_long_mps2": accel, "accel_lat_mps2": speed * yaw_rad,
        "steering_wheel_angle_deg": steer,
        "brake_pressed": (accel < BRAKE_ACCEL_MPS2).astype(np.float64),
        "gear": np.where(_parked(t, track), "P", "D"),
        "turn_signals": np.full(n, "none"), "hazard_lights": np.zeros(n),
        "low_beam": np.zeros(n), "high_beam": np.zeros(n),
    }


def host_frames(track: Track, profile: VehicleProfile, db: Any, start: float, end: float,
                encoder: CanEncoder | None = None) -> np.ndarray:
    """Every frame of the profile's messages from ``start`` to ``end`` (s, the table's
    clock, both included), each message at ``profile.rate_hz`` from ``start`` on, its
    fields from :func:`host_values` at the frame's time: a :data:`FRAME_DTYPE` array (bus
    0) in time order, then by arbitration id."""
    enc = encoder or CanEncoder(profile, db)
    rows: list[tuple[float, int, int, int, bytes]] = []
    for name in profile.messages():
        period = 1.0 / profile.rate_hz(name)
        count = math.floor((end - start) / period + 1e-9) + 1 if end >= start else 0
        times = start + np.arange(count) * period
        values = host_values(track, times)
        fields = [f for f, rule in profile.fields.items()
                  if rule.message == name and f in values]
        for k, t in enumerate(times.tolist()):
            address, data = enc.encode(name, {f: values[f][k] for f in fields})
            rows.append((t, 0, address, len(data), data))
    out = np.array(rows, dtype=FRAME_DTYPE) if rows else np.zeros(0, FRAME_DTYPE)
    return out[np.lexsort((out["address"], out["t"]))]


# --- GNSS ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class GnssEpoch:
    """One GNSS epoch: when it is sent (s, the table's clock), the fix, the true position
    at its UTC time, and why it was not sent (``"loss"``, ``"outage"``) or None."""

    t_send: float
    fix: Fix
    true_lat: float
    true_lon: float
    dropped: str | None = None


def _gauss_markov(rng: np.random.Generator, n: int, std: float, dt: float,
                  tau: float) -> np.ndarray:
    """``n`` samples ``dt`` apart of a stationary first-order Gauss-Markov process of
    standard deviation ``std`` and correlation time ``tau``."""
    if n == 0 or std == 0.0:
        return np.zeros(n)
    a = math.exp(-dt / tau)
    w = rng.standard_normal(n) * std
    out = np.empty(n)
    out[0] = w[0]
    b = math.sqrt(1.0 - a * a)
    for i in range(1, n):
        out[i] = a * out[i - 1] + b * w[i]
    return out


def gnss_epochs(track: Track, utc_base: float, noise_m: float = 0.5,
                latency_s: float = 0.05, loss: float = 0.0,
                outages: Iterable[tuple[float, float]] = (), seed: int = 0,
                start: float | None = None, end: float | None = None) -> list[GnssEpoch]:
    """Every GNSS epoch of the host's ``track`` from ``start`` to ``end`` (s, the table's
    clock; default the track's span), sent or not.

    Epochs fall on every 0.1 s of UTC (UTC = ``utc_base`` + table time).  The position is
    the track's at the epoch plus a north and an east error, each a first-order
    Gauss-Markov process of standard deviation ``noise_m`` and correlation time
    :data:`NOISE_TAU_S` (GNSS errors are slow); speed and course over ground are the
    track's with small white noise; GST gives ``noise_m`` as both standard deviations.
    Each is sent ``latency_s`` after its epoch; lost with probability ``loss``; and none
    whose epoch lies in an outage ``(start, duration)``, seconds from ``start``.
    Everything drawn is a function of ``seed`` alone (the losses of their own stream, so
    ``loss`` does not change the errors)."""
    if not (noise_m >= 0 and latency_s >= 0 and 0.0 <= loss <= 1.0):
        raise ValueError("noise and latency must be >= 0 and loss within 0..1")
    start = float(track.t[0]) if start is None else float(start)
    end = float(track.t[-1]) if end is None else float(end)
    k0 = math.ceil(round((utc_base + start) / GNSS_PERIOD_S, 6))
    k1 = math.floor(round((utc_base + end) / GNSS_PERIOD_S, 6))
    ks = np.arange(k0, k1 + 1) if k1 >= k0 else np.zeros(0, dtype=np.int64)
    utc = ks / round(1.0 / GNSS_PERIOD_S)  # k / 10: the nearest float to each epoch
    t = utc - utc_base
    n = len(t)
    noise_rng = np.random.default_rng([seed, 0])
    loss_rng = np.random.default_rng([seed, 1])
    north = _gauss_markov(noise_rng, n, noise_m, GNSS_PERIOD_S, NOISE_TAU_S)
    east = _gauss_markov(noise_rng, n, noise_m, GNSS_PERIOD_S, NOISE_TAU_S)
    course_noise = noise_rng.standard_normal(n) * COURSE_STD_DEG_PER_M * noise_m
    speed_noise = noise_rng.standard_normal(n) * SPEED_STD_MPS_PER_M * noise_m
    lost = loss_rng.random(n) < loss
    lat = _interp(t, track, "lat")
    lon = _interp(t, track, "lon")
    elev = _interp(t, track, "elev")
    phi = np.radians(lat)
    s2 = np.sin(phi) ** 2
    m_radius = _A * (1 - _E2) / (1 - _E2 * s2) ** 1.5  # meridian
    n_radius = _A / np.sqrt(1 - _E2 * s2)  # prime vertical
    lat_out = lat + np.degrees(north / m_radius)
    lon_out = lon + np.degrees(east / (n_radius * np.cos(phi)))
    speed = np.maximum(_interp(t, track, "speed") + speed_noise, 0.0)
    course = (_heading(t, track) + course_noise) % 360.0
    windows = [(start + float(a), start + float(a) + float(d)) for a, d in outages]
    out = []
    for i in range(n):
        ti = float(t[i])
        fix = Fix(t_unix=float(utc[i]), lat=float(lat_out[i]), lon=float(lon_out[i]),
                  alt_m=float(elev[i]) if math.isfinite(elev[i]) else None,
                  speed_mps=float(speed[i]), course_deg=float(course[i]), quality=QUALITY,
                  num_sv=NUM_SV, hdop=HDOP, std_lat_m=float(noise_m),
                  std_lon_m=float(noise_m))
        dropped = ("outage" if any(a <= ti + 1e-9 and ti < b - 1e-9 for a, b in windows)
                   else "loss" if lost[i] else None)
        out.append(GnssEpoch(ti + latency_s, fix, float(lat[i]), float(lon[i]), dropped))
    return out


def gnss_fixes(track: Track, utc_base: float, noise_m: float = 0.5,
               latency_s: float = 0.05, loss: float = 0.0,
               outages: Sequence[tuple[float, float]] = (), seed: int = 0,
               start: float | None = None, end: float | None = None,
               ) -> list[tuple[float, Fix, tuple[float, float]]]:
    """The fixes :func:`gnss_epochs` sends: ``(t_send, fix, (true lat, true lon))``."""
    return [(e.t_send, e.fix, (e.true_lat, e.true_lon))
            for e in gnss_epochs(track, utc_base, noise_m, latency_s, loss, outages, seed,
                                 start, end) if e.dropped is None]
