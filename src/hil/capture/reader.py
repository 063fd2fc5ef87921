"""Reading a capture directory back: the one reader of the files :mod:`hil.capture.schema`
names, for ``captures score``, ``view``, ``plot`` and ``tracks``.

Every file is read as a stream (:meth:`Capture.iter_rx`, :meth:`Capture.iter_track_blocks`
...), so a reader that aggregates as it goes (``captures score``) needs memory for what it
keeps, not for the capture; the lists (:attr:`Capture.ticks`, :attr:`Capture.tracks` ...)
are read on first use, for the readers that want everything (plot, view).

Torn tails.  A file the daemon was writing when it was killed, or when the disk filled,
may end inside a record: a JSON line without its end, a gzip stream cut short, a block of
``obu.tracks.bin`` cut off.  The reader reads up to there and notes the file and the byte
offset where the whole part ends (:attr:`Capture.torn`, or the ``torn`` callback of the
functions); a bad record before the end is an error.  :class:`CaptureError` says what is
wrong in one line.

Segments (``obu run --capture-max-mb``): the OBU's per-tick files are read segment by
segment in order (:func:`segment_files`); :meth:`Capture.missing_segments` names the ones
deleted under the cap.  Captures written before 2026-11-27 (``obu.rx.jsonl``,
``obu.tracks.jsonl``: :data:`hil.capture.schema.LEGACY`) are read as well.
A file that cannot be read raises an :class:`OSError` that names it.
"""

from __future__ import annotations

import itertools
import json
import re
import zlib
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from catc.bsm import sec_mark
from catc.geo import EnuFrame
from hil.capture.schema import (
    LEGACY,
    OBU_CONFIG,
    OBU_END,
    OBU_EVENTS,
    OBU_MBD,
    OBU_MBR,
    OBU_RX,
    OBU_TICKS,
    OBU_TRACKS,
    OBU_VERIFY,
    RVE_CONFIG,
    RVE_END,
    RVE_SCHEDULE,
    RVE_TRUTH,
)
from hil.capture.tracks import FIELDS, TrackBlock, block_rows, iter_blocks
from hil.errors import InputError, load_json

__all__ = ["Capture", "CaptureError", "Torn", "clock_offset", "gunzip", "iter_lines",
           "read_capture",
           "read_json", "read_lines", "read_rx", "read_tracks", "segment_files", "torn_line",
           "truth_in_frame"]

#: Where a file's whole part ends: (file, byte offset, why).
Torn = tuple[Path, int, str]
TornCallback = Callable[[Path, int, str], None]
_CHUNK = 1 << 20


class CaptureError(InputError):
    """A capture that cannot be read or joined; ``str()`` is one line."""


def _missing(path: Path) -> CaptureError:
    return CaptureError(f"{path}: missing (is this a capture directory of rve and obu?)")


def _records(lines: Iterable[tuple[int, bytes]], path: Path,
             bad_last: Callable[[int], None]) -> Iterator[dict[str, Any]]:
    """JSON records of ``(offset, line)`` pairs; the last line may be torn: then
    ``bad_last(its offset)``."""
    pending: tuple[int, bytes] | None = None
    for n, item in enumerate(lines):  # n: the pending line's number, from 1
        if not item[1].strip():
            continue
        if pending is not None:
            try:
                yield json.loads(pending[1])
            except ValueError:
                raise CaptureError(f"{path}:{n}: not a JSON line (byte {pending[0]})"
                                   ) from None
        pending = item
    if pending is not None:
        try:
            yield json.loads(pending[1])
        except ValueError:  # only the last line of a killed daemon may be torn
            bad_last(pending[0])


def _plain_lines(path: Path) -> Iterator[tuple[int, bytes]]:
    with open(path, "rb") as f:
        off = 0
        for line in f:
            yield off, line
            off += len(line)


_SYNC = b"\x00\x00\xff\xff"  # the empty stored block a sync flush ends with


def _gzip_lines(path: Path, state: dict[str, Any]) -> Iterator[tuple[int, bytes]]:
    """Lines of a gzip file (members one after the other) up to where it is cut; sets
    ``state["cut"]`` (why) and ``state["whole"]`` (the offset the whole part ends at: after
    the last sync flush) when the last member has no end.  Offsets are of the compressed
    file, where each line's chunk of input began."""
    d = zlib.decompressobj(31)
    rest, fed, started = b"", 0, False
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            at, fed = fed, fed + len(chunk)
            while chunk:
                try:
                    out = d.decompress(chunk)
                except zlib.error:
                    state.update(cut="gzip data corrupt", whole=at)
                    return
                started = True
                *lines, rest = (rest + out).split(b"\n")
                for line in lines:
                    if line.strip():
                        yield at, line
                chunk = d.unused_data if d.eof else b""
                if d.eof:  # a member ended; another may follow
                    d, started = zlib.decompressobj(31), False
    if rest.strip():
        yield fed, rest
    if started and not d.eof:
        with open(path, "rb") as f:
            f.seek(max(0, fed - _CHUNK))
            tail = f.read()
        if not tail.endswith(_SYNC) or rest.strip():
            last = tail.rfind(_SYNC)
            state.update(cut="gzip stream cut", whole=fed - len(tail) + last + len(_SYNC)
                         if last >= 0 else fed)


