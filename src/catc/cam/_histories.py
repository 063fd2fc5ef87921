"""The RVs' concise path histories as rows of shared arrays (issue 30, item 3): what one
:class:`catc.pathhistory.ConcisePathHistory` per track computes, bit for bit, with a
tick's samples added in one compiled loop instead of a Python call each (at 1,000 RVs,
~5 ms of a 27 ms step).

:class:`PathHistories` holds the rows; a track's ``history`` is a :class:`HistoryRow`
(``add`` queues the sample; reading the points flushes the queue).  The compiled loop
(:func:`_add`) is ``ConcisePathHistory.add`` operation for operation, on the same
numbers: :func:`_hypot` is CPython 3.11's ``math.hypot`` (``vector_norm`` of two
coordinates, Veltkamp-Dekker squaring, compensated sums and a corrected square root),
since the C library's ``hypot`` differs from it in the last bit for ~0.6 % of inputs;
``atan2``, ``asin`` and ``floor`` are the C library's in both, and the sums of segment
lengths run left to right as Python 3.11's ``sum`` of floats does.
tests/test_cam_histories.py holds every row to the objects', bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from catc.compiled import compiled
from catc.pathhistory import ConcisePathHistory

__all__ = ["HistoryRow", "PathHistories"]


class HistoryRow:
    """One track's concise path history, a row of :class:`PathHistories` (the methods of
    :class:`~catc.pathhistory.ConcisePathHistory` the CA-TC uses)."""

    __slots__ = ("alive", "slot", "table")

    def __init__(self, table: PathHistories, slot: int) -> None:
        self.table, self.slot, self.alive = table, slot, True

    def add(self, t: float, x: float, y: float) -> None:
        """Queue the sample ``(t, x, y)``: added at the table's next flush."""
        self.table._pending.append((self, t, x, y))

    def point_tuple(self) -> tuple[tuple[float, float], ...]:
        """``ConcisePathHistory.point_tuple``: (x, y), most recent first."""
        return self.table.points(self.slot)

    def points(self) -> list[tuple[float, float]]:
        return list(self.point_tuple())

    def release(self) -> None:
        """Give the row back; its queued samples are dropped."""
        if self.alive:
            self.alive = False
            self.table._dead.append(self.slot)


