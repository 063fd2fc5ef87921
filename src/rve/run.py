"""``rve run``: the Remote Vehicle Emulator daemon.

It loads a mobility log, plans the replay through the channel model (``catc.replay.plan``:
rate, loss, bursts, distance, latency, all seeded), then sends every frame at its
deadline in real time (``hil.pacing``, absolute deadlines, ``--speed`` factor or
``--asap``) over UDP or CAN (``hil.transport``): the RVs' BSMs on one channel, the host
vehicle's own state on another with no loss.  The capture directory receives, append-only
and flushed at every host tick:

* ``rve.config.json``: the run's settings, versions and vehicle ids;
* ``rve.truth.jsonl``: the true state of every vehicle at every 10 Hz sample;
* ``rve.schedule.jsonl``: every scheduled message with its channel decision (dropped,
  cause, delay) and, when sent, the wall-clock send time and its lateness;
* ``rve.frames.pcapng`` (UDP, with IP/UDP headers; Wireshark opens it) or
  ``rve.frames.asc`` and ``rve.frames.log`` (every raw CAN frame, in python-can's ASC and
  in can-utils' candump log format, which ``canplayer`` replays onto a bus).

On the wire (``--framing``): the bare UPER MessageFrame (default), an IEEE 1609.2
``Ieee1609Dot2Data`` (``1609``; unsecured, or with ``--sign PKI_DIR`` the RVs' BSMs as
SignedData, see :class:`Signer`), or that inside an IEEE 1609.3 WSMP message (``wsmp``;
the pcapng capture then holds Ethernet frames of ethertype 0x88DC, as over the air).

Errors: a bad dataset, flag or config file prints one line and exits 2, and so does an
unreachable address or bus or a capture directory that cannot be made or written.  A
capture file that cannot be written during the replay (a full disk) ends it with one line
naming the file and exit status 1; every file keeps what was written before, and
``rve.end.json`` names the error.  SIGINT and SIGTERM stop the replay, flush and exit 0.

``--host-bus`` (:mod:`rve.hostbus`): the host vehicle's own CAN bus (its frames encoded
through a vehicle profile's DBC, each message at its rate) and a GNSS receiver's NMEA
0183 at 10 Hz (seeded noise, latency, losses, outages), made from the host's trajectory
and sent beside the RVs' frames on the same clock.  The host's state then does NOT go
out as a BSM on the private host channel.  The capture gets ``rve.hostbus.log`` and
``rve.gnss.jsonl`` too.
"""


from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import signal
import sys
import time
from pathlib import Path
from typing import Any

from catc.channel import ChannelConfig
from catc.replay import Plan, plan, temp_id
from hil.capture import schema
from hil.datasets import load_table
from hil.errors import WriteError, describe
from hil.pacing import Pacer
from rve.attacking import Attacking
from rve.capture import Capture
from rve.framing import encode_event, framing_of
from rve.hostbus import HostBus, HostBusPlan, ReplayClock, prepare
from rve.options import DEFAULTS, add_arguments
from rve.progress import Progress
from rve.signahead import sign_ahead
from rve.signing import Signer, make_signer

__all__ = ["DEFAULTS", "add_arguments", "replay", "run"]


async def _open_sender(args: argparse.Namespace, on_frame):
    from hil.transport import open_sender

    if args.transport == "udp":
        return await open_sender("udp", to=args.to, host_to=args.host_to)
    return await open_sender("can", interface=args.can_interface, channel=args.can_channel,
                             fd=bool(args.can_fd), on_frame=on_frame)


async def _finish_host(task: asyncio.Task, stop: asyncio.Event, clock: ReplayClock) -> None:
    """Let the host bus send the rest of what is due by the replay's end (with --asap: at
    once), unless the replay was stopped; raise what ended it."""
    if not stop.is_set():
        clock.advance(math.inf)
        waiter = asyncio.ensure_future(stop.wait())
        await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
        waiter.cancel()
    if not task.done():
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    elif not task.cancelled() and task.exception() is not None:
        raise task.exception()