def gunzip(data: bytes) -> tuple[bytes, tuple[int, str] | None]:
    """The content of gzip data (members one after the other) up to where it is cut, and
    where the whole part ends ``(byte offset, why)`` when it is cut (None when it is
    whole, or ends at a flush: see :func:`iter_lines`)."""
    out: list[bytes] = []
    d = zlib.decompressobj(31)
    rest, started = bytes(data), False
    while rest:
        try:
            out.append(d.decompress(rest))
        except zlib.error:
            return b"".join(out), (len(data) - len(rest), "gzip data corrupt")
        started = True
        rest = d.unused_data if d.eof else b""
        if d.eof:
            d, started = zlib.decompressobj(31), False
    text = b"".join(out)
    if started and not d.eof and (not data.endswith(_SYNC) or not text.endswith(b"\n")):
        last = data.rfind(_SYNC)
        return text, (last + len(_SYNC) if last >= 0 else len(data), "gzip stream cut")
    return text, None


def iter_lines(path: Path, torn: TornCallback | None = None) -> Iterator[dict[str, Any]]:
    """Every record of a JSON-lines capture file (``.gz``: one gzip stream), in order.  A
    torn last line, or a gzip stream cut inside a flush, ends it: ``torn(path, offset,
    why)`` with the offset where the whole part ends; a bad line before the last raises
    :class:`CaptureError`.  (A gzip stream without its end marker but cut at a flush, a
    daemon killed between two ticks or still writing, is whole.)"""
    path = Path(path)
    if not path.is_file():
        raise _missing(path)
    bad: list[int] = []
    if path.suffix == ".gz":
        state: dict[str, Any] = {}
        yield from _records(_gzip_lines(path, state), path, bad.append)
        if (bad or state) and torn is not None:
            torn(path, state.get("whole", path.stat().st_size),
                 state.get("cut", "gzip stream cut inside a line"))
    else:
        yield from _records(_plain_lines(path), path, bad.append)
        if bad and torn is not None:
            torn(path, bad[0], "last line cut off")


def read_lines(path: Path, torn: TornCallback | None = None) -> list[dict[str, Any]]:
    """Every record of a JSON-lines capture file (a torn last line is dropped)."""
    return list(iter_lines(path, torn))


def torn_line(torn: list[Torn], prefix: str) -> str | None:
    """The one stderr line that says where files were torn (None when none was)."""
    if not torn:
        return None
    where = ", ".join(f"{p} at byte {off} ({why})" for p, off, why in torn)
    return f"{prefix}: read up to a torn tail (killed, or the disk full?): {where}"


def read_json(path: Path) -> dict[str, Any]:
    """A capture's JSON file (a config, an end record or the counters): an object."""
    path = Path(path)
    if not path.is_file():
        raise _missing(path)
    try:
        doc = load_json(path)
    except InputError as err:
        raise CaptureError(str(err)) from None
    if not isinstance(doc, dict):
        raise CaptureError(f"{path}: not a JSON object")
    return doc


def segment_files(directory: Path, name: str) -> list[tuple[int, Path]]:
    """The segments of the OBU file ``name`` (:data:`hil.capture.schema.SEGMENTED`) in
    ``directory``, by number: ``[(0, obu.ticks.jsonl), (3, obu.ticks.000003.jsonl)...]``;
    a capture of before 2026-11-27 gives its file of the old name."""
    directory = Path(directory)
    daemon, stream, ext = name.split(".", 2)
    pattern = re.compile(rf"{re.escape(daemon)}\.{re.escape(stream)}\.(\d{{6}})\."
                         rf"{re.escape(ext)}$")
    found = [(int(m.group(1)), p) for p in directory.glob(f"{daemon}.{stream}.*.{ext}")
             if (m := pattern.match(p.name))]
    if (directory / name).is_file():
        found.append((0, directory / name))
    elif name in LEGACY and (directory / LEGACY[name]).is_file():
        found.append((0, directory / LEGACY[name]))
    return sorted(found)


