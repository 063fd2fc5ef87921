"""Tests for catc.datasets.scene and the ``scene:`` dataset spec: every vehicle of a
multi-trip file in one table with one host.

The real NGSIM I-80 pairs are read from ../shared/data (skipped when absent) and the merge
is checked against the CSV read independently of catc; synthetic pairs pin the junction,
clock and error rules, and a synthetic table pins how ``plan``/``simulate`` treat RVs
present for only part of the host's time.
"""

from __future__ import annotations

import csv
import functools
import io
import math
from dataclasses import replace

import numpy as np
import pytest

from catc.cam import CamConfig, ContextAwareMap
from catc.channel import ChannelConfig
from catc.datasets import ngsim, scene
from catc.geo import EnuFrame
from catc.mobility import DT, MobilityTable, Track
from catc.replay import plan, simulate, temp_id
from hil.datasets import DatasetError, load, load_files, load_table
from tests.conftest import shared_path
from tests.test_datasets import NGSIM_HEADER

NGSIM_DIR = "ngsim-i80-pairs"
NGSIM_CSV = "i80_0400-0415_leader_follower_pairs.csv"
#: The scene's host by the default rule (most neighbour samples within 300 m).
HOST = "232"


@functools.cache
def _csv_rows() -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(shared_path(NGSIM_DIR, NGSIM_CSV).read_text())))


@functools.cache
def _tables() -> list[MobilityTable]:
    return ngsim.parse(shared_path(NGSIM_DIR, NGSIM_CSV).read_text(), "i80")


@functools.cache
def _merged() -> MobilityTable:
    return scene.merge(_tables(), "i80")


@functools.cache
def _scene() -> MobilityTable:
    return load_table(f"scene:ngsim:{shared_path(NGSIM_DIR)}", None)


def _along_across(tr: Track) -> tuple[np.ndarray, np.ndarray]:
    """ENU -> road coordinates of the NGSIM reference line (inverse of road_to_enu)."""
    az = math.radians(ngsim.AZIMUTH_DEG)
    return (tr.x * math.sin(az) + tr.y * math.cos(az),
            tr.x * math.cos(az) - tr.y * math.sin(az))


# --- the real NGSIM I-80 file ---------------------------------------------------------------

def test_ngsim_scene_has_every_vehicle_once():
    rows = _csv_rows()
    ids = {r["vehicle_id"] for r in rows} | {r["preceding"] for r in rows}
    merged = _merged()
    assert len(ids) == 167 and set(merged.tracks) == ids
    assert merged.meta["scene"]["trips"] == len(_tables()) == 95
    assert merged.meta["scene"]["dropped_samples"] == 0
    for tr in merged.tracks.values():  # one clock: frame_id * 0.1 s, no gap
        frames = np.rint(tr.t / DT)
        np.testing.assert_allclose(tr.t, frames * DT, atol=1e-9)
        assert np.all(np.diff(frames) == 1)


def test_ngsim_pieces_agree_where_they_overlap():
    """A vehicle that is a follower in one pair and the leader in another has identical
    longitudinal position, speed, acceleration and size in both; only its lateral
    position differs (a leader's is its follower's), by up to 2.61 m."""
    info = _merged().meta["scene"]
    assert info["overlap"]["samples"] == 9565
    diff = info["overlap"]["max_disagreement"]
    assert diff["speed"] == diff["accel"] == diff["length"] == diff["width"] == 0.0
    assert diff["position_m"] == pytest.approx(2.61, abs=1e-6)
    # the CSV itself, without catc: follower rows against leader rows of the same frame
    follower, leader = {}, {}
    for r in _csv_rows():
        f = int(float(r["frame_id"]))
        follower[r["vehicle_id"], f] = (float(r["local_y"]), float(r["v_vel"]),
                                       float(r["local_x"]))
        leader[r["preceding"], f] = (float(r["preceding_local_y"]),
                                     float(r["preceding_vel"]), float(r["local_x"]))
    both = follower.keys() & leader.keys()
    assert len(both) == 9565
    d = np.array([np.subtract(follower[k], leader[k]) for k in both])
    assert np.abs(d[:, :2]).max() == 0.0 and np.abs(d[:, 2]).max() == pytest.approx(2.61)


