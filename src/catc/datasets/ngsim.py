"""NGSIM I-80 leader/follower pairs CSV -> one :class:`~catc.mobility.MobilityTable` per pair.

Format (see the data's PROVENANCE.md): one row per pair and 0.1 s frame with the
follower's ``local_x`` (lateral, m from the left road edge), ``local_y`` (longitudinal, m,
position of the vehicle's *front*), size, ``v_vel``/``v_acc``, and the leader's
``preceding_local_y``, size, ``preceding_vel``/``preceding_acc`` (all metric, EMD-smoothed).

Choices:

* Road coordinates are laid on a straight, georeferenced reference line: its start is
  :data:`ORIGIN` (on eastbound I-80 in Emeryville, CA, near the Powell Street
  interchange, where the NGSIM study section begins; h0 = 0 is nominal) and it runs at
  :data:`AZIMUTH_DEG` (eastbound I-80 runs north-north-west there).  Position =
  origin + local_y along the azimuth + local_x to its right, in the ENU frame of the
  origin (:class:`catc.geo.EnuFrame`), converted to WGS-84.  This approximates the real
  road (which curves slightly) to some tens of metres; the geometry *between* vehicles is
  exact.  ``local_y`` is kept as given, so x/y are the vehicles' front centres.
* The leader has no lateral position in the data: it is placed at the follower's
  ``local_x`` at the same time (the pairs stay in one lane).
* Time is the dataset time ``frame_id * 0.1`` s (the ``time`` column is ``t - t[0]``
  except where frames skip, where that column is wrong).  Frame gaps of at most 5 frames
  are linearly interpolated; across longer gaps only the longest contiguous piece is kept
  (pair 1175-1167 skips 61 frames after 2.7 s, so its first 2.7 s are dropped).
* Speed and acceleration are the given (EMD-smoothed) values; heading and yaw rate are
  derived from the track (:mod:`catc.datasets.derive`; the heading is ~ the azimuth).
  Length and width come from the data.  ``default_host`` is the follower.
"""

from __future__ import annotations

import csv
import io
import math

import numpy as np

from catc.datasets import derive
from catc.geo import EnuFrame
from catc.mobility import DT, MobilityTable, Track

#: Start of the reference line: lat, lon (deg WGS-84), h (m, nominal).
ORIGIN = (37.8400, -122.2975, 0.0)
#: Direction of the reference line (deg cw from north): eastbound I-80 at Emeryville.
AZIMUTH_DEG = 347.0
#: Pairs (after gap handling) shorter than this many samples (5 s) are dropped.
MIN_SAMPLES = 50

_NUMERIC = (
    "frame_id", "local_x", "local_y", "v_length", "v_width", "v_vel", "v_acc",
    "preceding_local_y", "preceding_length", "preceding_width", "preceding_vel",
    "preceding_acc",
)  # fmt: skip
_IDS = ("pair_id", "vehicle_id", "preceding")
_LINE = (
    f"road line from {ORIGIN[0]:.4f} N {ORIGIN[1]:.4f} E at azimuth {AZIMUTH_DEG:g} deg "
    "(straight approximation of I-80), via catc.geo.EnuFrame"
)
_PROVENANCE = {
    "t": "measured: NGSIM frame_id * 0.1 s",
    "x": f"derived: local_y along / local_x across the {_LINE}; front centre",
    "y": f"derived: local_y along / local_x across the {_LINE}; front centre",
    "lat": "derived: x/y converted to WGS-84",
    "lon": "derived: x/y converted to WGS-84",
    "elev": "derived: x/y on the ENU plane of the nominal origin height (not the road's)",
    "heading": derive.HEADING_METHOD,
    "yaw_rate": derive.YAW_RATE_METHOD,
    "length": "measured: NGSIM vehicle length",
    "width": "measured: NGSIM vehicle width",
}
_FOLLOWER = {
    "speed": "measured: v_vel (video tracking, EMD-smoothed)",
    "accel": "measured: v_acc (video tracking, EMD-smoothed)",
}
_LEADER = {
    "speed": "measured: preceding_vel (video tracking, EMD-smoothed)",
    "accel": "measured: preceding_acc (video tracking, EMD-smoothed)",
    "x": f"derived: preceding_local_y along / the follower's local_x across the {_LINE}",
    "y": f"derived: preceding_local_y along / the follower's local_x across the {_LINE}",
}


