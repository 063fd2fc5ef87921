"""Tests for catc.apps.fcw (CAMP Linear FCW, paper equations (FCW-1)/(FCW-2)).

Expected values are computed by hand in the comments.  Unless said otherwise the
config is C = FcwConfig(t_d=1.0, a_req=-5.0) so the arithmetic stays exact:

    (FCW-1)  r_w = BOR + (v_HV - v_RV) t_d + 1/2 (a_HV - a_RV) t_d^2
    (FCW-2)  case 1: BOR = v_HVp^2 / (-2 a_req)
             case 2: BOR = (v_HVp - v_RVp)^2 / (-2 (a_req - a_RV))
             case 3: BOR = v_HVp^2 / (-2 a_req) - v_RVp^2 / (-2 a_RV)
    v_HVp = max(0, v_HV + a_HV t_d),  v_RVp = max(0, v_RV + a_RV t_d)
"""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from catc.apps.events import AppEvent, WarningMonitor
from catc.apps.fcw import (
    FcwConfig,
    FcwRange,
    required_deceleration,
    should_warn,
    warning_range,
)

C = FcwConfig(t_d=1.0, a_req=-5.0)
TOL = 1e-9


# --------------------------------------------------------------------------- cases


def test_case1_rv_stationary() -> None:
    # HV 25 m/s constant, RV stopped.
    # v_HVp = 25 + 0*1 = 25;  v_RVp = 0
    # BOR = 25^2 / (-2 * -5) = 625 / 10 = 62.5
    # delay = (25 - 0)*1 + 1/2 (0 - 0)*1 = 25
    # r_w = 62.5 + 25 = 87.5
    r = warning_range(25.0, 0.0, 0.0, 0.0, C)
    assert r.case == 1
    assert r.v_hvp == pytest.approx(25.0, abs=TOL)
    assert r.v_rvp == 0.0
    assert r.bor == pytest.approx(62.5, abs=TOL)
    assert r.delay_term == pytest.approx(25.0, abs=TOL)
    assert r.r_w == pytest.approx(87.5, abs=TOL)
    assert r.closing and r.active


def test_default_config_is_camp_required_deceleration_model() -> None:
    # Defaults: t_d = 2.05 s, a_req from the CAMP RDM (ft/s^2 coefficients x 0.3048).
    # HV 25 m/s constant, RV stopped: v_HVp = 25, v_RVp = 0, closing 25, RV not moving:
    #   a_req = -5.308*0.3048 - 0.086*25 = -1.6178784 - 2.15 = -3.7678784
    #   BOR (case 1) = 625 / (2 * 3.7678784) = 82.93792...
    #   delay = 25 * 2.05 = 51.25 ;  r_w = 134.18792...
    cfg = FcwConfig()
    assert cfg.t_d == 2.05 and cfg.a_req is None
    r = warning_range(25.0, 0.0, 0.0, 0.0)
    assert r.case == 1
    assert r.a_req == pytest.approx(-3.7678784, abs=TOL)
    assert r.bor == pytest.approx(625.0 / 7.5357568, abs=TOL)
    assert r.r_w == pytest.approx(134.18792, abs=1e-5)


def test_camp_rdm_moving_lead_case2() -> None:
    # HV 25, RV 15 m/s, both constant, default config.  closing = 10, RV moving:
    #   a_req = -1.6178784 + 2.570*0.3048 - 0.086*10 = -1.6178784 + 0.783336 - 0.86
    #         = -1.6945424
    #   BOR (case 2) = 10^2 / (-2 (a_req - 0)) = 100 / 3.3890848 = 29.50649...
    #   delay = 10 * 2.05 = 20.5 ;  r_w = 50.00649...
    r = warning_range(25.0, 0.0, 15.0, 0.0)
    assert r.case == 2
    assert r.a_req == pytest.approx(-1.6945424, abs=TOL)
    assert r.bor == pytest.approx(100.0 / 3.3890848, abs=TOL)
    assert r.r_w == pytest.approx(50.00649, abs=1e-5)


def test_camp_rdm_braking_lead_case3() -> None:
    # HV 25 m/s constant, RV 20 m/s braking at -3 m/s^2, default config.
    #   v_RVp = 20 - 3*2.05 = 13.85 ; closing = 25 - 13.85 = 11.15
    #   a_req = -1.6178784 + 0.685*(-3) + 0.783336 - 0.086*11.15 = -3.8484424
    #   RV stops first: 13.85/3 = 4.62 s < 25/3.8484424 = 6.50 s -> case 3
    #   BOR = 625/(2*3.8484424) - 13.85^2/(2*3) = 81.20160... - 31.97042 = 49.23118...
    #   delay = 5*2.05 + 1/2 (0 + 3) 2.05^2 = 10.25 + 6.30375 = 16.55375
    r = warning_range(25.0, 0.0, 20.0, -3.0)
    assert r.case == 3
    assert r.a_req == pytest.approx(-3.8484424, abs=TOL)
    want_bor = 625.0 / (2 * 3.8484424) - 13.85**2 / 6.0
    assert r.bor == pytest.approx(want_bor, abs=TOL)
    assert r.r_w == pytest.approx(want_bor + 16.55375, abs=TOL)


