"""Tests for catc.pathhistory: the concise path history (SAE J2945/1 style).

Expectations come from geometry worked out by hand (straight lines, a circle's sagitta
``R (1 - cos(theta / 2))``, a right-angle corner, a reversal) and from one brute-force
check that the module does not use: the distance of every raw sample from the concise
polyline, segment by segment, in numpy.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from catc import units as u
from catc.bsm import PathHistory, PathHistoryPoint
from catc.classify import HostPath
from catc.geo import EnuFrame
from catc.pathhistory import ConcisePathHistory, from_bsm_path_history

Sample = tuple[float, float, float]
EPS = 1e-9


# --- helpers -------------------------------------------------------------------------------


def feed(ph: ConcisePathHistory, samples: list[Sample]) -> ConcisePathHistory:
    for t, x, y in samples:
        ph.add(t, x, y)
    return ph


def polyline_distances(points: list[tuple[float, float]], xy: np.ndarray) -> np.ndarray:
    """Distance of each row of ``xy`` from the polyline ``points`` (brute force)."""
    p = np.asarray(points, dtype=float)
    if len(p) == 1:
        return np.hypot(xy[:, 0] - p[0, 0], xy[:, 1] - p[0, 1])
    a, b = p[:-1], p[1:]
    ab = b - a
    ab2 = np.einsum("ij,ij->i", ab, ab)
    rel = xy[:, None, :] - a[None, :, :]
    t = np.einsum("kij,ij->ki", rel, ab) / np.where(ab2 > 0.0, ab2, 1.0)[None, :]
    t = np.clip(t, 0.0, 1.0)
    e = rel - t[:, :, None] * ab[None, :, :]
    return np.sqrt(np.einsum("kij,kij->ki", e, e)).min(axis=1)


def covered(ph: ConcisePathHistory, samples: list[Sample]) -> np.ndarray:
    """The raw samples the history still covers: not older than its oldest point."""
    oldest_t = ph.crumbs()[-1][0]
    return np.array([(x, y) for t, x, y in samples if t >= oldest_t])


def assert_within_tolerance(ph: ConcisePathHistory, samples: list[Sample]) -> None:
    d = polyline_distances(ph.points(), covered(ph, samples))
    assert d.max() <= ph.tolerance_m + EPS, f"sample {int(d.argmax())} is {d.max():.6f} m off"


def polyline_length(points: list[tuple[float, float]]) -> float:
    p = np.asarray(points, dtype=float)
    return float(np.hypot(*np.diff(p, axis=0).T).sum()) if len(p) > 1 else 0.0


def line(n: int, step: float = 1.0, dt: float = 0.1) -> list[Sample]:
    """``n`` samples east along y = 0, ``step`` metres apart, from (0, 0)."""
    return [(i * dt, i * step, 0.0) for i in range(n)]


# --- straight lines and the caps -----------------------------------------------------------


def test_straight_line_keeps_only_its_end_points() -> None:
    ph = feed(ConcisePathHistory(), line(50))
    assert ph.points() == [(49.0, 0.0), (0.0, 0.0)]
    assert ph.crumbs() == [(pytest.approx(4.9), 49.0, 0.0), (0.0, 0.0, 0.0)]
    assert ph.length_m == 49.0
    assert ph.rejected == 0


def test_first_sample_alone() -> None:
    ph = ConcisePathHistory()
    assert ph.points() == [] and ph.crumbs() == [] and ph.length_m == 0.0
    ph.add(3.0, 1.0, 2.0)
    assert ph.points() == [(1.0, 2.0)]
    assert ph.crumbs() == [(3.0, 1.0, 2.0)]


def test_straight_line_forced_points_from_the_buffer_cap() -> None:
    # Anchor s0, raw samples s1..s100 fill the 100-sample buffer; s101 forces s100.
    ph = feed(ConcisePathHistory(max_buffer=100), line(250))
    assert ph.points() == [(249.0, 0.0), (200.0, 0.0), (100.0, 0.0), (0.0, 0.0)]


def test_straight_line_forced_points_from_the_chord_bound() -> None:
    # 10 m steps: s0 -> s31 would be a 310 m chord > 300 m, so s30 (300 m) is kept.
    ph = feed(ConcisePathHistory(max_buffer=1000), line(40, step=10.0))
    assert ph.points() == [(390.0, 0.0), (300.0, 0.0), (0.0, 0.0)]
    # s61 forces s60; the history then spans 700 m, and without its oldest segment
    # (s0 -> s300) it still spans 400 >= 300 m, so s0 goes; without s300 it would span
    # only 100 m, so s300 stays.
    ph = feed(ConcisePathHistory(max_buffer=1000), line(71, step=10.0))
    assert ph.points() == [(700.0, 0.0), (600.0, 0.0), (300.0, 0.0)]
    assert ph.length_m == 400.0


def test_length_bound_keeps_the_shortest_history_covering_max_length() -> None:
    ph = ConcisePathHistory(max_length_m=120.0, max_chord_m=50.0)
    for i, s in enumerate(line(2000, step=0.7)):
        ph.add(*s)
        pts = ph.points()
        total = polyline_length(pts)
        assert total == pytest.approx(ph.length_m)
        if i * 0.7 >= 120.0:
            assert total >= 120.0 - EPS  # covers max_length_m ...
            oldest = math.dist(pts[-1], pts[-2])
            assert total - oldest < 120.0  # ... and no more than needed
            assert total <= 120.0 + 50.0 + EPS  # so at most one chord beyond it


def test_points_cap_drops_the_oldest_points() -> None:
    # A staircase of 5 m legs: every corner is a concise point.
    samples: list[Sample] = []
    x = y = 0.0
    t = 0.0
    for leg in range(60):
        for _ in range(10):
            t += 0.1
            if leg % 2 == 0:
                x += 0.5
            else:
                y += 0.5
            samples.append((t, x, y))
    ph = ConcisePathHistory(max_points=23)
    for s in samples:
        ph.add(*s)
        assert len(ph.points()) <= 23 + 1  # 23 crumbs behind the current position
    assert len(ph.points()) == 24
    assert ph.points()[0] == (x, y)
    assert_within_tolerance(ph, samples)
    small = feed(ConcisePathHistory(max_points=5), samples)
    assert small.crumbs() == ph.crumbs()[:6]


# --- curves ---------------------------------------------------------------------------------


def test_circle_keeps_points_where_the_sagitta_reaches_the_tolerance() -> None:
    r, tol, step = 50.0, 1.0, 0.25  # metres; dense sampling along the arc
    dphi = step / r
    theta_max = 2.0 * math.acos(1.0 - tol / r)  # widest chord with sagitta <= tol
    n = int(1.5 * math.pi / dphi)  # three quarters of a turn, ~236 m
    samples = [(i * 0.01, r * math.cos(i * dphi), r * math.sin(i * dphi)) for i in range(n)]
    ph = feed(ConcisePathHistory(tolerance_m=tol), samples)
    assert_within_tolerance(ph, samples)

    pts = ph.points()
    angles = [math.atan2(py, px) for px, py in reversed(pts)]  # oldest first, increasing
    spans = np.diff(np.unwrap(angles))
    interior = spans[:-1]  # the newest span ends at the current sample, not a kept point
    assert len(interior) == int(1.5 * math.pi / theta_max)
    for theta in interior:
        # kept: its chord's sagitta is within tolerance (the sample nearest its middle
        # is at most half a step from it); the next sample's chord broke it.
        assert r * (1.0 - math.cos((theta - dphi) / 2.0)) <= tol
        assert r * (1.0 - math.cos((theta + 2.0 * dphi) / 2.0)) > tol
    for px, py in pts:
        assert math.hypot(px, py) == pytest.approx(r)  # kept points are samples


def test_right_angle_turn_keeps_the_corner() -> None:
    east = [(i * 0.1, float(i), 0.0) for i in range(101)]  # (0,0) .. (100,0)
    north = [(10.0 + j * 0.1, 100.0, float(j)) for j in range(1, 101)]  # (100,1) .. (100,100)
    ph = feed(ConcisePathHistory(max_buffer=1000), east + north)
    # (0,0) -> (100,1): the farthest sample, (100,0), is 100/sqrt(10001) = 0.99995 m off;
    # (0,0) -> (100,2): (100,0) is 200/sqrt(10004) = 1.9996 m off, so (100,1) is kept.
    assert ph.points() == [(100.0, 100.0), (100.0, 1.0), (0.0, 0.0)]
    assert_within_tolerance(ph, east + north)
    # With 2 m steps the corner sample itself is the kept point.
    ph = feed(ConcisePathHistory(), [(t, x, y) for t, x, y in east + north if x % 2 == y % 2 == 0])
    assert ph.points() == [(100.0, 100.0), (100.0, 0.0), (0.0, 0.0)]


def test_reversal_keeps_the_turning_point_within_tolerance() -> None:
    # 20 m east then back west: from (0,0) the chord to (19,0) leaves (20,0) exactly 1 m
    # beyond its end (allowed), the chord to (18,0) leaves it 2 m beyond: keep (19,0).
    out = [(i * 0.1, float(i), 0.0) for i in range(21)]
    back = [(2.0 + j * 0.1, 20.0 - j, 0.0) for j in range(1, 6)]
    ph = feed(ConcisePathHistory(), out + back)
    assert ph.points() == [(15.0, 0.0), (19.0, 0.0), (0.0, 0.0)]
    assert_within_tolerance(ph, out + back)


def test_merged_samples_still_bound_the_chord_end() -> None:
    # (10.05, 0) is 5 cm from (10, 0): the buffer keeps them as one entry of radius 0.05.
    # Coming back to (9, 0), the sample (10.05, 0) would be 1.05 m beyond the chord's
    # end: keep it.
    samples = [(i * 0.1, float(i), 0.0) for i in range(11)] + [(1.1, 10.05, 0.0),
                                                               (1.2, 9.0, 0.0)]
    ph = feed(ConcisePathHistory(), samples)
    assert ph.points() == [(9.0, 0.0), (10.05, 0.0), (0.0, 0.0)]
    assert_within_tolerance(ph, samples)


def test_standstill_does_not_use_up_points() -> None:
    rng = np.random.default_rng(7)
    samples = line(100)  # 99 m east
    t = samples[-1][0]
    for _ in range(3000):  # five minutes at 10 Hz, a few cm of jitter
        t += 0.1
        dx, dy = rng.uniform(-0.05, 0.05, 2)
        samples.append((t, 99.0 + dx, dy))
    ph = feed(ConcisePathHistory(), samples)
    assert len(ph.points()) <= 3
    assert_within_tolerance(ph, samples)
    for i in range(1, 101):
        samples.append((t + 0.1 * i, 99.0 + i, 0.0))
        ph.add(*samples[-1])
    assert len(ph.points()) <= 4
    assert_within_tolerance(ph, samples)


# --- input handling and output form -------------------------------------------------------


def test_out_of_order_and_non_finite_samples_are_rejected_and_counted() -> None:
    ph = ConcisePathHistory()
    ph.add(1.0, 0.0, 0.0)
    ph.add(2.0, 10.0, 0.0)
    ph.add(2.0, 99.0, 99.0)  # same time
    ph.add(1.5, 99.0, 99.0)  # earlier
    ph.add(math.nan, 99.0, 99.0)
    ph.add(3.0, math.nan, 0.0)
    ph.add(3.0, 0.0, math.inf)
    assert ph.rejected == 5
    assert ph.points() == [(10.0, 0.0), (0.0, 0.0)]
    ph.add(3.0, 20.0, 0.0)  # a rejected time does not block the next good sample
    assert ph.points() == [(20.0, 0.0), (0.0, 0.0)]
    assert ph.rejected == 5


def test_points_are_most_recent_first_and_cached_copies() -> None:
    east = [(i * 0.1, float(i), 0.0) for i in range(31)]
    north = [(3.0 + j * 0.1, 30.0, float(j)) for j in range(1, 31)]
    ph = feed(ConcisePathHistory(), east + north)
    pts, crumbs = ph.points(), ph.crumbs()
    assert pts[0] == (30.0, 30.0)  # the latest sample first
    assert pts[-1] == (0.0, 0.0)
    assert [(x, y) for _, x, y in crumbs] == pts
    times = [c[0] for c in crumbs]
    assert times == sorted(times, reverse=True) and len(set(times)) == len(times)
    pts.clear()  # callers get copies
    assert ph.points() == [(c[1], c[2]) for c in crumbs]
    assert len(ph) == len(crumbs)
    # the format catc.classify.HostPath expects: most recent first, current point first
    host = HostPath(30.0, 30.0, 0.0, history=tuple(ph.points()))
    s, d = host.to_path_frame((31.0, 15.0))  # beside the northbound leg, 15 m back
    assert s == pytest.approx(-15.0) and d == pytest.approx(1.0)


def test_bad_configuration_is_refused() -> None:
    for kwargs in ({"tolerance_m": 0.0}, {"tolerance_m": math.nan}, {"max_chord_m": -1.0},
                   {"max_length_m": math.inf}, {"max_points": 0}, {"max_buffer": 0}):
        with pytest.raises(ValueError):
            ConcisePathHistory(**kwargs)


# --- property: random smooth paths ------------------------------------------------------------


def smooth_path(n: int, dt: float, v0: float, dv: float, k0: float, k1: float, w: float,
                phase: float, heading: float) -> list[Sample]:
    """Speed v0 (1 + dv sin(w t)), curvature k0 + k1 sin(w t + phase), Euler-integrated."""
    x = y = 0.0
    psi = heading
    out = [(0.0, 0.0, 0.0)]
    for i in range(1, n):
        t = i * dt
        v = v0 * (1.0 + dv * math.sin(w * t))
        psi += v * (k0 + k1 * math.sin(w * t + phase)) * dt
        x += v * math.cos(psi) * dt
        y += v * math.sin(psi) * dt
        out.append((t, x, y))
    return out


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(2, 600),
    dt=st.sampled_from([0.05, 0.1, 0.2]),
    v0=st.floats(0.5, 40.0),
    dv=st.floats(0.0, 0.9),
    k0=st.floats(-0.1, 0.1),
    k1=st.floats(-0.1, 0.1),
    w=st.floats(0.0, 2.0),
    phase=st.floats(0.0, 2.0 * math.pi),
    heading=st.floats(-math.pi, math.pi),
    tol=st.sampled_from([0.3, 1.0, 2.5]),
    max_points=st.integers(1, 23),
)
def test_every_covered_sample_is_within_tolerance_of_the_polyline(
    n: int, dt: float, v0: float, dv: float, k0: float, k1: float, w: float, phase: float,
    heading: float, tol: float, max_points: int,
) -> None:
    samples = smooth_path(n, dt, v0, dv, k0, k1, w, phase, heading)
    ph = feed(ConcisePathHistory(tolerance_m=tol, max_points=max_points, max_length_m=150.0),
              samples)
    assert_within_tolerance(ph, samples)
    pts = ph.points()
    assert pts[0] == samples[-1][1:]
    assert len(pts) <= max_points + 1
    if len(pts) > 2:
        assert polyline_length(pts) - math.dist(pts[-1], pts[-2]) < 150.0


def reference_history(samples: list[Sample], tol: float) -> tuple[list[Sample], float]:
    """The rule written out plainly (no caps, no merging), and its closest call to ``tol``.

    Keep the anchor and every raw sample since it; when a raw sample is farther than
    ``tol`` from the segment anchor -> new sample, the previous sample becomes the anchor.
    """
    kept, buf = [samples[0]], []
    margin = math.inf
    for s in samples[1:]:
        if buf:
            a = np.array(kept[-1][1:])
            d = polyline_distances([tuple(a), s[1:]], np.array([b[1:] for b in buf]))
            margin = min(margin, float(np.abs(d - tol).min()))
            if d.max() > tol:
                kept.append(buf[-1])
                buf = []
        buf.append(s)
    return ([buf[-1]] if buf else []) + kept[::-1], margin


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.tuples(st.floats(0.3, 5.0), st.floats(-math.pi, math.pi)), min_size=1,
                   max_size=150),
)
def test_matches_the_plain_quadratic_rule(steps: list[tuple[float, float]]) -> None:
    # Steps of 0.3 m or more never merge buffer entries (a quarter of the tolerance).
    x = y = psi = 0.0
    samples: list[Sample] = [(0.0, 0.0, 0.0)]
    for i, (length, turn) in enumerate(steps, start=1):
        psi += turn
        x += length * math.cos(psi)
        y += length * math.sin(psi)
        samples.append((i * 0.1, x, y))
    expected, margin = reference_history(samples, 1.0)
    assume(margin > 1e-9)  # exact ties at the tolerance may round either way
    ph = feed(ConcisePathHistory(max_chord_m=1e9, max_length_m=1e9, max_points=10**6,
                                 max_buffer=10**6), samples)
    assert ph.crumbs() == expected


@settings(max_examples=40, deadline=None)
@given(
    steps=st.lists(st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)), min_size=1,
                   max_size=400),
    stop_every=st.integers(2, 50),
)
def test_noisy_paths_with_stops_and_reversals_stay_within_tolerance(
    steps: list[tuple[float, float]], stop_every: int,
) -> None:
    x = y = 0.0
    samples: list[Sample] = [(0.0, 0.0, 0.0)]
    for i, (dx, dy) in enumerate(steps, start=1):
        scale = 0.01 if i % stop_every < stop_every // 2 else 1.0  # jitter when "stopped"
        x += dx * scale
        y += dy * scale
        samples.append((i * 0.1, x, y))
    ph = feed(ConcisePathHistory(max_buffer=30), samples)
    assert_within_tolerance(ph, samples)


# --- BSM Part II path history ----------------------------------------------------------------


FRAME = EnuFrame(42.2808, -83.7430, 0.0)


def quantised(q: u.Quantity, x: float) -> float:
    value = q.from_raw(q.to_raw(x))
    assert value is not None
    return value


def make_path_history(current: tuple[float, float], trail: list[tuple[float, float, float]]
                      ) -> tuple[PathHistory, float, float]:
    """A PathHistory whose crumbs are the ENU points ``trail`` (dt_back, x, y), as sent."""
    lat, lon, _ = FRAME.to_geodetic(*current, 0.0)
    lat, lon = quantised(u.LATITUDE, lat), quantised(u.LONGITUDE, lon)
    crumbs = []
    for dt_back, x, y in trail:
        clat, clon, _ = FRAME.to_geodetic(x, y, 0.0)
        crumbs.append(PathHistoryPoint(
            lat_offset=quantised(u.OFFSET_LL, clat - lat),
            lon_offset=quantised(u.OFFSET_LL, clon - lon),
            elev_offset=quantised(u.VERT_OFFSET, 0.3),
            time_offset=quantised(u.TIME_OFFSET, dt_back),
        ))
    return PathHistory(points=tuple(crumbs)), lat, lon


def test_bsm_path_history_round_trips_to_enu() -> None:
    current = (1250.0, -830.0)  # km-scale offsets from the frame origin
    trail = [(0.5, 1245.0, -829.0), (2.3, 1230.0, -820.0), (4.87, 1205.5, -790.25),
             (9.01, 1180.0, -700.0)]
    ph, lat, lon = make_path_history(current, trail)
    got = from_bsm_path_history(ph, FRAME, lat, lon, 100.0)
    assert len(got) == 1 + len(trail)
    t0, x0, y0 = got[0]
    assert t0 == 100.0
    assert math.hypot(x0 - current[0], y0 - current[1]) < 0.02  # 1e-7 deg quantisation
    for (t, x, y), (dt_back, ex, ey) in zip(got[1:], trail, strict=True):
        assert t == pytest.approx(100.0 - dt_back, abs=1e-9)
        assert math.hypot(x - ex, y - ey) < 0.03


def test_bsm_path_history_skips_unavailable_crumbs_and_sorts_by_time() -> None:
    current = (-40.0, 75.0)
    trail = [(1.0, -45.0, 70.0), (3.0, -60.0, 55.0), (6.0, -80.0, 30.0)]
    ph, lat, lon = make_path_history(current, trail)
    p1, p3, p6 = ph.points
    crumbs = (
        p6,  # out of order on purpose
        PathHistoryPoint(None, p1.lon_offset, 0.0, 2.0),
        p1,
        PathHistoryPoint(p1.lat_offset, None, 0.0, 2.0),
        PathHistoryPoint(p1.lat_offset, p1.lon_offset, 0.0, None),
        PathHistoryPoint(p3.lat_offset, p3.lon_offset, None, p3.time_offset),  # no elev: kept
    )
    got = from_bsm_path_history(PathHistory(points=crumbs), FRAME, lat, lon, 10.0)
    assert [t for t, _, _ in got] == pytest.approx([10.0, 9.0, 7.0, 4.0])
    for (_, x, y), (_, ex, ey) in zip(got[1:], trail, strict=True):
        assert math.hypot(x - ex, y - ey) < 0.03
    only_current = from_bsm_path_history(PathHistory(points=()), FRAME, lat, lon, 10.0)
    assert len(only_current) == 1 and only_current[0][:1] == (10.0,)


def test_bsm_path_history_feeds_a_concise_history() -> None:
    current = (0.0, 0.0)
    trail = [(k * 0.5, 0.0, -5.0 * k) for k in range(1, 13)]  # 60 m straight north-bound
    ph, lat, lon = make_path_history(current, trail)
    got = from_bsm_path_history(ph, FRAME, lat, lon, 50.0)
    hist = feed(ConcisePathHistory(), list(reversed(got)))
    pts = hist.points()
    assert len(pts) == 2
    assert math.dist(pts[0], current) < 0.02 and math.dist(pts[1], (0.0, -60.0)) < 0.03