async def replay(args: argparse.Namespace, the_plan: Plan,
                 lateness: list[float] | None = None,
                 signer: Signer | None = None,
                 host_plan: HostBusPlan | None = None) -> dict[str, int]:
    """Send the plan in real time (or as fast as possible); returns the counters.
    ``lateness`` collects every sent frame's send time minus its deadline (s); ``signer``
    signs the RVs' frames (made from ``args.sign`` when not given); with ``--host-bus``
    ``host_plan`` is what the host bus sends (made from ``args`` when not given)."""
    host_bus = bool(getattr(args, "host_bus", False))
    if host_bus and host_plan is None:
        host_plan = prepare(args, the_plan)
    framing = framing_of(args)
    signer = signer or make_signer(args, the_plan)
    attacking = Attacking(args, the_plan, signer, framing) if args.attack else None
    attacks = attacking.attacks if attacking else None
    ahead = sign_ahead(args, the_plan, signer, framing, host_bus)
    cap = Capture(Path(args.capture), the_plan, args) if args.capture else None
    on_frame = cap.canlog.on_message_received if cap is not None and cap.canlog else None
    hostbus = None
    try:
        sender = await _open_sender(args, on_frame)
        if host_bus:
            hostbus = HostBus(args, host_plan, Path(args.capture) if cap else None)
            try:
                hostbus.open()
            except BaseException:
                await sender.aclose()
                raise
            if cap is not None:
                cap.attach(hostbus.files())
    except BaseException as err:
        if cap is not None:
            with contextlib.suppress(OSError):  # err, not a capture file, ends the run
                cap.end(*schema.failed(err))
        raise
    try:  # the first lookahead window signed before the clock starts
        start = ahead.prime() if ahead is not None else None
    except BaseException as err:
        ahead.close()
        await sender.aclose()
        if hostbus is not None:
            hostbus.close()
        if cap is not None:
            with contextlib.suppress(OSError):
                cap.end(*schema.failed(err))
        raise
    stop = asyncio.Event()
    stopped_by: list[str] = []  # the signal that stopped the replay
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, lambda s=sig: (stopped_by.append(s.name), stop.set()))
    ending = ("error", "")
    raised = False  # an exception ends the run: it is the one to raise
    events = the_plan.events
    tids = [temp_id(v) for v in the_plan.vehicles]
    t0 = float(events["time"][0]) if len(events) else 0.0
    pacer = Pacer(t0, None if args.asap else args.speed, start=start)
    clock = ReplayClock(pacer) if hostbus is not None else None
    host_task = None
    if hostbus is not None:
        host_task = asyncio.create_task(hostbus.run(clock))
        host_task.add_done_callback(
            lambda task: stop.set() if not task.cancelled() and task.exception() else None)
    progress = Progress(args.progress, t0, float(events["time"][-1]) if len(events) else t0)
    if cap is not None:  # where each channel's datagrams come from: the sockets' own ports
        src = dict(getattr(sender, "local", {}))
        src.setdefault("rv", ("127.0.0.1", 0))
        src.setdefault("host", src["rv"])
        cap.sources(src)
    counts = {"sent": 0, "dropped": 0, "host": 0, "late_ms_max": 0.0, "late_over_1s": 0}
    times = events["time"].tolist()
    hosts = events["host"].tolist()  # (a record's field costs ~0.3 us: 1,000 per burst)
    try:
        i, n, tick = 0, len(events), -1
        while i < n and not stop.is_set():
            due = times[i]
            j = i
            while j < n and times[j] == due:
                j += 1
            batch = events[i:j]
            tick += 1
            # Encode before the deadline, send at it, write the capture after the sends.
            if ahead is None:
                gen_unix = time.time() + max(0.0, pacer.deadline(due) - pacer.clock())
                encoded = [(None, None) if host_bus and ev["host"] else
                           encode_event(ev, the_plan, framing, signer, gen_unix, attacks)
                           for ev in batch]
                frames = [frame for frame, _ in encoded]
                extra = attacking.frames(batch, frames, gen_unix) if attacking else []
            else:  # signed by the workers: this tick's frames are taken at its deadline
                ahead.fill(due)
                extra = []
            if clock is not None:
                clock.advance(due)
            await pacer.wait(due)
            if ahead is not None:
                encoded = await ahead.take(tick)
                frames = [frame for frame, _ in encoded]
            deadline = pacer.deadline(due)

            def stamp() -> tuple[float, float]:
                return (time.time(), 0.0 if args.asap
                        else max(0.0, pacer.clock() - deadline))  # noqa: B023

            sent_at: list = [None] * len(frames)
            extra_at: list = []
            burst: list[int] = []  # the RV frames due before the next host frame
            for k, (host, frame) in enumerate(zip(hosts[i:j], frames, strict=True)):
                if not host:
                    if frame is not None:
                        burst.append(k)
                    continue
                await _send_burst(sender, frames, burst, sent_at, stamp)
                if len(extra_at) < len(extra):  # attackers before the host
                    for attack_frame, _ in extra:
                        await sender.send(attack_frame)
                        extra_at.append(stamp())
                if frame is not None:
                    await sender.send_host(frame)
                    sent_at[k] = stamp()
            await _send_burst(sender, frames, burst, sent_at, stamp)
            for attack_frame, _ in extra[len(extra_at):]:
                await sender.send(attack_frame)
                extra_at.append(stamp())
            for ev, (frame, label), when in zip(batch, encoded, sent_at, strict=True):
                if host_bus and ev["host"]:  # not sent: the host bus carries the host
                    continue
                _account(ev, frame, when, counts, lateness)
                if cap is not None:
                    v = int(ev["vehicle"])
                    cap.write_event(ev, the_plan.vehicles[v], tids[v], frame, when, label)
            if cap is not None:
                for (attack_frame, record), when in zip(extra, extra_at, strict=True):
                    cap.write_attack(record, attack_frame, when)
            progress.update(due, counts["sent"], counts["dropped"],
                            max((w[1] for w in sent_at if w is not None), default=0.0))
            if cap is not None and bool(events["host"][j - 1]):
                cap.write_truth(the_plan, due)
                cap.flush()
            i = j
        if host_task is not None:
            await _finish_host(host_task, stop, clock)
        ending = ("signal", stopped_by[0]) if stopped_by else ("clean", "replayed")
    except BaseException as err:
        ending, raised = schema.failed(err), True
        raise
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        if host_task is not None and not host_task.done():
            host_task.cancel()
            with contextlib.suppress(BaseException):
                await host_task
        if hostbus is not None:
            hostbus.close()
            counts.update(hostbus.counts)
        if ahead is not None:
            ahead.close()
            counts.update(ahead.counts)
        if signer is not None:
            counts.update(signer.counts)
        await sender.aclose()
        last = float(events["time"][min(i, len(events) - 1)]) if len(events) else 0.0
        progress.update(last, counts["sent"], counts["dropped"], 0.0, final=True)
        if cap is not None:
            try:  # every file flushed and closed, even after a failed write
                cap.end(*ending, sent=counts["sent"], dropped=counts["dropped"],
                        host_frames=counts["host"],
                        **{k: counts[k] for k in _LATE_COUNTS},
                        **(dict(hostbus.counts) if hostbus is not None else {}),
                        **{k: counts[k] for k in _SIGN_COUNTS if k in counts})
            except OSError:
                if not raised:
                    raise
    counts["interrupted"] = int(stop.is_set())
    if attacking is not None:
        counts.update(attacking.counts)
    return counts