@pytest.mark.parametrize(("v_rv", "a_rv", "closing"),
                         [(0.0, 5.0, -30.0), (10.0, 3.0, -20.0), (30.0, 0.0, 0.0)])
def test_camp_rdm_stays_braking_outside_its_domain(v_rv, a_rv, closing) -> None:
    # An accelerating lead or an opening gap is outside the fitted domain: clamped to the
    # model's value at a_RV = 0 and closing 0, which is still braking.
    a = required_deceleration(v_rv, a_rv, closing)
    assert a == pytest.approx(-1.6178784 + (0.783336 if v_rv > 0 else 0.0), abs=TOL)
    assert a < -0.8


def test_case2_rv_constant_speed() -> None:
    # HV 25 m/s, RV 15 m/s, both constant.  a_RV = 0: the RV never stops -> case 2.
    # v_HVp = 25, v_RVp = 15
    # BOR = (25 - 15)^2 / (-2 (-5 - 0)) = 100 / 10 = 10
    # delay = (25 - 15)*1 + 1/2 (0 - 0) = 10
    # r_w = 20
    r = warning_range(25.0, 0.0, 15.0, 0.0, C)
    assert r.case == 2
    assert (r.v_hvp, r.v_rvp) == (25.0, 15.0)
    assert r.bor == pytest.approx(10.0, abs=TOL)
    assert r.r_w == pytest.approx(20.0, abs=TOL)


def test_case2_rv_braking_but_outlasting_hv() -> None:
    # HV 20 constant; RV 12 braking at -2.
    # v_HVp = 20; v_RVp = 12 - 2*1 = 10
    # stop times after brake onset: RV 10/2 = 5 s, HV 20/5 = 4 s -> HV stops first -> case 2
    # BOR = (20 - 10)^2 / (-2 (-5 - (-2))) = 100 / 6 = 16.666...
    # delay = (20 - 12)*1 + 1/2 (0 - (-2))*1 = 8 + 1 = 9
    # r_w = 100/6 + 9 = 25.666...
    r = warning_range(20.0, 0.0, 12.0, -2.0, C)
    assert r.case == 2
    assert r.v_rvp == pytest.approx(10.0, abs=TOL)
    assert r.bor == pytest.approx(100.0 / 6.0, abs=TOL)
    assert r.delay_term == pytest.approx(9.0, abs=TOL)
    assert r.r_w == pytest.approx(100.0 / 6.0 + 9.0, abs=TOL)


def test_case3_rv_stops_before_hv() -> None:
    # HV 25 constant; RV 15 braking at -4.
    # v_HVp = 25; v_RVp = 15 - 4*1 = 11
    # stop times: RV 11/4 = 2.75 s < HV 25/5 = 5 s -> RV stops first -> case 3
    # BOR = 25^2/(-2*-5) - 11^2/(-2*-4) = 625/10 - 121/8 = 62.5 - 15.125 = 47.375
    # delay = (25 - 15)*1 + 1/2 (0 - (-4))*1 = 10 + 2 = 12
    # r_w = 47.375 + 12 = 59.375
    r = warning_range(25.0, 0.0, 15.0, -4.0, C)
    assert r.case == 3
    assert r.v_rvp == pytest.approx(11.0, abs=TOL)
    assert r.bor == pytest.approx(47.375, abs=TOL)
    assert r.delay_term == pytest.approx(12.0, abs=TOL)
    assert r.r_w == pytest.approx(59.375, abs=TOL)


def test_hv_acceleration_enters_predicted_speed_and_delay_term() -> None:
    # HV 25 braking -2, RV stopped: v_HVp = 25 - 2*1 = 23
    # BOR = 23^2/10 = 52.9 ; delay = 25*1 + 1/2 (-2 - 0)*1 = 24 ; r_w = 76.9
    r = warning_range(25.0, -2.0, 0.0, 0.0, C)
    assert r.case == 1
    assert r.v_hvp == pytest.approx(23.0, abs=TOL)
    assert r.bor == pytest.approx(52.9, abs=TOL)
    assert r.r_w == pytest.approx(76.9, abs=TOL)


