"""The Kalman filter baseline with constant-acceleration dynamics (KF).

Valiente et al., "Context-Aware Target Classification with Hybrid Gaussian Process
prediction for Cooperative Vehicle Safety systems", section "Prediction Baseline Models",
subsection "Kalman Filter Model": state ``[x, s, a]`` (position, speed, acceleration), the
CA transition ``A = [[1, T, T²/2], [0, 1, T], [0, 0, 1]]``, measurement noise
``R = diag(10, 1, 0.5)``; on a received BSM a time update and a measurement update run, on
a lost one only the time update.

Our reading, for the two-dimensional ENU frame:

* State.  The paper's ``[x, s, a]`` per ENU axis: ``[p, v, a]`` for east and for north.
  The two axes share ``A``, ``Q``, ``R`` and the initial covariance and are not coupled,
  so they are two filters with one common 3×3 covariance ``P``; the state is stored as a
  3×2 array (rows ``p, v, a``; columns east, north).
* Measurement.  The paper prints ``H = [1 1 1]``, which would add a position, a speed and an
  acceleration into one number and cannot go with a 3×3 ``R``; ``R``'s three variances say
  that each state component is measured, i.e. ``H = I₃``.  A BSM gives per axis the
  position, the velocity ``s·(sin h, cos h)`` and the acceleration vector
  ``a·(sin h, cos h) + s·ω·(cos h, −sin h)``: the longitudinal acceleration along the
  heading plus the centripetal ``s·ω`` (yaw rate ω in rad/s, clockwise, so it points to the
  right of the heading).  The centripetal term is what makes the 1-D model of the paper
  work in 2-D: without it the filter is told that a turning vehicle has no lateral
  acceleration and lags every curve by metres.
* R = diag(10 m², 1 (m/s)², 0.5 (m/s²)²) per axis: the paper's variances of the position,
  speed and acceleration measurements, applied to each ENU component (position standard
  deviation 3.2 m, GNSS grade; the speed variance taken as isotropic in velocity).
* Q.  Continuous white-noise jerk (Bar-Shalom, Li & Kirubarajan 2001, §6.2.3, "Wiener
  process acceleration"): per axis, over ``dt``,
  ``Q = q·[[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]]``.  Being the
  exact integral over ``dt`` it is right for any interval, so a gap of lost messages is
  crossed in one step with the actual ``dt``.  ``q`` is the jerk's power spectral density in
  m²/s⁵; the default :data:`JERK_PSD` = 1 m²/s⁵ lets the acceleration change by
  ``√(q·T)`` ≈ 0.32 m/s² (one standard deviation) over a 100 ms BSM period — jerk of a few
  m/s³, the order of ordinary driving (Bar-Shalom's guide: ``√(q·T)`` of the order of the
  acceleration change over one period).  The paper gives no ``Q``.
* Initialisation.  The first BSM is taken as the state with ``P = R``.

Anchoring.  The forecast starts from the last *received* position: the filter supplies the
motion (velocity and acceleration), and the offset between the BSM's position and the
filtered one at that instant is carried along.  So at a tick with a fresh BSM the estimate
is that BSM, as in the paper's table (KF PTE 0.000 at PER 0), and the forecast does not
jump when a gap begins.  ``anchor=False`` reports the filtered position instead (it smooths
GNSS noise; it also lags by up to R's 3.2 m on real data).

``predict(t)`` propagates the filtered state to ``t`` without changing it and reports
``var_x = var_y`` = the propagated position variance, speed ``|v|`` and the heading of
``v``; below :data:`MIN_HEADING_SPEED` the velocity's direction is noise and the last
observed heading is reported.

Stop rule (the one of the "ca" predictor): the velocity component along the last observed
heading is ``u(τ) = u₀ + a_h·τ``.  If the filtered acceleration decelerates it
(``a_h < 0``), the forecast stops where ``u`` reaches 0 (at once if ``u₀ ≤ 0``) and stays
there with speed 0 and the last observed heading, instead of reversing.  The variance is
still the one propagated to ``t``: the rule moves the mean only.

Duplicates, validation and the time tolerance are as in :mod:`catc.predict.kinematic`.  At
the last observation's time the filtered (not the observed) state is returned.
"""

