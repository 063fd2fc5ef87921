"""The CA-TC's concise path histories as rows of shared arrays (issue 30, item 3) against
:class:`catc.pathhistory.ConcisePathHistory`, bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from catc.cam._histories import PathHistories, _kernels
from catc.pathhistory import ConcisePathHistory


def test_the_compiled_hypot_is_python_s() -> None:
    """math.hypot is CPython's own (vector_norm), not the C library's: the compiled copy
    must agree on every input, subnormal, huge, infinite and NaN ones too."""
    _kernels()
    from catc.cam import _histories

    rng = np.random.default_rng(3)
    for scale in (1e-310, 1e-9, 1.0, 300.0, 1e200):
        a = rng.normal(size=20_000) * scale
        b = rng.normal(size=20_000) * scale * rng.uniform(0.0, 2.0, 20_000)
        for x, y in zip(a.tolist(), b.tolist(), strict=True):
            assert _histories._hypot(x, y) == math.hypot(x, y), (x, y)
    for x, y in ((math.inf, math.nan), (math.nan, 1.0), (0.0, -0.0), (3.0, 4.0)):
        got, want = _histories._hypot(x, y), math.hypot(x, y)
        assert got == want or (got != got and want != want)


@pytest.mark.parametrize("tolerance", [0.3, 1.0])
def test_rows_keep_the_points_the_objects_keep(tolerance: float) -> None:
    """Straight, weaving and turning vehicles, one standing with GNSS jitter, reversals,
    speed changes, lost and out-of-order samples, and a row released and made again:
    every row's points equal its object's at every read."""
    rng = np.random.default_rng(5)
    table = PathHistories(tolerance, capacity=4)  # grows
    n = 36
    rows = [table.row() for _ in range(n)]
    objs = [ConcisePathHistory(tolerance_m=tolerance) for _ in range(n)]
    state = [(0.0, rng.uniform(-100, 100), rng.uniform(-100, 100), rng.uniform(0, 6.3),
              rng.uniform(0, 30)) for _ in range(n)]
    compared = 0
    for step in range(1500):
        for j in range(n):
            t, x, y, h, v = state[j]
            kind = j % 6
            t += 0.1
            if kind == 0:
                h += rng.normal(0, 0.02)
            elif kind == 1:
                h += 0.05
            elif kind == 2:  # standing, GNSS jitter
                v = 0.0
                x += rng.normal(0, 0.15)
                y += rng.normal(0, 0.15)
            elif kind == 3 and step % 50 == 0:
                h += math.pi
            elif kind == 4:
                v = abs(v + rng.normal(0, 1))
            x += v * 0.1 * math.sin(h) + rng.normal(0, 0.05)
            y += v * 0.1 * math.cos(h) + rng.normal(0, 0.05)
            state[j] = (t, x, y, h, v)
            if rng.random() < 0.3:
                continue
            tt = t if rng.random() > 0.01 else t - 0.5  # not after the last: ignored
            rows[j].add(tt, x, y)
            objs[j].add(tt, x, y)
        if step % 3 == 0:
            for row, obj in zip(rows, objs, strict=True):
                assert row.point_tuple() == obj.point_tuple()
                compared += 1
        if step % 300 == 150:
            rows[3].add(1e9, 0.0, 0.0)  # queued, then dropped with its row
            rows[3].release()
            rows[3], objs[3] = table.row(), ConcisePathHistory(tolerance_m=tolerance)
    assert compared > 10_000 and max(len(r.point_tuple()) for r in rows) > 10


def test_trail_offsets_are_trail_offset_s() -> None:
    """The compiled trail offsets (lane estimation, CA-TC step 6) against
    catc.classify.trail_offset on the same trails: the HV beside, on, ahead of and
    behind each trail, heads on a trail's first point (a zero-length segment), empty and
    one-point histories: every number the same, None where it is None."""
    from catc.classify import trail_offset

    rng = np.random.default_rng(11)
    table = PathHistories(0.3, capacity=8)
    rows = [table.row() for _ in range(40)]
    for j, row in enumerate(rows):
        x, y, h = rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(0, 6.3)
        for k in range(j * 7 % 200):  # row 0 stays empty
            h += (0.03 if j % 3 else -0.02) + rng.normal(0, 0.01)
            x, y = x + 2.0 * math.sin(h), y + 2.0 * math.cos(h)
            row.add(0.1 * k, x, y)
    checked = found = 0
    for _ in range(60):
        heads = []
        for j, row in enumerate(rows):
            pts = row.point_tuple()
            if j % 5 == 0 and pts:
                heads.append(pts[0])  # a zero-length first segment
            else:
                base = pts[0] if pts else (0.0, 0.0)
                heads.append((base[0] + rng.normal(0, 3), base[1] + rng.normal(0, 3)))
        pts0 = rows[rng.integers(len(rows))].point_tuple() or ((0.0, 0.0),)
        anchor = pts0[rng.integers(len(pts0))]
        p = (anchor[0] + rng.normal(0, 2), anchor[1] + rng.normal(0, 2))
        got = table.trail_offsets([r.slot for r in rows], np.array(heads), p)
        for k, row in enumerate(rows):
            want = trail_offset((heads[k], *row.point_tuple()), p)
            if want is None:
                assert np.isnan(got[k]).all(), (k, got[k])
            else:
                assert tuple(got[k].tolist()) == want, (k, got[k], want)
                found += 1
            checked += 1
    assert found > 200 and checked - found > 200, (found, checked)
