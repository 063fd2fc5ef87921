"""What becomes of each frame the OBU receives, before any tick: decoded, verified,
checked for misbehavior, counted, and an RV message queued for its tick.

* Decoding (:func:`catc.j2735.open_envelope`, :func:`catc.j2735.decode_frame`): a frame
  that does not decode (garbage, truncated, another message, absurd values) is counted by
  reason (``decode_errors``, ``decode_<reason>``), logged at most once per reason per
  second, recorded with its reason as status, and dropped.
* Security (``--verify log|enforce``): every RV frame's IEEE 1609.2 envelope (inside a
  WSMP message or not) is verified with :class:`catc.security.Verifier` at its receive
  time: signature and its canonical encoding, chain to the trusted root, psid 0x20 (and
  the WSM's), one signed layer, validity period, generationTime freshness, expiryTime,
  replays (:mod:`catc.security`).  Each verdict is counted (``verify_ok``,
  ``verify_<reason>``) and kept in the frame's record; ``enforce`` drops a frame that
  fails (status ``rejected``), ``log`` tracks it anyway.  Host frames are not verified
  (they are the host's own state, not radio traffic).
* Verify on demand (``--verify enforce --verify-policy on-demand``, the default policy;
  :mod:`catc.security.ondemand`): every signed RV frame gets the cheap checks on arrival
  (:meth:`catc.security.Verifier.check`; a failure is rejected as above), then its
  priority from the last snapshot.  An urgent one (a new RV, hard braking, in the path
  within the FCW's reach, in a side lane, an unverified track ahead) is verified at once
  (``ondemand_at_once``); the others are deferred (``ondemand_deferred``) into a
  :class:`~catc.security.ondemand.VerifyQueue` that :meth:`Frames.work` verifies in the
  OBU's idle time and before each tick.  A deferred frame verified before its tick is
  trusted there (``ondemand_deferred_ok``; one that fails is rejected and never stepped);
  one its tick reaches unverified is stepped as such (``ondemand_unverified_stepped``; the
  CAM flags its track and no application sees it), and when it is verified later and
  fails (``ondemand_late_rejected``) its sender's track is dropped, unless it was a replay:
  a copy of what the sender said.  The queue drops the oldest low-threat frames under
  overload (``ondemand_skipped``); ``verify_ok`` and ``verify_<reason>`` count every
  verdict, at once or later (the ``ondemand_`` counters are each frame's way, kept apart
  from the ``verify_`` ones, which name verdicts only).  So an RV frame is a decode
  error, or ``verify_ok + verify_rejected + ondemand_skipped`` + the frames still queued
  (``ondemand_queue``).
  The ECDSA at once is bounded (``--verify-urgent``, :class:`catc.security.UrgentLimiter`):
  an urgent frame beyond the bound is held (``ondemand_held``), queued at the highest
  threat, and withheld from its tick unless verified first (``ondemand_withheld``, status
  ``withheld``): never stepped unverified.
  Misbehavior detection sees a deferred frame only once verified before its tick.
* Replays never reach misbehavior detection, in either mode.  A ``replay`` is a copy of
  a message already accepted, octet for octet or re-encoded: what it says about its
  sender is what that sender said earlier, and sent again by someone else it is
  evidence against the wrong vehicle (a leader replayed 1 s late "jumps back" and would
  be quarantined, and its genuine frames dropped with it).  Under ``enforce`` it is
  dropped (``verify_replay``, status ``rejected``); under ``log`` it is tracked with its
  verdict, as every failure is there, but not given to the checks.
* The host channel (:class:`obu.host.HostGate`): a host frame is believed only when it is
  the host's (``--host-id``, or the first id heard) and its own motion explains it; the
  rest are counted (``host_rejected``, ``host_<reason>``), logged at most once per reason
  per second, recorded with status ``host_<reason>``, and start no tick.
* Misbehavior (``--mbd``): :class:`catc.mbd.MisbehaviorDetector`'s checks on every RV
  message that passes verification, on the host's clock; a detection is counted
  (``mbd_<check>``) and reported, and a sender in quarantine is dropped with its track
  (status ``quarantined``).  With ``--verify`` the evidence attaches to the signing
  certificate (the verdict's HashedId8), which holds the ids it signs: a message under an
  id another certificate holds is dropped (``mbd_id-conflict``), its signer the suspect,
  and a quarantine drops every id of its signer.  A copy of a message already heard, or
  one older than its sender's last (a replay: it needs no key), is dropped without a
  finding (``mbd_copy``, ``mbd_stale``).  All these frames are recorded with status
  ``quarantined`` and why (``why``: ``quarantine``, its sender's; ``copy``, ``stale``,
  ``id-conflict``), so a capture tells a quarantined sender from a dropped copy.
  Without ``--verify`` the evidence attaches to the TemporaryID, which anyone can claim:
  that mode cannot resist id theft.
* The queue: a decoded RV message waits in :attr:`Frames.pending` until the tick it is due
  at (:meth:`Frames.due`, :mod:`obu.tick`).
"""

