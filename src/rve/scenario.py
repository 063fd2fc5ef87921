"""``rve scenario``: built-in traffic scenarios, generated with Eclipse SUMO.

Each scenario is a road network (plain SUMO node and edge XML in ``hil/scenarios``,
georeferenced with a ``<location>`` element: UTM zone 33N, net (0, 0) at 46.890000 N
16.840000 E, at the ZalaZONE proving ground in Zalaegerszeg, Hungary; the roads are
synthetic, not the track's layout), a seeded route file written here, and for the
scripted manoeuvres a TraCI controller.  :func:`generate` builds the network with
``netconvert`` in a temporary directory, runs ``sumo`` at 0.1 s steps and returns its FCD
output in geo coordinates (x = lon, y = lat, 7 decimals = 1e-7 deg, the J2735 lat/lon
unit) with accelerations: what :mod:`catc.datasets.sumo` reads.

SUMO comes from the ``eclipse-sumo`` wheel (``pip install 'catc-hil[sumo]'``).  Its
location is found without importing it (``import sumo`` sets ``SUMO_HOME`` and
``PROJ_LIB`` in this process's environment); the binaries get ``SUMO_HOME``, and
``PROJ_LIB`` / ``PROJ_DATA`` pointing at the wheel's own ``data/proj``, in their own
environment only, so the geo conversion uses SUMO's PROJ database and pyproj in this
process is left alone.  TraCI talks to ``sumo`` over TCP on 127.0.0.1.

Determinism: for a given name, seed and duration the output is the same file byte for
byte.  The seed draws the speeds, headways, positions and departure times of the route
file and is passed to ``sumo --seed`` (the drivers have no random imperfection, sigma 0,
so SUMO itself draws nothing today); SUMO's header comment is kept without its
generation date, TraCI port and temporary paths.  A shorter ``duration`` cuts the run.

Every vehicle is 5.0 m x 1.8 m (SUMO's passenger default, what the reader assumes),
follows the Krauss model with sigma 0, and on the motorway changes lane only when a
script says so (TraCI lane change mode 0).  Lane changes take 2 s of sideways motion
(``--lanechange.duration``; SUMO's default jumps a lane in one step).  The host
vehicle's id is ``host``; where a hazard starts, its driver reacts after 1.0 s
(:data:`REACTION_S`: TraCI holds its speed, ignoring the car ahead, until then):
SUMO's drivers otherwise react within one 0.1 s step, before any warning could help.

``highway-braking`` (default, 50 s)
    A straight 3-lane motorway running 61.3 deg from true north (ENE) from 46.8900 N
    16.8400 E.  A platoon of six cars (``lead``, ``host``, ``p2``..``p5``) in the
    middle lane at 26-29 m/s with time headways of 1.0-1.5 s; slower traffic in the
    right lane (22-25 m/s), faster in the left (31-34 m/s).  At t = 20.0 s ``lead``
    brakes at 7 m/s² to a stop (TraCI ``setSpeed 0``, its deceleration set to 7 m/s²);
    ``host`` right behind it reacts at 21.0 s and brakes at about 7 m/s², stopping
    2.5 m behind it.  At t = 32 s ``lead`` drives off again.  About 1.9 km of road.
``cut-in`` (40 s)
    The same motorway.  ``host`` drives in the middle lane at 26-28 m/s, 2 s behind
    ``front``; ``cutter``, 4-6 m/s slower in the right lane, is being overtaken.  When
    its rear is 20 m ahead of ``host``'s front (t ~ 15.2 s) it changes into the middle
    lane regardless of the gap (TraCI ``changeLane``) and is across the lane line at
    t ~ 16.9 s; ``host`` brakes 1 s later.
``intersection`` (60 s)
    A signalised crossroads centred on 46.8900 N 16.8400 E (300 m arms, two lanes each
    way, 50 km/h).  ``host`` approaches from the south in the left lane behind two
    cars; its light is red until t = 33 s (netconvert's program, started at the
    east-west green for 30 s), so it stops in the queue while cross traffic runs
    east-west through the junction in front of it.  Then it drives straight through,
    with oncoming traffic and left-turners yielding to it.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DEFAULT", "SCENARIOS", "SumoMissing", "add_arguments", "command", "generate",
           "sumo_home"]

#: SUMO's step: the 10 Hz grid of the mobility table, so no resampling is needed.
STEP = 0.1
#: Decimals of the FCD's lon/lat (1e-7 deg = 1.1 cm, the J2735 unit) and other values.
PRECISION_GEO = 7
PRECISION = 2
#: SUMO's default FCD attributes without ``slope`` (flat roads), plus the acceleration.
FCD_ATTRIBUTES = "x,y,angle,type,speed,pos,lane,acceleration"


class SumoMissing(RuntimeError):
    """Eclipse SUMO (the ``eclipse-sumo`` wheel) is not installed."""


@dataclass(frozen=True)
class Scenario:
    """One built-in scenario (see the module docstring)."""

    name: str
    summary: str  # a few words for --help
    network: str  # <network>.nod.xml / <network>.edg.xml in hil/scenarios
    duration: float  # s, the default length
    routes: Callable[[np.random.Generator], str]  # the seeded .rou.xml text
    #: Makes the run's TraCI script: called before every step with (connection, time).
    control: Callable[[], Callable[[Any, float], None]]
    #: No vehicle changes lane by itself (TraCI lane change mode 0 from its departure).
    keep_lanes: bool = True
    sumo_options: tuple[str, ...] = ()


# --- route files ------------------------------------------------------------------------

#: Every vehicle: SUMO's passenger size, no driver imperfection (sigma 0: smooth tracks).
_CAR = ('length="5.0" width="1.8" minGap="2.5" accel="2.6" decel="4.5" emergencyDecel="9.0" '
        'sigma="0"')
#: Lane speeds (m/s): SUMO's desired speed is speedFactor times the lane's.
MOTORWAY_SPEED = 36.11
CITY_SPEED = 13.89


def _vtype(vid: str, tau: float = 1.0) -> str:
    return f'    <vType id="{vid}" {_CAR} tau="{tau:.2f}"/>'


def _vehicle(vid: str, vtype: str, route: str, lane: int | str, pos: float, speed: float,
             depart: float = 0.0, desired: float | None = None,
             lane_speed: float = MOTORWAY_SPEED) -> str:
    factor = (desired or speed) / lane_speed
    return (f'    <vehicle id="{vid}" type="{vtype}" route="{route}" depart="{depart:.1f}" '
            f'departLane="{lane}" departPos="{pos:.1f}" departSpeed="{speed:.2f}" '
            f'speedFactor="{factor:.4f}"/>')


def _routes(lines: list[str]) -> str:
    return "<routes>\n" + "\n".join(lines) + "\n</routes>\n"


def _background(rng: np.random.Generator, lane: int, count: int, speed: tuple[float, float],
                span: tuple[float, float], prefix: str) -> list[str]:
    """``count`` motorway cars of type ``bg`` in ``lane``, one per equal slot of ``span``
    (m, the front's position along the edge) at a seeded place in it, at seeded speeds."""
    slot = (span[1] - span[0]) / count
    return [_vehicle(f"{prefix}{i}", "bg", "motorway", lane,
                     span[1] - (i + rng.uniform(0.0, 0.5)) * slot, float(rng.uniform(*speed)))
            for i in range(count)]


#: The host driver's reaction time (s): its speed is held this long after a hazard starts.
REACTION_S = 1.0
#: SUMO speed modes: every check (the default), and every check but the safe speed.
SPEED_MODE_ALL = 31
SPEED_MODE_UNSAFE = 30


def _at(t: float, when: float) -> bool:
    return abs(t - when) < STEP / 2


def _hold_speed(conn: Any, vid: str) -> None:
    """The driver has not reacted yet: keep the current speed, whatever is ahead."""
    conn.vehicle.setSpeedMode(vid, SPEED_MODE_UNSAFE)
    conn.vehicle.setSpeed(vid, conn.vehicle.getSpeed(vid))


def _release(conn: Any, vid: str) -> None:
    conn.vehicle.setSpeed(vid, -1.0)
    conn.vehicle.setSpeedMode(vid, SPEED_MODE_ALL)


# highway-braking ---------------------------------------------------------------------------

PLATOON = ("lead", "host", "p2", "p3", "p4", "p5")
BRAKE_T = 20.0
BRAKE_DECEL = 7.0
RESUME_T = 32.0


def _highway_braking_routes(rng: np.random.Generator) -> str:
    v0 = float(rng.uniform(26.0, 29.0))
    headways = rng.uniform(1.0, 1.5, len(PLATOON) - 1)
    lines = [_vtype("bg"), _vtype("lead")]
    lines += [_vtype(f"t{vid}", h) for vid, h in zip(PLATOON[1:], headways, strict=True)]
    lines.append('    <route id="motorway" edges="motorway"/>')
    pos = 600.0
    lines.append(_vehicle("lead", "lead", "motorway", 1, pos, v0))
    for vid, h in zip(PLATOON[1:], headways, strict=True):
        pos -= 5.0 + 2.5 + v0 * h  # length + minGap + the time gap
        lines.append(_vehicle(vid, f"t{vid}", "motorway", 1, pos, v0, desired=v0 + 3.0))
    lines += _background(rng, 0, 6, (22.0, 25.0), (150.0, 1100.0), "r")
    lines += _background(rng, 2, 5, (31.0, 34.0), (0.0, 500.0), "l")
    return _routes(lines)


def _highway_braking_control() -> Callable[[Any, float], None]:
    def control(conn: Any, t: float) -> None:
        if _at(t, BRAKE_T):
            conn.vehicle.setDecel("lead", BRAKE_DECEL)
            conn.vehicle.setSpeed("lead", 0.0)
            _hold_speed(conn, "host")
        elif _at(t, BRAKE_T + REACTION_S):
            _release(conn, "host")
        elif _at(t, RESUME_T):
            conn.vehicle.setDecel("lead", 4.5)
            conn.vehicle.setSpeed("lead", -1.0)

    return control


# cut-in ------------------------------------------------------------------------------------

#: The cutter starts its lane change when its rear is this far (m) ahead of host's front.
#: Host's driver reacts REACTION_S after the cutter crosses the lane line (its speed is
#: held from the start of the lane change until then).
CUT_GAP = 20.0
CUT_T = 15.0  # s, about when that happens (the start positions are set for it)
#: Lane changes take this long (s), moving sideways; SUMO's default 0 jumps a lane at once.
LANE_CHANGE_S = 2.0
_LANE_CHANGE_OPTION = ("--lanechange.duration", f"{LANE_CHANGE_S}")


def _cut_in_routes(rng: np.random.Generator) -> str:
    v = float(rng.uniform(26.0, 28.0))
    slower = v - float(rng.uniform(4.0, 6.0))
    host = 300.0
    cutter = host + 5.0 + CUT_GAP + (v - slower) * CUT_T
    lines = [_vtype("bg"), _vtype("car"), '    <route id="motorway" edges="motorway"/>',
             _vehicle("front", "car", "motorway", 1, host + 7.5 + 2.0 * v, v),
             _vehicle("host", "car", "motorway", 1, host, v),
             _vehicle("f1", "car", "motorway", 1, host - 7.5 - 1.5 * v, v, desired=v + 2.0),
             _vehicle("f2", "car", "motorway", 1, host - 2 * (7.5 + 1.5 * v), v,
                      desired=v + 2.0),
             _vehicle("cutter", "car", "motorway", 0, cutter, slower)]
    lines += [_vehicle(f"r{i}", "bg", "motorway", 0, cutter - 40.0 * (i + 1) - rng.uniform(0, 10),
                       slower) for i in range(2)]
    lines += _background(rng, 2, 3, (31.0, 34.0), (0.0, 400.0), "l")
    return _routes(lines)


def _cut_in_control() -> Callable[[Any, float], None]:
    state: dict[str, float] = {}

    def control(conn: Any, t: float) -> None:
        if "crossed" in state:
            if _at(t, state["crossed"] + REACTION_S):
                _release(conn, "host")
        elif "started" in state:
            if conn.vehicle.getLaneIndex("cutter") == 1:
                state["crossed"] = t
        elif {"cutter", "host"} <= set(conn.vehicle.getIDList()):
            gap = (conn.vehicle.getLanePosition("cutter") - 5.0
                   - conn.vehicle.getLanePosition("host"))
            if gap <= CUT_GAP:
                state["started"] = t
                conn.vehicle.changeLane("cutter", 1, 10.0)  # lane change mode 0: forced
                _hold_speed(conn, "host")

    return control


# intersection ------------------------------------------------------------------------------

#: The east-west green at the start (s); netconvert's program then runs on (3 s yellow,
#: 42 s north-south green, ...), so host's light turns green at 33 s.
EW_GREEN_S = 30.0
#: Phase indices of netconvert's program for the crossroads: 0 = north-south green,
#: 2 = east-west green.
EW_PHASE = 2
ARM = 300.0  # m, the length of each approach
_ROUTES = {"sn": "south_in north_out", "ns": "north_in south_out", "ew": "east_in west_out",
           "we": "west_in east_out", "ne": "north_in east_out", "ws": "west_in south_out"}


def _intersection_routes(rng: np.random.Generator) -> str:
    lines = [_vtype("car")]
    lines += [f'    <route id="{r}" edges="{edges}"/>' for r, edges in _ROUTES.items()]
    vehicles: list[tuple[float, str]] = []
    v = 13.0

    def arrive(vid: str, route: str, at: float, lane: str = "best") -> None:
        """A car reaching the stop line at time ``at`` (s) when nothing holds it up."""
        depart, pos = max(0.0, at - ARM / v), max(0.0, ARM - v * at)
        vehicles.append((depart, _vehicle(vid, "car", route, lane, pos, v, depart,
                                          lane_speed=CITY_SPEED)))

    # Host in the left lane of the south approach behind two cars, two more behind it.
    for vid, at in (("q0", 11.0), ("q1", 14.0), ("host", 17.0), ("b0", 24.0), ("b1", 30.0)):
        arrive(vid, "sn", at + rng.uniform(-0.5, 0.5), "1")
    # Cross traffic both ways while the east-west light is green: in front of host.
    for i, at in enumerate(np.arange(3.0, EW_GREEN_S - 2.0, 4.0)):
        arrive(f"e{i}", "ew", at + rng.uniform(-1.0, 1.0))
        arrive(f"w{i}", "we", at + 2.0 + rng.uniform(-1.0, 1.0))
    # For host's green: oncoming traffic, left-turners that must yield to host, and a
    # right-turner from the west.
    for i, route in enumerate(("ns", "ne", "ns", "ne", "ns")):
        arrive(f"n{i}", route, 31.0 + 3.0 * i + rng.uniform(0.0, 1.5))
    arrive("t0", "ws", 36.0 + rng.uniform(0.0, 3.0))
    lines += [line for _, line in sorted(vehicles, key=lambda d: d[0])]
    return _routes(lines)


def _intersection_control() -> Callable[[Any, float], None]:
    def control(conn: Any, t: float) -> None:
        if _at(t, 0.0):
            conn.trafficlight.setPhase("centre", EW_PHASE)
            conn.trafficlight.setPhaseDuration("centre", EW_GREEN_S)

    return control


SCENARIOS: dict[str, Scenario] = {
    s.name: s for s in (
        Scenario("highway-braking",
                 "a motorway platoon, the car ahead of host brakes to a stop at 7 m/s² at 20 s",
                 "highway", 50.0, _highway_braking_routes, _highway_braking_control),
        Scenario("cut-in", "a slower car cuts in 20 m ahead of host on the motorway at ~15 s",
                 "highway", 40.0, _cut_in_routes, _cut_in_control,
                 sumo_options=_LANE_CHANGE_OPTION),
        Scenario("intersection",
                 "a signalised crossroads, host waits at red while cross traffic passes",
                 "crossing", 60.0, _intersection_routes, _intersection_control,
                 keep_lanes=False, sumo_options=_LANE_CHANGE_OPTION),
    )
}
DEFAULT = "highway-braking"


# --- running SUMO -----------------------------------------------------------------------

def sumo_home() -> Path:
    """The ``eclipse-sumo`` wheel's SUMO_HOME (:class:`SumoMissing` when not installed)."""
    spec = importlib.util.find_spec("sumo")
    if spec is None or not spec.submodule_search_locations:
        raise SumoMissing("Eclipse SUMO is not installed: pip install 'catc-hil[sumo]'")
    home = Path(next(iter(spec.submodule_search_locations)))
    if not (home / "bin" / "sumo").is_file():
        raise SumoMissing(f"no sumo binary in {home / 'bin'}: pip install 'catc-hil[sumo]'")
    return home


def _env(home: Path) -> dict[str, str]:
    proj = str(home / "data" / "proj")
    return {**os.environ, "SUMO_HOME": str(home), "PROJ_LIB": proj, "PROJ_DATA": proj}


def _traci(home: Path):
    """SUMO's own TraCI client, from its tools directory (an installed one goes first)."""
    tools = str(home / "tools")
    if tools not in sys.path:
        sys.path.append(tools)
    try:
        import traci
    except ImportError:
        raise SumoMissing(f"no TraCI in {tools}: pip install 'catc-hil[sumo]'") from None
    return traci


def _run(cmd: list[str], env: dict[str, str], what: str) -> None:
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        lines = [ln for ln in (done.stderr + done.stdout).splitlines() if "Error" in ln]
        raise RuntimeError(f"{what} failed: {lines[0] if lines else done.returncode}")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _simulate(scenario: Scenario, net: Path, rou: Path, fcd: Path, seed: int,
              duration: float, home: Path, env: dict[str, str]) -> None:
    """Run ``sumo`` under the scenario's TraCI script, writing the FCD to ``fcd``."""
    steps = round(duration / STEP)
    log = fcd.with_suffix(".log")
    cmd = [str(home / "bin" / "sumo"), "-n", str(net), "-r", str(rou),
           "--step-length", f"{STEP}", "--begin", "0", "--end", f"{steps * STEP:.1f}",
           "--seed", str(seed), "--fcd-output", str(fcd), "--fcd-output.geo", "true",
           "--fcd-output.acceleration", "true", "--fcd-output.attributes", FCD_ATTRIBUTES,
           "--precision", str(PRECISION), "--precision.geo", str(PRECISION_GEO),
           "--collision.action", "warn", "--no-step-log", "true",
           "--duration-log.disable", "true", "--log", str(log), *scenario.sumo_options,
           "--remote-port", str(_free_port())]
    traci = _traci(home)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # TraCI prints its retries
            conn = traci.connect(int(cmd[-1]), numRetries=200, host="127.0.0.1", proc=proc,
                                 waitBetweenRetries=0.05)
        control = scenario.control()
        try:
            for k in range(steps):
                control(conn, round(k * STEP, 1))
                conn.simulationStep()
                if scenario.keep_lanes:
                    for vid in conn.simulation.getDepartedIDList():
                        conn.vehicle.setLaneChangeMode(vid, 0)
        finally:
            conn.close()
        proc.wait(timeout=60)
    except (traci.TraCIException, traci.FatalTraCIError) as err:
        raise RuntimeError(f"sumo (TraCI): {err}") from None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    messages = log.read_text().splitlines() if log.exists() else []
    bad = [m for m in messages if m.startswith("Error") or "collision" in m.lower()]
    if proc.returncode != 0 or bad:
        raise RuntimeError(f"sumo: {bad[0] if bad else f'exit status {proc.returncode}'}")


def _clean_header(text: str, tmp: Path) -> str:
    """SUMO's header comment without its generation date and the temporary paths."""
    # "on 2026-11-27T22:02:12 by" (SUMO 1.28), "on 2026-11-27 22:02:12 by" (1.20)
    text = re.sub(r"<!-- generated on [^\n]*? by ", "<!-- generated by ", text, count=1)
    text = re.sub(r"\n\n *<traci_server>.*?</traci_server>\n", "\n", text, count=1, flags=re.S)
    return text.replace(str(tmp) + os.sep, "")


def generate(name: str = DEFAULT, seed: int = 0, duration: float | None = None) -> str:
    """The FCD XML (geo, with accelerations) of scenario ``name``; see the module doc."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r} (known: {', '.join(SCENARIOS)})")
    scenario = SCENARIOS[name]
    duration = scenario.duration if duration is None else float(duration)
    if not (STEP <= duration <= 3600.0):
        raise ValueError(f"duration must be 0.1 to 3600 s, got {duration:g}")
    home = sumo_home()
    env = _env(home)
    data = resources.files("hil").joinpath("scenarios")
    with tempfile.TemporaryDirectory(prefix="rve-scenario-") as tmpdir:
        tmp = Path(tmpdir)
        for ext in ("nod.xml", "edg.xml"):
            shutil.copyfile(str(data.joinpath(f"{scenario.network}.{ext}")),
                            tmp / f"{scenario.network}.{ext}")
        net = tmp / f"{scenario.network}.net.xml"
        _run([str(home / "bin" / "netconvert"), "--node-files",
              str(tmp / f"{scenario.network}.nod.xml"), "--edge-files",
              str(tmp / f"{scenario.network}.edg.xml"), "-o", str(net)], env, "netconvert")
        rou = tmp / f"{name}.rou.xml"
        rou.write_text(scenario.routes(np.random.default_rng(seed)))
        fcd = tmp / f"{name}.fcd.xml"
        _simulate(scenario, net, rou, fcd, seed, duration, home, env)
        return _clean_header(fcd.read_text(), tmp)


# --- the command ------------------------------------------------------------------------

def _duration(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not STEP <= value <= 3600.0:
        raise argparse.ArgumentTypeError(f"must be 0.1 to 3600 s, got {text}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``rve scenario``."""
    p.add_argument("name", nargs="?", default=DEFAULT, choices=list(SCENARIOS), metavar="NAME",
                   help=f"the scenario (default {DEFAULT}): "
                        + "; ".join(f"{s.name}: {s.summary}" for s in SCENARIOS.values()))
    p.add_argument("--out", required=True, metavar="FILE",
                   help="where to write the FCD XML (catc dataset kind sumo)")
    p.add_argument("--seed", type=int, default=0, metavar="N",
                   help="seed of the traffic (speeds, headways, positions) and of sumo "
                        "--seed; the same seed gives the same file (default 0)")
    p.add_argument("--duration", type=_duration, metavar="S",
                   help="simulated seconds (default the scenario's: "
                        + ", ".join(f"{s.name} {s.duration:g}" for s in SCENARIOS.values())
                        + ")")


def command(args: argparse.Namespace) -> int:
    """``rve scenario``: generate, then write ``--out``; the exit status."""
    try:
        text = generate(args.name, args.seed, args.duration)
    except SumoMissing as err:
        print(f"rve scenario: {err}", file=sys.stderr)
        return 2
    except (RuntimeError, OSError, subprocess.SubprocessError) as err:
        print(f"rve scenario: {err}", file=sys.stderr)
        return 1
    try:
        Path(args.out).write_text(text)
    except OSError as err:
        print(f"rve scenario: cannot write {args.out}: {err.strerror}", file=sys.stderr)
        return 2
    return 0