def read_rx(directory: Path) -> list[dict[str, Any]]:
    """Every ``obu.rx`` record of an OBU capture directory, segments in order."""
    return [r for _, p in segment_files(Path(directory), OBU_RX) for r in iter_lines(p)]


def read_tracks(directory: Path) -> list[dict[str, Any]]:
    """Every track row of an OBU capture directory as
    :func:`hil.capture.schema.track_rows` made it (the JSON lines of before), segments in
    order."""
    rows: list[dict[str, Any]] = []
    for _, p in segment_files(Path(directory), OBU_TRACKS):
        if p.suffix == ".jsonl":
            rows += iter_lines(p)
        else:
            rows += [r for b in iter_blocks(p) for r in block_rows(b)]
    return rows


def _block_of(rows: list[dict]) -> TrackBlock:
    """JSON track rows of one tick (a capture of before 2026-11-27) as a block."""
    cols: dict[str, np.ndarray] = {
        "id": np.array([int(r["id"], 16) for r in rows], dtype=np.uint32),
        "source": np.array([r["source"] for r in rows], dtype=object)}
    for i, (now, pred) in enumerate((("ahead", "p_ahead"), ("lateral", "p_lateral"),
                                     ("direction", "p_direction"))):
        cols[now] = np.array([r["zone"][i] for r in rows])
        cols[pred] = np.array([r["predicted_zone"][i] for r in rows])
    for name in FIELDS:
        if name not in cols:
            cols[name] = np.array([np.nan if r.get(name) is None else r[name] for r in rows])
    return TrackBlock(rows[0]["t"], rows[0]["sec_mark"], cols)


@dataclass(eq=False)
class Capture:
    """An RVE + OBU capture directory: the configs and end records, the other files as
    streams (``iter_*``) or, read on first use, as lists of records."""

    directory: Path
    rve_config: dict[str, Any]
    obu_config: dict[str, Any]
    rve_end: dict[str, Any] | None = None  # None: no end record (killed, or before 2026-11-27)
    obu_end: dict[str, Any] | None = None
    #: Files that end in a torn tail, as they were read: (file, byte offset, why).
    torn: list[Torn] = field(default_factory=list)

    def _torn(self, path: Path, offset: int, why: str) -> None:
        if not any(t[0] == path for t in self.torn):
            self.torn.append((path, offset, why))

    def _stream(self, name: str, required: bool = True) -> Iterator[dict[str, Any]]:
        files = segment_files(self.directory, name)
        if not files and required:
            raise _missing(self.directory / name)
        for _, path in files:
            yield from iter_lines(path, self._torn)

    def iter_truth(self) -> Iterator[dict[str, Any]]:
        return iter_lines(self.directory / RVE_TRUTH, self._torn)

    def iter_schedule(self) -> Iterator[dict[str, Any]]:
        return iter_lines(self.directory / RVE_SCHEDULE, self._torn)

    def iter_ticks(self) -> Iterator[dict[str, Any]]:
        return self._stream(OBU_TICKS)

    def iter_events(self) -> Iterator[dict[str, Any]]:
        return self._stream(OBU_EVENTS, required=False)

    def iter_rx(self) -> Iterator[dict[str, Any]]:
        return self._stream(OBU_RX)

    def iter_mbr(self) -> Iterator[dict[str, Any]]:
        return self._stream(OBU_MBR, required=False)

    def iter_verify(self) -> Iterator[dict[str, Any]]:
        """``obu.verify.jsonl`` (verify on demand: what became of the messages stepped
        unverified); nothing for a run without it."""
        return self._stream(OBU_VERIFY, required=False)

    def iter_findings(self) -> Iterator[dict[str, Any]]:
        return self._stream(OBU_MBD, required=False)

    def has(self, name: str) -> bool:
        """Whether the OBU wrote ``name`` (``obu.mbr.jsonl`` only with ``--mbd``)."""
        return bool(segment_files(self.directory, name))

    def iter_track_blocks(self) -> Iterator[TrackBlock]:
        """The tracks, one block per tick that had rows (:mod:`hil.capture.tracks`)."""
        files = segment_files(self.directory, OBU_TRACKS)
        if not files:
            raise _missing(self.directory / OBU_TRACKS)
        for _, path in files:
            if path.suffix == ".jsonl":  # before 2026-11-27
                rows: list[dict] = []
                for r in iter_lines(path, self._torn):
                    if rows and r["t"] != rows[0]["t"]:
                        yield _block_of(rows)
                        rows = []
                    rows.append(r)
                if rows:
                    yield _block_of(rows)
                continue
            try:
                yield from iter_blocks(path, self._torn)
            except ValueError as err:
                raise CaptureError(str(err)) from None

    def segments(self) -> list[int]:
        """The numbers of the OBU's segments in the directory (``[0]`` without a cap)."""
        return [k for k, _ in segment_files(self.directory, OBU_TICKS)]

    def missing_segments(self) -> list[int]:
        """Segments deleted under ``--capture-max-mb`` (gaps in the numbering)."""
        have = self.segments()
        return sorted(set(range(max(have) + 1)) - set(have)) if have else []

    @cached_property
    def truth(self) -> list[dict[str, Any]]:
        return list(self.iter_truth())

    @cached_property
    def schedule(self) -> list[dict[str, Any]]:
        return list(self.iter_schedule())

    @cached_property
    def ticks(self) -> list[dict[str, Any]]:
        return list(self.iter_ticks())

    @cached_property
    def events(self) -> list[dict[str, Any]]:
        return list(self.iter_events())

    @cached_property
    def tracks(self) -> list[dict[str, Any]]:
        """Every track row as :func:`hil.capture.schema.track_rows` made it."""
        return [r for b in self.iter_track_blocks() for r in block_rows(b)]

    @cached_property
    def rx(self) -> list[dict[str, Any]]:
        return list(self.iter_rx())

    @cached_property
    def mbr(self) -> list[dict[str, Any]] | None:
        """The misbehavior reports; None when the OBU ran without --mbd."""
        return list(self.iter_mbr()) if self.has(OBU_MBR) else None

    @cached_property
    def findings(self) -> list[dict[str, Any]] | None:
        """Every misbehavior finding, reported or not; None when the OBU ran without
        --mbd (before 2026-11-28 ``obu.mbr.jsonl`` held them all: then those)."""
        if self.has(OBU_MBD):
            return list(self.iter_findings())
        return self.mbr


