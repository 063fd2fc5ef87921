"""Lane estimation from an RV's trail: where a point lies relative to the path it drove.

Reference paper, section "Context-Aware Target Classification (CA-TC)": the CAM uses the
vehicles' "path history ... for lane estimation".  An HV on the trail of an RV ahead
drives where that RV drove, so the CAM measures that RV's offsets along its trail
(:mod:`catc.cam`, step 6); this is the geometry, on Python floats.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import pairwise

from catc.classify._path import Point


def trail_offset(trail: Sequence[Point], p: Point) -> tuple[float, float, float] | None:
    """Where ``p`` lies relative to a vehicle's trail: ``(s, d, heading_deg)`` or None.

    ``trail`` is the vehicle's path history, most recent first, starting at its current
    position (ENU m).  ``s`` is the arc length from ``p``'s closest point on the trail
    forward to the vehicle, ``d`` the offset of ``p`` from the trail, positive to the
    right of the direction of travel, ``heading_deg`` the trail's direction of travel at
    that closest point (the lane heading there).  None when ``p``'s closest point is the trail's
    head approached from ahead (``p`` is ahead of the vehicle), its oldest point
    approached from beyond (the trail does not reach back to ``p``), or the trail has
    no length.  Used for lane estimation: an HV on the trail of an RV ahead drives
    where that RV drove (the CAM's "path history ... for lane estimation").
    """
    px, py = p
    best: tuple[float, float, float, float, float] | None = None  # (dist2, s, d, fx, fy)
    walked = 0.0
    last = len(trail) - 2
    sqrt = math.sqrt
    for i, ((nx, ny), (ox, oy)) in enumerate(pairwise(trail)):  # newer, older
        bx, by = ox - nx, oy - ny
        seg2 = bx * bx + by * by
        if seg2 == 0.0:
            continue
        seg = sqrt(seg2)
        t = ((px - nx) * bx + (py - ny) * by) / seg2
        off_head, off_tail = (i == 0 and t < 0.0), (i == last and t > 1.0)
        if t < 0.0:  # t = min(max(t, 0.0), 1.0), NaN and -0.0 included
            t = 0.0
        elif t > 1.0:
            t = 1.0
        ex, ey = px - (nx + t * bx), py - (ny + t * by)
        dist2 = ex * ex + ey * ey
        if best is None or dist2 < best[0]:
            if off_head or off_tail:
                best = (dist2, math.nan, math.nan, 0.0, 0.0)
            else:
                fx, fy = -bx / seg, -by / seg  # direction of travel
                side = ex * fy - ey * fx
                best = (dist2, walked + t * seg, math.copysign(sqrt(dist2), side), fx, fy)
        walked += seg
    if best is None or math.isnan(best[1]):
        return None
    return best[1], best[2], math.degrees(math.atan2(best[3], best[4])) % 360.0