from __future__ import annotations

import math

import numpy as np

from catc.predict.base import Observation, Prediction
from catc.predict.kinematic import check_observation, elapsed, wrap_heading

#: The paper's measurement noise variances: position m², speed (m/s)², acceleration (m/s²)².
PAPER_R = (10.0, 1.0, 0.5)
#: Default white-jerk power spectral density q (m²/s⁵), see the module docstring.
JERK_PSD = 1.0
#: Below this speed (m/s) the heading of the velocity is noise (as in catc.datasets.derive).
MIN_HEADING_SPEED = 1.0


def transition(dt: float) -> np.ndarray:
    """The constant-acceleration transition matrix ``A`` over ``dt`` seconds."""
    return np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])


def process_noise(dt: float, q: float) -> np.ndarray:
    """White-jerk process noise covariance over ``dt`` seconds, jerk PSD ``q`` (m²/s⁵)."""
    d2 = dt * dt
    d3 = d2 * dt
    return q * np.array([[d3 * d2 / 20.0, d2 * d2 / 8.0, d3 / 6.0],
                         [d2 * d2 / 8.0, d3 / 3.0, d2 / 2.0],
                         [d3 / 6.0, d2 / 2.0, dt]])


def measurement(obs: Observation) -> np.ndarray:
    """The BSM as a 3×2 measurement: rows position, velocity, acceleration; columns E, N.

    The acceleration is longitudinal along the heading plus centripetal (speed × yaw rate)
    to its right, for the clockwise-positive yaw rate.
    """
    h = math.radians(obs.heading)
    east, north = math.sin(h), math.cos(h)
    lateral = obs.speed * math.radians(obs.yaw_rate)
    return np.array([[obs.x, obs.y],
                     [obs.speed * east, obs.speed * north],
                     [obs.accel * east + lateral * north, obs.accel * north - lateral * east]])


