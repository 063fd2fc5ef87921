"""``obu.tracks.bin``: every tracked RV at every tick, compactly (issue 27).

The JSON lines it replaces took ~280 octets a row; a storm of spoofed ids that fills the
OBU's table (1,000 RVs) wrote 290 MB a minute of them.  Here a row takes a few octets,
because a tick's rows are written as what changed since the tick before:

* **File**: the magic ``CATCTRK1``, then one block per tick that has rows:
  ``b"TBLK"``, the payload's length and its CRC-32 (``<4sII``), then the payload,
  zlib-compressed.
* **Payload**: ``<diII`` tick time, host secMark, rows ``n``, new source names; each new
  name as a length octet and UTF-8 (the names, ``bsm`` and the predictors', are numbered
  in order of first use in the file); one dtype code octet per column (0-3: int8, 16, 32,
  64, the narrowest that holds the column); then the columns: ``ref``, the TemporaryIDs
  of the new rows (uint32), and one residual column per field of :data:`FIELDS`.
* **ref**: each row's index among the previous block's rows, -1 for an RV that was not
  in it, stored as ``s[i] - s[i-1] - 1`` with ``s = ref + 1`` (zeros while the map's order
  holds).  A row with a ref takes its TemporaryID from there.
* **Fields** are integers: positions in 1e-7 m, the other measures in 1e-3 (the digits
  :func:`hil.capture.schema.track_rows` rounds to), non-finite values as -2**63; flags,
  lanes, zone codes and the source's number as they are.  A measure is stored as its
  residual against ``2 v[k-1] - v[k-2]`` of the same RV (a straight-line extrapolation:
  zero for a track moved by a constant-velocity prediction, up to rounding), a code against
  ``v[k-1]``; a new RV's values against zero.  Arithmetic is int64, wrapping.

A block depends on the one before, so the file is read from its start (a segment of a
capped capture starts afresh); a torn last block (a kill, a full disk) ends the reading
there and is reported with its byte offset.  Read back, the values are those the JSON lines
held (``k / 1e7``, ``k / 1e3``: the same decimal, to the last bit but in a tie of
rounding; a ``-0.0`` reads ``0.0``), so every figure of ``captures score`` is unchanged.
:func:`read_columns` gives a file as numpy columns (``pandas.DataFrame(read_columns(path))``
is a table of it).
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.capture.writers import CaptureFile

__all__ = ["FIELDS", "MAGIC", "TrackBlock", "TrackWriter", "block_rows", "iter_blocks",
           "read_columns"]

MAGIC = b"CATCTRK1"
_BLOCK = struct.Struct("<4sII")
_BLOCK_MAGIC = b"TBLK"
_HEAD = struct.Struct("<diII")
#: The measures (extrapolated) with their scale, then the codes (as they are).
MEASURES = (("x", 1e7), ("y", 1e7), ("speed", 1e3), ("heading", 1e3), ("age", 1e3),
            ("s", 1e3), ("d", 1e3), ("predicted_x", 1e7), ("predicted_y", 1e7))
CODES = ("fresh", "lane", "ahead", "lateral", "direction", "p_ahead", "p_lateral",
         "p_direction", "source")
FIELDS = tuple(name for name, _ in MEASURES) + CODES
_BOOLS = ("fresh", "ahead", "p_ahead")
_DTYPES = (np.int8, np.int16, np.int32, np.int64)
_NAN = np.iinfo(np.int64).min
_LIMIT = float(2**62)
_LEVEL = 6  # zlib: 6 is ~20 % smaller than 1 on storm rows, at ~0.3 ms a 1,000-row tick

#: ``(file, byte offset)`` of a torn tail, to whoever reads.
TornCallback = Callable[[Path, int, str], None]


def _fixed(values: Any, scale: float) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64) * scale
    out = np.full(v.shape, _NAN, dtype=np.int64)
    ok = np.isfinite(v) & (np.abs(v) < _LIMIT)
    out[ok] = np.rint(v[ok]).astype(np.int64)
    return out


def _narrow(a: np.ndarray) -> tuple[int, bytes]:
    if not len(a):
        return 0, b""
    lo, hi = int(a.min()), int(a.max())
    for code, dt in enumerate(_DTYPES):
        info = np.iinfo(dt)
        if info.min <= lo and hi <= info.max:
            return code, a.astype(dt).tobytes()
    raise AssertionError("int64 holds every int64")


class _State:
    """The previous block's rows: ids, and per field the last value and the last step."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, dtype=np.uint32)
        self.last: dict[str, np.ndarray] = {f: np.zeros(0, np.int64) for f in FIELDS}
        self.step: dict[str, np.ndarray] = {f: np.zeros(0, np.int64) for f in FIELDS}
        self.sources: list[str] = []

    def refs(self, ids: np.ndarray) -> np.ndarray:
        """Each id's row in the previous block, -1 where it was not there."""
        if not len(self.ids) or not len(ids):
            return np.full(len(ids), -1, dtype=np.int64)
        order = np.argsort(self.ids, kind="stable")
        pos = np.minimum(np.searchsorted(self.ids[order], ids), len(order) - 1)
        return np.where(self.ids[order][pos] == ids, order[pos], -1).astype(np.int64)

    def predict(self, name: str, ref: np.ndarray, measure: bool) -> np.ndarray:
        has = ref >= 0
        r = np.where(has, ref, 0)
        last = self.last[name]
        pred = np.zeros(len(ref), dtype=np.int64)
        if len(last):
            pred = np.where(has, last[r], 0)
            if measure:
                pred = np.where(has, pred + self.step[name][r], 0)
        return pred

    def advance(self, name: str, ref: np.ndarray, value: np.ndarray) -> None:
        has = ref >= 0
        last = self.last[name]
        before = np.where(has, last[np.where(has, ref, 0)], 0) if len(last) else 0
        self.step[name] = np.where(has, value - before, 0)
        self.last[name] = value


