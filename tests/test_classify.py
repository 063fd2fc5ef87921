"""Tests for catc.classify: the paper's target-classification zones on HV path coordinates.

Expectations are computed here from the paper's equations (tc_longi, tc_lateral,
tc_heading) written out independently, with ``ld`` positive to the LEFT as in the paper;
the module under test uses ``d`` positive to the right (``ld = -d``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from catc.classify import (
    ClassifyConfig,
    Direction,
    HostPath,
    Lateral,
    Longitudinal,
    classify,
    classify_direction,
    classify_lateral,
    classify_many,
    classify_pair,
    hv_radius_m,
    relative_position,
    trail_offset,
)

CFG = ClassifyConfig()
W = CFG.w_lane
A, B = Longitudinal.AHEAD, Longitudinal.BEHIND
FL, L, C, R, FR = (
    Lateral.FAR_LEFT,
    Lateral.LEFT,
    Lateral.ON_CENTRE,
    Lateral.RIGHT,
    Lateral.FAR_RIGHT,
)
ONG, ONC, NC = Direction.ONGOING, Direction.ONCOMING, Direction.NOT_CLASSIFIED


# --- the paper's equations, written out independently -------------------------------------


def paper_longitudinal(xrel: float) -> Longitudinal:
    return A if xrel >= 0 else B


def paper_lateral(ld: float, w: float = W) -> Lateral:
    """Eq. (tc_lateral) with ld positive to the left, interval by interval."""
    if 1.5 * w < ld:
        return FL
    if 0.5 * w < ld <= 1.5 * w:
        return L
    if -0.5 * w <= ld <= 0.5 * w:
        return C
    if -1.5 * w <= ld < -0.5 * w:
        return R
    return FR


def paper_direction(rv_heading: float, lane_heading: float, cfg: ClassifyConfig = CFG) -> Direction:
    diff = abs((rv_heading - lane_heading + 180.0) % 360.0 - 180.0)
    if diff <= cfg.delta_phi_ongoing:
        return ONG
    if diff >= cfg.delta_phi_oncoming:
        return ONC
    return NC


def place(hv: tuple[float, float], heading: float, s: float, d: float) -> tuple[float, float]:
    """ENU position s metres ahead and d metres to the right of a straight HV."""
    h = math.radians(heading)
    return (
        hv[0] + s * math.sin(h) + d * math.cos(h),
        hv[1] + s * math.cos(h) - d * math.sin(h),
    )


def on_arc(k: float, s: float) -> tuple[float, float, float]:
    """(x, y, heading) at arc length s on the curvature-k path from the origin heading north."""
    if k == 0.0:
        return 0.0, s, 0.0
    return (1.0 - math.cos(k * s)) / k, math.sin(k * s) / k, math.degrees(k * s) % 360.0


# --- classification table on a straight path ----------------------------------------------

LONGS = [float(v) for v in range(-50, 51, 5)]
LATS = sorted({float(v) for v in range(-12, 13)} | {0.5 * W, -0.5 * W, 1.5 * W, -1.5 * W})
HEADINGS = [float(v) for v in range(0, 360, 15)]


def test_grid_north_at_origin_exact_boundaries() -> None:
    """HV at the origin heading north: s = y and d = x exactly, so boundaries are exact."""
    host = HostPath(0.0, 0.0, 0.0)
    n = 0
    for s in LONGS:
        for d in LATS:
            for h in HEADINGS:
                z = classify(host, (d, s), h, CFG)
                assert (z.s, z.d) == (s, d)
                expected = (paper_longitudinal(s), paper_lateral(-d), paper_direction(h, 0.0))
                assert (z.longitudinal, z.lateral, z.direction) == expected, (s, d, h)
                n += 1
    assert n == len(LONGS) * len(LATS) * len(HEADINGS)


def test_grid_rotated_translated_hv() -> None:
    """HV elsewhere, heading 30 deg: same table (cells on a boundary are left out)."""
    hv, hh = (123.4, -56.7), 30.0
    host = HostPath(*hv, hh)
    bounds = {0.5 * W, 1.5 * W}
    for s in (v for v in LONGS if v != 0.0):
        for d in (v for v in LATS if abs(v) not in bounds):
            for h in HEADINGS:
                z = classify(host, place(hv, hh, s, d), hh + h, CFG)
                assert z.s == pytest.approx(s, abs=1e-9)
                assert z.d == pytest.approx(d, abs=1e-9)
                expected = (paper_longitudinal(s), paper_lateral(-d), paper_direction(h, 0.0))
                assert (z.longitudinal, z.lateral, z.direction) == expected, (s, d, h)


# (rv_x, rv_y, rv_heading) with the HV at the origin heading north -> literal zone
HAND_PICKED = [
    ((0.0, 10.0, 0.0), (A, C, ONG)),
    ((0.0, -10.0, 180.0), (B, C, ONC)),
    ((3.6, 20.0, 10.0), (A, R, ONG)),
    ((-3.6, -20.0, 350.0), (B, L, ONG)),
    ((1.8, 5.0, 0.0), (A, C, ONG)),  # |ld| = 0.5 w is On Centre (closed)
    ((1.81, 5.0, 0.0), (A, R, ONG)),
    ((-1.8, 5.0, 0.0), (A, C, ONG)),
    ((5.4, 5.0, 0.0), (A, R, ONG)),  # |ld| = 1.5 w is still Right (closed)
    ((5.41, 5.0, 0.0), (A, FR, ONG)),
    ((-5.4, -5.0, 0.0), (B, L, ONG)),
    ((-5.41, -5.0, 0.0), (B, FL, ONG)),
    ((8.0, 0.0, 90.0), (A, FR, NC)),  # Xrel = 0 is Ahead
    ((-12.0, 50.0, 200.0), (A, FL, ONC)),
    ((0.0, -0.01, 45.0), (B, C, ONG)),  # 45 deg: ongoing (<=)
    ((0.0, 30.0, 135.0), (A, C, ONC)),  # 135 deg: oncoming (>=)
    ((0.0, 30.0, 134.0), (A, C, NC)),
    ((-3.0, -40.0, 225.0), (B, L, ONC)),
]


@pytest.mark.parametrize(("rv", "expected"), HAND_PICKED)
def test_hand_picked_cells(
    rv: tuple[float, float, float], expected: tuple[Longitudinal, Lateral, Direction]
) -> None:
    z = classify(HostPath(0.0, 0.0, 0.0), rv[:2], rv[2])
    assert (z.longitudinal, z.lateral, z.direction) == expected


def test_hand_picked_heading_east() -> None:
    # HV heading east: south is to its right, north to its left.
    host = HostPath(10.0, 10.0, 90.0)
    z = classify(host, (30.0, 6.4), 90.0)
    assert (z.longitudinal, z.lateral, z.direction) == (A, R, ONG)
    assert (z.s, z.d) == pytest.approx((20.0, 3.6))
    z = classify(host, (0.0, 17.0), 270.0)
    assert (z.longitudinal, z.lateral, z.direction) == (B, FL, ONC)


def test_relative_position_straight_sign() -> None:
    # heading north: east is right (+), west left (-)
    assert relative_position((0.0, 0.0), 0.0, (2.0, 5.0)) == pytest.approx((5.0, 2.0))
    assert relative_position((0.0, 0.0), 0.0, (-2.0, -5.0)) == pytest.approx((-5.0, -2.0))
    # heading 180 (south): west is right
    assert relative_position((1.0, 1.0), 180.0, (-1.0, -4.0)) == pytest.approx((5.0, 2.0))


def test_lateral_and_direction_functions_match_paper() -> None:
    for i in range(-2000, 2001):
        d = i / 100.0
        assert classify_lateral(d, W) is paper_lateral(-d, W), d
    for i in range(0, 1801):
        diff = i / 10.0
        assert classify_direction(diff, CFG) is paper_direction(diff, 0.0), diff


def test_config_validation() -> None:
    with pytest.raises(ValueError):
        ClassifyConfig(w_lane=0.0)
    with pytest.raises(ValueError):
        ClassifyConfig(delta_phi_ongoing=100.0, delta_phi_oncoming=90.0)
    with pytest.raises(ValueError):
        ClassifyConfig(delta_phi_oncoming=181.0)
    with pytest.raises(ValueError):
        HostPath(0.0, 0.0, 0.0, radius_m=0.0)


# --- headings ------------------------------------------------------------------------------


def test_heading_wrap_ongoing() -> None:
    z = classify(HostPath(0.0, 0.0, 1.0), place((0.0, 0.0), 1.0, 20.0, 0.0), 359.0)
    assert z.direction is ONG
    assert z.heading_diff_deg == pytest.approx(2.0)
    z = classify(HostPath(0.0, 0.0, 359.0), place((0.0, 0.0), 359.0, 20.0, 0.0), 1.0)
    assert z.direction is ONG
    assert z.heading_diff_deg == pytest.approx(2.0)


@pytest.mark.parametrize(
    ("rv_heading", "expected"),
    [(180.0, ONC), (0.0, ONG), (90.0, NC), (270.0, NC), (-180.0, ONC), (540.0, ONC)],
)
def test_heading_classes(rv_heading: float, expected: Direction) -> None:
    z = classify(HostPath(0.0, 0.0, 0.0), (0.0, 30.0), rv_heading)
    assert z.direction is expected


def test_custom_thresholds() -> None:
    cfg = ClassifyConfig(w_lane=3.0, delta_phi_ongoing=20.0, delta_phi_oncoming=160.0)
    host = HostPath(0.0, 0.0, 0.0)
    assert classify(host, (2.0, 10.0), 30.0, cfg).direction is NC
    assert classify(host, (1.6, 10.0), 30.0, cfg).lateral is R  # 1.6 > 0.5 * 3.0
    assert classify(host, (1.6, 10.0), 30.0).lateral is C  # 1.6 <= 0.5 * 3.6
    assert classify(host, (1.6, 10.0), 30.0).direction is ONG  # 30 <= 45
    assert classify(host, (0.0, 10.0), 165.0, cfg).direction is ONC


# --- curved path ahead ---------------------------------------------------------------------


def test_hv_radius() -> None:
    assert hv_radius_m(20.0, math.degrees(0.2)) == pytest.approx(100.0)
    assert hv_radius_m(20.0, -math.degrees(0.2)) == pytest.approx(-100.0)
    assert math.isinf(hv_radius_m(20.0, 0.0))
    assert math.isinf(hv_radius_m(0.0, 5.0))
    host = HostPath.from_motion(0.0, 0.0, 0.0, 20.0, math.degrees(0.2))
    assert host.radius_m == pytest.approx(100.0)


@pytest.mark.parametrize(
    ("radius", "arc", "straight_lateral"),
    [
        (100.0, 30.0, R),
        (100.0, 40.0, FR),
        (-100.0, 30.0, L),
        (-100.0, 40.0, FL),
    ],
)
def test_curve_same_lane_is_on_centre_along_path(
    radius: float, arc: float, straight_lateral: Lateral
) -> None:
    """An RV ahead in the HV's lane around a 100 m bend: On Centre on the path, not straight."""
    k = 1.0 / radius
    x, y, h = on_arc(k, arc)
    curved = HostPath(0.0, 0.0, 0.0, radius_m=radius)
    z = classify(curved, (x, y), h)
    assert (z.longitudinal, z.lateral, z.direction) == (A, C, ONG)
    assert z.s == pytest.approx(arc, abs=1e-9)
    assert z.d == pytest.approx(0.0, abs=1e-9)
    assert z.heading_diff_deg == pytest.approx(0.0, abs=1e-9)
    # the straight-line projection of the same scene puts it in another lane
    straight = classify(HostPath(0.0, 0.0, 0.0), (x, y), h)
    assert straight.longitudinal is A
    assert straight.lateral is straight_lateral
    s_line, d_line = relative_position((0.0, 0.0), 0.0, (x, y))
    assert s_line == pytest.approx(abs(radius) * math.sin(arc / abs(radius)))
    assert abs(d_line) == pytest.approx(abs(radius) * (1.0 - math.cos(arc / abs(radius))))
    assert relative_position((0.0, 0.0), 0.0, (x, y), radius_m=radius) == pytest.approx(
        (arc, 0.0), abs=1e-9
    )