class KalmanPredictor:
    """The paper's constant-acceleration Kalman filter, per ENU axis (module docstring).

    The arithmetic is written out on Python floats: the covariance is symmetric 3×3 (six
    numbers), the state two columns of three, and numpy's per-call overhead on 3×3
    matrices cost 4× the filter itself in a sweep (20 µs per sample, now ~5).  The
    matrix form it computes (``tests/test_kinematic.py`` checks the two agree):
    ``x⁻ = A x``, ``P⁻ = A P Aᵀ + Q``, ``K = P⁻ (P⁻ + R)⁻¹``, ``x = x⁻ + K (z − x⁻)``,
    ``P = (I − K) P⁻ (I − K)ᵀ + K R Kᵀ`` (Joseph form).
    """

    name = "kf"

    def __init__(self, q: float = JERK_PSD, r: tuple[float, float, float] = PAPER_R,
                 min_heading_speed: float = MIN_HEADING_SPEED, anchor: bool = True) -> None:
        if not q >= 0.0 or not all(v > 0.0 for v in r):
            raise ValueError(f"need q >= 0 and positive variances, got q={q}, r={r}")
        self.q = q
        self.r = np.diag(r)
        self._r = tuple(float(v) for v in r)
        compiled_kf_step()  # compiled (or loaded) now, with the first filter
        self.min_heading_speed = min_heading_speed
        self.anchor = anchor
        self.reset()

    def reset(self) -> None:
        """Forget the filtered state."""
        self._t: float | None = None
        # state rows p, v, a of the east and the north axis; P as (p00 p01 p02 p11 p12 p22)
        self._east = self._north = (0.0, 0.0, 0.0)
        self._p = (0.0,) * 6
        self._heading = 0.0
        self._anchor = (0.0, 0.0)  # last received position minus the filtered one

    @property
    def state(self) -> np.ndarray:
        """The filtered state, 3×2: rows position, velocity, acceleration; columns E, N."""
        return np.array([self._east, self._north]).T

    @property
    def covariance(self) -> np.ndarray:
        """The filtered 3×3 covariance shared by both axes."""
        p00, p01, p02, p11, p12, p22 = self._p
        return np.array([[p00, p01, p02], [p01, p11, p12], [p02, p12, p22]])

    def update(self, obs: Observation) -> None:
        """Time update to ``obs.t`` and measurement update with ``obs`` (ignored if not newer)."""
        check_observation(obs)
        if self._t is not None and obs.t <= self._t:
            return
        h = math.radians(obs.heading)
        se, ce = math.sin(h), math.cos(h)
        lat = obs.speed * math.radians(obs.yaw_rate)
        ze = (obs.x, obs.speed * se, obs.accel * se + lat * ce)
        zn = (obs.y, obs.speed * ce, obs.accel * ce - lat * se)
        r0, r1, r2 = self._r
        if self._t is None:
            self._east, self._north = ze, zn
            self._p = (r0, 0.0, 0.0, r1, 0.0, r2)
        else:
            dt = obs.t - self._t
            self._east, self._north, self._p = _COMPILED_KF_STEP(
                dt, self.q, self._r, self._p, self._east, self._north, ze, zn)
        self._t, self._heading = obs.t, obs.heading
        if self.anchor:
            self._anchor = (obs.x - self._east[0], obs.y - self._north[0])

    def predict(self, t: float) -> Prediction:
        """The filtered state propagated to ``t`` (time update only; the filter is unchanged)."""
        if self._t is None:
            raise LookupError("no observation yet")
        dt = elapsed(self._t, t)
        h2 = 0.5 * dt * dt
        p00, p01, p02, p11, p12, p22 = self._p
        # row (1, dt, dt²/2) of A through P: the propagated position variance
        var = (p00 + 2.0 * dt * p01 + 2.0 * h2 * p02 + dt * dt * p11 + 2.0 * dt * h2 * p12
               + h2 * h2 * p22) + self.q * dt**5 / 20.0
        pe, ve, ae = self._east
        pn, vn, an = self._north
        stop = stop_point(pe, ve, ae, pn, vn, an, self._heading, dt)
        if stop is not None:
            x, y = stop[0] + self._anchor[0], stop[1] + self._anchor[1]
            return Prediction(x, y, 0.0, wrap_heading(self._heading), var, var, self.name)
        x = pe + dt * ve + h2 * ae + self._anchor[0]
        y = pn + dt * vn + h2 * an + self._anchor[1]
        vx, vy = ve + dt * ae, vn + dt * an
        speed = math.hypot(vx, vy)
        heading = (math.degrees(math.atan2(vx, vy)) if speed >= self.min_heading_speed
                   else self._heading)
        return Prediction(x, y, speed, wrap_heading(heading), var, var, self.name)

    def position(self, t: float) -> tuple[float, float]:
        """``predict(t)``'s (x, y) alone, the same arithmetic: what a branch score needs."""
        if self._t is None:
            raise LookupError("no observation yet")
        dt = elapsed(self._t, t)
        pe, ve, ae = self._east
        pn, vn, an = self._north
        stop = stop_point(pe, ve, ae, pn, vn, an, self._heading, dt)
        if stop is not None:
            return stop[0] + self._anchor[0], stop[1] + self._anchor[1]
        h2 = 0.5 * dt * dt
        return pe + dt * ve + h2 * ae + self._anchor[0], pn + dt * vn + h2 * an + self._anchor[1]


_COMPILED_KF_STEP = None


