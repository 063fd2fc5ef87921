"""``obu run --host-source vehicle``: the OBU reads its own car's CAN bus and a GNSS
receiver, fuses them and ticks at 10 Hz on GNSS time.

The OBU runs as its own process in a network namespace of the test's (the netns fixture
of tests/test_transport.py): the car's bus is python-can's ``udp_multicast`` on that
namespace's loopback.  The test process plays the car: from a thread that joined the
namespace it opens the bus and a UDP socket, then encodes the shipped profile's frames
with cantools (Toyota checksums where the DBC has them) at the car's rates and sends NMEA
fixes (catc.gnss.to_nmea) over UDP, through a pty, or to Debian's gpsd on a pty.
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
import tty
from collections import Counter
from importlib import resources
from pathlib import Path

import can
import pytest

from catc.bsm import sec_mark
from catc.geo import EnuFrame
from catc.gnss import Fix, to_nmea
from catc.vehicle import toyota_checksum
from hil.vehicle import load_dbc
from tests.test_obu import PY, finish, start_obu
from tests.test_transport import netns  # noqa: F401  (fixture)

#: The RV and host-channel ports of the OBU inside the namespace, and the GNSS port.
PORTS = [4500, 4501]
GNSS_PORT = 4502
LAT0, LON0 = 42.3, -83.7  # the car's start
SPEED_KMH = 54.0  # 15 m/s
HEADING = 30.0  # deg clockwise from north
CAN = ("--host-source", "vehicle", "--vehicle-can-interface", "udp_multicast",
       "--predictor", "ca")
DBC = load_dbc(resources.files("catc").joinpath("vehicle", "profiles",
                                                "toyota_rav4_2017.dbc"))


def in_netns(name: str, fn):
    """``fn()`` in a thread that joined network namespace ``name``: what it opens (a
    socket, a python-can bus) lives there, used from any thread afterwards."""
    out: list = []

    def run():
        libc = ctypes.CDLL(None, use_errno=True)
        fd = os.open(f"/var/run/netns/{name}", os.O_RDONLY)
        try:
            if libc.setns(fd, 0x40000000) != 0:  # CLONE_NEWNET: this thread only
                out.append(OSError(ctypes.get_errno(), "setns"))
                return
        finally:
            os.close(fd)
        try:
            out.append(fn())
        except Exception as err:
            out.append(err)

    t = threading.Thread(target=run)
    t.start()
    t.join()
    if isinstance(out[0], Exception):
        raise out[0]
    return out[0]


def frame(name: str, **signals) -> tuple[int, bytes]:
    msg = DBC.get_message_by_name(name)
    full = {s.name: 0 for s in msg.signals} | signals
    data = bytearray(msg.encode(full, scaling=True, strict=False))
    if any(s.name == "CHECKSUM" for s in msg.signals):
        data[-1] = toyota_checksum(msg.frame_id, bytes(data))
    return msg.frame_id, bytes(data)


#: The frames of the car at each 12.5 ms (80 Hz) and each 100 ms (10 Hz).
FAST = [frame("WHEEL_SPEEDS", **{f"WHEEL_SPEED_{w}": SPEED_KMH for w in
                                 ("FL", "FR", "RL", "RR")}),
        frame("KINEMATICS", YAW_RATE=0.0, ACCEL_X=0.0, ACCEL_Y=0.0),
        frame("STEER_ANGLE_SENSOR", STEER_ANGLE=3.0)]
SLOW = [frame("SPEED", SPEED=SPEED_KMH * 1.021), frame("BRAKE_MODULE"),
        frame("GEAR_PACKET", GEAR=0), frame("BLINKERS_STATE", TURN_SIGNALS=3),
        frame("LIGHT_STALK", LOW_BEAM=1)]
#: The speed the OBU must read: the wheel speed as the DBC decodes what was sent (m/s).
WHEEL_MPS = DBC.decode_message("WHEEL_SPEEDS", FAST[0][1])["WHEEL_SPEED_FL"] / 3.6


class Car:
    """The host car: its bus and GNSS receiver, driving straight at 15 m/s."""

    def __init__(self, ns: str, gnss_out=None) -> None:
        self.bus = in_netns(ns, lambda: can.Bus(interface="udp_multicast",
                                                 channel="239.74.163.3"))
        self.udp = in_netns(ns, lambda: socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        self.gnss_out = gnss_out or (lambda data: self.udp.sendto(
            data, ("127.0.0.1", GNSS_PORT)))
        self.t0 = math.ceil(time.time()) + 1000.0  # GNSS time: not this machine's clock
        self.frame = EnuFrame(LAT0, LON0, 0.0)
        self.fixes: list[Fix] = []
        self.grid: list[float] = []  # the GNSS time of every 100 ms step, fix or not
        self.can_sent = 0

    def truth(self, t_gnss: float) -> tuple[float, float]:
        d = SPEED_KMH / 3.6 * (t_gnss - self.t0)
        lat, lon, _ = self.frame.to_geodetic(d * math.sin(math.radians(HEADING)),
                                             d * math.cos(math.radians(HEADING)), 0.0)
        return float(lat), float(lon)

    def send_can(self, fid: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        self.can_sent += 1

    def drive(self, seconds: float, silent=(math.inf, math.inf), at=None) -> None:
        """Drive for ``seconds``: CAN at 80 and 10 Hz, a fix every 100 ms of GNSS time
        (none in ``silent``, [from, to) s); ``at(k)`` at each 100 ms step ``k``."""
        start = time.monotonic() + 0.05
        for i in range(int(seconds * 80)):
            delay = start + i / 80 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            for f in FAST:
                self.send_can(*f)
            if i % 8:
                continue
            k = i // 8
            for f in SLOW:
                self.send_can(*f)
            t = self.t0 + k / 10
            self.grid.append(t)
            if not silent[0] <= k / 10 < silent[1]:
                lat, lon = self.truth(t)
                fix = Fix(t, lat, lon, alt_m=200.0, speed_mps=SPEED_KMH / 3.6,
                          course_deg=HEADING, num_sv=12, hdop=0.8, std_lat_m=0.5,
                          std_lon_m=0.5)
                self.fixes.append(fix)
                self.gnss_out(b"".join(to_nmea(fix)))
            if at is not None:
                at(k)

    def close(self) -> None:
        self.bus.shutdown()
        self.udp.close()


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def stop(proc) -> str:
    """SIGTERM the OBU (its ticks never stop on their own: dead reckoning); its stderr."""
    proc.send_signal(signal.SIGTERM)
    return finish(proc)[1]


def metres(a: tuple[float, float], b: tuple[float, float]) -> float:
    e, n, _ = EnuFrame(a[0], a[1], 0.0).to_enu(b[0], b[1], 0.0)
    return math.hypot(float(e), float(n))


def check_run(car: Car, cap: Path, exact: bool = True) -> tuple[list, list, dict]:
    """The checks every run passes: 10 Hz ticks on GNSS time, the host's position on the
    car's path, its speed the wheel speed."""
    ticks = read_jsonl(cap / "obu.ticks.jsonl")
    vehicle = read_jsonl(cap / "obu.vehicle.jsonl")
    counters = Counter(json.loads((cap / "obu.counters.json").read_text()))
    first, last = car.grid[0], car.grid[-1]
    assert len(ticks) >= 10 * (last - first) - 2
    marks = [t["sec_mark"] for t in ticks]
    assert all(m % 100 == 0 for m in marks)
    assert all((b - a) % 60_000 == 100 for a, b in itertools.pairwise(marks))
    # the ticks are on the NMEA's UTC: every tick of the drive is at a 100 ms step of the
    # car's GNSS time (a fix's, but in a silence)
    grid = {sec_mark(t) for t in car.grid}
    assert vehicle[0]["t_gnss"] >= first
    during = [v for v in vehicle if first + 1.0 <= v["t_gnss"] <= last]
    assert len(during) >= 10 * (last - first - 1.0) - 2
    if exact:
        assert {sec_mark(v["t_gnss"]) for v in during} <= grid
    for v in vehicle:
        assert abs(round(v["t_gnss"] * 10) - v["t_gnss"] * 10) < 1e-6
    for v in during:
        off = metres(car.truth(v["t_gnss"]), (v["lat"], v["lon"]))
        assert off < (3.0 if v["gnss_age_s"] > 0.5 else 1.5), (v, off)
        assert abs(v["speed"] - WHEEL_MPS) < 1e-3, v
        assert abs((v["heading"] - HEADING + 180) % 360 - 180) < 1.0, v
    assert all(abs(t["host_speed"] - WHEEL_MPS) <= 0.02 for t in ticks[10:])
    assert counters["ticks"] == counters["vehicle_ticks"] == len(ticks)
    assert counters["host_rejected"] == 0 and counters["can_updates"] > 0
    return ticks, vehicle, counters


