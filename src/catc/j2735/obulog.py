"""OBU binary log records (WYDOT/CDOT connected-vehicle pilots, as imported by the USDOT ODE).

A log file is a plain sequence of packed little-endian records, each a small header
followed by ``length`` payload octets; the payload is normally an IEEE 1609.2
``Ieee1609Dot2Data`` carrying a UPER MessageFrame (see :mod:`catc.j2735.ieee1609`).
Layouts, from the ODE importer (usdot-jpo-ode/jpo-ode ``importer/parser``:
BsmLogFileParser, RxMsgFileParser, DistressMsgFileParser, LocationParser, TimeParser,
SecurityResultCodeParser, PayloadParser), offsets in octets::

  location (16) = lat int32 1e-7 deg | lon int32 1e-7 deg | elevation int32 0.1 m
                  | speed uint16 0.02 m/s | heading uint16 0.0125 deg
  time (6)      = utcTimeInSec uint32 | mSec uint16

  bsmTx, bsmLogDuringEvent (BsmLogFileParser), 26-octet header:
    0 direction uint8 (0 EV, 1 RV) | 1 location | 17 time | 23 securityResultCode uint8
    | 24 length uint16 | 26 payload
  rxMsg (RxMsgFileParser, 2018 on), 26-octet header:
    0 rxSource uint8 | 1 location | 17 time | 23 securityResultCode uint8 | 24 length | 26
  rxMsg (RxMsgFileParser, 2017 ``receivedMsgRecord`` C struct), 29-octet header:
    0 location | 16 time | 22 rxSource uint32 (C enum) | 26 verificationStatus int8
    | 27 length uint16 | 29 payload
  dnMsg (DistressMsgFileParser), 25-octet header:
    0 location | 16 time | 22 securityResultCode uint8 | 23 length uint16 | 25 payload

Enumerations: rxSource RSU, SAT, RV, SNMP, NA, unknown; securityResultCode is the ODE
``OdeLogMetadata.SecurityResultCode`` list (0 ``success``, 1 ``unknown``, ...).  The
J2735 "unavailable" values of the location fields decode to None.

Checked record by record against the ODE's decoded output: ``bsmLogDuringEvent.bin``
(222 records, current BSM layout) and ``rxMsg_BSM.bin`` (228 records, 2017 rxMsg
layout); see tests/test_obulog.py.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from catc.errors import DecodeError
from catc.j2735 import ieee1609

DIRECTIONS = ("EV", "RV")
RX_SOURCES = ("RSU", "SAT", "RV", "SNMP", "NA", "unknown")
SECURITY_RESULT_CODES = (
    "success",
    "unknown",
    "inconsistentInputParameters",
    "spduParsingInvalidInput",
    "spduParsingUnsupportedCriticalInformationField",
    "spduParsingCertificateNotFound",
    "spduParsingGenerationTimeNotAvailable",
    "spduParsingGenerationLocationNotAvailable",
    "spduCertificateChainNotEnoughInformationToConstructChain",
    "spduCertificateChainChainEndedAtUntrustedRoot",
    "spduCertificateChainChainWasTooLongForImplementation",
    "spduCertificateChainCertificateRevoked",
    "spduCertificateChainOverdueCRL",
    "spduCertificateChainInconsistentExpiryTimes",
    "spduCertificateChainInconsistentStartTimes",
    "spduCertificateChainInconsistentChainPermissions",
    "spduCryptoVerificationFailure",
    "spduConsistencyFutureCertificateAtGenerationTime",
    "spduConsistencyExpiredCertificateAtGenerationTime",
    "spduConsistencyExpiryDateTooEarly",
    "spduConsistencyExpiryDateTooLate",
    "spduConsistencyGenerationLocationOutsideValidityRegion",
    "spduConsistencyNoGenerationLocation",
    "spduConsistencyUnauthorizedPSID",
    "spduInternalConsistencyExpiryTimeBeforeGenerationTime",
    "spduInternalConsistencyextDataHashDoesntMatch",
    "spduInternalConsistencynoExtDataHashProvided",
    "spduInternalConsistencynoExtDataHashPresent",
    "spduLocalConsistencyPSIDsDontMatch",
    "spduLocalConsistencyChainWasTooLongForSDEE",
    "spduRelevanceGenerationTimeTooFarInPast",
    "spduRelevanceGenerationTimeTooFarInFuture",
    "spduRelevanceExpiryTimeInPast",
    "spduRelevanceGenerationLocationTooDistant",
    "spduRelevanceReplayedSpdu",
    "spduCertificateExpired",
)


@dataclass(frozen=True)
class _Layout:
    """A record layout: the header fields in order, read with one little-endian struct
    whose last field is the payload ``length`` (uint16); the payload follows."""

    fields: tuple[str, ...]
    header: struct.Struct


def _layout(*parts: tuple[str, str]) -> _Layout:
    """A layout from (field, struct format character) pairs, ``length`` appended."""
    parts = (*parts, ("length", "H"))
    return _Layout(tuple(name for name, _ in parts),
                   struct.Struct("<" + "".join(code for _, code in parts)))


_LOCATION = (("lat", "i"), ("lon", "i"), ("elevation", "i"), ("speed", "H"), ("heading", "H"))
_TIME = (("utcTimeInSec", "I"), ("mSec", "H"))

_BSM_LOG = _layout(("direction", "B"), *_LOCATION, *_TIME, ("securityResultCode", "B"))
_RX_MSG = _layout(("rxSource", "B"), *_LOCATION, *_TIME, ("securityResultCode", "B"))
_RX_MSG_2017 = _layout(*_LOCATION, *_TIME, ("rxSource", "I"), ("verificationStatus", "b"))
_DN_MSG = _layout(*_LOCATION, *_TIME, ("securityResultCode", "B"))

#: The layouts each ODE record type may have been logged with.
_LAYOUTS: dict[str, tuple[_Layout, ...]] = {
    "bsmLogDuringEvent": (_BSM_LOG,),
    "bsmTx": (_BSM_LOG,),
    "rxMsg": (_RX_MSG, _RX_MSG_2017),
    "dnMsg": (_DN_MSG,),
}
#: What kind=None tries, in order; on a tie the first wins (bsmTx is indistinguishable
#: from bsmLogDuringEvent, and an rxMsg log whose rxSource is only ever 0 or 1 from both).
_AUTO = (
    ("bsmLogDuringEvent", _BSM_LOG),
    ("rxMsg", _RX_MSG),
    ("rxMsg", _RX_MSG_2017),
    ("dnMsg", _DN_MSG),
)


@dataclass(frozen=True)
class LogRecord:
    """One OBU log record: its header in SI units and degrees, and its payload."""

    kind: str
    direction: str | None  # "EV" | "RV" for BSM logs
    lat: float | None
    lon: float | None
    elevation_m: float | None
    speed_mps: float | None
    heading_deg: float | None
    utc_time: float  # seconds since the Unix epoch, msec included
    security_result: str | int  # ODE SecurityResultCode name; raw verificationStatus (2017)
    rx_source: str | None
    payload: bytes
    frame: bytes  # the MessageFrame: unwrapped 1609.2, else the payload itself


def _scaled(raw: int, unavailable: int, lo: int, hi: int, per_unit: int, name: str) -> float | None:
    """``raw / per_unit`` (exactly rounded), None for the J2735 unavailable value."""
    if raw == unavailable:
        return None
    if not lo <= raw <= hi:
        raise DecodeError("out-of-range", f"OBU log {name} {raw} outside {lo}..{hi}")
    return raw / per_unit


def _enum(names: tuple[str, ...], raw: int, name: str) -> str:
    if raw >= len(names):
        raise DecodeError("out-of-range", f"OBU log {name} {raw} (known: 0..{len(names) - 1})")
    return names[raw]


def _record(c: dict[str, Any], kind: str) -> LogRecord:
    """The record of the header fields and payload ``c`` of one framed record."""
    if c["mSec"] > 999:
        raise DecodeError("out-of-range", f"OBU log mSec {c['mSec']}")
    payload = c["payload"]
    frame = ieee1609.unwrap(payload).frame if ieee1609.looks_like_1609(payload) else payload
    if "verificationStatus" in c:
        security: str | int = c["verificationStatus"]
    else:
        security = _enum(SECURITY_RESULT_CODES, c["securityResultCode"], "securityResultCode")
    return LogRecord(
        kind=kind,
        direction=_enum(DIRECTIONS, c["direction"], "direction") if "direction" in c else None,
        lat=_scaled(c["lat"], 900000001, -900000000, 900000000, 10_000_000, "latitude"),
        lon=_scaled(c["lon"], 1800000001, -1799999999, 1800000000, 10_000_000, "longitude"),
        elevation_m=_scaled(c["elevation"], -4096, -4095, 61439, 10, "elevation"),
        speed_mps=_scaled(c["speed"], 8191, 0, 8190, 50, "speed"),
        heading_deg=_scaled(c["heading"], 28800, 0, 28799, 80, "heading"),
        utc_time=c["utcTimeInSec"] + c["mSec"] / 1000,
        security_result=security,
        rx_source=_enum(RX_SOURCES, c["rxSource"], "rxSource") if "rxSource" in c else None,
        payload=payload,
        frame=frame,
    )


_Fit = tuple[list[LogRecord], DecodeError | None]


def _frame_record(data: bytes, start: int, layout: _Layout) -> dict[str, Any] | None:
    """The header fields and payload of the record at ``start``; None if cut short."""
    header_end = start + layout.header.size
    if header_end > len(data):
        return None
    fields = dict(zip(layout.fields, layout.header.unpack_from(data, start), strict=True))
    end = header_end + fields["length"]
    if end > len(data):
        return None
    fields["payload"] = data[header_end:end]
    return fields


def _split(
    data: bytes, layout: _Layout, limit: int | None = None
) -> tuple[list[dict[str, Any]], DecodeError | None]:
    """The framed records of ``data`` (headers parsed), and the error that ended framing."""
    data = bytes(data)
    size, start, parsed = len(data), 0, []
    while start < size and (limit is None or len(parsed) < limit):
        fields = _frame_record(data, start, layout)
        if fields is None:
            return parsed, DecodeError(
                "truncated",
                f"OBU log record {len(parsed)} at offset {start}: only {size - start} octets left",
            )
        parsed.append(fields)
        start += layout.header.size + fields["length"]
    return parsed, None


def _fit(data: bytes, kind: str, layout: _Layout, limit: int | None = None) -> _Fit | None:
    """Records and framing error, or None unless every record is a sane header + frame."""
    parsed, tail = _split(data, layout, limit)
    try:
        records = [_record(c, kind) for c in parsed]
    except DecodeError:
        return None
    if not all(r.payload[:1] == b"\x00" or ieee1609.looks_like_1609(r.payload) for r in records):
        return None
    return records, tail


def _detect(data: bytes, candidates: tuple[tuple[str, _Layout], ...]) -> _Fit:
    """The candidate layout that frames the whole file (or all but a truncated tail)."""
    best: tuple[tuple[bool, int], _Fit] | None = None
    for kind, layout in candidates:
        fit = _fit(data, kind, layout)
        if fit is None or (fit[1] is not None and not fit[0]):
            continue
        rank = (fit[1] is None, len(fit[0]))
        if best is None or rank > best[0]:
            best = (rank, fit)
    if best is None:
        raise DecodeError("garbage", "not an OBU log: no record layout (bsmLog, rxMsg, dnMsg) fits")
    return best[1]


def iter_records(data: bytes, kind: str | None = None) -> Iterator[LogRecord]:
    """Yield the records of an OBU log; ``kind`` None detects the layout from the content.

    ``kind`` is an ODE record type: bsmLogDuringEvent, bsmTx, rxMsg or dnMsg.  A
    truncated last record raises DecodeError("truncated") after the complete ones.
    """
    if kind is not None and kind not in _LAYOUTS:
        raise DecodeError("unsupported", f"OBU log kind {kind!r} (known: {', '.join(_LAYOUTS)})")
    if kind is not None and len(_LAYOUTS[kind]) == 1:
        parsed, tail = _split(data, _LAYOUTS[kind][0])
        for c in parsed:
            yield _record(c, kind)
    else:
        candidates = _AUTO if kind is None else tuple((kind, lay) for lay in _LAYOUTS[kind])
        records, tail = _detect(data, candidates)
        yield from records
    if tail is not None:
        raise tail


def looks_like_obulog(data: bytes) -> bool:
    """Cheap sniff: some layout frames a complete first record with a sane header + frame."""
    for kind, layout in _AUTO:
        fit = _fit(data, kind, layout, limit=1)
        if fit is not None and fit[0]:
            return True
    return False
