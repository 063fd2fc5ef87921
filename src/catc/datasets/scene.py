"""One dense scene from a multi-vehicle file: every vehicle of its trips in ONE table.

A dataset file of several trips (the NGSIM leader/follower pairs: one trip per pair) holds
more traffic than any one trip: the same period of the same road, a vehicle of one pair
driving next to those of others.  :func:`scene` puts all of it into one
:class:`~catc.mobility.MobilityTable` with one host, so that a run sees every vehicle the
host would have heard (``scene:`` dataset specs, :mod:`hil.datasets`).

* **Clock and frame.**  The trips must share the dataset's clock: kinds in
  :data:`SHARED_CLOCK` (NGSIM: ``frame_id * 0.1`` s for every pair of a file; SUMO: the
  simulation time).  Every sample must lie on one 10 Hz grid (within 1 ms), else
  ValueError.  The frame is the first trip's ENU origin; a trip with another origin is
  moved into it through its WGS-84 positions (NGSIM pairs all share
  :data:`catc.datasets.ngsim.ORIGIN`, so nothing moves there).
* **One track per vehicle id.**  A vehicle may be in several trips (an NGSIM car is the
  follower of one pair and the leader of the next).  Its samples are the union of its
  pieces on the grid; where pieces overlap, the piece of the trip whose ``default_host``
  it is wins (the NGSIM follower: its lateral position is measured, while a leader is
  placed at its follower's lateral position), then the earlier trip.  How much the
  overlapping samples disagree is measured (``meta["scene"]["overlap"]``).  Runs of at
  most :data:`catc.datasets.derive.MAX_GAP` missing samples are interpolated; of longer
  gaps only the longest contiguous run is kept, like the readers do.
* **Junctions.**  Where consecutive samples come from different pieces, the positions may
  step (NGSIM: up to ~1 m sideways, where a measured lateral position meets a leader's
  borrowed one).  The lower-ranked side is shifted to continue the other one (each
  side's one-sample step, averaged) and the shift fades linearly to zero over
  :data:`TAPER_SAMPLES` (3 s) or that side's stretch, whichever is shorter; lat/lon follow.
  A merged track whose heading was derived gets it (and its yaw rate) derived again from
  the merged positions (:mod:`catc.datasets.derive`); speed and acceleration are the
  pieces' (NGSIM: identical where they overlap).
* **Host.**  ``host`` when given, else :func:`choose_host`: the vehicle with the most
  neighbour samples (other vehicles within :data:`RADIUS_M` of it, summed over its
  samples: long present and in dense traffic); of several, the first in order; the
  trip's own ``default_host`` when the file has one trip (a SUMO scenario).  (The
  vehicle present longest is a poor host in NGSIM I-80: 2121, 74 s, has 6 vehicles
  within 300 m on average; 232, 68 s, has 17.)  Every
  track is then cut to the host's time span and vehicles never present in it are left
  out: the others appear and disappear during the run as they enter and leave the data.
* **Order.**  Vehicles in order of first appearance in the trips, the host right after
  the vehicle ahead of it in its own trip (what a sweep's FCW scene takes as its target,
  :func:`catc.sweep.fcw_scene`).

``meta["scene"]`` records the numbers: trips, vehicles, overlap and its disagreement,
junctions and their largest shift, the host rule, the span, and how many RVs are within
:data:`RADIUS_M` of the host (mean, max).
"""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np

from catc.datasets import derive
from catc.geo import EnuFrame, heading_diff_deg
from catc.mobility import DT, MobilityTable, Track

__all__ = ["RADIUS_M", "SHARED_CLOCK", "TAPER_SAMPLES", "choose_host", "clip", "merge",
           "neighbours", "scene"]

#: Kinds whose trips of one file share one clock (what a scene needs).
SHARED_CLOCK = ("ngsim", "sumo")
#: Neighbours are vehicles within this distance (m) of the host: the DSRC range the
#: safety apps plan for.
RADIUS_M = 300.0
#: Samples over which a junction's position shift fades out (3 s).
TAPER_SAMPLES = 30
_CLOCK_TOL_S = 1e-3
_FIELDS = ("t", "x", "y", "lat", "lon", "elev", "speed", "heading", "accel", "yaw_rate")
_F = {name: i for i, name in enumerate(_FIELDS)}