# ----------------------------------------------------------------- case boundaries


def test_case2_case3_boundary_is_case2_and_continuous() -> None:
    # HV 20 constant; RV 12.5 braking at -2.5: v_RVp = 12.5 - 2.5 = 10.
    # Stop times: RV 10/2.5 = 4 s, HV 20/5 = 4 s -> tie (v_RVp*a_req = -50 = v_HVp*a_RV).
    # Tie -> case 2: BOR = (20-10)^2 / (-2(-5+2.5)) = 100/5 = 20
    # case-3 formula there: 400/10 - 100/5 = 40 - 20 = 20 (same: continuous boundary)
    # delay = (20 - 12.5) + 1/2 (0 + 2.5) = 7.5 + 1.25 = 8.75 ; r_w = 28.75
    r = warning_range(20.0, 0.0, 12.5, -2.5, C)
    assert r.case == 2
    assert r.bor == pytest.approx(20.0, abs=TOL)
    assert r.r_w == pytest.approx(28.75, abs=TOL)
    case3_formula = 20.0**2 / 10.0 - 10.0**2 / 5.0
    assert case3_formula == pytest.approx(r.bor, abs=TOL)

    # One ulp faster HV: HV stops later than the RV -> case 3, same BOR to 1e-9.
    up = warning_range(math.nextafter(20.0, math.inf), 0.0, 12.5, -2.5, C)
    assert up.case == 3
    assert up.bor == pytest.approx(20.0, abs=TOL)
    # One ulp slower HV: HV stops first -> case 2.
    down = warning_range(math.nextafter(20.0, 0.0), 0.0, 12.5, -2.5, C)
    assert down.case == 2
    assert down.bor == pytest.approx(20.0, abs=TOL)


def test_case1_case2_boundary_on_rv_speed() -> None:
    # v_RV = 0 -> case 1; tiny v_RV > 0 with a_RV = 0 -> case 2 with nearly the same BOR
    # (case 2 at v_RVp = 0 is 25^2/10 = 62.5 = case 1).
    tiny = 1e-12
    assert warning_range(25.0, 0.0, 0.0, 0.0, C).case == 1
    r = warning_range(25.0, 0.0, tiny, 0.0, C)
    assert r.case == 2
    assert r.bor == pytest.approx(62.5, abs=1e-9)
    # A configured stationary threshold moves the boundary: v_RV <= 0.1 -> case 1.
    cfg = dataclasses.replace(C, rv_stationary_speed=0.1)
    assert warning_range(25.0, 0.0, 0.1, 0.0, cfg).case == 1
    assert warning_range(25.0, 0.0, 0.11, 0.0, cfg).case == 2


# -------------------------------------------------------------------- edge cases


def test_predicted_speeds_clamped_at_zero() -> None:
    # HV 25 constant; RV 3 braking at -5: 3 - 5*1 = -2 -> v_RVp = 0 (stopped within t_d).
    # a_RV < 0 and v_RVp*a_req = 0 > v_HVp*a_RV = -125 -> case 3
    # BOR = 625/10 - 0^2/10 = 62.5
    # delay (as printed, not clamped) = (25-3)*1 + 1/2 (0+5)*1 = 22 + 2.5 = 24.5
    # r_w = 87.0
    r = warning_range(25.0, 0.0, 3.0, -5.0, C)
    assert r.v_rvp == 0.0
    assert r.case == 3
    assert r.bor == pytest.approx(62.5, abs=TOL)
    assert r.r_w == pytest.approx(87.0, abs=TOL)

    # HV 3 braking at -5: 3 - 5 = -2 -> v_HVp = 0; RV stopped: BOR = 0
    # delay = 3*1 + 1/2 (-5 - 0) = 0.5 -> r_w = 0.5
    h = warning_range(3.0, -5.0, 0.0, 0.0, C)
    assert h.v_hvp == 0.0
    assert h.bor == 0.0
    assert h.r_w == pytest.approx(0.5, abs=TOL)


def test_not_closing_gives_no_warning() -> None:
    # HV 15, RV 25, both constant -> case 2, v_HVp = 15 < v_RVp = 25.
    # printed BOR = (15-25)^2/10 = 10 (the square hides the sign) -> used BOR = 0
    # delay = (15 - 25)*1 = -10 -> r_w = -10 <= 0: never warns.
    r = warning_range(15.0, 0.0, 25.0, 0.0, C)
    assert r.case == 2
    assert not r.closing
    assert r.bor_printed == pytest.approx(10.0, abs=TOL)
    assert r.bor == 0.0
    assert r.r_w == pytest.approx(-10.0, abs=TOL)
    for rng in (0.0, 0.1, 5.0, 100.0):
        assert not should_warn(rng, r)


