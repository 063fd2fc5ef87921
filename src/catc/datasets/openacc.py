"""OpenACC (JRC) platoon CSV -> :class:`~catc.mobility.MobilityTable`.

Format (see the data's PROVENANCE.md): metadata lines ``Date``, ``Vehicle_order``,
``Number_of_vehicles``, ``ACC``, ``Distance_setting``, then the header
``Time,Speed1,E1,N1,Lon1,Lat1,Alt1,Speed2,...,IVS1,...`` and one row per 0.1 s.  Column
index k is the k-th name of ``Vehicle_order`` (leader first); indices may skip vehicles
that have no columns, and ``Number_of_vehicles`` is not used (it disagrees with the order
in some files).  Empty cells are missing samples; trailing commas are ignored.

Choices:

* Position truth is Lat/Lon (degrees WGS-84) and Alt.  The ENU origin is the first
  valid sample of the leader (the first vehicle in platoon order that has columns), with
  h0 its Alt.  The file's own E/N agree with these x/y up to a constant offset (a few
  cm over the ~700 m tracks).  Alt is passed through as ``elev``; the files do not say
  whether it is ellipsoidal or above sea level, which moves x/y by < 0.1 mm here.
* Speed is measured (GNSS Doppler).  Heading, acceleration and yaw rate are derived with
  :mod:`catc.datasets.derive` (Savitzky-Golay, 1 s window; heading held below 1 m/s).
* A sample is valid when Speed, Lat, Lon and Alt are all present.  Runs of at most
  0.5 s (5 samples) of invalid samples are linearly interpolated (speed, lat, lon, alt);
  longer runs split the vehicle into pieces: the first kept piece has the vehicle's
  name as id, later ones ``NAME#2``, ``NAME#3``...  Pieces shorter than 5 s are dropped.
* IVS (GNSS bumper-to-bumper spacing) is not used.  Length and width are unknown (NaN).
* ``default_host`` is the last vehicle in platoon order that has a track.
"""

from __future__ import annotations

import re

import numpy as np

from catc.datasets import derive
from catc.geo import EnuFrame
from catc.mobility import DT, MobilityTable, Track

#: Pieces shorter than this many samples (5 s) are dropped.
MIN_SAMPLES = 50
_FIELDS = ("Speed", "Lat", "Lon", "Alt")
_COLUMN = re.compile(r"(Speed|Lat|Lon|Alt)(\d+)")
_PROVENANCE = {
    "t": "measured: the file's Time (JRC common 10 Hz base)",
    "lat": "measured: GNSS Lat (deg WGS-84)",
    "lon": "measured: GNSS Lon (deg WGS-84)",
    "elev": "measured: GNSS Alt as given (datum not stated in the file)",
    "x": "derived: ENU east of lat/lon/elev (catc.geo.EnuFrame at the table origin)",
    "y": "derived: ENU north of lat/lon/elev (catc.geo.EnuFrame at the table origin)",
    "speed": "measured: GNSS Doppler speed",
    "heading": derive.HEADING_METHOD,
    "accel": derive.ACCEL_METHOD,
    "yaw_rate": derive.YAW_RATE_METHOD,
    "length": "unknown",
    "width": "unknown",
}


def _metadata(lines: list[str]) -> dict[str, list[str]]:
    return {cells[0].strip(): cells[1:] for cells in (line.split(",") for line in lines)}


def _table(lines: list[str], width: int) -> np.ndarray:
    """The data rows as a float array (empty cell -> NaN), ``width`` columns."""
    rows = [(line.split(",") + [""] * width)[:width] for line in lines if line.strip()]
    if not rows:
        raise ValueError("openacc: no data rows")
    cells = np.char.strip(np.array(rows, dtype=str))
    try:
        return np.where(cells == "", "nan", cells).astype(np.float64)
    except ValueError as exc:
        raise ValueError(f"openacc: bad number in the data rows ({exc})") from None