def test_ngsim_merged_tracks_keep_the_pairs_values():
    """A measured (follower) sample is kept exactly; a leader's sample (its lateral
    position borrowed from its follower) is shifted only near a junction: sideways by at
    most the 2.61 m the pieces disagree, along the road by the junction's extrapolation
    (a few mm)."""
    merged = _merged()
    info = merged.meta["scene"]
    assert info["junctions"] == 24 and 1.0 < info["max_junction_shift_m"] < 1.2
    for table in _tables():
        for vid, piece in table.tracks.items():
            tr = merged.tracks[vid]
            i = np.rint((piece.t - tr.t[0]) / DT).astype(int)
            along, across = _along_across(tr)
            p_along, p_across = _along_across(piece)
            np.testing.assert_array_equal(tr.speed[i], piece.speed)
            np.testing.assert_array_equal(tr.accel[i], piece.accel)
            measured = vid == table.default_host
            assert np.abs(along[i] - p_along).max() <= (1e-6 if measured else 0.02)
            assert np.abs(across[i] - p_across).max() <= (1e-6 if measured else 2.62)
            lat, lon, _ = EnuFrame(*merged.origin).to_geodetic(tr.x, tr.y, 0.0)
            np.testing.assert_allclose([lat, lon], [tr.lat, tr.lon], atol=1e-9)
    # no step left at a junction: the largest lateral move in 0.1 s is the data's own
    worst = max(np.abs(np.diff(_along_across(tr)[1])).max(initial=0.0)
                for tr in merged.tracks.values())
    assert worst < 0.5


def test_ngsim_scene_host_and_span():
    s = _scene()
    info = s.meta["scene"]
    assert s.default_host == HOST and info["host"] == HOST
    assert info["host_rule"] == "most neighbour samples"
    assert s.name == f"{NGSIM_CSV[:-4]}:scene:{HOST}"
    assert info["rvs"] == len(s.tracks) - 1 == 45
    assert info["duration_s"] == pytest.approx(67.8)
    assert info["rvs_within_radius"] == {"mean": pytest.approx(17.39, abs=0.01), "max": 25}
    host = s.tracks[HOST]
    spans = np.array([(tr.t[0], tr.t[-1]) for tr in s.tracks.values()])
    assert spans[:, 0].min() >= host.t[0] - 1e-9 and spans[:, 1].max() <= host.t[-1] + 1e-9
    partial = sum(1 for tr in s.tracks.values() if len(tr) < len(host))
    assert partial >= 30  # most RVs enter or leave the data during the run
    names = list(s.tracks)  # the host right after the vehicle ahead of it in its pair
    assert names[names.index(HOST) - 1] == "216"


def test_host_choice_is_deterministic_and_follows_the_rule():
    merged = _merged()
    sums = {v: int(scene.neighbours(merged, v).sum()) for v in merged.tracks}
    assert scene.choose_host(merged) == HOST == max(sums, key=sums.__getitem__)
    reordered = replace(merged, tracks=dict(reversed(merged.tracks.items())))
    assert scene.choose_host(reordered) == HOST
    again = scene.scene(list(reversed(_tables())), "i80")
    assert again.default_host == HOST and set(again.tracks) == set(_scene().tracks)
    given = load_table(f"scene:ngsim:{shared_path(NGSIM_DIR)}?host=2121", None)
    assert given.default_host == "2121" and given.meta["scene"]["host_rule"] == "given"
    assert given.meta["scene"]["duration_s"] == pytest.approx(74.0)


def test_plan_and_simulate_over_the_ngsim_scene():
    s = _scene()
    the_plan = plan(s, ChannelConfig(), 0)
    ev = the_plan.events
    assert the_plan.host_id == HOST and len(the_plan.vehicles) == 46
    for k, vid in enumerate(the_plan.vehicles):  # every sample once, at its own time
        mine = ev[ev["vehicle"] == k]
        assert len(mine) == len(s.tracks[vid])
        np.testing.assert_array_equal(np.sort(mine["t"]), s.tracks[vid].t)
    first = {temp_id(v): float(tr.t[0]) for v, tr in s.tracks.items()}
    cam = ContextAwareMap(CamConfig(predictor="ca", origin=s.origin))
    seen: set[int] = set()
    ticks = 0
    offset = None  # the CAM's clock is the host's secMark (minutes dropped)
    for snap in simulate(the_plan, cam, wire=False):
        ticks += 1
        offset = float(s.tracks[HOST].t[0]) - snap.t if offset is None else offset
        for tid in snap.ids.tolist():
            if tid not in seen:
                seen.add(tid)
                assert snap.t + offset >= first[tid] - 1e-6  # no RV before it is in the data
    assert ticks == len(s.tracks[HOST])
    # every RV gets a track but 469, in the data for the run's last sample only
    assert {v for v, tr in s.tracks.items() if len(tr) == 1} == {"469"}
    assert seen == {temp_id(v) for v in s.tracks if v not in (HOST, "469")}


# --- the rules, on synthetic pairs ------------------------------------------------------------

def _row(pair: str, follower: str, leader: str, f: int, x: float, y: float, gap: float,
         v: float = 8.0) -> str:
    return (f"{pair},0.0,6.0,{follower},{f},{x},{y},4.5,1.8,2,{v},0.0,1,{leader},{gap},2.5,"
            f"{y + gap},4.8,1.9,2,{v},0.0")