def test_case3_negative_printed_bor_is_clamped() -> None:
    # t_d = 0: HV 10, RV 30 braking at -20.  Stop times RV 30/20 = 1.5 s < HV 10/5 = 2 s
    # -> case 3: printed BOR = 100/10 - 900/40 = 10 - 22.5 = -12.5 -> BOR = 0; r_w = 0.
    cfg = FcwConfig(t_d=0.0, a_req=-5.0)
    r = warning_range(10.0, 0.0, 30.0, -20.0, cfg)
    assert r.case == 3
    assert r.bor_printed == pytest.approx(-12.5, abs=TOL)
    assert r.bor == 0.0
    assert r.r_w == 0.0
    assert not should_warn(0.0, r)


def test_stationary_hv_is_inactive() -> None:
    # HV and RV stopped: everything 0, r_w = 0, inactive.
    r = warning_range(0.0, 0.0, 0.0, 0.0, C)
    assert (r.r_w, r.bor, r.active) == (0.0, 0.0, False)
    assert not should_warn(0.0, r)
    # HV stopped but pulling away at +2 toward a stopped RV:
    # v_HVp = 2, BOR = 4/10 = 0.4, delay = 0 + 1/2 * 2 = 1, r_w = 1.4 -- but inactive.
    c = warning_range(0.0, 2.0, 0.0, 0.0, C)
    assert c.r_w == pytest.approx(1.4, abs=TOL)
    assert not c.active
    assert not should_warn(1.0, c)
    # The same kinematics at v_HV just above min_hv_speed would warn.
    m = warning_range(0.001, 2.0, 0.0, 0.0, C)
    assert m.active and should_warn(1.0, m)