#: how late the RV frames left (the largest, ms; how many over 1 s): a replay that cannot
#: keep its schedule says so, as a verifying OBU rejects frames over 2 s old as stale
_LATE_COUNTS = ("late_ms_max", "late_over_1s")
#: the signing counters of the summary and rve.end.json (rve.signing, rve.signahead)
_SIGN_COUNTS = ("signed", "with_certificate", "sign_ahead_batches", "sign_ahead_waits",
                "sign_ahead_wait_ms_max")


async def _send_burst(sender: Any, frames: list[bytes | None], burst: list[int],
                      sent_at: list, stamp: Any) -> None:
    """Send the RV frames ``burst`` indexes back to back, each one's ``stamp()`` into
    ``sent_at``; empties ``burst``."""
    if burst:
        stamps = await sender.send_many([frames[k] for k in burst], stamp)
        for k, when in zip(burst, stamps, strict=True):
            sent_at[k] = when
        burst.clear()


def _account(ev: Any, frame: bytes | None, when: tuple[float, float] | None,
             counts: dict[str, float], lateness: list[float] | None) -> None:
    """The counters and lateness of one event after its batch was sent."""
    host = bool(ev["host"])
    if frame is None:
        counts["dropped"] += 1
    else:
        counts["host" if host else "sent"] += 1
        if not host:
            late = when[1]
            if late * 1000.0 > counts["late_ms_max"]:
                counts["late_ms_max"] = round(late * 1000.0, 3)
            counts["late_over_1s"] += late > 1.0
            if lateness is not None:
                lateness.append(late)