class PathHistories:
    """Rows of concise path histories with the parameters of ``ConcisePathHistory(
    tolerance_m=tolerance_m)`` (the CA-TC's); see the module docstring."""

    def __init__(self, tolerance_m: float, capacity: int = 64) -> None:
        ref = ConcisePathHistory(tolerance_m=tolerance_m)  # checks, and the bounds
        self.tol, self.inv_cell = ref.tolerance_m, ref._inv_cell
        self.max_chord, self.max_length = ref.max_chord_m, ref.max_length_m
        self.max_points, self.max_buffer = ref.max_points, ref.max_buffer
        self._kernel = _kernels()
        self._cap = 0
        self._free: list[int] = []
        self._dead: list[int] = []
        self._pending: list[tuple[HistoryRow, float, float, float]] = []
        self._cache: dict[int, tuple] = {}
        self._grow(capacity)

    def _grow(self, capacity: int) -> None:
        old, n = self._cap, max(capacity, 2 * self._cap)
        kept, buf = self.max_points + 1, self.max_buffer

        def grown(name: str, shape: tuple, dtype: type) -> None:
            a = np.zeros((n, *shape), dtype=dtype)
            prev = getattr(self, name, None)
            if prev is not None:
                a[:old] = prev
            setattr(self, name, a)

        grown("f", (_NF,), np.float64)  # per row: the scalars of _F
        grown("i", (_NI,), np.int64)  # per row: the counts of _I
        grown("kept", (3, kept), np.float64)  # t, x, y of the concise points, oldest first
        grown("segs", (kept,), np.float64)
        grown("buf", (5, buf), np.float64)  # x, y, distance, radius, running max
        grown("cells", (2, buf), np.int64)
        self._free.extend(range(n - 1, old - 1, -1))
        self._cap = n

    def row(self) -> HistoryRow:
        """A new, empty history."""
        if not self._free:
            self.flush()
            if not self._free:
                self._grow(2 * self._cap)
        s = self._free.pop()
        self.f[s] = (-math.inf, 0.0, 0.0, 0.0, 0.0, math.nan, -math.inf, math.inf)
        self.i[s] = 0
        self._cache.pop(s, None)
        return HistoryRow(self, s)

    def flush(self) -> None:
        """Add the queued samples, in order."""
        pending, self._pending = self._pending, []
        live = [(r.slot, t, x, y) for r, t, x, y in pending if r.alive]
        if live:
            slots = np.array([v[0] for v in live], dtype=np.int64)
            samples = np.array([v[1:] for v in live], dtype=np.float64)
            self._kernel(slots, samples, self.f, self.i, self.kept, self.segs, self.buf,
                         self.cells, self.tol, self.inv_cell, self.max_chord,
                         self.max_length, self.max_points, self.max_buffer)
            cache = self._cache
            for s in slots.tolist():
                cache.pop(s, None)
        if self._dead:
            self._free.extend(self._dead)
            for s in self._dead:
                self._cache.pop(s, None)
            self._dead = []

    def points(self, s: int) -> tuple[tuple[float, float], ...]:
        """``ConcisePathHistory.point_tuple`` of row ``s``."""
        if self._pending:
            self.flush()
        out = self._cache.get(s)
        if out is None:
            n, _, head_kept, _ = self.i[s].tolist()
            xs, ys = self.kept[s, 1:3, n - 1::-1].tolist() if n else ([], [])
            if n and not head_kept:
                hx, hy = self.f[s, _HX:_HY + 1].tolist()
                out = ((hx, hy), *zip(xs, ys, strict=True))
            else:
                out = tuple(zip(xs, ys, strict=True))
            self._cache[s] = out
        return out

    def trail_offsets(self, slots: list[int], heads: np.ndarray, p: tuple[float, float]
                      ) -> np.ndarray:
        """:func:`catc.classify.trail_offset` of ``p`` on the trail of each row ``slots[k]``
        that starts at ``heads[k]`` (the RV's estimate, x and y) and goes on along the
        row's points: (B, 3) ``s, d, heading_deg``, a row of NaN where it is None.  One
        compiled loop, the same operations on the same numbers."""
        if self._pending:
            self.flush()
        out = np.empty((len(slots), 3))
        kernel = compiled(_trail_offsets)
        kernel(np.array(slots, dtype=np.int64), np.ascontiguousarray(heads, dtype=np.float64),
               float(p[0]), float(p[1]), self.f, self.i, self.kept, out)
        return out


# the per-row scalars (f) and counts (i)
_LAST_T, _KEPT_LEN, _HT, _HX, _HY, _REF, _LO, _HI = range(8)
_NF = 8
_KEPT, _BUF, _HEAD_KEPT, _REJECTED = range(4)
_NI = 4

_KERNEL = None


def _kernels():
    """:func:`_add` compiled (numba, cached per machine), with its helpers; made with the
    first table."""
    global _KERNEL, _hypot, _fits, _find, _push, _popleft, _segs_sum, _retain_head
    global _trim_length
    if _KERNEL is None:
        from numba import njit

        opts = {"cache": True, "error_model": "numpy"}
        # the helpers first: each compiled function calls the compiled ones
        _hypot = njit(**opts)(_hypot)
        _find = njit(**opts)(_find)
        _popleft = njit(**opts)(_popleft)
        _segs_sum = njit(**opts)(_segs_sum)
        _fits = njit(**opts)(_fits)
        _push = njit(**opts)(_push)
        _retain_head = njit(**opts)(_retain_head)
        _trim_length = njit(**opts)(_trim_length)
        _KERNEL = njit(**opts)(_add)
    return _KERNEL


