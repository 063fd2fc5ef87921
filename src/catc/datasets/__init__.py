"""Dataset readers: file *contents* -> normalised :class:`~catc.mobility.MobilityTable`.

Pure parsers (no file I/O): the caller reads the file and passes its text, or its bytes
for the binary OBU logs of kind ``ode``.  Each reader raises :class:`ValueError` with a
one-line message on content it cannot use.
"""

from __future__ import annotations

from catc.datasets import ngsim, nyc, ode, openacc, spmd, sumo
from catc.mobility import MobilityTable

__all__ = ["KINDS", "detect_kind", "parse"]

KINDS = ("openacc", "ngsim", "nyc", "spmd", "ode", "sumo")


def detect_kind(text: str | bytes) -> str | None:
    """The dataset kind of file contents, or None when it is not one :data:`KINDS` reads.

    OpenACC: the first line starts with ``Date,`` and a ``Vehicle_order`` line follows.
    NGSIM leader/follower pairs: the header starts with ``pair_id,time,``.
    NYC CV pilot event: a JSON object with ``eventHeader`` and ``bsmList`` keys.
    SPMD BSM table: its header, or 19 numeric columns (:func:`catc.datasets.spmd.looks_like`).
    ODE: an OBU log (bytes), or JSON whose first two records are decoded BSMs.
    SUMO FCD: ``<fcd-export`` in the first KB, or a CSV header starting ``timestep_time``.
    """
    if isinstance(text, bytes):
        return "ode" if ode.looks_like(text) else None
    if nyc.looks_like(text):
        return "nyc"
    if ode.looks_like(text):
        return "ode"
    lines = text.lstrip("\ufeff").splitlines()
    if not lines:
        return None
    if lines[0].startswith("Date,") and any(ln.startswith("Vehicle_order,") for ln in lines[:10]):
        return "openacc"
    if lines[0].startswith("pair_id,time,"):
        return "ngsim"
    if sumo.looks_like(text):
        return "sumo"
    if spmd.looks_like(text):
        return "spmd"
    return None


def parse(kind: str, text: str | bytes, name: str) -> list[MobilityTable]:
    """Parse file contents of the given kind: always a list of tables (trips)."""
    if kind == "ode":
        return [ode.parse(text, name)]
    if isinstance(text, bytes):
        raise ValueError(f"{kind}: binary content (only ode reads binary OBU logs)")
    if kind == "openacc":
        return [openacc.parse(text, name)]
    if kind == "ngsim":
        return ngsim.parse(text, name)
    if kind == "nyc":
        return [nyc.parse(text, name)]
    if kind == "spmd":
        return spmd.parse(text, name)
    if kind == "sumo":
        return [sumo.parse(text, name)]
    raise ValueError(f"unknown dataset kind {kind!r} (expected one of {', '.join(KINDS)})")
