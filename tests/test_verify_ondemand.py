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


# --- the OBU's receive path, in process ------------------------------------------------------


class _Capture:
    """What obu.frames records: frames it does not queue, and the late outcomes."""

    def __init__(self) -> None:
        self.frames: list[tuple[str, dict]] = []
        self.late_records: list[tuple[int, str, bool]] = []

    def frame(self, rx_unix, channel, data, status, **details) -> None:
        self.frames.append((status, details))

    def late(self, rx_unix, bsm, outcome, stepped) -> None:
        self.late_records.append((bsm.msg_cnt, outcome, stepped))


def _on_demand_frames(pki, snap=None):
    import argparse
    from collections import Counter

    from catc.cam import SecMarkClock
    from catc.security import Threats, unix_to_time64
    from obu.frames import Frames
    from obu.status import RateLimitedLog

    dropped: list[int] = []
    args = argparse.Namespace(verify="off", trust=None, mbd=False, host_id=None)
    cap = _Capture()
    fr = Frames(args, Counter(), RateLimitedLog(), SecMarkClock(), cap,
                lambda tid: dropped.append(tid) or True)
    fr.verifier, fr.to_time64, fr.enforce = _verifier(pki), unix_to_time64, True
    fr.queue, fr.new_threats = VerifyQueue(on_skip=fr._skipped), Threats
    fr.threats = Threats(snap)
    return fr, cap, dropped


def _signed(pki, count: int, gen: int, *, bad: bool = False, tid: int = 0x12345678) -> bytes:
    p = pki.pseudonyms[0]
    frame = encode_frame(BSM(msg_cnt=count, temp_id=tid, sec_mark=1000 + count, lat=42.3,
                             lon=-83.7, elev=200.0, speed=13.4, heading=90.0))
    data = bytearray(sign_bsm(frame, p.key, p.raw, gen, include_cert=True))
    if bad:
        data[-1] ^= 1
    return bytes(data)


def test_obu_verifies_new_rvs_at_once_and_defers_the_others(pki) -> None:
    from catc.security import time64_to_unix

    rx = time64_to_unix(NOW)
    fr, cap, _ = _on_demand_frames(pki)  # no snapshot yet: every RV is new
    fr.take("rv", _signed(pki, 1, NOW), rx)
    fr.take("rv", _signed(pki, 2, NOW + 1, bad=True), rx)
    c = fr.counters
    assert c["ondemand_at_once"] == 1 and c["verify_bad-signature"] == 1
    assert c["ondemand_urgent_new"] == 2 and not c["ondemand_deferred"]
    assert [(s, d["verify"], d["verdict"]) for s, d in cap.frames] == [
        ("rejected", "at-once", "bad-signature")]
    assert [fr.pending_rx[id(m)][2:] for m in fr.pending] == [("ok", "at-once")]
    # far behind in the host's lane: deferred; verified before its tick, a bad one never
    # reaches it
    fr, cap, _ = _on_demand_frames(pki, _snapshot([(0x12345678, -200.0, 0.0, 2, 0, False)]))
    fr.take("rv", _signed(pki, 3, NOW + 3), rx)
    fr.take("rv", _signed(pki, 4, NOW + 4, bad=True), rx)
    assert c is not fr.counters and fr.counters["ondemand_deferred"] == 2
    assert fr.work(math.inf, lambda: 0.0, rx) == 2 and len(fr.queue) == 0
    assert [m.msg_cnt for m in fr.pending] == [3]
    assert fr.pending_rx[id(fr.pending[0])][2:] == ("ok", "queue")
    assert [(s, d["verify"], d["verdict"]) for s, d in cap.frames] == [
        ("rejected", "queue", "bad-signature")]
    assert fr.unverified(fr.pending) == frozenset()


