"""catc.mbd: plausibility checks on verified BSMs (F2MD's legacy checks, adapted).

A clean run of real trajectories must raise nothing: the default SUMO scenario through
the RVE's channel (PER 0 and 50 %, burst loss, latency with jitter and reordering, through
UPER), and the real GNSS platoons of OpenACC.  Each attack of the brief must be caught by
its check, quarantine its sender and leave the honest neighbours alone.  A real faulty BSM
stream (the NYC CV pilot's target, whose speed source is stuck) is caught too.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from catc import geo
from catc.bsm import BSM, TransmissionState
from catc.channel import ChannelConfig
from catc.mbd import CHECKS, Detection, MbdConfig, MisbehaviorDetector, local_offset_m
from catc.mbd.geometry import blocks, iou, max_min_dist, scale
from catc.mbd.quarantine import is_strong
from catc.replay import plan, temp_id
from hil.datasets import load_table
from tests.conftest import shared_path

# --- helpers ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def table():
    return load_table("scenario:highway-braking", None)


@pytest.fixture(scope="module")
def clean_plan(table):
    return plan(table, ChannelConfig(), 0)


def _shift(m: BSM, east: float, north: float) -> BSM:
    """``m`` moved ``east``/``north`` metres (small offsets, local scale)."""
    k = math.pi / 180 * 6_378_137.0
    return dataclasses.replace(m, lat=m.lat + north / k,
                               lon=m.lon + east / (k * math.cos(math.radians(m.lat))))


def _stream(the_plan, extra=(), modify=None, wire=False, hosted=False):
    """``(time, bsm, host_lat, host_lon)`` of every delivered RV frame of ``the_plan`` in
    arrival order, with ``extra`` ``(time, bsm)`` frames merged in and ``modify(vehicle,
    bsm) -> bsm | None`` applied to the plan's frames.  The host position is the host's
    latest frame (what the OBU knows), None once that is over 0.5 s old.  ``hosted``:
    ``(time, bsm, host_bsm)`` instead, the host's frame None when over 0.5 s old."""
    if wire:
        from catc.j2735 import decode_frame, encode_frame
    items = []
    ev = the_plan.events
    for k in np.flatnonzero(~ev["dropped"]):
        e = ev[k]
        items.append((float(e["time"]), 0 if e["host"] else 1, int(k), e, None))
    for j, (t, m) in enumerate(extra):
        items.append((float(t), 1, len(ev) + j, None, m))
    items.sort(key=lambda x: x[:3])
    host, host_t = None, -math.inf
    for t, _, _, e, m in items:
        if e is not None:
            m = the_plan.bsm(e)
            if wire:
                m = decode_frame(encode_frame(m))
            if e["host"]:
                host, host_t = m, t
                continue
            if modify is not None:
                m = modify(int(e["vehicle"]), m)
                if m is None:
                    continue
        hb = host if t - host_t <= 0.5 else None
        if hosted:
            yield t, m, hb
        else:
            yield t, m, *((hb.lat, hb.lon) if hb is not None else (None, None))


def _run_hosted(the_plan, det=None, **kw):
    """:func:`_run` with the host's heading, speed and yaw rate, as the OBU passes them;
    also every report (:attr:`MisbehaviorDetector.reports`) as it was filed."""
    det = MisbehaviorDetector() if det is None else det
    found: list[Detection] = []
    reports: list[Detection] = []
    for t, m, hb in _stream(the_plan, hosted=True, **kw):
        found += det.observe(m, t, *((hb.lat, hb.lon) if hb else (None, None)),
                             host_heading=hb.heading if hb else None,
                             host_speed=hb.speed if hb else None,
                             host_yaw_rate=hb.yaw_rate if hb else None)
        reports += det.reports
    return det, found, reports


def _run(the_plan, det=None, **kw):
    det = MisbehaviorDetector() if det is None else det
    found: list[Detection] = []
    for t, m, hlat, hlon in _stream(the_plan, **kw):
        found += det.observe(m, t, hlat, hlon)
    return det, found


def _vehicle(the_plan, name):
    return the_plan.vehicles.index(name)


def _bsms_of(the_plan, name):
    """The plan's frames of one vehicle as ``(time, bsm)``."""
    v = _vehicle(the_plan, name)
    ev = the_plan.events
    sel = ev[(ev["vehicle"] == v) & ~ev["dropped"]]
    return [(float(e["time"]), the_plan.bsm(e)) for e in sel]


def _checks(found, suspect=None):
    return {d.check for d in found if suspect is None or d.suspect == suspect}


# --- geometry ---------------------------------------------------------------------------


@pytest.mark.parametrize("lat", [0.0, 46.89, -33.9, 64.1])
def test_local_offsets_agree_with_the_geodesic(lat):
    rng = np.random.default_rng(1)
    for _ in range(200):
        d = float(rng.uniform(0.5, 2000.0))
        az = float(rng.uniform(0.0, 360.0))
        lon = float(rng.uniform(-179.0, 179.0))
        k = math.pi / 180 * 6_378_137.0
        lat2 = lat + d * math.cos(math.radians(az)) / k
        lon2 = lon + d * math.sin(math.radians(az)) / (k * math.cos(math.radians(lat)))
        east, north = local_offset_m(lat, lon, lat2, lon2)
        ref = geo.distance_m(lat, lon, lat2, lon2)
        assert math.hypot(east, north) == pytest.approx(ref, rel=1e-6, abs=1e-3)
        # the direction at the midpoint: the geodesic's initial azimuth differs from it by
        # half the meridian convergence, (lon2 - lon1) sin(lat) / 2 (~0.002 deg at 2 km)
        bearing = math.degrees(math.atan2(east, north)) % 360.0
        convergence = abs(lon2 - lon) * abs(math.sin(math.radians(lat))) / 2
        assert abs(geo.heading_diff_deg(bearing, geo.bearing_deg(lat, lon, lat2, lon2))) \
            < convergence + 1e-4 + 0.01 / d
    east, north = local_offset_m(10.0, 179.9999, 10.0, -179.9999)  # across the antimeridian
    assert east == pytest.approx(2e-4 * math.pi / 180 * 6_378_137.0 * math.cos(
        math.radians(10.0)), rel=1e-2) and abs(north) < 1e-9


def test_the_per_message_scale_is_good_to_the_check_tolerances():
    """observe() converts with one metric scale per message (at its latitude); over the
    largest distance it compares (the radio range) that is within a few metres."""
    for lat in (0.0, 40.7, 46.89, 60.0):
        kx, ky = scale(lat)
        for az in range(0, 360, 30):
            d = 1500.0
            k = math.pi / 180 * 6_378_137.0
            lat2 = lat + d * math.cos(math.radians(az)) / k
            lon2 = 16.0 + d * math.sin(math.radians(az)) / (k * math.cos(math.radians(lat)))
            approx = math.hypot((lon2 - 16.0) * kx, (lat2 - lat) * ky)
            assert approx == pytest.approx(geo.distance_m(lat, 16.0, lat2, lon2), abs=0.5)