_RAD2DEG = 180.0 / math.pi  # math.degrees multiplies by this same constant


def _trail_offsets(slots, heads, px, py, f, i, kept, out):  # pragma: no cover - compiled
    """``trail_offset(((hx, hy), *points(s)), (px, py))`` for each row (PathHistories.
    trail_offsets), operation for operation: ``sqrt``, ``copysign`` and ``atan2`` are the
    C library's in both, and ``% 360`` is Python's float remainder (CPython's
    ``float_rem``)."""
    m = kept.shape[2] + 2
    tx = np.empty(m)
    ty = np.empty(m)
    for b in range(slots.shape[0]):
        s = slots[b]
        tx[0], ty[0] = heads[b, 0], heads[b, 1]
        k = 1
        n = i[s, _KEPT]
        if n and not i[s, _HEAD_KEPT]:
            tx[k], ty[k] = f[s, _HX], f[s, _HY]
            k += 1
        for j in range(n - 1, -1, -1):
            tx[k], ty[k] = kept[s, 1, j], kept[s, 2, j]
            k += 1
        found = False
        best2 = bs = bd = bfx = bfy = 0.0
        walked = 0.0
        last = k - 2
        for q in range(k - 1):
            nx, ny = tx[q], ty[q]
            bx, by = tx[q + 1] - nx, ty[q + 1] - ny
            seg2 = bx * bx + by * by
            if seg2 == 0.0:
                continue
            seg = math.sqrt(seg2)
            t = ((px - nx) * bx + (py - ny) * by) / seg2
            off = (q == 0 and t < 0.0) or (q == last and t > 1.0)
            if t < 0.0:
                t = 0.0
            elif t > 1.0:
                t = 1.0
            ex, ey = px - (nx + t * bx), py - (ny + t * by)
            dist2 = ex * ex + ey * ey
            if not found or dist2 < best2:
                found = True
                best2 = dist2
                if off:
                    bs, bd, bfx, bfy = math.nan, math.nan, 0.0, 0.0
                else:
                    fx, fy = -bx / seg, -by / seg
                    side = ex * fy - ey * fx
                    bs, bd, bfx, bfy = walked + t * seg, math.copysign(math.sqrt(dist2),
                                                                         side), fx, fy
            walked += seg
        if not found or bs != bs:
            out[b, 0] = out[b, 1] = out[b, 2] = math.nan
            continue
        h = math.atan2(bfx, bfy) * _RAD2DEG
        # h % 360.0 (float_rem: fmod, then + 360 when negative; +0.0 for a zero); fmod(h,
        # 360) is h itself, since |h| <= 180
        out[b, 0], out[b, 1], out[b, 2] = bs, bd, h + 360.0 if h < 0.0 else h + 0.0


_T27 = 134217729.0  # 2 ** 27 + 1, Veltkamp's constant
_TWO_PI = 2.0 * math.pi


def _hypot(a, b):  # pragma: no cover - compiled
    """CPython 3.11's ``math.hypot(a, b)`` (``vector_norm``), operation for operation."""
    a, b = abs(a), abs(b)
    mx = a if a > b else b
    if math.isinf(a) or math.isinf(b):
        return math.inf
    if a != a or b != b:
        return math.nan
    if mx == 0.0:
        return mx
    _, e = math.frexp(mx)
    if e >= -1023:
        scale = math.ldexp(1.0, -e)
        csum, frac1, frac2, frac3 = 1.0, 0.0, 0.0, 0.0
        for x in (a, b):
            x *= scale
            t = x * _T27
            hi = t - (t - x)
            lo = x - hi
            x = hi * hi
            old = csum
            csum += x
            frac1 += (old - csum) + x
            x = 2.0 * hi * lo
            old = csum
            csum += x
            frac2 += (old - csum) + x
            frac3 += lo * lo
        h = math.sqrt(csum - 1.0 + (frac1 + frac2 + frac3))
        t = h * _T27
        hi = t - (t - h)
        lo = h - hi
        x = -hi * hi
        old = csum
        csum += x
        frac1 += (old - csum) + x
        x = -2.0 * hi * lo
        old = csum
        csum += x
        frac2 += (old - csum) + x
        x = -lo * lo
        old = csum
        csum += x
        frac3 += (old - csum) + x
        x = csum - 1.0 + (frac1 + frac2 + frac3)
        return (h + x / (2.0 * h)) / scale
    csum, frac = 1.0, 0.0  # subnormal: divided by the largest instead
    for x in (a, b):
        x /= mx
        x = x * x
        old = csum
        csum += x
        frac += (old - csum) + x
    return mx * math.sqrt(csum - 1.0 + frac)


