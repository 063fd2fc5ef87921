"""Interacting Multiple Model filter (IMM): constant velocity, constant acceleration and
coordinated turn, mixed by a Markov chain (Blom & Bar-Shalom 1988; Bar-Shalom, Li &
Kirubarajan 2001, §11.6.6).

The standard tracker of automotive sensor fusion, and the strongest kinematic peer the
HGP is measured against (``imm`` in :mod:`catc.predict`).

State, per model, ``[pE, vE, aE, pN, vN, aN]``: position, velocity and acceleration of the
east and the north axis (the order of filterpy's kinematic filters).  The BSM measures all
six, as for the paper's KF (:func:`catc.predict.kalman.measurement`: the acceleration
vector is the longitudinal acceleration along the heading plus the centripetal
speed × yaw rate), with the paper's ``R = diag(10, 1, 0.5)`` per axis.

Models (transition ``F`` over ``dt``, white process noise ``Q``):

* **CV**, constant velocity: ``p += v·dt``, ``v`` kept, ``a`` = 0; white acceleration of
  PSD :data:`Q_CV` on ``p, v`` (Bar-Shalom §6.2.2, continuous white-noise acceleration)
  and ``Q_CV·dt`` on ``a`` (what the model calls acceleration is that noise).
* **CA**, constant acceleration: the KF's model (:mod:`catc.predict.kalman`), white jerk
  of PSD :data:`~catc.predict.kalman.JERK_PSD`.
* **CT**, coordinated turn with a known rate (Bar-Shalom §11.7.1): the velocity turns at
  the last BSM's yaw rate ω, the position integrates the turning velocity, and the
  acceleration is the centripetal ω × v; noise as CV's with PSD :data:`Q_CT`.  With the
  rate taken from the BSM the model is linear, so every model is a linear Kalman filter
  and the IMM's mixing is exact in the Gaussian sense.

The Markov chain stays in a model with probability :data:`P_STAY` per 0.1 s BSM period
(switching to each other model with half the rest); a gap of ``k`` periods uses ``Mᵏ``.

One IMM cycle per received BSM, in the order of filterpy's ``IMMEstimator`` (``predict``
then ``update``): mixing probabilities ``ω_ij = M_ij μ_i / c̄_j`` with ``c̄ = μ M``, mixed
states and covariances (with the spread of the means), each model's time update over the
actual ``dt`` and Kalman measurement update (Joseph form), mode probabilities
``μ_j ∝ c̄_j · N(y_j; 0, S_j)``, and the combined estimate.  ``tests/test_imm.py`` runs the
same cycle through filterpy's ``IMMEstimator`` and compares every state.

Why not filterpy itself: it installs and is maintained (2.0.0, 2026-10), but its IMM with
three 6-state ``KalmanFilter`` objects costs ~400 µs per BSM here (Python loops over
filters and matrix elements), 80× the KF; a sweep replays millions of samples and the OBU
hundreds of RVs per tick.  This one, the three models stacked in numpy arrays, costs
~90 µs per BSM with one prediction (the KF: 12 µs), and is checked against filterpy's in
the tests.

Prediction (``predict(t)``, the filter unchanged): each model's mean propagated to ``t``
(CA with the stop rule of the KF: no reversing under deceleration), weighted by the mode
probabilities of the last BSM; the position variance is the mixture's (each model's
propagated variance plus the spread of the means).  The probabilities are not carried
over the gap by the chain (``μ Mᵏ``): that drifts them towards uniform (``0.925ᵏ`` of the
difference is left after k periods), which pulled a turn's forecast towards CV's straight
line: 0.42 m against 0.02 m after 1.1 s in ``tests/test_imm.py``'s 12°/s turn.  As for the KF the
forecast starts from the last *received* position (the offset to the filtered one is
carried), so a fresh BSM is its own estimate.
"""

from __future__ import annotations

import math

import numpy as np

from catc.predict.base import Observation, Prediction
from catc.predict.kalman import (
    JERK_PSD,
    MIN_HEADING_SPEED,
    PAPER_R,
    process_noise,
    stop_point,
)
from catc.predict.kinematic import check_observation, elapsed, wrap_heading

#: The BSM period (s): the Markov chain's step.
DT = 0.1
#: Probability of staying in a model for one BSM period.
P_STAY = 0.95
#: White-acceleration PSD (m²/s³) of the CV model and of the CT model: chosen on the HGP
#: bank's training trips (four OpenACC dynamic runs, the NGSIM pairs; PTE95 at PER 30 and
#: 90 %, seed 0) from 0.01, 0.05, 0.5, 2 and 8, as the lowest mean ratio to the KF's
#: PTE95; see docs/log/2026-11-25-imm.md.
Q_CV = 8.0
Q_CT = 8.0
#: Below |ω| (rad/s) the CT model's sin(ωt)/ω terms use their series.
_SMALL_RATE = 1e-6
#: Model names, in the order of the state stack.
MODELS = ("cv", "ca", "ct")

