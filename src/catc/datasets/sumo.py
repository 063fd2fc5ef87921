"""SUMO floating car data (FCD) -> :class:`~catc.mobility.MobilityTable`.

Two forms of the same data, both as written by Eclipse SUMO run with
``--fcd-output FILE --fcd-output.geo true`` (and preferably
``--fcd-output.acceleration true``):

* XML: ``<fcd-export><timestep time=".."><vehicle id x y angle type speed pos lane slope
  acceleration .../>...</timestep>...</fcd-export>``; persons and containers are ignored.
* CSV, as SUMO's ``tools/xml/xml2csv.py`` makes of that XML, or SUMO itself with
  ``--output.format csv``: a header ``timestep_time;vehicle_id;vehicle_x;...`` (columns in
  any order, separated by ``;``, ``,`` or a tab: the character after ``timestep_time``),
  one row per vehicle and time step.  Rows without a ``vehicle_id`` (empty time steps)
  are skipped.  Needed: ``timestep_time, vehicle_id, vehicle_x, vehicle_y,
  vehicle_speed``; used when present: ``vehicle_angle, vehicle_acceleration,
  vehicle_z`` (in the XML: ``angle, acceleration, z``).

Content detection (:func:`looks_like`): the XML root is ``<fcd-export`` (after the
declaration and comments: SUMO's header comment lists its options and is often longer
than 1 KB), or the CSV header starts with ``timestep_time``.

Choices:

* **Coordinates.**  With ``--fcd-output.geo`` SUMO writes x = longitude and y =
  latitude in degrees (WGS-84, via the network's projection), and ``z`` (when the network
  has elevations) in metres, taken as the ellipsoidal height (0 when absent).  Without
  it x/y are network metres, which this reader rejects: a value outside ±180 / ±90, a
  SUMO header that records no ``fcd-output.geo``, or positions that move ~1e5 times
  farther than the speed says (metres read as degrees) all raise "run SUMO with
  --fcd-output.geo true".
* **Vehicle centre.**  SUMO's position is the centre of the *front bumper*; BSM
  positions are vehicle centres, so every position is moved back by half the length
  (2.5 m) along the heading (below), in the ENU frame, and lat/lon are recomputed.
* **Heading** is SUMO's ``angle`` corrected to true north.  That angle is in degrees
  clockwise from the network's +y axis, i.e. from *grid* north of its projection, which
  differs from true north by the projection's meridian convergence (1.34 deg for UTM
  zone 33 at 46.89 N 16.84 E, the built-in scenarios); the FCD does not state it.  The
  reader measures it: the median, over every stretch of about 1 s where a vehicle moved
  at least 0.5 m per step with an unchanged angle, of the chord's direction minus the
  angle (``meta["grid_convergence_deg"]``; 1.349 deg on the shipped scenario, PROJ gives
  1.35 there).  The heading is angle + convergence, interpolated like the positions; it
  is SUMO's body direction, so it is kept while stopped and includes the sideways
  motion of a lane change.  Without angles (or no such stretch) the heading is the
  direction of motion of the front bumper (:func:`derive.heading_from_track`).  Yaw
  rate is derived from the heading (:func:`derive.yaw_rate_from_heading`).
* **Speed** is SUMO's ``speed`` (m/s).  **Acceleration** is SUMO's ``acceleration``
  (m/s²) when every sample of the vehicle has it, else derived from the speed.
* **Size.**  FCD carries no vehicle sizes: length 5.0 m and width 1.8 m, SUMO's
  default passenger vType (what the built-in scenarios use) for every vehicle.
* **Time.**  Timesteps must strictly increase (XML) and CSV rows must not go back in
  time.  The file's step is the median interval between its timesteps; a vehicle's
  samples more than 1.5 steps apart split it into pieces (the first keeps the id, later
  ones are ``ID#2``, ``ID#3``...), and a vehicle present for only part of the run is a
  track over its own span.  Each piece is linearly interpolated (positions in ENU, angle,
  speed, acceleration, height) onto the 10 Hz grid ``k * 0.1`` s within its span: exact for
  SUMO's 0.1 s steps, a resampling for others (SUMO's default step is 1 s).  Pieces of
  fewer than :data:`MIN_SAMPLES` grid samples (1 s) are dropped.
* **ENU origin**: the first position (as given, the front bumper) of the first vehicle
  of the first timestep, with its height.
* **Order and host.**  Tracks are in order of first appearance (file order within a
  timestep).  FCD cannot mark a host vehicle, so ``default_host`` is the vehicle whose
  id is ``host`` when there is one, else the last vehicle to depart (the latest first
  appearance; of several, the last in file order).
"""

