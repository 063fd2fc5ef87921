"""``obu run``: the On-Board Unit daemon, the device under test.

It receives frames over UDP or CAN (``hil.transport``: the RVs' BSMs on one channel, the
host vehicle's own state on the other), decodes J2735 with or without an IEEE 1609.2
envelope, and at every host-vehicle frame (10 Hz) steps the CA-TC
(:class:`catc.cam.ContextAwareMap` with the FCW, EEBL, BSW and LCW applications).  Its
clock is the host vehicle's (:class:`catc.cam.SecMarkClock`).

Tick rule: the step at host frame ``T`` takes every RV message received so far that was
generated at or before ``T``; newer ones wait for a later tick.  Before stepping it takes
every frame that reached the receiver before the host frame (in its queue or still in the
socket buffer: ``Receiver.waiting``, up to 50 ms), then lets the RV channel go quiet (up
to ``--collect-ms``), so frames sent just before the host's are in the tick, as a radio's
would be within one 100 ms slot.  Which tick a frame joins thus depends on the order of
the frames, not on how fast this process reads them.

Security (``--verify log|enforce --trust PKI_DIR|ROOT.oer``): every RV frame's IEEE 1609.2
envelope (inside a WSMP message or not) is verified with :class:`catc.security.Verifier`
at its receive time: signature, chain to the trusted root, psid 0x20, validity period,
generationTime freshness.  Each verdict is counted (``verify_ok``, ``verify_<reason>``)
and kept in the frame's ``obu.rx.jsonl`` record (``verdict``); ``enforce`` drops a frame
that fails (status ``rejected``), ``log`` tracks it anyway.  Host frames are not verified
(they are the host's own state, not radio traffic).

Outputs:

* warnings: a log line on stderr per event, and one JSON object per event on stdout
  (or ``--warnings FILE``);
* a status line on stderr every second: frames/s, decode errors, tracked RVs, tick time
  p99, deadline misses, warnings;
* the capture directory (append-only, flushed at every tick): ``obu.config.json``
  (settings, versions, ENU origin), ``obu.rx.jsonl`` (every frame with its receive time,
  channel, octets and what became of it; ``unticked``: received after the last host
  frame, so never stepped), ``obu.ticks.jsonl`` (one line per tick: time,
  HV state, step time, warnings), ``obu.tracks.jsonl`` (every tracked RV at every tick:
  estimate, source, age, zones now and predicted, lane), ``obu.events.jsonl`` (warning
  starts and ends), ``obu.counters.json`` (rewritten every second and at the end).

Robustness: a frame that does not decode (garbage, truncated, another message, absurd
values), an oversized datagram or a broken ISO-TP transfer is counted by reason and
dropped, with at most one log line per reason per second; a step slower than the 100 ms
tick period is counted as a deadline miss, never skipped; SIGINT/SIGTERM flush and stop;
``kill -9`` loses at most the last tick.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import signal
import sys
import time
from collections import Counter, deque
from pathlib import Path

import numpy as np

from catc.apps import SafetyApps
from catc.bsm import BSM
from catc.cam import CamConfig, ContextAwareMap, MapSnapshot, SecMarkClock
from catc.errors import DecodeError
from catc.j2735 import decode_frame, open_envelope
from catc.predict import check
from catc.replay import split_due
from hil.capture import schema
from hil.gcpolicy import GcPolicy
from obu.capture import ObuCapture
from obu.options import DEFAULTS, add_arguments
from obu.tick import STEP, TAKE, TICK_S, WAIT, TickRule

__all__ = ["DEFAULTS", "add_arguments", "run"]

class _RateLimitedLog:
    """At most one stderr line per key per second (a flood of garbage must not flood)."""

    def __init__(self) -> None:
        self.last: dict[str, float] = {}
        self.suppressed: Counter[str] = Counter()

    def __call__(self, key: str, message: str) -> None:
        now = time.monotonic()
        if now - self.last.get(key, -1e9) < 1.0:
            self.suppressed[key] += 1
            return
        extra = f" (+{self.suppressed.pop(key)} more)" if self.suppressed.get(key) else ""
        self.last[key] = now
        print(f"obu: {message}{extra}", file=sys.stderr, flush=True)


def _claims(frame: bytes) -> tuple[int, int, int | None] | None:
    """Who a rejected frame claims to be (TemporaryID, msgCnt, secMark), for the capture;
    None when it does not decode."""
    try:
        bsm = decode_frame(frame)
    except DecodeError:
        return None
    return (bsm.temp_id, bsm.msg_cnt, bsm.sec_mark)


def _verifier(args: argparse.Namespace):
    """The IEEE 1609.2 verifier of ``--verify log|enforce`` (None when off); ValueError
    (one line) for a missing or unusable trust store."""
    if args.verify in (None, "off"):
        return None
    if not args.trust:
        raise ValueError(f"--verify {args.verify} needs --trust PKI_DIR or ROOT.oer")
    from catc.security import Verifier
    from hil.pki import trust_store

    roots, cas = trust_store(args.trust)
    try:
        return Verifier(roots, certificates=cas)
    except ValueError as err:
        raise ValueError(f"--trust {args.trust}: {err}") from None


class Obu:
    """The daemon's state: the CAM, the clock, pending messages and counters."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        config = CamConfig(predictor=args.predictor, max_tracks=args.max_tracks)
        self.cam = ContextAwareMap(config, SafetyApps())
        if args.predictor == "hgp":  # its compiled kernels, before the first tick
            from catc.predict.hgp import warm_up

            warm_up()
        self.clock = SecMarkClock()
        self.gc = None  # the GcPolicy, once serve() has started everything
        self.pending: list = []  # decoded RV BSMs waiting for their tick
        self.pending_rx: dict[int, tuple[float, bytes]] = {}  # id(bsm) -> (rx unix, octets)
        self.counters: Counter[str] = Counter()
        self.log = _RateLimitedLog()
        self.step_ms: deque[float] = deque(maxlen=6000)  # the last 10 min of ticks
        self.cap = ObuCapture(Path(args.capture), args) if args.capture else None
        self.warn_out = (open(args.warnings, "a", encoding="utf-8")  # noqa: SIM115
                         if args.warnings else sys.stdout)
        self.verifier = _verifier(args)
        if self.verifier is not None:
            from catc.security import unix_to_time64

            self.to_time64 = unix_to_time64
        self.mbd = None
        if args.mbd:
            from catc.mbd import MisbehaviorDetector

            self.mbd = MisbehaviorDetector()
        self.last_host = None  # (BSM, rx unix) of the newest host frame
        self.enforce = args.verify == "enforce"
        self.rule = TickRule(args.collect_ms)
        self.last_frame = time.monotonic()
        self.web = None  # the live view's hub (obu.web.Hub) when --web is on
        self.frames_per_s = 0.0

    def frame(self, channel: str, data: bytes, rx_unix: float) -> BSM | None:
        """One received frame: decode it; the host's BSM when it is a host frame that
        decodes (it triggers a tick), else None."""
        self.counters["frames"] += 1
        self.counters[f"frames_{channel}"] += 1
        self.last_frame = time.monotonic()
        if channel == "rv":  # any datagram, decodable or not: the channel is not quiet
            self.rule.rv_frame(self.last_frame)
        verdict = None
        try:
            frame, envelope = open_envelope(data)
            if channel == "rv" and self.verifier is not None:
                verdict = self.verify(envelope, rx_unix)
                if verdict != "ok" and self.enforce:
                    self.log(verdict, f"dropped an RV frame that does not verify: {verdict}")
                    if self.cap is not None:
                        self.cap.frame(rx_unix, channel, data, "rejected",
                                       sender=_claims(frame), verdict=verdict)
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
            if self.mbd is not None and self.misbehaves(bsm, rx_unix, data):
                return None
            self.pending.append(bsm)
            self.pending_rx[id(bsm)] = (rx_unix, data, verdict)
            return None
        if bsm.sec_mark is not None:  # the host's clock (data time), for the MBD
            self.last_host = (bsm, rx_unix, self.clock(bsm.sec_mark))
        return bsm

    #: A host frame older than this (s) is no position for the range and appearance
    #: checks (catc.mbd: a stale host position gives false sudden appearances).
    HOST_FRESH_S = 0.5

    def misbehaves(self, bsm, rx_unix: float, data: bytes) -> bool:
        """Run the misbehavior checks on one RV BSM; write a report per detection
        (:meth:`obu.capture.ObuCapture.report`); True (drop it, and its track) when its
        sender is in quarantine.

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
        found = self.mbd.observe(bsm, t, hb.lat if hb else None, hb.lon if hb else None,
                                 host_heading=hb.heading if hb else None)
        for d in found:
            self.counters[f"mbd_{d.check}"] += 1
            if self.cap is not None:
                self.cap.report(rx_unix, t, hb.temp_id if hb else None, d, bsm, data)
        if not self.mbd.quarantined(bsm.temp_id, t):
            return False
        self.counters["mbd_quarantined"] += 1
        keep = []
        for m in self.pending:
            if m.temp_id == bsm.temp_id:
                self.pending_rx.pop(id(m), None)
            else:
                keep.append(m)
        self.pending = keep
        if self.cam.drop(bsm.temp_id):
            self.counters["mbd_tracks_dropped"] += 1
        if self.cap is not None:
            self.cap.frame(rx_unix, "rv", data, "quarantined",
                           sender=(bsm.temp_id, bsm.msg_cnt, bsm.sec_mark))
        return True

    def verify(self, envelope, rx_unix: float) -> str:
        """The 1609.2 verdict of one RV frame (``ok`` or a reason), counted."""
        if envelope is None:
            reason = "unsigned"
        else:
            reason = self.verifier.verify(envelope, self.to_time64(rx_unix)).reason
        self.counters[f"verify_{reason}"] += 1
        if reason != "ok":
            self.counters["verify_rejected" if self.enforce else "verify_failed"] += 1
        return reason

    def tick(self, host) -> MapSnapshot | None:
        """Step the CAM at host frame ``host`` (see the module docstring)."""
        if host.sec_mark is None or host.lat is None or host.lon is None:
            self.counters["host_incomplete"] += 1
            self.log("host", "a host frame without time or position: no tick")
            return None
        now = self.clock(host.sec_mark)
        due, self.pending = split_due(now, self.pending, self.cam.config.max_future_s)
        t0 = time.perf_counter()
        try:
            snap = self.cam.step(now, host, due)
        except ValueError as err:  # time going backwards on the host channel
            self.counters["host_rejected"] += 1
            self.log("host", f"host frame rejected: {err}")
            return None
        ms = (time.perf_counter() - t0) * 1000.0
        self.step_ms.append(ms)
        self.counters["ticks"] += 1
        if ms > TICK_S * 1000.0:
            self.counters["deadline_misses"] += 1
        decided = time.time()
        received = [(m, *self.pending_rx.pop(id(m), (None, b"", None))) for m in due]
        self._outputs(snap, host, ms, decided, received)
        if self.web is not None and (self.web.clients or self.web.polled):
            self._publish(snap, host)
        return snap

    def _publish(self, snap: MapSnapshot, host) -> None:
        """The tick's state to the live view (after the step: not in its time)."""
        from obu.web import tick_state

        c = self.counters
        ms = self.step_ms
        recent = list(ms)[-600:]  # the last minute of ticks
        panel = {"frames_per_s": round(self.frames_per_s), "decode_errors":
                 c["decode_errors"], "rejected": c["verify_rejected"] + c["mbd_quarantined"],
                 "tick_p50": round(float(np.percentile(recent, 50)), 2),
                 "tick_p99": round(float(np.percentile(recent, 99)), 2),
                 "deadline_misses": c["deadline_misses"], "tentative": self.cam.tentative}
        self.web.publish(tick_state(snap, host.sec_mark, panel))

    def _outputs(self, snap: MapSnapshot, host, ms: float, decided: float,
                 received: list) -> None:
        for e in snap.events:
            rec = schema.event(e)
            self.warn_out.write(json.dumps(rec) + "\n")
            print(f"obu: {e.app.upper()} {e.kind} RV {rec['rv']} at t={rec['t']:.1f} s",
                  file=sys.stderr, flush=True)
            self.counters[f"events_{e.app}"] += 1
            if self.cap is not None:
                self.cap.event(rec)
        self.warn_out.flush()
        self.counters["warning_ticks"] += bool(snap.warnings)
        if self.cap is None:
            return
        if not self.cap.origin_written and self.cam.frame is not None:
            f = self.cam.frame
            self.cap.write_origin([f.lat0, f.lon0, f.h0])
        self.cap.tick(snap, host.sec_mark, ms, decided, received)

    def status(self, frames_per_s: float) -> str:
        p99 = float(np.percentile(self.step_ms, 99)) if self.step_ms else 0.0
        c = self.counters
        events = sum(v for k, v in c.items() if k.startswith("events_"))
        return (f"obu: {frames_per_s:7.0f} frames/s  decode errors {c['decode_errors']}  "
                f"tracked {len(self.cam)}  tick p99 {p99:.1f} ms  deadline misses "
                f"{c['deadline_misses']}  warning events {events}")

    def all_counters(self, transport_stats: dict) -> dict:
        out = dict(self.counters)
        out["pending"] = len(self.pending)  # received, not yet due at a tick
        out["cam_tentative"] = self.cam.tentative
        out.update({f"cam_{k}": v for k, v in self.cam.counters.items()})
        out.update({f"transport_{k}": v for k, v in transport_stats.items()})
        if self.gc is not None:
            out.update(self.gc.counters())
        if self.step_ms:
            out["tick_ms_p50"] = round(float(np.percentile(self.step_ms, 50)), 3)
            out["tick_ms_p99"] = round(float(np.percentile(self.step_ms, 99)), 3)
            out["tick_ms_max"] = round(float(max(self.step_ms)), 3)
        return out

    def close(self) -> None:
        if self.cap is not None:
            # received, never stepped (no host frame came after them): recorded all the
            # same, so that the capture has every frame the OBU received
            for m in self.pending:
                received = (m, *self.pending_rx.pop(id(m), (None, b"", None)))
                self.cap.message(received, "unticked")
            self.pending = []
            self.cap.close()
        if self.warn_out is not sys.stdout:
            self.warn_out.close()