def _encode_ref(ref: np.ndarray) -> np.ndarray:
    s = ref + 1
    return np.diff(s, prepend=0) - 1


def _decode_ref(e: np.ndarray) -> np.ndarray:
    return np.cumsum(e.astype(np.int64) + 1) - 1


class TrackWriter(CaptureFile):
    """``obu.tracks.bin`` written a tick at a time: :meth:`write` the columns of
    :func:`hil.capture.schema.track_columns` (one block), :meth:`flush`, :meth:`close`.
    ``tell()`` is the file's size so far."""

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(path, "wb")
        self._put(MAGIC)
        self._state = _State()
        self.rows = 0

    def write(self, t: float, sec_mark: int, cols: dict[str, Any]) -> None:
        ids = np.asarray(cols["id"]).astype(np.uint32)
        n = len(ids)
        if n == 0:
            return
        st = self._state
        names = [str(s) for s in cols["source"]]
        new_names = [s for s in dict.fromkeys(names) if s not in st.sources]
        st.sources.extend(new_names)
        index = {s: i for i, s in enumerate(st.sources)}
        values = {name: _fixed(cols[name], scale) for name, scale in MEASURES}
        for name in CODES[:-1]:
            values[name] = np.asarray(cols[name]).astype(np.int64)
        values["source"] = np.array([index[s] for s in names], dtype=np.int64)
        ref = st.refs(ids)
        codes, parts = [], []
        for column in (_encode_ref(ref),):
            code, raw = _narrow(column)
            codes.append(code)
            parts.append(raw)
        parts.append(ids[ref < 0].astype("<u4").tobytes())
        measures = {name for name, _ in MEASURES}
        for name in FIELDS:
            residual = values[name] - st.predict(name, ref, name in measures)
            code, raw = _narrow(residual)
            codes.append(code)
            parts.append(raw)
            st.advance(name, ref, values[name])
        st.ids = ids
        head = [_HEAD.pack(float(t), int(sec_mark), n, len(new_names))]
        for s in new_names:
            b = s.encode()
            head.append(bytes([len(b)]) + b)
        payload = zlib.compress(b"".join(head) + bytes(codes) + b"".join(parts), _LEVEL)
        self._put(_BLOCK.pack(_BLOCK_MAGIC, len(payload), zlib.crc32(payload)) + payload)
        self.rows += n



@dataclass(frozen=True)
class TrackBlock:
    """One tick's rows: its time, the host's secMark, and the columns: ``id`` (uint32),
    the measures (float64, NaN where not finite), ``fresh, ahead, p_ahead`` (bool), the
    other codes (int64) and ``source`` (str objects)."""

    t: float
    sec_mark: int
    cols: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.cols["id"])


