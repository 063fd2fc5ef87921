"""Reading a capture directory back: the one reader of the files :mod:`hil.capture.schema`
names, for ``captures score``, ``view`` and ``plot``.

A JSON-lines file may end in a torn line (the daemon was killed while writing it): that
line is dropped.  A torn line anywhere else is an error, and so is a missing file a reader
needs, or one that is not UTF-8 text or JSON; :class:`CaptureError` says which, in one
line.  A file that cannot be read raises an :class:`OSError` that names it.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from catc.bsm import sec_mark
from catc.geo import EnuFrame
from hil.capture.schema import (
    OBU_CONFIG,
    OBU_END,
    OBU_EVENTS,
    OBU_MBR,
    OBU_RX,
    OBU_TICKS,
    OBU_TRACKS,
    RVE_CONFIG,
    RVE_END,
    RVE_SCHEDULE,
    RVE_TRUTH,
)
from hil.errors import InputError, load_json, read_text

__all__ = ["Capture", "CaptureError", "clock_offset", "read_capture", "read_json",
           "read_lines", "truth_in_frame"]


class CaptureError(InputError):
    """A capture that cannot be read or joined; ``str()`` is one line."""


def read_lines(path: Path) -> list[dict[str, Any]]:
    """Every record of a JSON-lines capture file (a torn last line is dropped)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: missing (is this a capture directory of rve and obu?)")
    try:
        lines = read_text(path).splitlines()
    except InputError as err:
        raise CaptureError(str(err)) from None
    out = []
    for n, line in enumerate(lines, 1):
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            if n < len(lines):  # only the last line of a killed daemon may be torn
                raise CaptureError(f"{path}:{n}: not a JSON line") from None
    return out


def read_json(path: Path) -> dict[str, Any]:
    """A capture's JSON file (a config, an end record or the counters): an object."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: missing (is this a capture directory of rve and obu?)")
    try:
        doc = load_json(path)
    except InputError as err:
        raise CaptureError(str(err)) from None
    if not isinstance(doc, dict):
        raise CaptureError(f"{path}: not a JSON object")
    return doc


@dataclass
class Capture:
    """The files of an RVE + OBU capture directory, as lists of records."""

    directory: Path
    rve_config: dict[str, Any]
    obu_config: dict[str, Any]
    truth: list[dict[str, Any]]
    schedule: list[dict[str, Any]]
    ticks: list[dict[str, Any]]
    tracks: list[dict[str, Any]]
    events: list[dict[str, Any]]
    rx: list[dict[str, Any]] | None  # None when not read
    mbr: list[dict[str, Any]] | None  # None when the OBU ran without --mbd
    rve_end: dict[str, Any] | None = None  # None: no end record (killed, or before 2026-11-27)
    obu_end: dict[str, Any] | None = None


def read_capture(directory: Path, rx: bool = True) -> Capture:
    """The files of an RVE + OBU capture directory, checked (the OBU ticked at least once
    and recorded its ENU origin); ``rx`` False skips ``obu.rx.jsonl``, the largest."""
    directory = Path(directory)
    if not directory.is_dir():
        raise CaptureError(f"{directory}: not a directory")

    def optional(name: str) -> list[dict[str, Any]] | None:
        path = directory / name
        return read_lines(path) if path.is_file() else None

    cap = Capture(
        directory=directory,
        rve_config=read_json(directory / RVE_CONFIG),
        obu_config=read_json(directory / OBU_CONFIG),
        truth=read_lines(directory / RVE_TRUTH),
        schedule=read_lines(directory / RVE_SCHEDULE),
        ticks=read_lines(directory / OBU_TICKS),
        tracks=read_lines(directory / OBU_TRACKS),
        events=optional(OBU_EVENTS) or [],
        rx=read_lines(directory / OBU_RX) if rx else None,
        mbr=optional(OBU_MBR),
        rve_end=read_json(directory / RVE_END) if (directory / RVE_END).is_file() else None,
        obu_end=read_json(directory / OBU_END) if (directory / OBU_END).is_file() else None)
    if not cap.ticks:
        raise CaptureError(f"{directory}: the OBU recorded no tick")
    if cap.obu_config.get("origin") is None:
        raise CaptureError(f"{directory}: {OBU_CONFIG} has no ENU origin")
    return cap


def clock_offset(truth: list[dict], first_tick: dict, directory: Path) -> float:
    """OBU clock - dataset time (a whole number of minutes): the host truth sample whose
    secMark is the OBU's first tick's."""
    matches = [r["t"] for r in truth
               if r["host"] and sec_mark(r["t"]) == first_tick["sec_mark"]]
    if not matches:
        raise CaptureError(f"{directory}: the OBU's first tick (secMark "
                           f"{first_tick['sec_mark']}) matches no host sample of the RVE's "
                           "truth")
    return first_tick["t"] - matches[0]


def truth_in_frame(truth: list[dict], origin) -> dict[str, tuple[list[dict], np.ndarray,
                                                                    np.ndarray, np.ndarray]]:
    """Truth rows per vehicle id with their times and positions in the OBU's ENU frame
    (``origin``: its lat, lon, h): ``id -> (rows, t, x, y)``."""
    frame = EnuFrame(*origin)
    by_vehicle: dict[str, list[dict]] = defaultdict(list)
    for r in truth:
        by_vehicle[r["id"]].append(r)
    out = {}
    for tid, rows in by_vehicle.items():
        x, y, _ = frame.to_enu(np.array([r["lat"] for r in rows]),
                               np.array([r["lon"] for r in rows]), 0.0)
        out[tid] = (rows, np.array([r["t"] for r in rows]), np.atleast_1d(x),
                    np.atleast_1d(y))
    return out
