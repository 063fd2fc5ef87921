"""SUMO FCD reader (catc.datasets.sumo) and the built-in scenarios (rve scenario).

The shipped default scenario is read as is; fresh scenarios are generated with the
``eclipse-sumo`` wheel (skipped with the reason when it is absent), and SUMO's own
``tools/xml/xml2csv.py`` makes the CSV form of one.
"""

from __future__ import annotations

import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from pyproj import Proj

from catc import datasets
from catc.apps import SafetyApps
from catc.cam import CamConfig, ContextAwareMap
from catc.datasets import sumo
from catc.geo import EnuFrame, enu_heading_deg, heading_diff_deg
from catc.mobility import DT, MobilityTable
from catc.replay import run_offline, temp_id
from rve import scenario
from rve.cli import main as rve_main

SHIPPED = resources.files("hil").joinpath("scenarios", "highway-braking.fcd.xml")
FRAME = EnuFrame(46.89, 16.84, 0.0)


def shipped_text() -> str:
    return SHIPPED.read_text()


@pytest.fixture(scope="module")
def shipped() -> MobilityTable:
    return sumo.parse(shipped_text(), "highway-braking")


@pytest.fixture(scope="module")
def home() -> Path:
    try:
        return scenario.sumo_home()
    except scenario.SumoMissing as err:
        pytest.skip(str(err))


@pytest.fixture(scope="module")
def cut_in(home: Path, tmp_path_factory) -> tuple[str, str]:
    """A fresh 25 s cut-in scenario: (FCD XML, the CSV SUMO's xml2csv makes of it)."""
    xml = scenario.generate("cut-in", seed=1, duration=25.0)
    tmp = tmp_path_factory.mktemp("cut-in")
    (tmp / "fcd.xml").write_text(xml)
    subprocess.run([sys.executable, str(home / "tools" / "xml" / "xml2csv.py"),
                    str(tmp / "fcd.xml"), "-o", str(tmp / "fcd.csv")],
                   env=scenario._env(home), check=True, capture_output=True, timeout=60)
    return xml, (tmp / "fcd.csv").read_text()


def synthetic(vehicles: dict[str, list[tuple[float, float]]], step: float = 0.1,
              speed: float = 20.0, azimuth: float = 30.0, end: float = 4.0) -> str:
    """FCD XML of vehicles driving straight at ``speed`` along ``azimuth`` from
    46.89 N 16.84 E, each present over its (start, stop) spans (s)."""
    lines = ["<fcd-export>"]
    for t in np.round(np.arange(0.0, end + step / 2, step), 6):
        lines.append(f'  <timestep time="{t:.2f}">')
        for i, (vid, spans) in enumerate(vehicles.items()):
            if not any(a - 1e-9 <= t <= b + 1e-9 for a, b in spans):
                continue
            s = speed * t + 30.0 * i
            e, n = s * np.sin(np.radians(azimuth)), s * np.cos(np.radians(azimuth))
            lat, lon, _ = FRAME.to_geodetic(e, n, 0.0)
            lines.append(f'    <vehicle id="{vid}" x="{lon:.7f}" y="{lat:.7f}" '
                         f'angle="{azimuth:.2f}" type="car" speed="{speed:.2f}" '
                         f'acceleration="0.00"/>')
        lines.append("  </timestep>")
    return "\n".join([*lines, "</fcd-export>"]) + "\n"


# --- the reader on the shipped scenario ---------------------------------------------------


def test_shipped_default_scenario(shipped: MobilityTable):
    assert SHIPPED.is_file() and len(SHIPPED.read_bytes()) < 1_500_000
    assert shipped.kind == "sumo" and shipped.default_host == "host"
    assert len(shipped.tracks) == 17 and next(iter(shipped.tracks)) == "host"
    for track in shipped.tracks.values():
        np.testing.assert_allclose(np.diff(track.t), DT, atol=1e-9)
        assert 0.0 <= track.t[0] <= 0.3 and track.t[-1] == pytest.approx(49.9)
        assert (track.length, track.width) == (5.0, 1.8)
        assert track.provenance["accel"].startswith("given: SUMO acceleration")
    assert shipped.tracks["p3"].t[0] == pytest.approx(0.1)  # inserted one step late
    assert shipped.tracks["lead"].accel.min() == pytest.approx(-7.0)
    assert not shipped.meta["resampled"]
    # SUMO's angle is from grid north (UTM 33N): the reader adds the meridian convergence.
    origin = shipped.origin
    gamma = Proj("+proj=utm +zone=33 +ellps=WGS84").get_factors(
        origin[1], origin[0]).meridian_convergence
    assert shipped.meta["grid_convergence_deg"] == pytest.approx(gamma, abs=0.05)
    assert np.all(np.abs(shipped.tracks["host"].heading - (60.0 + gamma)) < 0.1)


