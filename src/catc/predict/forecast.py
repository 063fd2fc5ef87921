"""What every forecasting predictor shares: a forecast table on the 0.1 s grid after the
last BSM, read at any time, and the position integration of speed and heading forecasts.

The HGP family (:mod:`catc.predict.hgp`) and the neural baselines (:mod:`catc.predict.nn`)
make a forecast once per received BSM, as far ahead as the OBU will ask (its tick plus the
2 s prediction horizon), and read it at every tick until the next BSM arrives.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from catc.predict.base import Observation, Prediction
from catc.predict.kinematic import along_heading

#: The forecast grid step, s (the BSM period at 10 Hz).
DT = 0.1


class Forecast:
    """A forecast from the last BSM: the state at τ = k·DT for k = 0..K, one row per
    quantity of ``table``: x, y, speed, heading (deg), var_x, var_y."""

    __slots__ = ("end", "source", "table", "tau")

    def __init__(self, tau: np.ndarray, table: np.ndarray, source: Sequence[str],
                 end: float | None = None) -> None:
        self.tau = tau
        self.table = table
        self.source = source
        self.end = float(tau[-1]) if end is None else end  # the horizon, s

    x = property(lambda self: self.table[0])
    y = property(lambda self: self.table[1])
    speed = property(lambda self: self.table[2])
    heading = property(lambda self: self.table[3])
    var_x = property(lambda self: self.table[4])
    var_y = property(lambda self: self.table[5])


def integrate(x0: float, y0: float, tau: np.ndarray, mu_s: np.ndarray, mu_h: np.ndarray,
              var_h: np.ndarray, rule: str = "trapezoid") -> tuple[np.ndarray, np.ndarray]:
    """Positions from speed/heading forecasts at ``tau`` (paper eq. "position prediction 2").

    The expected velocity is E[s]·E[sin h], E[s]·E[cos h] with E[cos h] = exp(−σh²/2)·cos μh
    (heading clockwise from north, so east uses sin).  ``rule`` "left" is the paper's
    literal recursion x_{j+1} = x_j + Δt·v_j; "trapezoid" averages v_j and v_{j+1}.
    """
    damp = np.exp(-0.5 * var_h)
    vx = mu_s * damp * np.sin(mu_h)
    vy = mu_s * damp * np.cos(mu_h)
    dt = np.diff(tau)
    if rule == "trapezoid":
        dx, dy = 0.5 * (vx[1:] + vx[:-1]) * dt, 0.5 * (vy[1:] + vy[:-1]) * dt
    elif rule == "left":
        dx, dy = vx[:-1] * dt, vy[:-1] * dt
    else:
        raise ValueError(f"unknown integration rule {rule!r}")
    return (x0 + np.concatenate(([0.0], np.cumsum(dx))),
            y0 + np.concatenate(([0.0], np.cumsum(dy))))


def read(f: Forecast, tau: float) -> Prediction:
    """The forecast state ``tau`` seconds after the last BSM (linear between 0.1 s steps)."""
    if tau >= f.end:  # beyond the computed horizon: constant speed onwards
        x, y, speed, heading, var_x, var_y = f.table[:, -1].tolist()
        extra = tau - f.end
        h = math.radians(heading)
        return Prediction(x + speed * extra * math.sin(h), y + speed * extra * math.cos(h),
                          speed, heading, var_x, var_y, f.source[-1])
    k = min(int(tau / DT), len(f.source) - 2)  # float round-off at the horizon's end
    w = min(tau / DT - k, 1.0)
    (x0, x1), (y0, y1), (s0, s1), (h0, h1), (vx0, vx1), (vy0, vy1) = \
        f.table[:, k:k + 2].tolist()
    dh = (h1 - h0 + 180.0) % 360.0 - 180.0
    return Prediction((1 - w) * x0 + w * x1, (1 - w) * y0 + w * y1, (1 - w) * s0 + w * s1,
                      (h0 + w * dh) % 360.0, (1 - w) * vx0 + w * vx1, (1 - w) * vy0 + w * vy1,
                      f.source[k + 1])


def read_xy(f: Forecast, tau: float) -> tuple[float, float]:
    """The position of :func:`read` (the same arithmetic), without the rest: a branch
    score needs only where the GP put the vehicle at the gap's end."""
    if tau >= f.end:
        x, y, speed, heading = f.table[:4, -1].tolist()
        extra = tau - f.end
        h = math.radians(heading)
        return x + speed * extra * math.sin(h), y + speed * extra * math.cos(h)
    k = min(int(tau / DT), len(f.source) - 2)
    w = min(tau / DT - k, 1.0)
    (x0, x1), (y0, y1) = f.table[:2, k:k + 2].tolist()
    return (1 - w) * x0 + w * x1, (1 - w) * y0 + w * y1