def road_to_enu(along: np.ndarray, across: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Road coordinates (m along the line, m to its right) -> ENU (east, north) in m."""
    az = math.radians(AZIMUTH_DEG)
    return (
        along * math.sin(az) + across * math.cos(az),
        along * math.cos(az) - across * math.sin(az),
    )


def _columns(rows: list[list[str]], header: list[str]) -> dict[str, np.ndarray]:
    index = {name: j for j, name in enumerate(header)}
    missing = [c for c in (*_IDS, *_NUMERIC) if c not in index]
    if missing:
        raise ValueError(f"ngsim: missing columns {', '.join(missing)}")
    if any(len(row) != len(header) for row in rows):
        raise ValueError("ngsim: rows with a different number of cells than the header")
    cells = np.array(rows, dtype=str)
    data = {c: cells[:, index[c]] for c in _IDS}
    for c in _NUMERIC:
        try:
            data[c] = cells[:, index[c]].astype(np.float64)
        except ValueError as exc:
            raise ValueError(f"ngsim: bad number in column {c} ({exc})") from None
    return data


def _track(
    frame: EnuFrame,
    vehicle_id: str,
    t: np.ndarray,
    road: tuple[np.ndarray, np.ndarray],
    motion: tuple[np.ndarray, np.ndarray],
    size: tuple[float, float],
    provenance: dict[str, str],
) -> Track:
    """A track from road coordinates (along, across), (speed, accel) and (length, width)."""
    x, y = road_to_enu(*road)
    lat, lon, elev = frame.to_geodetic(x, y, np.zeros_like(x))
    speed, accel = motion
    return derive.track(vehicle_id, t, (x, y, lat, lon, elev), speed, accel,
                        {**_PROVENANCE, **provenance}, size)


def _vehicle_id(cell: str) -> str:
    """NGSIM ids are integers; accept "47" or "47.0"."""
    try:
        return str(int(float(cell)))
    except ValueError:
        return cell.strip()


def _pair(
    frame: EnuFrame, name: str, pair_id: str, data: dict[str, np.ndarray]
) -> MobilityTable | None:
    """One pair's rows -> a table, or None when less than 5 s survives gap handling."""
    frames = np.rint(data["frame_id"]).astype(np.int64)
    order = np.argsort(frames, kind="stable")
    frames = frames[order]
    if np.any(np.diff(frames) == 0):
        raise ValueError(f"ngsim: pair {pair_id} repeats a frame_id")
    valid = np.zeros(frames[-1] - frames[0] + 1, dtype=bool)
    valid[frames - frames[0]] = True
    piece = max(derive.pieces(valid), key=lambda s: s.stop - s.start)
    if piece.stop - piece.start < MIN_SAMPLES:
        return None
    grid = np.full((len(valid), len(_NUMERIC)), np.nan)
    grid[frames - frames[0]] = np.column_stack([data[c][order] for c in _NUMERIC])
    col = dict(zip(_NUMERIC, derive.fill_gaps(grid[piece], valid[piece]).T, strict=True))
    gaps = int(np.count_nonzero(~valid[piece]))
    note = {"gaps": f"{gaps} missing frames linearly interpolated (runs <= 0.5 s)"}
    t = (frames[0] + np.arange(piece.start, piece.stop)) * DT
    follower, leader = _vehicle_id(data["vehicle_id"][0]), _vehicle_id(data["preceding"][0])
    tracks = {
        leader: _track(
            frame,
            leader,
            t,
            road=(col["preceding_local_y"], col["local_x"]),
            motion=(col["preceding_vel"], col["preceding_acc"]),
            size=(col["preceding_length"][0], col["preceding_width"][0]),
            provenance={**_LEADER, **note},
        ),
        follower: _track(
            frame,
            follower,
            t,
            road=(col["local_y"], col["local_x"]),
            motion=(col["v_vel"], col["v_acc"]),
            size=(col["v_length"][0], col["v_width"][0]),
            provenance={**_FOLLOWER, **note},
        ),
    }
    return MobilityTable(
        name=f"{name}:{pair_id}",
        kind="ngsim",
        origin=ORIGIN,
        tracks=tracks,
        default_host=follower,
    )


def parse(text: str, name: str) -> list[MobilityTable]:
    """Parse the contents of an NGSIM pairs CSV: one table per pair, in file order."""
    rows = list(csv.reader(io.StringIO(text.lstrip("\ufeff"))))
    if not rows or not rows[0] or rows[0][0] != "pair_id":
        raise ValueError("ngsim: no pair_id header")
    body = [row for row in rows[1:] if row]
    if not body:
        raise ValueError("ngsim: no data rows")
    data = _columns(body, rows[0])
    pair_ids, first = np.unique(data["pair_id"], return_index=True)
    frame = EnuFrame(*ORIGIN)
    tables = []
    for pair_id in pair_ids[np.argsort(first)]:
        mask = data["pair_id"] == pair_id
        table = _pair(frame, name, str(pair_id), {c: v[mask] for c, v in data.items()})
        if table is not None:
            tables.append(table)
    return tables
