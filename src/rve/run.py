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
unreachable address or bus.  SIGINT and SIGTERM stop the replay, flush and exit 0.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import signal
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

from catc.channel import CAUSES, ChannelConfig
from catc.j2735 import encode_frame
from catc.j2735.ieee1609 import ETHERTYPE_WSMP
from catc.replay import Plan, plan, temp_id
from hil.capture import JsonLines, PcapngWriter, can_log, ethernet, udp_packet, versions
from hil.datasets import load_table
from hil.pacing import Pacer
from rve.framing import encode_event, framing_of, wrap
from rve.options import DEFAULTS, add_arguments
from rve.signing import Signer, make_signer

__all__ = ["DEFAULTS", "add_arguments", "replay", "run"]

def _can_channel(args: argparse.Namespace) -> str:
    """The bus channel the CAN frames go out on, as the candump log names it."""
    if args.can_channel:
        return str(args.can_channel)
    from hil.transport.can import DEFAULT_CHANNELS

    return DEFAULT_CHANNELS.get(args.can_interface, "can0")


class _Capture:
    """The RVE's capture files (module docstring)."""

    def __init__(self, directory: Path, the_plan: Plan, args: argparse.Namespace) -> None:
        self.dir = directory
        directory.mkdir(parents=True, exist_ok=True)
        self.schedule = JsonLines(directory / "rve.schedule.jsonl")
        self.truth = JsonLines(directory / "rve.truth.jsonl")
        self.wsmp = framing_of(args) == "wsmp"  # the pcapng gets Ethernet/0x88DC frames
        self.pcap = PcapngWriter(directory / "rve.frames.pcapng") \
            if args.transport == "udp" else None
        self.canlog = can_log(directory / "rve.frames", _can_channel(args)) \
            if args.transport == "can" else None
        table = the_plan.table
        config = {
            "settings": {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in vars(args).items() if k not in ("func",)},
            "versions": versions(),
            "dataset": {"name": table.name, "kind": table.kind, "origin": table.origin},
            "host": the_plan.host_id,
            "vehicles": {v: f"{temp_id(v):08X}" for v in the_plan.vehicles},
            "channel": dataclasses.asdict(the_plan.config),
            "seed": the_plan.seed,
            "started_unix": time.time(),
        }
        with open(directory / "rve.config.json", "w", encoding="utf-8") as f:
            json.dump(config, f, indent=1, default=str)
        self._truth_pos = {v: 0 for v in the_plan.vehicles}

    def write_truth(self, the_plan: Plan, up_to: float) -> None:
        """Truth rows of every vehicle for samples generated at or before ``up_to``."""
        for v in the_plan.vehicles:
            tr = the_plan.table.tracks[v]
            lo = self._truth_pos[v]
            hi = int(np.searchsorted(tr.t, up_to + 1e-9, side="right"))
            for i in range(lo, hi):
                self.truth.write({
                    "vehicle": v, "id": f"{temp_id(v):08X}", "index": i, "t": float(tr.t[i]),
                    "lat": float(tr.lat[i]), "lon": float(tr.lon[i]), "x": float(tr.x[i]),
                    "y": float(tr.y[i]), "speed": float(tr.speed[i]),
                    "heading": float(tr.heading[i]), "accel": float(tr.accel[i]),
                    "yaw_rate": float(tr.yaw_rate[i]), "host": v == the_plan.host_id})
            self._truth_pos[v] = hi

    def flush(self) -> None:
        self.schedule.flush()
        self.truth.flush()
        if self.pcap is not None:
            self.pcap.flush()
        if self.canlog is not None:
            self.canlog.flush()

    def close(self) -> None:
        self.schedule.close()
        self.truth.close()
        if self.pcap is not None:
            self.pcap.close()
        if self.canlog is not None:
            self.canlog.stop()


