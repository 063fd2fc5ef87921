"""Vehicle profiles and the comma2k19 minute's raw CAN, read from files.

:func:`load_profile` reads a :class:`catc.vehicle.VehicleProfile` (a JSON file naming
the fields, and the DBC it reads them through) and loads the DBC with :mod:`cantools`:
a shipped profile by name (``toyota-rav4-2017``: ``catc/vehicle/profiles/``), or a
JSON file; ``dbc`` replaces the profile's own DBC with any full DBC of the car (the
profile's messages and signals must be in it).  Every problem is one line
(:class:`ProfileError`).

:func:`comma2k19_can` reads a comma2k19 segment's ``processed_log/CAN/raw_can`` (the
real minute of a 2017 RAV4 in ``../shared/data/comma2k19-example``).  Its ``data.npy``
holds each frame as an 8-byte NumPy string, which drops trailing zero bytes (on buses 0
and 1, 994 frames of ids the DBCs know are stored shorter than they were sent).  A frame
whose id the DBC knows is padded back to the DBC's length (after which the Toyota checksum passes on
every checksummed frame); one it does not know keeps its stored length.  Buses 0 (the
car) and 1 (the radar) only: 128 and 129 are the frames openpilot itself sent.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from catc.vehicle import VehicleProfile
from hil.errors import InputError

__all__ = ["ProfileError", "comma2k19_can", "load_dbc", "load_profile", "profile_names",
           "rav4_lengths"]


class ProfileError(InputError):
    """A vehicle profile or DBC that cannot be used (one line)."""


def profile_names() -> list[str]:
    """The shipped profiles."""
    folder = resources.files("catc").joinpath("vehicle", "profiles")
    return sorted(p.name[:-5].replace("_", "-") for p in folder.iterdir()
                  if p.name.endswith(".json"))


def load_dbc(path: Path | Any) -> Any:
    """A :mod:`cantools` database from a DBC file (``strict=False``: opendbc's generated
    Toyota DBC has two overlapping signals)."""
    import cantools

    try:
        return cantools.database.load_file(str(path), database_format="dbc", strict=False)
    except OSError as err:
        raise ProfileError(f"{path}: {err.strerror or err}") from None
    except Exception as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ProfileError(f"{path}: not a DBC that parses: {first}") from None


def load_profile(spec: str, dbc: Path | None = None) -> tuple[VehicleProfile, Any]:
    """The profile ``spec`` (a shipped name or a JSON file) and its cantools database
    (``dbc`` if given, else the profile's own DBC), checked against each other."""
    shipped = resources.files("catc").joinpath("vehicle", "profiles",
                                               spec.replace("-", "_") + ".json")
    path = shipped if shipped.is_file() else Path(spec)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ProfileError(f"vehicle profile {spec!r}: no such file or shipped profile "
                           f"(shipped: {', '.join(profile_names())})") from None
    except OSError as err:
        raise ProfileError(f"{spec}: {err.strerror or err}") from None
    except json.JSONDecodeError as err:
        raise ProfileError(f"{spec}: not JSON: {err.msg} at line {err.lineno}") from None
    try:
        profile = VehicleProfile.from_dict(doc)
    except ValueError as err:
        raise ProfileError(f"{spec}: {err}") from None
    if dbc is None:
        own = doc.get("dbc")
        if not own:
            raise ProfileError(f"{spec}: names no DBC; give one (--dbc)")
        dbc = path.parent / own if isinstance(path, Path) else path.parent.joinpath(own)
    db = load_dbc(dbc)
    try:
        profile.check(db)
    except ValueError as err:
        raise ProfileError(f"{err} ({dbc})") from None
    return profile, db


def rav4_lengths() -> dict[int, dict[int, int]]:
    """The 2017 RAV4's frame lengths by bus and CAN id
    (``catc/vehicle/profiles/toyota_rav4_2017_lengths.json``: opendbc's lengths where its
    DBCs know the id, else the longest frame of the id in the comma2k19 minute)."""
    doc = json.loads(resources.files("catc").joinpath(
        "vehicle", "profiles", "toyota_rav4_2017_lengths.json").read_text(encoding="utf-8"))
    out: dict[int, dict[int, int]] = {}
    for part in ("observed", "dbc"):  # the DBC's length wins
        for bus, ids in doc[part].items():
            out.setdefault(int(bus), {}).update({int(k, 16): int(v) for k, v in ids.items()})
    return out


def comma2k19_can(segment: Path, dbs: dict[int, Any]) -> np.ndarray:
    """The segment's raw CAN of the buses in ``dbs`` (bus -> a cantools database, or a
    mapping of CAN id -> length such as :func:`rav4_lengths` gives: the lengths that
    restore the stored frames), in time order: a structured array of ``t`` (s, the
    segment's boot clock), ``bus``, ``address``, ``length`` and ``data`` (8 bytes,
    zero-padded)."""
    base = Path(segment) / "processed_log" / "CAN" / "raw_can"
    try:
        t, src, address, data = (np.load(base / f"{n}.npy") for n in
                                 ("t", "src", "address", "data"))
    except FileNotFoundError as err:
        raise ProfileError(f"{segment}: not a comma2k19 segment ({err.filename} missing)") \
            from None
    keep = np.isin(src, list(dbs))
    out = np.zeros(int(keep.sum()), dtype=[("t", "f8"), ("bus", "u1"), ("address", "u4"),
                                           ("length", "u1"), ("data", "S8")])
    out["t"], out["bus"], out["address"] = t[keep], src[keep], address[keep]
    out["data"] = data[keep]
    out["length"] = np.char.str_len(out["data"]) if len(out) else 0
    for bus, db in dbs.items():  # the DBC's length where it knows the id
        known_lengths = ({m.frame_id: m.length for m in db.messages}
                         if hasattr(db, "messages") else dict(db))
        ids = np.array(list(known_lengths), dtype=np.uint32)
        lengths = np.array(list(known_lengths.values()), dtype=np.uint8)
        order = np.argsort(ids)
        ids, lengths = ids[order], lengths[order]
        on = out["bus"] == bus
        k = np.clip(np.searchsorted(ids, out["address"][on]), 0, max(len(ids) - 1, 0))
        known = (ids[k] == out["address"][on]) if len(ids) else np.zeros(on.sum(), bool)
        sel = np.flatnonzero(on)[known]
        out["length"][sel] = lengths[k[known]]
    return out[np.argsort(out["t"], kind="stable")]