from __future__ import annotations

import itertools
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable

import numpy as np

from catc.datasets import derive
from catc.geo import EnuFrame, enu_heading_deg, heading_diff_deg, wrap_deg_360
from catc.mobility import DT, MobilityTable, Track

__all__ = ["DEFAULT_LENGTH", "DEFAULT_WIDTH", "MIN_SAMPLES", "looks_like", "parse"]

#: SUMO's default passenger vType size (m): FCD does not carry sizes.
DEFAULT_LENGTH = 5.0
DEFAULT_WIDTH = 1.8
#: Pieces shorter than this many 10 Hz samples (1 s) are dropped.
MIN_SAMPLES = 10
#: The id that names the host vehicle.
HOST_ID = "host"
#: Steps at least this long (m), with an unchanged angle, estimate the grid convergence.
MIN_STEP_M = 0.5

_GEO_HINT = "run SUMO with --fcd-output.geo true"
#: The values read per sample, by their XML attribute name (CSV: ``vehicle_`` + name),
#: and the default of the optional ones (None: required).
_FIELDS: dict[str, float | None] = {
    "x": None, "y": None, "speed": None, "z": 0.0, "acceleration": math.nan,
    "angle": math.nan,
}
_PROVENANCE = {
    "t": "given: SUMO timestep time, on the 10 Hz grid",
    "lat": "derived: WGS-84 of the centre x/y (catc.geo.EnuFrame at the table origin)",
    "lon": "derived: WGS-84 of the centre x/y (catc.geo.EnuFrame at the table origin)",
    "x": ("derived: ENU east of SUMO's geo x/y (front bumper centre), moved back half the "
          "length along the heading to the vehicle centre"),
    "y": ("derived: ENU north of SUMO's geo x/y (front bumper centre), moved back half the "
          "length along the heading to the vehicle centre"),
    "speed": "given: SUMO speed (m/s)",
    "yaw_rate": derive.YAW_RATE_METHOD,
    "length": f"assumed: {DEFAULT_LENGTH:g} m, SUMO's default passenger vType (FCD has no size)",
    "width": f"assumed: {DEFAULT_WIDTH:g} m, SUMO's default passenger vType (FCD has no size)",
}

#: One vehicle's samples: field name (and "t") -> values in file order.
_Samples = dict[str, list[float]]


#: An XML declaration and comments (SUMO's header lists its options), then the root.
_FCD_ROOT = re.compile(r"\s*(<\?xml[^>]*\?>\s*)?(<!--.*?-->\s*)*<fcd-export\b", re.S)


def looks_like(text: str) -> bool:
    """SUMO FCD content: an XML document whose root is ``<fcd-export`` (after the
    declaration and comments, however long SUMO's header comment is), or a CSV whose
    header starts ``timestep_time``."""
    head = text.lstrip("\ufeff")
    return head.lstrip().startswith("timestep_time") or bool(_FCD_ROOT.match(head))


def _number(value: str | None, what: str, where: str, default: float | None) -> float:
    if value is None or value.strip() == "":
        if default is not None:
            return default
        raise ValueError(f"sumo: {where}: missing {what}")
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"sumo: {where}: bad number {what}={value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"sumo: {where}: {what} is not finite ({value!r})")
    return number


