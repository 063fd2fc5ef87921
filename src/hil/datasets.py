"""Dataset specs on the command line (docs/architecture.md): ``PATH`` (kind detected from the
content), ``KIND:PATH``, or ``scenario:NAME`` (a built-in scenario, ``hil/scenarios``).  A
directory means every file in it that parses.  ``scene:SPEC`` (SPEC one of those, naming
one file), optionally ending in ``?host=ID``, is every vehicle of that file's trips in one
trip with one host (:mod:`catc.datasets.scene`; e.g.
``scene:ngsim:../shared/data/ngsim-i80-pairs?host=232``).  ``comma2k19:PATH`` is a
comma2k19 segment (a folder of NumPy arrays): its host and the vehicles its radar
tracked (:mod:`catc.datasets.comma2k19`).  ``dense:N:SPEC`` is every trip of SPEC with N
background vehicles on straight roads parallel to the host's (:mod:`catc.datasets.background`;
e.g. ``dense:1000:scenario:highway-braking``).  This is the one place that
reads dataset files, for ``rve run`` and for every ``captures`` command; the parsers in
:mod:`catc.datasets` work on their text, or on their bytes when the file is not text (an
OBU ``.bin`` log) or the kind is ``ode``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from catc.datasets import KINDS, detect_kind, parse, scene
from catc.mobility import MobilityTable
from hil.errors import InputError

__all__ = ["DatasetError", "load", "load_files", "load_table", "scenario_file"]


class DatasetError(InputError):
    """A dataset spec that cannot be loaded; ``str()`` is a one-line message."""


def scenario_file(name: str) -> Path:
    """The shipped FCD XML of built-in scenario ``name`` (``rve scenario`` makes them)."""
    path = resources.files("hil").joinpath("scenarios", f"{name}.fcd.xml")
    if not path.is_file():
        raise DatasetError(f"unknown scenario {name!r} (see rve scenario --help)")
    return Path(str(path))


#: The prefix of a scene spec, and what ends one to choose its host.
SCENE, HOST = "scene:", "?host="


def _resolve(spec: str) -> str:
    """``scenario:NAME`` as the ``sumo:`` spec of its file; other specs as they are."""
    if spec.startswith("scenario:"):
        return f"sumo:{scenario_file(spec.split(':', 1)[1])}"
    return spec


def _scene(spec: str) -> list[tuple[Path, list[MobilityTable]]]:
    """``scene:SPEC[?host=ID]``: the one table of every vehicle in the file SPEC names."""
    inner, host = spec[len(SCENE):], None
    if HOST in inner:
        inner, host = inner.rsplit(HOST, 1)
        if not host:
            raise DatasetError(f"dataset {spec!r}: no vehicle after {HOST}")
    if inner.startswith(SCENE):
        raise DatasetError(f"dataset {spec!r}: a scene of a scene")
    try:
        files = [(f, tables) for f, tables in load_files(inner) if tables]
    except DatasetError as err:
        raise DatasetError(f"{err} (in {spec!r})") from None
    if len(files) != 1:
        raise DatasetError(f"dataset {spec!r}: a scene takes the trips of one file; "
                           f"{inner!r} has {len(files)} ({', '.join(f.name for f, _ in files)})")
    f, tables = files[0]
    try:
        return [(f, [scene.scene(tables, f.stem, host)])]
    except ValueError as err:
        raise DatasetError(f"dataset {spec!r}: {err}") from None


#: The prefix of a comma2k19 segment (a folder of NumPy arrays, not a file to parse).
COMMA = "comma2k19:"


def _comma(spec: str) -> list[tuple[Path, list[MobilityTable]]]:
    """``comma2k19:PATH``: the segment at PATH (or the one segment in it), one trip
    (:mod:`catc.datasets.comma2k19`)."""
    from hil import comma2k19

    path = Path(spec[len(COMMA):])
    try:
        return [(path, [comma2k19.table(path)])]
    except InputError as err:
        raise DatasetError(f"dataset {spec!r}: {err}") from None
    except (ValueError, KeyError, IndexError) as err:
        raise DatasetError(f"dataset {spec!r}: not a usable comma2k19 segment: {err}") \
            from None


def _split(spec: str) -> tuple[str | None, Path]:
    kind, sep, rest = spec.partition(":")
    if sep and kind in KINDS:
        return kind, Path(rest)
    if sep and kind.isalpha() and len(kind) > 1 and not Path(spec).exists():
        raise DatasetError(f"dataset {spec!r}: unknown kind {kind!r}; known: "
                           f"{', '.join(KINDS)}")
    return None, Path(spec)


def _read(f: Path) -> str | bytes:
    """The file's text, or its bytes when it is not UTF-8 text."""
    try:
        return f.read_text()
    except UnicodeDecodeError:
        return f.read_bytes()