def _fits(s, x, y, dx, dy, dist, f, i, kept, buf, tol):  # pragma: no cover - compiled
    """``ConcisePathHistory._fits``."""
    ref = f[s, _REF]
    if ref != ref:
        return True
    if dist == 0.0:
        return False
    d = math.atan2(dy, dx) - ref
    if d >= math.pi:
        d -= _TWO_PI
    elif d < -math.pi:
        d += _TWO_PI
    if d < f[s, _LO] or d > f[s, _HI]:
        return False
    n = i[s, _BUF]
    if buf[s, 4, n - 1] <= dist:
        return True
    k = i[s, _KEPT] - 1
    ax, ay = kept[s, 1, k], kept[s, 2, k]
    ux, uy = dx / dist, dy / dist
    for j in range(n - 1, -1, -1):
        if buf[s, 4, j] <= dist:
            break
        px, py, rad = buf[s, 0, j], buf[s, 1, j], buf[s, 3, j]
        if ((px - ax) * ux + (py - ay) * uy + rad > dist
                and _hypot(px - x, py - y) + rad > tol):
            return False
    return True


def _find(s, cx, cy, i, cells):  # pragma: no cover - compiled
    for j in range(i[s, _BUF]):
        if cells[s, 0, j] == cx and cells[s, 1, j] == cy:
            return j
    return -1


def _push(s, x, y, dx, dy, dist, f, i, buf, cells, tol, inv):  # pragma: no cover
    """``ConcisePathHistory._push``."""
    if dist > tol:
        phi = math.atan2(dy, dx)
        half = math.asin(tol / dist)
        if f[s, _REF] != f[s, _REF]:
            f[s, _REF], f[s, _LO], f[s, _HI] = phi, -half, half
        else:
            d = phi - f[s, _REF]
            if d >= math.pi:
                d -= _TWO_PI
            elif d < -math.pi:
                d += _TWO_PI
            if d - half > f[s, _LO]:
                f[s, _LO] = d - half
            if d + half < f[s, _HI]:
                f[s, _HI] = d + half
    cx, cy = math.floor(x * inv), math.floor(y * inv)
    n = i[s, _BUF]
    j = _find(s, cx, cy, i, cells)
    if j >= 0:  # within _MERGE_FRACTION * tol of that entry's centre
        gap = _hypot(x - buf[s, 0, j], y - buf[s, 1, j])
        if gap > buf[s, 3, j]:
            buf[s, 3, j] = gap
            reach = buf[s, 2, j] + gap
            for k in range(j, n):  # the running maximum is non-decreasing
                if buf[s, 4, k] >= reach:
                    break
                buf[s, 4, k] = reach
        return
    cells[s, 0, n], cells[s, 1, n] = cx, cy
    buf[s, 4, n] = dist if n == 0 or dist > buf[s, 4, n - 1] else buf[s, 4, n - 1]
    buf[s, 0, n], buf[s, 1, n], buf[s, 2, n], buf[s, 3, n] = x, y, dist, 0.0
    i[s, _BUF] = n + 1