from __future__ import annotations

import argparse
import math
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from catc.bsm import BSM
from catc.cam import SecMarkClock
from catc.errors import DecodeError
from catc.j2735 import decode_frame, open_envelope
from catc.replay import split_due
from obu.capture import ObuCapture, Received
from obu.host import HostGate
from obu.status import RateLimitedLog

__all__ = ["PUMP_EVERY", "Deferred", "Frames", "claimed_sender", "verifier"]

#: With ``--verify-workers``: the workers are fed (and their answers settled) at least
#: every this many deferred frames, besides once per pass of the event loop and per tick.
PUMP_EVERY = 128


def verifier(args: argparse.Namespace) -> Any:
    """The IEEE 1609.2 verifier (:class:`catc.security.Verifier`) of ``--verify
    log|enforce`` (None when off); ValueError (one line) for a missing or unusable trust
    store."""
    if args.verify in (None, "off"):
        return None
    if not args.trust:
        raise ValueError(f"--verify {args.verify} needs --trust PKI_DIR or ROOT.oer")
    from catc.security import Verifier
    from hil.pki import trust_store

    roots, cas = trust_store(args.trust)
    try:
        return Verifier(roots, certificates=cas,
                        canonical_only=getattr(args, "signatures", "strict") == "strict")
    except ValueError as err:
        raise ValueError(f"--trust {args.trust}: {err}") from None


def claimed_sender(frame: bytes) -> tuple[int, int, int | None] | None:
    """Who a rejected frame claims to be (TemporaryID, msgCnt, secMark), for the capture;
    None when it does not decode."""
    try:
        bsm = decode_frame(frame)
    except DecodeError:
        return None
    return (bsm.temp_id, bsm.msg_cnt, bsm.sec_mark)


class Deferred:
    """A frame waiting in the verification queue: its BSM, what the cheap checks left for
    the ECDSA (:class:`catc.security.Checked`), its receive time and octets, whether a
    tick stepped it unverified, whether it is an urgent frame held back by the
    :class:`~catc.security.UrgentLimiter` (its tick withholds it unless it is verified
    first), and its key in the queue."""

    __slots__ = ("bsm", "checked", "data", "held", "rx_unix", "seq", "stepped")

    def __init__(self, bsm: BSM, checked: Any, rx_unix: float, data: bytes,
                 held: bool = False) -> None:
        self.bsm, self.checked, self.rx_unix, self.data = bsm, checked, rx_unix, data
        self.stepped, self.held, self.seq = False, held, 0