class _Progress:
    """A status line on stderr every second: dataset time, sent, dropped, lateness."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.last = time.monotonic()
        self.late: deque[float] = deque(maxlen=5000)

    def update(self, t: float, t0: float, sent: int, dropped: int, late_s: float,
               final: bool = False) -> None:
        self.late.append(late_s)
        now = time.monotonic()
        if not self.enabled or (now - self.last < 1.0 and not final):
            return
        self.last = now
        p99 = 1000 * float(np.percentile(self.late, 99)) if self.late else 0.0
        line = (f"rve: t={t - t0:8.1f} s  sent {sent}  dropped {dropped}  "
                f"late p99 {p99:.2f} ms")
        sys.stderr.write(("\r" + line) if self.tty and not final else (line + "\n"))
        sys.stderr.flush()


async def _open_sender(args: argparse.Namespace, on_frame):
    from hil.transport import open_sender

    if args.transport == "udp":
        return await open_sender("udp", to=args.to, host_to=args.host_to)
    return await open_sender("can", interface=args.can_interface, channel=args.can_channel,
                             fd=bool(args.can_fd), on_frame=on_frame)


async def replay(args: argparse.Namespace, the_plan: Plan,
                 lateness: list[float] | None = None,
                 signer: Signer | None = None) -> dict[str, int]:
    """Send the plan in real time (or as fast as possible); returns the counters.
    ``lateness`` collects every sent frame's send time minus its deadline (s); ``signer``
    signs the RVs' frames (made from ``args.sign`` when not given)."""
    framing = framing_of(args)
    signer = signer or make_signer(args, the_plan)
    attacking = _Attacking(args, the_plan, signer, framing) if args.attack else None
    cap = _Capture(Path(args.capture), the_plan, args) if args.capture else None
    on_frame = cap.canlog.on_message_received if cap is not None and cap.canlog else None
    sender = await _open_sender(args, on_frame)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    events = the_plan.events
    tids = [temp_id(v) for v in the_plan.vehicles]
    t0 = float(events["time"][0]) if len(events) else 0.0
    pacer = Pacer(t0, None if args.asap else args.speed)
    progress = _Progress(args.progress)
    # where each channel's datagrams come from, for the pcapng (the sockets' own ports)
    src = dict(getattr(sender, "local", {}))
    src.setdefault("rv", ("127.0.0.1", 0))
    src.setdefault("host", src["rv"])
    counts = {"sent": 0, "dropped": 0, "host": 0}
    times = events["time"].tolist()
    try:
        i, n = 0, len(events)
        while i < n and not stop.is_set():
            due = times[i]
            j = i
            while j < n and times[j] == due:
                j += 1
            batch = events[i:j]
            # Encode before the deadline, send at it, write the capture after the sends.
            gen_unix = time.time() + max(0.0, pacer.deadline(due) - pacer.clock())
            encoded = [encode_event(ev, the_plan, framing, signer, gen_unix,
                                    attacking.attacks if attacking else None) for ev in batch]
            frames = [frame for frame, _ in encoded]
            extra = attacking.frames(batch, frames, gen_unix) if attacking else []
            await pacer.wait(due)
            deadline = pacer.deadline(due)

            def stamp() -> tuple[float, float]:
                return (time.time(), 0.0 if args.asap
                        else max(0.0, pacer.clock() - deadline))  # noqa: B023

            sent_at, extra_at = [], []
            for ev, frame in zip(batch, frames, strict=True):
                if ev["host"] and len(extra_at) < len(extra):  # attackers before the host
                    for attack_frame, _ in extra:
                        await sender.send(attack_frame)
                        extra_at.append(stamp())
                if frame is None:
                    sent_at.append(None)
                    continue
                await (sender.send_host(frame) if ev["host"] else sender.send(frame))
                sent_at.append(stamp())
            for attack_frame, _ in extra[len(extra_at):]:
                await sender.send(attack_frame)
                extra_at.append(stamp())
            for ev, (frame, label), when in zip(batch, encoded, sent_at, strict=True):
                _account(ev, frame, when, the_plan, args, cap, counts, tids, src, lateness,
                         label)
            for (attack_frame, record), when in zip(extra, extra_at, strict=True):
                _account_attack(record, attack_frame, when, args, cap, src)
            progress.update(due, t0, counts["sent"], counts["dropped"],
                            max((w[1] for w in sent_at if w is not None), default=0.0))
            if cap is not None and bool(events["host"][j - 1]):
                cap.write_truth(the_plan, due)
                cap.flush()
            i = j
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        await sender.aclose()
        if cap is not None:
            cap.flush()
            cap.close()
        last = float(events["time"][min(i, len(events) - 1)]) if len(events) else 0.0
        progress.update(last, t0, counts["sent"], counts["dropped"], 0.0, final=True)
    counts["interrupted"] = int(stop.is_set())
    if signer is not None:
        counts.update(signer.counts)
    if attacking is not None:
        counts.update(attacking.counts)
    return counts