def _vehicle_columns(header: list[str], names: list[str]) -> dict[int, dict[str, int]]:
    """Vehicle index k -> {field: column} for the fields each track needs."""
    columns: dict[int, dict[str, int]] = {}
    for j, cell in enumerate(header):
        match = _COLUMN.fullmatch(cell.strip())
        if match:
            columns.setdefault(int(match[2]), {})[match[1]] = j
    for k, fields in columns.items():
        if not 1 <= k <= len(names):
            raise ValueError(f"openacc: column index {k} but Vehicle_order names {len(names)}")
        if len(fields) != len(_FIELDS):
            missing = sorted(set(_FIELDS) - set(fields))
            raise ValueError(f"openacc: vehicle {k} lacks columns {', '.join(missing)}")
    if not columns:
        raise ValueError("openacc: no vehicle columns (Speed<k>, Lat<k>, ...)")
    return dict(sorted(columns.items()))


def _track(vehicle_id: str, t: np.ndarray, data: np.ndarray, gaps: int, frame: EnuFrame) -> Track:
    """A track from (speed, lat, lon, alt) columns with ``gaps`` interpolated samples."""
    speed, lat, lon, alt = data.T
    x, y, _ = frame.to_enu(lat, lon, alt)
    return derive.track(
        vehicle_id, t, (x, y, lat, lon, alt), speed, None,
        {
            **_PROVENANCE,
            "gaps": f"{gaps} missing samples linearly interpolated (runs <= 0.5 s)",
        },
    )


def parse(text: str, name: str) -> MobilityTable:
    """Parse the contents of one OpenACC CSV file into a table (see the module doc)."""
    lines = text.lstrip("\ufeff").splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith("Time,")), None)
    if start is None:
        raise ValueError("openacc: no Time column")
    names = [n.strip() for n in _metadata(lines[:start]).get("Vehicle_order", []) if n.strip()]
    if not names:
        raise ValueError("openacc: no Vehicle_order line")
    if len(set(names)) != len(names):
        raise ValueError("openacc: duplicate names in Vehicle_order")
    header = lines[start].split(",")
    columns = _vehicle_columns(header, names)
    values = _table(lines[start + 1 :], len(header))
    t = np.round(values[:, 0], 3)
    bad = np.flatnonzero(np.abs(np.diff(t) - DT) > 1e-3)
    if len(bad):
        row = start + 2 + int(bad[0]) + 1  # 1-based line number of the offending row
        raise ValueError(f"openacc: line {row}: Time {t[bad[0] + 1]:g} after {t[bad[0]]:g} "
                         "breaks the strictly increasing 10 Hz grid")

    vehicles = {k: values[:, [fields[f] for f in _FIELDS]] for k, fields in columns.items()}
    valid = {k: np.isfinite(data).all(axis=1) for k, data in vehicles.items()}
    leader = next((k for k in vehicles if valid[k].any()), None)
    if leader is None:
        raise ValueError("openacc: no row has Speed, Lat, Lon and Alt of a vehicle")
    _, lat, lon, alt = vehicles[leader][np.argmax(valid[leader])]
    frame = EnuFrame(lat, lon, alt)

    tracks: dict[str, Track] = {}
    for k, data in vehicles.items():
        kept = [s for s in derive.pieces(valid[k]) if s.stop - s.start >= MIN_SAMPLES]
        for i, piece in enumerate(kept):
            vehicle_id = names[k - 1] if i == 0 else f"{names[k - 1]}#{i + 1}"
            filled = derive.fill_gaps(data[piece], valid[k][piece])
            gaps = int(np.count_nonzero(~valid[k][piece]))
            tracks[vehicle_id] = _track(vehicle_id, t[piece], filled, gaps, frame)
    if not tracks:
        raise ValueError("openacc: no vehicle has 5 s of valid samples")
    host = next(n for n in reversed(names) if n in tracks)
    return MobilityTable(
        name=name,
        kind="openacc",
        origin=(frame.lat0, frame.lon0, frame.h0),
        tracks=tracks,
        default_host=host,
    )