def _check_kinematics(table: MobilityTable, max_heading_err: float) -> None:
    """Heading and speed agree with the positions while moving; lat/lon agree with ENU."""
    frame = EnuFrame(*table.origin)
    for track in table.tracks.values():
        e, n, _ = frame.to_enu(track.lat, track.lon, track.elev)
        np.testing.assert_allclose(e, track.x, atol=1e-6)
        np.testing.assert_allclose(n, track.y, atol=1e-6)
        de, dn = np.diff(track.x), np.diff(track.y)
        moving = track.speed[1:] > 5.0
        mid = track.heading[1:] + np.asarray(heading_diff_deg(track.heading[:-1],
                                                              track.heading[1:])) / 2
        course_err = np.abs(heading_diff_deg(enu_heading_deg(de, dn), mid))
        assert course_err[moving].max(initial=0.0) < max_heading_err, track.vehicle_id
        # SUMO moves each step by the new speed times the step (Euler).
        speed_err = np.abs(np.hypot(de, dn) / DT - track.speed[1:])
        assert speed_err[moving].max(initial=0.0) < 0.2, track.vehicle_id


def test_heading_speed_and_positions_agree_on_the_shipped_scenario(shipped):
    _check_kinematics(shipped, 1.5)


def test_positions_are_vehicle_centres_half_a_length_behind_sumos_front_bumper(shipped):
    root = ET.fromstring(shipped_text())
    host = shipped.tracks["host"]
    frame = EnuFrame(*shipped.origin)
    for step in list(root.iter("timestep"))[::50]:
        k = round(float(step.get("time")) / DT)
        front = next(v for v in step.iter("vehicle") if v.get("id") == "host")
        e, n, _ = frame.to_enu(float(front.get("y")), float(front.get("x")), 0.0)
        ahead = np.array([e - host.x[k], n - host.y[k]])
        assert np.hypot(*ahead) == pytest.approx(2.5, abs=0.02)
        assert float(heading_diff_deg(enu_heading_deg(*ahead), host.heading[k])) == (
            pytest.approx(0.0, abs=1.0))


def test_fcw_fires_when_the_leader_brakes_and_not_before(shipped):
    """``lead`` brakes at 7 m/s² from t = 20.0 s; ``host``'s driver reacts at 21.0 s.

    Measured: the FCW (CAMP Linear, CA predictor) starts on ``lead`` at 20.0 s (the first
    BSM that carries the braking), ends at 21.0 s when host brakes hard too, and starts
    again from 23.0 to 24.0 s as host closes in on the stopping lead.  No FCW before.
    """
    cam = ContextAwareMap(CamConfig(predictor="ca", origin=shipped.origin), SafetyApps())
    snaps = list(run_offline(shipped, cam, host_id="host"))
    starts = [e for s in snaps for e in s.events if e.app == "fcw" and e.kind == "start"]
    warned = [s.t for s in snaps if any(w.app == "fcw" for w in s.warnings)]
    brake = scenario.BRAKE_T
    assert starts and starts[0].rv_id == temp_id("lead")
    assert brake <= starts[0].t_start <= brake + 1.0
    assert min(warned) >= brake  # nothing in the 20 s (>= 15 s) of steady following
    assert {e.rv_id for e in starts} == {temp_id("lead")}


# --- fresh scenarios: XML and CSV ----------------------------------------------------------


def test_xml_and_xml2csv_csv_read_the_same(cut_in):
    xml, csv = cut_in
    assert csv.startswith("timestep_time;")
    assert datasets.detect_kind(xml) == datasets.detect_kind(csv) == "sumo"
    a, b = (datasets.parse("sumo", text, "cut-in")[0] for text in (xml, csv))
    assert list(a.tracks) == list(b.tracks) and a.origin == b.origin
    for vid, ta in a.tracks.items():
        tb = b.tracks[vid]
        for field in ("t", "x", "y", "lat", "lon", "speed", "heading", "accel", "yaw_rate"):
            np.testing.assert_allclose(getattr(ta, field), getattr(tb, field), atol=1e-9)
    _check_kinematics(a, 2.5)  # lane change: SUMO's angle includes the sideways motion
    cutter = a.tracks["cutter"]
    assert cutter.yaw_rate.min() < -1.0  # the cut-in to the left shows in the yaw rate


def test_fcw_fires_on_the_cut_in(cut_in):
    table = sumo.parse(cut_in[0], "cut-in")
    cam = ContextAwareMap(CamConfig(predictor="ca", origin=table.origin), SafetyApps())
    starts = [e for s in run_offline(table, cam) for e in s.events
              if e.app == "fcw" and e.kind == "start"]
    assert [e.rv_id for e in starts] == [temp_id("cutter")]
    assert scenario.CUT_T <= starts[0].t_start <= scenario.CUT_T + 3.5