def test_footprint_overlap_and_the_kinematic_envelope():
    car = (0.0, 0.0, 0.3, 5.0, 1.8)
    assert iou(car, car) == pytest.approx(1.0)
    ahead = (2.5 * math.sin(0.3), 2.5 * math.cos(0.3), 0.3, 5.0, 1.8)  # half a length on
    assert iou(car, ahead) == pytest.approx(1 / 3)
    across = (0.0, 0.0, 0.3 + math.pi / 2, 5.0, 1.8)  # a cross: 1.8 x 1.8 in common
    assert iou(car, across) == pytest.approx(3.24 / (18.0 - 3.24))
    assert iou((0.0, 0.0, 0.0, 5.0, 1.8), (3.0, 0.0, 0.0, 5.0, 1.8)) == 0.0  # next lane
    # F2MD calculateMaxMinDist: constant speed lies inside; from rest the greatest distance
    # accelerates half the time and brakes the other half
    lo, hi = max_min_dist(20.0, 20.0, 1.0, 10.0, 10.0, 70.0)
    assert lo < 20.0 < hi and hi - 20.0 == pytest.approx(2.5) and 20.0 - lo == pytest.approx(2.5)
    assert max_min_dist(0.0, 0.0, 1.0, 10.0, 10.0, 70.0) == pytest.approx((0.0, 2.5))
    lo, hi = max_min_dist(69.0, 69.0, 1.0, 10.0, 10.0, 70.0)  # capped at 70 m/s
    assert lo == pytest.approx(69.0 - 2.5) and 69.0 < hi <= 70.0


def test_a_footprint_blocks_a_line_of_sight_it_crosses():
    car = (0.0, 10.0, 0.0, 4.5, 1.8)  # 10 m north, heading north
    assert blocks(0.0, 0.0, 0.0, 30.0, car)  # straight through it
    assert blocks(0.0, 0.0, 0.8, 30.0, car)  # grazing its side
    assert not blocks(0.0, 0.0, 6.0, 30.0, car)  # past its side
    assert not blocks(0.0, 0.0, 0.0, 7.0, car)  # ends before it
    assert blocks(-5.0, 10.0, 5.0, 10.0, car) and blocks(-5.0, 10.0, 5.0, 10.0,
                                                         (0.0, 10.0, math.pi / 2, 4.5, 1.8))


# --- configuration ----------------------------------------------------------------------


