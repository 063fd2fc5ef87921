"""``rve run --host-bus``: the host vehicle's CAN bus and GNSS receiver made from its track.

* pure: the encoder round-trips through our :class:`CanDecoder` and through cantools on
  opendbc's full DBC within one DBC scale step, checksums hold, messages come at the
  profile's rates; the GNSS epochs have the noise, latency, losses and outages asked for;
  a dataset's recorded frames and fixes are replayed exactly;
* ``rve run`` as a process: NMEA over UDP parsed with pynmeagps, CAN over python-can's
  ``udp_multicast`` in a network namespace decoded with cantools, NMEA through a pty into
  Debian's gpsd (``gpspipe``), and CAN on vcan recorded by can-utils ``candump``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime as dt
import json
import math
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest
from pynmeagps import NMEAReader

from catc.geo import distance_m
from catc.gnss import DEFAULT_UTC_BASE, Fix, NmeaStream
from catc.mobility import MobilityTable, Track
from catc.vehicle import CanDecoder, toyota_checksum
from catc.vehicle.encode import (
    CanEncoder,
    gnss_epochs,
    gnss_fixes,
    host_frames,
    host_values,
)
from hil.datasets import load_table
from hil.transport.udp import free_ports
from hil.vehicle import load_dbc, load_profile
from tests.conftest import shared_path
from tests.test_transport import netns, vcan_interface  # noqa: F401  (fixture)

RVE = [sys.executable, "-m", "rve.cli", "run"]
#: NMEA's precision: minutes to 5 decimals (2 cm) and 10 ms.
DEG = 1e-5 / 60 * 0.51


@pytest.fixture(scope="module")
def rav4():
    return load_profile("toyota-rav4-2017")


@pytest.fixture(scope="module")
def opendbc():
    return load_dbc(shared_path("opendbc-toyota", "toyota_new_mc_pt_generated.dbc"))


def _track(seconds: float = 30.0) -> Track:
    """A host that accelerates, turns left and right, brakes hard and stands still."""
    t = np.round(np.arange(0.0, seconds + 1e-9, 0.1), 1)
    speed = np.clip(np.interp(t, [0, 8, 18, 24, 30], [5, 25, 25, 0, 0]), 0, None)
    accel = np.gradient(speed, t)
    yaw = 12.0 * np.sin(t / 3.0) * (speed > 1)
    heading = np.cumsum(yaw) * 0.1 % 360.0
    lat = 48.0 + np.cumsum(speed * np.cos(np.radians(heading))) * 0.1 / 111_200.0
    lon = 11.0 + np.cumsum(speed * np.sin(np.radians(heading))) * 0.1 / 74_400.0
    z = np.zeros_like(t)
    return Track("hv", t, z, z, lat, lon, z + 500.0, speed, heading, accel, yaw)


def _step(db, profile, name: str) -> float:
    """One DBC scale step of a field, in the field's unit."""
    rule = profile.fields[name]
    msg = db.get_message_by_name(rule.message)
    sig = msg.get_signal_by_name(rule.signals[-1])
    return abs(sig.scale * rule.scale)


def _data(row) -> bytes:
    return bytes(row["data"]).ljust(int(row["length"]), b"\0")


# --- the encoder ---------------------------------------------------------------------------

def test_the_encoder_round_trips_through_our_decoder_and_opendbc(rav4, opendbc):
    profile, ours = rav4
    track = _track()
    frames = host_frames(track, profile, ours, 0.0, 30.0)
    assert np.all(np.diff(frames["t"]) >= 0)
    worst: dict[str, float] = {}
    for db in (ours, opendbc):
        dec = CanDecoder(profile, db)
        for row in frames:
            t = float(row["t"])
            assert dec.take(t, int(row["address"]), _data(row)), dict(dec.counters)
            want = host_values(track, np.array([t]))
            for name, value in dec.state.items():
                if dec.stamps[name] != t or name not in want:
                    continue
                w = want[name][0]
                if isinstance(value, str):
                    assert value == str(w), (name, t)
                else:
                    err = abs(value - float(w))
                    assert err <= _step(db, profile, name) + 1e-9, (name, t, value, w)
                    worst[name] = max(worst.get(name, 0.0), err)
        assert dec.counters["can_bad_checksum"] == dec.counters["can_bad_length"] == 0
    # the track covers each: turning, braking and parking were all encoded
    assert worst["steering_wheel_angle_deg"] > 0 and worst["yaw_rate_dps"] > 0
    gears = {str(g) for g in host_values(track, frames["t"])["gear"]}
    brakes = set(host_values(track, frames["t"])["brake_pressed"].tolist())
    assert gears == {"D", "P"} and brakes == {0.0, 1.0}


