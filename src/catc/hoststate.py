"""The host vehicle's own state from its CAN bus and its GNSS receiver (no I/O).

A real OBU does not receive its host as a ready-made BSM: it reads the car's CAN bus
(:class:`catc.vehicle.CanDecoder`, through a vehicle profile) and a GNSS receiver
(:class:`catc.gnss.NmeaStream`), and fuses them.  :class:`HostEstimator` is that fusion,
fed in the order things reach the OBU, each with its local arrival time (any monotonic
clock, seconds):

* :meth:`HostEstimator.can` after each decoded CAN frame, with the fields it updated;
* :meth:`HostEstimator.fix` after each GNSS epoch (an NMEA fix);
* :meth:`HostEstimator.state` at a tick, for the state at that local time.

What feeds which BSM field, and why (docs/reference/vehicle.md has the table):

* **Position** is dead reckoning on the wheel speed and the yaw rate between fixes,
  pulled towards each fix by a Kalman gain.  A fix is placed where it was measured,
  ``latency`` before it arrived: the receiver's fix reaches the OBU late (on the
  comma2k19 minute the u-blox fixes taken at their arrival are 1.9 m p95 off comma's
  fused pose, 17 m/s times ~0.1 s).  The latency is measured, not assumed
  (``latency_s=None``), against the wheel-speed track: over the last
  :data:`LAG_WINDOW_S` the fixes are fitted, by least squares, to the odometry path
  (wheel speed and heading integrated, never pulled by a fix) taken ``latency`` earlier,
  plus an offset that drifts linearly (the odometry's own slow error).  While the speed
  changes, a wrong latency leaves an error that grows with the speed, so the fit tells
  it apart (it is kept only when its standard error is under :data:`LATENCY_SE_S`).  The
  receiver's own speed over ground is no measure of it: on the minute it lags the wheel
  speed by 0.16 s while its positions lag by ~0.08 s (the receiver filters its speed).
  The dead-reckoned path between the fix's time and now carries the fix forward.
* **Heading** is the yaw rate integrated, pulled towards the GNSS course over ground
  while the car moves faster than :data:`COURSE_MIN_SPEED` (below it a course is noise);
  the same loop learns the yaw-rate sensor's bias (a complementary filter with an
  integral term).  The BSM's yaw rate is the CAN yaw rate minus that bias.
* **Speed** is the wheel speed (J2945/1: the vehicle's own speed); dead reckoning uses it
  times the scale that fits the GNSS speed (tyre wear and pressure: 1.009 on the minute).
* **Accelerations** are CAN's, low-pass filtered (first order, 1 Hz cut-off, J2945/1).
* Brake, gear, steering wheel angle and lights are CAN's latest values.
* **Time**: the OBU's clock is GNSS time.  A fix's sentences arrive ``gnss_delay_s``
  after its UTC stamp, so the GNSS time at local ``t`` is ``t`` plus
  ``stamp + gnss_delay_s - arrival``, smoothed over the fixes (:data:`CLOCK_GAIN`;
  a step of more than :data:`CLOCK_STEP_S` is taken at once).  When the fixes stop,
  the clock keeps that offset and the position keeps dead reckoning (its uncertainty
  grows; ``gnss_age_s`` says how long it has been); after ``gnss_timeout_s`` the state
  is marked ``gnss_lost``.

Before the first fix there is no state (no position, no clock).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from catc.bsm import (
    BSM,
    BrakeStatus,
    PositionalAccuracy,
    TransmissionState,
    msg_cnt,
    sec_mark,
)
from catc.geo import EnuFrame
from catc.gnss import Fix

__all__ = ["COURSE_MIN_SPEED", "LAG_WINDOW_S", "EstimatorConfig", "HostEstimator",
           "HostState"]

#: Below this speed (m/s) the GNSS course does not steer the heading.
COURSE_MIN_SPEED = 3.0
#: The window (s) of GNSS and wheel speeds over which the latency is fitted.
LAG_WINDOW_S = 120.0
#: The latency used until it is measured (s): a typical receiver's (a 10 Hz solution is
#: out within its 100 ms epoch).  Not the clock's ``gnss_delay_s``: on the comma2k19
#: minute the sentences came 0.20 s after their stamps, the positions ~0.06 s old.
LATENCY0_S = 0.1
#: A latency fit is kept when its standard error is below this (s).
LATENCY_SE_S = 0.01
#: Fixes in the window before a latency fit is tried.
_LAG_MIN_FIXES = 50
#: The fit compares the fixes' and the odometry's motion over this many fixes (1 s).
_LAG_STEP = 10
#: How long the dead-reckoning history is kept (s): the longest fix latency.
_HISTORY_S = 1.0
#: The GNSS clock follows each fix's offset by this fraction (the sentences' arrival
#: jitter, ~±30 ms on the comma2k19 minute, is smoothed out of it; a time constant of
#: ten fixes)...
CLOCK_GAIN = 0.1
#: ...unless the offset moved by more than this (s): then the clock steps.
CLOCK_STEP_S = 0.5
#: The wheel speed is used while its newest frame is at most this old (s).
CAN_FRESH_S = 0.5
#: The accelerations' low-pass cut-off (Hz), J2945/1.
ACCEL_CUTOFF_HZ = 1.0

_GEARS = {"P": TransmissionState.PARK, "R": TransmissionState.REVERSE_GEARS,
          "N": TransmissionState.NEUTRAL, "D": TransmissionState.FORWARD_GEARS,
          "S": TransmissionState.FORWARD_GEARS, "B": TransmissionState.FORWARD_GEARS}


@dataclass(frozen=True)
class EstimatorConfig:
    """How :class:`HostEstimator` fuses (see the module docstring)."""

    #: How long after its UTC stamp a fix's sentences arrive (s): the receiver's output
    #: latency, for the clock (0.1 s: a typical receiver's, and rve run's default).
    gnss_delay_s: float = 0.1
    #: How old a fix's position is when it arrives (s); None: measured against the
    #: wheel speed.
    latency_s: float | None = None
    #: Without a fix for this long (s) the state is ``gnss_lost``.
    gnss_timeout_s: float = 5.0
    #: A fix's horizontal standard deviation (m) when its receiver sends no GST.
    fix_std_m: float = 1.0
    #: Dead reckoning's position noise (m per sqrt(s)) per m/s of speed.
    dr_noise: float = 0.02
    #: The heading loop's gains: proportional (1/s) and integral (1/s², the bias).
    heading_kp: float = 0.5
    heading_ki: float = 0.02

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gnss_delay_s) and 0.0 <= self.gnss_delay_s <= 5.0):
            raise ValueError(f"GNSS delay must be 0..5 s, got {self.gnss_delay_s}")
        if self.latency_s is not None and not 0.0 <= self.latency_s <= 1.0:
            raise ValueError(f"GNSS latency must be 0..1 s, got {self.latency_s}")
        if not self.gnss_timeout_s > 0:
            raise ValueError(f"GNSS timeout must be > 0 s, got {self.gnss_timeout_s}")


@dataclass(frozen=True)
class HostState:
    """The host at one instant: GNSS time (unix s), WGS-84 position, the motion in J2735
    units (m/s, deg clockwise from north, deg/s clockwise, m/s²) and the CAN's discrete
    state (None: not known)."""

    t_gnss: float
    lat: float
    lon: float
    elev: float | None
    speed: float | None
    heading: float | None
    yaw_rate: float
    accel_long: float | None
    accel_lat: float | None
    std_m: float
    gnss_age_s: float
    gnss_lost: bool
    brake: bool | None = None
    gear: str | None = None
    steering_deg: float | None = None
    lights: Mapping[str, Any] = field(default_factory=dict)

    def bsm(self, seq: int, temp_id: int, length: float | None = None,
            width: float | None = None) -> BSM:
        """The host's BSM of this state: its ``seq``-th (msgCnt ``seq mod 128``)."""
        std = min(self.std_m, 12.7)
        wheels = None if self.brake is None else (0b01111 if self.brake else 0)
        brakes = BrakeStatus() if wheels is None else BrakeStatus(wheel_brakes=wheels)
        return BSM(
            msg_cnt=msg_cnt(seq), temp_id=temp_id, sec_mark=sec_mark(self.t_gnss),
            lat=self.lat, lon=self.lon, elev=self.elev, speed=self.speed,
            heading=None if self.heading is None else self.heading % 360.0,
            accuracy=PositionalAccuracy(std, std, 0.0),
            transmission=_GEARS.get(self.gear) if self.gear else None,
            steering_angle=None if self.steering_deg is None
            else max(-189.0, min(189.0, self.steering_deg)),
            accel_long=self.accel_long, accel_lat=self.accel_lat, yaw_rate=self.yaw_rate,
            brakes=brakes, length=length, width=width)