def test_a_frame_stepped_unverified_that_fails_later_drops_its_track(pki) -> None:
    from catc.security import time64_to_unix

    rx = time64_to_unix(NOW)
    fr, cap, dropped = _on_demand_frames(pki, _snapshot([(0x12345678, -200.0, 0.0, 2, 0,
                                                          False)]))
    good, bad = _signed(pki, 5, NOW + 5), _signed(pki, 6, NOW + 6, bad=True)
    replayed = _signed(pki, 7, NOW + 7)
    for data in (good, bad, replayed, replayed):
        fr.take("rv", data, rx)
    ids = fr.unverified(fr.pending)  # the tick comes before the queue is worked
    assert len(ids) == 4 and fr.counters["ondemand_unverified_stepped"] == 4
    assert [fr.pending_rx[id(m)][2:] for m in fr.pending] == [(None, "deferred")] * 4
    assert fr.work(math.inf, lambda: 0.0, rx) == 4
    c = fr.counters
    assert c["ondemand_late_ok"] == 2 and c["ondemand_late_rejected"] == 2
    assert c["verify_bad-signature"] == 1 and c["verify_replay"] == 1
    assert dropped == [0x12345678] and c["ondemand_late_tracks_dropped"] == 1  # not the copy
    assert sorted(cap.late_records) == [(5, "ok", True), (6, "bad-signature", True),
                                        (7, "ok", True), (7, "replay", True)]


def test_the_obu_counts_every_frame_the_full_queue_drops(pki) -> None:
    from catc.security import time64_to_unix

    rx = time64_to_unix(NOW)
    fr, cap, _ = _on_demand_frames(pki, _snapshot([(0x12345678, -200.0, 0.0, 2, 0, False)]))
    fr.queue = VerifyQueue(2, on_skip=fr._skipped)
    for k in range(5):
        fr.take("rv", _signed(pki, 10 + k, NOW + 10 + k), rx + k * 0.01)
    assert fr.counters["ondemand_skipped"] == 3 and len(fr.queue) == 2
    assert [r[:2] for r in cap.late_records] == [(10, "skipped"), (11, "skipped"),
                                                 (12, "skipped")]
    # the skipped ones reach their tick unverified; the queued ones were verified
    fr.work(math.inf, lambda: 0.0, rx)
    assert len(fr.unverified(fr.pending)) == 3
    c = fr.counters
    assert c["ondemand_deferred"] == (c["ondemand_deferred_ok"] + c["ondemand_deferred_failed"]
                                      + c["ondemand_skipped"] + len(fr.queue))


# --- rve run --sign into obu run --verify enforce --verify-policy on-demand ------------------


