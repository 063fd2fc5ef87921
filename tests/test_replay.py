"""Replays (issue 28): the verifier's replay cache (:mod:`catc.security`) and what the OBU
does with a replay (:mod:`obu.frames`), up to ``rve run --attack replay`` into ``obu run
--verify enforce --mbd``.

* A copy of an accepted message is a ``replay``, octet for octet or re-encoded in any
  way that needs no key (the other s, rSig as a point, another signer field, a WSM).
* Only a message that verified enters the cache: a forgery carrying a future message's
  ToBeSignedData does not make that message a replay.
* The cache forgets a message when it would be stale anyway, and holds at most
  ``max_replays`` hashes.
* The OBU drops a replay under enforce, tracks it under log, and never hands it to
  misbehavior detection: the leader whose frames are replayed is not quarantined and
  its FCW fires as in the clean run.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from functools import cache

import pytest

from catc.bsm import BSM
from catc.cam import SecMarkClock
from catc.j2735 import encode_frame, open_envelope
from catc.j2735.ieee1609 import build_signed, wrap_wsmp
from catc.security import (
    P256_ORDER,
    Pki,
    ReplayCache,
    Verifier,
    make_pki,
    sign_bsm,
    time64_to_unix,
)
from hil.capture import read_rx
from hil.transport.udp import free_ports
from obu.frames import Frames
from obu.status import RateLimitedLog
from tests.test_obu import finish, rve, score, start_obu
from tests.test_security_e2e import pki  # noqa: F401  (fixture)

FRAME = encode_frame(BSM(msg_cnt=7, temp_id=0x12345678, sec_mark=1000, lat=42.3, lon=-83.7,
                         elev=200.0, speed=13.4, heading=90.0))
NOW = 636_913_807_899_000  # Time64, 2024-03-07 TAI
WEEK = 7 * 86400


@cache
def _pki() -> Pki:
    return make_pki(2, start_time32=NOW // 1_000_000 - 86400, duration_s=WEEK, seed=b"replay")


def _verifier(**kw: int) -> Verifier:
    return Verifier([_pki().root.raw], certificates=[_pki().aa.raw], **kw)


def _msg(gen: int = NOW, *, include_cert: bool = True, i: int = 0) -> bytes:
    p = _pki().pseudonyms[i]
    return sign_bsm(FRAME, p.key, p.raw, gen, include_cert=include_cert)


# --- the verifier ------------------------------------------------------------------------------


def test_a_copy_of_an_accepted_message_is_a_replay() -> None:
    v = _verifier()
    msg = _msg()
    assert v.verify(msg, NOW).reason == "ok"
    assert v.verify(msg, NOW + 1_000_000).reason == "replay"  # 1 s late: still fresh
    assert v.verify(msg, NOW + 1_000_000).reason == "replay"  # and again
    assert v.verify(_msg(NOW + 100_000), NOW + 100_000).reason == "ok"  # the next one is new


def test_copies_re_encoded_without_the_key_are_replays() -> None:
    """What a replayer can change without the key is outside the ToBeSignedData: the
    signature's encoding (the other s, rSig as the point R), the signer field (digest or
    certificate), the layers around it (a WSM).  Each copy is a ``replay`` (not a
    ``non-canonical`` signature), also where non-canonical signatures are accepted."""
    msg = _msg()
    r, s = msg[-64:-32], int.from_bytes(msg[-32:], "big")
    copies = {
        "high-S twin": msg[:-32] + (P256_ORDER - s).to_bytes(32, "big"),
        "rSig compressed-y-0": msg[:-65] + b"\x82" + msg[-64:],
        "rSig compressed-y-1": msg[:-65] + b"\x83" + msg[-64:],
        "rSig uncompressed": msg[:-65] + b"\x84" + r + bytes(32) + msg[-32:],
        "digest signer": _msg(include_cert=False),
        "in a WSM": open_envelope(wrap_wsmp(msg))[1],
        "signed by another key": _msg(i=1),  # the same content, another pseudonym
        "garbage signature": msg[:-64] + bytes(range(64)),
    }
    for strict in (True, False):
        v = _verifier(canonical_only=strict)
        assert v.verify(msg, NOW).ok
        for name, copy in copies.items():
            assert v.verify(copy, NOW + 500_000).reason == "replay", (strict, name)
    # the high-S twin is a valid signature: without the cache, a lenient verifier takes it
    twin = copies["high-S twin"]
    assert _verifier(canonical_only=False, max_replays=0).verify(twin, NOW).ok


def test_a_forged_frame_does_not_poison_the_cache() -> None:
    """A forgery carrying the ToBeSignedData of a message not yet sent (its
    generationTime 50 ms ahead) fails its signature and is not remembered: the genuine
    message is accepted when it comes, and only its copies are replays."""
    v = _verifier()
    assert v.verify(_msg(), NOW).ok  # the signer's certificate is now known
    later = NOW + 50_000
    p = _pki().pseudonyms[0]
    genuine = _msg(later, include_cert=False)
    forged = build_signed(FRAME, generation_time_us=later, signer=("digest", p.hashed_id8),
                          signature=genuine[-64:-32] + (12345).to_bytes(32, "big"))
    assert v.verify(forged, NOW).reason == "bad-signature"
    assert v.verify(forged, NOW).reason == "bad-signature"  # not a replay either
    unknown = build_signed(FRAME, generation_time_us=later, signer=("digest", bytes(8)),
                           signature=genuine[-64:])
    assert v.verify(unknown, NOW).reason == "unknown-signer"
    assert v.verify(genuine, later).reason == "ok"
    assert v.verify(genuine, later).reason == "replay"
    assert len(v.replays) == 2


def test_a_message_leaves_the_cache_when_it_would_be_stale() -> None:
    v = _verifier()
    msg = _msg()
    assert v.verify(msg, NOW).ok
    assert v.verify(msg, NOW + v.max_age_us).reason == "replay"  # the last fresh µs
    assert v.verify(msg, NOW + v.max_age_us + 1).reason == "stale"
    later = NOW + 5_000_000
    assert v.verify(_msg(later), later).ok and len(v.replays) == 1  # the old one dropped


def test_the_replay_cache_is_bounded() -> None:
    cache = ReplayCache(1000)
    for i in range(1500):  # all live: the cap evicts the oldest
        cache.add(i.to_bytes(32, "big"), NOW + 10_000_000, NOW)
    assert len(cache) == 1000 and cache.evicted == 500
    assert not cache.seen((0).to_bytes(32, "big"), NOW)
    assert cache.seen((1499).to_bytes(32, "big"), NOW)
    cache.add(b"new", NOW + 20_000_000, NOW + 10_000_001)  # everything else has expired
    assert len(cache) == 1 and cache.evicted == 500
    # the verifier's default: 200,000 hashes at most
    assert _verifier().replays.max_entries == 200_000
    full = ReplayCache()
    for i in range(250_000):
        full.add(i.to_bytes(32, "big"), NOW + 3_000_000, NOW)
    assert len(full) == 200_000 and full.evicted == 50_000
    # through the verifier: a cap of 8 keeps 8 of 20 messages
    v = _verifier(max_replays=8)
    msgs = [_msg(NOW + i) for i in range(20)]
    assert all(v.verify(m, NOW).ok for m in msgs) and len(v.replays) == 8
    assert v.verify(msgs[-1], NOW).reason == "replay"
    assert v.verify(msgs[0], NOW).reason == "ok"  # evicted early: the price of the cap
    with pytest.raises(ValueError):
        ReplayCache(0)


def test_max_replays_zero_turns_the_check_off() -> None:
    v = _verifier(max_replays=0)
    assert v.replays is None
    assert v.verify(_msg(), NOW).ok and v.verify(_msg(), NOW).ok


# --- the OBU's receive path ----------------------------------------------------------------------


class _Capture:
    """What obu.frames records of the frames it does not queue."""

    def __init__(self) -> None:
        self.frames: list[tuple[str, dict]] = []

    def frame(self, rx_unix, channel, data, status, **details) -> None:
        self.frames.append((status, details))


def _frames(mode: str) -> tuple[Frames, list, _Capture]:
    """obu.frames at ``--verify mode --mbd``, with the test PKI's verifier and a spy on
    the misbehavior checks."""
    args = argparse.Namespace(verify="off", trust=None, mbd=True, host_id=None)
    cap = _Capture()
    fr = Frames(args, Counter(), RateLimitedLog(), SecMarkClock(), cap, lambda _id: False)
    from catc.security import unix_to_time64

    fr.verifier, fr.to_time64, fr.enforce = _verifier(), unix_to_time64, mode == "enforce"
    checked: list[int] = []
    misbehaves = fr.misbehaves

    def spy(bsm, rx_unix, data, *rest):
        checked.append(bsm.msg_cnt)
        return misbehaves(bsm, rx_unix, data, *rest)

    fr.misbehaves = spy
    return fr, checked, cap


@pytest.mark.parametrize("mode", ["enforce", "log"])
def test_the_obu_never_gives_a_replay_to_misbehavior_detection(mode: str) -> None:
    fr, checked, cap = _frames(mode)
    rx = time64_to_unix(NOW)
    msg = _msg(NOW - 100_000)
    s = int.from_bytes(msg[-32:], "big")
    high_s = msg[:-32] + (P256_ORDER - s).to_bytes(32, "big")
    fr.take("rv", msg, rx)
    assert checked == [7] and len(fr.pending) == 1
    for copy in (msg, high_s, wrap_wsmp(msg)):
        assert fr.take("rv", copy, rx + 0.5) is None
    assert checked == [7]  # no check saw a copy
    assert fr.counters["verify_ok"] == 1 and fr.counters["verify_replay"] == 3
    if mode == "enforce":
        assert len(fr.pending) == 1 and fr.counters["verify_rejected"] == 3
        assert [(st, d["verdict"], d["sender"][0]) for st, d in cap.frames] == [
            ("rejected", "replay", 0x12345678)] * 3
    else:  # tracked, with its verdict, as log mode tracks every failure
        assert len(fr.pending) == 4 and fr.counters["verify_failed"] == 3
        assert [fr.pending_rx[id(m)][2] for m in fr.pending] == ["ok"] + ["replay"] * 3
        assert cap.frames == []


# --- rve run --attack replay into obu run --verify enforce --mbd --------------------------------


def _run(trust, cap, *attack: str) -> dict:
    ports = free_ports()
    obu = start_obu(cap, ports, "--predictor", "ca", "--verify", "enforce", "--trust",
                    str(trust), "--mbd", "--collect-ms", "30")
    summary = rve(ports, "--sign", str(trust), "--per", "0", "--speed", "8", "--duration", "30",
                  "--capture", str(cap), *attack)
    finish(obu)
    return summary


def test_a_replayed_leader_is_not_quarantined_and_its_fcw_still_fires(pki, tmp_path):  # noqa: F811
    """``--attack replay:vehicle=lead,delay=1,start=10``: the leader's own frames again,
    1 s late, inside the freshness window.  Every copy is dropped as ``replay`` before
    misbehavior detection, so nothing is reported against the leader, it is not
    quarantined, and the FCW on it fires at the same ticks as in the clean run."""
    clean, attacked = tmp_path / "clean", tmp_path / "replay"
    _run(pki, clean)
    summary = _run(pki, attacked, "--attack", "replay:vehicle=lead,delay=1,start=10")
    assert summary["attack_frames"] > 100
    # nobody quarantined, nothing reported, no check fired
    rx = list(read_rx(attacked))
    assert not [r for r in rx if r["status"] == "quarantined"]
    assert (attacked / "obu.mbd.jsonl").read_text() == ""
    assert (attacked / "obu.mbr.jsonl").read_text() == ""
    counters = json.loads((attacked / "obu.counters.json").read_text())
    assert not {k for k in counters if k.startswith("mbd_") and k != "mbd_no_host_yet"}
    # the FCW on the leader, and every app, as in the clean run
    a, b = score(attacked), score(clean)
    assert a["fcw"]["tp"] > 0 and a["fcw"] == b["fcw"]
    assert a["apps"] == b["apps"]
    assert a["received"] == b["received"]
    # every copy dropped as a replay
    assert counters["verify_replay"] == counters["verify_rejected"] == summary["attack_frames"]
    assert a["attacks"]["replay"]["rejected"] == {"replay": summary["attack_frames"]}
    assert {r["verdict"] for r in rx if r["status"] == "rejected"} == {"replay"}


def test_obu_signatures_flag_picks_the_encodings_it_accepts(pki):  # noqa: F811
    """``obu run --signatures standard`` takes every form 1609.2 allows (real senders
    send rSig compressed and high s); ``strict``, the default, only the canonical one."""
    from obu.frames import verifier

    base = dict(verify="enforce", trust=str(pki))
    assert verifier(argparse.Namespace(**base, signatures="strict")).canonical_only
    assert not verifier(argparse.Namespace(**base, signatures="standard")).canonical_only
    assert verifier(argparse.Namespace(**base)).canonical_only  # an older config: strict
