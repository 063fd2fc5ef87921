"""The host vehicle's CAN bus: the shipped RAV4 profile against opendbc's DBC and the
real comma2k19 minute (../shared/data; skipped, with the reason, when absent)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from catc.vehicle import CanDecoder, VehicleProfile, toyota_checksum
from hil.vehicle import ProfileError, comma2k19_can, load_dbc, load_profile, profile_names
from tests.conftest import shared_path


def _segment():
    root = shared_path("comma2k19-example")
    (seg,) = sorted(root.glob("segment_*"))
    return seg


@pytest.fixture(scope="module")
def opendbc():
    return load_dbc(shared_path("opendbc-toyota", "toyota_new_mc_pt_generated.dbc"))


@pytest.fixture(scope="module")
def adas():
    return load_dbc(shared_path("opendbc-toyota", "toyota_adas.dbc"))


@pytest.fixture(scope="module")
def frames(opendbc, adas):
    return comma2k19_can(_segment(), {0: opendbc, 1: adas})


def _data(row) -> bytes:
    return bytes(row["data"]).ljust(int(row["length"]), b"\0")


def test_the_shipped_profile_is_opendbc_s_messages_and_signals(opendbc):
    """Our RAV4 DBC has the ids, lengths, bit positions, byte orders, scales and offsets
    of opendbc's (the facts, not the file)."""
    assert "toyota-rav4-2017" in profile_names()
    profile, ours = load_profile("toyota-rav4-2017")
    assert profile.checksum == "toyota"
    for msg in ours.messages:
        ref = opendbc.get_message_by_frame_id(msg.frame_id)
        assert (ref.name, ref.length) == (msg.name, msg.length)
        for s in msg.signals:
            r = ref.get_signal_by_name(s.name)
            assert (r.start, r.length, r.byte_order, r.is_signed, r.scale, r.offset) == \
                (s.start, s.length, s.byte_order, s.is_signed, s.scale, s.offset), s.name
            assert r.choices == s.choices or not s.choices
    profile.check(opendbc)  # the profile reads through the full DBC as well


def test_lengths_restored_every_checksum_passes(frames, opendbc, adas):
    """The stored frames lose their trailing zero bytes (994 of those on buses 0 and 1
    whose id the DBCs know); padded to the DBC's length, the Toyota checksum passes on
    every checksummed frame of the minute: 51,056 (the issue counts 39,957; it does not
    say over which ids)."""
    assert set(np.unique(frames["bus"])) == {0, 1}
    assert int((frames["bus"] == 0).sum()) == 53_800 and len(frames) == 98_800
    assert np.all(np.diff(frames["t"]) >= 0)
    stored = np.char.str_len(frames["data"])
    assert int((stored < frames["length"]).sum()) == 994  # restored to their DBC length
    checked = 0
    for row in frames:
        try:
            msg = (opendbc, adas)[row["bus"]].get_message_by_frame_id(int(row["address"]))
        except KeyError:
            continue
        if any(s.name == "CHECKSUM" for s in msg.signals):
            data = _data(row)
            assert data[-1] == toyota_checksum(int(row["address"]), data)
            checked += 1
    assert checked == 51_056  # bus 0: 12,656; bus 1 (radar): 38,400