def test_the_obu_ticks_on_gnss_time_from_its_cars_can_and_nmea_over_udp(netns, tmp_path):  # noqa: F811
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    car = Car(netns)
    obu = start_obu(tmp_path, PORTS, *CAN, "--gnss", f"udp:127.0.0.1:{GNSS_PORT}",
                    "--gnss-latency", "0", "--gnss-delay", "0",
                    prefix=("ip", "netns", "exec", netns))
    try:
        car.drive(8.0)
        time.sleep(0.3)
    finally:
        err = stop(obu)
        car.close()
    _, _vehicle, counters = check_run(car, tmp_path)
    assert counters["can_frames"] == car.can_sent
    assert counters["nmea_fixes"] == counters["gnss_fixes"] == len(car.fixes)
    assert counters["can_bad_checksum"] == counters["can_unknown_id"] == 0
    assert counters["nmea_bad_checksum"] == counters["nmea_garbage"] == 0
    assert "GNSS silent" not in err
    config = json.loads((tmp_path / "obu.config.json").read_text())
    assert config["settings"]["host_source"] == "vehicle"


def test_bad_input_is_one_line_and_a_counter_and_ticks_go_on(netns, tmp_path):  # noqa: F811
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    car = Car(netns)
    obu = start_obu(tmp_path, PORTS, *CAN, "--gnss", f"udp:127.0.0.1:{GNSS_PORT}",
                    "--gnss-latency", "0", "--gnss-delay", "0",
                    prefix=("ip", "netns", "exec", netns))
    good = to_nmea(Fix(car.t0, LAT0, LON0))[0]
    bad_sum = good[:-4] + (b"00" if good[-4:-2] != b"00" else b"11") + b"\r\n"
    speed_id, speed = SLOW[0]
    bad_speed = speed[:-1] + bytes([(speed[-1] + 1) % 256])

    def misbehave(k: int) -> None:
        if k == 15:  # three of each, at once: one line per reason
            for _ in range(3):
                car.gnss_out(bad_sum)
                car.gnss_out(b"\x00\xff not nmea at all \xfe\r\n")
                car.send_can(speed_id, bad_speed)
                car.send_can(0x123, bytes(8))
                car.udp.sendto(b"\x00\x14\x01\x00", ("127.0.0.1", PORTS[1]))

    try:
        car.drive(13.0, silent=(3.0, 9.5), at=misbehave)
        time.sleep(0.3)
    finally:
        err = stop(obu)
        car.close()
    lines = err.splitlines()
    for needle in ("NMEA sentence with a bad checksum",
                   "garbage that is no NMEA", "bad checksum on id 0x0B4",
                   "unknown id 0x123", "GNSS silent for 5.0 s: dead reckoning",
                   "private host channel ignored"):
        assert sum(needle in line for line in lines) == 1, (needle, err)
    _ticks, vehicle, c = check_run(car, tmp_path)
    assert c["nmea_bad_checksum"] == 3 and c["nmea_garbage"] == 3
    assert c["can_bad_checksum"] == 3 and c["can_unknown_id"] == 3
    assert c["gnss_silent"] == 1 and c["host_channel_ignored"] == 3
    # dead reckoning through the silence: a tick every 100 ms, the age growing
    silent = [v for v in vehicle if car.t0 + 3.5 <= v["t_gnss"] < car.t0 + 9.5]
    assert len(silent) >= 58
    assert max(v["gnss_age_s"] for v in silent) > 5.5
    assert any(v["gnss_lost"] for v in silent)


