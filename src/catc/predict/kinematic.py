"""Kinematic baselines: hold (BSM-dependent), constant speed, constant acceleration, CTRV.

Valiente et al., "Context-Aware Target Classification with Hybrid Gaussian Process
prediction for Cooperative Vehicle Safety systems", section "Prediction Baseline Models",
subsection "Kinematic Models".  The paper writes CS and CA as one-dimensional time updates
of ``[x, s, a]`` (position along the path, speed, acceleration) stepped by ``T_s``; here each
is its closed form evaluated at the actual time since the last received BSM, on the straight
line along the last heading.  CTRV (constant turn rate and velocity) is not in the paper; it
is the usual next kinematic model, using the BSM's yaw rate.

Rules shared by every predictor in this module (and :mod:`catc.predict.kalman`):

* ``predict`` before the first observation raises ``LookupError("no observation yet")``.
* An observation whose ``t`` is at or before the last accepted one is a duplicate or a
  replay and is ignored (the protocol's "times must not decrease; duplicates are
  ignored").  Invalid values (non-finite, negative speed) raise ``ValueError``; J2735
  Speed is unsigned, a reversing vehicle is signalled by its transmission state.
* ``predict(t)`` needs ``t`` at or after the last observation.  A ``t`` earlier by at most
  :data:`TIME_TOLERANCE` (time-stamp rounding, e.g. ``0.1 * k`` against a parsed time) is
  answered as the last observation's time; earlier still raises ``ValueError``.
* At the last observation's time, hold, CS, CA and CTRV return that observation's state
  exactly (heading wrapped to [0, 360)).
* The kinematic models have no uncertainty: ``var_x``/``var_y`` are NaN.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

from catc.predict.base import Observation, Prediction

#: How far (s) before the last observation ``predict`` still answers at that observation.
TIME_TOLERANCE = 1e-6

#: Below this |ω·dt/2| (rad) CTRV's sin(u)/u is evaluated by its series (the straight line).
_SINC_SERIES_BELOW = 1e-6


def wrap_heading(deg: float) -> float:
    """``deg`` wrapped into [0, 360) (``%`` alone can return 360.0 for tiny negatives)."""
    wrapped = deg % 360.0
    return 0.0 if wrapped >= 360.0 else wrapped


def check_observation(obs: Observation) -> None:
    """Raise ``ValueError`` unless every field is finite and the speed is not negative."""
    fin = math.isfinite  # spelled out: a generator here cost more than a CA update
    if not (fin(obs.t) and fin(obs.x) and fin(obs.y) and fin(obs.speed) and fin(obs.heading)
            and fin(obs.accel) and fin(obs.yaw_rate)):
        raise ValueError(f"non-finite value in {obs}")
    if obs.speed < 0.0:
        raise ValueError(f"negative speed in {obs}")


def elapsed(last_t: float, t: float) -> float:
    """Seconds from the last observation to ``t`` (see :data:`TIME_TOLERANCE`)."""
    dt = t - last_t
    if dt >= 0.0:
        return dt
    if dt >= -TIME_TOLERANCE:
        return 0.0
    raise ValueError(f"t={t} is before the last observation at t={last_t}")


class _FromLastObservation(ABC):
    """A model that extrapolates from the last accepted observation alone."""

    name: str

    def __init__(self) -> None:
        self._last: Observation | None = None

    def update(self, obs: Observation) -> None:
        """Keep ``obs`` as the last observation, unless it is not newer (then ignore it)."""
        check_observation(obs)
        if self._last is not None and obs.t <= self._last.t:
            return
        self._last = obs

    def predict(self, t: float) -> Prediction:
        """The model's state at time ``t`` (at or after the last observation)."""
        if self._last is None:
            raise LookupError("no observation yet")
        return self._extrapolate(self._last, elapsed(self._last.t, t))

    def position(self, t: float) -> tuple[float, float]:
        """``predict(t)``'s (x, y): what a branch score needs (subclasses may skip the rest)."""
        p = self.predict(t)
        return p.x, p.y

    def reset(self) -> None:
        """Forget the last observation."""
        self._last = None

    @abstractmethod
    def _extrapolate(self, obs: Observation, dt: float) -> Prediction:
        """The state ``dt >= 0`` seconds after ``obs``."""