def test_cantools_on_opendbc_reads_every_signal_within_one_step(rav4, opendbc):
    """Every signal cantools decodes from opendbc's full DBC is what the encoder meant
    (:meth:`CanEncoder.signals`) within one scale step; the signals no field names are 0;
    every checksummed frame (SPEED) carries Toyota's checksum."""
    profile, ours = rav4
    enc = CanEncoder(profile, ours)
    track = _track()
    frames = host_frames(track, profile, ours, 0.0, 30.0, encoder=enc)
    checked = 0
    for row in frames[::7]:
        address, data = int(row["address"]), _data(row)
        msg = opendbc.get_message_by_frame_id(address)
        got = msg.decode(data, decode_choices=False, scaling=True)
        values = host_values(track, np.array([float(row["t"])]))
        meant: dict[str, float] = {}
        for name, rule in profile.fields.items():
            if rule.message == msg.name:
                v = values[name][0]
                meant.update(enc.signals(name, str(v) if isinstance(v, str) else float(v)))
        for sig in msg.signals:
            if sig.name == "CHECKSUM":
                assert data[-1] == toyota_checksum(address, data)
                checked += 1
                continue
            want = meant.get(sig.name, 0.0)
            assert abs(float(got[sig.name]) - want) <= abs(sig.scale) + 1e-9, \
                (msg.name, sig.name, got[sig.name], want)
    assert checked > 0


def test_messages_come_at_the_profile_s_rates(rav4):
    profile, ours = rav4
    frames = host_frames(_track(), profile, ours, 2.0, 22.0)
    assert frames["t"].min() == 2.0 and frames["t"].max() <= 22.0
    for name in profile.messages():
        msg = ours.get_message_by_name(name)
        t = frames["t"][frames["address"] == msg.frame_id]
        rate = profile.rate_hz(name)
        assert len(t) == math.floor(20.0 * rate + 1e-9) + 1, name
        if len(t) > 1:
            assert np.allclose(np.diff(t), 1.0 / rate)
    assert profile.rate_hz("WHEEL_SPEEDS") == 83.0 and profile.rate_hz("SPEED") == 41.5


def test_a_sum_field_splits_into_steps_and_remainder(rav4):
    profile, ours = rav4
    enc = CanEncoder(profile, ours)
    for angle in (-370.25, -0.75, 0.0, 0.74, 0.76, 1.05, 87.4, 400.0):
        sig = enc.signals("steering_wheel_angle_deg", angle)
        assert -0.8 - 1e-9 <= sig["STEER_FRACTION"] <= 0.7 + 1e-9
        assert abs(sig["STEER_ANGLE"] / 1.5 - round(sig["STEER_ANGLE"] / 1.5)) < 1e-9
        assert abs(-(sig["STEER_ANGLE"] + sig["STEER_FRACTION"]) - angle) <= 0.05 + 1e-9


# --- GNSS ----------------------------------------------------------------------------------

def _long_track(seconds: float) -> Track:
    t = np.round(np.arange(0.0, seconds, 0.1), 1)
    z = np.zeros_like(t)
    lat = 48.0 + t * 1e-6
    return Track("hv", t, z, z, lat, z + 11.0, z, z + 10.0, z, z, z)


