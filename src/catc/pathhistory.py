"""Concise path history of a vehicle (SAE J2945/1 style) and BSM Part II path history in ENU.

The Context-Aware Map keeps, for the HV and every RV, the path the vehicle has travelled
as a short polyline: "concise" points such that the chord between two consecutive points
never deviates from the actual path by more than an allowable error.  This is the
path-history representation of SAE J2945/1 (its "PH_AllowableError" of 1 m), built here
from the samples as they arrive.

Algorithm (online chord test)
-----------------------------
Keep an *anchor* ``A`` (the last concise point) and the raw samples since it.  When a
sample ``N`` arrives, test the chord ``A -> N``: if any raw sample since ``A`` lies
farther than ``tolerance_m`` from the segment ``A N``, the previous sample becomes a
concise point and the new anchor.  So every raw sample lies within ``tolerance_m`` of the
concise polyline (of the segment whose chord was tested against it); each segment is as
long as the test allows when it is closed (a greedy, online pass: no look-ahead).

The test is done in O(1) per sample, without looping over the buffer, by cone
intersection (Williams 1978, "An efficient algorithm for the piecewise linear
approximation of planar curves"; Sklansky & Gonzalez 1980, "Fast polygonal approximation
of digitized curves"): a sample ``P`` at distance ``r > tol`` from ``A`` and direction
``phi_P`` is within ``tol`` of the *line* through ``A`` with direction ``phi`` iff
``|phi - phi_P| <= asin(tol / r)``.  The intersection of these angular intervals over the
buffered samples is one interval (each is narrower than a half turn and the first one
fixes the branch), so "every buffered sample is within ``tol`` of the line ``A N``" is
"``phi_N`` is in the interval".  Samples with ``r <= tol`` are within ``tol`` of ``A``,
hence of any chord from ``A``.  Line and segment distance differ only for samples that
project beyond ``N`` (the vehicle came back towards ``A``: a reversal, or GNSS jitter at
a standstill); they can exist only when some buffered sample is farther from ``A`` than
``N`` is, and only then is the buffer scanned for them, newest first, stopping at the
first sample whose running maximum distance from ``A`` is within ``|A N|``.

Raw samples are kept only for that scan, as buffer entries on a grid of cells
``_MERGE_FRACTION * tol / sqrt(2)`` wide: a sample falling in the cell of an existing
entry is merged into it (the entry records the radius it covers, at most
``_MERGE_FRACTION * tol``, and the scan tests entries conservatively with it, so a merged
sample can never end up farther than ``tol`` from the polyline).  A vehicle waiting at a
light with ~0.1-0.2 m of GNSS jitter therefore does not fill the buffer (measured: ten
minutes of it keep the same few points as an unbounded buffer; with jitter of ~0.3 m and
more the chord test itself keeps points, the jitter being as large as the tolerance).

Cost: ``add`` is O(1) apart from that scan, ~1 us in CPython; :meth:`~ConcisePathHistory.points`
is cached until the next accepted sample.

Bounds (memory and time are bounded whatever the input):

* ``max_chord_m`` (default 300 m): a concise point is also kept when the chord would be
  longer.  Our choice: the history length below, so a straight road keeps a point at
  least every 300 m.  (An open J2945/1 implementation cites J2945/1-2020 values of
  210 m maximum chord, 200 m minimum history and 15 points; pass those for conformance.)
* ``max_buffer`` (default 100 entries since the anchor): when it is full the latest
  sample becomes a concise point.  Our choice: 10 s of samples at the 10 Hz BSM rate;
  on a straight road at 30 m/s (108 km/h) and faster ``max_chord_m`` comes first.
* ``max_length_m`` (default 300 m, J2945/1's ~300 m path-history distance): the oldest
  concise points are dropped while the rest of the history still spans at least
  ``max_length_m`` from the current position.  Dropping them as soon as the total
  exceeded ``max_length_m`` would cut the history to almost nothing every time a long
  chord is closed on a straight road; as in J2945/1 the distance is a minimum coverage,
  so the polyline spans at most ``max_length_m + max_chord_m``.
* ``max_points`` (default 23, the J2735 ``crumbData`` limit ``SIZE(1..23)``): concise
  points behind the current position (the crumbs a BSM would carry); the oldest go first.
* ``tolerance_m`` (default 1.0 m): J2945/1's PH allowable error.

Conventions: ENU metres (x east, y north) in the run's local frame, times in seconds;
:meth:`ConcisePathHistory.points` is most recent first, starting with the current
position, as :class:`catc.classify.HostPath` ``history`` and
:func:`catc.classify.trail_offset` expect.

:func:`from_bsm_path_history` turns a received BSM's Part II ``PathHistory`` (crumb
offsets from the current position, see :class:`catc.bsm.PathHistoryPoint` and
:data:`catc.units.OFFSET_LL` / :data:`catc.units.TIME_OFFSET`) into the same ENU form.

Everything here is pure computation: no I/O, no clocks.
"""