def _pairs(chain_x: float = 2.4, second: range = range(100, 180)) -> str:
    """Pair 2-1 (frames 100-179) and pair 3-2 (``second``): vehicle 2 is the follower of
    the first and the leader of the second; its lateral position there is 3's
    (``chain_x``), while the first pair measures it at 2.4 m."""
    rows = [_row("2-1", "2", "1", f, 2.4, 0.8 * (f - 100), 20.0) for f in range(100, 180)]
    rows += [_row("3-2", "3", "2", f, chain_x, 0.8 * (f - 100) - 20.0, 20.0) for f in second]
    return NGSIM_HEADER + "\n" + "\n".join(rows) + "\n"


def test_merge_dedups_and_prefers_the_pairs_own_vehicle():
    tables = ngsim.parse(_pairs(chain_x=3.4), "s")
    merged = scene.merge(tables, "s")
    assert list(merged.tracks) == ["1", "2", "3"]
    two = merged.tracks["2"]
    assert len(two) == 80  # both pieces cover frames 100-179: one track
    np.testing.assert_allclose(two.x, tables[0].tracks["2"].x, atol=1e-9)  # measured wins
    info = merged.meta["scene"]
    assert info["overlap"]["samples"] == 80 and info["junctions"] == 0
    assert info["overlap"]["max_disagreement"]["position_m"] == pytest.approx(1.0)
    assert merged.meta["ahead"] == {"2": "1", "3": "2"}


def test_a_junction_is_faded_not_stepped():
    # vehicle 2: measured (pair 2-1) for frames 100-179, then only as 3's leader, 1 m off
    tables = ngsim.parse(_pairs(chain_x=3.4, second=range(150, 260)), "s")
    merged = scene.merge(tables, "s")
    two = merged.tracks["2"]
    assert len(two) == 160 and merged.meta["scene"]["junctions"] == 1
    assert merged.meta["scene"]["max_junction_shift_m"] == pytest.approx(1.0, abs=1e-6)
    along, across = _along_across(two)
    np.testing.assert_allclose(np.diff(along), 0.8, atol=1e-9)
    steps = np.abs(np.diff(across))
    assert steps.max() == pytest.approx(1.0 / scene.TAPER_SAMPLES, rel=1e-6)
    np.testing.assert_allclose(across[:80], across[0], atol=1e-9)  # measured part untouched
    np.testing.assert_allclose(across[80 + scene.TAPER_SAMPLES:], across[-1], atol=1e-9)
    assert abs(across[-1] - across[0]) == pytest.approx(1.0, abs=1e-9)
    assert "merged from 2" in two.provenance["scene"]


def test_longest_run_kept_across_a_long_gap():
    tables = ngsim.parse(_pairs(second=range(200, 300)), "s")  # 2: frames 100-179, 200-299
    merged = scene.merge(tables, "s")
    assert len(merged.tracks["2"]) == 100 and merged.tracks["2"].t[0] == pytest.approx(20.0)
    assert merged.meta["scene"]["dropped_samples"] == 80


def test_clip_gives_partial_rvs_and_default_host_rule():
    tables = ngsim.parse(_pairs(second=range(150, 260)), "s")
    s = scene.scene(tables, "s", host="1")
    assert s.default_host == "1" and s.name == "s:scene:1"
    assert {v: len(tr) for v, tr in s.tracks.items()} == {"1": 80, "2": 80, "3": 30}
    assert s.tracks["3"].t[0] == pytest.approx(15.0) and s.tracks["3"].t[-1] == pytest.approx(17.9)
    chosen = scene.scene(tables, "s")
    assert chosen.default_host == "2"  # longest present, and 1 and 3 near it


def test_merge_refuses_other_clocks_and_kinds():
    (table,) = ngsim.parse(_pairs(second=range(0)), "s")
    tr = table.tracks["2"]
    off = replace(table, name="t", tracks={"9": replace(tr, vehicle_id="9", t=tr.t + 0.03)})
    with pytest.raises(ValueError, match="off the common 10 Hz clock by 30 ms"):
        scene.merge([table, off], "s")
    with pytest.raises(ValueError, match="kind openacc do not share one clock"):
        scene.merge([replace(table, kind="openacc")], "s")
    with pytest.raises(ValueError, match="no vehicle '7'"):
        scene.scene([table], "s", host="7")


def test_a_trip_in_another_frame_is_moved_into_the_first():
    (table,) = ngsim.parse(_pairs(second=range(0)), "s")
    moved = replace(table, name="t", origin=(37.85, -122.30, 0.0),
                    tracks={"9": replace(table.tracks["1"], vehicle_id="9", x=table.tracks["1"].x
                                         + 1e4)})  # x/y in its own frame: wrong here
    merged = scene.merge([table, moved], "s")
    np.testing.assert_allclose(merged.tracks["9"].x, table.tracks["1"].x, atol=1e-6)