class _Attacking:
    """The RVE's side of ``--attack``: fabricated and replayed frames for each batch, and
    their schedule records."""

    def __init__(self, args: argparse.Namespace, the_plan: Plan, signer: Signer | None,
                 framing: str) -> None:
        from catc.attacks import SECURITY, Attacks, parse

        specs = [parse(text) for text in args.attack]
        if signer is None:
            bad = [a.kind for a in specs if a.kind in SECURITY]
            if bad:
                raise ValueError(f"--attack {bad[0]} needs --sign PKI_DIR")
        else:
            for a in specs:
                if a.kind in ("ghost", "sudden"):
                    signer.attacker(a["signer"])  # fail now, in one line, if it is missing
                if a.kind == "foreign-cert":
                    signer.attacker("outsider")
        self.attacks = Attacks(specs, the_plan)
        self.plan, self.signer, self.framing = the_plan, signer, framing
        # what a replay attacker heard: replayed vehicle -> {ms of t: (frame, seq)}, kept
        # for the longest replay delay only
        self.replayed: dict[int, float] = {}
        for k, a in enumerate(specs):
            if a.kind == "replay":
                v = self.attacks.targets[k]
                self.replayed[v] = max(a["delay"], self.replayed.get(v, 0.0))
        self.history: dict[int, dict] = {v: {} for v in self.replayed}
        self.counts = {"attack_frames": 0}

    def frames(self, batch, frames: list, gen_unix: float) -> list[tuple[bytes, dict]]:
        """The attack frames to send with ``batch`` (after its RV frames, before the host
        frame), each with its schedule record."""
        out = []
        for ev, frame in zip(batch, frames, strict=True):
            if ev["host"]:
                continue
            v, t = int(ev["vehicle"]), float(ev["t"])
            if v not in self.history:
                continue
            heard = self.history[v]
            if frame is not None:
                heard[round(t * 1000)] = (frame, int(ev["seq"]))
                oldest = round((t - self.replayed[v]) * 1000)
                for ms in [ms for ms in heard if ms < oldest]:
                    del heard[ms]
            for a in self.attacks.replays(v, t):
                old = heard.get(round((t - a["delay"]) * 1000))
                if old is not None:
                    name = self.plan.vehicles[v]
                    out.append((old[0], self._record(a, name, f"{temp_id(name):08X}",
                                                     t - a["delay"], old[1])))
        host = [ev for ev in batch if ev["host"]]
        if host:
            t = float(host[0]["t"])
            for inj in self.attacks.injected(t):
                frame = encode_frame(inj.bsm)
                signed = None
                if self.signer is not None and self.framing != "uper":
                    who = inj.attack["signer"] if "signer" in inj.attack.params else "insider"
                    signed = self.signer.sign(("attack", inj.bsm.temp_id), frame, t,
                                              gen_unix, self.signer.attacker(who))
                record = self._record(inj.attack, f"attack-{inj.index}",
                                      f"{inj.bsm.temp_id:08X}", t, inj.bsm.msg_cnt)
                out.append((wrap(frame, self.framing, signed), record))
        self.counts["attack_frames"] += len(out)
        return out

    @staticmethod
    def _record(a, vehicle: str, tid: str, t: float, seq: int | None) -> dict:
        return {"vehicle": vehicle, "id": tid, "channel": "rv", "index": -1,
                "seq": -1 if seq is None else seq, "t": t, "dropped": False,
                "cause": "attack", "delay": 0.0, "attack": a.kind,
                **({"signer": a["signer"]} if "signer" in a.params else {})}