def _add(vehicles: dict[str, _Samples], vid: str, t: float, get: Callable[[str], str | None],
         where: str, prefix: str = "") -> None:
    """Append one sample of ``vid``; ``get(name)`` is the raw value of field ``name``."""
    values = {f: _number(get(prefix + f), prefix + f, where, d) for f, d in _FIELDS.items()}
    if not (-180.0 <= values["x"] <= 180.0 and -90.0 <= values["y"] <= 90.0):
        raise ValueError(f"sumo: {where}: x={values['x']:g} y={values['y']:g} are not lon/lat "
                         f"degrees (network metres?); {_GEO_HINT}")
    samples = vehicles.setdefault(vid, {f: [] for f in ("t", *_FIELDS)})
    samples["t"].append(t)
    for f, value in values.items():
        samples[f].append(value)


def _parse_xml(text: str) -> tuple[dict[str, _Samples], list[float]]:
    head = text[: text.find("<fcd-export")]
    if "<fcd-output value=" in head and 'fcd-output.geo value="true"' not in head:
        raise ValueError(f"sumo: the SUMO header records FCD output without geo; {_GEO_HINT}")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f"sumo: not well-formed XML ({exc})") from None
    if root.tag != "fcd-export":
        raise ValueError(f"sumo: not SUMO FCD output (root element <{root.tag}>, expected "
                         "<fcd-export>)")
    vehicles: dict[str, _Samples] = {}
    times: list[float] = []
    for n, step in enumerate(root.iter("timestep"), 1):
        t = _number(step.get("time"), "time", f"timestep {n}", None)
        if times and t <= times[-1]:
            raise ValueError(f"sumo: timestep {n}: time {t:g} is not after the previous "
                             f"timestep's {times[-1]:g}")
        times.append(t)
        seen: set[str] = set()
        for vehicle in step.iter("vehicle"):
            vid = vehicle.get("id") or ""
            if not vid or vid in seen:
                raise ValueError(f"sumo: timestep {n} (time {t:g}): "
                                 + (f"vehicle {vid!r} appears twice" if vid
                                    else "a vehicle without id"))
            seen.add(vid)
            _add(vehicles, vid, t, vehicle.get, f"timestep {n} (time {t:g}), vehicle {vid!r}")
    if not times:
        raise ValueError("sumo: no <timestep> elements")
    return vehicles, times


def _parse_csv(text: str) -> tuple[dict[str, _Samples], list[float]]:
    lines = text.splitlines()
    match = re.match(r"timestep_time([;,\t])", lines[0])
    if match is None:
        raise ValueError("sumo: not SUMO FCD CSV (the header must start with timestep_time "
                         "and a separator)")
    sep = match[1]
    header = [h.strip() for h in lines[0].split(sep)]
    needed = ["vehicle_id", *(f"vehicle_{f}" for f, d in _FIELDS.items() if d is None)]
    missing = [c for c in needed if c not in header]
    if missing:
        raise ValueError(f"sumo: CSV lacks column(s) {', '.join(missing)}")
    col = {name: j for j, name in enumerate(header)}
    vehicles: dict[str, _Samples] = {}
    times: list[float] = []
    seen: set[str] = set()
    for n, line in enumerate(lines[1:], 2):
        if not line.strip():
            continue
        cells = line.split(sep)
        cells += [""] * (len(header) - len(cells))

        def get(name: str, cells: list[str] = cells) -> str | None:
            return cells[col[name]] if name in col else None

        t = _number(get("timestep_time"), "timestep_time", f"row {n}", None)
        if times and t < times[-1]:
            raise ValueError(f"sumo: row {n}: time {t:g} is before the previous row's "
                             f"{times[-1]:g}")
        if not times or t > times[-1]:
            times.append(t)
            seen = set()
        vid = (get("vehicle_id") or "").strip()
        if not vid:
            continue  # an empty timestep (xml2csv writes its time alone)
        if vid in seen:
            raise ValueError(f"sumo: row {n}: vehicle {vid!r} appears twice at time {t:g}")
        seen.add(vid)
        _add(vehicles, vid, t, get, f"row {n}", "vehicle_")
    if not times:
        raise ValueError("sumo: no data rows")
    return vehicles, times


Arrays = dict[str, np.ndarray]