def test_defaults_are_f2md_s_or_the_documented_adaptations():
    c = MbdConfig()
    assert c.max_range_m == 1500.0  # F2MD MAX_PLAUSIBLE_RANGE 420, adapted to our radio
    assert c.sa_range_m == 210.0  # F2MD MAX_SA_RANGE
    assert c.max_time_delta_s == 3.1  # F2MD MAX_TIME_DELTA
    assert c.max_delta_inter_s == 2.0  # F2MD MAX_DELTA_INTER
    assert c.max_mgt_rng_up_m == 2.1 and c.max_mgt_rng_down_m == 6.2  # F2MD MAX_MGT_RNG_*
    assert c.pos_heading_time_s == 1.1  # F2MD POS_HEADING_TIME
    assert c.min_interval_s == pytest.approx(0.09)  # F2MD 0.9 s of its 1 s beacon, at 10 Hz
    assert c.intersection_threshold == 0.5  # F2MD IntersectionCheck: inter > 0.5
    assert set(CHECKS) == {"range", "position-consistency", "speed-consistency",
                           "position-speed", "sudden-appearance", "frequency", "heading",
                           "sybil", "intersection"}
    for bad in ({"max_range_m": 0.0}, {"max_accel_mps2": -1.0}, {"quarantine_k": 0},
                {"min_interval_s": math.nan}, {"intersection_threshold": 1.5}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            MbdConfig(**bad)
    with pytest.raises(ValueError, match="max_senders"):
        MisbehaviorDetector(max_senders=0)


def test_every_check_is_one_function_in_the_table():
    """catc.mbd.checks.TABLE lists each check function once, under a Detection.check name;
    the pair checks (run per neighbour) come after the message checks."""
    from catc.mbd.checks import TABLE

    assert {k.name for k in TABLE} == set(CHECKS)
    assert len({k.run for k in TABLE}) == len(TABLE)
    pair = [k.pair for k in TABLE]
    assert pair == sorted(pair) and any(pair)


# --- false positives: real trajectories raise nothing -----------------------------------


@pytest.mark.parametrize("channel", [
    ChannelConfig(),
    ChannelConfig(per=0.5),
    ChannelConfig(per=0.5, burst=3.0, latency_s=0.02, jitter_s=0.15),  # reorders
    ChannelConfig(rate_hz=1.0, per=0.3),
], ids=["10Hz", "per50", "burst-jitter-reorder", "1Hz-per30"])
def test_the_default_scenario_raises_nothing(table, channel):
    the_plan = plan(table, channel, 3)
    det, found = _run(the_plan)
    assert found == []
    assert not det.counters
    assert not any(det.quarantined(temp_id(v), 60.0) for v in the_plan.vehicles)


def test_the_default_scenario_through_uper_raises_nothing(clean_plan):
    """What the OBU decodes: positions to 1e-7 deg, speeds to 0.02 m/s, headings to
    0.0125 deg."""
    _, found = _run(clean_plan, wire=True)
    assert found == []


def test_real_gnss_platoons_raise_nothing_but_late_starters():
    """OpenACC (JRC, ZalaZONE): raw GNSS of production cars at 10 Hz, on ACC and by hand,
    down to 0.3 s time gaps.  The files carry no vehicle size; 4.6 x 1.8 m is given to
    every car so that the intersection and Sybil checks run too.

    The reader splits a vehicle's track at a GNSS gap into a new id (``NAME#2``) that
    continues after seconds of silence: a pseudonym change, which is not flagged (at
    1 Hz and 30 % loss too, where the old id's last message and the new one's first are
    6 s apart).  Two logs begin late: one 8 s into its file, 65 m from the host, one
    1.6 s in, 35 m ahead of the host behind the car in between: to a receiver, cars
    switching their radios on nearby, which is what F2MD's sudden appearance flags.  Those
    findings are reported but, outside the host's safety range or in the radio shadow of
    another car, quarantine nobody.  (Before issue 28 a blind 2.1 s warm-up hid the
    second one.)"""
    from hil.datasets import load

    folder = shared_path("openacc-zalazone")
    files = sorted(folder.glob("*.csv"))
    assert files
    late = []
    for path in files:
        (tab,) = load(f"openacc:{path}")
        t0 = min(float(tr.t[0]) for tr in tab.tracks.values())
        starts = {temp_id(v): float(tr.t[0]) for v, tr in tab.tracks.items()
                  if "#" not in v}

        def sized(_v, m):
            return dataclasses.replace(m, length=4.6, width=1.8)

        for channel in (ChannelConfig(), ChannelConfig(per=0.5),
                        ChannelConfig(rate_hz=1.0, per=0.3)):
            det, found = _run(plan(tab, channel, 1), modify=sized)
            for d in found:
                assert d.check == "sudden-appearance", (path.name, d)
                assert starts[d.suspect] > t0 + 1.5  # a log that starts late
                assert d.evidence["distance_m"] > d.evidence["safety_range_m"] \
                    or d.evidence["behind"] is not None
                late.append((path.name, d.suspect))
            assert det.counters["quarantines"] == 0
    assert len(set(late)) == 2


@pytest.mark.parametrize("name", ["cut-in", "intersection"])
def test_the_other_sumo_scenarios_raise_nothing_but_insertions(name, tmp_path):
    """cut-in: a forced lane change 20 m ahead of the host.  intersection: a queue at a red
    light with cross traffic in front of it.  SUMO inserts vehicles where their routes
    begin, up to 300 m from the junction: one that enters within F2MD's 210 m of the host
    is a (weak) sudden appearance, never a quarantine."""
    from hil.datasets import load
    from rve import scenario

    try:
        xml = scenario.generate(name, seed=3)
    except scenario.SumoMissing as err:
        pytest.skip(str(err))
    path = tmp_path / f"{name}.fcd.xml"
    path.write_text(xml)
    (tab,) = load(f"sumo:{path}")
    t0 = min(float(tr.t[0]) for tr in tab.tracks.values())
    starts = {temp_id(v): float(tr.t[0]) for v, tr in tab.tracks.items()}
    for channel in (ChannelConfig(), ChannelConfig(per=0.5, burst=3.0, latency_s=0.02,
                                                   jitter_s=0.15)):
        det, found = _run(plan(tab, channel, 3))
        if name == "cut-in":
            assert found == []
        for d in found:
            assert d.check == "sudden-appearance" and starts[d.suspect] > t0 + 2.1, d
            assert d.evidence["distance_m"] > d.evidence["safety_range_m"]
        assert det.counters["quarantines"] == 0


def test_a_real_faulty_bsm_stream_is_caught():
    """The NYC CV pilot's FCW target broadcast a speed stuck at 5.68 m/s while its positions
    advance at about 22 m/s (a J3287 faulty BSM): the position-speed check catches it, and
    nothing else fires."""
    from hil.datasets import load

    (tab,) = load(f"nyc:{shared_path('cv-pilot-samples', 'nycdot-fcw-event.json')}")
    the_plan = plan(tab, ChannelConfig(), 0)
    det, found = _run(the_plan)
    target = next(temp_id(v) for v in the_plan.vehicles if v != the_plan.host_id)
    assert _checks(found) == {"position-speed"}
    assert {d.suspect for d in found} == {target}
    d = found[0]
    assert d.score >= 1.0 and d.evidence["distance_m"] > d.evidence["max_m"]
    assert det.quarantined(target, d.t + 1.0)


# --- attacks ----------------------------------------------------------------------------


def _host_at(table, t):
    host = table.tracks[table.default_host]
    return tuple(float(np.interp(t, host.t, c)) for c in (host.lat, host.lon, host.heading,
                                                          host.speed))


def test_a_ghost_appearing_20_m_ahead_is_a_sudden_appearance(table, clean_plan):
    ghost_id = 0x6A7A0000
    extra = []
    for k in range(30):  # from 8 s, 3 s long, at the host's speed, 20 m ahead
        t = 8.0 + 0.1 * k
        lat, lon, hdg, v = _host_at(table, t)
        m = BSM(msg_cnt=k % 128, temp_id=ghost_id, sec_mark=round(t * 1000) % 60000,
                lat=lat, lon=lon, speed=v, heading=hdg, length=4.5, width=1.8)
        extra.append((t, _shift(m, 20 * math.sin(math.radians(hdg)),
                                20 * math.cos(math.radians(hdg)))))
    det, found = _run(clean_plan, extra=extra)
    assert {d.suspect for d in found} == {ghost_id}
    first = found[0]
    assert first.check == "sudden-appearance" and first.t == pytest.approx(8.0)
    assert first.evidence["distance_m"] == pytest.approx(20.0, abs=3.5)
    assert first.score >= 1.0
    assert det.quarantined(ghost_id, 8.05)  # at once: inside the host's safety range
    assert det.quarantined(ghost_id, 8.0 + det.config.quarantine_s - 0.5)
    assert not any(det.quarantined(temp_id(v), 9.0) for v in clean_plan.vehicles)
    assert det.counters["sudden-appearance"] == 1 and det.counters["quarantines"] == 1


def test_sudden_appearance_waits_for_the_warm_up_and_spares_a_pseudonym_change(clean_plan):
    # the first messages heard: everyone is new, nobody is flagged (the warm-up)
    _, found = _run(clean_plan)
    assert found == []
    # a vehicle that changes its TemporaryID mid-run continues its own path: no appearance
    lead = _vehicle(clean_plan, "lead")

    def new_id(v, m):
        if v == lead and m.sec_mark >= 15_000:
            return dataclasses.replace(m, temp_id=0x12345678)
        return m

    _, found = _run(clean_plan, modify=new_id)
    assert found == []


def test_a_constant_position_jump_fails_position_consistency(clean_plan):
    p2 = _vehicle(clean_plan, "p2")

    def jump(v, m):
        return _shift(m, 0.0, 40.0) if v == p2 and m.sec_mark >= 12_000 else m

    det, found = _run(clean_plan, modify=jump)
    sid = temp_id("p2")
    assert {d.suspect for d in found} == {sid}
    assert "position-consistency" in _checks(found)
    d = next(d for d in found if d.check == "position-consistency")
    assert d.t == pytest.approx(12.0, abs=0.05)
    assert d.evidence["distance_m"] > d.evidence["limit_m"] and d.score >= 1.0
    assert det.quarantined(sid, d.t + 1.0)
    # the shifted track is consistent again once the allowance covers the jump (and the
    # first message accepted there starts a new baseline for position-speed)
    assert max(x.t for x in found) < 12.0 + 1.0
    assert not det.quarantined(temp_id("lead"), d.t + 1.0)


def test_a_speed_that_contradicts_the_positions_fails_position_speed(clean_plan):
    r3 = _vehicle(clean_plan, "r3")

    def doubled(v, m):  # the catc.attacks "speed" kind: factor 2
        if v == r3 and 10_000 <= m.sec_mark < 14_000:
            return dataclasses.replace(m, speed=2.0 * m.speed)
        return m

    det, found = _run(clean_plan, modify=doubled)
    sid = temp_id("r3")
    assert {d.suspect for d in found} == {sid}
    assert "position-speed" in _checks(found)
    assert "speed-consistency" in _checks(found)  # the step itself, 22 m/s in 0.1 s
    assert det.quarantined(sid, 12.0)


def test_a_stuck_speed_fails_position_speed(clean_plan):
    r4 = _vehicle(clean_plan, "r4")

    def stuck(v, m):  # the speed source freezes at 20 km/h, the positions go on at ~80
        return dataclasses.replace(m, speed=5.5) if v == r4 and m.sec_mark >= 10_000 else m

    det, found = _run(clean_plan, modify=stuck)
    sid = temp_id("r4")
    assert {d.suspect for d in found} == {sid}
    assert "position-speed" in _checks(found)
    assert sum(d.check == "position-speed" for d in found if d.t > 13.0) >= 5  # it goes on
    assert det.quarantined(sid, 20.0)


def test_a_replay_is_dropped_without_evidence_against_the_replayed_vehicle(clean_plan):
    """A replay needs no key: the copies of the leader's frames 3 s late, and frames it
    sent 3 s ago that this receiver had missed, say nothing of the leader's behaviour.
    They are dropped (``dropped``: copy, stale) and raise no finding.  (Before issue 28
    they failed ``frequency`` against the leader, three of them quarantined it, and the
    OBU dropped its genuine frames with it.)"""
    frames = _bsms_of(clean_plan, "lead")
    old = [m for t, m in frames if 7.0 <= t < 8.0]
    missed = [m for t, m in frames if 5.0 <= t < 6.0]
    lead = temp_id("lead")

    def lose(v, m):  # the receiver missed the leader's frames of 5-6 s
        return None if m in missed else m

    extra = [(10.0 + 0.1 * k + 0.05, m) for k, m in enumerate(old)]  # 3 s late, 1 s long
    extra += [(9.0 + 0.1 * k + 0.05, m) for k, m in enumerate(missed)]
    det = MisbehaviorDetector()
    dropped = []
    for t, m, hlat, hlon in _stream(clean_plan, extra=extra, modify=lose):
        assert det.observe(m, t, hlat, hlon) == []
        if det.dropped:
            dropped.append((m.sec_mark, det.dropped))
    assert dropped == [(m.sec_mark, "stale") for m in missed] \
        + [(m.sec_mark, "copy") for m in old]
    assert det.counters == {"copy": len(old), "stale": len(missed)}
    assert not det.quarantined(lead, 11.0)


def test_a_replay_from_a_minute_ago_fails_on_the_clock(clean_plan):
    """secMark wraps at 60 s: a frame 55 s old reads as 5 s in the future."""
    frames = _bsms_of(clean_plan, "r3")
    old = next(m for t, m in frames if t >= 1.0)
    later = next(m for t, m in frames if t >= 45.0)
    det = MisbehaviorDetector()
    assert det.observe(later, 45.0, None, None) == []
    (d,) = det.observe(dataclasses.replace(old, sec_mark=(later.sec_mark + 5000) % 60000),
                       45.1, None, None)
    assert d.check == "frequency" and d.evidence["ahead_s"] == pytest.approx(4.9, abs=0.01)


def test_messages_too_close_in_time_fail_frequency(clean_plan):
    frames = [(t, m) for t, m in _bsms_of(clean_plan, "p3") if 10.0 <= t < 11.0]
    extra = [(t + 0.025, dataclasses.replace(m, sec_mark=(m.sec_mark + 25) % 60000))
             for t, m in frames]  # the DoS kind: 4x the rate
    det, found = _run(clean_plan, extra=extra)
    assert _checks(found) == {"frequency"} and {d.suspect for d in found} == {temp_id("p3")}
    assert all(d.evidence["interval_s"] == pytest.approx(0.025, abs=1e-6) for d in found)
    assert det.quarantined(temp_id("p3"), 11.0)


def test_a_sybil_copying_a_vehicle_with_a_small_offset(clean_plan):
    frames = [(t, m) for t, m in _bsms_of(clean_plan, "lead") if 6.0 <= t < 12.0]
    sybil = 0x5B11
    extra = []
    for t, m in frames:  # F2MD's grid Sybil: 5 m behind and 2 m aside (SybilDistanceX/Y)
        h = math.radians(m.heading)
        e = -5 * math.sin(h) + 2 * math.cos(h)
        n = -5 * math.cos(h) - 2 * math.sin(h)
        extra.append((t + 0.001, dataclasses.replace(_shift(m, e, n), temp_id=sybil,
                                                      length=4.5, width=1.8)))
    det, found = _run(clean_plan, extra=extra)
    assert {d.suspect for d in found} == {sybil}
    # appearing 34 m ahead of the host, it is also a sudden appearance
    assert "sybil" in _checks(found) <= {"sybil", "sudden-appearance"}
    d = next(d for d in found if d.check == "sybil")
    assert d.other == temp_id("lead")
    assert d.evidence["messages"] == det.config.sybil_messages
    assert d.evidence["lateral_m"] == pytest.approx(2.0, abs=0.05)
    assert det.quarantined(sybil, d.t + 0.01)
    assert not det.quarantined(temp_id("lead"), d.t + 0.01)


def test_the_catc_attacks_sybil_formation_is_caught(clean_plan):
    """catc.attacks' sybil kind: ids every 8 m behind the sender, on its path."""
    tr = clean_plan.table.tracks["lead"]
    extra = []
    for i in range(60, 120):  # 6-12 s
        t = float(tr.t[i])
        for j in (1, 2, 3):
            s_back = 8.0 * j
            h = math.radians(float(tr.heading[i]))
            m = BSM(msg_cnt=i % 128, temp_id=0x6A7A0000 | j, sec_mark=round(t * 1000) % 60000,
                    lat=float(tr.lat[i]), lon=float(tr.lon[i]), speed=float(tr.speed[i]),
                    heading=float(tr.heading[i]), length=4.5, width=1.8)
            extra.append((t, _shift(m, -s_back * math.sin(h), -s_back * math.cos(h))))
    det, found = _run(clean_plan, extra=extra)
    assert {d.suspect for d in found if d.check == "sybil"} == {0x6A7A0001, 0x6A7A0002,
                                                                   0x6A7A0003}
    assert _checks(found) == {"sybil", "sudden-appearance"}
    assert not det.quarantined(temp_id("lead"), 12.0)


def test_an_id_out_of_radio_range_fails_range(clean_plan):
    frames = [(t, m) for t, m in _bsms_of(clean_plan, "l4") if t < 20.0]
    extra = [(t + 0.001, dataclasses.replace(_shift(m, 2500.0, 1500.0), temp_id=0xFA))
             for t, m in frames]
    det, found = _run(clean_plan, extra=extra)
    assert _checks(found) == {"range"} and {d.suspect for d in found} == {0xFA}
    assert all(d.evidence["distance_m"] > 1500 and d.evidence["limit_m"] == 1500.0
               for d in found)
    assert det.quarantined(0xFA, 19.0)


def test_a_heading_90_degrees_off_the_path_fails_heading(clean_plan):
    p4 = _vehicle(clean_plan, "p4")

    def sideways(v, m):
        if v == p4 and 10_000 <= m.sec_mark < 13_000:
            return dataclasses.replace(m, heading=(m.heading + 90.0) % 360.0)
        return m

    det, found = _run(clean_plan, modify=sideways)
    sid = temp_id("p4")
    assert _checks(found) == {"heading"} and {d.suspect for d in found} == {sid}
    d = found[0]
    assert d.evidence["difference_deg"] == pytest.approx(90.0, abs=1.0)
    assert det.quarantined(sid, 12.0)


def test_a_clone_on_top_of_a_vehicle_and_a_ghost_on_the_host_intersect(table, clean_plan):
    frames = [(t, m) for t, m in _bsms_of(clean_plan, "p2") if 6.0 <= t < 8.0]
    clone = [(t + 0.002, dataclasses.replace(_shift(m, 0.3, 0.3), temp_id=0xC1))
             for t, m in frames]
    extra = list(clone)
    for k in range(10):  # on the host itself, from 9 s
        t = 9.0 + 0.1 * k
        lat, lon, hdg, v = _host_at(table, t)
        extra.append((t, BSM(msg_cnt=k, temp_id=0xC2, sec_mark=round(t * 1000) % 60000,
                             lat=lat, lon=lon, speed=v, heading=hdg, length=5.0, width=1.8)))
    det, found = _run(clean_plan, extra=extra)
    assert {d.suspect for d in found} == {0xC1, 0xC2}
    with_p2 = [d for d in found if d.suspect == 0xC1]
    assert {d.check for d in with_p2} >= {"intersection"}
    assert {d.other for d in with_p2 if d.check == "intersection"} == {temp_id("p2")}
    on_host = [d for d in found if d.suspect == 0xC2]
    assert on_host[0].check in ("intersection", "sudden-appearance")
    assert any(d.check == "intersection" and d.other is None for d in on_host)
    assert det.quarantined(0xC1, 8.0) and det.quarantined(0xC2, 9.5)
    assert not det.quarantined(temp_id("p2"), 8.0)


def test_a_speed_step_fails_speed_consistency():
    det = MisbehaviorDetector()
    m = BSM(msg_cnt=0, temp_id=7, sec_mark=0, lat=46.9, lon=16.9, speed=20.0, heading=0.0)
    k = math.pi / 180 * 6_378_137.0
    for i in range(30):
        mi = dataclasses.replace(m, msg_cnt=i, sec_mark=100 * i, lat=46.9 + 2.0 * i / k)
        assert det.observe(mi, 0.1 * i, None, None) == []
    bad = dataclasses.replace(m, msg_cnt=30, sec_mark=3000, lat=46.9 + 60.2 / k, speed=23.0)
    found = det.observe(bad, 3.0, None, None)
    assert "speed-consistency" in {d.check for d in found}
    d = next(d for d in found if d.check == "speed-consistency")
    assert d.evidence["accel_mps2"] == pytest.approx(30.0) and d.score >= 1.0
    # an implausible speed on its own
    (d,) = [d for d in det.observe(dataclasses.replace(bad, sec_mark=3100, speed=80.0,
                                                       lat=46.9 + 60.4 / k), 3.1, None, None)
            if d.check == "speed-consistency" and "speed_mps" in d.evidence]
    assert d.evidence["limit_mps"] == det.config.max_speed_mps


# --- identity: ids bound to signers ----------------------------------------------------


def _cert(tid: int) -> bytes:
    """The HashedId8 of the pseudonym certificate each honest id is signed with here."""
    return b"cert" + tid.to_bytes(4, "big")


def _run_signed(the_plan, det=None, signers=None, **kw):
    """:func:`_run` with every message signed: by ``signers[id(bsm)]`` for those given,
    else by its id's own certificate (:func:`_cert`)."""
    det = MisbehaviorDetector() if det is None else det
    signers = signers or {}
    found: list[Detection] = []
    for t, m, hlat, hlon in _stream(the_plan, **kw):
        found += det.observe(m, t, hlat, hlon, signer=signers.get(id(m), _cert(m.temp_id)))
    return det, found


def _on_host(table, tid, t, t_host):
    """A BSM of ``tid`` at ``t`` placed where the host was at ``t_host``."""
    lat, lon, hdg, v = _host_at(table, t_host)
    return BSM(msg_cnt=5, temp_id=tid, sec_mark=round(t * 1000) % 60000, lat=lat, lon=lon,
               speed=v, heading=hdg, length=5.0, width=1.8)


def test_a_second_signer_claiming_an_id_is_the_suspect_not_its_holder(table, clean_plan):
    """Issue 28: one correctly signed frame of an insider pseudonym claiming the leader's
    id, on top of the host, quarantined the leader for the rest of the run.  Bound to the
    certificate that signs it, the id is the leader's: the frame is an id conflict, its
    signer the suspect (quarantined at once), and the leader's frames flow on."""
    lead, thief = temp_id("lead"), b"insider!"
    bad = _on_host(table, lead, 10.05, 10.0)
    det, found = _run_signed(clean_plan, extra=[(10.05, bad)], signers={id(bad): thief})
    (d,) = found
    assert d.check == "id-conflict" and d.suspect == lead and d.signer == thief
    assert d.evidence == {"holder": _cert(lead).hex(), "signer": thief.hex()}
    assert det.quarantined(lead, 10.1, thief) and det.ids_of(lead, 10.1, thief) == {lead}
    assert not det.quarantined(lead, 10.1, _cert(lead))
    assert not det.quarantined(lead, 10.1)  # the id's holder, the leader
    assert det.counters == {"id-conflict": 1, "quarantines": 1, "reported": 1}
    # unsigned, nothing binds the id: whoever claims it gets the leader quarantined
    det, found = _run(clean_plan, extra=[(10.05, bad)])
    assert "intersection" in _checks(found) and det.quarantined(lead, 30.0)


def test_an_unsigned_message_under_a_held_id_is_a_conflict_too(table, clean_plan):
    lead = temp_id("lead")
    bad = _on_host(table, lead, 10.05, 10.0)
    det, found = _run_signed(clean_plan, extra=[(10.05, bad)], signers={id(bad): None})
    assert [d.check for d in found] == ["id-conflict"] and found[0].signer is None
    assert det.dropped is None and not det.quarantined(lead, 10.1, _cert(lead))


def test_a_pseudonym_change_binds_the_new_id_to_the_new_certificate(clean_plan):
    """SCMS changes the certificate and the TemporaryID together: the new id under the
    new certificate is no conflict, no appearance.  An id falls free ``id_hold_s`` after
    its holder last used it."""
    lead = _vehicle(clean_plan, "lead")
    new_id, new_cert = 0x12345678, b"newcert!"
    changed: dict[int, bytes] = {}

    def change(v, m):
        if v == lead and m.sec_mark >= 15_000:
            m = dataclasses.replace(m, temp_id=new_id)
            changed[id(m)] = new_cert
        return m

    det, found = _run_signed(clean_plan, modify=change, signers=changed)
    assert found == [] and not det.counters
    assert det.ids_of(new_id, 20.0, new_cert) == {new_id}
    # the old id, silent since 15 s, is still the old certificate's until id_hold_s
    late = BSM(msg_cnt=0, temp_id=temp_id("lead"), sec_mark=40_000, lat=46.9, lon=16.9)
    assert [d.check for d in det.observe(late, 40.0, None, None, signer=b"someone!")] \
        == ["id-conflict"]
    det = MisbehaviorDetector(MbdConfig(id_hold_s=10.0))
    _run_signed(clean_plan, det=det, modify=change, signers=changed)
    assert det.observe(late, 40.0, None, None, signer=b"someone!") == []


def _ghost_ahead(table, ahead: float, t0: float, n: int, tid: int = 0x6A7A0000,
                 turned: tuple[int, ...] = ()) -> list:
    """``n`` messages of a fabricated id ``ahead`` m ahead of the host at its speed, at
    10 Hz from ``t0`` s, its heading turned 90 degrees in messages ``turned``: ``extra``
    for :func:`_run`."""
    extra = []
    for k in range(n):
        t = t0 + 0.1 * k
        lat, lon, hdg, v = _host_at(table, t)
        m = BSM(msg_cnt=k % 128, temp_id=tid, sec_mark=round(t * 1000) % 60000,
                lat=lat, lon=lon, speed=v, heading=hdg, length=4.5, width=1.8)
        m = _shift(m, ahead * math.sin(math.radians(hdg)), ahead * math.cos(math.radians(hdg)))
        if k in turned:
            m = dataclasses.replace(m, heading=(hdg + 90.0) % 360.0)
        extra.append((t, m))
    return extra


def _weak_ghost(table):
    """A fabricated id 80 m ahead of the host, 8-18 s, its heading 90 degrees off at 12 s
    and 16 s: weak findings only (``(id, extra)``)."""
    return 0x6A7A0100, _ghost_ahead(table, 80.0, 8.0, 100, 0x6A7A0100, (40, 80))


def test_weak_findings_accumulate_to_quarantine_a_fabricated_id(table, clean_plan):
    """Issue 28: a fabricated id with weak findings only (here a sudden appearance 80 m
    ahead of the host, beyond its safety range, and a heading 90 degrees off at 12 s and
    at 16 s) never reached three failures in 2 s.  Its evidence now adds up over F2MD's
    10 s window: quarantined at the third."""
    ghost, extra = _weak_ghost(table)
    det, found = _run(clean_plan, extra=extra[:80])  # to 15.9 s: two failures
    assert [(d.check, round(d.t, 1)) for d in found] == [
        ("sudden-appearance", 8.0), ("heading", 12.0)]
    assert not is_strong(found[0], det.config)  # 80 m: outside the safety range
    assert not det.quarantined(ghost, 15.9) and not det.counters["quarantines"]
    det, found = _run(clean_plan, extra=extra)
    assert [(d.check, round(d.t, 1)) for d in found][2:] == [("heading", 16.0)]
    assert det.quarantined(ghost, 16.05) and det.counters["quarantines"] == 1
    old = MisbehaviorDetector(MbdConfig(quarantine_window_s=2.0))  # the rule before
    _run(clean_plan, det=old, extra=extra)
    assert not old.quarantined(ghost, 16.05) and not old.counters["quarantines"]


def _insider_ids(table, ids, starts, seconds=1.0):
    """Messages of ``ids`` of one insider certificate, ``ids[j]`` from ``starts[j]`` s for
    ``seconds``, 70 + 30 j m ahead of the host at its speed, in the lane on its left:
    ``(extra, signers)`` for :func:`_run_signed`."""
    insider, extra, signers = b"insider!", [], {}
    for j, (tid, t0) in enumerate(zip(ids, starts, strict=True)):
        for k in range(round(seconds * 10)):
            t = t0 + 0.1 * k
            lat, lon, hdg, v = _host_at(table, t)
            m = BSM(msg_cnt=k, temp_id=tid, sec_mark=round(t * 1000) % 60000, lat=lat,
                    lon=lon, speed=v, heading=hdg, length=4.5, width=1.8)
            h, ahead = math.radians(hdg), 70.0 + 30.0 * j
            m = _shift(m, ahead * math.sin(h) - 3.6 * math.cos(h),
                       ahead * math.cos(h) + 3.6 * math.sin(h))
            extra.append((t, m))
            signers[id(m)] = insider
    return extra, signers


def test_weak_findings_of_one_signer_add_up_across_its_ids(table, clean_plan):
    """Ids of one insider certificate, one after the other, each a weak sudden
    appearance only: their evidence is the signer's, and the third quarantines it with
    every id it holds.  Under three certificates they stay three weak findings."""
    insider, ids = b"insider!", (0x6A7A0001, 0x6A7A0002, 0x6A7A0003)
    extra, signers = _insider_ids(table, ids, (8.0, 10.0, 12.0))
    det, found = _run_signed(clean_plan, extra=extra, signers=signers)
    assert [(d.check, d.suspect, d.signer, d.t) for d in found] == [
        ("sudden-appearance", tid, insider, t) for tid, t in zip(ids, (8.0, 10.0, 12.0),
                                                                 strict=True)]
    assert not any(is_strong(d, det.config) for d in found)
    assert det.quarantined(ids[2], 12.05, insider) and det.quarantined(ids[0], 12.05)
    assert det.ids_of(ids[2], 12.05, insider) == set(ids)
    assert det.counters["quarantines"] == 1
    det, _ = _run_signed(clean_plan, extra=extra)
    assert not det.counters["quarantines"]


def test_one_certificate_under_two_ids_at_once_is_a_sybil(table, clean_plan):
    """The Sybil of issue 28 (``rve run --attack sybil``): ids of one insider certificate
    sending together.  One signer sends under one id at a time: the second id's first
    message overlaps the first id's on the signer's clock, a strong finding, and the
    signer is quarantined with every id it holds.  (Before, the one id whose only finding
    was a weak sudden appearance raised LCW and BSW.)"""
    insider, ids = b"insider!", (0x6A7A0001, 0x6A7A0002, 0x6A7A0003)
    extra, signers = _insider_ids(table, ids, (8.0, 8.0, 8.0), seconds=3.0)
    det, found = _run_signed(clean_plan, extra=extra, signers=signers)
    twins = [d for d in found if d.check == "sybil"]
    assert twins[0].t == 8.0 and twins[0].suspect == ids[1] and twins[0].other == ids[0]
    assert twins[0].evidence == {"signer": insider.hex(), "same_certificate": True}
    assert {d.suspect for d in twins} == set(ids)
    assert det.quarantined(ids[0], 10.95, insider) and det.ids_of(ids[0], 11.0,
                                                                  insider) == set(ids)
    # an id changed without changing the certificate is no Sybil, reordered or not
    lead = _vehicle(clean_plan, "lead")

    def change(v, m):
        return dataclasses.replace(m, temp_id=0x12345678) \
            if v == lead and m.sec_mark >= 15_000 else m

    cert = _cert(temp_id("lead"))
    jittery = plan(table, ChannelConfig(per=0.5, burst=3.0, latency_s=0.02, jitter_s=0.15), 3)
    for the_plan in (clean_plan, jittery):
        det = MisbehaviorDetector()
        for t, m, hlat, hlon in _stream(the_plan, modify=change):
            signer = cert if m.temp_id == 0x12345678 else _cert(m.temp_id)
            assert det.observe(m, t, hlat, hlon, signer=signer) == []


# --- sudden appearance from the first host fix -------------------------------------------


def test_a_ghost_in_the_first_second_is_a_sudden_appearance(table, clean_plan):
    """Issue 28: F2MD's blind 2.1 s warm-up let a ghost that starts at once raise a
    22-tick FCW false alarm.  The warm-up now ends when the loss measured so far says
    every vehicle in range has been heard: 0.5 s here (10 Hz, no loss), so a ghost
    20 m ahead at 0.9 s is caught at its first message."""
    ghost = 0x6A7A0000
    extra = []
    for k in range(20):
        t = 0.9 + 0.1 * k
        lat, lon, hdg, v = _host_at(table, t)
        m = BSM(msg_cnt=k, temp_id=ghost, sec_mark=round(t * 1000) % 60000, lat=lat,
                lon=lon, speed=v, heading=hdg, length=4.5, width=1.8)
        extra.append((t, _shift(m, 20 * math.sin(math.radians(hdg)),
                                20 * math.cos(math.radians(hdg)))))
    det, found = _run(clean_plan, extra=extra)
    assert found[0].check == "sudden-appearance" and found[0].t == pytest.approx(0.9)
    assert found[0].evidence["behind"] is None and is_strong(found[0], det.config)
    assert det.quarantined(ghost, 0.95)
    # at 50 % loss in bursts an honest car could still be unheard at 0.9 s: not yet
    lossy = plan(table, ChannelConfig(per=0.5, burst=3.0), 3)
    det, found = _run(lossy, extra=extra)
    assert not _checks(found, ghost) and det._senders.unheard_s(det.config) > 1.0


def test_a_car_first_heard_behind_another_is_no_strong_appearance(table, clean_plan):
    """Vehicles shadow the radio: a car first heard 45 m ahead, behind the leader (39 m
    ahead in the host's lane), may have been there all along; at 25 m, in the clear, it
    could not have."""
    found = {}
    for ahead in (45.0, 25.0):
        lat, lon, hdg, v = _host_at(table, 12.0)
        m = _shift(BSM(msg_cnt=0, temp_id=0x77, sec_mark=12_000, lat=lat, lon=lon, speed=v,
                       heading=hdg, length=4.5, width=1.8),
                   ahead * math.sin(math.radians(hdg)), ahead * math.cos(math.radians(hdg)))
        det, f = _run(clean_plan, extra=[(12.0, m)])
        (found[ahead],) = f
        assert det.quarantined(0x77, 12.05) == (ahead == 25.0)
    assert found[45.0].evidence["behind"] == temp_id("lead")
    assert found[25.0].evidence["behind"] is None


# --- state and quarantine rules ---------------------------------------------------------


def test_one_glitch_neither_poisons_the_track_nor_quarantines(clean_plan):
    p3 = _vehicle(clean_plan, "p3")

    def glitch(v, m):
        return _shift(m, 30.0, 0.0) if v == p3 and m.sec_mark == 15_000 else m

    det, found = _run(clean_plan, modify=glitch)
    sid = temp_id("p3")
    assert {d.suspect for d in found} == {sid}
    assert all(d.t == pytest.approx(15.0, abs=0.01) for d in found)  # that message only
    assert not det.quarantined(sid, 15.05)  # a GNSS glitch is not an attacker
    assert det.counters["quarantines"] == 0


def test_repeated_failures_quarantine_and_the_quarantine_expires():
    c = MbdConfig(quarantine_k=3, quarantine_window_s=2.0, quarantine_s=10.0)
    det = MisbehaviorDetector(c)
    k = math.pi / 180 * 6_378_137.0

    def msg(i, north):
        return BSM(msg_cnt=i % 128, temp_id=9, sec_mark=(100 * i) % 60000,
                   lat=46.9 + north / k, lon=16.9, speed=10.0, heading=0.0)

    for i in range(40):  # 4 s of a clean track
        assert det.observe(msg(i, i * 1.0), 0.1 * i, None, None) == []
    det.observe(msg(40, 100.0), 4.0, None, None)  # glitch 1
    assert not det.quarantined(9, 4.0)
    det.observe(msg(41, 41.0), 4.1, None, None)
    det.observe(msg(42, 150.0), 4.2, None, None)  # glitch 2
    assert not det.quarantined(9, 4.2)
    det.observe(msg(43, 43.0), 4.3, None, None)
    det.observe(msg(44, 200.0), 4.4, None, None)  # 3 failing messages in 2 s
    assert det.quarantined(9, 4.4) and det.counters["quarantines"] == 1
    assert det.quarantined(9, 14.3) and not det.quarantined(9, 14.5)
    for i in range(45, 60):
        det.observe(msg(i, float(i)), 0.1 * i, None, None)
    det.observe(msg(60, 400.0), 6.0, None, None)  # renewed while quarantined
    assert det.quarantined(9, 15.9) and not det.quarantined(9, 16.1)
    assert det.counters["quarantines"] == 1


def test_state_is_bounded_by_max_senders():
    det = MisbehaviorDetector(max_senders=4096)
    k = math.pi / 180 * 6_378_137.0
    for i in range(10_000):
        m = BSM(msg_cnt=0, temp_id=i, sec_mark=(i * 7) % 60000, lat=46.9 + (i % 100) * 30 / k,
                lon=16.9 + (i // 100) * 0.0004, speed=10.0, heading=90.0, length=4.5,
                width=1.8)
        det.observe(m, 0.001 * i, 46.9, 16.9)
    assert len(det) == 4096
    assert det.grid_entries() <= 4096
    assert len(det._quarantine) <= 4096


def test_unavailable_fields_skip_their_checks(clean_plan):
    p4 = _vehicle(clean_plan, "p4")

    def bare(v, m):
        if v == p4 and m.sec_mark >= 10_000:
            return dataclasses.replace(m, speed=None, heading=None, length=None, width=None,
                                       sec_mark=None)
        return m

    _, found = _run(clean_plan, modify=bare)
    assert found == []
    det = MisbehaviorDetector()
    assert det.observe(BSM(msg_cnt=0, temp_id=1, sec_mark=None, lat=None, lon=None), 0.0,
                       None, None) == []
    # reverse gear: the heading points against the motion, legitimately
    frames = _bsms_of(clean_plan, "r3")[:40]
    det = MisbehaviorDetector()
    for t, m in frames:
        back = dataclasses.replace(m, heading=(m.heading + 180.0) % 360.0,
                                   transmission=TransmissionState.REVERSE_GEARS)
        assert det.observe(back, t, None, None) == []


def test_a_late_message_within_the_reorder_window_is_not_misbehavior(clean_plan):
    frames = [(t, m) for t, m in _bsms_of(clean_plan, "p2") if 5.0 <= t < 7.0]
    det = MisbehaviorDetector()
    order = list(range(len(frames)))
    for i in range(0, len(order) - 1, 4):
        order[i], order[i + 1] = order[i + 1], order[i]
    for rank, i in enumerate(order):
        _, m = frames[i]
        assert det.observe(m, 5.0 + 0.1 * rank, None, None) == []


# --- robustness -------------------------------------------------------------------------

_num = st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True),
                 st.integers(-10**6, 10**6))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(
    st.integers(0, 3),  # temp_id
    st.one_of(st.none(), st.integers(-100, 70_000)),  # sec_mark
    _num, _num, _num, _num, _num, _num, _num,  # lat lon speed heading length width accel
    st.floats(allow_nan=True, allow_infinity=True),  # t
    st.one_of(st.none(), st.floats(-90, 90)), st.one_of(st.none(), st.floats(-180, 180)),
), min_size=1, max_size=25))
def test_random_field_values_never_raise(rows):
    det = MisbehaviorDetector(max_senders=3)
    for tid, sm, lat, lon, speed, heading, length, width, accel, t, hlat, hlon in rows:
        m = BSM(msg_cnt=0, temp_id=tid, sec_mark=sm, lat=lat, lon=lon, speed=speed,
                heading=heading, length=length, width=width, accel_long=accel)
        out = det.observe(m, t, hlat, hlon)
        assert all(d.check in CHECKS and d.score >= 1.0 and math.isfinite(d.score)
                   for d in out)
        det.quarantined(tid, t)