def run(args: argparse.Namespace) -> int:
    """``rve run`` after flags and config are merged; the exit status."""
    from hil.transport import TransportError

    try:
        table = load_table(args.dataset, args.trip)
        if args.idm_host:
            from catc.hostsim import with_synthetic_host

            table = with_synthetic_host(table, args.idm_host, vehicle_id="idm-host")
            args.host = "idm-host"
        config = ChannelConfig(per=args.per / 100.0, burst=args.burst, rate_hz=args.rate,
                               latency_s=args.latency / 1000.0,
                               jitter_s=args.jitter / 1000.0, distance=bool(args.distance))
        the_plan = plan(table, config, args.seed, args.host, args.duration)
        if args.speed is not None and not args.speed > 0:
            raise ValueError(f"--speed must be > 0, got {args.speed}")
        framing_of(args)
        signer = make_signer(args, the_plan)
        if args.attack:
            Attacking(args, the_plan, signer, framing_of(args))  # one line if it cannot be
        host_plan = prepare(args, the_plan) if args.host_bus else None
    except ValueError as err:  # hil.pki.PkiError, hil.vehicle.ProfileError included
        print(f"rve run: {err}", file=sys.stderr)
        return 2
    try:
        counts = asyncio.run(replay(args, the_plan, signer=signer, host_plan=host_plan))
    except WriteError as err:  # a capture file, during the run
        print(f"rve run: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # the capture directory
        print(f"rve run: {describe(err)}", file=sys.stderr)
        return 2
    except TransportError as err:
        print(f"rve run: {err}", file=sys.stderr)
        return 2
    if counts["late_over_1s"]:
        print(f"rve run: {counts['late_over_1s']} RV frames left more than 1 s after their "
              f"deadline (the latest {counts['late_ms_max'] / 1000.0:.1f} s): this machine "
              "did not keep the schedule, and a verifying OBU rejects frames over 2 s old "
              "as stale", file=sys.stderr)
    print(json.dumps({"sent": counts["sent"], "dropped": counts["dropped"],
                      "host_frames": counts["host"], "interrupted": bool(counts["interrupted"]),
                      "vehicles": len(the_plan.vehicles) - 1, "host": the_plan.host_id,
                      **{k: counts[k] for k in (*_LATE_COUNTS, *_SIGN_COUNTS,
                                                 "attack_frames", "host_can_frames",
                                                 "host_can_errors", "nmea_epochs",
                                                 "gnss_dropped", "nmea_full")
                         if k in counts}}),
          flush=True)
    return 0