def test_gnss_noise_is_slow_gauss_markov_of_the_std_asked(rav4):
    track = _long_track(4000.0)
    epochs = gnss_epochs(track, DEFAULT_UTC_BASE, noise_m=2.0, seed=5)
    north = np.array([(e.fix.lat - e.true_lat) * 111_200.0 for e in epochs])
    east = np.array([(e.fix.lon - e.true_lon) * 111_320.0 * math.cos(math.radians(48))
                     for e in epochs])
    for err in (north, east):
        assert err.std() == pytest.approx(2.0, rel=0.2)
        r1 = np.corrcoef(err[:-1], err[1:])[0, 1]
        r100 = np.corrcoef(err[:-100], err[100:])[0, 1]  # 10 s: one correlation time
        assert r1 > 0.98 and 0.2 < r100 < 0.55
    assert abs(np.corrcoef(north, east)[0, 1]) < 0.2
    assert all(e.fix.std_lat_m == e.fix.std_lon_m == 2.0 for e in epochs[:5])
    # the same seed, the same errors; the loss stream does not move them
    again = gnss_epochs(track, DEFAULT_UTC_BASE, noise_m=2.0, seed=5, loss=0.5)
    assert [e.fix for e in again] == [e.fix for e in epochs]


def test_gnss_epochs_latency_loss_and_outages():
    track = _long_track(300.0)
    base = DEFAULT_UTC_BASE + 0.04  # UTC epochs fall between the table's samples
    epochs = gnss_epochs(track, base, noise_m=0.0, latency_s=0.12, loss=0.2,
                         outages=[(10.0, 5.0), (100.0, 0.5)], seed=3, start=2.0)
    assert all(abs(e.fix.t_unix * 10 - round(e.fix.t_unix * 10)) < 1e-4 for e in epochs)
    assert np.allclose(np.diff([e.fix.t_unix for e in epochs]), 0.1)
    t_fix = np.array([e.fix.t_unix - base for e in epochs])
    assert np.allclose([e.t_send for e in epochs] - t_fix, 0.12)
    out = (((t_fix >= 12.0 - 1e-9) & (t_fix < 17.0 - 1e-9))
           | ((t_fix >= 102.0 - 1e-9) & (t_fix < 102.5 - 1e-9)))
    dropped = np.array([e.dropped for e in epochs], dtype=object)
    assert np.all(dropped[out] == "outage") and not np.any(dropped[~out] == "outage")
    lost = np.mean(dropped[~out] == "loss")
    assert lost == pytest.approx(0.2, abs=0.03)
    sent = gnss_fixes(track, base, noise_m=0.0, latency_s=0.12, loss=0.2,
                      outages=[(10.0, 5.0), (100.0, 0.5)], seed=3, start=2.0)
    assert len(sent) == int(np.sum(dropped == None))  # noqa: E711
    t_send, fix, (lat, lon) = sent[0]
    assert t_send == pytest.approx(fix.t_unix - base + 0.12)
    assert (fix.lat, fix.lon) == (lat, lon)  # no noise: the truth
    assert (fix.quality, fix.num_sv, fix.hdop) == (1, 12, 0.8)


# --- recorded data: replayed as it was -----------------------------------------------------

def _args(**over) -> argparse.Namespace:
    from rve.options import DEFAULTS

    return argparse.Namespace(**{**DEFAULTS, "progress": False, "asap": True,
                                 "host_bus": True, **over})


def _recorded_table() -> MobilityTable:
    track = _track(3.0)
    rec = np.zeros(5, dtype=[("t", "f8"), ("bus", "u1"), ("address", "u4"),
                             ("length", "u1"), ("data", "S8")])
    rec["t"] = [0.2, 0.5, 0.5, 1.0, 2.5]
    rec["bus"] = [0, 1, 0, 0, 1]
    rec["address"] = [0xAA, 0x2E4, 0x24, 0xB4, 0x2E4]
    rec["data"] = [bytes(range(1, 9)), b"\x10\x20", b"\x00\x00\x00\x01", b"\x07" * 8,
                   b"\x99" * 8]
    rec["length"] = [8, 8, 8, 8, 8]
    fixes = [(0.3 + 0.1 * k, Fix(DEFAULT_UTC_BASE + 0.2 + 0.1 * k, 48.0 + k * 1e-5, 11.0,
                                 speed_mps=5.0, course_deg=10.0, num_sv=7, hdop=1.3))
             for k in range(20)]
    return MobilityTable("rec", "test", (48.0, 11.0, 0.0), {"hv": track}, "hv",
                         meta={"vehicle_can": rec, "gnss_fixes": fixes})