def read_many(answers: list[tuple[Forecast, float]]) -> tuple[np.ndarray, list[str]]:
    """:func:`read` of every ``(forecast, tau)`` pair at once: a (6, N) array, rows x, y,
    speed, heading, var_x, var_y, and the sources.  The same arithmetic as :func:`read`,
    element by element, so the same numbers (a 500-RV tick's ~570 reads: 0.35 ms here
    against 1 ms for :func:`read` one by one, ``python bench/step_parts.py``)."""
    n = len(answers)
    out = np.empty((6, n))
    if not n:
        return out, []
    forecasts = [f for f, _ in answers]
    tau = np.array([t for _, t in answers])
    ends = np.array([f.end for f in forecasts])
    lens = np.array([len(f.source) for f in forecasts])
    q = tau / DT
    k = np.minimum(q.astype(np.intp), lens - 2)  # int(): truncation (tau > 0)
    w = np.minimum(q - k, 1.0)
    far = (tau >= ends).nonzero()[0].tolist()  # beyond the horizon: read one by one (rare)
    if far:
        k[far] = lens[far] - 2
        w[far] = 1.0
    # every table side by side, then steps k and k + 1 of each
    at = np.cumsum(lens) - lens + k
    both = np.concatenate([f.table for f in forecasts], axis=1)
    lo, hi = both[:, at], both[:, at + 1]
    np.multiply(1.0 - w, lo, out=out)
    out += w * hi
    dh = np.subtract(hi[3], lo[3])
    dh += 180.0
    np.remainder(dh, 360.0, out=dh)
    dh -= 180.0
    dh *= w
    np.add(lo[3], dh, out=out[3])
    np.remainder(out[3], 360.0, out=out[3])
    sources = [f.source[j] for f, j in zip(forecasts, (k + 1).tolist(), strict=True)]
    for i in far:
        p = read(*answers[i])
        out[:, i] = (p.x, p.y, p.speed, p.heading, p.var_x, p.var_y)
        sources[i] = p.source
    return out, sources


def fill_columns(out: np.ndarray, sources: list[str], whole: tuple[list, list],
                 reads: tuple[list, list]) -> None:
    """Into ``out`` (10, n: x, y, speed, heading at t0 and t1 interleaved, then var_x and
    var_y at t0) and ``sources`` (at t0): the answers of :func:`catc.predict.
    predict_columns`, per time j (0: t0, 1: t1) ``whole[j]`` rows of (column, x, y,
    speed, heading, var_x, var_y) (their sources set by the caller) and ``reads[j]``
    pairs of (column, (forecast, tau)), read at once (:func:`read_many`)."""
    for j in (0, 1):
        if whole[j]:
            rows = np.array(whole[j]).T
            idx = rows[0].astype(np.intp)
            out[j:8:2, idx] = rows[1:5]
            if j == 0:
                out[8:, idx] = rows[5:]
        if reads[j]:
            idx = [i for i, _ in reads[j]]
            values, src = read_many([a for _, a in reads[j]])
            out[j:8:2, idx] = values[:4]
            if j == 0:
                out[8:, idx] = values[4:]
                for i, s in zip(idx, src, strict=True):
                    sources[i] = s


def bsm_prediction(last: Observation) -> Prediction:
    """The state a fresh BSM gives (zero variance, source ``"bsm"``)."""
    return Prediction(last.x, last.y, last.speed, last.heading, 0.0, 0.0, "bsm")


def constant_speed(last: Observation, tau: float) -> Prediction:
    """Constant speed and heading from ``last`` for ``tau`` s (source ``"cs"``, the ``cs``
    predictor's answer): the forecasting predictors' answer while they have too few BSMs
    to forecast from."""
    return along_heading(last, last.speed * tau, last.speed, "cs")


def covers(f: Forecast, tau: float, horizon_s: float) -> bool:
    """Whether forecast ``f`` reaches ``tau`` s (or the longest forecast made).  The step
    count rounds down by up to 1e-9 s, so a forecast made for ``tau`` may end
    a hair before it; it still covers it (reading beyond the end extrapolates)."""
    return f.end >= min(tau, horizon_s) - 1e-9
