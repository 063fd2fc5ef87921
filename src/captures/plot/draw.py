"""Small drawing helpers of the bird's-eye view: a heading's unit vectors, a car's outline,
and artists added to axes whose view is fixed (no autoscaling, no data-limit update)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.axes import Axes
    from matplotlib.lines import Line2D

__all__ = ["CAR_LENGTH", "CAR_WIDTH", "add_artist", "add_line", "car", "fwd_right"]

#: A vehicle's outline when the capture does not say (m): a mid-size car.
CAR_LENGTH, CAR_WIDTH = 4.8, 1.9


def fwd_right(heading_deg: np.ndarray | float) -> tuple[tuple[Any, Any], tuple[Any, Any]]:
    """The unit vectors ``(east, north)`` forward along and to the right of a heading
    (deg clockwise from north)."""
    h = np.radians(heading_deg)
    return (np.sin(h), np.cos(h)), (np.cos(h), -np.sin(h))


def car(x: float, y: float, heading: float, length: float = CAR_LENGTH,
        width: float = CAR_WIDTH) -> np.ndarray:
    """A car outline (pointed nose) centred at (x, y), pointing along ``heading``."""
    (fx, fy), (rx, ry) = fwd_right(heading)
    lo, wi = length / 2.0, width / 2.0
    local = ((-lo, -wi), (lo - 1.0, -wi), (lo, 0.0), (lo - 1.0, wi), (-lo, wi))
    return np.array([(x + u * fx + v * rx, y + u * fy + v * ry) for u, v in local])


def add_artist(ax: Axes, patch: Artist) -> Artist:
    """Add a patch without the data-limit update of ``add_patch`` (the view is fixed)."""
    ax.add_artist(patch)
    return patch


def add_line(ax: Axes, x: npt.ArrayLike, y: npt.ArrayLike, **kw: Any) -> Line2D:
    """``ax.plot`` without autoscaling (the view is fixed), several times faster."""
    from matplotlib.lines import Line2D

    line = Line2D(np.atleast_1d(x), np.atleast_1d(y), **kw)
    ax.add_artist(line)
    return line