def test_recorded_can_and_fixes_are_replayed_exactly(tmp_path):
    from catc.channel import ChannelConfig
    from catc.replay import plan
    from rve.run import replay

    table = _recorded_table()
    the_plan = plan(table, ChannelConfig(), 0, "hv", None)
    host, radar = (f"hb-{os.getpid()}-{k}" for k in ("host", "radar"))
    (port,) = free_ports(1)
    args = _args(host_can_channel=host, radar_can_channel=radar,
                 nmea=("udp", ("127.0.0.1", port)), capture=str(tmp_path),
                 to=("127.0.0.1", free_ports(1)[0]), host_to=("127.0.0.1", free_ports(1)[0]))
    buses = [can.Bus(interface="virtual", channel=c) for c in (host, radar)]
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    try:
        counts = asyncio.run(replay(args, the_plan))
        got = [[], []]
        for k, bus in enumerate(buses):
            while (m := bus.recv(0.2)) is not None:
                got[k].append((m.arbitration_id, bytes(m.data)))
        sock.settimeout(0.5)
        stream, fixes = NmeaStream(), []
        with contextlib.suppress(TimeoutError):
            while True:
                fixes += stream.feed(sock.recv(4096))
    finally:
        for bus in buses:
            bus.shutdown()
        sock.close()
    rec = table.meta["vehicle_can"]
    want = [[(int(r["address"]), _data(r)) for r in rec if r["bus"] == b] for b in (0, 1)]
    assert got == want
    assert counts["host"] == 0 and counts["host_can_frames"] == 5
    want_fixes = [f for t, f in table.meta["gnss_fixes"] if t <= 3.0 + 1e-9]
    assert len(fixes) == len(want_fixes) == counts["nmea_epochs"]
    for a, b in zip(fixes, want_fixes, strict=True):
        assert a.t_unix == pytest.approx(b.t_unix, abs=0.011)
        assert (a.lat, a.lon) == pytest.approx((b.lat, b.lon), abs=DEG)
        assert (a.num_sv, a.hdop) == (7, 1.3)
    log = (tmp_path / "rve.hostbus.log").read_text().splitlines()
    assert [line.split()[1] for line in log] == [host, radar, host, host, radar]
    assert log[0].split()[2] == "0AA#0102030405060708"
    sched = [json.loads(line) for line in (tmp_path / "rve.schedule.jsonl").open()]
    assert not [r for r in sched if r["channel"] == "host"]  # the private channel: silent


# --- rve run as a process ------------------------------------------------------------------