def _grid(t: np.ndarray, t0: float, where: str) -> np.ndarray:
    k = np.rint((t - t0) / DT).astype(np.int64)
    off = np.abs(t - t0 - k * DT)
    if off.size and off.max() > _CLOCK_TOL_S:
        raise ValueError(f"scene: {where} is off the common 10 Hz clock by "
                         f"{off.max() * 1000:.0f} ms")
    return k


def _moved(track: Track, frame: EnuFrame) -> Track:
    """``track`` with x/y in ``frame`` (from its WGS-84 positions)."""
    x, y, _ = frame.to_enu(track.lat, track.lon, track.elev)
    return replace(track, x=np.atleast_1d(x), y=np.atleast_1d(y))


class _Merge:
    """The overlap and junction figures of a merge, over all its vehicles."""

    def __init__(self) -> None:
        self.overlap = 0
        self.max_diff = {"position_m": 0.0, "speed": 0.0, "accel": 0.0,
                         "heading_deg": 0.0, "length": 0.0, "width": 0.0}
        self.junctions = 0
        self.max_shift_m = 0.0
        self.dropped = 0  # samples outside a vehicle's longest run

    def compare(self, old: np.ndarray, new: np.ndarray, sizes: tuple[Track, Track]) -> None:
        """Overlapping samples (columns of :data:`_FIELDS`) of two pieces of one vehicle."""
        self.overlap += old.shape[1]
        d = self.max_diff
        pairs = {
            "position_m": np.hypot(old[_F["x"]] - new[_F["x"]], old[_F["y"]] - new[_F["y"]]),
            "speed": np.abs(old[_F["speed"]] - new[_F["speed"]]),
            "accel": np.abs(old[_F["accel"]] - new[_F["accel"]]),
            "heading_deg": np.abs(heading_diff_deg(old[_F["heading"]], new[_F["heading"]])),
        }
        for k, v in pairs.items():
            d[k] = max(d[k], float(np.nanmax(v, initial=0.0)))
        a, b = sizes
        for k in ("length", "width"):
            diff = abs(getattr(a, k) - getattr(b, k))
            if np.isfinite(diff):
                d[k] = max(d[k], float(diff))

    def summary(self) -> dict:
        return {"overlap": {"samples": self.overlap,
                            "max_disagreement": {k: round(v, 6)
                                                 for k, v in self.max_diff.items()}},
                "junctions": self.junctions, "max_junction_shift_m": round(self.max_shift_m, 3),
                "dropped_samples": self.dropped}


def _shift(v: np.ndarray, src: np.ndarray, a: int, b: int, later: bool, stats: _Merge) -> None:
    """Shift the lower-ranked side of the junction between valid samples ``a < b`` (the
    side after it when ``later``) so that it continues the other, fading out."""
    xy = v[[_F["x"], _F["y"]]]
    steps = [xy[:, a] - xy[:, a - 1]] if a > 0 and src[a - 1] == src[a] else []
    if b + 1 < v.shape[1] and src[b + 1] == src[b]:
        steps.append(xy[:, b + 1] - xy[:, b])
    step = np.mean(steps, axis=0) if steps else np.zeros(2)
    if later:
        offset = xy[:, a] + step * (b - a) - xy[:, b]
        side = src[b]
        stop = b
        while stop < len(src) and src[stop] in (side, -1):
            stop += 1
        idx = np.arange(b, min(stop, b + TAPER_SAMPLES))
        weight = 1.0 - (idx - b) / len(idx)
    else:
        offset = xy[:, b] - step * (b - a) - xy[:, a]
        side = src[a]
        start = a
        while start >= 0 and src[start] in (side, -1):
            start -= 1
        idx = np.arange(max(start + 1, a - TAPER_SAMPLES + 1), a + 1)
        weight = 1.0 - (a - idx) / len(idx)
    v[_F["x"], idx] += offset[0] * weight
    v[_F["y"], idx] += offset[1] * weight
    stats.junctions += 1
    stats.max_shift_m = max(stats.max_shift_m, float(np.hypot(*offset)))