def test_curve_adjacent_lane() -> None:
    """On the circle one lane inside a right-hand bend: Right; one lane outside: Left."""
    for offset, expected in ((W, R), (-W, L), (2.0 * W, FR), (-2.0 * W, FL)):
        r = 100.0 - offset  # radius of the RV's lane circle, centre at (100, 0)
        a = 0.35
        x, y = 100.0 - r * math.cos(a), r * math.sin(a)
        z = classify(HostPath(0.0, 0.0, 0.0, radius_m=100.0), (x, y), math.degrees(a))
        assert z.lateral is expected
        assert z.d == pytest.approx(offset)
        assert z.s == pytest.approx(100.0 * a)


def test_huge_radius_is_straight() -> None:
    host = HostPath(0.0, 0.0, 0.0, radius_m=1e15)
    assert host.to_path_frame((2.0, 30.0)) == pytest.approx((30.0, 2.0), abs=1e-9)


# --- curved path history behind ------------------------------------------------------------

K_HIST = -0.01  # the HV came out of a left-hand bend (radius 100 m)
HISTORY = tuple(on_arc(K_HIST, -float(i))[:2] for i in range(1, 81))  # most recent first


def test_behind_on_history_polyline() -> None:
    x, y, h = on_arc(K_HIST, -40.0)
    host = HostPath(0.0, 0.0, 0.0, history=HISTORY)  # straight now
    z = classify(host, (x, y), h)
    assert (z.longitudinal, z.lateral, z.direction) == (B, C, ONG)
    assert z.s == pytest.approx(-40.0, abs=1e-3)
    assert z.d == pytest.approx(0.0, abs=2e-3)  # chord sag of 1 m segments is 1.25 mm
    # without the history the straight line back puts it two lanes to the left
    flat = classify(HostPath(0.0, 0.0, 0.0), (x, y), h)
    assert (flat.longitudinal, flat.lateral) == (B, FL)
    # one lane to the right of the history path is Right
    hr = math.radians(h)
    zr = classify(host, (x + W * math.cos(hr), y - W * math.sin(hr)), h)
    assert (zr.longitudinal, zr.lateral) == (B, R)
    assert zr.d == pytest.approx(W, abs=2e-3)
    # and to the left, Left
    zl = classify(host, (x - W * math.cos(hr), y + W * math.sin(hr)), h)
    assert (zl.longitudinal, zl.lateral) == (B, L)