def _rve(*args: str, prefix: tuple[str, ...] = (), **kw) -> subprocess.Popen:
    return subprocess.Popen([*prefix, *RVE, "--no-progress", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _finish(proc: subprocess.Popen, timeout: float = 120) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    assert proc.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _host_truth(cap: Path) -> dict[float, dict]:
    return {round(r["t"], 3): r for r in _lines(cap / "rve.truth.jsonl") if r["host"]}


def _check_sent_fixes(cap: Path, got: list[tuple[float, float, float]]) -> list[dict]:
    """``got`` (UTC, lat, lon) are the records of rve.gnss.jsonl that were sent, and those
    are the truth of rve.truth.jsonl plus noise."""
    sent = [r for r in _lines(cap / "rve.gnss.jsonl") if r["dropped"] is None]
    by_utc = {round(r["utc"], 2): r for r in sent}
    for utc, lat, lon in got:
        r = by_utc[round(utc, 2)]
        assert (lat, lon) == pytest.approx((r["lat"], r["lon"]), abs=DEG)
    truth = _host_truth(cap)
    for r in sent:
        if round(r["t_fix"], 3) in truth:
            row = truth[round(r["t_fix"], 3)]
            assert (r["true_lat"], r["true_lon"]) == pytest.approx((row["lat"], row["lon"]),
                                                                   abs=1e-9)
    return sent


def test_nmea_over_udp_at_10_hz_matches_the_capture(tmp_path):
    (port,) = free_ports(1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    got: list[tuple[float, bytes]] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            if select.select([sock], [], [], 0.05)[0]:
                got.append((time.monotonic(), sock.recv(65536)))

    thread = threading.Thread(target=receive, daemon=True)
    thread.start()
    rv = free_ports(2)
    try:
        summary = _finish(_rve("--host-bus", "--nmea", f"udp:127.0.0.1:{port}",
                               "--duration", "4", "--speed", "2", "--seed", "4",
                               "--gnss-loss", "10", "--to", f"127.0.0.1:{rv[0]}",
                               "--host-to", f"127.0.0.1:{rv[1]}", "--capture",
                               str(tmp_path)))
        time.sleep(0.2)
    finally:
        done.set()
        thread.join(5)
        sock.close()
    assert summary["host_frames"] == 0 and summary["host_can_frames"] > 0
    fixes = []
    for _, datagram in got:
        msgs = [NMEAReader.parse(line + b"\r\n") for line in datagram.split(b"\r\n") if line]
        assert [m.msgID for m in msgs] == ["GST", "GGA", "RMC", "VTG"]
        rmc = msgs[2]
        utc = dt.datetime.combine(rmc.date, rmc.time, dt.UTC).timestamp()
        fixes.append((utc, rmc.lat, rmc.lon))
        assert (msgs[1].lat, msgs[1].lon) == (rmc.lat, rmc.lon)
    assert len(fixes) == summary["nmea_epochs"] and summary["gnss_dropped"] > 0
    records = _check_sent_fixes(tmp_path, fixes)
    assert len(records) == len(fixes)
    # 10 Hz of UTC, bar the lost epochs; sent at 10 Hz / --speed of the wall clock
    utc = np.array([f[0] for f in fixes])
    assert np.all(np.abs(np.diff(utc) / 0.1 - np.round(np.diff(utc) / 0.1)) < 0.02)
    all_epochs = _lines(tmp_path / "rve.gnss.jsonl")
    assert np.allclose(np.diff([r["utc"] for r in all_epochs]), 0.1)
    wall = np.array([w for w, _ in got])
    gaps = np.diff(wall) / np.round(np.diff(utc) / 0.1)
    assert np.median(gaps) == pytest.approx(0.05, abs=0.01)


_RECEIVER = """
import can, json, sys, time
bus = can.Bus(interface="udp_multicast", channel=sys.argv[1], receive_own_messages=False)
print("ready", flush=True)
out, last = [], time.monotonic() + 30
while time.monotonic() < last:
    m = bus.recv(0.2)
    if m is None:
        if out and time.monotonic() - out[-1][2] > 1.5:
            break
        continue
    out.append((m.arbitration_id, bytes(m.data).hex(), time.monotonic()))
bus.shutdown()
print(json.dumps(out))
"""


def _decode_checked(db, frames: list[tuple[int, bytes]], profile) -> dict[str, int]:
    """Every frame decodes with cantools through ``db`` and every checksum passes; the
    number of frames of each message."""
    per: dict[str, int] = {}
    dec = CanDecoder(profile, db)
    for address, data in frames:
        msg = db.get_message_by_frame_id(address)
        msg.decode(data)
        assert dec.take(0.0, address, data), dict(dec.counters)
        if any(s.name == "CHECKSUM" for s in msg.signals):
            assert data[-1] == toyota_checksum(address, data)
        per[msg.name] = per.get(msg.name, 0) + 1
    return per


def _expected_frames(cap: Path, profile, db) -> list[tuple[int, bytes]]:
    """What the host bus of the run captured in ``cap`` should have sent."""
    table = load_table("scenario:highway-braking", None)
    host = json.loads((cap / "rve.config.json").read_text())["host"]
    truth = sorted(_host_truth(cap))
    rows = host_frames(table.tracks[host], profile, db, truth[0], truth[-1])
    return [(int(r["address"]), _data(r)) for r in rows]


def test_can_over_udp_multicast_between_processes(netns, tmp_path, rav4):  # noqa: F811
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    profile, ours = rav4
    group = "239.74.163.9"
    prefix = ("ip", "netns", "exec", netns)
    receiver = subprocess.Popen([*prefix, sys.executable, "-c", _RECEIVER, group],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready = select.select([receiver.stdout], [], [], 20)[0]
        assert ready and receiver.stdout.readline().strip() == "ready"
        summary = _finish(_rve("--host-bus", "--host-can-interface", "udp_multicast",
                               "--host-can-channel", group, "--duration", "2", "--speed",
                               "2", "--capture", str(tmp_path), prefix=prefix))
        out, _ = receiver.communicate(timeout=30)
    finally:
        if receiver.poll() is None:
            receiver.kill()
            receiver.wait(5)
    got = [(a, bytes.fromhex(d)) for a, d, _ in json.loads(out.strip().splitlines()[-1])]
    assert len(got) == summary["host_can_frames"]
    assert got == _expected_frames(tmp_path, profile, ours)
    per = _decode_checked(ours, got, profile)
    assert per["WHEEL_SPEEDS"] == math.floor(2.0 * 83) + 1 and per["SPEED"] == 84
    log = (tmp_path / "rve.hostbus.log").read_text().splitlines()
    assert [(int(x.split()[2].split("#")[0], 16), bytes.fromhex(x.split()[2].split("#")[1]))
            for x in log] == got


def test_gpsd_reads_the_nmea_from_a_pty_and_so_does_our_obu(tmp_path):
    """gpsd (Debian) reads the RVE's NMEA from a pty and gpspipe reports the fixes within
    NMEA's precision; our OBU reads the same feed through gpsd (with the car's CAN from
    the same RVE, as a serial slcan adapter on a second pty) and its host follows it."""
    for tool in ("gpsd", "gpspipe"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} absent (apt-get install gpsd gpsd-clients)")
    link, can_link = tmp_path / "gnss0", tmp_path / "can0"
    (port,) = free_ports(1)
    rv = free_ports(2)
    rve = _rve("--host-bus", "--nmea", f"pty:{link}", "--duration", "8", "--gnss-noise",
               "1.5", "--to", f"127.0.0.1:{rv[0]}", "--host-to", f"127.0.0.1:{rv[1]}",
               "--host-can-interface", "slcan", "--host-can-channel", str(can_link),
               "--capture", str(tmp_path / "cap"))
    gpsd = pipe = obu = None
    try:
        deadline = time.monotonic() + 20
        while not link.is_symlink():
            assert rve.poll() is None and time.monotonic() < deadline, rve.communicate()
            time.sleep(0.05)
        gpsd = subprocess.Popen(["gpsd", "-N", "-n", "-S", str(port), "-F",
                                 str(tmp_path / "gpsd.sock"), str(link)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(0.5)
        obu = subprocess.Popen(
            [sys.executable, "-m", "obu.cli", "run", "--listen", f"127.0.0.1:{rv[0]}",
             "--host-listen", f"127.0.0.1:{rv[1]}", "--host-source", "vehicle",
             "--vehicle-can-interface", "slcan", "--vehicle-can-channel", str(can_link),
             "--gnss", f"gpsd:127.0.0.1:{port}", "--capture", str(tmp_path / "obu"),
             "--idle-exit", "2", "--no-progress", "--predictor", "ca"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        pipe = subprocess.run(["gpspipe", "-w", "-n", "40", f"127.0.0.1:{port}"],
                              capture_output=True, text=True, timeout=30)
        summary = _finish(rve)
        _, obu_err = obu.communicate(timeout=30)
        assert obu.returncode == 0, obu_err
    finally:
        for proc in (obu, gpsd, rve):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(5)
    assert not link.exists() and not link.is_symlink()  # the link went with the run
    tpv = [o for o in map(json.loads, pipe.stdout.splitlines())
           if o.get("class") == "TPV" and o.get("mode", 0) >= 2 and "time" in o]
    assert len(tpv) >= 10, pipe.stdout[-2000:]
    got = [(dt.datetime.fromisoformat(o["time"].replace("Z", "+00:00")).timestamp(),
            o["lat"], o["lon"]) for o in tpv]
    sent = _check_sent_fixes(tmp_path / "cap", got)
    assert summary["nmea_epochs"] == len(sent)
    by_utc = {round(r["utc"], 2): r for r in sent}
    for o, (utc, _, _) in zip(tpv, got, strict=True):
        r = by_utc[round(utc, 2)]
        if "speed" in o:
            assert o["speed"] == pytest.approx(r["speed_mps"], abs=0.001)
    # our OBU through the same gpsd: a fix per epoch, a tick per 100 ms of GNSS time, the
    # host within the fixes' noise (1.5 m) of the truth
    counters = json.loads((tmp_path / "obu" / "obu.counters.json").read_text())
    assert counters["slcan_frames"] > 1_000 and counters.get("can_bad_checksum", 0) == 0
    truth = {round(r["utc"], 1): r for r in sent}
    ticks = _lines(tmp_path / "obu" / "obu.vehicle.jsonl")
    assert len(ticks) >= 40
    # the OBU starts after gpsd (on a loaded machine, seconds later): every fix gpsd had
    # from its first one on reached it
    since = [r for r in sent if r["utc"] >= ticks[0]["t_gnss"] - 0.15]
    assert len(since) >= 40 and counters["gnss_gpsd_fixes"] >= len(since) - 2, \
        (len(since), counters["gnss_gpsd_fixes"])
    off = [distance_m(v["lat"], v["lon"], truth[k]["true_lat"], truth[k]["true_lon"])
           for v in ticks if (k := round(v["t_gnss"], 1)) in truth]
    assert len(off) >= 40 and float(np.percentile(off, 95)) < 3.0, off


@pytest.mark.socketcan
def test_candump_on_vcan_reads_frames_cantools_decodes_with_opendbc(tmp_path, rav4, opendbc):
    if shutil.which("candump") is None:
        pytest.fail("can-utils missing (candump): make debs installs it")
    profile, ours = rav4
    with vcan_interface() as iface:
        out = tmp_path / "candump.log"
        with open(out, "w") as f:
            dump = subprocess.Popen(["stdbuf", "-oL", "candump", "-L", iface], stdout=f,
                                    stderr=subprocess.PIPE, text=True)
        try:
            time.sleep(1.0)  # candump binds at once; the VM is slow
            assert dump.poll() is None, dump.communicate()
            summary = _finish(_rve("--host-bus", "--host-can-interface", "socketcan",
                                   "--host-can-channel", iface, "--duration", "1",
                                   "--asap", "--capture", str(tmp_path / "cap")), 300)
            deadline = time.monotonic() + 30
            while out.read_text().count("\n") < summary["host_can_frames"] \
                    and time.monotonic() < deadline:
                time.sleep(0.1)
        finally:
            dump.send_signal(signal.SIGINT)
            dump.wait(10)
    got = []
    for line in out.read_text().splitlines():
        _, name, frame = line.split()[:3]
        assert name == iface
        address, data = frame.split("#")
        got.append((int(address, 16), bytes.fromhex(data)))
    assert len(got) == summary["host_can_frames"]
    assert got == _expected_frames(tmp_path / "cap", profile, ours)
    per = _decode_checked(opendbc, got, profile)
    assert per["WHEEL_SPEEDS"] == 84 and per["SPEED"] == 42
    # candump's frames, decoded by cantools through opendbc's DBC: the host's speed
    table = load_table("scenario:highway-braking", None)
    host = table.tracks[json.loads((tmp_path / "cap" / "rve.config.json").read_text())["host"]]
    wheels = [opendbc.decode_message(a, d) for a, d in got if a == 0xAA]
    for k, w in enumerate(wheels):
        v = float(np.interp(k / 83.0 + float(host.t[0]), host.t, host.speed)) * 3.6
        assert all(abs(w[f"WHEEL_SPEED_{x}"] - v) <= 0.01 + 1e-9 for x in ("FL", "FR", "RL",
                                                                         "RR"))


def test_bad_host_bus_values_are_one_line_and_exit_2(tmp_path):
    for argv, needle in ((["--nmea", "tcp:1.2.3.4:5"], "--nmea"),
                         (["--gnss-outage", "5"], "START:DURATION"),
                         (["--gnss-loss", "120"], "percentage"),
                         (["--vehicle", "no-such-car"], "no-such-car"),
                         (["--dbc", str(tmp_path / "none.dbc")], "none.dbc"),
                         (["--nmea", f"pty:{tmp_path}"], str(tmp_path)),
                         (["--host-can-interface", "socketcan", "--host-can-channel",
                           "nocan0"], "nocan0")):
        out = subprocess.run([*RVE, "--host-bus", "--duration", "1", "--no-progress", *argv],
                             capture_output=True, text=True, timeout=60)
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2 and len(lines) == 1 and needle in lines[0], (argv, lines)
