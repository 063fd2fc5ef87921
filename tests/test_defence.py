"""``captures defence`` (issue 28 part 4, "the score measures the defence"): an attacked
run against its clean twin.  The score reported a replay of the leader as detection
recall 1.0 and precision 1.0, because the id it quarantined was the one the attack named,
the honest victim's; and it did not count the warnings the attack suppressed.

* The OBU's rx record says why misbehavior detection dropped a frame (its sender's
  quarantine, a copy, a stale frame, an id conflict), so a capture tells a quarantined
  vehicle from a dropped copy.
* A hand-made pair of captures (the offline simulator's run of the built-in scenario
  written through the capture writers, as in ``tests/test_capture_files.py``): the
  attacked run lost the FCW on the leader and quarantined the leader.
* Live, ``attack_checks`` with a replay of the leader against ``enforce+mbd`` (the
  verifier's replay cache drops every copy: nothing lost, nobody quarantined) and
  against no defence.
"""

from __future__ import annotations

import argparse
from collections import Counter

from catc.bsm import BSM
from catc.cam import SecMarkClock
from catc.replay import temp_id
from hil.capture import schema
from obu.frames import Frames
from obu.status import RateLimitedLog

T0 = 1_800_000_000.0  # the run's wall clock at dataset time 0
DURATION = 30.0  # the leader brakes at 20 s
REPLAY = "replay:vehicle=lead,delay=1,start=10"
QUARANTINE_T = 15.0  # the attacked OBU quarantines the leader from here on
LEAD = f"{temp_id('lead'):08X}"


# --- the rx record says why a frame was dropped --------------------------------------------


class _Capture:
    def __init__(self) -> None:
        self.frames: list[tuple[str, dict]] = []

    def frame(self, rx_unix, channel, data, status, **details) -> None:
        self.frames.append((status, details))

    def report(self, *args) -> None:
        pass


def test_the_rx_record_tells_a_quarantined_sender_from_a_dropped_copy():
    args = argparse.Namespace(verify="off", trust=None, mbd=True, host_id=None)
    cap = _Capture()
    fr = Frames(args, Counter(), RateLimitedLog(), SecMarkClock(), cap, lambda _id: False)
    host = BSM(msg_cnt=0, temp_id=1, sec_mark=0, lat=47.0, lon=19.0, speed=0.0, heading=0.0,
               length=5.0, width=1.8)
    fr.last_host = (host, 100.0, 10.0)
    fr.last_signer = b"A" * 8

    def rv(tid: int, k: int) -> BSM:  # 2.2 km from the host: out of range, a weak finding
        return BSM(msg_cnt=k, temp_id=tid, sec_mark=10_000 + 100 * k, lat=47.02, lon=19.0,
                   speed=0.0, heading=0.0, length=4.5, width=1.8)

    dropped = [fr.misbehaves(rv(7, k), 100.0, b"", "ok") for k in range(3)]
    assert dropped == [False, False, True]  # 3 weak findings in 10 s: quarantined
    assert fr.misbehaves(rv(7, 2), 100.0, b"", "ok")  # the same message again
    fr.last_signer = b"B" * 8  # another certificate under the same id
    assert fr.misbehaves(rv(7, 3), 100.0, b"", "ok")
    assert [(st, d["why"]) for st, d in cap.frames] == [
        ("quarantined", "quarantine"), ("quarantined", "copy"),
        ("quarantined", "id-conflict")]
    rec = schema.received(1.0, "rv", b"", "quarantined", sender=(7, 3, 10_300),
                          why="copy")
    assert rec["status"] == "quarantined" and rec["why"] == "copy"
    assert "why" not in schema.received(1.0, "rv", b"", "ok", sender=(7, 3, 10_300))
