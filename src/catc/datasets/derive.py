"""Derived kinematics shared by the dataset readers: gaps, heading, acceleration, yaw rate.

All functions take 10 Hz arrays (:data:`catc.mobility.DT`) and are vectorised numpy.
Derivatives are Savitzky-Golay derivatives (what :func:`scipy.signal.savgol_filter` gives
with ``deriv=1, mode="interp"``, computed here with numpy: scipy.signal costs the daemons
0.7 s of start-up; a test checks the two agree): a quadratic least-squares fit over a
centred window of :data:`WINDOW` = 11 samples (1 s), differentiated analytically; the
first and last 5 samples use the fit over the first or last full window).  Relative to
an ideal differentiator its gain is 0.95 at 0.2 Hz, 0.71 (-3 dB) at 0.5 Hz and 0 at
1.3 Hz: it keeps braking and steering manoeuvres (seconds long) and removes GNSS sample
noise and the steps of positions that were held or interpolated onto the 10 Hz grid.
The ``*_METHOD`` strings are the provenance entries of the fields these functions derive.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from catc.geo import enu_heading_deg
from catc.mobility import DT, Track

__all__ = [
    "ACCEL_METHOD",
    "HEADING_METHOD",
    "MAX_GAP",
    "MIN_MOVING_SPEED",
    "WINDOW",
    "YAW_RATE_METHOD",
    "accel_from_speed",
    "fill_gaps",
    "heading_from_track",
    "pieces",
    "yaw_rate_from_heading",
]

Array = npt.NDArray[np.float64]

#: Savitzky-Golay window in samples (odd): 11 samples = 1.0 s.
WINDOW = 11
#: Savitzky-Golay polynomial order.
POLYORDER = 2
#: Below this speed (m/s) the direction of motion is noise: the heading is held.
MIN_MOVING_SPEED = 1.0
#: The longest run of missing samples bridged by interpolation (5 samples = 0.5 s).
MAX_GAP = 5

_SG = f"Savitzky-Golay (quadratic, {WINDOW} samples)"
HEADING_METHOD = (
    f"derived: direction of the {_SG} velocity of x/y, held while the speed or that "
    f"velocity is below {MIN_MOVING_SPEED:g} m/s"
)
ACCEL_METHOD = f"derived: {_SG} derivative of the speed"
YAW_RATE_METHOD = f"derived: {_SG} derivative of the unwrapped heading"


def _derivative(values: Array, window: int) -> Array:
    """Savitzky-Golay first derivative per second (window shrunk to fit short arrays)."""
    n = len(values)
    window = min(window, n if n % 2 else n - 1)
    if window <= POLYORDER:
        raise ValueError(f"need at least {POLYORDER + 1} samples to differentiate, got {n}")
    return savgol_derivative(np.asarray(values, dtype=float), window, POLYORDER, DT)


def savgol_derivative(values: Array, window: int, polyorder: int, delta: float) -> Array:
    """``scipy.signal.savgol_filter(values, window, polyorder, deriv=1, delta=delta,
    mode="interp")``: the slope of the least-squares polynomial of the centred window at
    its centre, and at the edges the slope of the fit over the first or last window."""
    half = window // 2
    offsets = np.arange(-half, half + 1, dtype=float)
    vander = np.vander(offsets, polyorder + 1, increasing=True)  # columns 1, k, k^2, ...
    fit = np.linalg.pinv(vander)  # polynomial coefficients of the window's values
    out = np.empty(len(values))
    # interior: the linear coefficient of the centred fit, as a correlation
    out[half:len(values) - half] = np.correlate(values, fit[1], mode="valid")
    # edges: differentiate the polynomial of the first / last window at each edge sample
    powers = np.arange(1, polyorder + 1)
    n = len(values)

    def slope(window_values: Array, at: Array) -> Array:
        coef = fit @ window_values
        return np.power.outer(at, powers - 1) @ (coef[1:] * powers)

    out[:half] = slope(values[:window], offsets[:half])
    out[n - half:] = slope(values[n - window:], offsets[half + 1:])
    return out / delta


def pieces(valid: npt.ArrayLike, max_gap: int = MAX_GAP) -> list[slice]:
    """Split a sample mask into pieces, breaking at runs of more than ``max_gap`` invalid samples.

    Each piece starts and ends on a valid sample; runs of at most ``max_gap`` invalid
    samples inside a piece are left for :func:`fill_gaps`.  Leading and trailing invalid
    samples belong to no piece.  Returned in time order.
    """
    index = np.flatnonzero(np.asarray(valid, dtype=bool))
    if index.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(index) > max_gap + 1)
    starts = index[np.r_[0, breaks + 1]]
    stops = index[np.r_[breaks, index.size - 1]] + 1
    return [slice(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def fill_gaps(values: npt.ArrayLike, valid: npt.ArrayLike) -> Array:
    """Linear interpolation in time (sample index) over the invalid samples of ``values``.

    ``values`` is (n,) or (n, k) (columns interpolated independently); ``valid`` is the
    (n,) mask of good samples, which must include the first and the last sample.
    """
    values = np.asarray(values, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if not (valid[0] and valid[-1]):
        raise ValueError("fill_gaps: the first and last samples must be valid")
    index = np.arange(len(valid))
    columns = values.reshape(len(valid), -1)
    filled = [np.interp(index, index[valid], column[valid]) for column in columns.T]
    return np.stack(filled, axis=1).reshape(values.shape)


def heading_from_track(
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    speed: npt.ArrayLike,
    *,
    window: int = WINDOW,
    min_speed: float = MIN_MOVING_SPEED,
) -> Array:
    """Heading (deg cw from north, [0, 360)) of the direction of motion of an ENU track.

    The velocity (dE/dt, dN/dt) is the Savitzky-Golay derivative of x and y over
    ``window`` samples (quadratic), and the heading is its direction.  Where the vehicle
    is nearly stationary the direction is noise, so the last heading while moving is
    held; samples before the first moving one take that first moving heading.  Moving
    means both ``speed`` (m/s, the measured or given speed) and the magnitude of that
    velocity are at least ``min_speed``: the second test also holds the heading where
    the positions freeze while the speed does not (a GNSS position outage).  A track that
    never moves gets 0 (north) by convention.
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    ve, vn = _derivative(x, window), _derivative(y, window)
    moving = (np.asarray(speed, dtype=np.float64) >= min_speed) & (np.hypot(ve, vn) >= min_speed)
    if not moving.any():
        return np.zeros_like(x)
    raw = np.asarray(enu_heading_deg(ve, vn))
    last = np.maximum.accumulate(np.where(moving, np.arange(len(x)), -1))
    return raw[np.where(last < 0, np.argmax(moving), last)]