def compiled_kf_step():
    """:func:`_kf_step` compiled (numba, cached per machine): the same IEEE operations in
    the same order (no fast-math, no fused multiply-adds; tests/test_kinematic.py checks
    it bit for bit), 1.2 µs a call against 4.1 µs (``python bench/step_parts.py``).  The
    KF runs beside every HGP as a branch, once per accepted BSM (250 a tick at 500 RVs).
    Compiled, or loaded from numba's cache, when the first filter is made, not on import:
    a process that never filters never compiles it (a cold cache, or another CPU such as
    the SocketCAN tests' emulated one, costs a compilation).  The explicit signature
    converts ints to floats at the call."""
    global _COMPILED_KF_STEP
    if _COMPILED_KF_STEP is None:
        from numba import njit, types

        f3, f6 = types.UniTuple(types.float64, 3), types.UniTuple(types.float64, 6)
        _COMPILED_KF_STEP = njit(types.Tuple((f3, f3, f6))(
            types.float64, types.float64, f3, f6, f3, f3, f3, f3),
            cache=True, error_model="numpy")(_kf_step)
    return _COMPILED_KF_STEP


def stop_point(pe: float, ve: float, ae: float, pn: float, vn: float, an: float,
               heading_deg: float, dt: float) -> tuple[float, float] | None:
    """The stop rule of a constant-acceleration state (position, velocity, acceleration
    per ENU axis) propagated ``dt`` s: when its acceleration along the last observed
    heading decelerates it to a stop within ``dt`` (at once if it is not moving forward),
    the (x, y) where it stops; None when it does not stop (module docstring)."""
    hd = math.radians(heading_deg)
    se, ce = math.sin(hd), math.cos(hd)
    u0 = ve * se + vn * ce
    a_h = ae * se + an * ce
    if not (a_h < 0.0 and dt * -a_h >= u0):
        return None
    ts = max(u0, 0.0) / -a_h
    hs = 0.5 * ts * ts
    return pe + ts * ve + hs * ae, pn + ts * vn + hs * an