class Frames:
    """The receive path of ``obu run`` (see the module docstring).  ``counters``, ``log``
    and ``clock`` (the host's) are the daemon's; ``cap`` its capture (or None); ``drop``
    removes a quarantined sender's track from the map (:meth:`catc.cam.ContextAwareMap.drop`,
    True when there was one)."""

    #: A host frame older than this (s) is no position for the range and appearance
    #: checks (catc.mbd: a stale host position gives false sudden appearances).
    HOST_FRESH_S = 0.5

    def __init__(self, args: argparse.Namespace, counters: Counter[str], log: RateLimitedLog,
                 clock: SecMarkClock, cap: ObuCapture | None,
                 drop: Callable[[int], bool]) -> None:
        self.counters = counters
        self.log = log
        self.clock = clock
        self.cap = cap
        self.drop = drop
        self.pending: list[BSM] = []  # decoded RV BSMs waiting for their tick
        # id(bsm) -> (rx unix, octets, verdict, when verified: verify on demand)
        self.pending_rx: dict[int, tuple[float, bytes, str | None, str | None]] = {}
        self.verifier = verifier(args)
        if self.verifier is not None:
            from catc.security import unix_to_time64

            self.to_time64 = unix_to_time64
        self.mbd = None
        if args.mbd:
            from catc.mbd import MisbehaviorDetector

            self.mbd = MisbehaviorDetector()
        self.last_host: tuple[BSM, float, float] | None = None  # the ticking host frame:
        # BSM, rx unix, its time on the host's clock
        self.host_rx: dict[int, float] = {}  # id(host BSM) -> rx unix, until its tick
        self.gate = HostGate(getattr(args, "host_id", None))
        self.last_signer: bytes | None = None  # the HashedId8 of the last verified frame
        self.enforce = args.verify == "enforce"
        #: verify on demand: the queue, the priorities at the last tick, and the frames
        #: waiting for their tick unverified (id(bsm) -> its queue entry)
        self.queue: Any = None
        self.deferred: dict[int, Deferred] = {}
        if self.enforce and getattr(args, "verify_policy", "all") == "on-demand":
            from catc.security import Threats, VerifyQueue

            self.queue = VerifyQueue(getattr(args, "verify_queue", 2000),
                                     on_skip=self._skipped)
            self.threats = Threats(None)
            self.new_threats = Threats
        #: verify on demand: the bound on the ECDSA run at once (None: unbounded)
        self.limiter: Any = None
        urgent = getattr(args, "verify_urgent", None)
        if self.queue is not None and urgent not in (None, "off"):
            from catc.security import UrgentLimiter

            self.limiter = UrgentLimiter(float(urgent), max(1.0, float(urgent) / 5.0))
        #: --verify-workers: processes that run the queue's ECDSA (obu.ecdsa_worker)
        self.worker: Any = None
        if self.queue is not None and getattr(args, "verify_workers", 0):
            from obu.ecdsa_worker import EcdsaWorker

            self.worker = EcdsaWorker(args.verify_workers)

    def take(self, channel: str, data: bytes, rx_unix: float) -> BSM | None:
        """One received frame on ``channel`` (``rv`` or ``host``): an RV message is
        queued; the host's BSM is returned (it triggers a tick); None for the rest."""
        verdict = None
        try:
            frame, envelope = open_envelope(data)
            if channel == "rv" and self.queue is not None:
                return self._on_demand(frame, envelope, data, rx_unix)
            if channel == "rv" and self.verifier is not None:
                verdict = self.verify(envelope, rx_unix)
                if verdict != "ok" and self.enforce:
                    self.log(verdict, f"dropped an RV frame that does not verify: {verdict}")
                    if self.cap is not None:
                        self.cap.frame(rx_unix, channel, data, "rejected",
                                       sender=claimed_sender(frame), verdict=verdict)
                    return None
                if verdict == "replay":  # log: tracked, but no evidence for MBD
                    bsm = decode_frame(frame)
                    self.pending.append(bsm)
                    self.pending_rx[id(bsm)] = (rx_unix, data, verdict, None)
                    return None
            bsm = decode_frame(frame)
        except DecodeError as err:
            self.counters["decode_errors"] += 1
            self.counters[f"decode_{err.reason}"] += 1
            self.log(err.reason, f"dropped an undecodable {channel} frame ({err})")
            if self.cap is not None:
                self.cap.frame(rx_unix, channel, data, err.reason)
            return None
        if channel == "rv":
            if self.mbd is not None and self.misbehaves(bsm, rx_unix, data, verdict):
                return None
            self.pending.append(bsm)
            self.pending_rx[id(bsm)] = (rx_unix, data, verdict, None)
            return None
        resyncs = self.gate.resyncs
        reason = self.gate.check(bsm, rx_unix)
        if self.gate.resyncs != resyncs:
            self.counters["host_resyncs"] += 1
            self.log("host_resync", "the host's frames went on after a gap: resynced")
        if reason is not None:
            self.counters["host_rejected"] += 1
            self.counters[f"host_{reason}"] += 1
            self.log(f"host_{reason}", f"host frame not believed: {reason} (host id "
                                       f"{self.gate.host_id:08x})")
            if self.cap is not None:
                self.cap.frame(rx_unix, channel, data, f"host_{reason}",
                               sender=(bsm.temp_id, bsm.msg_cnt, bsm.sec_mark))
            return None
        self.host_rx[id(bsm)] = rx_unix
        return bsm

    def _count(self, reason: str) -> None:
        self.counters[f"verify_{reason}"] += 1
        if reason != "ok":
            self.counters["verify_rejected"] += 1

    def _reject(self, rx_unix: float, data: bytes, frame: bytes | None, reason: str,
                verify: str | None = None, sender: Any = None) -> None:
        self.log(reason, f"dropped an RV frame that does not verify: {reason}")
        if self.cap is not None:
            self.cap.frame(rx_unix, "rv", data, "rejected", verify=verify, verdict=reason,
                           sender=sender if sender is not None else claimed_sender(frame))

    def _on_demand(self, frame: bytes, envelope: Any, data: bytes, rx_unix: float) -> None:
        """An RV frame under verify on demand (module docstring): checked, then verified
        at once or queued.  Raises :class:`DecodeError` for a frame that does not decode."""
        from catc.security import Verdict

        checked = (Verdict(False, "unsigned", frame) if envelope is None
                   else self.verifier.check(envelope, self.to_time64(rx_unix)))
        if isinstance(checked, Verdict):  # a cheap check failed
            self._count(checked.reason)
            self._reject(rx_unix, data, frame, checked.reason)
            return None
        bsm = decode_frame(frame)
        priority = self.threats.priority(bsm)
        if priority.urgent and self.limiter is not None and not self.limiter.admit(
                bsm.temp_id, priority.why, self._data_time()):
            self.counters[f"ondemand_urgent_{priority.why}"] += 1
            self.counters["ondemand_held"] += 1
            self._defer(Deferred(bsm, checked, rx_unix, data, held=True), math.inf,
                        "held")
            return None
        if priority.urgent:
            v = self.verifier.finish(checked)
            self._count(v.reason)
            self.counters[f"ondemand_urgent_{priority.why}"] += 1
            if not v.ok:
                self.counters["ondemand_at_once_failed"] += 1
                self._reject(rx_unix, data, frame, v.reason, "at-once")
                return None
            self.counters["ondemand_at_once"] += 1
            self.last_signer = v.signer_digest
            if self.mbd is not None and self.misbehaves(bsm, rx_unix, data, "ok"):
                return None
            self.pending.append(bsm)
            self.pending_rx[id(bsm)] = (rx_unix, data, "ok", "at-once")
            return None
        self._defer(Deferred(bsm, checked, rx_unix, data), priority.threat, "deferred")
        return None

    def _data_time(self) -> float:
        """The limiter's clock: the host's data time at its newest frame (0 before the
        first), so that a replay faster than real time (``rve run --speed``) is not taken
        for a flood."""
        return self.last_host[2] if self.last_host is not None else 0.0

    def _defer(self, entry: Deferred, threat: float, how: str) -> None:
        """Queue ``entry`` for its ECDSA, its message waiting for its tick meanwhile."""
        self.counters["ondemand_deferred"] += 1
        bsm = entry.bsm
        self.pending.append(bsm)
        self.pending_rx[id(bsm)] = (entry.rx_unix, entry.data, None, how)
        self.deferred[id(bsm)] = entry
        entry.seq = self.queue.push(entry, threat, entry.rx_unix)
        if self.worker is not None and not self.counters["ondemand_deferred"] % PUMP_EVERY:
            self.pump(entry.rx_unix)  # a busy OBU seldom gets back to its loop: feed it

    def _skipped(self, entry: Deferred) -> None:
        """The queue dropped ``entry`` unverified (overload, or too old)."""
        self.counters["ondemand_skipped"] += 1
        # still in self.deferred: its tick steps it unverified
        if self.cap is not None:
            self.cap.late(entry.rx_unix, entry.bsm, "skipped", entry.stepped)

    def work(self, until: float, clock: Callable[[], float],
             now_unix: float | None = None) -> int:
        """Verify queued frames, most threatening first, until ``clock()`` reaches
        ``until`` or the queue is empty (and, with ``--verify-workers``, no batch is left
        at a worker: its answers are waited for meanwhile); how many were verified here.
        ``now_unix`` (default the wall clock) ages the queue: frames received too long
        before are dropped."""
        queue = self.queue
        if queue is None or not self.queued():
            return 0
        if now_unix is None:
            now_unix = time.time()
        n = 0
        finish, worker = self._finish, self.worker
        while (left := until - clock()) > 0.0:
            entry = queue.pop(now_unix)
            if entry is not None:
                finish(entry)
                n += 1
            elif worker is None or not worker.wait(left):
                break
            else:  # the queue is empty, a worker answers: those count now too
                self.pump(now_unix)
        return n

    def pump(self, now_unix: float | None = None) -> None:
        """With ``--verify-workers``: settle the frames the workers have verified, and
        send them more from the queue (never blocks)."""
        worker = self.worker
        if worker is None:
            return
        settle = self.verifier.settle
        n = 0
        for entry, ok in worker.done():
            self._finish(entry, settle(entry.checked, ok))
            n += 1
        self.counters["ondemand_worker"] += n
        if len(self.queue):
            if now_unix is None:
                now_unix = time.time()
            self.counters["ondemand_sent"] += worker.feed(lambda: self.queue.pop(now_unix))
        self.counters["ondemand_pumps"] += 1

    def _finish(self, e: Deferred, v: Any = None) -> None:
        """The ECDSA of a queued frame (``v``: its verdict when a worker made it), and
        what follows from its verdict."""
        if v is None:
            v = self.verifier.finish(e.checked)
        self._count(v.reason)
        bsm, key = e.bsm, id(e.bsm)
        if e.stepped:  # its tick took it unverified: too late to keep it out
            if v.ok:
                self.counters["ondemand_deferred_ok"] += 1
                self.counters["ondemand_late_ok"] += 1
            else:
                self.counters["ondemand_deferred_failed"] += 1
                self.counters["ondemand_late_rejected"] += 1
                self.log("late", f"an RV frame stepped unverified does not verify: "
                                 f"{v.reason}" + ("" if v.reason == "replay" else
                                                  "; its sender's track dropped"))
                # a replay is a copy of what its sender said: no reason to drop the track
                if v.reason != "replay" and self.drop(bsm.temp_id):
                    self.counters["ondemand_late_tracks_dropped"] += 1
            if self.cap is not None:
                self.cap.late(e.rx_unix, bsm, v.reason, True)
            return
        self.deferred.pop(key, None)
        self.counters["ondemand_deferred_ok" if v.ok else "ondemand_deferred_failed"] += 1
        if key not in self.pending_rx:  # quarantined meanwhile (--mbd): gone already
            return
        if v.ok:
            self.pending_rx[key] = (e.rx_unix, e.data, "ok", "queue")
            self.last_signer = v.signer_digest
            if self.mbd is not None and self.misbehaves(bsm, e.rx_unix, e.data, "ok"):
                self._unqueue(bsm)
            return
        self._unqueue(bsm)
        self._reject(e.rx_unix, e.data, None, v.reason, "queue",
                     (bsm.temp_id, bsm.msg_cnt, bsm.sec_mark))

    def _unqueue(self, bsm: BSM) -> None:
        """Take ``bsm`` out of the messages waiting for their tick (when still there)."""
        self.pending_rx.pop(id(bsm), None)
        for i, m in enumerate(self.pending):
            if m is bsm:
                del self.pending[i]
                break

    def unverified(self, messages: list[BSM]) -> frozenset[int]:
        """The ``id()`` of the ``messages`` a tick takes unverified (for
        :meth:`catc.cam.ContextAwareMap.step`); each is marked stepped, and stays queued."""
        if not self.deferred:
            return frozenset()
        out = []
        for m in messages:
            entry = self.deferred.pop(id(m), None)
            if entry is not None:
                entry.stepped = True
                out.append(id(m))
        self.counters["ondemand_unverified_stepped"] += len(out)
        return frozenset(out)

    def new_snapshot(self, snap: Any) -> None:
        """A tick's snapshot: the priorities of the frames until the next."""
        if self.queue is not None:
            self.threats = self.new_threats(snap)

    def queued(self) -> int:
        """Frames waiting for their ECDSA: in the queue, and sent to a worker."""
        if self.queue is None:
            return 0
        return len(self.queue) + (len(self.worker.in_flight()) if self.worker else 0)

    def drain(self) -> None:
        """The run ends: what is still queued (or at a worker) is recorded ``pending``;
        the workers stop."""
        if self.queue is None:
            return
        left = self.queue.drain()
        if self.worker is not None:
            left += self.worker.in_flight()
            self.worker.close()
        for e in left:
            if self.cap is not None:
                self.cap.late(e.rx_unix, e.bsm, "pending", e.stepped)

    def start_tick(self, host: BSM) -> float:
        """Host frame ``host`` (believed by :meth:`take`) starts its tick: from now on
        it is the host's position and clock for the misbehavior checks.  Its rx time."""
        rx_unix = self.host_rx.pop(id(host))
        self.last_host = (host, rx_unix, self.clock(host.sec_mark))
        return rx_unix

    def verify(self, envelope: Any, rx_unix: float) -> str:
        """The 1609.2 verdict of one RV frame (``ok`` or a reason), counted."""
        if envelope is None:
            reason = "unsigned"
        else:
            reason = (v := self.verifier.verify(envelope, self.to_time64(rx_unix))).reason
            self.last_signer = v.signer_digest
        self.counters[f"verify_{reason}"] += 1
        if reason != "ok":
            self.counters["verify_rejected" if self.enforce else "verify_failed"] += 1
        return reason

    def misbehaves(self, bsm: BSM, rx_unix: float, data: bytes,
                   verdict: str | None = None) -> bool:
        """Run the misbehavior checks on one RV BSM; write each finding
        (:meth:`obu.capture.ObuCapture.finding`) and each report, once its sender's
        evidence passed the reporting threshold (:meth:`~obu.capture.ObuCapture.report`,
        :attr:`catc.mbd.MisbehaviorDetector.reports`); True (drop it) when the detector drops
        it (a copy, a stale message, an id another signer holds) or its signer is in
        quarantine (then the tracks of every id the signer holds go too).  ``verdict`` is
        its 1609.2 verdict: only a verified signature (``ok``) names a signer.

        The checks' clock is the host's (its secMark time at the newest host frame), like
        the CAM's: a replay faster than real time (``rve run --speed``) then looks to them
        as it would on the road, where the receive clock and the senders' secMarks
        advance together.  Before the first host frame nothing is checked."""
        host = self.last_host
        if host is None:
            self.counters["mbd_no_host_yet"] += 1
            return False
        t = host[2]
        fresh = rx_unix - host[1] <= self.HOST_FRESH_S
        hb = host[0] if fresh else None
        signer = self.last_signer if verdict == "ok" else None
        mbd = self.mbd
        found = mbd.observe(bsm, t, hb.lat if hb else None, hb.lon if hb else None,
                            host_heading=hb.heading if hb else None,
                            host_speed=hb.speed if hb else None,
                            host_yaw_rate=hb.yaw_rate if hb else None, signer=signer)
        reporter = hb.temp_id if hb else None
        for d in found:
            self.counters[f"mbd_{d.check}"] += 1
            if self.cap is not None:
                self.cap.finding(rx_unix, t, reporter, d, bsm, data)
        if mbd.reports:
            self.counters["mbd_reports"] += len(mbd.reports)
            if self.cap is not None:
                for d in mbd.reports:
                    self.cap.report(rx_unix, t, reporter, d, bsm, data)
        if mbd.dropped in ("copy", "stale"):
            self.counters[f"mbd_{mbd.dropped}"] += 1
        elif mbd.dropped is None:
            if not mbd.quarantined(bsm.temp_id, t, signer):
                return False
            self.counters["mbd_quarantined"] += 1
            ids = mbd.ids_of(bsm.temp_id, t, signer)
            keep = []
            for m in self.pending:
                if m.temp_id in ids:
                    self.pending_rx.pop(id(m), None)
                    self.deferred.pop(id(m), None)
                else:
                    keep.append(m)
            self.pending = keep
            for tid in ids:
                if self.drop(tid):
                    self.counters["mbd_tracks_dropped"] += 1
        if self.cap is not None:
            self.cap.frame(rx_unix, "rv", data, "quarantined",
                           sender=(bsm.temp_id, bsm.msg_cnt, bsm.sec_mark),
                           why=mbd.dropped or "quarantine")
        return True

    def due(self, now: float, future_s: float) -> list[BSM]:
        """The RV messages a tick at ``now`` takes (:func:`catc.replay.split_due`), out of
        the queue; the rest stay."""
        due, self.pending = split_due(now, self.pending, future_s)
        if self.limiter is not None and self.deferred:
            due = [m for m in due if not self._withhold(m)]
        return due

    def _withhold(self, m: BSM) -> bool:
        """True when ``m`` is an urgent frame the limiter held back and still unverified:
        it is not stepped (``ondemand_withheld``, status ``withheld``); out of the queue
        (``ondemand_skipped``), or, at a worker, only its verdict will count."""
        entry = self.deferred.get(id(m))
        if entry is None or not entry.held:
            return False
        del self.deferred[id(m)]
        rx_unix, data, _, _ = self.pending_rx.pop(id(m))
        self.counters["ondemand_withheld"] += 1
        if self.queue.remove(entry.seq):
            self.counters["ondemand_skipped"] += 1
            if self.cap is not None:
                self.cap.late(rx_unix, m, "skipped", False)
        if self.cap is not None:
            self.cap.frame(rx_unix, "rv", data, "withheld", verify="held",
                           sender=(m.temp_id, m.msg_cnt, m.sec_mark))
        return True

    def received(self, messages: list[BSM]) -> list[Received]:
        """``messages`` with their receive time, octets and verdict, for the capture."""
        return [(m, *self.pending_rx.pop(id(m), (None, b"", None, None))) for m in messages]

    def unticked(self) -> list[Received]:
        """The queue emptied: messages received after the last host frame, never
        stepped."""
        left = self.received(self.pending)
        self.pending = []
        return left