def _wrap180(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


class HostEstimator:
    """The fusion of CAN and GNSS (see the module docstring).  ``counters``:
    ``gnss_fixes``, ``gnss_fixes_stale`` (a stamp not after the last), ``gnss_silent``
    (the fixes stopped for ``gnss_timeout_s``; once per silence), ``can_updates``."""

    def __init__(self, config: EstimatorConfig | None = None) -> None:
        self.config = config or EstimatorConfig()
        self.counters: Counter[str] = Counter()
        self.frame: EnuFrame | None = None
        self.offset: float | None = None  # GNSS time minus local time
        self.t: float | None = None  # local time of the dead-reckoned state
        self.e = self.n = 0.0  # m, in self.frame
        self.var = 0.0  # the position's variance (m², each axis)
        self.heading: float | None = None  # deg clockwise from north
        self.bias = 0.0  # the yaw-rate sensor's bias (deg/s, clockwise)
        self.scale = 1.0  # true speed per wheel speed
        self.elev: float | None = None
        self.last_fix: float | None = None  # local arrival of the newest fix
        self.last_stamp: float | None = None
        self.silent = False
        self.can_state: dict[str, Any] = {}
        self.accel: dict[str, float] = {}  # low-passed accelerations
        self._accel_t: dict[str, float] = {}
        #: (local t, e, n, heading) of the dead-reckoned path, newest last
        self.history: deque[tuple[float, float, float, float | None]] = deque()
        #: (local t, wheel speed) for the speed scale; the newest GNSS speed
        self.wheel: deque[tuple[float, float]] = deque()
        self.gnss_speed: float | None = None
        #: the odometry path (never pulled by a fix), and at each fix of the window:
        #: (arrival, fix e, fix n, odometry e, n, velocity e, n) for the latency fit
        self.oe = self.on = 0.0
        self.ve = self.vn = 0.0
        self.lag_window: deque[tuple[float, ...]] = deque()
        self.latency = LATENCY0_S if self.config.latency_s is None else self.config.latency_s
        self.latency_fitted = self.config.latency_s is not None
        #: the newest fit of the latency and its standard error (s), used or not
        self.latency_fit: tuple[float, float] | None = None

    # ---- inputs -------------------------------------------------------------------
    def can(self, t: float, fields: Mapping[str, Any]) -> None:
        """Fields decoded from a CAN frame that arrived at local ``t``."""
        self.counters["can_updates"] += 1
        if self.t is not None and t > self.t:
            self._propagate(t)
        for name, value in fields.items():
            if name in ("accel_long_mps2", "accel_lat_mps2"):
                self._low_pass(name, t, float(value))
            self.can_state[name] = value
        v = fields.get("speed_mps")
        if v is not None:
            self.wheel.append((t, float(v)))
            while self.wheel and self.wheel[0][0] < t - 2.0 * _HISTORY_S:
                self.wheel.popleft()

    def fix(self, t: float, fix: Fix) -> None:
        """A GNSS fix whose epoch was complete at local ``t``."""
        if self.last_stamp is not None and fix.t_unix <= self.last_stamp:
            self.counters["gnss_fixes_stale"] += 1
            return
        self.counters["gnss_fixes"] += 1
        self.last_stamp, self.last_fix, self.silent = fix.t_unix, t, False
        offset = fix.t_unix + self.config.gnss_delay_s - t
        if self.offset is None or abs(offset - self.offset) > CLOCK_STEP_S:
            self.offset = offset  # the first fix, or a clock step: take it
        else:  # smooth the sentences' arrival jitter out of the clock
            self.offset += CLOCK_GAIN * (offset - self.offset)
        if fix.alt_m is not None:
            self.elev = fix.alt_m
        if fix.speed_mps is not None:
            self.gnss_speed = fix.speed_mps
        std = _fix_std(fix, self.config.fix_std_m)
        if self.frame is None:
            self.frame = EnuFrame(fix.lat, fix.lon, 0.0)
            self.t, self.e, self.n, self.var = t, 0.0, 0.0, std * std
            if fix.course_deg is not None and (fix.speed_mps or 0.0) > COURSE_MIN_SPEED:
                self.heading = fix.course_deg % 360.0
            self.history.clear()
            self.history.append((t, 0.0, 0.0, self.heading))
            return
        self._propagate(max(t, self.t))
        ze, zn, _ = self.frame.to_enu(fix.lat, fix.lon, 0.0)
        if self.config.latency_s is None and self.heading is not None:
            self.lag_window.append((t, ze, zn, self.oe, self.on, self.ve, self.vn))
            while self.lag_window and self.lag_window[0][0] < t - LAG_WINDOW_S:
                self.lag_window.popleft()
            if self.counters["gnss_fixes"] % 10 == 0:
                self._fit_latency()
        when = t - self.latency
        pe, pn, ph = self._at(when)
        # position: a Kalman update of the state now with the fix's innovation at `when`
        k = self.var / (self.var + std * std)
        de, dn = k * (ze - pe), k * (zn - pn)
        self.e += de
        self.n += dn
        self.var *= 1.0 - k
        self.history = deque((ht, he + de, hn + dn, hh) for ht, he, hn, hh in self.history)
        # heading: towards the course over ground, learning the yaw-rate bias
        if fix.course_deg is not None and (fix.speed_mps or 0.0) > COURSE_MIN_SPEED:
            if self.heading is None or ph is None:
                self.heading = fix.course_deg % 360.0
            else:
                err = _wrap180(fix.course_deg - ph)
                prev = t - 0.1 if self._prev_fix_t is None else self._prev_fix_t
                dt = min(1.0, max(0.05, t - prev))
                self.heading = (self.heading + self.config.heading_kp * dt * err) % 360.0
                self.bias -= self.config.heading_ki * dt * err
                self.bias = max(-5.0, min(5.0, self.bias))
        # the wheel-speed scale: GNSS speed over the wheel speed at the fix's time
        if fix.speed_mps is not None and fix.speed_mps > COURSE_MIN_SPEED:
            w = _interp(self.wheel, when)
            if w is not None and w > COURSE_MIN_SPEED:
                ratio = fix.speed_mps / w
                if 0.9 < ratio < 1.1:
                    self.scale += 0.01 * (ratio - self.scale)
        self._prev_fix_t = t

    _prev_fix_t: float | None = None

    # ---- outputs ------------------------------------------------------------------
    def gnss_time(self, t: float) -> float | None:
        """The GNSS time (unix s) at local ``t``; None before the first fix."""
        return None if self.offset is None else t + self.offset

    def local_time(self, t_gnss: float) -> float | None:
        """The local time at GNSS time ``t_gnss``; None before the first fix."""
        return None if self.offset is None else t_gnss - self.offset

    def state(self, t: float) -> HostState | None:
        """The host at local ``t``; None before the first fix.  A ``t`` before the
        newest input (a tick decided after a later frame came) is read off the
        dead-reckoned path of the last second, corrections included."""
        if self.frame is None or self.offset is None:
            return None
        if t > self.t:
            self._propagate(t)
        e, n, heading = self._at(t)
        age = max(0.0, t - self.last_fix)
        lost = age > self.config.gnss_timeout_s
        if lost and not self.silent:
            self.silent = True
            self.counters["gnss_silent"] += 1
        lat, lon, _ = self.frame.to_geodetic(e, n, 0.0)
        c = self.can_state
        speed, _ = self._speed()
        yaw = c.get("yaw_rate_dps")
        return HostState(
            t_gnss=t + self.offset, lat=float(lat), lon=float(lon), elev=self.elev,
            speed=None if speed is None else max(0.0, float(speed)),
            heading=heading,
            yaw_rate=0.0 if yaw is None else float(yaw) - self.bias,
            accel_long=self.accel.get("accel_long_mps2"),
            accel_lat=self.accel.get("accel_lat_mps2"),
            std_m=math.sqrt(self.var), gnss_age_s=age, gnss_lost=lost,
            brake=_flag(c.get("brake_pressed")), gear=_gear(c.get("gear")),
            steering_deg=None if c.get("steering_wheel_angle_deg") is None
            else float(c["steering_wheel_angle_deg"]),
            lights={k: c[k] for k in ("turn_signals", "hazard_lights", "low_beam",
                                      "high_beam") if k in c})

    # ---- internals ----------------------------------------------------------------
    def _propagate(self, t: float) -> None:
        """Dead reckoning from ``self.t`` to ``t`` on the latest speed and yaw rate."""
        dt = t - self.t
        if dt <= 0.0:
            return
        v, from_can = self._speed()
        yaw = self.can_state.get("yaw_rate_dps")
        if self.heading is not None and v is not None:
            v = v * self.scale if from_can else v
            rate = 0.0 if yaw is None else float(yaw) - self.bias
            mid = math.radians(self.heading + 0.5 * rate * dt)
            de, dn = v * dt * math.sin(mid), v * dt * math.cos(mid)
            self.e += de
            self.n += dn
            self.oe += de
            self.on += dn
            self.ve, self.vn = de / dt, dn / dt
            self.heading = (self.heading + rate * dt) % 360.0
            q = self.config.dr_noise * max(v, 1.0)
            self.var += q * q * dt
        else:  # no motion known: the position only grows uncertain
            self.var += dt
        self.t = t
        self.history.append((t, self.e, self.n, self.heading))
        while len(self.history) > 2 and self.history[1][0] < t - _HISTORY_S:
            self.history.popleft()

    def _speed(self) -> tuple[float | None, bool]:
        """The speed (m/s) and whether it is CAN's: the wheel speed while its frames come
        (:data:`CAN_FRESH_S`), else the newest GNSS speed over ground."""
        v = self.can_state.get("speed_mps")
        if v is not None and self.wheel and self.t is not None \
                and self.t - self.wheel[-1][0] <= CAN_FRESH_S:
            return float(v), True
        if self.gnss_speed is not None:
            return self.gnss_speed, False
        return (None if v is None else float(v)), v is not None

    def _at(self, when: float) -> tuple[float, float, float | None]:
        """The dead-reckoned (e, n, heading) at local ``when`` (interpolated in the
        history; its ends beyond it)."""
        h = self.history
        if not h or when >= h[-1][0]:
            return self.e, self.n, self.heading
        if when <= h[0][0]:
            return h[0][1], h[0][2], h[0][3]
        lo, hi = 0, len(h) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if h[mid][0] <= when:
                lo = mid
            else:
                hi = mid
        (t0, e0, n0, h0), (t1, e1, n1, h1) = h[lo], h[hi]
        f = (when - t0) / (t1 - t0) if t1 > t0 else 0.0
        hh = None if h0 is None or h1 is None else (h0 + f * _wrap180(h1 - h0)) % 360.0
        return e0 + f * (e1 - e0), n0 + f * (n1 - n0), hh

    def _low_pass(self, name: str, t: float, value: float) -> None:
        last = self._accel_t.get(name)
        self._accel_t[name] = t
        if last is None or name not in self.accel:
            self.accel[name] = value
            return
        dt = max(0.0, t - last)
        alpha = 1.0 - math.exp(-2.0 * math.pi * ACCEL_CUTOFF_HZ * dt)
        self.accel[name] += alpha * (value - self.accel[name])

    def _fit_latency(self) -> None:
        """Fit the latency over the window (see the module docstring).  Over each second
        (:data:`_LAG_STEP` fixes) the fixes moved ``dz`` and the odometry ``do``, along
        the track; a fix placed ``latency`` late moved ``do - latency * dv``, with ``dv``
        the change of the odometry's speed, and a wheel-speed scale error ``s`` adds
        ``s * do``: least squares on ``dz - do = -latency * dv + s * do``."""
        w = list(self.lag_window)
        if len(w) < _LAG_MIN_FIXES:
            return
        arr = np.asarray(w)
        _, ze, zn, oe, on, ve, vn = arr.T
        k = _LAG_STEP
        speed = np.hypot(ve, vn)
        ue, un = ve / np.maximum(speed, 1e-6), vn / np.maximum(speed, 1e-6)
        ue, un = 0.5 * (ue[k:] + ue[:-k]), 0.5 * (un[k:] + un[:-k])
        dz = (ze[k:] - ze[:-k]) * ue + (zn[k:] - zn[:-k]) * un
        do = (oe[k:] - oe[:-k]) * ue + (on[k:] - on[:-k]) * un
        dv = (ve[k:] - ve[:-k]) * ue + (vn[k:] - vn[:-k]) * un
        a = np.column_stack([-dv, do])
        coef, _, rank, _ = np.linalg.lstsq(a, dz - do, rcond=None)
        if rank < 2:
            return
        resid = dz - do - a @ coef
        sigma2 = float(resid @ resid) / max(1, len(resid) - 2)
        try:
            se = math.sqrt(sigma2 * float(np.linalg.inv(a.T @ a)[0, 0]))
        except np.linalg.LinAlgError:
            return
        lag = float(coef[0])
        self.latency_fit = (lag, se)
        if se < LATENCY_SE_S and 0.0 <= lag <= 1.0:
            self.latency = lag if not self.latency_fitted \
                else self.latency + 0.3 * (lag - self.latency)
            self.latency_fitted = True
            self.counters["gnss_latency_fits"] += 1


def _fix_std(fix: Fix, default: float) -> float:
    if fix.std_lat_m is not None and fix.std_lon_m is not None:
        return max(0.05, math.hypot(fix.std_lat_m, fix.std_lon_m) / math.sqrt(2.0))
    if fix.hdop is not None:
        return max(0.3, 1.5 * fix.hdop)  # a UERE of ~1.5 m
    return default


def _interp(samples: deque[tuple[float, float]], t: float) -> float | None:
    if not samples or t < samples[0][0] or t > samples[-1][0]:
        return None
    return _interp_lists([s[0] for s in samples], [s[1] for s in samples], t)


def _interp_lists(ts: list[float], vs: list[float], t: float) -> float | None:
    import bisect

    if not ts or t < ts[0] or t > ts[-1]:
        return None
    i = bisect.bisect_right(ts, t)
    if i >= len(ts):
        return vs[-1]
    t0, t1 = ts[i - 1], ts[i]
    return vs[i - 1] + (vs[i] - vs[i - 1]) * ((t - t0) / (t1 - t0) if t1 > t0 else 0.0)


def _flag(value: Any) -> bool | None:
    if value is None:
        return None
    if isinstance(value, str):
        return value.strip().lower() not in ("0", "off", "false", "no", "")
    return bool(value)


def _gear(value: Any) -> str | None:
    return None if value is None else str(value).strip().upper()[:1] or None
