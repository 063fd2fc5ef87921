"""Dataset readers: file *contents* -> normalised :class:`~catc.mobility.MobilityTable`.

Pure parsers (no file I/O): the caller reads the file and passes its text.  Each reader
raises :class:`ValueError` with a one-line message on content it cannot use.
"""

from __future__ import annotations

from catc.datasets import ngsim, nyc, openacc
from catc.mobility import MobilityTable

__all__ = ["KINDS", "detect_kind", "parse"]

KINDS = ("openacc", "ngsim", "nyc")


def detect_kind(text: str) -> str | None:
    """The dataset kind of file contents, or None when it is not one :data:`KINDS` reads.

    OpenACC: the first line starts with ``Date,`` and a ``Vehicle_order`` line follows.
    NGSIM leader/follower pairs: the header starts with ``pair_id,time,``.
    NYC CV pilot event: a JSON object with ``eventHeader`` and ``bsmList`` keys.
    """
    if nyc.looks_like(text):
        return "nyc"
    lines = text.lstrip("\ufeff").splitlines()
    if not lines:
        return None
    if lines[0].startswith("Date,") and any(ln.startswith("Vehicle_order,") for ln in lines[:10]):
        return "openacc"
    if lines[0].startswith("pair_id,time,"):
        return "ngsim"
    return None


def parse(kind: str, text: str, name: str) -> list[MobilityTable]:
    """Parse file contents of the given kind: always a list of tables (trips)."""
    if kind == "openacc":
        return [openacc.parse(text, name)]
    if kind == "ngsim":
        return ngsim.parse(text, name)
    if kind == "nyc":
        return [nyc.parse(text, name)]
    raise ValueError(f"unknown dataset kind {kind!r} (expected one of {', '.join(KINDS)})")