async def _open_receiver(args: argparse.Namespace):
    from hil.transport import open_receiver

    if args.transport == "udp":
        return await open_receiver("udp", listen=args.listen, host_listen=args.host_listen)
    return await open_receiver("can", interface=args.can_interface, channel=args.can_channel,
                               fd=bool(args.can_fd))


async def serve(args: argparse.Namespace) -> dict:
    """Receive and step until stopped; returns the final counters."""
    obu = Obu(args)
    rx = await _open_receiver(args)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    inbox: deque[tuple[str, bytes, float]] = deque()  # frames in arrival order
    arrived = asyncio.Event()

    async def pump() -> None:
        while True:
            r = await rx.recv()
            inbox.append((r.channel, r.data, time.time()))
            arrived.set()

    pumping = asyncio.create_task(pump())
    runner = None
    if args.web:
        from obu.web import Hub, make_app, start

        obu.web = Hub()
        runner = await start(make_app(obu.web), *args.web)
        host_, port_ = args.web
        shown = f"[{host_}]" if ":" in host_ else host_
        print(f"obu: live view at http://{shown}:{port_}/", file=sys.stderr, flush=True)
    obu.gc = GcPolicy()  # start-up done: freeze it; collections after ticks only
    started = time.monotonic()
    last_status, frames_at_status = started, 0
    try:
        while not stop.is_set():
            if args.duration is not None and time.monotonic() - started > args.duration:
                break
            if args.idle_exit is not None and obu.counters["frames"] \
                    and time.monotonic() - obu.last_frame > args.idle_exit:
                break
            if not inbox:
                arrived.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(arrived.wait(), 0.2)
            while inbox:
                host = obu.frame(*inbox.popleft())
                if host is None:
                    continue
                # the tick rule (obu.tick): take the frames that reached the receiver
                # before this host frame, let the RV channel go quiet, then step
                obu.rule.host_frame(time.monotonic())
                action = WAIT
                while action is not STEP:
                    if action is TAKE:
                        obu.frame(*inbox.popleft())
                    else:
                        await asyncio.sleep(0)
                    head = inbox[0][0] if inbox else None
                    action = obu.rule.next(time.monotonic(), head,
                                           head is None and rx.waiting())
                obu.tick(host)
                obu.gc.after_tick()
                break
            now = time.monotonic()
            if now - last_status >= 1.0:
                obu.gc.idle()  # no ticks for a while: still collect (hil.gcpolicy)
                fps = (obu.counters["frames"] - frames_at_status) / (now - last_status)
                obu.frames_per_s = fps
                last_status, frames_at_status = now, obu.counters["frames"]
                if args.progress:
                    print(obu.status(fps), file=sys.stderr, flush=True)
                if obu.cap is not None:
                    obu.cap.write_counters(obu.all_counters(rx.stats))
    finally:
        obu.gc.restore()  # serve() may run inside another program (the tests)
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        pumping.cancel()
        if runner is not None:
            await runner.cleanup()
        counters = obu.all_counters(rx.stats)
        await rx.aclose()
        if obu.cap is not None:
            obu.cap.write_counters(counters)
            obu.cap.flush()
        obu.close()
    return counters


