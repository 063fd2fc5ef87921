"""GNSS fixes as NMEA 0183, both ways (no I/O): what a receiver sends an OBU.

:func:`to_nmea` writes one fix as the sentences a u-blox or any NMEA receiver sends each
epoch: GGA (position, altitude, fix quality, satellites, HDOP), RMC (date and time,
speed and course over ground), VTG (course and speed again, km/h too) and, when the fix
has its position's standard deviations, GST.  :class:`NmeaStream` reads them back from a
byte stream (a serial line, a pty, gpsd's raw mode, UDP), one :class:`Fix` per epoch:
it is emitted as soon as the epoch's RMC and GGA have both come (with its GST if that
came first; :func:`to_nmea` sends it first), or, from a receiver that sends no GGA, at
the next epoch's first sentence.
Bad input never raises: a sentence with a bad checksum, a line that is no NMEA, an
unknown sentence or a line too long are counted (:attr:`NmeaStream.counters`) and
dropped.  :mod:`pynmeagps` encodes and decodes the sentences.

Precision (pynmeagps' defaults, as most receivers): latitude and longitude in minutes
to 5 decimals (2 cm at most), time to 10 ms, speed to 0.001 knot, altitude to 1 cm.
"""

from __future__ import annotations

import datetime as dt
import math
from collections import Counter
from dataclasses import dataclass, field

from pynmeagps import GET, VALCKSUM, NMEAMessage, NMEAReader
from pynmeagps.exceptions import NMEAMessageError, NMEAParseError, NMEATypeError

__all__ = ["DEFAULT_UTC_BASE", "Fix", "NmeaStream", "to_nmea"]

#: The UTC time (unix s) of dataset time 0 when a dataset has none of its own
#: (``MobilityTable.meta["utc_base"]``): 2026-01-01T00:00:00Z.  A whole number of minutes,
#: so a GNSS fix at dataset time ``t`` (UTC ``base + t``) has the secMark of ``t``, as the
#: RVs' BSMs have.
DEFAULT_UTC_BASE = 1_767_225_600

_KNOT = 1852.0 / 3600.0
_MAX_LINE = 120  # NMEA 0183 caps a sentence at 82 characters; room for long talkers


@dataclass(frozen=True)
class Fix:
    """One GNSS epoch: UTC time (unix s), WGS-84 position (deg, m above the ellipsoid's
    geoid as GGA has it), speed (m/s) and course (deg from true north) over ground, and
    the receiver's quality figures (None: not sent)."""

    t_unix: float
    lat: float
    lon: float
    alt_m: float | None = None
    speed_mps: float | None = None
    course_deg: float | None = None
    quality: int = 1
    num_sv: int | None = None
    hdop: float | None = None
    std_lat_m: float | None = None
    std_lon_m: float | None = None


def _utc(t_unix: float) -> dt.datetime:
    return dt.datetime.fromtimestamp(round(t_unix, 2), dt.UTC)


def to_nmea(fix: Fix, talker: str = "GN") -> list[bytes]:
    """The NMEA sentences of ``fix``: GST (with standard deviations), GGA, RMC, VTG."""
    when = _utc(fix.t_unix)
    ns, ew = ("N" if fix.lat >= 0 else "S"), ("E" if fix.lon >= 0 else "W")
    pos = {"lat": fix.lat, "NS": ns, "lon": fix.lon, "EW": ew}
    knots = "" if fix.speed_mps is None else round(fix.speed_mps / _KNOT, 3)
    cog = "" if fix.course_deg is None else round(fix.course_deg % 360.0, 2)
    out = []
    if fix.std_lat_m is not None and fix.std_lon_m is not None:
        out.append(NMEAMessage(talker, "GST", GET, time=when.time(), rangeRms="",
                               stdMajor="", stdMinor="", orient="",
                               stdLat=round(fix.std_lat_m, 3), stdLong=round(fix.std_lon_m, 3),
                               stdAlt=""))
    out += [
        NMEAMessage(talker, "GGA", GET, time=when.time(), **pos, quality=fix.quality,
                    numSV="" if fix.num_sv is None else fix.num_sv,
                    HDOP="" if fix.hdop is None else round(fix.hdop, 2),
                    alt="" if fix.alt_m is None else round(fix.alt_m, 2), altUnit="M",
                    sep="", sepUnit="M", diffAge="", diffStation=""),
        NMEAMessage(talker, "RMC", GET, time=when.time(), status="A", **pos, spd=knots,
                    cog=cog, date=when.date(), mv="", mvEW="", posMode="A", navStatus="V"),
        NMEAMessage(talker, "VTG", GET, cogt=cog, cogtUnit="T", cogm="", cogmUnit="M",
                    sogn=knots, sognUnit="N",
                    sogk="" if fix.speed_mps is None else round(fix.speed_mps * 3.6, 3),
                    sogkUnit="K", posMode="A"),
    ]
    return [m.serialize() for m in out]