def _vehicle(vid: str, pieces: list[tuple[int, int, Track, np.ndarray]], frame: EnuFrame,
             stats: _Merge) -> Track:
    """The merged track of one vehicle from its pieces ``(rank, trip, track, grid)``."""
    pieces = sorted(pieces, key=lambda p: (p[0], p[1]))
    lo = min(int(p[3][0]) for p in pieces)
    n = max(int(p[3][-1]) for p in pieces) - lo + 1
    v = np.full((len(_FIELDS), n), np.nan)
    src = np.full(n, -1)
    for rank, (_, _, tr, k) in enumerate(pieces):
        cols = np.vstack([np.asarray(getattr(tr, f), dtype=np.float64) for f in _FIELDS])
        idx = k - lo
        taken = src[idx] >= 0
        if taken.any():
            first = pieces[int(src[idx[taken]][0])][2]
            stats.compare(v[:, idx[taken]], cols[:, taken], (first, tr))
        v[:, idx[~taken]] = cols[:, ~taken]
        src[idx[~taken]] = rank
    run = max(derive.pieces(src >= 0), key=lambda s: (s.stop - s.start, -s.start))
    stats.dropped += int(np.count_nonzero(src >= 0)) - int(np.count_nonzero(src[run] >= 0))
    v, src = v[:, run], src[run]
    valid = src >= 0
    if not valid.all():
        v[_F["heading"], valid] = np.unwrap(v[_F["heading"], valid], period=360.0)
        v = derive.fill_gaps(v.T, valid).T
        v[_F["heading"]] %= 360.0
    at = np.flatnonzero(valid)
    for a, b in itertools.pairwise(at.tolist()):
        if src[a] != src[b]:
            _shift(v, src, a, b, later=src[b] > src[a], stats=stats)
    best = pieces[0][2]
    provenance = dict(best.provenance)
    used = sorted({int(s) for s in src[valid]})
    if len(used) > 1 or not valid.all():
        _, _, up = frame.to_enu(v[_F["lat"]], v[_F["lon"]], v[_F["elev"]])
        v[_F["lat"]], v[_F["lon"]], v[_F["elev"]] = frame.to_geodetic(
            v[_F["x"]], v[_F["y"]], up)
        again = provenance.get("heading", "").startswith("derived") and v.shape[1] >= 3
        if again:
            v[_F["heading"]] = derive.heading_from_track(v[_F["x"]], v[_F["y"]],
                                                         v[_F["speed"]])
            v[_F["yaw_rate"]] = derive.yaw_rate_from_heading(v[_F["heading"]])
        provenance["scene"] = (
            f"merged from {len(used)} trips' pieces; where they overlap the trip whose "
            f"host it is wins; position steps at junctions faded out over "
            f"{TAPER_SAMPLES * DT:g} s" + ("; heading and yaw rate derived again" if again
                                           else ""))
    return Track(vid, *(v[_F[f]] for f in _FIELDS), length=best.length, width=best.width,
                 provenance=provenance)


def merge(tables: list[MobilityTable], name: str) -> MobilityTable:
    """Every vehicle of ``tables`` in one table (module docstring), with no host yet.
    ``meta["ahead"]`` maps a vehicle to the one before it in its own trip."""
    if not tables:
        raise ValueError("scene: no trips")
    kinds = sorted({t.kind for t in tables})
    if len(kinds) > 1 or kinds[0] not in SHARED_CLOCK:
        raise ValueError(f"scene: trips of kind {', '.join(kinds)} do not share one clock "
                         f"(a scene takes one file of {' or '.join(SHARED_CLOCK)})")
    origin = tables[0].origin
    frame = EnuFrame(*origin)
    t0 = min(float(tr.t[0]) for tb in tables for tr in tb.tracks.values())
    pieces: dict[str, list[tuple[int, int, Track, np.ndarray]]] = {}
    ahead: dict[str, tuple[int, str]] = {}
    for j, tb in enumerate(tables):
        names = list(tb.tracks)
        for i, (vid, tr) in enumerate(tb.tracks.items()):
            if tb.origin != origin:
                tr = _moved(tr, frame)
            k = _grid(np.asarray(tr.t, dtype=np.float64), t0, f"trip {tb.name} vehicle {vid}")
            primary = vid == tb.default_host
            pieces.setdefault(vid, []).append((0 if primary else 1, j, tr, k))
            if primary and i > 0 and len(tr) > ahead.get(vid, (0, ""))[0]:
                ahead[vid] = (len(tr), names[i - 1])
    stats = _Merge()
    tracks = {vid: _vehicle(vid, p, frame, stats) for vid, p in pieces.items()}
    meta = {"ahead": {v: a for v, (_, a) in ahead.items()},
            "scene": {"trips": len(tables), "vehicles_merged": len(tracks),
                      **stats.summary()}}
    return MobilityTable(name=name, kind=kinds[0], origin=origin, tracks=tracks, meta=meta)


