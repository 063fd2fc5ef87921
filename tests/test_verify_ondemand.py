"""Verify on demand (issue 30): the policy and the queue as pure units
(:mod:`catc.security.ondemand`), the verifier's two halves (check, then ECDSA), and the
OBU with ``--verify enforce --verify-policy on-demand`` against ``rve run`` as separate
processes over UDP on loopback."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from catc.bsm import BSM
from catc.j2735 import encode_frame
from catc.security import Verdict, Verifier, make_pki, sign_bsm
from catc.security.ondemand import OnDemandConfig, Threats, VerifyQueue

FRAME = encode_frame(BSM(msg_cnt=7, temp_id=0x12345678, sec_mark=1000, lat=42.3, lon=-83.7,
                         elev=200.0, speed=13.4, heading=90.0))
NOW = 636_913_807_899_000
START = NOW // 1_000_000 - 86400

# --- the verifier in two halves ------------------------------------------------------------


@pytest.fixture(scope="module")
def pki():
    return make_pki(2, start_time32=START, duration_s=7 * 86400, seed=b"ondemand")


def _verifier(pki) -> Verifier:
    return Verifier([pki.root.raw], certificates=[pki.aa.raw])


def test_check_then_finish_is_verify(pki) -> None:
    v = _verifier(pki)
    p = pki.pseudonyms[0]
    good = sign_bsm(FRAME, p.key, p.raw, NOW, include_cert=True)
    checked = v.check(good, NOW)
    assert not isinstance(checked, Verdict) and checked.frame == FRAME
    assert v.finish(checked) == Verdict(True, "ok", FRAME, p.hashed_id8)
    # a bad signature passes the cheap checks and fails only at the ECDSA
    bad = bytearray(sign_bsm(FRAME, p.key, p.raw, NOW + 1, include_cert=False))
    bad[-1] ^= 1
    checked = v.check(bytes(bad), NOW)
    assert not isinstance(checked, Verdict)
    assert v.finish(checked).reason == "bad-signature"
    # two copies checked before either is verified: the second is the replay
    msg = sign_bsm(FRAME, p.key, p.raw, NOW + 2, include_cert=False)
    a, b = v.check(msg, NOW), v.check(msg, NOW)
    assert v.finish(a).ok and v.finish(b).reason == "replay"
    assert v.check(msg, NOW).reason == "replay"  # once accepted: refused at once
    # an unknown digest never gets as far as the ECDSA
    q = pki.pseudonyms[1]
    assert v.check(sign_bsm(FRAME, q.key, q.raw, NOW + 3, include_cert=False),
                   NOW).reason == "unknown-signer"


# --- the policy ------------------------------------------------------------------------------


def _snapshot(rows: list[tuple], host_speed: float = 30.0, verified=None):
    """A hand-made snapshot: rows of (id, s, d, lateral code, direction code, ahead), the
    predicted zone the same as the current one."""
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    zone = SimpleNamespace(
        s=np.array([r[1] for r in rows], float), d=np.array([r[2] for r in rows], float),
        lateral=np.array([r[3] for r in rows], np.int8),
        direction=np.array([r[4] for r in rows], np.int8),
        ahead=np.array([r[5] for r in rows], bool))
    host = SimpleNamespace(speed=host_speed, accel=0.0, length=4.5)
    snap = SimpleNamespace(ids=ids, zone=zone, predicted_zone=zone, host=host,
                           length=np.full(len(rows), 4.5))
    if verified is not None:
        snap.verified = np.array(verified, bool)
    return snap


def _bsm(temp_id: int, accel: float | None = 0.0) -> BSM:
    return BSM(msg_cnt=1, temp_id=temp_id, sec_mark=0, lat=0.0, lon=0.0, elev=0.0,
               speed=20.0, heading=0.0, accel_long=accel)


ROWS = [
    (1, 120.0, 0.0, 2, 0, True),   # ahead in the path, within the FCW reach at 30 m/s
    (2, 240.0, 0.0, 2, 0, True),   # in the path, beyond it
    (3, -30.0, 3.6, 3, 0, False),  # right lane, behind: BSW/LCW
    (4, -30.0, 7.2, 4, 0, False),  # two lanes over: nobody's zone
    (5, 60.0, 0.0, 2, 1, True),    # oncoming in the host's lane
    (6, 100.0, -3.6, 1, 0, True),  # left lane ahead, beyond the side zone
    (7, -120.0, 0.0, 2, 0, False),  # behind in the host's lane
]


def test_priorities_from_a_hand_made_snapshot() -> None:
    threats = Threats(_snapshot(ROWS))
    why = {tid: threats.priority(_bsm(tid)).why for tid, *_ in ROWS}
    assert why == {1: "ahead", 2: "deferred", 3: "side", 4: "deferred", 5: "deferred",
                   6: "deferred", 7: "deferred"}
    assert threats.priority(_bsm(99)) == (True, math.inf, "new")  # not in the map
    assert Threats(None).priority(_bsm(1)).why == "new"  # before the first tick
    # hard braking by the BSM's own deceleration (0.4 g), wherever the RV is
    assert threats.priority(_bsm(7, accel=-4.5)).why == "braking"
    assert threats.priority(_bsm(7, accel=-3.0)).why == "deferred"
    # deferred ones rank by distance: nearer is more threatening
    t = {tid: threats.priority(_bsm(tid)).threat for tid in (2, 4, 5, 6, 7)}
    assert t[4] > t[5] > t[6] == t[7] > t[2]  # 31, 60, 100 and 120, 240 m: bands of 25 m
    # the FCW reach grows with the host's speed: at 45 m/s the RV 240 m ahead is urgent
    assert Threats(_snapshot(ROWS, host_speed=45.0)).priority(_bsm(2)).why == "ahead"
    # so does a track that no verified message feeds, ahead within the EEBL range
    unv = Threats(_snapshot(ROWS, verified=[True, False, True, True, True, False, False]))
    assert [unv.priority(_bsm(t)).why for t in (2, 6, 7)] == ["unverified", "unverified",
                                                            "deferred"]


def test_config_moves_the_zones() -> None:
    snap = _snapshot(ROWS, host_speed=10.0)
    assert Threats(snap).priority(_bsm(1)).why == "ahead"  # 150 m at least
    tight = OnDemandConfig(ahead_min_m=50.0, side_behind_m=10.0)
    assert Threats(snap, tight).priority(_bsm(1)).why == "deferred"
    assert Threats(snap, tight).priority(_bsm(3)).why == "deferred"


# --- the queue -------------------------------------------------------------------------------


def test_queue_orders_by_threat_then_newest() -> None:
    q: VerifyQueue[str] = VerifyQueue(max_len=10, max_age_s=5.0)
    q.push("far-old", -4, 0.0)
    q.push("near-old", -1, 0.1)
    q.push("far-new", -4, 0.2)
    q.push("near-new", -1, 0.3)
    assert [q.pop(0.5) for _ in range(5)] == ["near-new", "near-old", "far-new", "far-old",
                                              None]
    assert q.skipped == 0


def test_overload_drops_the_oldest_low_threat_frames_and_counts_them() -> None:
    skipped: list[str] = []
    q: VerifyQueue[str] = VerifyQueue(max_len=4, max_age_s=10.0, on_skip=skipped.append)
    for i in range(4):
        q.push(f"low{i}", -5, i * 0.01)
    q.push("high", -1, 0.05)
    q.push("low4", -5, 0.06)
    assert skipped == ["low0", "low1"] and q.skipped == 2 and len(q) == 4
    assert q.pop(0.1) == "high"
    # too old by the time it is reached: dropped, counted
    assert q.pop(10.025) == "low4" and skipped == ["low0", "low1", "low2"]
    assert q.drain() == ["low3"] and len(q) == 0 and q.skipped == 3


def test_queue_stays_bounded_when_worked_as_it_fills() -> None:
    q: VerifyQueue[int] = VerifyQueue(max_len=50, max_age_s=0.5)
    done = 0
    for i in range(20_000):
        q.push(i, -(i % 7), i * 1e-4)
        if i % 3 == 0 and q.pop(i * 1e-4) is not None:
            done += 1
    assert len(q) <= 50 and done + q.skipped + len(q) == 20_000
    assert len(q._best) + len(q._worst) + len(q._fifo) <= 6 * 50 + 192 + 3
