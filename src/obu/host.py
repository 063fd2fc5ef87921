"""Which host frames the OBU believes: the host channel defends itself.

The host vehicle's own state reaches the OBU on a channel of its own (a UDP port, a CAN
id).  Every accepted host frame moves the OBU's clock and steps the CA-TC, so a frame that
merely decodes must not be believed: a flood of corrupted copies at the host port once
drove the clock to 35,364 s in a 440 s run (issue 27).  :class:`HostGate` takes a host
frame only when the host's own motion explains it:

* **one vehicle**: the configured ``--host-id``, or else the first id heard, then that one
  only (``foreign_id``);
* **whole**: time and position present (``incomplete``);
* **newer**: its time after the last accepted frame's (``stale``: a duplicate, a replay, a
  frame from the past);
* **no clock jump**: at most :data:`MAX_GAP_S` later, and its msgCnt advanced by as many
  messages as that time allows: at least one, at most ``gap / MIN_PERIOD_S + 2`` (mod
  128) (``clock_jump``).  A one-bit error in a copied frame's secMark is caught here: the
  copy's msgCnt is its original's;
* **a reachable position and speed**: no farther from the last accepted position than
  the faster of the two speeds, plus :data:`MAX_ACCEL` for the gap, can carry it, with
  :data:`POSITION_SLACK_M` for GNSS noise; the speed changed by no more than
  :data:`MAX_ACCEL` allows (``implausible_motion``).

A host that really jumps (a gap in its own frames) would be locked out for good, so after
:data:`RESYNC_S` of wall time without a believed frame, a chain of :data:`RESYNC_CHAIN`
frames of the locked id, each explained by the one before it, becomes the new reference
(``resyncs``) if it is where the host's own pace (data time per wall time, learnt from
its believed frames) puts it.  While the real host sends, a flood of copies never gets
that chance; once it stops, a replay of its frames from the past is still refused,
unless it is so old that the minute wraps onto the present (a wire attacker who can
replay can also forge: the host channel is the vehicle's own, trusted as such).  A host
whose time went back is still refused by the CA-TC, whose steps must go forward
(``host_backwards``).

Times are secMark differences, read the nearer way round the minute, so the OBU's own
clock (:class:`catc.cam.SecMarkClock`) only ever sees believed frames, each at most
:data:`MAX_GAP_S` after the one before.

The bounds were checked on every host trip of the real datasets (tests/test_host_gate.py:
none is rejected).  Like :class:`obu.tick.TickRule` it reads no clock and touches no
socket: the caller gives it the time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from catc.bsm import BSM, MINUTE_MS, MSG_COUNT_MODULUS
from catc.geo import distance_m

__all__ = ["MAX_ACCEL", "MAX_GAP_S", "MIN_PERIOD_S", "POSITION_SLACK_M", "REASONS",
           "RESYNC_CHAIN", "RESYNC_S", "HostGate", "elapsed", "explains"]

#: The longest gap (s of the host's data time) between two host frames it accepts.
MAX_GAP_S = 2.0
#: The shortest host BSM period it allows for (s): msgCnt may advance by gap / this + 2.
MIN_PERIOD_S = 0.05
#: Acceleration bound (m/s²) for the speed and the distance between two frames: above
#: any road vehicle's braking or acceleration.
MAX_ACCEL = 15.0
#: GNSS noise allowed on top of the distance the motion explains (m).
POSITION_SLACK_M = 5.0
#: Speed assumed when a frame has none (m/s).
DEFAULT_SPEED = 70.0
#: Without an accepted host frame for this long (s, monotonic), a chain may resync.
RESYNC_S = 1.0
#: Frames of the locked id, each explained by the one before, that resync the gate.
RESYNC_CHAIN = 3

#: Why a host frame was not believed (counted as ``host_<reason>``).
REASONS = ("incomplete", "foreign_id", "stale", "clock_jump", "implausible_motion")


@dataclass(frozen=True, slots=True)
class _Fix:
    """What the gate keeps of a host frame."""

    sec_mark: int
    msg_cnt: int
    lat: float
    lon: float
    speed: float | None


class HostGate:
    """Judge host frames (see the module docstring): :meth:`check` returns None for a
    frame to believe (and takes it as the new reference) or the reason it is not."""

    def __init__(self, host_id: int | None = None) -> None:
        #: The host's TemporaryID: configured, or the first heard.
        self.host_id = host_id
        self.last: _Fix | None = None
        self.last_ok = -math.inf  # when (wall s) the last frame was believed
        self.since = -math.inf  # when the believed run of frames began (wall s)
        self.data_s = 0.0  # the host's data time over that run
        self.chain: list[_Fix] = []  # frames not believed, each explained by the one before
        self.resyncs = 0

    def rate(self) -> float | None:
        """The host's data seconds per wall second so far (its replay speed); None
        before :data:`RESYNC_S` of it."""
        wall = self.last_ok - self.since
        return self.data_s / wall if wall >= RESYNC_S else None

    def check(self, bsm: BSM, now: float) -> str | None:
        """None when ``bsm`` (a decoded host frame, received at ``now``, wall-clock s)
        is to be believed; else the reason, one of :data:`REASONS`."""
        if bsm.sec_mark is None or bsm.lat is None or bsm.lon is None:
            return "incomplete"
        if self.host_id is None:
            self.host_id = bsm.temp_id
        elif bsm.temp_id != self.host_id:
            return "foreign_id"
        fix = _Fix(bsm.sec_mark, bsm.msg_cnt, bsm.lat, bsm.lon, bsm.speed)
        if self.last is None:
            self.last, self.last_ok, self.since = fix, now, now
            return None
        reason = explains(self.last, fix)
        if reason is None:
            self.data_s += elapsed(self.last.sec_mark, fix.sec_mark)
            self.last, self.last_ok, self.chain = fix, now, []
            return None
        if now - self.last_ok >= RESYNC_S and self._resync(fix, now):
            self.resyncs += 1
            if self.rate() is None:  # a new pace to learn
                self.since, self.data_s = now, 0.0
            else:  # the same host at the same pace, across its gap
                self.data_s += elapsed(self.last.sec_mark, fix.sec_mark)
            self.last, self.last_ok, self.chain = fix, now, []
            return None
        return reason

    def _resync(self, fix: _Fix, now: float) -> bool:
        """``fix`` extends the chain of frames not believed; True when the chain is long
        enough and ``fix`` is where the host's own pace puts it, :data:`RESYNC_S` or more
        after the last believed frame: its time after that frame's within 10 % (and
        0.5 s) of the wall time since then at the host's rate (a replay of the host's
        older frames is not)."""
        if self.chain and explains(self.chain[-1], fix) is None:
            self.chain.append(fix)
        else:
            self.chain = [fix]
        if len(self.chain) < RESYNC_CHAIN:
            return False
        rate = self.rate()
        if rate is None:
            return True
        expected = rate * (now - self.last_ok)
        return abs(elapsed(self.last.sec_mark, fix.sec_mark) - expected) \
            <= 0.1 * expected + 0.5


def elapsed(a: int, b: int) -> float:
    """Seconds from secMark ``a`` to secMark ``b`` (ms within the minute), read as the
    nearer of the two ways round the minute: in (-30, 30]."""
    return ((b - a + 29_999) % MINUTE_MS - 29_999) / 1000.0


def explains(a: _Fix, b: _Fix) -> str | None:
    """None when frame ``b`` can follow frame ``a`` of the same vehicle; else why not."""
    dt = elapsed(a.sec_mark, b.sec_mark)
    if dt <= 0.0:
        return "stale"
    n = (b.msg_cnt - a.msg_cnt) % MSG_COUNT_MODULUS
    if dt > MAX_GAP_S or not 1 <= n <= dt / MIN_PERIOD_S + 2:
        return "clock_jump"
    va = DEFAULT_SPEED if a.speed is None else a.speed
    vb = DEFAULT_SPEED if b.speed is None else b.speed
    if abs(vb - va) > MAX_ACCEL * dt + 1.0:
        return "implausible_motion"
    reach = (max(va, vb) + MAX_ACCEL * dt) * dt + POSITION_SLACK_M
    if distance_m(a.lat, a.lon, b.lat, b.lon) > reach:
        return "implausible_motion"
    return None