def neighbours(table: MobilityTable, host: str, radius: float = RADIUS_M) -> np.ndarray:
    """How many other vehicles are within ``radius`` (m) of ``host`` at each of its samples."""
    h = table.tracks[host]
    counts = np.zeros(len(h), dtype=np.int64)
    for vid, tr in table.tracks.items():
        if vid == host:
            continue
        i = np.rint((np.asarray(tr.t) - h.t[0]) / DT).astype(np.int64)
        keep = (i >= 0) & (i < len(h))
        i = i[keep]
        near = np.hypot(tr.x[keep] - h.x[i], tr.y[keep] - h.y[i]) <= radius
        np.add.at(counts, i[near], 1)
    return counts


def choose_host(table: MobilityTable, radius: float = RADIUS_M) -> str:
    """The vehicle with the most neighbour samples: :func:`neighbours` summed over its
    samples (vehicle-seconds within ``radius`` x 10), which favours a vehicle both long
    present and in dense traffic; of several, the first in order."""
    score = {v: int(neighbours(table, v, radius).sum()) for v in table.tracks}
    best = max(score.values())
    return next(v for v in table.tracks if score[v] == best)


def clip(table: MobilityTable, host: str) -> MobilityTable:
    """``table`` cut to the span of ``host``'s track: the vehicles present in it, each on
    its samples within it; the host right after the vehicle ahead of it
    (``meta["ahead"]``), or last."""
    h = table.tracks[host]
    lo, hi = float(h.t[0]) - _CLOCK_TOL_S, float(h.t[-1]) + _CLOCK_TOL_S
    tracks: dict[str, Track] = {}
    for vid, tr in table.tracks.items():
        keep = (tr.t >= lo) & (tr.t <= hi)
        if vid != host and keep.any():
            tracks[vid] = tr if keep.all() else replace(
                tr, **{f: getattr(tr, f)[keep] for f in _FIELDS})
    lead = table.meta.get("ahead", {}).get(host)
    names = list(tracks)
    at = names.index(lead) + 1 if lead in tracks else len(names)
    names.insert(at, host)
    tracks[host] = h
    return replace(table, tracks={v: tracks[v] for v in names}, default_host=host)


def scene(tables: list[MobilityTable], name: str, host: str | None = None,
          radius: float = RADIUS_M) -> MobilityTable:
    """The scene of ``tables`` (the trips of one file) around ``host`` (default:
    :func:`choose_host`), named ``NAME:scene:HOST`` (module docstring)."""
    merged = merge(tables, name)
    rule = "given"
    if host is None and len(tables) == 1 and tables[0].default_host is not None:
        host, rule = tables[0].default_host, "the trip's host"
    elif host is None:
        host, rule = choose_host(merged, radius), "most neighbour samples"
    elif host not in merged.tracks:
        some = ", ".join(list(merged.tracks)[:10])
        more = f" and {len(merged.tracks) - 10} more" if len(merged.tracks) > 10 else ""
        raise ValueError(f"scene: no vehicle {host!r}; vehicles: {some}{more}")
    out = clip(merged, host)
    counts = neighbours(out, host, radius)
    h = out.tracks[host]
    info = {**merged.meta["scene"], "host": host, "host_rule": rule,
            "span_s": [round(float(h.t[0]), 3), round(float(h.t[-1]), 3)],
            "duration_s": round(float(h.t[-1] - h.t[0]), 3), "rvs": len(out.tracks) - 1,
            "radius_m": radius, "rvs_within_radius": {
                "mean": round(float(counts.mean()), 2), "max": int(counts.max())}}
    return replace(out, name=f"{name}:scene:{host}", meta={**merged.meta, "scene": info})