from __future__ import annotations

import math
from collections import deque
from operator import itemgetter

import numpy as np

from catc.bsm import PathHistory
from catc.geo import EnuFrame

__all__ = ["ConcisePathHistory", "from_bsm_path_history"]

Point = tuple[float, float]
Crumb = tuple[float, float, float]

#: Buffer entries cover raw samples up to this fraction of the tolerance from their centre.
#: A quarter of the tolerance absorbs standstill GNSS jitter of ~0.1-0.2 m (and the
#: 1e-7 deg ~ 1 cm position quantisation) in a few dozen cells while costing at most that
#: much of the tolerance in the conservative beyond-the-end test.
_MERGE_FRACTION = 0.25

_TWO_PI = 2.0 * math.pi

#: (x, y) of a crumb (t, x, y).
_XY = itemgetter(1, 2)


class ConcisePathHistory:
    """Online concise path history: :meth:`add` samples, read :meth:`points`.

    See the module docstring for the algorithm and the defaults.  ``rejected`` counts the
    samples ignored because their time was not after the last accepted one, or a value was
    not finite.
    """

    __slots__ = (
        "_bc", "_bpm", "_br", "_bx", "_by", "_cache", "_cells", "_head", "_hi", "_inv_cell",
        "_kept", "_kept_len", "_last_t", "_lo", "_pcache", "_ref", "_segs", "max_buffer",
        "max_chord_m", "max_length_m", "max_points", "rejected", "tolerance_m",
    )

    def __init__(
        self,
        tolerance_m: float = 1.0,
        max_chord_m: float = 300.0,
        max_length_m: float = 300.0,
        max_points: int = 23,
        max_buffer: int = 100,
    ) -> None:
        for name, value in (("tolerance_m", tolerance_m), ("max_chord_m", max_chord_m),
                            ("max_length_m", max_length_m)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {value}")
        if max_points < 1 or max_buffer < 1:
            raise ValueError(f"max_points and max_buffer must be >= 1, got {max_points}, "
                             f"{max_buffer}")
        self.tolerance_m = float(tolerance_m)
        self.max_chord_m = float(max_chord_m)
        self.max_length_m = float(max_length_m)
        self.max_points = int(max_points)
        self.max_buffer = int(max_buffer)
        self.rejected = 0
        self._inv_cell = math.sqrt(2.0) / (_MERGE_FRACTION * self.tolerance_m)
        self._last_t = -math.inf
        #: Concise points, oldest first; the last is the anchor.
        self._kept: deque[Crumb] = deque()
        #: Lengths of the segments between consecutive kept points, oldest first.
        self._segs: deque[float] = deque()
        self._kept_len = 0.0
        #: The latest accepted sample (the current position), None before the first.
        self._head: Crumb | None = None
        # Buffer entries since the anchor, one per occupied grid cell: centre (the first
        # sample in the cell), distance of the centre from the anchor, covered radius, and
        # the running maximum over entries 0..i of (distance + radius).
        self._bx: list[float] = []
        self._by: list[float] = []
        self._bc: list[float] = []
        self._br: list[float] = []
        self._bpm: list[float] = []
        self._cells: dict[tuple[int, int], int] = {}
        # The cone: reference direction (rad) and the allowed interval relative to it.
        self._ref: float | None = None
        self._lo = -math.inf
        self._hi = math.inf
        self._cache: tuple[Crumb, ...] | None = None
        self._pcache: tuple[Point, ...] | None = None

    # --- input ------------------------------------------------------------------------------

    def add(self, t: float, x: float, y: float) -> None:
        """Add the sample ``(t, x, y)`` (s, ENU m); ``t`` must be after the last one."""
        if not (t > self._last_t and math.isfinite(t) and math.isfinite(x)
                and math.isfinite(y)):
            self.rejected += 1
            return
        self._last_t = t
        self._cache = self._pcache = None
        kept = self._kept
        if not kept:
            kept.append((t, x, y))
            self._head = kept[-1]
            return
        _, ax, ay = kept[-1]
        dx, dy = x - ax, y - ay
        dist = math.hypot(dx, dy)
        bx = self._bx
        if bx and (dist > self.max_chord_m or not self._fits(x, y, dx, dy, dist)
                   or (len(bx) >= self.max_buffer and self._cell(x, y) not in self._cells)):
            self._retain_head()
            _, ax, ay = kept[-1]
            dx, dy = x - ax, y - ay
            dist = math.hypot(dx, dy)
        self._head = (t, x, y)
        self._push(x, y, dx, dy, dist)
        self._trim_length(dist)

    def _fits(self, x: float, y: float, dx: float, dy: float, dist: float) -> bool:
        """True when every buffered sample is within tolerance of the segment anchor -> (x, y)."""
        ref = self._ref
        if ref is None:  # every buffered sample is within tolerance of the anchor itself
            return True
        if dist == 0.0:
            return False
        d = math.atan2(dy, dx) - ref
        if d >= math.pi:
            d -= _TWO_PI
        elif d < -math.pi:
            d += _TWO_PI
        if d < self._lo or d > self._hi:
            return False
        bpm = self._bpm
        if bpm[-1] <= dist:  # nothing reaches beyond the chord's end
            return True
        # Samples that may project beyond (x, y): their distance to the segment is their
        # distance to (x, y).  Entry i covers samples within br[i] of its centre.
        _, ax, ay = self._kept[-1]
        ux, uy = dx / dist, dy / dist
        tol = self.tolerance_m
        bx, by, br = self._bx, self._by, self._br
        for i in range(len(bx) - 1, -1, -1):
            if bpm[i] <= dist:
                break
            px, py, rad = bx[i], by[i], br[i]
            if ((px - ax) * ux + (py - ay) * uy + rad > dist
                    and math.hypot(px - x, py - y) + rad > tol):
                return False
        return True

    def _cell(self, x: float, y: float) -> tuple[int, int]:
        inv = self._inv_cell
        return math.floor(x * inv), math.floor(y * inv)

    def _push(self, x: float, y: float, dx: float, dy: float, dist: float) -> None:
        """Record the accepted sample: its cone constraint and its buffer entry."""
        tol = self.tolerance_m
        if dist > tol:
            phi = math.atan2(dy, dx)
            half = math.asin(tol / dist)
            if self._ref is None:
                self._ref, self._lo, self._hi = phi, -half, half
            else:
                d = phi - self._ref
                if d >= math.pi:
                    d -= _TWO_PI
                elif d < -math.pi:
                    d += _TWO_PI
                if d - half > self._lo:
                    self._lo = d - half
                if d + half < self._hi:
                    self._hi = d + half
        bx, br, bpm = self._bx, self._br, self._bpm
        inv = self._inv_cell
        key = (math.floor(x * inv), math.floor(y * inv))
        i = self._cells.get(key)
        if i is not None:  # within _MERGE_FRACTION * tol of that entry's centre
            gap = math.hypot(x - bx[i], y - self._by[i])
            if gap > br[i]:
                br[i] = gap
                reach = self._bc[i] + gap
                for k in range(i, len(bpm)):  # bpm is non-decreasing
                    if bpm[k] >= reach:
                        break
                    bpm[k] = reach
            return
        self._cells[key] = len(bx)
        bpm.append(dist if not bpm or dist > bpm[-1] else bpm[-1])
        bx.append(x)
        self._by.append(y)
        self._bc.append(dist)
        br.append(0.0)

    def _retain_head(self) -> None:
        """The latest sample becomes a concise point and the new anchor."""
        head = self._head
        assert head is not None
        _, ax, ay = self._kept[-1]
        kept, segs = self._kept, self._segs
        kept.append(head)
        segs.append(math.hypot(head[1] - ax, head[2] - ay))
        while len(kept) > self.max_points:
            kept.popleft()
            segs.popleft()
        self._kept_len = sum(segs)
        self._bx, self._by, self._bc, self._br, self._bpm = [], [], [], [], []
        self._cells = {}
        self._ref, self._lo, self._hi = None, -math.inf, math.inf

    def _trim_length(self, head_dist: float) -> None:
        """Drop the oldest points while the rest still spans ``max_length_m``."""
        segs = self._segs
        if segs and head_dist + self._kept_len - segs[0] >= self.max_length_m:
            kept = self._kept
            while segs and head_dist + self._kept_len - segs[0] >= self.max_length_m:
                kept.popleft()
                segs.popleft()
                self._kept_len = sum(segs)

    # --- output ------------------------------------------------------------------------------

    def _crumbs(self) -> tuple[Crumb, ...]:
        if self._cache is None:
            out = list(reversed(self._kept))
            if self._head is not None and self._head is not self._kept[-1]:
                out.insert(0, self._head)
            self._cache = tuple(out)
        return self._cache

    def crumbs(self) -> list[Crumb]:
        """``(t, x, y)`` of the concise polyline, most recent first, from the current sample."""
        return list(self._crumbs())

    def points(self) -> list[Point]:
        """``(x, y)`` of the concise polyline, most recent first, from the current sample."""
        return list(self.point_tuple())

    def point_tuple(self) -> tuple[Point, ...]:
        """:meth:`points` as a tuple (the cached one: no copy)."""
        if self._pcache is None:
            self._pcache = tuple(map(_XY, self._crumbs()))
        return self._pcache

    def __len__(self) -> int:
        return len(self._crumbs())

    @property
    def length_m(self) -> float:
        """Length of the polyline :meth:`points` (m)."""
        if self._head is None:
            return 0.0
        _, ax, ay = self._kept[-1]
        return self._kept_len + math.hypot(self._head[1] - ax, self._head[2] - ay)


def from_bsm_path_history(
    ph: PathHistory, frame: EnuFrame, lat: float, lon: float, t: float, *, h: float = 0.0
) -> list[Crumb]:
    """A BSM's Part II path history as ENU ``(t, x, y)``, most recent first.

    ``lat``, ``lon`` (degrees) and ``t`` (s) are the BSM's current position and time; a
    crumb is at ``(lat + lat_offset, lon + lon_offset)`` and ``time_offset`` seconds
    earlier.  The first entry is the current position itself, so the result has the form
    of :meth:`ConcisePathHistory.crumbs` (and, reversed, can be fed to :meth:`add`).
    Crumbs whose latitude, longitude or time offset is unavailable (``None``) are
    skipped; the others are sorted by time offset (J2735 sends them most recent first,
    but nothing relies on it).  All positions go through ``frame`` in one vectorised
    call, at the height ``h`` (m): elevation offsets are ignored, as the CAM places every
    vehicle on the same ellipsoid-height surface (a 10 m height difference moves a point
    10 km from the frame origin by under 2 cm horizontally).

    The current position is computed here rather than passed in, so it and the crumbs
    come from one conversion and cannot disagree.
    """
    crumbs = sorted(
        (p.time_offset, p.lat_offset, p.lon_offset) for p in ph.points
        if p.lat_offset is not None and p.lon_offset is not None
        and p.time_offset is not None
    )
    dts = np.array([0.0] + [c[0] for c in crumbs])
    lats = lat + np.array([0.0] + [c[1] for c in crumbs])
    lons = lon + np.array([0.0] + [c[2] for c in crumbs])
    x, y, _ = frame.to_enu(lats, lons, h)
    return [(float(t - dt), float(xi), float(yi))
            for dt, xi, yi in zip(dts.tolist(), np.asarray(x).tolist(),
                                  np.asarray(y).tolist(), strict=True)]
