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
and kept in the frame's ``obu.rx.jsonl.gz`` record (``verdict``); ``enforce`` drops a frame
that fails (status ``rejected``), ``log`` tracks it anyway.  Host frames are not verified
(they are the host's own state, not radio traffic).  ``--verify-policy on-demand`` (the
default under enforce; :mod:`obu.frames`): the cheap checks on arrival, the ECDSA at once
for the frames that could warn or start a track, the rest from a queue by threat, in idle
time (slices of :data:`IDLE_SLICE_S`), before each step (:mod:`obu.daemon`) and in
``--verify-workers`` processes (:mod:`obu.ecdsa_worker`); a frame
that its tick reaches unverified is stepped as such and can raise no warning
(``obu.verify.jsonl`` says what became of it).  ``all``: every frame on arrival.

Outputs:

* warnings: a log line on stderr per event, and one JSON object per event on stdout
  (or ``--warnings FILE``);
* a status line on stderr every second: frames/s, decode errors, tracked RVs, tick time
  p99, the lag from a frame's arrival (the kernel's stamp) to its tick's decision
  (p50/p99), the receive queue (frames, and kB in the socket buffers), deadline misses
  (a step over 100 ms, or a tick decided over 100 ms after its host frame arrived),
  warnings;
* the capture directory (append-only, flushed at every tick): ``obu.config.json``
  (settings, versions, ENU origin), ``obu.rx.jsonl.gz`` (every frame with its receive
  time, channel, octets and what became of it; ``unticked``: received after the last host
  frame, so never stepped), ``obu.ticks.jsonl`` (one line per tick: time,
  HV state, step time, warnings), ``obu.tracks.bin`` (every tracked RV at every tick:
  estimate, source, age, zones now and predicted, lane; compact, ``captures tracks``
  prints it), ``obu.events.jsonl`` (warning starts and ends), ``obu.counters.json``
  (rewritten every second and at the end); ``--capture-max-mb`` caps them
  (:mod:`obu.capture`).

``--host-source vehicle`` (:mod:`obu.vehicle`): the host's frames are not received but
made from the car's own CAN bus and a GNSS receiver every 100 ms of GNSS time, and go
through the same path as received host frames; frames on the private host channel are
then counted (``host_channel_ignored``) and dropped.

The host channel defends itself (:class:`obu.host.HostGate`): only the host's id
(``--host-id``, or the first heard) is believed, and only frames its own motion explains:
no clock jump, no position or speed it cannot reach.  The rest are counted
(``host_<reason>``) and start no tick, so a flood at the host port changes nothing.

Robustness: a frame that does not decode (garbage, truncated, another message, absurd
values), an oversized datagram or a broken ISO-TP transfer is counted by reason and
dropped, with at most one log line per reason per second; a step slower than the 100 ms
tick period is counted as a deadline miss, never skipped; SIGINT/SIGTERM flush and stop;
``kill -9`` loses at most the last tick.  A capture or ``--warnings`` file that cannot be
written (a full disk) ends the run with one line naming it and exit status 1, every other
file flushed and closed, and ``obu.end.json`` naming the error; a capture directory that
cannot be made or written at the start is one line and exit status 2.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import signal
import sys
import time
from collections import deque

from catc.predict import check
from hil.capture import schema
from hil.errors import WriteError, describe
from hil.gcpolicy import GcPolicy
from hil.transport import Receiver, TransportError, open_receiver
from obu.daemon import Obu
from obu.frames import verifier
from obu.options import DEFAULTS, add_arguments
from obu.tick import STEP, TAKE, WAIT

__all__ = ["DEFAULTS", "IDLE_SLICE_S", "add_arguments", "fix_mmap_threshold", "run", "serve"]

#: Verify on demand: with no frame to handle, queued frames are verified in slices of
#: this long (s), the sockets read between them.
IDLE_SLICE_S = 0.002


async def _open_receiver(args: argparse.Namespace) -> Receiver:
    if args.transport == "udp":
        return await open_receiver("udp", listen=args.listen, host_listen=args.host_listen)
    return await open_receiver("can", interface=args.can_interface, channel=args.can_channel,
                               fd=bool(args.can_fd))