_LOG_2PI = math.log(2.0 * math.pi)


def markov(p_stay: float = P_STAY, n: int = 3) -> np.ndarray:
    """The per-period mode transition matrix: ``p_stay`` on the diagonal, the rest shared."""
    m = np.full((n, n), (1.0 - p_stay) / (n - 1))
    np.fill_diagonal(m, p_stay)
    return m


def _axis_block(f3: np.ndarray) -> np.ndarray:
    """A 6×6 matrix with the same 3×3 block for both axes."""
    out = np.zeros((6, 6))
    out[:3, :3] = f3
    out[3:, 3:] = f3
    return out


#: Per (dt, PSDs): CV's and CA's F and every model's Q (they depend on nothing else);
#: bounded, BSM gaps are a few multiples of 0.1 s.
_FIXED: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _fixed(dt: float, q: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """``transitions(dt, 0)`` with CT's block left zero, and ``noises(dt, *q)``."""
    key = (round(dt, 9), q)
    got = _FIXED.get(key)
    if got is None:
        if len(_FIXED) > 512:
            _FIXED.clear()
        f = np.zeros((3, 6, 6))
        f[0] = _axis_block(np.array([[1.0, dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]))
        f[1] = _axis_block(np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt],
                                     [0.0, 0.0, 1.0]]))
        got = _FIXED[key] = (f, noises(dt, *q))
    return got


def transitions(dt: float, omega: float, q: tuple = (0.0, 0.0, 0.0)) -> np.ndarray:
    """``F`` of CV, CA and CT over ``dt`` (CT turning at ``omega`` rad/s, clockwise
    positive), shape (3, 6, 6)."""
    f = _fixed(dt, q)[0].copy()
    th = omega * dt
    c, s = math.cos(th), math.sin(th)
    if abs(omega) < _SMALL_RATE:
        sw, cw = dt, 0.5 * omega * dt * dt  # sin(ωt)/ω, (1 − cos ωt)/ω
    else:
        sw, cw = s / omega, (1.0 - c) / omega
    # Clockwise turn in ENU: vE' = c vE + s vN, vN' = −s vE + c vN.
    ct = f[2]
    ct[0, 0] = ct[3, 3] = 1.0
    ct[0, 1], ct[0, 4] = sw, cw
    ct[3, 1], ct[3, 4] = -cw, sw
    ct[1, 1], ct[1, 4] = c, s
    ct[4, 1], ct[4, 4] = -s, c
    # Centripetal acceleration of the turned velocity: aE = ω vN', aN = −ω vE'.
    ct[2, 1], ct[2, 4] = omega * -s, omega * c
    ct[5, 1], ct[5, 4] = -omega * c, -omega * s
    return f


def _white_accel(dt: float, q: float) -> np.ndarray:
    """Per-axis noise of a constant-velocity model with white acceleration PSD ``q``."""
    return q * np.array([[dt**3 / 3.0, dt * dt / 2.0, 0.0], [dt * dt / 2.0, dt, 0.0],
                         [0.0, 0.0, dt]])


def noises(dt: float, q_cv: float = Q_CV, q_ca: float = JERK_PSD,
           q_ct: float = Q_CT) -> np.ndarray:
    """``Q`` of CV, CA and CT over ``dt``, shape (3, 6, 6)."""
    return np.stack([_axis_block(_white_accel(dt, q_cv)), _axis_block(process_noise(dt, q_ca)),
                     _axis_block(_white_accel(dt, q_ct))])


def measurement_vector(obs: Observation) -> np.ndarray:
    """The BSM as the state-ordered measurement ``[pE, vE, aE, pN, vN, aN]``."""
    h = math.radians(obs.heading)
    se, ce = math.sin(h), math.cos(h)
    lat = obs.speed * math.radians(obs.yaw_rate)
    return np.array([obs.x, obs.speed * se, obs.accel * se + lat * ce,
                     obs.y, obs.speed * ce, obs.accel * ce - lat * se])