def _num(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


@dataclass
class NmeaStream:
    """Reads NMEA from bytes as they come: :meth:`feed` returns the fixes completed.
    ``counters``: ``nmea_sentences`` (read), ``nmea_bad_checksum``, ``nmea_garbage`` (not
    NMEA, or malformed), ``nmea_too_long``, ``nmea_ignored`` (other sentence types),
    ``nmea_no_fix`` (RMC status V: the receiver has no fix), ``nmea_fixes``."""

    counters: Counter = field(default_factory=Counter)
    _buf: bytes = b""
    _epoch: dict = field(default_factory=dict)  # the current epoch's sentences by type
    _time: object = None  # its UTC time of day
    _done: bool = False  # its fix was emitted

    def feed(self, data: bytes) -> list[Fix]:
        self._buf += data
        *lines, self._buf = self._buf.split(b"\n")
        if len(self._buf) > _MAX_LINE:  # no newline in sight: garbage, drop it
            self.counters["nmea_too_long"] += 1
            self._buf = b""
        out = []
        for line in lines:
            fix = self._line(line.strip())
            if fix is not None:
                out.append(fix)
        return out

    def _line(self, line: bytes) -> Fix | None:
        if not line:
            return None
        if len(line) > _MAX_LINE:
            self.counters["nmea_too_long"] += 1
            return None
        if not line.startswith(b"$") or b"*" not in line:
            self.counters["nmea_garbage"] += 1
            return None
        try:
            msg = NMEAReader.parse(line + b"\r\n", validate=VALCKSUM)
        except NMEAParseError as err:
            self.counters["nmea_bad_checksum" if "checksum" in str(err).lower()
                          else "nmea_garbage"] += 1
            return None
        except (NMEAMessageError, NMEATypeError, ValueError, UnicodeDecodeError):
            self.counters["nmea_garbage"] += 1
            return None
        if msg is None:
            self.counters["nmea_garbage"] += 1
            return None
        self.counters["nmea_sentences"] += 1
        kind = msg.msgID
        if kind not in ("GGA", "RMC", "GST"):
            if kind != "VTG":
                self.counters["nmea_ignored"] += 1
            return None
        out = None
        time = getattr(msg, "time", None)
        if time != self._time:  # a new epoch: an RMC without its GGA goes out now
            if not self._done and "RMC" in self._epoch:
                out = self._fix(self._epoch["RMC"])
            self._epoch, self._time, self._done = {}, time, False
        self._epoch[kind] = msg
        if not self._done and "RMC" in self._epoch and "GGA" in self._epoch:
            self._done = True
            return self._fix(self._epoch["RMC"])  # (out is None here: a fresh epoch)
        return out

    def _fix(self, rmc) -> Fix | None:
        if getattr(rmc, "status", "") != "A":
            self.counters["nmea_no_fix"] += 1
            return None
        lat, lon = _num(getattr(rmc, "lat", None)), _num(getattr(rmc, "lon", None))
        date, time = getattr(rmc, "date", None), getattr(rmc, "time", None)
        if lat is None or lon is None or not isinstance(date, dt.date) \
                or not isinstance(time, dt.time):
            self.counters["nmea_garbage"] += 1
            return None
        t = dt.datetime.combine(date, time, dt.UTC).timestamp()
        gga, gst = self._epoch.get("GGA"), self._epoch.get("GST")
        spd, cog = _num(getattr(rmc, "spd", None)), _num(getattr(rmc, "cog", None))
        self.counters["nmea_fixes"] += 1
        return Fix(
            t, lat, lon,
            alt_m=_num(gga.alt) if gga is not None else None,
            speed_mps=None if spd is None else spd * _KNOT, course_deg=cog,
            quality=int(_num(gga.quality) or 0) if gga is not None else 1,
            num_sv=int(_num(gga.numSV) or 0) if gga is not None and gga.numSV != "" else None,
            hdop=_num(gga.HDOP) if gga is not None else None,
            std_lat_m=_num(gst.stdLat) if gst is not None else None,
            std_lon_m=_num(gst.stdLong) if gst is not None else None)