#: glibc's mallopt parameter M_MMAP_THRESHOLD.
_M_MMAP_THRESHOLD = -3


def fix_mmap_threshold(size: int = 128 * 1024) -> bool:
    """Fix glibc's mmap threshold (True when set; False off glibc).  asyncio reads every
    datagram into a 256 kB buffer and shrinks it to the datagram's size; with glibc's
    dynamic threshold those buffers soon come from the heap, and a flood of datagrams of
    every size fragments it: the OBU's RSS crept up by ~0.65 MB/min under
    bench/obu_flood.py (0.09 MB/min without the flood).  A fixed threshold keeps them
    mmapped, returned to the system when freed."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name or not sys.platform.startswith("linux"):
        return False
    try:
        return bool(ctypes.CDLL(name).mallopt(_M_MMAP_THRESHOLD, size))
    except (OSError, AttributeError):
        return False


def run(args: argparse.Namespace) -> int:
    """``obu run`` after flags and config are merged; the exit status."""
    from hil.transport import TransportError

    fix_mmap_threshold()
    if args.max_tracks is not None and args.max_tracks < 1:
        print("obu run: --max-tracks must be >= 1", file=sys.stderr)
        return 2
    try:
        check(args.predictor)
        _verifier(args)  # the trust store, checked before anything starts
    except ValueError as err:  # a neural predictor without PyTorch or its weights, a bad
        # --trust (hil.pki.PkiError)
        print(f"obu run: {err}", file=sys.stderr)
        return 2
    try:
        counters = asyncio.run(serve(args))
    except TransportError as err:
        print(f"obu run: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # the warnings file or capture directory
        print(f"obu run: {err}", file=sys.stderr)
        return 2
    print(json.dumps({"obu": counters}), file=sys.stderr)
    return 0
