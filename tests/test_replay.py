"""Replays (issue 28): the verifier's replay cache (:mod:`catc.security`).

* A copy of an accepted message is a ``replay``, octet for octet or re-encoded in any
  way that needs no key (the other s, rSig as a point, another signer field, a WSM).
* Only a message that verified enters the cache: a forgery carrying a future message's
  ToBeSignedData does not make that message a replay.
* The cache forgets a message when it would be stale anyway, and holds at most
  ``max_replays`` hashes.
"""

from __future__ import annotations

from functools import cache

import pytest

from catc.bsm import BSM
from catc.j2735 import encode_frame, open_envelope
from catc.j2735.ieee1609 import build_signed, wrap_wsmp
from catc.security import (
    P256_ORDER,
    Pki,
    ReplayCache,
    Verifier,
    make_pki,
    sign_bsm,
)

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