def along_heading(obs: Observation, distance: float, speed: float, name: str) -> Prediction:
    """The state ``distance`` metres from ``obs`` along its heading, moving at ``speed``."""
    h = math.radians(obs.heading)
    return Prediction(obs.x + distance * math.sin(h), obs.y + distance * math.cos(h), speed,
                      wrap_heading(obs.heading), source=name)


class HoldPredictor(_FromLastObservation):
    """The BSM-dependent baseline ("No estimation"): ``X(t+1) = X(t)``.

    Paper, "Kinematic Models": the last received position is kept until the next BSM; the
    last received speed and heading are reported with it.
    """

    name = "hold"

    def _extrapolate(self, obs: Observation, dt: float) -> Prediction:
        return Prediction(obs.x, obs.y, obs.speed, wrap_heading(obs.heading), source=self.name)


class ConstantSpeedPredictor(_FromLastObservation):
    """Constant speed (CS): a straight line at the last speed along the last heading.

    Paper, "Kinematic Models", the CS time update ``x ← x + T_s·s`` with the speed held,
    here in closed form: ``x(t) = x₀ + s₀·dt`` along the heading.
    """

    name = "cs"

    def _extrapolate(self, obs: Observation, dt: float) -> Prediction:
        return along_heading(obs, obs.speed * dt, obs.speed, self.name)


class ConstantAccelerationPredictor(_FromLastObservation):
    """Constant acceleration (CA) along the last heading, with a stop rule.

    Paper, "Kinematic Models", the CA time update ``x ← x + T_s·s + T_s²/2·a``,
    ``s ← s + T_s·a``, here in closed form.  Stop rule (ours; the paper notes that plain CA
    diverges for long gaps): a decelerating vehicle stops, it does not reverse.  Once the
    speed would reach 0, at ``dt = s₀/|a|``, the vehicle stays at that point with speed 0.
    """

    name = "ca"

    def _extrapolate(self, obs: Observation, dt: float) -> Prediction:
        s, a = obs.speed, obs.accel
        if a < 0.0 and dt >= s / -a:
            return along_heading(obs, s * s / (-2.0 * a), 0.0, self.name)
        return along_heading(obs, s * dt + 0.5 * a * dt * dt, s + a * dt, self.name)

    def position(self, t: float) -> tuple[float, float]:
        """``predict(t)``'s (x, y) alone (the same arithmetic as :func:`along_heading`)."""
        obs = self._last
        if obs is None:
            raise LookupError("no observation yet")
        dt = elapsed(obs.t, t)
        s, a = obs.speed, obs.accel
        d = s * s / (-2.0 * a) if a < 0.0 and dt >= s / -a else s * dt + 0.5 * a * dt * dt
        h = math.radians(obs.heading)
        return obs.x + d * math.sin(h), obs.y + d * math.cos(h)


class CtrvPredictor(_FromLastObservation):
    """Constant turn rate and velocity (CTRV): a circular arc from the last speed and yaw rate.

    An extension of the paper's "Kinematic Models" using the BSM's yaw rate ω (deg/s,
    positive clockwise, the same sense as the heading h).  The exact arc is

        h(t) = h₀ + ω·dt
        x(t) = x₀ + s·dt·sin(h₀ + ω·dt/2)·sinc(ω·dt/2)
        y(t) = y₀ + s·dt·cos(h₀ + ω·dt/2)·sinc(ω·dt/2),   sinc(u) = sin(u)/u

    which equals the usual ``s/ω·(cos h₀ − cos h)`` form but never divides by ω: as ω → 0,
    sinc → 1 and the arc becomes the CS straight line.
    """

    name = "ctrv"

    def _extrapolate(self, obs: Observation, dt: float) -> Prediction:
        half_turn = math.radians(obs.yaw_rate) * dt / 2.0
        if abs(half_turn) < _SINC_SERIES_BELOW:
            sinc = 1.0 - half_turn * half_turn / 6.0
        else:
            sinc = math.sin(half_turn) / half_turn
        mid = math.radians(obs.heading) + half_turn
        chord = obs.speed * dt * sinc
        return Prediction(obs.x + chord * math.sin(mid), obs.y + chord * math.cos(mid),
                          obs.speed, wrap_heading(obs.heading + obs.yaw_rate * dt),
                          source=self.name)