# --- sudden appearance: in the host's path, or beside it -----------------------------------


def test_honest_newcomers_beside_and_behind_the_host_are_not_quarantined():
    """Issue 28: on the dense NGSIM I-80 scene (host 232, 45 RVs), cars enter the data
    beside and behind the host, five of them inside its 50 m safety range (8-45 m away):
    to a receiver, honest cars first heard nearby.  Each was quarantined at once for the
    whole of its time in the data, and every BSW and LCW warning of the run was lost.  A
    first message inside the safety range is strong only in the host's path ahead, where
    a ghost can trigger an FCW; beside or behind it is a weak finding, reported to
    nobody unless more evidence follows."""
    from hil.datasets import load

    (scene,) = load(f"scene:ngsim:{shared_path('ngsim-i80-pairs')}")
    det, found, reports = _run_hosted(plan(scene, ChannelConfig(), 0))
    assert found and _checks(found) == {"sudden-appearance"}
    near = [d for d in found if d.evidence["distance_m"] < d.evidence["safety_range_m"]]
    assert len(near) >= 5
    for d in near:  # beside (more than a lane across) or behind the host, in the clear
        assert d.evidence["along_m"] < 0.0 or abs(d.evidence["across_m"]) > 3.0, d
    assert sum(d.evidence["behind"] is None for d in near) >= 3
    assert not any(is_strong(d, det.config) for d in found)
    assert det.counters["quarantines"] == 0 and reports == []
    # the rule before: any clear first message inside the safety range was strong (as
    # now without the host's heading)
    old, _ = _run(plan(scene, ChannelConfig(), 0))
    assert old.counters["quarantines"] >= 3


