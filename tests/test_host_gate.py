"""The host channel defends itself (issue 27, :class:`obu.host.HostGate`): the host's id
only, no clock jump, no position its motion cannot reach; every real host trip is
believed whole, and no one-bit corruption of a copied host frame is."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from catc.bsm import BSM
from catc.errors import DecodeError
from catc.j2735 import decode_frame, encode_frame
from catc.replay import temp_id, track_bsm
from hil.datasets import load, scenario_file
from obu.host import MAX_GAP_S, RESYNC_S, HostGate, elapsed

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def _host_frames(spec: str) -> list[list[BSM]]:
    """Every trip's host BSMs, as the RVE sends them."""
    out = []
    for table in load(spec):
        if table.default_host is None:  # single-vehicle logs: no host to send
            continue
        host = table.tracks[table.default_host]
        out.append([track_bsm(host, k, temp_id(table.default_host)) for k in range(len(host))])
    return out


def _scenario() -> list[BSM]:
    return _host_frames(f"sumo:{scenario_file('highway-braking')}")[0]


@pytest.mark.parametrize("name", ["openacc-zalazone", "ngsim-i80-pairs", "cv-pilot-samples",
                                  "jpo-ode-bsm-vectors"])
def test_every_real_host_trip_is_believed_whole(name):
    """The bounds are no tighter than real driving: no frame of any host trip of the real
    data is refused, sent at 10 Hz wall or at any replay speed."""
    if not (DATA / name).is_dir():
        pytest.skip(f"{DATA / name} is absent (../shared/data is not checked out)")
    trips = _host_frames(str(DATA / name))
    if not trips:
        pytest.skip(f"{name}: no trip with a host vehicle")
    for frames in trips:
        for speed in (1.0, 8.0):
            gate = HostGate()
            t0 = frames[0].sec_mark / 1000.0
            refused = [(k, r) for k, b in enumerate(frames)
                       if (r := gate.check(b, t0 + k * 0.1 / speed)) is not None]
            assert refused == [], (name, refused[:5])


def test_only_the_host_id_is_believed():
    frames = _scenario()
    other = dataclasses.replace(frames[1], temp_id=frames[1].temp_id ^ 1)
    gate = HostGate()  # the first id heard
    assert gate.check(frames[0], 0.0) is None and gate.host_id == frames[0].temp_id
    assert gate.check(other, 0.1) == "foreign_id"
    assert gate.check(frames[1], 0.1) is None
    configured = HostGate(host_id=other.temp_id)
    assert configured.check(frames[0], 0.0) == "foreign_id"
    incomplete = dataclasses.replace(frames[0], lat=None)
    assert HostGate().check(incomplete, 0.0) == "incomplete"


def test_time_must_move_on_by_what_the_frame_count_allows():
    frames = _scenario()
    gate = HostGate()
    for k in range(50):
        assert gate.check(frames[k], k * 0.1) is None
    now = frames[49]
    assert gate.check(frames[40], 5.0) == "stale"  # the past
    assert gate.check(now, 5.0) == "stale"  # a duplicate
    jump = dataclasses.replace(frames[50], sec_mark=(now.sec_mark + 5000) % 60000)
    assert gate.check(jump, 5.0) == "clock_jump"  # 5 s in 0.1 s of counts
    early = dataclasses.replace(frames[50], msg_cnt=now.msg_cnt)
    assert gate.check(early, 5.0) == "clock_jump"  # a new time, the old count
    far = dataclasses.replace(frames[50], lat=now.lat + 0.01)  # 1.1 km in 0.1 s
    assert gate.check(far, 5.0) == "implausible_motion"
    fast = dataclasses.replace(frames[50], speed=now.speed + 20.0)
    assert gate.check(fast, 5.0) == "implausible_motion"
    assert gate.check(frames[50], 5.0) is None  # the host's own next frame
    assert elapsed(59_950, 50) == pytest.approx(0.1) and elapsed(50, 59_950) < 0
    assert MAX_GAP_S < 30


def test_no_one_bit_corruption_of_a_copied_host_frame_is_believed():
    """Brute force over every bit of the host's frames, copied 0 to 8 s after they were
    sent (as ``rve flood`` copies them): each flipped copy that still decodes is refused
    (before, one in the secMark moved the OBU's clock by up to 32 s)."""
    frames = _scenario()
    k_now = 150
    decoded = 0
    for lag in (0, 1, 5, 40, 80):
        original = encode_frame(frames[k_now - lag])
        for bit in range(len(original) * 8):
            gate = HostGate()
            for k in range(k_now - 60, k_now + 1):
                assert gate.check(frames[k], k * 0.1) is None
            data = bytearray(original)
            data[bit // 8] ^= 0x80 >> (bit % 8)
            try:
                bsm = decode_frame(bytes(data))
            except DecodeError:
                continue
            decoded += 1
            assert gate.check(bsm, k_now * 0.1 + 0.01) is not None, (lag, bit, bsm)
    assert decoded > 500


def test_a_gap_resyncs_at_the_hosts_pace_but_a_replay_never_does():
    frames = _scenario()
    speed = 4.0  # data s per wall s

    def wall(k: int) -> float:
        return k * 0.1 / speed

    gate = HostGate()
    for k in range(100):
        assert gate.check(frames[k], wall(k)) is None
    # the host falls silent for 3 s of its data (0.75 s of wall), then goes on
    refused = [k for k in range(130, 170) if gate.check(frames[k], wall(k)) is not None]
    assert gate.resyncs == 1 and refused and max(refused) < 130 + 2 + 40 * RESYNC_S
    # it stops at 170; a replay of its last 10 s, from the next wall second on, is refused
    for j in range(300):
        k = 70 + j % 100
        assert gate.check(frames[k], wall(170) + RESYNC_S + j * 0.025) is not None
    assert gate.resyncs == 1
