"""Tests for catc.geo: WGS-84 geodetic/ECEF/ENU conversions and heading helpers.

Position errors are measured in metres: the horizontal part as the WGS-84
geodesic distance (pyproj.Geod, independent of the PROJ transformers under
test) and the vertical part as the height difference.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyproj import Geod, Transformer

from catc.geo import (
    EnuFrame,
    bearing_deg,
    distance_m,
    ecef_to_geodetic,
    enu_heading_deg,
    enu_yaw_rad_to_heading,
    geodetic_to_ecef,
    heading_diff_deg,
    heading_to_enu_yaw_rad,
    unwrap_heading_rad,
    wrap_deg_180,
    wrap_deg_360,
)

GEOD = Geod(ellps="WGS84")
MM = 1e-3

lats = st.floats(-89.9, 89.9, allow_nan=False)
lons = st.floats(-180.0, 180.0, allow_nan=False)
heights = st.floats(-500.0, 9000.0, allow_nan=False)
angles = st.floats(-1e4, 1e4, allow_nan=False)
# Within 50 km of a frame's reference point.
offsets = st.floats(-50_000.0, 50_000.0, allow_nan=False)
ranges = st.floats(0.0, 50_000.0, allow_nan=False)
azimuths = st.floats(-180.0, 180.0, allow_nan=False)

fast = settings(deadline=None, max_examples=200)


def position_error_m(lat1, lon1, h1, lat2, lon2, h2) -> float:
    """3-D distance in metres between two nearby geodetic points (float or array)."""
    _, _, horizontal = GEOD.inv(lon1, lat1, lon2, lat2)
    return np.hypot(horizontal, np.subtract(h2, h1))


# --- geodetic <-> ECEF -----------------------------------------------------------------------


@fast
@given(lats, lons, heights)
def test_geodetic_ecef_round_trip_within_1_mm(lat, lon, h):
    lat2, lon2, h2 = ecef_to_geodetic(*geodetic_to_ecef(lat, lon, h))
    assert position_error_m(lat, lon, h, lat2, lon2, h2) < MM


@fast
@given(lats, lons, heights)
def test_ecef_radius_is_consistent_with_the_ellipsoid(lat, lon, h):
    # Independent closed form: r = ((N + h) cos(lat) (cos lon, sin lon), (N (1 - e2) + h) sin lat)
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    phi, lam = math.radians(lat), math.radians(lon)
    n = a / math.sqrt(1 - e2 * math.sin(phi) ** 2)
    expected = (
        (n + h) * math.cos(phi) * math.cos(lam),
        (n + h) * math.cos(phi) * math.sin(lam),
        (n * (1 - e2) + h) * math.sin(phi),
    )
    assert np.allclose(geodetic_to_ecef(lat, lon, h), expected, rtol=0, atol=MM)


def test_known_ecef_values():
    assert geodetic_to_ecef(0.0, 0.0, 0.0) == pytest.approx((6378137.0, 0.0, 0.0), abs=MM)
    assert geodetic_to_ecef(0.0, 90.0, 0.0) == pytest.approx((0.0, 6378137.0, 0.0), abs=MM)
    assert geodetic_to_ecef(90.0, 0.0, 0.0) == pytest.approx((0.0, 0.0, 6356752.314245), abs=MM)
    assert geodetic_to_ecef(-90.0, 0.0, 100.0) == pytest.approx((0.0, 0.0, -6356852.314245), abs=MM)
    lat, lon, h = ecef_to_geodetic(6378137.0 + 10.0, 0.0, 0.0)
    assert (lat, lon, h) == pytest.approx((0.0, 0.0, 10.0), abs=1e-9)


# --- ENU -------------------------------------------------------------------------------------


@fast
@given(lats, lons, heights, azimuths, ranges, heights)
def test_geodetic_enu_round_trip_within_1_mm(lat0, lon0, h0, az, dist, h):
    frame = EnuFrame(lat0, lon0, h0)
    lon, lat, _ = GEOD.fwd(lon0, lat0, az, dist)
    lat2, lon2, h2 = frame.to_geodetic(*frame.to_enu(lat, lon, h))
    assert position_error_m(lat, lon, h, lat2, lon2, h2) < MM


@fast
@given(lats, lons, heights, offsets, offsets, heights)
def test_enu_geodetic_round_trip_within_1_mm(lat0, lon0, h0, e, n, u):
    frame = EnuFrame(lat0, lon0, h0)
    e2, n2, u2 = frame.to_enu(*frame.to_geodetic(e, n, u))
    assert math.dist((e, n, u), (e2, n2, u2)) < MM


@settings(deadline=None, max_examples=25)
@given(lats, lons, heights, offsets, offsets, heights)
def test_enu_matches_proj_topocentric(lat0, lon0, h0, e, n, u):
    # PROJ's own topocentric conversion is an independent implementation of the same frame.
    topo = Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad"
        " +step +proj=cart +ellps=WGS84"
        f" +step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0={h0!r}"
    )
    frame = EnuFrame(lat0, lon0, h0)
    lat, lon, h = frame.to_geodetic(e, n, u)
    assert math.dist(frame.to_enu(lat, lon, h), topo.transform(lon, lat, h)) < MM


@pytest.mark.parametrize("h0", [0.0, 200.0])
def test_enu_of_a_point_north_of_the_reference(h0):
    lat0, lon0 = 42.3, -83.7
    frame = EnuFrame(lat0, lon0, h0)
    e, n, u = frame.to_enu(lat0 + 0.001, lon0, h0)
    _, _, geodesic = GEOD.inv(lon0, lat0, lon0, lat0 + 0.001)
    # The geodesic runs on the ellipsoid; at height h0 the meridian arc is longer by
    # (M + h0) / M, M the meridian radius of curvature (3.5 mm over 111 m at 200 m).
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    m = a * (1 - e2) / (1 - e2 * math.sin(math.radians(lat0 + 0.0005)) ** 2) ** 1.5
    assert abs(e) < 1e-6
    assert n == pytest.approx(111.0, abs=0.5)
    assert n == pytest.approx(geodesic * (m + h0) / m, abs=MM)
    # Same ellipsoidal height, so the ellipsoid curves below the tangent plane.
    assert -2 * MM < u < 0


def test_enu_axes_point_east_north_up():
    frame = EnuFrame(48.0, 11.0, 500.0)
    assert frame.to_enu(48.0, 11.0, 500.0) == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
    assert frame.to_enu(48.0, 11.0, 510.0) == pytest.approx((0.0, 0.0, 10.0), abs=1e-6)
    e, n, _ = frame.to_enu(48.0, 11.001, 500.0)
    assert e > 70.0
    assert abs(n) < 0.01
    e, n, _ = frame.to_enu(47.999, 11.0, 500.0)
    assert n < -100.0
    assert abs(e) < 1e-6
    _, _, h = frame.to_geodetic(0.0, 0.0, 25.0)
    assert h == pytest.approx(525.0, abs=1e-6)


def test_enu_frame_is_immutable_and_validated():
    frame = EnuFrame(10.0, 20.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        frame.lat0 = 11.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        frame.rotation[0, 0] = 1.0
    with pytest.raises(ValueError):
        frame.r0[0] = 1.0
    assert np.allclose(frame.rotation @ frame.rotation.T, np.eye(3), atol=1e-15)
    assert frame == EnuFrame(10, 20, 0)
    assert hash(frame) == hash(EnuFrame(10, 20, 0))
    for bad in [(90.5, 0.0, 0.0), (math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (0.0, 0.0, math.nan)]:
        with pytest.raises(ValueError):
            EnuFrame(*bad)


# --- vectorisation ---------------------------------------------------------------------------


def test_vectorised_calls_match_scalar_calls():
    rng = np.random.default_rng(2735)
    size = 100_000
    lat = rng.uniform(-89.9, 89.9, size)
    lon = rng.uniform(-180.0, 180.0, size)
    h = rng.uniform(-500.0, 9000.0, size)
    frame = EnuFrame(37.4, -122.1, 10.0)
    local_lat = frame.lat0 + rng.uniform(-0.4, 0.4, size)
    local_lon = frame.lon0 + rng.uniform(-0.4, 0.4, size)

    x, y, z = geodetic_to_ecef(lat, lon, h)
    lat2, lon2, h2 = ecef_to_geodetic(x, y, z)
    e, n, u = frame.to_enu(local_lat, local_lon, h)
    lat3, lon3, h3 = frame.to_geodetic(e, n, u)
    bearing = bearing_deg(lat[0], lon[0], lat, lon)
    dist = distance_m(lat[0], lon[0], lat, lon)
    heading = enu_heading_deg(e, n)
    for out in (x, y, z, lat2, lon2, h2, e, n, u, lat3, lon3, h3, bearing, dist, heading):
        assert isinstance(out, np.ndarray)
        assert out.shape == (size,)
    assert np.max(position_error_m(lat, lon, h, lat2, lon2, h2)) < MM
    assert np.max(position_error_m(local_lat, local_lon, h, lat3, lon3, h3)) < MM

    for i in rng.choice(size, 200, replace=False):
        scalar = geodetic_to_ecef(float(lat[i]), float(lon[i]), float(h[i]))
        assert all(type(v) is float for v in scalar)
        assert scalar == (x[i], y[i], z[i])
        assert ecef_to_geodetic(x[i], y[i], z[i]) == (lat2[i], lon2[i], h2[i])
        assert frame.to_enu(local_lat[i], local_lon[i], h[i]) == (e[i], n[i], u[i])
        assert frame.to_geodetic(e[i], n[i], u[i]) == (lat3[i], lon3[i], h3[i])
        assert bearing_deg(lat[0], lon[0], lat[i], lon[i]) == bearing[i]
        assert distance_m(lat[0], lon[0], lat[i], lon[i]) == dist[i]
        assert enu_heading_deg(e[i], n[i]) == heading[i]


def test_vectorised_calls_broadcast_and_keep_shape():
    lat = np.array([[10.0, 20.0, 30.0], [-10.0, -20.0, -30.0]])
    x, y, z = geodetic_to_ecef(lat, 5.0, 0.0)
    assert x.shape == y.shape == z.shape == (2, 3)
    assert x[1, 2] == geodetic_to_ecef(-30.0, 5.0, 0.0)[0]
    e, n, u = EnuFrame(0.0, 0.0).to_enu([0.0, 0.001], 0.0)
    assert e.shape == n.shape == u.shape == (2,)
    lat2, lon2, h2 = EnuFrame(0.0, 0.0).to_geodetic([0.0, 10.0], 0.0)
    assert lat2.shape == lon2.shape == h2.shape == (2,)
    assert wrap_deg_360([-90.0, 450.0]).tolist() == [270.0, 90.0]
    assert heading_diff_deg([10.0, 350.0], 0.0).tolist() == [10.0, -10.0]
    assert type(wrap_deg_360(np.float64(-90.0))) is float


# --- headings and bearings -------------------------------------------------------------------


def test_heading_diff_across_north():
    assert heading_diff_deg(359.9, 0.1) == pytest.approx(-0.2, abs=1e-9)
    assert heading_diff_deg(0.1, 359.9) == pytest.approx(0.2, abs=1e-9)
    assert heading_diff_deg(-0.1, 0.1) == pytest.approx(-0.2, abs=1e-9)
    assert heading_diff_deg(720.1, -0.1) == pytest.approx(0.2, abs=1e-9)


def test_half_turn_convention_is_minus_180():
    # [-180, 180): +180 is represented as -180, whichever way round.
    assert wrap_deg_180(180.0) == -180.0
    assert wrap_deg_180(-180.0) == -180.0
    assert wrap_deg_180(540.0) == -180.0
    assert heading_diff_deg(180.0, 0.0) == -180.0
    assert heading_diff_deg(0.0, 180.0) == -180.0
    assert heading_diff_deg(270.0, 90.0) == -180.0
    assert wrap_deg_180(179.9) == pytest.approx(179.9)
    assert wrap_deg_180(-179.9) == pytest.approx(-179.9)


def test_wrap_360_edges():
    assert wrap_deg_360(360.0) == 0.0
    assert wrap_deg_360(0.0) == 0.0
    assert wrap_deg_360(-360.0) == 0.0
    assert wrap_deg_360(-0.1) == pytest.approx(359.9)
    assert wrap_deg_360(359.9) == 359.9
    # np.mod(-1e-20, 360) is 360.0 in floating point; the range must stay half-open.
    assert wrap_deg_360(-1e-20) == 0.0
    assert wrap_deg_180(180.0 - 1e-14) < 180.0


@given(angles)
def test_wrap_ranges_and_congruence(a):
    w360, w180 = wrap_deg_360(a), wrap_deg_180(a)
    assert 0.0 <= w360 < 360.0
    assert -180.0 <= w180 < 180.0
    for w in (w360, w180):
        turns = (a - w) / 360.0
        assert turns == pytest.approx(round(turns), abs=1e-9)


@given(angles, angles)
def test_heading_diff_is_the_smallest_signed_rotation(a, b):
    d = heading_diff_deg(a, b)
    assert -180.0 <= d < 180.0
    # Rotating b by d lands on a.
    assert abs(wrap_deg_180(b + d - a)) < 1e-9


def test_yaw_heading_known_values():
    assert heading_to_enu_yaw_rad(0.0) == pytest.approx(math.pi / 2)
    assert heading_to_enu_yaw_rad(90.0) == pytest.approx(0.0)
    assert heading_to_enu_yaw_rad(180.0) == pytest.approx(-math.pi / 2)
    assert heading_to_enu_yaw_rad(270.0) == pytest.approx(-math.pi)
    assert enu_yaw_rad_to_heading(math.pi / 2) == pytest.approx(0.0)
    assert enu_yaw_rad_to_heading(0.0) == pytest.approx(90.0)
    assert enu_yaw_rad_to_heading(math.pi) == pytest.approx(270.0)
    assert enu_yaw_rad_to_heading(-math.pi / 2) == pytest.approx(180.0)


@given(angles)
def test_yaw_heading_round_trips(a):
    yaw = heading_to_enu_yaw_rad(a)
    assert -math.pi <= yaw < math.pi
    assert abs(heading_diff_deg(enu_yaw_rad_to_heading(yaw), a)) < 1e-9
    yaw_rad = math.radians(a)
    back = heading_to_enu_yaw_rad(enu_yaw_rad_to_heading(yaw_rad))
    assert abs(math.remainder(back - yaw_rad, 2 * math.pi)) < 1e-9


def test_yaw_and_enu_heading_agree():
    for yaw in np.linspace(-math.pi, math.pi, 37):
        heading = enu_heading_deg(math.cos(yaw), math.sin(yaw))
        assert abs(heading_diff_deg(heading, enu_yaw_rad_to_heading(yaw))) < 1e-9


def test_enu_heading_compass_points():
    assert enu_heading_deg(0.0, 1.0) == 0.0
    assert enu_heading_deg(1.0, 0.0) == 90.0
    assert enu_heading_deg(0.0, -1.0) == 180.0
    assert enu_heading_deg(-1.0, 0.0) == 270.0
    assert enu_heading_deg(1.0, 1.0) == pytest.approx(45.0)
    assert enu_heading_deg(-1e-300, 1.0) == 0.0  # a hair west of north is not 360
    assert enu_heading_deg(0.0, 0.0) == 0.0


def test_bearing_and_distance_known_values():
    assert bearing_deg(0.0, 0.0, 1.0, 0.0) == pytest.approx(0.0, abs=1e-9)
    assert bearing_deg(0.0, 0.0, 0.0, 1.0) == pytest.approx(90.0, abs=1e-9)
    assert bearing_deg(0.0, 0.0, -1.0, 0.0) == pytest.approx(180.0, abs=1e-9)
    assert bearing_deg(0.0, 0.0, 0.0, -1.0) == pytest.approx(270.0, abs=1e-9)
    assert bearing_deg(45.0, 10.0, 45.0, 10.0) == 0.0  # coincident: 0 by convention
    # One degree of latitude at the equator on WGS-84.
    assert distance_m(0.0, 0.0, 1.0, 0.0) == pytest.approx(110574.389, abs=MM)
    assert distance_m(0.0, 0.0, 0.0, 1.0) == pytest.approx(111319.491, abs=MM)
    assert distance_m(45.0, 10.0, 45.0, 10.0) == 0.0


@fast
@given(lats, lons, azimuths, st.floats(1.0, 200.0))
def test_short_bearing_matches_enu_heading(lat0, lon0, az, dist):
    # Over a short hop the geodesic azimuth and the ENU displacement heading coincide.
    lon, lat, _ = GEOD.fwd(lon0, lat0, az, dist)
    e, n, _ = EnuFrame(lat0, lon0).to_enu(lat, lon)
    bearing = bearing_deg(lat0, lon0, lat, lon)
    assert 0.0 <= bearing < 360.0
    assert abs(heading_diff_deg(bearing, az)) < 1e-6
    assert abs(heading_diff_deg(enu_heading_deg(e, n), bearing)) < 0.01
    assert distance_m(lat0, lon0, lat, lon) == pytest.approx(dist, abs=MM)


def test_unwrap_heading_across_north():
    out = unwrap_heading_rad([350.0, 355.0, 0.0, 5.0])
    assert isinstance(out, np.ndarray)
    assert np.all(np.diff(out) > 0)
    assert out == pytest.approx(np.radians([350.0, 355.0, 360.0, 365.0]))
    down = unwrap_heading_rad([5.0, 0.0, 355.0, 350.0])
    assert np.all(np.diff(down) < 0)
    assert down == pytest.approx(np.radians([5.0, 0.0, -5.0, -10.0]))
    # Wrapping back gives the inputs.
    assert wrap_deg_360(np.degrees(out)) == pytest.approx([350.0, 355.0, 0.0, 5.0])