def _ghost_on_arc(radius: float, ahead: float, t: float, tid: int = 0x6A7A0000):
    """A host at the origin heading north at 20 m/s on a right turn of ``radius`` m (its
    yaw rate as J2735 has it, deg/s clockwise), and a BSM of a vehicle ``ahead`` m along
    that arc: ``(host, ghost)``."""
    yaw = math.degrees(20.0 / radius)
    host = BSM(msg_cnt=0, temp_id=0x11, sec_mark=round(t * 1000) % 60000, lat=47.0,
               lon=8.0, speed=20.0, heading=0.0, yaw_rate=yaw, length=4.5, width=1.8)
    a = ahead / radius  # the angle turned
    east, north = radius * (1.0 - math.cos(a)), radius * math.sin(a)
    ghost = _shift(BSM(msg_cnt=0, temp_id=tid, sec_mark=host.sec_mark, lat=47.0, lon=8.0,
                       speed=20.0, heading=math.degrees(a), length=4.5, width=1.8),
                   east, north)
    return host, ghost


def _warmed() -> MisbehaviorDetector:
    """A detector that heard a parked car 1 km south of 47 N 8 E for 1 s at 10 Hz: past
    its warm-up, a first message is an appearance."""
    det = MisbehaviorDetector()
    for k in range(11):
        assert det.observe(BSM(msg_cnt=k, temp_id=0x22, sec_mark=100 * k, lat=46.991,
                               lon=8.0, speed=0.0, heading=0.0), 0.1 * k, 47.0, 8.0) == []
    return det