def test_behind_beyond_history_extends_last_segment() -> None:
    x, y, h = on_arc(K_HIST, -80.0)
    hr = math.radians(h)
    rv = (x - 20.0 * math.sin(hr), y - 20.0 * math.cos(hr))  # 20 m further back, straight
    z = classify(HostPath(0.0, 0.0, 0.0, history=HISTORY), rv, h)
    assert (z.longitudinal, z.lateral) == (B, C)
    assert z.s == pytest.approx(-100.0, abs=0.05)


def test_behind_without_history_follows_arc_back() -> None:
    x, y, _ = on_arc(K_HIST, -40.0)
    host = HostPath(0.0, 0.0, 0.0, radius_m=1.0 / K_HIST)
    assert host.to_path_frame((x, y)) == pytest.approx((-40.0, 0.0), abs=1e-9)


def test_history_current_position_duplicate_and_beside() -> None:
    host = HostPath(0.0, 0.0, 0.0, history=((0.0, 0.0), (0.0, -1.0), (0.0, -1.0), (0.0, -5.0)))
    assert host.to_path_frame((1.0, -3.0)) == pytest.approx((-3.0, 1.0))
    # beside the HV, closest history point is the HV itself: tangent-frame coordinates
    host = HostPath(0.0, 0.0, 0.0, history=((1.0, -1.0), (2.0, -2.0)))
    s, d = host.to_path_frame((-3.0, -0.5))
    assert (s, d) == pytest.approx((-0.5, -3.0))