def _arrays(samples: _Samples, frame: EnuFrame) -> Arrays:
    """The samples as arrays, with the ENU position (e, n, u) of the front bumper."""
    a = {f: np.array(v, dtype=np.float64) for f, v in samples.items()}
    a["e"], a["n"], a["u"] = frame.to_enu(a["y"], a["x"], a["z"])
    return a


def _steps(a: Arrays, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per consecutive pair of samples: (east, north) displacement and 'same piece'."""
    return np.diff(a["e"]), np.diff(a["n"]), np.diff(a["t"]) <= 1.5 * step


def _check_moves_like_its_speed(data: dict[str, Arrays], step: float) -> None:
    """Metres read as degrees move ~1e5 times farther than the speed says: reject them."""
    ratios = []
    for a in data.values():
        de, dn, joined = _steps(a, step)
        moving = joined & (a["speed"][1:] >= 1.0)
        ratios.append(np.hypot(de, dn)[moving] / (a["speed"][1:] * np.diff(a["t"]))[moving])
    ratio = float(np.median(np.concatenate(ratios))) if any(r.size for r in ratios) else 1.0
    if ratio > 100.0:
        raise ValueError(f"sumo: positions move {ratio:.3g} times farther than the speeds "
                         f"say: x/y are not lon/lat degrees; {_GEO_HINT}")


def _grid_convergence(data: dict[str, Arrays], step: float) -> float | None:
    """Direction of motion minus SUMO angle (deg), median over straight moving stretches.

    SUMO's ``angle`` is measured from the network's +y axis, the grid north of its
    projection; this is the angle from true north to that grid north (the meridian
    convergence, constant over a scenario's few km).  The direction of motion is the
    chord over about 1 s (positions have 1 cm resolution), taken where the vehicle moved
    at least :data:`MIN_STEP_M` per step and kept its angle.  None without such stretches.
    """
    lag = max(1, round(1.0 / step))
    diffs = []
    for a in data.values():
        if len(a["t"]) <= lag:
            continue
        de, dn, joined = _steps(a, step)
        good = np.r_[0, np.cumsum(joined & (np.hypot(de, dn) >= MIN_STEP_M))]
        angle = a["angle"]
        ok = ((good[lag:] - good[:-lag] == lag) & np.isfinite(angle[lag:])
              & np.isfinite(angle[:-lag]))
        ok[ok] &= np.abs(heading_diff_deg(angle[lag:][ok], angle[:-lag][ok])) < 0.05
        course = enu_heading_deg(a["e"][lag:] - a["e"][:-lag], a["n"][lag:] - a["n"][:-lag])
        diffs.append(np.asarray(heading_diff_deg(np.asarray(course)[ok], angle[lag:][ok])))
    if not any(d.size for d in diffs):
        return None
    return float(np.median(np.concatenate(diffs)))


def _pieces(t: np.ndarray, step: float) -> list[slice]:
    breaks = np.flatnonzero(np.diff(t) > 1.5 * step) + 1
    bounds = [0, *breaks.tolist(), len(t)]
    return [slice(a, b) for a, b in itertools.pairwise(bounds)]


def _grid(t: np.ndarray) -> np.ndarray | None:
    """The 10 Hz grid times within ``[t[0], t[-1]]``, None when under MIN_SAMPLES."""
    first, last = math.ceil(t[0] / DT - 1e-6), math.floor(t[-1] / DT + 1e-6)
    if last - first + 1 < MIN_SAMPLES:
        return None
    return np.round(np.arange(first, last + 1) * DT, 6)


def _track(vehicle_id: str, a: Arrays, grid: np.ndarray, frame: EnuFrame,
           convergence: float | None, resampled: bool) -> Track:
    """The track of one piece ``a`` of a vehicle's samples (see the module doc)."""

    def on_grid(values: np.ndarray) -> np.ndarray:
        return np.interp(grid, a["t"], values)

    e, n, u, speed = on_grid(a["e"]), on_grid(a["n"]), on_grid(a["u"]), on_grid(a["speed"])
    if convergence is not None and np.isfinite(a["angle"]).all():
        unwrapped = np.unwrap(a["angle"], period=360.0)
        heading = np.asarray(wrap_deg_360(on_grid(unwrapped) + convergence))
        heading_method = (f"given: SUMO angle (deg cw from the network's grid north) plus the "
                          f"grid convergence {convergence:.3f} deg (median of direction of "
                          f"motion minus angle over the file's straight moving steps)")
    else:
        heading = derive.heading_from_track(e, n, speed)
        heading_method = derive.HEADING_METHOD + " (of the front bumper)"
    x = e - 0.5 * DEFAULT_LENGTH * np.sin(np.radians(heading))
    y = n - 0.5 * DEFAULT_LENGTH * np.cos(np.radians(heading))
    lat, lon, elev = frame.to_geodetic(x, y, u)
    given_accel = bool(np.isfinite(a["acceleration"]).all())
    provenance = {
        **_PROVENANCE,
        "heading": heading_method,
        "elev": ("given: SUMO z (m), taken as ellipsoidal height" if np.any(a["z"] != 0.0)
                 else "assumed: 0 m (the FCD has no z)"),
        "accel": ("given: SUMO acceleration (m/s^2)" if given_accel else derive.ACCEL_METHOD),
        "resampling": ("linear interpolation of the FCD's steps onto the 10 Hz grid"
                       if resampled else "none: the FCD is on the 10 Hz grid"),
    }
    return Track(
        vehicle_id=vehicle_id, t=grid, x=x, y=y, lat=lat, lon=lon, elev=elev, speed=speed,
        heading=heading,
        accel=on_grid(a["acceleration"]) if given_accel else derive.accel_from_speed(speed),
        yaw_rate=derive.yaw_rate_from_heading(heading), length=DEFAULT_LENGTH,
        width=DEFAULT_WIDTH, provenance=provenance)


def parse(text: str, name: str) -> MobilityTable:
    """Parse SUMO FCD contents (XML or CSV) into one table (see the module doc)."""
    body = text.lstrip("\ufeff").lstrip()
    if body.startswith("timestep_time"):
        vehicles, times = _parse_csv(body)
    elif body.startswith("<"):
        vehicles, times = _parse_xml(body)
    else:
        raise ValueError("sumo: not SUMO FCD output (neither XML nor a timestep_time CSV)")
    if not vehicles:
        raise ValueError("sumo: no vehicles in the FCD")
    if len(times) < 2:
        raise ValueError("sumo: fewer than 2 timesteps")
    step = float(np.median(np.diff(times)))
    first = next(iter(vehicles.values()))
    frame = EnuFrame(first["y"][0], first["x"][0], first["z"][0])
    data = {vid: _arrays(samples, frame) for vid, samples in vehicles.items()}
    _check_moves_like_its_speed(data, step)
    convergence = _grid_convergence(data, step)
    resampled = not (abs(step - DT) < 1e-6
                     and all(abs(t / DT - round(t / DT)) < 1e-6 for t in times))

    tracks: dict[str, Track] = {}
    departs: dict[str, float] = {}
    for vid, a in data.items():
        kept = [(p, g) for p in _pieces(a["t"], step) if (g := _grid(a["t"][p])) is not None]
        for i, (piece, grid) in enumerate(kept):
            key = vid if i == 0 else f"{vid}#{i + 1}"
            tracks[key] = _track(key, {f: v[piece] for f, v in a.items()}, grid, frame,
                                 convergence, resampled)
        if kept:
            departs[vid] = float(a["t"][0])
    if not tracks:
        raise ValueError(f"sumo: no vehicle is present for {MIN_SAMPLES * DT:g} s")
    if HOST_ID in tracks:
        host = HOST_ID
    else:
        latest = max(departs.values())
        host = [v for v, t0 in departs.items() if t0 == latest][-1]
    return MobilityTable(
        name=name, kind="sumo", origin=(frame.lat0, frame.lon0, frame.h0), tracks=tracks,
        default_host=host,
        meta={"fcd_step_s": step, "resampled": resampled,
              "grid_convergence_deg": convergence})