def _decode(payload: bytes, st: _State) -> TrackBlock:
    raw = memoryview(zlib.decompress(payload))
    t, sec_mark, n, n_names = _HEAD.unpack_from(raw, 0)
    pos = _HEAD.size
    for _ in range(n_names):
        k = raw[pos]
        st.sources.append(bytes(raw[pos + 1:pos + 1 + k]).decode())
        pos += 1 + k
    codes = raw[pos:pos + 1 + len(FIELDS)]
    pos += 1 + len(FIELDS)

    def column(code: int, count: int) -> np.ndarray:
        nonlocal pos
        dt = np.dtype(_DTYPES[code]).newbyteorder("<")
        a = np.frombuffer(raw, dtype=dt, count=count, offset=pos).astype(np.int64)
        pos += count * dt.itemsize
        return a

    ref = _decode_ref(column(codes[0], n))
    new = ref < 0
    n_new = int(new.sum())
    new_ids = np.frombuffer(raw, dtype="<u4", count=n_new, offset=pos)
    pos += 4 * n_new
    ids = np.empty(n, dtype=np.uint32)
    ids[new] = new_ids
    if (~new).any():
        ids[~new] = st.ids[ref[~new]]
    measures = dict(MEASURES)
    cols: dict[str, np.ndarray] = {"id": ids}
    for i, name in enumerate(FIELDS, start=1):
        value = column(codes[i], n) + st.predict(name, ref, name in measures)
        st.advance(name, ref, value)
        if name in measures:
            out = value / measures[name]
            out[value == _NAN] = np.nan
            cols[name] = out
        elif name == "source":
            cols[name] = np.array(st.sources, dtype=object)[value] if n else \
                np.zeros(0, dtype=object)
        else:
            cols[name] = value.astype(bool) if name in _BOOLS else value
    st.ids = ids
    return TrackBlock(t, sec_mark, cols)


def iter_blocks(path: str | os.PathLike, torn: TornCallback | None = None
                ) -> Iterator[TrackBlock]:
    """The blocks of one ``obu.tracks.bin`` file in order.  A torn tail (a block cut off,
    or the last block's checksum wrong) ends the file: ``torn(path, offset, why)`` is
    called with the offset of the block where it starts.  A bad block before the last one
    raises ValueError."""
    path = Path(path)
    with open(path, "rb") as f:
        data = f.read()
    if data[:len(MAGIC)] != MAGIC:
        if len(data) < len(MAGIC) and MAGIC.startswith(data):
            if torn is not None:
                torn(path, 0, "file header cut off")
            return
        raise ValueError(f"{path}: not an obu.tracks.bin file (no {MAGIC.decode()} header)")
    st = _State()
    pos = len(MAGIC)
    while pos < len(data):
        if pos + _BLOCK.size > len(data):
            if torn is not None:
                torn(path, pos, "block header cut off")
            return
        magic, length, crc = _BLOCK.unpack_from(data, pos)
        end = pos + _BLOCK.size + length
        if magic != _BLOCK_MAGIC:
            raise ValueError(f"{path}: byte {pos}: not a block")
        if end > len(data):
            if torn is not None:
                torn(path, pos, "block cut off")
            return
        payload = data[pos + _BLOCK.size:end]
        if zlib.crc32(payload) != crc:
            if end == len(data):
                if torn is not None:
                    torn(path, pos, "last block's checksum is wrong")
                return
            raise ValueError(f"{path}: byte {pos}: block checksum wrong")
        yield _decode(payload, st)
        pos = end


def block_rows(block: TrackBlock) -> list[dict[str, Any]]:
    """A block's rows as :func:`hil.capture.schema.track_rows` made them (the JSON lines
    of ``obu.tracks.jsonl``)."""
    c = block.cols
    lists = {k: v.tolist() for k, v in c.items()}
    return [{"t": block.t, "sec_mark": block.sec_mark, "id": f"{lists['id'][i]:08X}",
             "x": lists["x"][i], "y": lists["y"][i], "speed": lists["speed"][i],
             "heading": lists["heading"][i], "source": lists["source"][i],
             "age": lists["age"][i], "fresh": lists["fresh"][i], "lane": lists["lane"][i],
             "zone": [lists["ahead"][i], lists["lateral"][i], lists["direction"][i]],
             "s": lists["s"][i], "d": lists["d"][i],
             "predicted_x": lists["predicted_x"][i], "predicted_y": lists["predicted_y"][i],
             "predicted_zone": [lists["p_ahead"][i], lists["p_lateral"][i],
                                lists["p_direction"][i]]}
            for i in range(len(block))]


def read_columns(path: str | os.PathLike, torn: TornCallback | None = None
                 ) -> dict[str, np.ndarray]:
    """A whole ``obu.tracks.bin`` file as columns, ``t`` and ``sec_mark`` included: one
    entry per row, in order."""
    blocks = list(iter_blocks(path, torn))
    out: dict[str, np.ndarray] = {
        "t": np.concatenate([np.full(len(b), b.t) for b in blocks]) if blocks
        else np.zeros(0),
        "sec_mark": np.concatenate([np.full(len(b), b.sec_mark, dtype=np.int64)
                                    for b in blocks]) if blocks else np.zeros(0, np.int64)}
    for name in ("id", *FIELDS):
        parts = [b.cols[name] for b in blocks]
        out[name] = np.concatenate(parts) if parts else np.zeros(0)
    return out