def _where(args: argparse.Namespace, vehicle=None) -> str:
    if args.transport == "udp":
        where = "udp " + ", ".join(f"{h}:{p}" for h, p in (args.listen, args.host_listen))
    else:
        where = f"can {args.can_interface} {args.can_channel}"
    return where if vehicle is None else f"{where}; host: {vehicle.where()}"


async def serve(args: argparse.Namespace) -> dict:
    """Receive and step until stopped; returns the final counters."""
    obu = Obu(args)
    inbox: deque[tuple[str, bytes, float]] = deque()  # frames in arrival order
    arrived = asyncio.Event()

    def push(channel: str, data: bytes, arrival: float) -> None:
        inbox.append((channel, data, arrival))
        arrived.set()

    rx = None
    try:
        # the car's side first: once the RV ports are bound (what a launcher may wait
        # for) its bus is open too, and no frame of the car is sent to nobody
        if getattr(args, "host_source", "channel") == "vehicle":
            from obu.vehicle import VehicleHost

            obu.vehicle = VehicleHost(args, push, obu.log, obu.cap)
            await obu.vehicle.start()
        rx = await _open_receiver(args)
    except BaseException as err:
        if rx is not None:
            await rx.aclose()
        if obu.vehicle is not None:
            await obu.vehicle.aclose()
        with contextlib.suppress(OSError):  # err, not a capture file, ends the run
            obu.close(*schema.failed(err))
        raise
    vehicle = obu.vehicle
    stop = asyncio.Event()
    stopped_by: list[str] = []  # the signal that stopped the run
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, lambda s=sig: (stopped_by.append(s.name), stop.set()))
    ending = ("error", "")  # until the loop ends without an exception
    raised = False  # an exception ends the run: it is the one to raise
    pending = None  # a believed host frame that ended the last tick's collection

    async def pump() -> None:
        while True:
            r = await rx.recv()
            if vehicle is not None and r.channel == "host":  # the host is the car's
                obu.counters["host_channel_ignored"] += 1
                obu.log("host_channel_ignored", "a frame on the private host channel "
                        "ignored (--host-source vehicle)")
                continue
            push(r.channel, r.data, r.arrival)

    pumping = asyncio.create_task(pump())
    queue = obu.frames.queue  # verify on demand's (None otherwise)
    runner = None
    if args.web:
        from obu.web import Hub, make_app, start

        obu.web = Hub()
        runner = await start(make_app(obu.web), *args.web)
        host_, port_ = args.web
        shown = f"[{host_}]" if ":" in host_ else host_
        print(f"obu: live view at http://{shown}:{port_}/", file=sys.stderr, flush=True)
    obu.gc = GcPolicy()  # start-up done: freeze it; collections after ticks only
    # receiving from here on (frames already wait in the sockets' or the bus's queue):
    # what a launcher waits for before it sends, whatever the transport or namespace
    print(f"obu: ready ({_where(args, vehicle)})", file=sys.stderr, flush=True)
    started = time.monotonic()
    last_status, frames_at_status = started, 0
    done = "stopped"  # why the loop ended, when no signal did
    try:
        while not stop.is_set():
            if args.duration is not None and time.monotonic() - started > args.duration:
                done = "duration"
                break
            # idle: no frame for a while; with the car as the host (whose own frames are
            # made here), no RV frame and nothing from the car
            last = obu.last_frame if vehicle is None \
                else max(obu.last_rv, vehicle.last_input)
            if args.idle_exit is not None and obu.counters["frames"] \
                    and time.monotonic() - last > args.idle_exit:
                done = "idle"
                break
            if queue is not None:  # verify on demand: the workers' answers, and more work
                obu.frames.pump()
            if not inbox and pending is None:
                if queue is not None and len(queue):  # verify on demand: idle time
                    obu.counters["ondemand_idle"] += obu.frames.work(
                        time.monotonic() + IDLE_SLICE_S, time.monotonic)
                    await asyncio.sleep(0)  # read the sockets between slices
                else:  # (batches at the workers: back soon for their answers)
                    arrived.clear()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(arrived.wait(), 0.005 if queue is not None
                                               and obu.frames.queued() else 0.2)
            while inbox or pending is not None:
                if pending is None:
                    host = obu.frame(*inbox.popleft())
                    if host is None:  # an RV frame, or a host frame not believed
                        continue
                else:
                    host, pending = pending, None
                # the tick rule (obu.tick): take the frames that reached the receiver
                # before this host frame, let the RV channel go quiet, then step
                obu.begin(host)
                action = WAIT
                while action is not STEP:
                    if action is TAKE:
                        pending = obu.frame(*inbox.popleft())
                        if pending is not None:  # the next believed host frame
                            action = obu.rule.next_host()
                            continue
                    else:
                        await asyncio.sleep(0)
                    head = inbox[0][0] if inbox else None
                    action = obu.rule.next(time.monotonic(), head,
                                           head is None and rx.waiting("rv"))
                obu.tick(host)
                obu.gc.after_tick()
                break
            now = time.monotonic()
            if now - last_status >= 1.0:
                obu.gc.idle()  # no ticks for a while: still collect (hil.gcpolicy)
                fps = (obu.counters["frames"] - frames_at_status) / (now - last_status)
                obu.status.frames_per_s = fps
                backlog = rx.backlog()
                backlog["queued"] += len(inbox)
                obu.status.backlog = backlog
                last_status, frames_at_status = now, obu.counters["frames"]
                if args.progress:
                    print(obu.status.line(fps, len(obu.cam)), file=sys.stderr, flush=True)
                obu.status.lag_recent.clear()
                if obu.cap is not None:
                    obu.cap.write_counters(obu.all_counters(rx.stats))
        ending = ("signal", stopped_by[0]) if stopped_by else ("clean", done)
    except BaseException as err:
        ending, raised = schema.failed(err), True
        raise
    finally:
        obu.gc.restore()  # serve() may run inside another program (the tests)
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        pumping.cancel()
        if vehicle is not None:
            await vehicle.aclose()
        if runner is not None:
            await runner.cleanup()
        backlog = rx.backlog()
        backlog["queued"] += len(inbox)
        obu.status.backlog = backlog
        counters = obu.all_counters(rx.stats)
        await rx.aclose()
        try:  # every file flushed and closed, even after a failed write
            obu.close(*ending, counters=counters)
        except OSError:
            if not raised:
                raise
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


