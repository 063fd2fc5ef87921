"""The checks' geometry in local metres: the WGS-84 local scale, F2MD's kinematic envelope
(``MDMLib::calculateMaxMinDist``) and the overlap of two vehicle footprints
(``MDMLib::RectRectFactor``), and whether a footprint blocks a line of sight.

Distances come from a local metric scale, not from :mod:`catc.geo`'s geodesics: catc.geo's
pyproj calls cost ~11 us each, more than the whole budget of one message here; the tests
check :func:`local_offset_m` against them.  Headings are radians clockwise from north.
"""

from __future__ import annotations

import math

__all__ = ["RAD", "blocks", "dlon", "iou", "local_offset_m", "max_min_dist", "overlap",
           "scale"]

# WGS-84
_A = 6_378_137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)
#: Radians per degree.
RAD = math.pi / 180.0


def scale(lat: float) -> tuple[float, float]:
    """Metres per degree of longitude and of latitude at ``lat`` (WGS-84 radii of
    curvature: prime vertical N and meridian M)."""
    s = math.sin(lat * RAD)
    w = 1.0 - _E2 * s * s
    n = _A / math.sqrt(w)
    return n * math.cos(lat * RAD) * RAD, n * (1.0 - _E2) / w * RAD


def dlon(a: float, b: float) -> float:
    """``a - b`` in degrees of longitude, across the antimeridian the short way."""
    d = a - b
    if d > 180.0:
        d -= 360.0
    elif d < -180.0:
        d += 360.0
    return d


def local_offset_m(lat1: float, lon1: float, lat2: float, lon2: float) -> tuple[float, float]:
    """East and north (m) of point 2 from point 1, on the WGS-84 ellipsoid's local scale at
    their mean latitude: within 1e-6 of the geodesic distance up to 2 km (the tests check
    it against :func:`catc.geo.distance_m` and :func:`catc.geo.bearing_deg`)."""
    kx, ky = scale(0.5 * (lat1 + lat2))
    return dlon(lon2, lon1) * kx, (lat2 - lat1) * ky


def max_min_dist(cur: float, old: float, dt: float, accel: float, decel: float,
                 vmax: float) -> tuple[float, float]:
    """Least and greatest distance (m) a vehicle covers in ``dt`` s going from speed
    ``old`` to ``cur`` with accelerations within ``accel``/``decel`` and speed within
    ``vmax``: F2MD ``MDMLib::calculateMaxMinDist`` (accelerate then brake for the
    greatest, brake then accelerate for the least).  Two changes: the switch time is kept
    in [0, dt] (an infeasible speed change is the speed check's finding), and the capped
    branch decelerates from ``vmax``, not from the uncapped peak speed (F2MD's version
    overstates the greatest distance there)."""
    cur = max(cur, 0.0)
    old = max(old, 0.0)
    t1 = min(max((cur - old + dt * decel) / (accel + decel), 0.0), dt)
    t2 = dt - t1
    peak = accel * t1 + old
    if peak > vmax:
        n1 = min(max((vmax - old) / accel, 0.0), dt)
        n2 = min(max((vmax - cur) / decel, 0.0), dt - n1)
        top = max(old, min(vmax, peak))
        greatest = (old * n1 + 0.5 * accel * n1 * n1 + top * n2 - 0.5 * decel * n2 * n2
                    + top * (dt - n1 - n2))
    else:
        greatest = old * t1 + 0.5 * accel * t1 * t1 + peak * t2 - 0.5 * decel * t2 * t2
    low = old - decel * t2
    if low < 0.0:
        n1 = cur / accel
        n2 = old / decel
        least = old * n2 - 0.5 * decel * n2 * n2 + 0.5 * accel * n1 * n1
    else:
        least = old * t2 - 0.5 * decel * t2 * t2 + low * t1 + 0.5 * accel * t1 * t1
    return least, greatest


def _corners(x: float, y: float, h: float, length: float, width: float
             ) -> list[tuple[float, float]]:
    """Corners of a vehicle's footprint (centre ``x, y`` east/north m, heading ``h``
    radians clockwise from north, ``length`` along it), counter-clockwise."""
    ax, ay = math.sin(h) * 0.5 * length, math.cos(h) * 0.5 * length  # forward
    bx, by = math.cos(h) * 0.5 * width, -math.sin(h) * 0.5 * width  # right
    return [(x + ax + bx, y + ay + by), (x + ax - bx, y + ay - by),
            (x - ax - bx, y - ay - by), (x - ax + bx, y - ay + by)]


