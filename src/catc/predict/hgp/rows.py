"""The compiled loop of :class:`catc.predict.hgp.table.HgpTable`: the Kalman branch's
update and the window's push for many rows, in one call per tick (numba, cached per
machine; compiled, or loaded from the cache, when the first table is made)."""

from __future__ import annotations

import math

from catc.predict.kalman import compiled_kf_step

__all__ = ["apply", "kernel", "positions"]

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


_DEG2RAD = math.pi / 180.0  # math.radians multiplies by this same constant


def positions(slots, t, last, kf_t, kf_h, kf_e, kf_n, kf_a, out):  # pragma: no cover
    """The kinematic branches' positions at ``t[k]`` of row ``slots[k]``, ``out[k]`` =
    (x, y) of ``ConstantAccelerationPredictor.position`` then of
    ``KalmanPredictor.position``: the same operations in the same order (``sin`` and
    ``cos`` the C library's in both).  Every row has an observation and ``t[k]`` is not
    before it (the caller checks)."""
    for k in range(slots.shape[0]):
        s = slots[k]
        tk = t[k]
        # ConstantAccelerationPredictor.position
        dt = tk - last[s, 0]
        if dt < 0.0:
            dt = 0.0  # elapsed(): within its tolerance
        sp, a = last[s, 3], last[s, 5]
        d = sp * sp / (-2.0 * a) if a < 0.0 and dt >= sp / -a else sp * dt + 0.5 * a * dt * dt
        h = last[s, 4] * _DEG2RAD
        out[k, 0] = last[s, 1] + d * math.sin(h)
        out[k, 1] = last[s, 2] + d * math.cos(h)
        # KalmanPredictor.position, with stop_point
        dt = tk - kf_t[s]
        if dt < 0.0:
            dt = 0.0
        pe, ve, ae = kf_e[s, 0], kf_e[s, 1], kf_e[s, 2]
        pn, vn, an = kf_n[s, 0], kf_n[s, 1], kf_n[s, 2]
        hd = kf_h[s] * _DEG2RAD
        se, ce = math.sin(hd), math.cos(hd)
        u0 = ve * se + vn * ce
        a_h = ae * se + an * ce
        if a_h < 0.0 and dt * -a_h >= u0:
            ts = (0.0 if u0 < 0.0 else u0) / -a_h  # max(u0, 0.0)
            hs = 0.5 * ts * ts
            out[k, 2] = pe + ts * ve + hs * ae + kf_a[s, 0]
            out[k, 3] = pn + ts * vn + hs * an + kf_a[s, 1]
        else:
            h2 = 0.5 * dt * dt
            out[k, 2] = pe + dt * ve + h2 * ae + kf_a[s, 0]
            out[k, 3] = pn + dt * vn + h2 * an + kf_a[s, 1]


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
