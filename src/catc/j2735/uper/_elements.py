"""J2735 data elements and frames that several parts of the BSM share, in UPER (X.691).

``TransmissionState`` (3 bits, raw 7 unavailable), ``PositionalAccuracy`` (semiMajor,
semiMinor, orientation: 32 bits), ``DDateTime`` (seven OPTIONAL components, no extension
marker) and the extension additions of an extensible SEQUENCE (X.691 §19.7-19.9), which
every part skips the same way.  See ``catc/j2735/bsm.asn``.
"""

from __future__ import annotations

from catc import units as u
from catc.bsm import DDateTime, PositionalAccuracy, TransmissionState
from catc.j2735.bits import BitReader, BitWriter

TRANSMISSION = (*TransmissionState, None)  # raw 7 = unavailable


def scaled(quantity: u.Quantity, raw: int) -> float | None:
    """A raw field in SI units, None for its "unavailable" code."""
    return None if raw == quantity.unavailable else raw * quantity.lsb


def accuracy_from_raw(raw: int) -> PositionalAccuracy:
    """``PositionalAccuracy`` from its 32 bits (semiMajor 8, semiMinor 8, orientation 16)."""
    orient = raw & 0xFFFF
    smin = (raw >> 16) & 0xFF
    smaj = raw >> 24
    return PositionalAccuracy(
        None if smaj == 255 else smaj * 0.05,
        None if smin == 255 else smin * 0.05,
        None if orient == 65535 else orient * u.ORIENTATION.lsb,
    )


def accuracy_raw(a: PositionalAccuracy) -> int:
    """The 32 bits of ``PositionalAccuracy``."""
    return ((u.SEMI_AXIS.to_raw(a.semi_major) << 24) | (u.SEMI_AXIS.to_raw(a.semi_minor) << 16)
            | u.ORIENTATION.to_raw(a.orientation))


def skip_extensions(r: BitReader, what: str) -> None:
    """Skip the extension additions of an extensible SEQUENCE (X.691 §19.7-19.9)."""
    count = r.small_length(f"{what} extension bitmap")
    present = r.read(count, f"{what} extension bitmap")
    for _ in range(bin(present).count("1")):
        r.open_type(f"{what} extension addition")


#: DDateTime components: name, lower bound, upper bound, bits (all OPTIONAL, no extension).
_DDATETIME = (("year", 0, 4095, 12), ("month", 0, 12, 4), ("day", 0, 31, 5),
              ("hour", 0, 31, 5), ("minute", 0, 60, 6), ("second", 0, 65535, 16),
              ("offset", -840, 840, 11))


def read_ddatetime(r: BitReader) -> DDateTime:
    """``DDateTime``: a 7-bit presence bitmap, then the components present."""
    present = r.read(7, "DDateTime preamble")
    values = {}
    for i, (name, lo, hi, nbits) in enumerate(_DDATETIME):
        if present & (1 << (6 - i)):
            values[name] = r.constrained(lo, hi, nbits, f"DDateTime.{name}")
    return DDateTime(**values)


def write_ddatetime(w: BitWriter, t: DDateTime) -> None:
    """``DDateTime``: the components that are not None."""
    values = [getattr(t, name) for name, *_ in _DDATETIME]
    w.write(sum(1 << (6 - i) for i, v in enumerate(values) if v is not None), 7)
    for (name, lo, hi, nbits), v in zip(_DDATETIME, values, strict=True):
        if v is not None:
            w.constrained(v, lo, hi, nbits, f"DDateTime.{name}")