def test_on_demand_run_warns_on_verified_data_only_and_its_counters_add_up(tmp_path):
    """Two daemons over UDP on loopback.  A queue of 3 frames cannot hold a tick's
    deferred frames, so many reach their tick unverified (skipped), and the lead vehicle,
    which brakes hard at 20 s, signs badly from 5 s on: it must raise no warning, nor
    the outsider's ghost braking ahead of the host; every warning the run does raise is
    on a verified message, from the capture alone."""
    import json
    import subprocess

    from hil.capture import read_rx
    from hil.capture.reader import iter_lines
    from hil.transport.udp import free_ports
    from tests.test_obu import PY, finish, rve, score, start_obu

    pki_dir = tmp_path / "pki"
    out = subprocess.run([PY, "-m", "rve.cli", "pki", "init", str(pki_dir), "--vehicles",
                          "20", "--seed", "ondemand"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    cap = tmp_path / "cap"
    ports = free_ports()
    obu = start_obu(cap, ports, "--predictor", "ca", "--verify", "enforce", "--trust",
                    str(pki_dir), "--verify-queue", "3", "--collect-ms", "30")
    rve(ports, "--sign", str(pki_dir), "--per", "0", "--speed", "8", "--capture", str(cap),
        "--attack", "bad-signature:vehicle=lead", "--attack", "ghost:signer=outsider,start=8")
    _, err = finish(obu)
    c = {k: v for k, v in json.loads(err.strip().splitlines()[-1])["obu"].items()}
    for k in ("ondemand_deferred_failed", "ondemand_late_ok", "ondemand_queue"):
        c.setdefault(k, 0)
    # every RV frame: a verdict (ok or rejected), skipped, or still queued at the end
    assert c.get("decode_errors", 0) == 0
    assert c["frames_rv"] == (c["verify_ok"] + c["verify_rejected"] + c["ondemand_skipped"]
                              + c["ondemand_queue"])
    assert c["ondemand_deferred"] == (c["ondemand_deferred_ok"] + c["ondemand_deferred_failed"]
                                      + c["ondemand_skipped"] + c["ondemand_queue"])
    assert c["ondemand_skipped"] > 0 and c["ondemand_unverified_stepped"] > 0
    assert c["ondemand_at_once"] > 0 and c["verify_bad-signature"] > 0 and c["verify_chain"] > 0
    # the capture says the same, frame by frame
    rx = [r for r in read_rx(cap) if r["channel"] == "rv"]
    how = {}
    for r in rx:
        key = (r["status"], r.get("verify"))
        how[key] = how.get(key, 0) + 1
    assert how.get(("ok", "deferred"), 0) == c["ondemand_unverified_stepped"]
    assert how.get(("ok", "at-once"), 0) + how.get(("ok", "queue"), 0) == (
        c["verify_ok"] - c["ondemand_late_ok"])
    # and what became of each frame stepped unverified (here mostly skipped before it)
    later = list(iter_lines(cap / "obu.verify.jsonl"))
    fate = {(r["id"], r["msgCnt"], r["sec_mark"]): r["outcome"] for r in later}
    stepped = [(r["id"], r["msgCnt"], r["sec_mark"]) for r in rx
               if (r["status"], r.get("verify")) == ("ok", "deferred")]
    assert all(k in fate for k in stepped)
    assert sum(r["outcome"] == "skipped" for r in later) == c["ondemand_skipped"]
    s = score(cap)
    v = s["verification"]
    assert v["policy"] == "on-demand" and v["frames"]["deferred"] > 0
    assert v["warning_ticks"] > 0 and v["warning_events"] > 0
    assert v["all_on_verified"], v["on_unverified"]
    lead = json.loads((cap / "rve.config.json").read_text())["vehicles"]["lead"]
    assert not [e for e in s["events"] if e["rv"] == lead]
    assert s["attacks"]["ghost"]["warnings"] == {} and s["attacks"]["ghost"]["accepted"] == 0


def test_a_worker_process_verifies_the_queue(pki) -> None:
    import time

    from catc.security import time64_to_unix
    from obu.ecdsa_worker import EcdsaWorker

    rx = time64_to_unix(NOW)
    fr, cap, dropped = _on_demand_frames(pki, _snapshot([(0x12345678, -200.0, 0.0, 2, 0,
                                                          False)]))
    fr.worker = EcdsaWorker(1)
    try:
        for k in range(100):
            fr.take("rv", _signed(pki, k, NOW + 20 + k, bad=k in (7, 70)), rx)
        fr.unverified(fr.pending[:50])  # the first half is stepped before the answers
        deadline = time.monotonic() + 30.0
        while fr.queued() and time.monotonic() < deadline:
            fr.pump(rx)
            time.sleep(0.01)
        c = fr.counters
        assert c["ondemand_worker"] == 100 and fr.queued() == 0
        assert c["verify_ok"] == 98 and c["verify_bad-signature"] == 2
        assert c["ondemand_late_rejected"] == 1 and dropped == [0x12345678]  # 7: stepped
        assert [(s, d["verdict"]) for s, d in cap.frames] == [("rejected", "bad-signature")]
        assert len(fr.pending) == 99  # 70 never reaches its tick
    finally:
        fr.drain()


# --- the OBU's tick, in process: a track fed by unverified frames cannot warn --------------


@pytest.mark.parametrize("zones", ["default", "tight"])
def test_a_track_fed_only_by_unverified_frames_raises_no_warning(tmp_path, zones):
    """A stopped RV 150 m ahead of a host at 25 m/s: FCW fires within two seconds.  With
    the default zones the RV is urgent (in the path, within the FCW's reach) and warns;
    with zones so tight that its frames are deferred, and no time to verify them, its
    track is fed by unverified frames once the map shows it (before, it is new: verified
    at once), and no warning may come of it."""
    import argparse
    import time

    from catc.security import OnDemandConfig, Threats, load_private_pem, unix_to_time64
    from hil.pki import init as pki_init
    from obu.daemon import Obu
    from obu.options import DEFAULTS

    pki_init(tmp_path / "pki", 2, 1.0, seed="tight", foreign=False)
    cert = (tmp_path / "pki" / "pseudonym-0.oer").read_bytes()
    key = load_private_pem((tmp_path / "pki" / "pseudonym-0.key.pem").read_bytes())
    args = argparse.Namespace(**DEFAULTS)
    args.verify, args.trust, args.predictor = "enforce", str(tmp_path / "pki"), "ca"
    args.warnings = str(tmp_path / "warnings.jsonl")
    args.verify_workers = 0  # nothing verifies the queue: no worker process either
    obu = Obu(args)
    if zones == "tight":  # nothing is urgent but a new RV or hard braking
        tight = OnDemandConfig(ahead_min_m=0.0, ahead_margin_m=-1e6, side_behind_m=-1e6,
                               unverified_ahead_m=-1.0)
        obu.frames.new_threats = lambda snap: Threats(snap, tight)
    obu._verify_before_step = lambda: None  # the queue is never worked
    lat0, m = 42.3, 1.0 / 111_320.0
    warned = []
    for k in range(30):
        t = 10.0 + 0.1 * k
        now = time.time()
        rv = BSM(msg_cnt=k % 128, temp_id=0x0BAD0001, sec_mark=round(t * 1000) % 60000,
                 lat=lat0 + 150.0 * m, lon=-83.7, elev=200.0, speed=0.0, heading=0.0,
                 accel_long=0.0, length=4.5, width=1.8)
        signed = sign_bsm(encode_frame(rv), key, cert, unix_to_time64(now), include_cert=True)
        obu.frame("rv", signed, now)
        host = BSM(msg_cnt=k % 128, temp_id=0x0000AAAA, sec_mark=round(t * 1000) % 60000,
                   lat=lat0 + 25.0 * 0.1 * k * m, lon=-83.7, elev=200.0, speed=25.0,
                   heading=0.0, accel_long=0.0, length=4.5, width=1.8)
        believed = obu.frame("host", encode_frame(host), now)
        assert believed is not None
        obu.begin(believed)
        snap = obu.tick(believed)
        warned += [w for w in snap.warnings if w.app == "fcw"]
    obu.close()
    c = obu.counters
    if zones == "default":
        assert warned and c["ondemand_at_once"] == 30
    else:
        assert not warned
        # new (at once) until the map shows it, then deferred and stepped unverified
        assert c["ondemand_at_once"] <= 3 and c["ondemand_deferred"] >= 27
        assert c["ondemand_at_once"] + c["ondemand_unverified_stepped"] == 30
        assert not snap.verified.all()  # drawn, as unverified


# --- captures score: the warnings on verified data, from the capture ------------------------


class _Cap:
    def __init__(self, rx, ticks, events, later=()):
        self.obu_config = {"settings": {"verify": "enforce", "verify_policy": "on-demand"}}
        self._rx, self._ticks, self.events, self._later = rx, ticks, events, later

    def iter_rx(self):
        return iter(self._rx)

    def iter_ticks(self):
        return iter(self._ticks)

    def iter_verify(self):
        return iter(self._later)


def _rx(rv: str, tick: float, sec_mark: int, verify: str, verdict: str | None) -> dict:
    r = {"channel": "rv", "status": "ok", "id": rv, "msgCnt": 1, "sec_mark": sec_mark,
         "tick": tick, "verify": verify}
    if verdict:
        r["verdict"] = verdict
    return r


def test_score_finds_a_warning_on_an_unverified_message() -> None:
    from captures.verification import lines, verification

    rx = [_rx("A", 1.0, 1000, "at-once", "ok"), _rx("A", 1.1, 1100, "deferred", None),
          _rx("B", 1.0, 1000, "queue", "ok"), _rx("B", 1.1, 1050, "at-once", "ok"),
          _rx("B", 1.1, 1010, "deferred", None),  # older than B's newest at that tick
          {**_rx("C", 1.1, 1100, "held", None), "status": "withheld"}]  # never stepped
    ticks = [{"t": 1.0, "warnings": [["fcw", "A"]]},
             {"t": 1.1, "warnings": [["bsw", "B"]], "unverified": ["A"]},
             {"t": 1.2, "warnings": [["fcw", "A"]]}]
    events = [{"app": "fcw", "kind": "start", "rv": "A", "t": 1.0}]
    v = verification(_Cap(rx, ticks, events, [{"outcome": "ok", "stepped": True}]))
    assert v["warning_ticks"] == 3 and v["warning_ticks_on_verified"] == 2
    assert v["on_unverified"] == [[1.2, "fcw", "A"]] and not v["all_on_verified"]
    assert v["warning_events_on_verified"] == 1 and v["unverified_track_ticks"] == 1
    assert v["frames"] == {"at_once": 2, "deferred": 2, "queue": 1, "withheld": 1}
    assert v["later"] == {"ok": 1}
    assert "NOT ALL" in "\n".join(lines(v))
    assert verification(_Cap(rx, ticks[:2], events))["all_on_verified"]


# --- the urgent path is bounded: a flood of forged urgent frames ----------------------------


def test_urgent_limiter_spares_honest_senders_and_bounds_a_flood() -> None:
    from catc.security import UrgentLimiter

    lim = UrgentLimiter(claims_per_s=100.0, claims_burst=20.0, per_id_hz=20.0,
                        per_id_burst=5.0)
    # an honest RV ahead at 10 Hz for a minute: never held
    assert all(lim.admit(1, "ahead", 0.1 * k) for k in range(600))
    # a flood of 1,000 frames/s under one id for 2 s: the burst, then 20/s
    flood = sum(lim.admit(2, "ahead", 100.0 + 0.001 * k) for k in range(2000))
    assert 5 + 40 - 1 <= flood <= 5 + 40 + 1
    # 10,000 new ids/s for 1 s: the claims burst, then 100/s, whatever the ids
    new = sum(lim.admit(1000 + k, "new", 200.0 + 0.0001 * k) for k in range(10_000))
    assert 20 + 100 - 1 <= new <= 20 + 100 + 1
    # meanwhile an RV beside the host (not a claim) is spared by the claims bucket
    assert lim.admit(3, "side", 200.5)
    # the ids forgotten once their bucket is full again: memory stays bounded
    lim.admit(4, "ahead", 300.0)
    assert len(lim._ids) == 1
    with pytest.raises(ValueError):
        UrgentLimiter(claims_per_s=0.0)


def _forged(pki, tid: int, count: int, gen: int, accel: float = 0.0) -> bytes:
    """A frame under ``tid`` that names pseudonym 0 as its signer (its digest, known to
    the OBU) and is signed by another key: it passes the cheap checks, fails the ECDSA."""
    p, thief = pki.pseudonyms[0], pki.pseudonyms[1]
    frame = encode_frame(BSM(msg_cnt=count % 128, temp_id=tid, sec_mark=2000 + count,
                             lat=42.3, lon=-83.7, elev=200.0, speed=13.4, heading=90.0,
                             accel_long=accel))
    signed = sign_bsm(frame, thief.key, thief.raw, gen, include_cert=False)
    digest_at = signed.index(thief.hashed_id8)
    return signed[:digest_at] + p.hashed_id8 + signed[digest_at + 8:]


def test_held_urgent_frames_are_withheld_from_their_tick_and_counted(pki) -> None:
    from catc.security import UrgentLimiter, time64_to_unix

    rx = time64_to_unix(NOW)
    fr, cap, dropped = _on_demand_frames(pki)  # no snapshot: every frame is "new"
    fr.limiter = UrgentLimiter(claims_per_s=1.0, claims_burst=2.0)
    fr.take("rv", _signed(pki, 1, NOW + 101), rx)  # the known signer's certificate
    for k in range(6):  # forged hard braking under fresh ids: one claim token left
        fr.take("rv", _forged(pki, 0x7000 + k, k, NOW + 110 + k, accel=-6.0), rx)
    fr.take("rv", _signed(pki, 2, NOW + 120, tid=0x0ABC), rx)  # honest, new: held too
    c = fr.counters
    assert c["ondemand_at_once"] == 1 and c["ondemand_at_once_failed"] == 1
    assert c["ondemand_held"] == 6 and c["ondemand_urgent_new"] == 8
    # the queue verifies one before the tick: the newest, the honest one (top threat)
    steps = iter([0.0, 1.0])
    assert fr.work(0.5, lambda: next(steps), rx) == 1
    due = fr.due(1e9, 1.0)
    assert [m.temp_id for m in due] == [0x12345678, 0x0ABC]
    assert fr.pending_rx[id(due[1])][2:] == ("ok", "queue")
    assert fr.unverified(due) == frozenset()
    assert c["ondemand_withheld"] == 5 and c["ondemand_skipped"] == 5 and not fr.queue
    assert [(s, d["verify"]) for s, d in cap.frames].count(("withheld", "held")) == 5
    assert not dropped  # nothing was stepped unverified: no late failure drops a track
    frames = 8
    assert frames == c["verify_ok"] + c["verify_rejected"] + c["ondemand_skipped"]


@pytest.mark.parametrize("limit", [100.0, "off"])
def test_a_flood_of_forged_urgent_frames_costs_bounded_ecdsa_and_fcw_still_warns(
        tmp_path, limit):
    """The host closes on a stopped RV 150 m ahead at 25 m/s.  Every tick an attacker
    sends 6 forged frames under the RV's own TemporaryID (3 before and 3 after its real
    one) and 20 claiming hard braking under fresh ids, all naming the RV's signer and
    failing its ECDSA (2,000 claims/s, the default bound's rate, would be 200 a tick).
    Bounded at 100 claims/s, the ECDSA run at once is at most the buckets' (20/s per id
    after a burst of 5, 100/s of claims after a burst of 20, on the host's data clock);
    unbounded, it is the whole flood.  Either way FCW warns on the real RV and no forged
    frame is stepped."""
    import argparse
    import time

    from catc.security import load_private_pem, unix_to_time64
    from hil.pki import init as pki_init
    from obu.daemon import Obu
    from obu.options import DEFAULTS

    pki_init(tmp_path / "pki", 2, 1.0, seed="flood", foreign=False)
    cert = (tmp_path / "pki" / "pseudonym-0.oer").read_bytes()
    key = load_private_pem((tmp_path / "pki" / "pseudonym-0.key.pem").read_bytes())
    thief = load_private_pem((tmp_path / "pki" / "pseudonym-1.key.pem").read_bytes())
    args = argparse.Namespace(**DEFAULTS)
    args.verify, args.trust, args.predictor = "enforce", str(tmp_path / "pki"), "ca"
    args.verify_workers, args.verify_urgent = 0, limit
    obu = Obu(args)
    obu._verify_before_step = lambda: None  # worked below, by hand
    lat0, m = 42.3, 1.0 / 111_320.0
    t_unix = time.time()
    warned, ticks, forged, serial = [], 40, 0, iter(range(10**6))

    def rv_frame(k: int, tid: int, signer, accel: float = 0.0, *, full: bool) -> bytes:
        t = 10.0 + 0.1 * k
        bsm = BSM(msg_cnt=k % 128, temp_id=tid, sec_mark=round(t * 1000) % 60000,
                  lat=lat0 + 150.0 * m, lon=-83.7, elev=200.0, speed=0.0, heading=0.0,
                  accel_long=accel, length=4.5, width=1.8)
        gen = unix_to_time64(now) + next(serial)  # µs apart: no two frames are copies
        data = sign_bsm(encode_frame(bsm), signer, cert, gen, include_cert=full)
        if signer is thief:  # a bad signature; the envelope names the RV's certificate
            data = data[:-1] + bytes([data[-1] ^ 1])
        return data

    for k in range(ticks):
        now = t_unix + 0.1 * k
        frames = [rv_frame(k, 0x0BAD0001, thief, full=False) for _ in range(3 if k else 0)]
        frames.append(rv_frame(k, 0x0BAD0001, key, full=k == 0))  # its certificate first
        frames += [rv_frame(k, 0x0BAD0001, thief, full=False) for _ in range(3)]
        frames += [rv_frame(k, 0x5000_0000 + 100 * k + j, thief, -6.0, full=False)
                   for j in range(20)]
        forged += len(frames) - 1
        for data in frames:
            obu.frame("rv", data, now)
        obu.frames.work(math.inf, time.monotonic, now)  # all of the queue, as idle time
        host = BSM(msg_cnt=k % 128, temp_id=0x0000AAAA,
                   sec_mark=round((10.0 + 0.1 * k) * 1000) % 60000,
                   lat=lat0 + 25.0 * 0.1 * k * m, lon=-83.7, elev=200.0, speed=25.0,
                   heading=0.0, accel_long=0.0, length=4.5, width=1.8)
        believed = obu.frame("host", encode_frame(host), now)
        obu.begin(believed)
        snap = obu.tick(believed)
        warned += [w for w in snap.warnings if w.app == "fcw"]
        assert set(snap.ids.tolist()) <= {0x0BAD0001}  # no forged id ever tracked
    obu.close()
    c = obu.counters
    assert warned and all(w.rv_id == 0x0BAD0001 for w in warned)
    assert c["verify_bad-signature"] == forged and c["verify_ok"] == ticks
    assert not c["ondemand_unverified_stepped"]
    at_once_forged = c["ondemand_at_once_failed"]
    print(f"limit {limit}: forged {forged}, ECDSA at once on forged {at_once_forged}, "
          f"held {c['ondemand_held']}, withheld {c['ondemand_withheld']}")
    if limit == "off":
        assert at_once_forged == forged and not c["ondemand_held"]
    else:
        # per tick 2 per-id tokens (20/s) after a burst of 5; 10 claims after 20
        bound = 5 + 2 * ticks + 20 + 10 * ticks
        assert at_once_forged <= bound < forged
        assert c["ondemand_held"] == forged - at_once_forged + (ticks - c["ondemand_at_once"])