def read_capture(directory: Path, rx: bool = True) -> Capture:
    """An RVE + OBU capture directory, checked: both configs, the RVE's truth and
    schedule, the OBU's ticks (at least one), tracks and ENU origin.  Nothing else is
    read yet; ``rx`` is kept for the callers that said they skip ``obu.rx`` (every
    stream is read only when asked for now)."""
    del rx
    directory = Path(directory)
    if not directory.is_dir():
        raise CaptureError(f"{directory}: not a directory")

    def end(name: str) -> dict[str, Any] | None:
        return read_json(directory / name) if (directory / name).is_file() else None

    cap = Capture(directory=directory, rve_config=read_json(directory / RVE_CONFIG),
                  obu_config=read_json(directory / OBU_CONFIG), rve_end=end(RVE_END),
                  obu_end=end(OBU_END))
    for name in (RVE_TRUTH, RVE_SCHEDULE):
        if not (directory / name).is_file():
            raise _missing(directory / name)
    for name in (OBU_TRACKS, OBU_RX):
        if not segment_files(directory, name):
            raise _missing(directory / name)
    if next(cap.iter_ticks(), None) is None:
        raise CaptureError(f"{directory}: the OBU recorded no tick")
    if cap.obu_config.get("origin") is None:
        raise CaptureError(f"{directory}: {OBU_CONFIG} has no ENU origin")
    return cap


def clock_offset(truth: Iterable[dict], first_tick: dict | Iterable[dict],
                 directory: Path) -> float:
    """OBU clock - dataset time (a whole number of minutes): the offset that puts the
    most of the OBU's first ticks (``first_tick``: one tick, or its first ticks; the first
    :data:`_OFFSET_TICKS` are used) on host samples of the RVE's truth with their secMark.
    One tick is not enough: an OBU that reads its own car ticks from its first GNSS fix,
    which may come before the replay's first host sample, and on a trip of a minute or
    more that tick's secMark names a sample a minute later."""
    ticks = [first_tick] if isinstance(first_tick, dict) else \
        list(itertools.islice(first_tick, _OFFSET_TICKS))
    host: dict[int, list[float]] = defaultdict(list)
    for r in truth:
        if r["host"]:
            host[sec_mark(r["t"])].append(r["t"])
    votes: Counter[float] = Counter()
    for tick in ticks:
        for t in host.get(tick["sec_mark"], ()):
            votes[round(tick["t"] - t, 3)] += 1
    if not votes:
        raise CaptureError(f"{directory}: the OBU's first tick (secMark "
                           f"{ticks[0]['sec_mark'] if ticks else None}) matches no host "
                           "sample of the RVE's truth")
    return votes.most_common(1)[0][0]


#: How many of the OBU's first ticks vote on its clock offset.
_OFFSET_TICKS = 50


def truth_in_frame(truth: Iterable[dict], origin) -> dict[str, tuple[list[dict], np.ndarray,
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
