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
    """The paper's constant-acceleration Kalman filter, per ENU axis (module docstring)."""

    name = "kf"

    def __init__(self, q: float = JERK_PSD, r: tuple[float, float, float] = PAPER_R,
                 min_heading_speed: float = MIN_HEADING_SPEED, anchor: bool = True) -> None:
        if not q >= 0.0 or not all(v > 0.0 for v in r):
            raise ValueError(f"need q >= 0 and positive variances, got q={q}, r={r}")
        self.q = q
        self.r = np.diag(r)
        self.min_heading_speed = min_heading_speed
        self.anchor = anchor
        self.reset()

    def reset(self) -> None:
        """Forget the filtered state."""
        self._t: float | None = None
        self._state = np.zeros((3, 2))  # set by the first update
        self._cov = np.zeros((3, 3))
        self._heading = 0.0
        self._anchor = np.zeros(2)  # last received position minus the filtered one

    def update(self, obs: Observation) -> None:
        """Time update to ``obs.t`` and measurement update with ``obs`` (ignored if not newer)."""
        check_observation(obs)
        if self._t is not None and obs.t <= self._t:
            return
        z = measurement(obs)
        if self._t is None:
            self._state, self._cov = z, self.r.copy()
        else:
            dt = obs.t - self._t
            a = transition(dt)
            prior = a @ self._state
            cov = a @ self._cov @ a.T + process_noise(dt, self.q)
            gain = np.linalg.solve(cov + self.r, cov).T  # P (P + R)⁻¹, both symmetric
            keep = np.eye(3) - gain
            self._state = prior + gain @ (z - prior)
            cov = keep @ cov @ keep.T + gain @ self.r @ gain.T  # Joseph form
            self._cov = 0.5 * (cov + cov.T)
        self._t, self._heading = obs.t, obs.heading
        if self.anchor:
            self._anchor = np.array([obs.x, obs.y]) - self._state[0]

    def predict(self, t: float) -> Prediction:
        """The filtered state propagated to ``t`` (time update only; the filter is unchanged)."""
        if self._t is None:
            raise LookupError("no observation yet")
        dt = elapsed(self._t, t)
        a = transition(dt)
        row = a[0]
        var = float(row @ self._cov @ row) + self.q * dt**5 / 20.0
        h = math.radians(self._heading)
        along = np.array([math.sin(h), math.cos(h)])
        u0 = float(self._state[1] @ along)
        a_h = float(self._state[2] @ along)
        if a_h < 0.0 and dt * -a_h >= u0:
            stopped = transition(max(u0, 0.0) / -a_h)[0] @ self._state + self._anchor
            return Prediction(float(stopped[0]), float(stopped[1]), 0.0,
                              wrap_heading(self._heading), var, var, self.name)
        p, v = a[:2] @ self._state
        p = p + self._anchor
        speed = math.hypot(v[0], v[1])
        heading = (math.degrees(math.atan2(v[0], v[1])) if speed >= self.min_heading_speed
                   else self._heading)
        return Prediction(float(p[0]), float(p[1]), speed, wrap_heading(heading), var, var,
                          self.name)