def test_should_warn_thresholds() -> None:
    r = warning_range(25.0, 0.0, 0.0, 0.0, C)  # r_w = 87.5
    assert should_warn(0.0, r)
    assert should_warn(87.4, r)
    assert not should_warn(87.5, r)  # "less than": equality does not warn
    assert not should_warn(100.0, r)
    assert not should_warn(-1.0, r)
    assert not should_warn(math.nan, r)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"a_req": 0.0},
        {"a_req": 1.0},
        {"a_req": math.nan},
        {"t_d": -0.1},
        {"t_d": math.inf},
        {"rv_stationary_speed": -1.0},
        {"min_hv_speed": -1.0},
    ],
)
def test_invalid_config_raises(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        FcwConfig(**kwargs)


def test_invalid_config_via_replace_raises() -> None:
    with pytest.raises(ValueError):
        dataclasses.replace(C, a_req=0.0)


@pytest.mark.parametrize(
    "args",
    [(-1.0, 0.0, 0.0, 0.0), (10.0, 0.0, -0.5, 0.0), (math.nan, 0, 0, 0), (10, math.inf, 0, 0)],
)
def test_invalid_inputs_raise(args: tuple[float, float, float, float]) -> None:
    with pytest.raises(ValueError):
        warning_range(*args, C)


def test_range_is_frozen() -> None:
    r = warning_range(25.0, 0.0, 0.0, 0.0, C)
    assert isinstance(r, FcwRange)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.r_w = 1.0  # type: ignore[misc]


# ------------------------------------------------------------------------ monitor
# Ticks every 0.125 s (exact in binary) so time differences are exact.
DT = 0.125


def feed(mon: WarningMonitor, rv: object, flags: str, t0: float = 0.0) -> list[AppEvent]:
    """Feed one tick per character ('1' = warn) starting at t0; collect events."""
    out: list[AppEvent] = []
    for k, f in enumerate(flags):
        out += mon.update(t0 + k * DT, rv, f == "1")
    return out


def test_monitor_flicker_within_off_time_keeps_event() -> None:
    # flags at t = 0, .125, .25, ...:  1 1 0 0 1 1 1 0 0 0 0 0
    # start at t=0.  Gap 1 starts t=0.25, back on at t=0.5 (0.25 s < 0.5 s): no end.
    # Gap 2 starts t=0.875 (index 7); end when t - 0.875 >= 0.5 -> t = 1.375 (index 11).
    # Event: t_start 0.0, t_end 0.875.
    mon = WarningMonitor()
    ev = feed(mon, "A", "110011100000")
    assert ev == [AppEvent("start", "A", 0.0), AppEvent("end", "A", 0.0, 0.875)]


def test_monitor_end_happens_exactly_at_off_time() -> None:
    mon = WarningMonitor(off_time=0.5)
    # on at 0; off from 0.125; at 0.5: 0.375 elapsed -> still open; at 0.625: 0.5 -> end.
    assert feed(mon, "A", "10000") == [AppEvent("start", "A", 0.0)]
    assert mon.open_events() == {"A": 0.0}
    assert mon.update(0.625, "A", False) == [AppEvent("end", "A", 0.0, 0.125)]
    assert mon.open_events() == {}


def test_monitor_long_gap_ends_and_new_event_starts_later() -> None:
    # 1 1 0 0 0 0 0 0 1 1 0 0 0 0 0   (15 ticks, t = 0 .. 1.75)
    # event 1: start 0.0; gap from 0.25; end at 0.75 (0.5 elapsed) -> t_end 0.25
    # event 2: start at index 8 -> t = 1.0; gap from 1.25; end at 1.75 -> t_end 1.25
    mon = WarningMonitor()
    ev = feed(mon, 7, "110000001100000")
    assert ev == [
        AppEvent("start", 7, 0.0),
        AppEvent("end", 7, 0.0, 0.25),
        AppEvent("start", 7, 1.0),
        AppEvent("end", 7, 1.0, 1.25),
    ]


def test_monitor_on_ticks_requires_consecutive_warns() -> None:
    # on_ticks = 3: 1 1 0 1 1 1 -> first run of two is dropped; the run starting at
    # index 3 (t = 0.375) completes at index 5 -> start with t_start = 0.375.
    mon = WarningMonitor(on_ticks=3)
    ev = feed(mon, "A", "110111")
    assert ev == [AppEvent("start", "A", 0.375)]


def test_monitor_rvs_are_independent() -> None:
    mon = WarningMonitor()
    events: list[AppEvent] = []
    a = "1111000000"  # A: start 0.0; off from 0.5; end at 1.0 -> t_end 0.5
    b = "0011111111"  # B: start 0.25; never ends
    for k in range(len(a)):
        t = k * DT
        events += mon.update(t, "A", a[k] == "1")
        events += mon.update(t, "B", b[k] == "1")
    assert events == [
        AppEvent("start", "A", 0.0),
        AppEvent("start", "B", 0.25),
        AppEvent("end", "A", 0.0, 0.5),
    ]
    assert mon.open_events() == {"B": 0.25}


def test_monitor_invalid_parameters() -> None:
    with pytest.raises(ValueError):
        WarningMonitor(on_ticks=0)
    with pytest.raises(ValueError):
        WarningMonitor(off_time=-0.1)


def test_monitor_end_to_end_with_warning_range() -> None:
    # HV 25 m/s closing on a stopped RV (r_w = 87.5 with C); range shrinks 10 m per
    # tick from 120 m: 120, 110, 100, 90, 80 -> first warn at 80 m (index 4, t=0.5).
    mon = WarningMonitor()
    r = warning_range(25.0, 0.0, 0.0, 0.0, C)
    events: list[AppEvent] = []
    for k, rng in enumerate((120.0, 110.0, 100.0, 90.0, 80.0, 70.0)):
        events += mon.update(k * DT, "rv1", should_warn(rng, r))
    assert events == [AppEvent("start", "rv1", 0.5)]


# ------------------------------------------------------------------------ property

speed = st.floats(min_value=0.0, max_value=60.0, allow_nan=False, allow_subnormal=False)
accel = st.floats(min_value=-10.0, max_value=5.0, allow_nan=False, allow_subnormal=False)
configs = st.builds(
    FcwConfig,
    t_d=st.floats(min_value=0.0, max_value=3.0, allow_subnormal=False),
    a_req=st.floats(min_value=-10.0, max_value=-0.5, allow_subnormal=False),
)


@settings(max_examples=500, deadline=None)
@given(v1=speed, v2=speed, a_hv=accel, v_rv=speed, a_rv=accel, cfg=configs)
def test_rw_finite_and_monotone_in_hv_speed(
    v1: float, v2: float, a_hv: float, v_rv: float, a_rv: float, cfg: FcwConfig
) -> None:
    lo, hi = sorted((v1, v2))
    r_lo = warning_range(lo, a_hv, v_rv, a_rv, cfg)
    r_hi = warning_range(hi, a_hv, v_rv, a_rv, cfg)
    for r in (r_lo, r_hi):
        assert math.isfinite(r.r_w) and math.isfinite(r.bor)
        assert r.bor >= 0.0
        assert r.case in (1, 2, 3)
    # A faster HV (same HV acceleration, same RV) never gets a smaller r_w.
    assert r_hi.r_w >= r_lo.r_w - 1e-9 * (1.0 + abs(r_lo.r_w))