def _check_vehicle(args: argparse.Namespace) -> None:
    """``--host-source vehicle``: its GNSS source given, its profile and DBC readable
    (ValueError, one line: :class:`hil.vehicle.ProfileError`), before anything starts."""
    if getattr(args, "host_source", "channel") != "vehicle":
        return
    if args.gnss is None:
        raise ValueError("--host-source vehicle needs --gnss SPEC (udp:HOST:PORT, "
                         "serial:PATH[@BAUD] or gpsd[:HOST[:PORT]])")
    from pathlib import Path

    from hil.vehicle import load_profile

    load_profile(args.vehicle, Path(args.dbc) if args.dbc else None)


def run(args: argparse.Namespace) -> int:
    """``obu run`` after flags and config are merged; the exit status."""
    fix_mmap_threshold()
    if args.max_tracks is not None and args.max_tracks < 1:
        print("obu run: --max-tracks must be >= 1", file=sys.stderr)
        return 2
    if getattr(args, "verify_queue", 1) < 1:
        print("obu run: --verify-queue must be >= 1", file=sys.stderr)
        return 2
    if getattr(args, "verify_workers", 0) < 0:
        print("obu run: --verify-workers must be >= 0", file=sys.stderr)
        return 2
    try:
        check(args.predictor)
        verifier(args)  # the trust store, checked before anything starts
        _check_vehicle(args)
    except ValueError as err:  # a neural predictor without PyTorch or its weights, a bad
        # --trust (hil.pki.PkiError)
        print(f"obu run: {err}", file=sys.stderr)
        return 2
    try:
        counters = asyncio.run(serve(args))
    except TransportError as err:
        print(f"obu run: {err}", file=sys.stderr)
        return 2
    except WriteError as err:  # a capture file or the warnings file, during the run
        print(f"obu run: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # the warnings file or capture directory, at the start
        print(f"obu run: {describe(err)}", file=sys.stderr)
        return 2
    print(json.dumps({"obu": counters}), file=sys.stderr)
    return 0