def test_a_ghost_on_the_hosts_curving_path_is_in_its_path():
    """The host's path ahead bends with its yaw rate: a ghost 40 m along a 200 m bend is
    4 m right of the host's heading, more than a lane, yet in its path."""
    host, ghost = _ghost_on_arc(200.0, 40.0, 1.1)
    kw = {"host_heading": host.heading, "host_speed": host.speed}
    det = _warmed()
    (d,) = det.observe(ghost, 1.1, host.lat, host.lon, host_yaw_rate=host.yaw_rate, **kw)
    assert d.check == "sudden-appearance"
    assert d.evidence["along_m"] == pytest.approx(39.7, abs=0.3)
    assert d.evidence["across_m"] == pytest.approx(0.0, abs=0.2)
    assert is_strong(d, det.config) and det.quarantined(ghost.temp_id, 1.15)
    assert det.reports == (d,)
    # without the yaw rate the path is straight: 4 m across, beside the host, weak
    det = _warmed()
    (d,) = det.observe(ghost, 1.1, host.lat, host.lon, **kw)
    assert d.evidence["across_m"] == pytest.approx(4.0, abs=0.1)
    assert not is_strong(d, det.config) and det.reports == ()
    assert not det.quarantined(ghost.temp_id, 1.15)
    # and with no host heading at all, the place is unknown: taken as in the path
    det = _warmed()
    (d,) = det.observe(ghost, 1.1, host.lat, host.lon)
    assert d.evidence["along_m"] is None and is_strong(d, det.config)