# --- the paper's example -------------------------------------------------------------------


def test_paper_example_behind_then_behind_right() -> None:
    """The paper: 'the local map is showing RV1 as behind, but the CAM is predicting RV1
    will be behind right' (HV northbound; RV1 20 m behind, predicted 15 m behind, one lane
    to the right)."""
    host = HostPath.from_motion(0.0, 0.0, 0.0, 25.0, 0.0)
    now, later = classify_pair(host, (0.0, -20.0), 0.0, (3.6, -15.0), 5.0)
    assert (now.longitudinal, now.lateral, now.direction) == (B, C, ONG)
    assert (later.longitudinal, later.lateral, later.direction) == (B, R, ONG)
    # against the HV's own predicted pose 1 s later (25 m further north)
    later_host = HostPath(0.0, 25.0, 0.0)
    _, later2 = classify_pair(host, (0.0, -20.0), 0.0, (3.6, 10.0), 5.0, predicted_host=later_host)
    assert (later2.longitudinal, later2.lateral) == (B, R)
    assert later2.s == pytest.approx(-15.0)


# --- invariance under rigid motion of the whole scene -------------------------------------

radii = st.one_of(
    st.just(math.inf),
    st.floats(100.0, 2000.0),
    st.floats(-2000.0, -100.0),
)
offsets = st.floats(-50.0, 50.0, allow_nan=False)
headings = st.floats(0.0, 360.0, exclude_max=True)