def test_nmea_through_a_pty(netns, tmp_path):  # noqa: F811
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    car = Car(netns, gnss_out=lambda data: os.write(master, data))
    obu = start_obu(tmp_path, PORTS, *CAN, "--gnss", f"serial:{path}@115200",
                    "--gnss-latency", "0", "--gnss-delay", "0",
                    prefix=("ip", "netns", "exec", netns))
    try:
        car.drive(6.0)
        time.sleep(0.3)
    finally:
        err = stop(obu)
        car.close()
        os.close(master)
        os.close(slave)
    _, _, counters = check_run(car, tmp_path)
    assert counters["nmea_fixes"] == len(car.fixes), err


def test_gpsd_on_a_pty(netns, tmp_path):  # noqa: F811
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    gpsd = shutil.which("gpsd") or ("/usr/sbin/gpsd" if Path("/usr/sbin/gpsd").exists()
                                    else None)
    if gpsd is None:
        pytest.skip("Debian's gpsd is not installed (make installs it: DEBS)")
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    car = Car(netns, gnss_out=lambda data: os.write(master, data))
    port = 4503
    daemon = subprocess.Popen(["ip", "netns", "exec", netns, gpsd, "-N", "-n", "-b", "-S",
                               str(port), "-F", str(tmp_path / "gpsd.sock"), path],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        obu = start_obu(tmp_path / "cap", PORTS, *CAN, "--gnss", f"gpsd:127.0.0.1:{port}",
                        "--gnss-latency", "0", "--gnss-delay", "0",
                    prefix=("ip", "netns", "exec", netns))
        try:
            car.drive(8.0)
            time.sleep(0.3)
        finally:
            err = stop(obu)
            car.close()
    finally:
        daemon.terminate()
        try:
            daemon.wait(timeout=10)
        except subprocess.TimeoutExpired:
            daemon.kill()
            daemon.wait()
        with contextlib.suppress(OSError):
            os.close(master)
            os.close(slave)
    vehicle = read_jsonl(tmp_path / "cap" / "obu.vehicle.jsonl")
    counters = Counter(json.loads((tmp_path / "cap" / "obu.counters.json").read_text()))
    assert counters["gnss_gpsd_fixes"] >= 0.8 * len(car.fixes), (counters, err)
    assert counters["gnss_fixes"] >= 0.8 * len(car.fixes)
    # gpsd passes the fixes on a little later than they came: no exact secMarks, but
    # the ticks are on the fixes' time and the host on the car's path
    late = [v for v in vehicle if v["t_gnss"] >= car.fixes[0].t_unix + 2.0
            and v["t_gnss"] <= car.fixes[-1].t_unix]
    assert len(late) >= 50
    for v in late:
        assert metres(car.truth(v["t_gnss"]), (v["lat"], v["lon"])) < 3.0, v
        assert abs(v["speed"] - WHEEL_MPS) < 1e-3


@pytest.mark.parametrize(("args", "needle"), [
    (["--vehicle", "no-such-car"], "no-such-car"),
    (["--dbc", "{bad}"], "not a DBC that parses"),
    ([], "--gnss"),
    (["--gnss", "tcp:1.2.3.4:5"], "not a GNSS source"),
])
def test_bad_vehicle_flags_are_one_line_and_exit_2(tmp_path, args, needle):
    bad = tmp_path / "bad.dbc"
    bad.write_text("BO_ this is not a DBC\n")
    args = [str(bad) if a == "{bad}" else a for a in args]
    gnss = [] if not args or args[0] == "--gnss" else ["--gnss", "udp:127.0.0.1:0"]
    out = subprocess.run([PY, "-m", "obu.cli", "run", "--duration", "1", "--host-source",
                          "vehicle", *gnss, *args], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines


def test_gnss_specs():
    from obu.options import GnssSpec, gnss_spec

    assert gnss_spec("udp:127.0.0.1:4502") == GnssSpec("udp", "127.0.0.1", 4502)
    assert gnss_spec("serial:/dev/pts/3@115200") == GnssSpec("serial", path="/dev/pts/3",
                                                             baud=115200)
    assert gnss_spec("serial:/dev/ttyACM0").baud is None
    assert gnss_spec("gpsd") == GnssSpec("gpsd", "127.0.0.1", 2947)
    assert gnss_spec("gpsd:localhost") == GnssSpec("gpsd", "localhost", 2947)
    assert gnss_spec("gpsd:127.0.0.1:3000") == GnssSpec("gpsd", "127.0.0.1", 3000)
    assert gnss_spec("gpsd:[::1]:3000") == GnssSpec("gpsd", "::1", 3000)
    assert gnss_spec("gpsd:::1") == GnssSpec("gpsd", "::1", 2947)
    for bad in ("tcp:1.2.3.4:5", "udp:nope", "serial:", "serial:/dev/x@fast"):
        with pytest.raises(Exception, match="not"):
            gnss_spec(bad)


def test_a_gpsd_tpv_is_a_fix_with_its_time_and_errors():
    from obu.vehicle import _tpv_fix

    fix = _tpv_fix({"class": "TPV", "mode": 3, "time": "2026-12-06T05:27:17.300Z",
                    "lat": 42.3, "lon": -83.7, "altHAE": 180.5, "alt": 215.0,
                    "speed": 15.0, "track": 30.0, "epx": 0.7, "epy": 0.4})
    assert fix.t_unix == pytest.approx(1796534837.3, abs=1e-6)
    assert (fix.alt_m, fix.speed_mps, fix.course_deg) == (180.5, 15.0, 30.0)
    assert (fix.std_lon_m, fix.std_lat_m) == (0.7, 0.4)
    for doc in ({"class": "TPV", "mode": 1, "time": "2026-12-06T05:27:17Z"},
                {"class": "SKY"}, [], {"class": "TPV", "mode": 2, "lat": 1, "lon": 2},
                {"class": "TPV", "mode": 2, "time": "yesterday", "lat": 1, "lon": 2}):
        assert _tpv_fix(doc) is None