def test_the_decoder_reads_the_real_minute_as_comma_processed_it(frames):
    """Through the shipped profile: the wheel speeds equal the segment's processed
    ``speed`` (m/s) at every frame; the steering angle comes as often as its
    ``steering_angle``; the yaw rate (J2735: clockwise) tracks the IMU gyro after a
    constant bias, which is measured here."""
    profile, db = load_profile("toyota-rav4-2017")
    dec = CanDecoder(profile, db)
    base = _segment() / "processed_log" / "CAN"
    speed_t = np.load(base / "speed" / "t.npy")
    speed = np.load(base / "speed" / "value.npy")[:, 0]
    ours_t, ours_v, yaw_t, yaw = [], [], [], []
    for row in frames[frames["bus"] == 0]:
        if dec.take(float(row["t"]), int(row["address"]), _data(row)):
            if int(row["address"]) == 0xAA:
                ours_t.append(float(row["t"]))
                ours_v.append(dec.state["speed_mps"])
            if int(row["address"]) == 0x24:
                yaw_t.append(float(row["t"]))
                yaw.append(dec.state["yaw_rate_dps"])
    assert dec.counters["can_bad_checksum"] == 0 and dec.counters["can_bad_length"] == 0
    assert dec.counters["can_WHEEL_SPEEDS"] == len(speed_t)
    np.testing.assert_allclose(ours_t, speed_t)
    np.testing.assert_allclose(ours_v, speed, atol=1e-9)
    assert dec.state["gear"] == "D" and dec.state["turn_signals"] in ("none", "left", "right")
    steer_t = np.load(base / "steering_angle" / "t.npy")
    assert dec.counters["can_STEER_ANGLE_SENSOR"] == len(steer_t)
    # the yaw rate against the gyro's z axis (the IMU's axes are forward, right, down:
    # positive z is clockwise, as J2735's YawRate); the yaw rates here are small (1st to
    # 99th percentile -0.2 to 1.3 deg/s), so the sign is checked by the correlation
    imu = _segment() / "processed_log" / "IMU" / "gyro"
    gyro_t, gyro = np.load(imu / "t.npy"), np.load(imu / "value.npy")
    gyro_cw = np.degrees(np.interp(yaw_t, gyro_t, gyro[:, 2]))
    assert np.corrcoef(yaw, gyro_cw)[0, 1] > 0.7
    bias = float(np.median(np.asarray(yaw) - gyro_cw))
    assert 0.40 < bias < 0.50  # KINEMATICS' offset: 0.447 deg/s
    resid = np.asarray(yaw) - bias - gyro_cw
    assert np.percentile(np.abs(resid), 95) < 0.5  # 0.32 deg/s


def test_bad_profiles_dbcs_and_frames_get_one_line_and_a_count(tmp_path):
    profile, db = load_profile("toyota-rav4-2017")
    with pytest.raises(ProfileError, match="no such file or shipped profile"):
        load_profile("no-such-car")
    (tmp_path / "p.json").write_text("{not json")
    with pytest.raises(ProfileError, match="not JSON"):
        load_profile(str(tmp_path / "p.json"))
    doc = {"name": "x", "dbc": "x.dbc", "fields": {"speed_mps": {
        "message": "WHEEL_SPEEDS", "signals": ["WHEEL_SPEED_XX"]}}}
    (tmp_path / "x.dbc").write_text("this is not a DBC\n")
    (tmp_path / "p.json").write_text(json.dumps(doc))
    with pytest.raises(ProfileError, match="not a DBC that parses") as err:
        load_profile(str(tmp_path / "p.json"))
    assert "\n" not in str(err.value)
    from importlib import resources

    own = resources.files("catc").joinpath("vehicle", "profiles", "toyota_rav4_2017.dbc")
    with pytest.raises(ProfileError, match="no signal 'WHEEL_SPEED_XX'"):
        load_profile(str(tmp_path / "p.json"), dbc=own)
    with pytest.raises(ValueError, match="checksum 'crc'"):
        VehicleProfile.from_dict({"name": "x", "checksum": "crc", "fields": {}})
    dec = CanDecoder(profile, db)
    assert not dec.take(0.0, 0x7FF, bytes(8))  # an id the DBC does not know
    assert not dec.take(0.0, 0xAA, bytes(5))  # short
    good = bytearray(8)
    good[-1] = toyota_checksum(0xB4, bytes(good))
    assert not dec.take(0.0, 0xB4, bytes(good[:-1]) + bytes([good[-1] ^ 1]))
    assert dec.counters == {"can_frames": 3, "can_unknown_id": 1, "can_bad_length": 1,
                            "can_bad_checksum": 1}
    assert dec.state == {}