def _rotate(
    p: tuple[float, float], theta_deg: float, t: tuple[float, float]
) -> tuple[float, float]:
    """Rotate clockwise by theta (so headings gain theta) about the origin, then translate."""
    th = math.radians(theta_deg)
    c, s = math.cos(th), math.sin(th)
    return p[0] * c + p[1] * s + t[0], -p[0] * s + p[1] * c + t[1]


@settings(max_examples=300, deadline=None)
@given(
    hv=st.tuples(offsets, offsets),
    hv_heading=headings,
    radius=radii,
    hist_k=st.one_of(st.none(), st.floats(-0.01, 0.01)),
    rv=st.tuples(offsets, offsets),
    rv_heading=headings,
    theta=st.floats(-720.0, 720.0),
    shift=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
)
def test_rigid_motion_invariance(
    hv: tuple[float, float],
    hv_heading: float,
    radius: float,
    hist_k: float | None,
    rv: tuple[float, float],
    rv_heading: float,
    theta: float,
    shift: tuple[float, float],
) -> None:
    history: tuple[tuple[float, float], ...] = ()
    if hist_k is not None:
        # a history arc ending at the HV, rotated to its heading, every 2 m for 80 m
        pts = [on_arc(hist_k, -2.0 * i)[:2] for i in range(1, 41)]
        history = tuple(_rotate(p, hv_heading, hv) for p in pts)
    host = HostPath(hv[0], hv[1], hv_heading, radius, history)
    z = classify(host, rv, rv_heading)

    # stay off the class boundaries, where rounding may legitimately flip a class
    u, _ = relative_position(hv, hv_heading, rv)
    assume(abs(u) > 1e-6 and abs(z.s) > 1e-6)
    assume(all(abs(abs(z.d) - b) > 1e-6 for b in (0.5 * W, 1.5 * W)))
    assume(all(abs(z.heading_diff_deg - b) > 1e-6 for b in (45.0, 135.0)))

    moved = HostPath(
        *_rotate(hv, theta, shift),
        hv_heading + theta,
        radius,
        tuple(_rotate(p, theta, shift) for p in history),
    )
    zm = classify(moved, _rotate(rv, theta, shift), rv_heading + theta)
    assert (zm.longitudinal, zm.lateral, zm.direction) == (z.longitudinal, z.lateral, z.direction)
    assert zm.s == pytest.approx(z.s, abs=1e-6)
    assert zm.d == pytest.approx(z.d, abs=1e-6)


