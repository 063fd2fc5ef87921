"""The CA-TC's results, pinned bit for bit.

``ContextAwareMap.step`` has fast paths for the few RVs of a sweep's scenes (row-by-row
classification, point-by-point ENU conversion, ...) beside the numpy paths that serve
hundreds of RVs.  Both must give exactly what the straightforward code gave: the digests
below were computed by the CA-TC before those fast paths existed (commit 69b633d), over
every field of every snapshot of short real replays (CA predictor, so that work on the
learned predictors does not trip them).  A change that alters any result, by one ulp or
one warning, fails here; if the change is meant, recompute the digests with
:func:`_digest` and say why in the commit.

Only the NGSIM scene (host + one RV: the pure-Python fast paths) is pinned to digests.
The bigger scenes go through numpy's vectorised trigonometry, whose last bits change
between numpy releases (numpy 2.4 moved them): there the test replays the scene twice,
fast paths on and off (every RV through the numpy paths), and wants the same digest.

The path-against-path tests run both implementations on the same random rows.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import math
import struct
from importlib import resources

import numpy as np
import pytest

from catc import geo
from catc.apps import SafetyApps
from catc.cam import CamConfig, ContextAwareMap, MapSnapshot
from catc.channel import ChannelConfig
from catc.classify import ClassifyConfig, HostPath, _rows, classify_many, classify_paths
from catc.geo import EnuFrame
from catc.mobility import MobilityTable
from catc.replay import plan, simulate
from tests.conftest import shared_path

#: The snapshot fields the digests cover (all of them but ``horizon_s``, a constant).
FIELDS = ("t", "host", "ids", "x", "y", "speed", "heading", "accel", "var_x", "var_y",
          "source", "age", "fresh", "lane", "zone", "pred_x", "pred_y", "pred_heading",
          "pred_speed", "predicted_zone", "hard_braking", "length", "width", "on_trail",
          "counters", "warnings", "events")


def _feed(h, obj) -> None:
    """Add ``obj`` to the hash ``h`` in a canonical form: type, shape and exact bits."""
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        h.update(b"A%s%r" % (a.dtype.str.encode(), a.shape))
        h.update(a.tobytes())
    elif isinstance(obj, (bool, np.bool_)):
        h.update(b"b1" if obj else b"b0")
    elif isinstance(obj, (int, np.integer)):
        h.update(b"i%d;" % int(obj))
    elif isinstance(obj, (float, np.floating)):
        h.update(b"f" + struct.pack("<d", float(obj)))
    elif obj is None:
        h.update(b"n")
    elif isinstance(obj, str):
        h.update(b"s%d:%s" % (len(obj), obj.encode()))
    elif isinstance(obj, enum.Enum):
        _feed(h, f"{type(obj).__name__}.{obj.name}")
    elif dataclasses.is_dataclass(obj):
        _feed(h, type(obj).__name__)
        for f in dataclasses.fields(obj):
            _feed(h, f.name)
            _feed(h, getattr(obj, f.name))
    elif isinstance(obj, dict):
        h.update(b"M%d" % len(obj))
        for k, v in obj.items():
            _feed(h, k)
            _feed(h, v)
    elif isinstance(obj, (list, tuple)):
        h.update(b"L%d" % len(obj))
        for v in obj:
            _feed(h, v)
    else:
        raise TypeError(f"cannot digest {type(obj)}")


#: Counters added after the digests were pinned (issue 18); left out of the digest when 0.
LATER_COUNTERS = ("inconsistent", "self", "shadow", "confirmed", "tentative_evicted",
                  "tentative_full")


def _digest(snaps: list[MapSnapshot]) -> str:
    h = hashlib.sha256()
    for s in snaps:
        for name in FIELDS:
            value = getattr(s, name)
            if name == "counters":
                value = {k: v for k, v in value.items() if k not in LATER_COUNTERS or v}
            _feed(h, value)
    return h.hexdigest()


def _replay(table: MobilityTable, duration: float | None = None) -> list[MapSnapshot]:
    """PER 0.5, seed 0, BSMs through UPER, CA predictor, every application; tracks
    confirmed at their first message, as when the values were pinned."""
    the_plan = plan(table, ChannelConfig(per=0.5), 0, duration=duration)
    cam = ContextAwareMap(CamConfig(predictor="ca", origin=table.origin, confirm_after=1,
                                    confirm_near=1), SafetyApps())
    return list(simulate(the_plan, cam, wire=True))


def _numpy_paths_digest(monkeypatch, table: MobilityTable) -> str:
    """The digest of :func:`_replay` with every fast path off."""
    with monkeypatch.context() as m:
        m.setattr(_rows, "SMALL_ROWS", -1)
        m.setattr(geo, "_SMALL_POINTS", -1)
        return _digest(_replay(table))


def _load(spec: str) -> list[MobilityTable]:
    from hil.datasets import load

    return load(spec)


# --- pinned replays (values from the code before the fast paths) -----------------------------

def test_ngsim_pair_host_and_one_rv_pinned() -> None:
    """A host and its leader (the sweep's FCW scene): row-by-row classification, trail
    lanes, FCW warnings and events."""
    table = _load(f"ngsim:{shared_path('ngsim-i80-pairs')}")[0]
    snaps = _replay(table)
    assert len(snaps) == 322
    s = snaps[200]
    assert [v.hex() for v in (s.x[0], s.y[0], s.zone.s[0], s.zone.d[0],
                              s.predicted_zone.s[0], s.predicted_zone.d[0],
                              s.host.predicted_path.x)] == PINNED_NGSIM_200
    assert sum(len(s.warnings) for s in snaps) == PINNED_NGSIM_WARNINGS
    assert dict(snaps[-1].counters) == PINNED_NGSIM_COUNTERS
    assert _digest(snaps) == PINNED_NGSIM_DIGEST


def test_openacc_platoon_fast_paths_are_exact(monkeypatch) -> None:
    """22 vehicles on the ZalaZone handling track (curves: trail lanes; more rows than
    the row-by-row path takes: the numpy path)."""
    table = _load(str(shared_path("openacc-zalazone",
                                  "short_setting_handling_part36.csv")))[0]
    snaps = _replay(table)
    sizes = {len(s) for s in snaps}
    assert min(sizes) <= _rows.SMALL_ROWS // 2 < max(sizes)  # both paths, and switches
    assert _digest(snaps) == _numpy_paths_digest(monkeypatch, table)


def test_sumo_highway_braking_fast_paths_are_exact(monkeypatch) -> None:
    """The packaged SUMO scenario: RVs behind the HV (path-history projection), BSW, LCW
    and EEBL warnings, 16 RVs (the numpy path).  No shared data needed."""
    path = resources.files("hil").joinpath("scenarios", "highway-braking.fcd.xml")
    table = _load(f"sumo:{path}")[0]
    snaps = _replay(table)
    assert max(len(s) for s in snaps) > _rows.SMALL_ROWS // 2
    apps = {w.app for s in snaps for w in s.warnings}
    assert apps == {"fcw", "eebl", "bsw", "lcw"}
    assert _digest(snaps) == _numpy_paths_digest(monkeypatch, table)


# --- fast path against numpy path ------------------------------------------------------------

def _paths(rng: np.random.Generator, radius: float) -> tuple[HostPath, HostPath]:
    """An HV path with a wiggly history, and a predicted path of the same radius."""
    pts = np.cumsum(rng.normal([-0.5, -0.85], 0.3, size=(8, 2)) * 8.0, axis=0)
    history = tuple((5.0 + px, 7.0 + py) for px, py in pts)
    now = HostPath(5.0, 7.0, float(rng.uniform(0, 360)), radius, history)
    later = HostPath(9.0, 40.0, float(rng.uniform(-10, 370)), radius, ((5.0, 7.0), *history))
    return now, later


def _bits(zones) -> list[bytes]:
    return [np.ascontiguousarray(getattr(z, f.name)).tobytes() + str(
        getattr(z, f.name).dtype).encode() for z in zones for f in dataclasses.fields(z)]


@pytest.mark.parametrize("radius", [math.inf, 80.0, -150.0, 2500.0])
@pytest.mark.parametrize("seed", range(6))
def test_row_by_row_classification_is_the_numpy_one(monkeypatch, seed: int,
                                                    radius: float) -> None:
    rng = np.random.default_rng(seed)
    now, later = _paths(rng, radius)
    n = int(rng.integers(0, 9))
    x = np.concatenate([rng.uniform(-120, 120, n), [5.0, 0.0]])
    y = np.concatenate([rng.uniform(-120, 120, n), [7.0, 0.0]])
    h = np.concatenate([rng.uniform(0, 360, n), [180.0, -0.0]])
    counts = (len(x) // 2, len(x) - len(x) // 2)
    cfg = ClassifyConfig()
    assert len(x) <= _rows.SMALL_ROWS
    small = classify_paths((now, later), counts, x, y, h, cfg)
    single = classify_many(now, x, y, h, cfg)
    monkeypatch.setattr(_rows, "SMALL_ROWS", -1)
    assert _bits(small) == _bits(classify_paths((now, later), counts, x, y, h, cfg))
    assert _bits([single]) == _bits([classify_many(now, x, y, h, cfg)])


@pytest.mark.parametrize("n", [1, 2, 5, 16])
def test_point_by_point_enu_is_the_array_one(monkeypatch, n: int) -> None:
    rng = np.random.default_rng(n)
    frame = EnuFrame(40.75, -73.98, 12.0)
    lat = 40.75 + rng.normal(0, 0.02, n)
    lon = -73.98 + rng.normal(0, 0.02, n)
    h = rng.normal(0, 30, n)
    small = frame.to_enu(lat, lon, h)
    lists = frame.en_lists(lat.tolist(), lon.tolist())
    scalar = frame.to_enu(float(lat[0]), float(lon[0]), float(h[0]))
    monkeypatch.setattr(geo, "_SMALL_POINTS", -1)
    big = frame.to_enu(lat, lon, h)
    assert [a.tobytes() for a in small] == [a.tobytes() for a in big]
    e, north, _ = frame.to_enu(lat, lon, 0.0)
    assert lists == (e.tolist(), north.tolist())
    assert frame.en_lists(lat.tolist(), lon.tolist()) == lists
    assert scalar == tuple(float(a[0]) for a in big)


def test_snapshots_carry_every_field() -> None:
    """The CAM builds snapshots without the dataclass ``__init__``: every field is set."""
    path = resources.files("hil").joinpath("scenarios", "highway-braking.fcd.xml")
    table = _load(f"sumo:{path}")[0]
    names = {f.name for f in dataclasses.fields(MapSnapshot)}
    for s in _replay(table, duration=5.0):
        assert set(vars(s)) == names


# Values of the CA-TC before its fast paths (see the module docstring).
PINNED_NGSIM_200 = ["-0x1.db4d80166ae4ap+5", "0x1.081e357004b46p+8", "0x1.7033195d50a4dp+5",
                    "0x1.efe6e9e3ad430p-2", "0x1.96cfa373f42e0p+5", "-0x1.6ed3f8e6a2892p+3",
                    "-0x1.adf994bf0edc4p+5"]
PINNED_NGSIM_WARNINGS = 12
PINNED_NGSIM_COUNTERS = {
    "received": 164, "accepted": 164, "incomplete": 0, "implausible": 0, "late": 0,
    "future": 0, "duplicate": 0, "out_of_order": 0, "jump": 0, "inconsistent": 0, "self": 0,
    "shadow": 0, "reacquired": 0, "table_full": 0, "displaced": 0, "evicted_stale": 0,
    "tracks_created": 1, "confirmed": 0, "tentative_evicted": 0, "tentative_full": 0,
    "ph_crumbs_used": 0, "ticks": 322}
PINNED_NGSIM_DIGEST = "ab3e60f9c3b43aae41c5dc03cff29512119ceedff48e57fb6f732f156039e19e"