class ImmPredictor:
    """IMM of CV, CA and CT (module docstring)."""

    name = "imm"

    def __init__(self, p_stay: float = P_STAY, q_cv: float = Q_CV, q_ca: float = JERK_PSD,
                 q_ct: float = Q_CT, r: tuple[float, float, float] = PAPER_R,
                 min_heading_speed: float = MIN_HEADING_SPEED) -> None:
        if not 0.0 < p_stay < 1.0:
            raise ValueError(f"p_stay must be in (0, 1), got {p_stay}")
        if not (q_cv >= 0.0 and q_ca >= 0.0 and q_ct >= 0.0) or not all(v > 0.0 for v in r):
            raise ValueError(f"need PSDs >= 0 and positive variances, got q=({q_cv}, {q_ca}, "
                             f"{q_ct}), r={r}")
        self.m = markov(p_stay)
        self.q = (q_cv, q_ca, q_ct)
        self.r = np.diag(list(r) * 2)
        self.min_heading_speed = min_heading_speed
        self._powers: dict[int, np.ndarray] = {1: self.m}
        self.reset()

    def reset(self) -> None:
        """Forget the filtered state."""
        self._t: float | None = None
        self.x = np.zeros((3, 6))  # per model state
        self.p = np.zeros((3, 6, 6))  # per model covariance
        self.mu = np.full(3, 1.0 / 3.0)  # mode probabilities
        self._omega = 0.0  # the last BSM's yaw rate, rad/s clockwise
        self._heading = 0.0
        self._anchor = np.zeros(2)

    # -- the filter ---------------------------------------------------------------------
    def _mk(self, dt: float) -> np.ndarray:
        """The mode transition matrix over ``dt`` (``Mᵏ`` for k BSM periods, at least 1)."""
        k = max(1, round(dt / DT))
        mk = self._powers.get(k)
        if mk is None:
            mk = self._powers[k] = np.linalg.matrix_power(self.m, k)
        return mk

    @property
    def state(self) -> np.ndarray:
        """The combined (mode-weighted) state ``[pE, vE, aE, pN, vN, aN]``."""
        return self.mu @ self.x

    def update(self, obs: Observation) -> None:
        """One IMM cycle to ``obs.t`` with ``obs`` as the measurement (ignored if not newer)."""
        check_observation(obs)
        if self._t is not None and obs.t <= self._t:
            return
        z = measurement_vector(obs)
        if self._t is None:
            self.x[:] = z
            self.p[:] = self.r
        else:
            dt = obs.t - self._t
            mk = self._mk(dt)
            # Mixing.
            cbar = self.mu @ mk
            w = mk * self.mu[:, None] / cbar[None, :]  # w[i, j]: i mixed into j
            x0 = w.T @ self.x
            d = self.x[None, :, :] - x0[:, None, :]  # [j, i, :] = x_i − x0_j
            p0 = np.einsum("ij,ikl->jkl", w, self.p) + np.einsum("ij,jik,jil->jkl", w, d, d)
            # Time update.
            f = transitions(dt, self._omega, self.q)
            x = np.einsum("jkl,jl->jk", f, x0)
            p = f @ p0 @ f.transpose(0, 2, 1) + _fixed(dt, self.q)[1]
            # Measurement update (H = I), Joseph form.
            s = p + self.r
            y = z[None, :] - x
            s_inv = np.linalg.inv(s)
            k = p @ s_inv
            x = x + np.einsum("jkl,jl->jk", k, y)
            ikh = np.eye(6)[None] - k
            p = ikh @ p @ ikh.transpose(0, 2, 1) + k @ self.r @ k.transpose(0, 2, 1)
            _, logdet = np.linalg.slogdet(s)
            loglik = -0.5 * (np.einsum("jk,jkl,jl->j", y, s_inv, y) + logdet + 6 * _LOG_2PI)
            mu = cbar * np.exp(loglik - loglik.max())
            self.mu = mu / mu.sum()
            self.x, self.p = x, p
        self._t, self._heading = obs.t, obs.heading
        self._omega = math.radians(obs.yaw_rate)
        comb = self.mu @ self.x
        self._anchor = np.array([obs.x - comb[0], obs.y - comb[3]])

    def predict(self, t: float) -> Prediction:
        """The mixture propagated to ``t`` (time update only; the filter is unchanged)."""
        if self._t is None:
            raise LookupError("no observation yet")
        dt = elapsed(self._t, t)
        if dt == 0.0:
            xs, mu, var_p = self.x, self.mu, self.p[:, [0, 3], [0, 3]]
        else:
            f = transitions(dt, self._omega, self.q)
            xs = np.einsum("jkl,jl->jk", f, self.x)
            self._stop(xs, dt)
            mu = self.mu
            q = _fixed(dt, self.q)[1]
            rows = f[:, [0, 3], :]  # the position rows of F
            var_p = (np.einsum("jak,jkl,jal->ja", rows, self.p, rows) + q[:, [0, 3], [0, 3]])
        mean = mu @ xs
        spread = xs[:, [0, 3]] - mean[[0, 3]]
        var = mu @ (var_p + spread * spread)
        ve, vn = float(mean[1]), float(mean[4])
        speed = math.hypot(ve, vn)
        heading = (math.degrees(math.atan2(ve, vn)) if speed >= self.min_heading_speed
                   else self._heading)
        return Prediction(float(mean[0] + self._anchor[0]), float(mean[3] + self._anchor[1]),
                          speed, wrap_heading(heading), float(var[0]), float(var[1]), self.name)

    def _stop(self, xs: np.ndarray, dt: float) -> None:
        """The CA model's stop rule (as the KF's): decelerating along the last heading, it
        stops where that speed reaches 0 instead of reversing (``xs`` row 1 rewritten)."""
        stop = stop_point(*self.x[1].tolist(), self._heading, dt)
        if stop is not None:
            xs[1] = (stop[0], 0.0, 0.0, stop[1], 0.0, 0.0)