def _popleft(s, i, kept, segs):  # pragma: no cover - compiled
    n = i[s, _KEPT]
    for k in range(n - 1):
        kept[s, 0, k], kept[s, 1, k], kept[s, 2, k] = (kept[s, 0, k + 1], kept[s, 1, k + 1],
                                                       kept[s, 2, k + 1])
    for k in range(n - 2):
        segs[s, k] = segs[s, k + 1]
    i[s, _KEPT] = n - 1


def _segs_sum(s, i, segs):  # pragma: no cover - compiled
    total = 0.0
    for k in range(i[s, _KEPT] - 1):
        total += segs[s, k]
    return total


def _retain_head(s, f, i, kept, segs, max_points):  # pragma: no cover - compiled
    """``ConcisePathHistory._retain_head``."""
    n = i[s, _KEPT]
    ax, ay = kept[s, 1, n - 1], kept[s, 2, n - 1]
    hx, hy = f[s, _HX], f[s, _HY]
    kept[s, 0, n], kept[s, 1, n], kept[s, 2, n] = f[s, _HT], hx, hy
    segs[s, n - 1] = _hypot(hx - ax, hy - ay)
    i[s, _KEPT] = n + 1
    while i[s, _KEPT] > max_points:
        _popleft(s, i, kept, segs)
    f[s, _KEPT_LEN] = _segs_sum(s, i, segs)
    i[s, _BUF] = 0
    f[s, _REF], f[s, _LO], f[s, _HI] = math.nan, -math.inf, math.inf


def _trim_length(s, head_dist, f, i, kept, segs, max_length):  # pragma: no cover
    """``ConcisePathHistory._trim_length``."""
    if i[s, _KEPT] > 1 and head_dist + f[s, _KEPT_LEN] - segs[s, 0] >= max_length:
        while i[s, _KEPT] > 1 and head_dist + f[s, _KEPT_LEN] - segs[s, 0] >= max_length:
            _popleft(s, i, kept, segs)
            f[s, _KEPT_LEN] = _segs_sum(s, i, segs)


def _add(slots, samples, f, i, kept, segs, buf, cells, tol, inv, max_chord, max_length,
         max_points, max_buffer):  # pragma: no cover - compiled
    """``ConcisePathHistory.add`` of ``samples[k]`` (t, x, y) to row ``slots[k]``, for
    each k in order."""
    for k in range(slots.shape[0]):
        s = slots[k]
        t, x, y = samples[k, 0], samples[k, 1], samples[k, 2]
        if not (t > f[s, _LAST_T] and math.isfinite(t) and math.isfinite(x)
                and math.isfinite(y)):
            i[s, _REJECTED] += 1
            continue
        f[s, _LAST_T] = t
        n = i[s, _KEPT]
        if n == 0:
            kept[s, 0, 0], kept[s, 1, 0], kept[s, 2, 0] = t, x, y
            i[s, _KEPT] = 1
            f[s, _HT], f[s, _HX], f[s, _HY] = t, x, y
            i[s, _HEAD_KEPT] = 1
            continue
        ax, ay = kept[s, 1, n - 1], kept[s, 2, n - 1]
        dx, dy = x - ax, y - ay
        dist = _hypot(dx, dy)
        nb = i[s, _BUF]
        if nb and (dist > max_chord or not _fits(s, x, y, dx, dy, dist, f, i, kept, buf, tol)
                   or (nb >= max_buffer and _find(s, math.floor(x * inv),
                                                   math.floor(y * inv), i, cells) < 0)):
            _retain_head(s, f, i, kept, segs, max_points)
            n = i[s, _KEPT]
            ax, ay = kept[s, 1, n - 1], kept[s, 2, n - 1]
            dx, dy = x - ax, y - ay
            dist = _hypot(dx, dy)
        f[s, _HT], f[s, _HX], f[s, _HY] = t, x, y
        i[s, _HEAD_KEPT] = 0
        _push(s, x, y, dx, dy, dist, f, i, buf, cells, tol, inv)
        _trim_length(s, dist, f, i, kept, segs, max_length)