def accel_from_speed(speed: npt.ArrayLike, *, window: int = WINDOW) -> Array:
    """Longitudinal acceleration (m/s²): Savitzky-Golay derivative of the speed (quadratic)."""
    return _derivative(np.asarray(speed, dtype=np.float64), window)


def yaw_rate_from_heading(heading_deg: npt.ArrayLike, *, window: int = WINDOW) -> Array:
    """Yaw rate (deg/s, positive clockwise) from a heading track (deg cw from north).

    The heading is unwrapped (each step taken as the smallest rotation, so 359 -> 1 is
    +2 deg), then differentiated by Savitzky-Golay (quadratic, ``window`` samples).  Where
    the heading is held (vehicle nearly stationary) the yaw rate is therefore 0.
    """
    unwrapped = np.unwrap(np.asarray(heading_deg, dtype=np.float64), period=360.0)
    return _derivative(unwrapped, window)


def track(vehicle_id: str, t: Array, position: tuple[Array, ...], speed: Array,
          accel: Array | None, provenance: dict[str, str],
          size: tuple[float, float] = (float("nan"), float("nan"))) -> Track:
    """A :class:`Track` from ``position`` = (x, y, lat, lon, elev) and the measured speed:
    heading from the track, yaw rate from the heading, and the acceleration from the speed
    unless the dataset gives it (``accel``)."""
    x, y, lat, lon, elev = position
    heading = heading_from_track(x, y, speed)
    return Track(
        vehicle_id=vehicle_id, t=t, x=x, y=y, lat=lat, lon=lon, elev=elev, speed=speed,
        heading=heading, accel=accel_from_speed(speed) if accel is None else accel,
        yaw_rate=yaw_rate_from_heading(heading), length=float(size[0]),
        width=float(size[1]), provenance=provenance)
