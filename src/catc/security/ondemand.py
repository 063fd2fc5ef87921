"""Verify on demand (issue 30; Krishnan and Weimerskirch, SAE 2011-01-0584): which RV
messages an OBU verifies at once, and the queue of the others.  Pure: no clock, no I/O.

An OBU in dense traffic cannot run ECDSA on every BSM as it arrives (1,000 RVs are 10,000
verifications/s, most of a core).  Each signed message gets the cheap checks at once
(:meth:`catc.security.Verifier.check`: envelope, psid, freshness, a known signer,
replays), and then its :class:`Priority`, from the last :class:`catc.cam.MapSnapshot`
and the decoded BSM (:class:`Threats`):

* **urgent**, its ECDSA at once, on arrival: the RV is new to the map (``new``: its
  TemporaryID is not in the last snapshot, or there is no snapshot yet); it brakes hard by
  its own BSM (``braking``: :func:`catc.cam.hard_braking`, EEBL); it is in the host's path
  ahead, ongoing, now or at the prediction horizon, within the FCW's warning range for a
  stopped RV plus :attr:`OnDemandConfig.ahead_margin_m`, and at least
  :attr:`~OnDemandConfig.ahead_min_m` (``ahead``); it is ongoing in a lane next to the
  host's, from :attr:`~OnDemandConfig.side_behind_m` behind to
  :attr:`~OnDemandConfig.side_ahead_m` ahead, now or at the horizon (``side``: BSW,
  LCW); or its track is unverified and ahead in the host's lane or the next ones within
  the EEBL range (``unverified``: such a track can warn only once a message of it is
  verified);
* **deferred**, the rest, with a threat rank: the RV's distance from the host in bands of
  :attr:`~OnDemandConfig.band_m` (nearer is higher).

:class:`VerifyQueue` holds the deferred messages, highest threat first, newest first
within a threat.  Bounded: beyond ``max_len`` the oldest message of the lowest threat is
dropped, and a message waiting longer than ``max_age_s`` is dropped when it comes to the
front; each drop goes to ``on_skip`` (the OBU counts it as ``verify_skipped``), never
silently.

:class:`UrgentLimiter` bounds the urgent path: per TemporaryID, and for the reasons a
message claims for itself (``new``, ``braking``) over all senders.  An urgent message
beyond it waits in the queue at the highest threat, and the OBU withholds it from its tick
until it is verified: a flood of forged urgent frames then costs the OBU a bounded share
of its ECDSA, and none of them reaches the map unverified.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, NamedTuple, TypeVar

import numpy as np

from catc.apps.fcw import FcwConfig, warning_range
from catc.bsm import BSM
from catc.cam import HARD_BRAKING_DECEL, hard_braking

__all__ = ["CLAIMS", "URGENT_REASONS", "OnDemandConfig", "Priority", "Threats", "UrgentLimiter",
           "VerifyQueue"]

#: Why a message is verified at once (:class:`Priority`.why; ``deferred`` otherwise).
URGENT_REASONS = ("new", "braking", "ahead", "side", "unverified")
#: The urgent reasons a message gives itself, whoever sent it: an unheard TemporaryID, a
#: hard-braking flag (:class:`UrgentLimiter` bounds them together).
CLAIMS = ("new", "braking")

_LEFT, _CENTRE, _RIGHT = 1, 2, 3  # catc.classify.LATERAL_CODES
_ONGOING = 0  # catc.classify.DIRECTION_CODES


@dataclass(frozen=True)
class OnDemandConfig:
    """The threat zones of :class:`Threats` (metres along the host's path, ``s``)."""

    #: Ahead in the path: urgent up to the FCW's range for a stopped RV plus this margin
    #: (the RV moves, and the snapshot is up to a tick old) ...
    ahead_margin_m: float = 50.0
    #: ... and never less than this.
    ahead_min_m: float = 150.0
    #: Adjacent lanes: from this far behind the host's centre (BSW's zone is 3 m behind
    #: its rear bumper; LCW's is that zone at the prediction horizon, which an RV 3 s
    #: behind closing at 15 m/s reaches) ...
    side_behind_m: float = 60.0
    #: ... to this far ahead.
    side_ahead_m: float = 10.0
    #: An unverified track ahead in the host's lane or the next: urgent within this
    #: (catc.apps.eebl's range).
    unverified_ahead_m: float = 300.0
    #: Deferred messages rank by distance in bands this wide (newest first within one).
    band_m: float = 25.0
    fcw: FcwConfig = field(default_factory=FcwConfig)


class Priority(NamedTuple):
    """A message's priority: ``urgent`` (verify at once) and why (one of
    :data:`URGENT_REASONS`, or ``deferred``), and its ``threat`` rank in the queue."""

    urgent: bool
    threat: float
    why: str


_NEW = Priority(True, math.inf, "new")
_BRAKING = Priority(True, math.inf, "braking")


def _zone_rows(zone: Any, length: np.ndarray, ahead_m: float,
               config: OnDemandConfig) -> tuple[np.ndarray, np.ndarray]:
    """Rows ahead in the host's path within ``ahead_m``, and rows in its side zones."""
    ongoing = zone.direction == _ONGOING
    path = zone.ahead & ongoing & (zone.lateral == _CENTRE) & (zone.s <= ahead_m)
    beside = (ongoing & ((zone.lateral == _LEFT) | (zone.lateral == _RIGHT))
              & (zone.s + 0.5 * length >= -config.side_behind_m)
              & (zone.s - 0.5 * length <= config.side_ahead_m))
    return path, beside


class Threats:
    """Every tracked RV's :class:`Priority` at one snapshot (``None``: before the first
    tick, when every RV is new).  Built once per tick (vectorised), then
    :meth:`priority` is a dict lookup per message."""

    def __init__(self, snap: Any | None, config: OnDemandConfig | None = None) -> None:
        self.config = config = config or OnDemandConfig()
        self._rows: dict[int, Priority] | None = None
        if snap is None:
            return
        host = snap.host
        v = host.speed if math.isfinite(host.speed) else 0.0
        a = host.accel if math.isfinite(host.accel) else 0.0
        r_w = warning_range(max(v, 0.0), a, 0.0, 0.0, config.fcw).r_w
        reach = max(config.ahead_min_m, (r_w if math.isfinite(r_w) else 0.0)
                    + 0.5 * host.length + config.ahead_margin_m)
        z, pz = snap.zone, snap.predicted_zone
        path, side = _zone_rows(z, snap.length, reach, config)
        ppath, pside = _zone_rows(pz, snap.length, reach, config)
        verified = getattr(snap, "verified", None)
        if verified is None:
            unverified = np.zeros(len(snap.ids), dtype=bool)
        else:
            lanes = (z.lateral >= _LEFT) & (z.lateral <= _RIGHT)
            unverified = (~np.asarray(verified, dtype=bool) & z.ahead & lanes
                          & (z.s <= config.unverified_ahead_m))
        band = -np.floor(np.hypot(z.s, z.d) / config.band_m)
        rows: dict[int, Priority] = {}
        for i, tid in enumerate(snap.ids.tolist()):
            if path[i] or ppath[i]:
                rows[tid] = Priority(True, math.inf, "ahead")
            elif side[i] or pside[i]:
                rows[tid] = Priority(True, math.inf, "side")
            elif unverified[i]:
                rows[tid] = Priority(True, math.inf, "unverified")
            else:
                b = float(band[i])
                rows[tid] = Priority(False, b if math.isfinite(b) else -1e9, "deferred")
        self._rows = rows

    def priority(self, bsm: BSM) -> Priority:
        """The priority of RV message ``bsm`` (module docstring)."""
        if self._rows is None:
            return _NEW
        row = self._rows.get(bsm.temp_id)
        if row is None:
            return _NEW
        if not row.urgent and hard_braking(bsm, HARD_BRAKING_DECEL):
            return _BRAKING
        return row


class UrgentLimiter:
    """Bounds the ECDSA the urgent path runs at once, so that no sender can make the OBU
    verify at once whatever it sends (a flood of forged frames that claim a new RV or hard
    braking, or that carry the TemporaryID of an RV ahead, each with a known signer's
    digest and a bad signature, would otherwise take a core).  Two token buckets:

    * per TemporaryID, ``per_id_hz`` (default 20/s: twice SAE J2945/1's highest BSM rate)
      with a burst of ``per_id_burst``: an honest sender never meets it;
    * for the :data:`CLAIMS` of all senders together, ``claims_per_s`` (default 2,000/s,
      ~15 % of a core's ECDSA) with a burst of ``claims_burst`` (400: 1,000 RVs heard at
      once come in within a few ticks).

    :meth:`admit` says whether an urgent message may be verified now (a token taken from
    each bucket it needs) or must wait: the OBU then queues it at the highest threat and
    withholds it from its tick unless it is verified before (``obu.frames``).  Times are
    seconds on any clock that does not go back."""

    def __init__(self, claims_per_s: float = 2000.0, claims_burst: float = 400.0,
                 per_id_hz: float = 20.0, per_id_burst: float = 5.0) -> None:
        if not min(claims_per_s, claims_burst, per_id_hz, per_id_burst) > 0.0:
            raise ValueError("the urgent limits must be positive")
        self.claims_per_s, self.claims_burst = claims_per_s, claims_burst
        self.per_id_hz, self.per_id_burst = per_id_hz, per_id_burst
        self._claims = (claims_burst, -math.inf)  # (tokens, at)
        self._ids: dict[int, tuple[float, float]] = {}
        self._pruned = -math.inf

    @staticmethod
    def _tokens(state: tuple[float, float], rate: float, burst: float, t: float) -> float:
        tokens, at = state
        return min(burst, tokens + max(t - at, 0.0) * rate) if at > -math.inf else burst

    def admit(self, temp_id: int, why: str, t: float) -> bool:
        """Whether the urgent message of ``temp_id`` (urgent for reason ``why``) received
        at ``t`` may have its ECDSA now."""
        claims = why in CLAIMS
        if claims:
            pool = self._tokens(self._claims, self.claims_per_s, self.claims_burst, t)
            if pool < 1.0:
                return False
        own = self._ids.get(temp_id)
        mine = (self.per_id_burst if own is None
                else self._tokens(own, self.per_id_hz, self.per_id_burst, t))
        if mine < 1.0:
            return False
        if claims:
            self._claims = (pool - 1.0, t)
        self._ids[temp_id] = (mine - 1.0, t)
        if t - self._pruned >= 1.0:  # forget the ids whose bucket is full again
            self._pruned = t
            full = self.per_id_burst / self.per_id_hz
            self._ids = {k: v for k, v in self._ids.items() if t - v[1] < full}
        return True


T = TypeVar("T")


class VerifyQueue(Generic[T]):
    """The deferred messages (module docstring): :meth:`push` with a threat and a time
    (any clock, seconds), :meth:`pop` the most threatening, newest first.  Each message
    dropped unverified goes to ``on_skip`` and is counted in :attr:`skipped`."""

    def __init__(self, max_len: int = 2000, max_age_s: float = 1.0,
                 on_skip: Callable[[T], None] | None = None) -> None:
        if max_len < 1 or max_age_s <= 0:
            raise ValueError("max_len and max_age_s must be positive")
        self.max_len, self.max_age_s = max_len, max_age_s
        self.on_skip = on_skip
        self.skipped = 0
        self._seq = 0
        self._live: dict[int, tuple[float, float, T]] = {}
        self._best: list[tuple[float, float, int]] = []  # (-threat, -t, -seq)
        self._worst: list[tuple[float, float, int]] = []  # (threat, t, seq)
        self._fifo: deque[tuple[float, int]] = deque()  # (t, seq), in push order

    def __len__(self) -> int:
        return len(self._live)

    def _skip(self, seq: int) -> None:
        item = self._live.pop(seq)[2]
        self.skipped += 1
        if self.on_skip is not None:
            self.on_skip(item)

    def _compact(self) -> None:
        """Rebuild the heaps and the FIFO when mostly made of removed entries."""
        n = len(self._live)
        if len(self._best) + len(self._worst) + len(self._fifo) <= 6 * n + 192:
            return
        live = self._live.items()
        self._best = [(-th, -t, -s) for s, (th, t, _) in live]
        self._worst = [(th, t, s) for s, (th, t, _) in live]
        heapq.heapify(self._best)
        heapq.heapify(self._worst)
        self._fifo = deque(sorted((t, s) for s, (_, t, _) in live))

    def push(self, item: T, threat: float, t: float) -> int:
        """Queue ``item`` (received at ``t``); beyond ``max_len``, the oldest of the lowest
        threat is dropped (possibly this one).  Its key, for :meth:`remove`."""
        self._seq += 1
        seq = self._seq
        self._live[seq] = (threat, t, item)
        heapq.heappush(self._best, (-threat, -t, -seq))
        heapq.heappush(self._worst, (threat, t, seq))
        self._fifo.append((t, seq))
        while len(self._live) > self.max_len:
            _, _, victim = heapq.heappop(self._worst)
            if victim in self._live:
                self._skip(victim)
        self._compact()
        return seq

    def remove(self, key: int) -> bool:
        """Take the item of ``key`` (:meth:`push`'s) out, not counted as skipped; False
        when it is no longer queued (popped, skipped or removed)."""
        if self._live.pop(key, None) is None:
            return False
        self._compact()
        return True

    def expire(self, now: float) -> None:
        """Drop every message received before ``now - max_age_s``."""
        fifo, live = self._fifo, self._live
        while fifo and (fifo[0][1] not in live or fifo[0][0] < now - self.max_age_s):
            _, seq = fifo.popleft()
            if seq in live:
                self._skip(seq)

    def pop(self, now: float) -> T | None:
        """The most threatening message (newest first within a threat), once those older
        than ``max_age_s`` at ``now`` are dropped; None when none is left."""
        self.expire(now)
        while self._best:
            _, _, neg = heapq.heappop(self._best)
            entry = self._live.pop(-neg, None)
            if entry is not None:
                return entry[2]
        return None

    def drain(self) -> list[T]:
        """Every message still queued (oldest first), the queue emptied (not skipped)."""
        out = [item for _, _, item in sorted(self._live.values(), key=lambda e: e[1])]
        self._live.clear()
        self._best, self._worst, self._fifo = [], [], deque()
        return out