def _account(ev, frame, when, the_plan: Plan, args, cap, counts, tids, src,
             lateness: list[float] | None, attack=None) -> None:
    """Counters, lateness and capture records of one event after its batch was sent."""
    host = bool(ev["host"])
    if frame is None:
        counts["dropped"] += 1
    else:
        counts["host" if host else "sent"] += 1
        if lateness is not None and not host:
            lateness.append(when[1])
    if cap is None:
        return
    record = {"vehicle": the_plan.vehicles[int(ev["vehicle"])],
              "id": f"{tids[int(ev['vehicle'])]:08X}", "channel": "host" if host else "rv",
              "index": int(ev["index"]), "seq": int(ev["seq"]), "t": float(ev["t"]),
              "dropped": bool(ev["dropped"]), "cause": CAUSES[int(ev["cause"])],
              "delay": None if ev["dropped"] else float(ev["delay"])}
    if attack is not None:
        record["attack"] = attack.kind
    if frame is not None:
        record.update(sent_unix=when[0], late_ms=round(when[1] * 1000.0, 4),
                      octets=len(frame))
        if cap.pcap is not None:
            channel = "host" if host else "rv"
            _pcap(cap, args, src, channel, tids[int(ev["vehicle"])], frame, when[0])
    cap.schedule.write(record)


def _pcap(cap, args, src, channel: str, tid: int, frame: bytes, t_unix: float) -> None:
    """One sent frame into the pcapng: as a UDP datagram, or with --framing wsmp as it
    goes over the air (Ethernet II, ethertype 0x88DC, from a MAC made of the sender's
    TemporaryID)."""
    if cap.wsmp:
        mac = b"\x02\x00" + tid.to_bytes(4, "big")
        cap.pcap.write(ethernet(b"\xff" * 6, mac, ETHERTYPE_WSMP, frame), t_unix,
                       cap.pcap.ETHERNET)
    else:
        cap.pcap.write(udp_packet(src[channel], args.host_to if channel == "host" else args.to,
                                  frame), t_unix)


def _account_attack(record: dict, frame: bytes, when, args, cap, src) -> None:
    """The schedule record (labelled with its attack) and capture of an attack frame."""
    if cap is None:
        return
    record = dict(record, sent_unix=when[0], late_ms=round(when[1] * 1000.0, 4),
                  octets=len(frame))
    if cap.pcap is not None:
        _pcap(cap, args, src, "rv", int(record["id"], 16), frame, when[0])
    cap.schedule.write(record)


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
            _Attacking(args, the_plan, signer, framing_of(args))  # one line if it cannot be
    except ValueError as err:  # hil.pki.PkiError included
        print(f"rve run: {err}", file=sys.stderr)
        return 2
    try:
        counts = asyncio.run(replay(args, the_plan, signer=signer))
    except TransportError as err:
        print(f"rve run: {err}", file=sys.stderr)
        return 2
    print(json.dumps({"sent": counts["sent"], "dropped": counts["dropped"],
                      "host_frames": counts["host"], "interrupted": bool(counts["interrupted"]),
                      "vehicles": len(the_plan.vehicles) - 1, "host": the_plan.host_id,
                      **{k: counts[k] for k in ("signed", "with_certificate",
                                                 "attack_frames") if k in counts}}),
          flush=True)
    return 0