def test_coarser_steps_are_resampled_onto_the_10hz_grid(shipped):
    """The shipped run thinned to SUMO's default 1 s step: linear interpolation is exact
    at constant speed and within a·dt²/8 (0.9 m at 7 m/s²) while braking."""
    text = re.sub(r'<timestep time="\d+\.[1-9]0">.*?</timestep>\s*', "", shipped_text(),
                  flags=re.S)
    coarse = sumo.parse(text, "coarse")
    assert coarse.meta["resampled"] and coarse.meta["fcd_step_s"] == pytest.approx(1.0)
    for vid, fine in shipped.tracks.items():
        c = coarse.tracks[vid]
        np.testing.assert_allclose(np.diff(c.t), DT, atol=1e-9)
        k = np.searchsorted(fine.t, c.t[0])
        err = np.hypot(c.x - fine.x[k:k + len(c)], c.y - fine.y[k:k + len(c)])
        assert err.max() < 1.0, vid
        assert err[c.t < 19.0].max() < 0.05, vid


def test_partial_spans_gaps_and_default_host():
    text = synthetic({"a": [(0.0, 1.5), (2.5, 4.0)], "b": [(1.0, 3.0)], "c": [(2.0, 2.5)]})
    table = sumo.parse(text, "s")
    assert list(table.tracks) == ["a", "a#2", "b"]  # c: 0.6 s, too short
    assert table.tracks["a#2"].t[0] == pytest.approx(2.5)
    assert (table.tracks["b"].t[0], table.tracks["b"].t[-1]) == (pytest.approx(1.0),
                                                                 pytest.approx(3.0))
    assert table.default_host == "b"  # the last to depart
    assert table.origin == pytest.approx((46.89, 16.84, 0.0), abs=1e-7)
    assert table.meta["grid_convergence_deg"] == pytest.approx(0.0, abs=0.05)
    _check_kinematics(table, 0.5)
    assert sumo.parse(synthetic({"a": [(0, 4)], "host": [(0, 2)]}), "s").default_host == "host"


# --- errors ---------------------------------------------------------------------------------

GOOD = synthetic({"a": [(0.0, 1.0)]}, end=1.0)
CSV = "timestep_time;vehicle_id;vehicle_x;vehicle_y;vehicle_speed\n"


@pytest.mark.parametrize("text, message", [
    ("<routes><vehicle id='a'/></routes>", "not SUMO FCD output (root element <routes>"),
    ("<fcd-export><timestep", "not well-formed XML"),
    ("hello", "neither XML nor a timestep_time CSV"),
    (GOOD.replace(' speed="20.00"', "", 1), "vehicle 'a': missing speed"),
    (GOOD.replace('time="0.20"', 'time="0.05"'), "timestep 3: time 0.05 is not after"),
    (GOOD.replace('x="16.84', 'x="1684', 1), "are not lon/lat degrees (network metres?); "
     "run SUMO with --fcd-output.geo true"),
    ('<!--\n<fcd-output value="f.xml"/>\n-->\n' + GOOD,
     "records FCD output without geo; run SUMO with --fcd-output.geo true"),
    # Small network metres pass the range test, but move 2 m a step at 20 m/s "in degrees".
    ("<fcd-export>" + "".join(
        f'<timestep time="{k / 10:.1f}"><vehicle id="a" x="{2.0 * k:.1f}" y="5.0" '
        f'speed="20.0"/></timestep>' for k in range(15)) + "</fcd-export>",
     "times farther than the speeds say"),
    (GOOD.replace("</timestep>", '<vehicle id="a"/></timestep>', 1),
     "vehicle 'a' appears twice"),
    (CSV + "0.0;a;16.84;46.89;20\n0.1;a;16.84;46.89;20\n0.0;b;16.84;46.89;20\n",
     "row 4: time 0 is before the previous row's 0.1"),
    ("timestep_time;vehicle_id;vehicle_x;vehicle_y\n0.0;a;16.84;46.89\n",
     "CSV lacks column(s) vehicle_speed"),
    (CSV + "0.0;a;16.84;46.89;fast\n", "row 2: bad number vehicle_speed='fast'"),
    (CSV + "0.0;a;16.84;46.89;20\n", "fewer than 2 timesteps"),
])
def test_bad_fcd_is_one_line_value_error(text, message):
    with pytest.raises(ValueError) as err:
        sumo.parse(text, "bad")
    assert message in str(err.value) and "\n" not in str(err.value)
    assert str(err.value).startswith("sumo: ")