def test_a_ghost_ahead_in_the_lane_is_still_quarantined_and_reported(table, clean_plan):
    """With the host's heading, speed and yaw rate (as the OBU passes them) the ghost
    20 m ahead in the host's lane is in its path: quarantined and reported at once."""
    ghost = 0x6A7A0000
    det, found, reports = _run_hosted(clean_plan, extra=_ghost_ahead(table, 20.0, 8.0, 30))
    first = found[0]
    assert first.check == "sudden-appearance" and first.t == pytest.approx(8.0)
    assert first.evidence["along_m"] == pytest.approx(20.0, abs=3.5)
    assert abs(first.evidence["across_m"]) < 0.5
    assert is_strong(first, det.config) and det.quarantined(ghost, 8.05)
    assert reports[0] is first and {d.suspect for d in reports} == {ghost}


def test_weak_findings_are_reported_only_past_the_threshold(table, clean_plan):
    """A misbehavior report goes out once the evidence passes the reporting threshold
    (F2MD's AggregationApp, J3287): two weak findings of a fabricated id file nothing; the
    third quarantines it, and its report carries all three."""
    ghost, extra = _weak_ghost(table)
    det, found, reports = _run_hosted(clean_plan, extra=extra[:80])
    assert len(found) == 2 and reports == [] and det.counters["reported"] == 0
    det, found, reports = _run_hosted(clean_plan, extra=extra)
    assert [(d.check, round(d.t, 1)) for d in reports] == [
        ("sudden-appearance", 8.0), ("heading", 12.0), ("heading", 16.0)]
    assert reports == found and det.counters["reported"] == 3
    assert {d.suspect for d in reports} == {ghost}


