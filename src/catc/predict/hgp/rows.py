"""The compiled loop of :class:`catc.predict.hgp.table.HgpTable`: the Kalman branch's
update and the window's push for many rows, in one call per tick (numba, cached per
machine; compiled, or loaded from the cache, when the first table is made)."""

from __future__ import annotations

import math

from catc.predict.kalman import compiled_kf_step

__all__ = ["apply", "kernel"]

_KERNEL = None


def kernel():
    """:func:`apply` compiled (numba, cached per machine), with the Kalman branch's
    compiled step inside; made with the first table."""
    global _KERNEL, _KF_STEP
    if _KERNEL is None:
        from numba import njit

        _KF_STEP = compiled_kf_step()
        _KERNEL = njit(cache=True, error_model="numpy")(apply)
    return _KERNEL


_KF_STEP = None


def apply(slots, obs, buf, lo, hi, turn, run, since, sel, last, kf_t, kf_h, kf_e, kf_n,
           kf_p, kf_a, tw, q, r0, r1, r2, gap_s, anchor):  # pragma: no cover - compiled
    """``KalmanPredictor.update`` and ``WindowState.push`` of observation ``obs[k]`` (the
    columns of :class:`Observation`) in row ``slots[k]``, for each k in order: the same
    operations in the same order as those methods."""
    width = buf.shape[2]
    for k in range(slots.shape[0]):
        s = slots[k]
        t, x, y, v = obs[k, 0], obs[k, 1], obs[k, 2], obs[k, 3]
        hd, ac, yw = obs[k, 4], obs[k, 5], obs[k, 6]
        # the Kalman branch
        h = math.radians(hd)
        se, ce = math.sin(h), math.cos(h)
        lat = v * math.radians(yw)
        ze = (x, v * se, ac * se + lat * ce)
        zn = (y, v * ce, ac * ce - lat * se)
        if kf_t[s] != kf_t[s]:  # its first observation
            e, n = ze, zn
            p = (r0, 0.0, 0.0, r1, 0.0, r2)
        else:
            e, n, p = _KF_STEP(t - kf_t[s], q, (r0, r1, r2),
                               (kf_p[s, 0], kf_p[s, 1], kf_p[s, 2], kf_p[s, 3], kf_p[s, 4],
                                kf_p[s, 5]),
                               (kf_e[s, 0], kf_e[s, 1], kf_e[s, 2]),
                               (kf_n[s, 0], kf_n[s, 1], kf_n[s, 2]), ze, zn)
        for i in range(3):
            kf_e[s, i] = e[i]
            kf_n[s, i] = n[i]
        for i in range(6):
            kf_p[s, i] = p[i]
        kf_t[s] = t
        kf_h[s] = hd
        if anchor:
            kf_a[s, 0] = x - e[0]
            kf_a[s, 1] = y - n[0]
        # the window
        if last[s, 0] != last[s, 0]:
            run[s] = 1
        else:
            dd = h - math.radians(last[s, 4])
            if abs(dd) >= math.pi:
                mod = (dd + math.pi) % (2.0 * math.pi) - math.pi
                if mod == -math.pi and dd > 0:
                    mod = math.pi
                turn[s] += mod - dd
            gap = t - last[s, 0]
            run[s] = run[s] + 1 if abs(gap - 0.1) <= 2e-6 else 1
            if gap > gap_s + 1e-6:
                sel[s, 0] = -1
                sel[s, 1] = -1
        if hi[s] == width:
            keep = tw - 1
            for j in range(keep):
                for r in range(5):
                    buf[s, r, j] = buf[s, r, hi[s] - keep + j]
            hi[s] = keep
        c = hi[s]
        buf[s, 0, c] = t
        buf[s, 1, c] = v
        buf[s, 2, c] = h + turn[s]
        buf[s, 3, c] = x
        buf[s, 4, c] = y
        hi[s] = c + 1
        lo[s] = max(0, c + 1 - tw)
        since[s] += 1
        for i in range(7):
            last[s, i] = obs[k, i]