def _kf_step(dt: float, q: float, r: tuple[float, float, float], p: tuple, east: tuple,
             north: tuple, ze: tuple, zn: tuple) -> tuple[tuple, tuple, tuple]:
    """One time + measurement update of both axes (see :class:`KalmanPredictor`).  The
    filter runs it compiled (:func:`compiled_kf_step`)."""
    p00, p01, p02, p11, p12, p22 = p
    h2 = 0.5 * dt * dt
    # P⁻ = A P Aᵀ + Q, A = [[1, dt, dt²/2], [0, 1, dt], [0, 0, 1]]
    a0 = (p00 + dt * p01 + h2 * p02, p01 + dt * p11 + h2 * p12, p02 + dt * p12 + h2 * p22)
    a1 = (p01 + dt * p02, p11 + dt * p12, p12 + dt * p22)  # rows of A P
    d2 = dt * dt
    d3 = d2 * dt
    m00 = a0[0] + dt * a0[1] + h2 * a0[2] + q * d3 * d2 / 20.0
    m01 = a0[1] + dt * a0[2] + q * d2 * d2 / 8.0
    m02 = a0[2] + q * d3 / 6.0
    m11 = a1[1] + dt * a1[2] + q * d3 / 3.0
    m12 = a1[2] + q * d2 / 2.0
    m22 = p22 + q * dt
    # S = P⁻ + R and its inverse (adjugate over the determinant; S is SPD)
    r0, r1, r2 = r
    s00, s11, s22 = m00 + r0, m11 + r1, m22 + r2
    c00 = s11 * s22 - m12 * m12
    c01 = m02 * m12 - m01 * s22
    c02 = m01 * m12 - m02 * s11
    c11 = s00 * s22 - m02 * m02
    c12 = m01 * m02 - s00 * m12
    c22 = s00 * s11 - m01 * m01
    inv_det = 1.0 / (s00 * c00 + m01 * c01 + m02 * c02)
    i00, i01, i02 = c00 * inv_det, c01 * inv_det, c02 * inv_det
    i11, i12, i22 = c11 * inv_det, c12 * inv_det, c22 * inv_det
    # gain K = P⁻ S⁻¹ (element kij: row i, column j)
    k00 = m00 * i00 + m01 * i01 + m02 * i02
    k01 = m00 * i01 + m01 * i11 + m02 * i12
    k02 = m00 * i02 + m01 * i12 + m02 * i22
    k10 = m01 * i00 + m11 * i01 + m12 * i02
    k11 = m01 * i01 + m11 * i11 + m12 * i12
    k12 = m01 * i02 + m11 * i12 + m12 * i22
    k20 = m02 * i00 + m12 * i01 + m22 * i02
    k21 = m02 * i01 + m12 * i11 + m22 * i12
    k22 = m02 * i02 + m12 * i12 + m22 * i22
    # state: x⁻ = A x, then x⁻ + K (z − x⁻), per axis
    out = []
    for x, z in ((east, ze), (north, zn)):
        x0 = x[0] + dt * x[1] + h2 * x[2]
        x1 = x[1] + dt * x[2]
        x2 = x[2]
        e0, e1, e2 = z[0] - x0, z[1] - x1, z[2] - x2
        out.append((x0 + k00 * e0 + k01 * e1 + k02 * e2,
                    x1 + k10 * e0 + k11 * e1 + k12 * e2,
                    x2 + k20 * e0 + k21 * e1 + k22 * e2))
    # Joseph form: (I − K) P⁻ (I − K)ᵀ + K R Kᵀ with B = (I − K) P⁻, symmetrised: entry
    # (i, j) is the mean of the (i, j) and (j, i) expressions (equal on the diagonal)
    b00 = m00 - k00 * m00 - k01 * m01 - k02 * m02
    b01 = m01 - k00 * m01 - k01 * m11 - k02 * m12
    b02 = m02 - k00 * m02 - k01 * m12 - k02 * m22
    b10 = m01 - k10 * m00 - k11 * m01 - k12 * m02
    b11 = m11 - k10 * m01 - k11 * m11 - k12 * m12
    b12 = m12 - k10 * m02 - k11 * m12 - k12 * m22
    b20 = m02 - k20 * m00 - k21 * m01 - k22 * m02
    b21 = m12 - k20 * m01 - k21 * m11 - k22 * m12
    b22 = m22 - k20 * m02 - k21 * m12 - k22 * m22
    c00 = (b00 - b00 * k00 - b01 * k01 - b02 * k02
           + k00 * r0 * k00 + k01 * r1 * k01 + k02 * r2 * k02)
    c01 = 0.5 * ((b01 - b00 * k10 - b01 * k11 - b02 * k12
                  + k00 * r0 * k10 + k01 * r1 * k11 + k02 * r2 * k12)
                 + (b10 - b10 * k00 - b11 * k01 - b12 * k02
                    + k10 * r0 * k00 + k11 * r1 * k01 + k12 * r2 * k02))
    c02 = 0.5 * ((b02 - b00 * k20 - b01 * k21 - b02 * k22
                  + k00 * r0 * k20 + k01 * r1 * k21 + k02 * r2 * k22)
                 + (b20 - b20 * k00 - b21 * k01 - b22 * k02
                    + k20 * r0 * k00 + k21 * r1 * k01 + k22 * r2 * k02))
    c11 = (b11 - b10 * k10 - b11 * k11 - b12 * k12
           + k10 * r0 * k10 + k11 * r1 * k11 + k12 * r2 * k12)
    c12 = 0.5 * ((b12 - b10 * k20 - b11 * k21 - b12 * k22
                  + k10 * r0 * k20 + k11 * r1 * k21 + k12 * r2 * k22)
                 + (b21 - b20 * k10 - b21 * k11 - b22 * k12
                    + k20 * r0 * k10 + k21 * r1 * k11 + k22 * r2 * k12))
    c22 = (b22 - b20 * k20 - b21 * k21 - b22 * k22
           + k20 * r0 * k20 + k21 * r1 * k21 + k22 * r2 * k22)
    return out[0], out[1], (c00, c01, c02, c11, c12, c22)