def test_the_overlap_of_a_car_inside_a_truck_is_whole():
    """F2MD's IoU cannot exceed the area ratio: a car inside a truck stays under 0.5.
    ``overlap`` is the IoU at the smaller footprint's size: the same for equal ones."""
    from catc.mbd.geometry import overlap

    car, truck = (0.0, 0.0, 0.0, 4.5, 1.8), (0.0, 1.0, 0.0, 10.85, 2.59)
    assert iou(car, truck) == pytest.approx(4.5 * 1.8 / (10.85 * 2.59))
    assert overlap(car, truck) == pytest.approx(1.0)
    half = (0.0, 2.25, 0.0, 4.5, 1.8)  # equal cars, half a length apart
    assert overlap(car, half) == pytest.approx(iou(car, half)) == pytest.approx(1 / 3)
    assert overlap(car, (0.0, 20.0, 0.0, 4.5, 1.8)) == 0.0


def test_a_ghost_behind_a_truck_raises_nothing_and_blames_nobody():
    """The dense NGSIM scene (host 232): ``rve run --attack ghost:start=5`` puts the ghost
    20 m ahead, 8 m beyond the front of a 10.9 m truck (216) 12 m ahead, and brakes it to
    a stop.  Behind the truck its first message is a weak sudden appearance, so it was
    tracked: it raised FCW and EEBL (26 ticks) before it ran into the host 3.5 s later,
    and, stopped and still sending, it got two honest cars that later drove through its
    place quarantined.  Now: in the host's path behind another vehicle it is an
    unconfirmed newcomer (no warning for 3 s); the truck driving through it is an
    intersection (the IoU of a car inside a truck is 0.29); and a quarantined sender is
    no witness against anybody."""
    from catc.attacks import Attacks, parse
    from hil.datasets import load

    (scene,) = load(f"scene:ngsim:{shared_path('ngsim-i80-pairs')}")
    the_plan = plan(scene, ChannelConfig(), 0)
    attacks = Attacks([parse("ghost:start=5")], the_plan)
    t0 = float(the_plan.events["t"][0])
    extra = [(float(e["time"]), inj.bsm) for e in the_plan.events if e["host"]
             for inj in attacks.injected(float(e["t"]))]
    ghost = Attacks.ID_BASE
    det, found, reports = _run_hosted(the_plan, extra=extra)
    first = next(d for d in found if d.suspect == ghost)
    assert first.check == "sudden-appearance" and first.t - t0 == pytest.approx(5.0)
    assert first.evidence["behind"] == temp_id("216") and not is_strong(first, det.config)
    assert ghost in det.muted(first.t + 0.1) and ghost not in det.muted(first.t + 3.0)
    caught = next(d for d in found if d.check == "intersection")
    assert caught.suspect == ghost and caught.other == temp_id("216")
    assert caught.t - t0 < 6.5 and det.quarantined(ghost, caught.t + 0.05)
    # of the others only the honest newcomers' weak sudden appearances: no report
    assert {d.check for d in found if d.suspect != ghost} == {"sudden-appearance"}
    assert {d.suspect for d in reports} == {ghost}


def test_muted_ids_raise_no_warning_and_no_event(clean_plan):
    """``SafetyApps.muted`` (what the OBU sets from ``MisbehaviorDetector.muted``): the
    default scenario's FCW, EEBL and the rest on the braking leader, then the same run with
    the leader muted: its warnings and events are gone, the others' stay."""
    from catc.apps import SafetyApps
    from catc.cam import CamConfig, ContextAwareMap
    from catc.replay import simulate

    def run(muted):
        apps = SafetyApps()
        apps.muted = muted
        cam = ContextAwareMap(CamConfig(predictor="ca", origin=clean_plan.table.origin),
                              apps)
        warned, events = [], []
        for snap in simulate(clean_plan, cam, wire=False):
            warned += [(snap.t, w.app, w.rv_id) for w in snap.warnings]
            events += [(e.app, e.rv_id) for e in snap.events]
        return warned, events

    lead = temp_id("lead")
    warned, events = run(frozenset())
    assert {w[1] for w in warned if w[2] == lead} >= {"fcw", "eebl"}
    quiet, quiet_events = run(frozenset({lead}))
    assert quiet == [w for w in warned if w[2] != lead]
    assert quiet_events == [e for e in events if e[1] != lead]