# --- rve scenario ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(scenario.SCENARIOS))
def test_rve_scenario_is_deterministic_and_readable(name, home, tmp_path, capsys):
    a, b = tmp_path / "a.xml", tmp_path / "b.xml"
    for out in (a, b):
        assert rve_main(["scenario", name, "--seed", "7", "--out", str(out)]) == 0
    assert a.read_bytes() == b.read_bytes()
    text = a.read_text()
    assert "generated on" not in text and str(tmp_path) not in text
    table = sumo.parse(text, name)
    assert table.default_host == "host"
    assert max(len(t) for t in table.tracks.values()) == round(
        scenario.SCENARIOS[name].duration / DT)
    if name == "intersection":  # turns: the centre slips sideways of the body axis
        _check_kinematics(MobilityTable(
            name, "sumo", table.origin,
            {k: t for k, t in table.tracks.items() if k in ("host", "q1")}), 3.0)
    else:
        _check_kinematics(table, 2.5)
    assert capsys.readouterr().err == ""


def test_rve_scenario_seed_changes_the_traffic(home, tmp_path):
    outs = [tmp_path / f"{seed}.xml" for seed in (1, 2)]
    for seed, out in zip((1, 2), outs, strict=True):
        assert rve_main(["scenario", "--seed", str(seed), "--duration", "5",
                         "--out", str(out)]) == 0
    assert outs[0].read_bytes() != outs[1].read_bytes()


def _sumo_version(fcd: str) -> tuple[int, ...]:
    """The SUMO version in an FCD file's header ("sumo 1.28.0", "sumo Version 1.20.0")."""
    found = re.search(r"Eclipse SUMO sumo (?:Version )?v?(\d+(?:\.\d+)+)", fcd)
    assert found, fcd[:200]
    return tuple(int(x) for x in found[1].split("."))


def _records(fcd: str) -> dict[tuple[str, str], dict[str, str]]:
    """Every vehicle record of an FCD file, by (time, id)."""
    root = ET.fromstring(fcd)
    return {(step.get("time"), v.get("id")): dict(v.attrib)
            for step in root.iter("timestep") for v in step.iter("vehicle")}


def test_the_shipped_file_is_what_the_readme_command_makes(home, shipped):
    """`rve scenario` (the README's command) makes the shipped scenario again with any SUMO
    pyproject.toml accepts (>= 1.20): a header without its date, the same vehicle records
    at the same steps, each on the same lane with the same speed, acceleration and
    heading to SUMO's 2 decimals, and positions within 2 cm (PROJ versions round the
    7th decimal of a degree differently: SUMO 1.20 against the shipped 1.28, 1 cm).
    Byte for byte with the SUMO that made the shipped file."""
    text = shipped_text()
    fresh_text = scenario.generate("highway-braking", seed=0)
    assert _sumo_version(fresh_text) >= (1, 20)
    assert "generated on" not in fresh_text and "generated by Eclipse SUMO" in fresh_text
    if _sumo_version(fresh_text) == _sumo_version(text):
        assert fresh_text == text
    ours, theirs = _records(fresh_text), _records(text)
    assert ours.keys() == theirs.keys()
    for key, rec in theirs.items():
        got = ours[key]
        assert (got["lane"], got["type"]) == (rec["lane"], rec["type"]), key
        for field in ("speed", "acceleration", "angle", "pos"):
            assert abs(float(got[field]) - float(rec[field])) <= 0.011, (key, field)
    fresh = sumo.parse(fresh_text, "highway-braking")
    assert list(fresh.tracks) == list(shipped.tracks) and fresh.origin == pytest.approx(
        shipped.origin, abs=2e-7)
    for vid, old in shipped.tracks.items():
        new = fresh.tracks[vid]
        np.testing.assert_allclose(new.t, old.t, atol=1e-9)
        assert np.hypot(new.x - old.x, new.y - old.y).max() < 0.02, vid


@pytest.mark.parametrize("argv, message", [
    (["scenario", "nope", "--out", "x"], "invalid choice: 'nope'"),
    (["scenario"], "the following arguments are required: --out"),
    (["scenario", "--out", "x", "--duration", "0"], "must be 0.1 to 3600 s"),
    (["scenario", "--out", "x", "--seed", "one"], "invalid int value"),
])
def test_rve_scenario_bad_arguments_are_one_line_exit_2(argv, message, capsys):
    assert rve_main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_rve_scenario_without_sumo_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    def missing() -> Path:
        raise scenario.SumoMissing("Eclipse SUMO is not installed: pip install "
                                   "'catc-hil[sumo]'")

    monkeypatch.setattr(scenario, "sumo_home", missing)
    assert rve_main(["scenario", "--out", str(tmp_path / "x.xml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install 'catc-hil[sumo]'" in err
    assert not (tmp_path / "x.xml").exists()


def test_rve_scenario_unwritable_out_is_exit_2(home, tmp_path, capsys):
    assert rve_main(["scenario", "--duration", "1", "--out",
                     str(tmp_path / "no" / "x.xml")]) == 2
    assert capsys.readouterr().err.startswith("rve scenario: cannot write")