def load(spec: str) -> list[MobilityTable]:
    """Every trip in ``spec`` (a file, a directory of files, optionally ``KIND:`` first;
    ``scenario:NAME``; ``scene:...``, one trip)."""
    return [table for _, tables in load_files(spec) for table in tables]


#: The prefix of a trip with background traffic: ``dense:N:SPEC``.
DENSE = "dense:"


def _dense(spec: str) -> list[tuple[Path, list[MobilityTable]]]:
    """``dense:N:SPEC``: every trip of SPEC with N background vehicles on parallel roads
    (:mod:`catc.datasets.background`)."""
    count, sep, inner = spec[len(DENSE):].partition(":")
    try:
        n = int(count)
    except ValueError:
        n = -1
    if not sep or n < 0:
        raise DatasetError(f"dataset {spec!r}: dense:N:SPEC with N a vehicle count >= 0")
    from catc.datasets.background import with_background

    out = []
    for f, tables in load_files(inner):
        try:
            out.append((f, [with_background(t, n) for t in tables]))
        except ValueError as err:
            raise DatasetError(f"dataset {spec!r}: {err}") from None
    return out


def load_files(spec: str) -> list[tuple[Path, list[MobilityTable]]]:
    """Like :func:`load`, grouped by the file each trip came from (only files that parsed)."""
    if spec.startswith(DENSE):
        return _dense(spec)
    if spec.startswith(SCENE):
        return _scene(spec)
    if spec.startswith(COMMA):
        return _comma(spec)
    kind, path = _split(_resolve(spec))
    if not path.exists():
        raise DatasetError(f"dataset {spec!r}: no such file or directory")
    files = sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]
    out: list[tuple[Path, list[MobilityTable]]] = []
    for f in files:
        try:
            content = f.read_bytes() if kind == "ode" else _read(f)
        except OSError:
            if path.is_dir():
                continue
            raise DatasetError(f"dataset {f}: not a readable file") from None
        detected = detect_kind(content)
        if path.is_dir() and (detected is None or kind not in (None, detected)):
            continue  # READMEs, provenance notes, files of another kind
        k = kind or detected
        if k is None:
            raise DatasetError(f"dataset {f}: unknown format; name it as KIND:PATH with KIND "
                               f"in {', '.join(KINDS)}")
        try:
            out.append((f, parse(k, content, f.stem)))
        except ValueError as err:
            raise DatasetError(f"dataset {f}: {err}") from None
    if not any(tables for _, tables in out):
        raise DatasetError(f"dataset {spec!r}: no trips found")
    return out


def load_table(spec: str, trip: str | None) -> MobilityTable:
    """The one trip of ``spec`` that ``rve run`` replays (``scenario:NAME`` too): ``trip``
    by name, or the first.  DatasetError (one line) when it cannot be loaded."""
    given = spec
    tables = load(spec)
    if trip is None:
        return tables[0]
    for t in tables:
        if t.name == trip:
            return t
    more = f" and {len(tables) - 10} more" if len(tables) > 10 else ""
    raise DatasetError(f"dataset {given!r} has no trip {trip!r}; trips: "
                       f"{', '.join(t.name for t in tables[:10])}{more}")