# --- the vectorised path equals the scalar one --------------------------------------------


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), radius=st.sampled_from([math.inf, 80.0, -150.0, 900.0]),
       with_history=st.booleans())
def test_classify_many_equals_classify(seed: int, radius: float, with_history: bool) -> None:
    rng = np.random.default_rng(seed)
    history: list[tuple[float, float]] = []
    if with_history:  # a wiggly path behind an HV at (5, 7) heading 30 deg
        pts = np.cumsum(rng.normal([-0.5, -0.85], 0.3, size=(12, 2)) * 8.0, axis=0)
        history = [(5.0 + px, 7.0 + py) for px, py in pts]
    host = HostPath(5.0, 7.0, 30.0, radius, tuple(history))
    xs = rng.uniform(-120, 120, 300)
    ys = rng.uniform(-120, 120, 300)
    heads = rng.uniform(0, 360, 300)
    many = classify_many(host, xs, ys, heads, CFG)
    for i in range(len(xs)):
        z = classify(host, (xs[i], ys[i]), heads[i], CFG)
        got = many.zone(i)
        assert (got.longitudinal, got.lateral, got.direction) == \
            (z.longitudinal, z.lateral, z.direction), i
        assert got.s == pytest.approx(z.s, abs=1e-9)
        assert got.d == pytest.approx(z.d, abs=1e-9)
        assert got.heading_diff_deg == pytest.approx(z.heading_diff_deg, abs=1e-9)


def test_classify_many_on_exact_lane_boundaries() -> None:
    host = HostPath(0.0, 0.0, 0.0)
    ds = np.array([-1.5 * W, -0.5 * W, 0.0, 0.5 * W, 1.5 * W, 1.5 * W + 1e-9])
    many = classify_many(host, ds, np.full(len(ds), 10.0), np.zeros(len(ds)), CFG)
    for i, d in enumerate(ds):
        assert many.zone(i).lateral == paper_lateral(-d)


# --- lane estimation from an RV's trail ------------------------------------------------------


def test_trail_offset_straight_and_curved() -> None:
    # An RV at (0, 50) heading north, trail straight back to (0, -100).
    trail = [(0.0, 50.0), (0.0, 0.0), (0.0, -100.0)]
    s, d, h = trail_offset(trail, (1.0, 10.0))
    assert (s, d, h) == pytest.approx((40.0, 1.0, 0.0))  # 1 m right of it, 40 m behind
    assert trail_offset(trail, (0.0, 60.0)) is None  # ahead of the RV
    assert trail_offset(trail, (0.0, -120.0)) is None  # the trail does not reach back
    assert trail_offset([(0.0, 0.0)], (1.0, 1.0)) is None
    # a quarter circle of radius 100 (RV going east at (100, 100) after turning right);
    # a point at radius 96 on it is 4 m to the right of the trail.
    arc = [(100 - 100 * math.cos(a), 100 * math.sin(a)) for a in np.linspace(math.pi / 2, 0, 91)]
    a = math.radians(30.0)
    s, d, h = trail_offset(arc, (100 - 96 * math.cos(a), 96 * math.sin(a)))
    assert d == pytest.approx(4.0, abs=0.01)
    assert h == pytest.approx(30.0, abs=0.6)  # tangent at 30 deg round the turn
    assert s == pytest.approx(100 * math.radians(60.0), abs=0.05)
