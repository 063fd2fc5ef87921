"""GNSS fixes as NMEA 0183 both ways (catc.gnss): the real u-blox fixes of the comma2k19
minute (../shared/data) through the sentences and back, and bad input."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from catc.gnss import Fix, NmeaStream, to_nmea
from tests.conftest import shared_path


@pytest.fixture(scope="module")
def ublox():
    (seg,) = sorted(shared_path("comma2k19-example").glob("segment_*"))
    v = np.load(seg / "processed_log" / "GNSS" / "live_gnss_ublox" / "value.npy")
    # lat, lon, speed m/s, UTC ms, altitude m, bearing deg
    return [Fix(r[3] / 1000.0, r[0], r[1], alt_m=r[4], speed_mps=r[2], course_deg=r[5],
                num_sv=12, hdop=0.9, std_lat_m=0.8, std_lon_m=0.7) for r in v]


def test_the_real_fixes_survive_nmea_within_its_precision(ublox):
    """579 real fixes (10 Hz) through GGA, RMC, VTG and GST, fed back in pieces of random
    size as a serial line delivers them: one fix each, within NMEA's precision."""
    wire = b"".join(s for f in ublox for s in to_nmea(f))
    assert all(len(line) <= 82 for line in wire.split(b"\r\n"))
    stream, got, rng, i = NmeaStream(), [], random.Random(3), 0
    while i < len(wire):
        n = rng.randint(1, 200)
        got += stream.feed(wire[i:i + n])
        i += n
    assert len(got) == len(ublox) == 579
    assert stream.counters == {"nmea_sentences": 4 * 579, "nmea_fixes": 579}
    k = math.pi / 180 * 6_378_137.0
    for a, b in zip(ublox, got, strict=True):
        assert b.t_unix == pytest.approx(round(a.t_unix, 2), abs=1e-6)  # 10 ms steps
        assert abs(b.lat - a.lat) * k < 0.02  # 1e-5 minute: 1.9 cm
        assert abs(b.lon - a.lon) * k * math.cos(math.radians(a.lat)) < 0.02
        assert b.speed_mps == pytest.approx(a.speed_mps, abs=0.001)
        assert b.course_deg == pytest.approx(a.course_deg, abs=0.005)
        assert b.alt_m == pytest.approx(a.alt_m, abs=0.0051)  # to 1 cm, rounded
        assert (b.num_sv, b.hdop, b.std_lat_m, b.std_lon_m) == (12, 0.9, 0.8, 0.7)


def test_bad_nmea_is_counted_and_dropped_never_raised():
    fix = Fix(1533198000.7, 37.72, -122.47, alt_m=30.0, speed_mps=17.0, course_deg=2.0)
    gga, rmc, vtg = to_nmea(fix)
    stream = NmeaStream()
    junk = [gga[:-4] + b"00\r\n",  # a wrong checksum
            b"\x00\xff garbage \x81\r\n", b"$GPGGA,no checksum\r\n",
            b"$GPZZZ,1,2*00\r\n", b"x" * 500,  # no newline: dropped as too long
            b"\r\n$GNGSV,1,1,00*" + b"%02X" % _xor(b"GNGSV,1,1,00") + b"\r\n"]
    assert stream.feed(b"".join(junk)) == []
    (got,) = stream.feed(gga + rmc + vtg)  # and then a good epoch reads as one
    assert (got.t_unix, got.lat, got.lon) == pytest.approx((fix.t_unix, 37.72, -122.47))
    c = stream.counters
    assert c["nmea_bad_checksum"] >= 2 and c["nmea_garbage"] >= 2
    assert c["nmea_too_long"] == 1 and c["nmea_ignored"] == 1 and c["nmea_fixes"] == 1
    no_fix = rmc.replace(b",A,", b",V,", 1)
    body = no_fix[1:no_fix.index(b"*")]
    assert NmeaStream().feed(no_fix) == []  # its checksum no longer matches
    stream = NmeaStream()
    stream.feed(b"$" + body + b"*" + b"%02X" % _xor(body) + b"\r\n")
    assert stream.counters["nmea_no_fix"] == 0  # V only: waits for the epoch's end
    stream.feed(to_nmea(Fix(1533198001.7, 37.72, -122.47))[1])
    assert stream.counters["nmea_no_fix"] == 1


def _xor(body: bytes) -> int:
    c = 0
    for b in body:
        c ^= b
    return c