def _signed_area(poly: list[tuple[float, float]]) -> float:
    """Shoelace area of ``poly``: positive counter-clockwise."""
    s = 0.0
    for i in range(len(poly)):
        x1, y1 = poly[i - 1]
        x2, y2 = poly[i]
        s += x1 * y2 - x2 * y1
    return 0.5 * s


def _clip(subject: list[tuple[float, float]], clip: list[tuple[float, float]]
          ) -> list[tuple[float, float]]:
    """Sutherland-Hodgman: ``subject`` clipped by the convex polygon ``clip``."""
    out = subject
    orient = 1.0 if _signed_area(clip) > 0 else -1.0
    for i in range(len(clip)):
        if not out:
            break
        (cx1, cy1), (cx2, cy2) = clip[i - 1], clip[i]
        ex, ey = cx2 - cx1, cy2 - cy1
        inp, out = out, []
        for j in range(len(inp)):
            px, py = inp[j - 1]
            qx, qy = inp[j]
            sp = orient * (ex * (py - cy1) - ey * (px - cx1))
            sq = orient * (ex * (qy - cy1) - ey * (qx - cx1))
            if sq >= 0.0:
                if sp < 0.0:
                    r = sp / (sp - sq)
                    out.append((px + r * (qx - px), py + r * (qy - py)))
                out.append((qx, qy))
            elif sp >= 0.0:
                r = sp / (sp - sq)
                out.append((px + r * (qx - px), py + r * (qy - py)))
    return out


def _intersection(a: tuple[float, float, float, float, float],
                  b: tuple[float, float, float, float, float]) -> float:
    """The area (m²) two footprints share."""
    # 0.5 |s| and |0.5 s| are the same float
    return abs(_signed_area(_clip(_corners(*a), _corners(*b))))


def iou(a: tuple[float, float, float, float, float],
        b: tuple[float, float, float, float, float]) -> float:
    """Intersection over union of two footprints ``(x, y, heading rad, length, width)``:
    F2MD ``MDMLib::RectRectFactor`` (intersection area / (area1 + area2 - intersection))."""
    inter = _intersection(a, b)
    union = a[3] * a[4] + b[3] * b[4] - inter
    return inter / union if union > 0.0 else 0.0


def overlap(a: tuple[float, float, float, float, float],
            b: tuple[float, float, float, float, float]) -> float:
    """F2MD's intersection over union (:func:`iou`) as if both footprints were the size of
    the smaller: ``f / (2 - f)`` with ``f`` the share of the smaller one covered.  The same
    as the IoU for footprints of one size; for unequal ones the IoU is capped by their
    area ratio (a 4.5 x 1.8 m car wholly inside a 10.9 x 2.6 m truck: 0.29, under F2MD's
    0.5), this is not (1.0)."""
    small = min(a[3] * a[4], b[3] * b[4])
    if not small > 0.0:
        return 0.0
    f = min(1.0, _intersection(a, b) / small)
    return f / (2.0 - f)


def blocks(x0: float, y0: float, x1: float, y1: float,
           box: tuple[float, float, float, float, float]) -> bool:
    """Whether the segment (``x0``, ``y0``)-(``x1``, ``y1``) crosses footprint ``box`` =
    (x, y, heading, length, width) (Liang-Barsky clipping in the footprint's frame)."""
    x, y, h, length, width = box
    sin_h, cos_h = math.sin(h), math.cos(h)
    ax, ay = x0 - x, y0 - y
    dx, dy = x1 - x0, y1 - y0
    lo, hi = 0.0, 1.0
    for p, q, half in ((ax * sin_h + ay * cos_h, dx * sin_h + dy * cos_h, 0.5 * length),
                       (ax * cos_h - ay * sin_h, dx * cos_h - dy * sin_h, 0.5 * width)):
        # p + s q within [-half, half] for s in [lo, hi]
        if q == 0.0:
            if abs(p) > half:
                return False
            continue
        s0, s1 = (-half - p) / q, (half - p) / q
        if s0 > s1:
            s0, s1 = s1, s0
        lo, hi = max(lo, s0), min(hi, s1)
        if lo > hi:
            return False
    return True