# --- plan() over RVs present for part of the host's time (synthetic) -------------------------

def _straight(vid: str, t: np.ndarray, x0: float, frame: EnuFrame) -> Track:
    x = x0 + 10.0 * (t - t[0])
    y = np.zeros_like(t)
    lat, lon, elev = frame.to_geodetic(x, y, 0.0)
    n = len(t)
    return Track(vid, t, x, y, np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(elev),
                 np.full(n, 10.0), np.full(n, 90.0), np.zeros(n), np.zeros(n), 4.5, 1.8)


def test_plan_with_rvs_of_partial_span():
    """The host drives 0-10 s; RV "early" is there 0-3 s, "late" 6-12 s (past the host's
    end).  plan gives each RV its own samples, the channel's distance comes from the host
    interpolated at the RV's times (np.interp holds the host's last position after its
    end), and simulate tracks each RV only once it is in the data (and its track
    confirmed); samples after the host's last one never reach a tick (a scene cuts them
    off: :func:`scene.clip`)."""
    frame = EnuFrame(*ngsim.ORIGIN)
    t = np.round(np.arange(0, 101) * DT, 9)
    host = _straight("h", t, 0.0, frame)
    early = _straight("early", t[:31], 30.0, frame)
    late = _straight("late", np.round(np.arange(60, 121) * DT, 9), 160.0, frame)
    table = MobilityTable("p", "sumo", ngsim.ORIGIN, {"early": early, "late": late, "h": host},
                          default_host="h")
    # distance model on: beyond 300 m a message is lost, so the distances show in the plan
    cfg = ChannelConfig(distance=True)
    the_plan = plan(table, cfg, 0)
    ev = the_plan.events
    late_ev = ev[ev["vehicle"] == the_plan.vehicles.index("late")]
    assert len(late_ev) == len(late) and late_ev["t"].min() == pytest.approx(6.0)
    # late is 100 m ahead of the host while both drive; after 10 s the host "stops" at its
    # last position, so late's distance grows 10 m per second: 100 m at 10 s, 120 at 12 s
    dist = np.hypot(late.x - np.interp(late.t, host.t, host.x), 0.0)
    assert dist[:41].max() == pytest.approx(100.0) and dist[-1] == pytest.approx(120.0)
    cam = ContextAwareMap(CamConfig(predictor="ca", origin=table.origin))
    present = {}
    for snap in simulate(plan(table, ChannelConfig(), 0), cam, wire=False):
        for tid in snap.ids[snap.fresh].tolist():
            present.setdefault(tid, []).append(snap.t)
    assert 6.0 <= min(present[temp_id("late")]) <= 6.5  # once its track is confirmed
    assert max(present[temp_id("late")]) == pytest.approx(10.0)  # the host's last tick
    assert max(present[temp_id("early")]) == pytest.approx(3.0)
    clipped = scene.clip(table, "h")
    assert clipped.tracks["late"].t[-1] == pytest.approx(10.0) and len(clipped.tracks) == 3


# --- the scene: spec ----------------------------------------------------------------------------

def test_scene_spec_errors(tmp_path):
    (tmp_path / "a.csv").write_text(_pairs())
    # all three have two neighbours all the time: a tie, the first wins
    assert [t.name for t in load(f"scene:{tmp_path / 'a.csv'}")] == ["a:scene:1"]
    assert len(load_files(f"scene:ngsim:{tmp_path}?host=3")) == 1
    cases = {
        f"scene:{tmp_path}?host=": "no vehicle after",
        f"scene:{tmp_path}?host=9": "no vehicle '9'",
        f"scene:{tmp_path / 'nope.csv'}": "no such file",
        f"scene:scene:{tmp_path}": "a scene of a scene",
    }
    for spec, message in cases.items():
        with pytest.raises(DatasetError, match=message) as info:
            load(spec)
        assert "\n" not in str(info.value)
    (tmp_path / "b.csv").write_text(_pairs())
    with pytest.raises(DatasetError, match=r"trips of one file; .* has 2 \(a.csv, b.csv\)"):
        load(f"scene:{tmp_path}")
    with pytest.raises(DatasetError, match="has no trip 'x'"):
        load_table(f"scene:{tmp_path / 'a.csv'}", "x")


def test_scene_of_a_scenario_keeps_its_host():
    s = load_table("scene:scenario:highway-braking", None)
    plain = load_table("scenario:highway-braking", None)
    assert s.default_host == plain.default_host == "host"
    assert s.meta["scene"]["host_rule"] == "the trip's host"
    assert [t.name for t in load("scenario:highway-braking")] == [plain.name]
