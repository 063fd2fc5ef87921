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
from catc.j2735.ieee1609 import ETHERTYPE_WSMP, wrap_unsecured, wrap_wsmp
from catc.replay import Plan, plan, temp_id
from hil.capture import JsonLines, PcapngWriter, can_log, ethernet, udp_packet, versions
from hil.config import address, percent
from hil.datasets import load_table
from hil.pacing import Pacer

__all__ = ["DEFAULTS", "add_arguments", "run"]

#: Settings when neither a flag nor the config file gives them.
DEFAULTS = {
    "dataset": "scenario:highway-braking", "transport": "udp", "to": ("127.0.0.1", 4500),
    "host_to": ("127.0.0.1", 4501), "per": 0.0, "burst": 1.0, "rate": 10.0, "latency": 0.0,
    "jitter": 0.0, "seed": 0, "speed": 1.0, "asap": False, "capture": None,
    "duration": None, "host": None, "trip": None, "ieee1609": False, "distance": False,
    "can_interface": "virtual", "can_channel": None, "can_fd": False, "progress": True,
    "idm_host": None, "sign": None, "framing": None, "attack": None,
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``rve run`` (DESIGN.md's contract); unset ones come from --config."""
    p.add_argument("--config", metavar="FILE.toml", help="settings file; flags override it")
    p.add_argument("--dataset", metavar="SPEC",
                   help="PATH, KIND:PATH or scenario:NAME (default scenario:highway-braking)")
    p.add_argument("--trip", metavar="NAME", help="which trip of a multi-trip dataset "
                   "(default the first)")
    p.add_argument("--host", metavar="ID", help="host vehicle (default: the dataset's)")
    p.add_argument("--idm-host", metavar="LEADER", help="add a synthetic host vehicle that "
                   "follows LEADER with the IDM car-following model (catc.hostsim) and use it")
    p.add_argument("--transport", choices=("udp", "can"), help="udp (default) or can")
    p.add_argument("--to", type=address, help="UDP HOST:PORT of the RV frames "
                   "(default 127.0.0.1:4500)")
    p.add_argument("--host-to", type=address, help="UDP HOST:PORT of the host "
                   "vehicle's frames (default 127.0.0.1:4501)")
    p.add_argument("--per", type=percent, help="packet error rate, %% (default 0)")
    p.add_argument("--burst", type=float, help="mean burst length in messages; 1 = "
                   "independent losses (default 1)")
    p.add_argument("--rate", type=float, help="transmission rate, 1-10 Hz (default 10)")
    p.add_argument("--latency", type=float, metavar="MS", help="fixed latency, ms")
    p.add_argument("--jitter", type=float, metavar="MS", help="each frame is delayed a "
                   "further U(0, jitter) ms; reordering happens")
    p.add_argument("--distance", action="store_true", default=None,
                   help="also lose messages by HV-RV distance (catc.channel curve)")
    p.add_argument("--seed", type=int, help="seed of the loss and jitter pattern")
    p.add_argument("--speed", type=float, help="replay speed factor (default 1 = real time)")
    p.add_argument("--asap", action="store_true", default=None,
                   help="send as fast as possible (no pacing)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S s of data")
    p.add_argument("--capture", metavar="DIR", help="capture directory (see rve run --help)")
    p.add_argument("--ieee1609", action="store_true", default=None,
                   help="wrap each frame in an unsecured IEEE 1609.2 envelope "
                        "(= --framing 1609)")
    p.add_argument("--framing", choices=("uper", "1609", "wsmp"),
                   help="what goes on the wire: the bare UPER MessageFrame (default), an "
                        "IEEE 1609.2 Ieee1609Dot2Data, or that inside an IEEE 1609.3 WSMP "
                        "WAVE Short Message (PSID 0x20); --sign implies 1609")
    p.add_argument("--sign", metavar="PKI_DIR",
                   help="sign every RV's BSM as IEEE 1609.2 SignedData with a pseudonym "
                        "certificate of PKI_DIR (rve pki init); the host channel stays "
                        "unsigned")
    p.add_argument("--attack", action="append", metavar="KIND[:KEY=VALUE,...]",
                   help="add a misbehaving sender (repeatable): ghost, sudden, sybil, replay, "
                        "offset, speed, unsigned, bad-signature, foreign-cert; each message "
                        "is labelled in rve.schedule.jsonl (catc.attacks has the parameters)")
    p.add_argument("--can-interface", choices=("socketcan", "virtual", "udp_multicast"),
                   help="python-can interface for --transport can (default virtual)")
    p.add_argument("--can-channel", metavar="NAME", help="CAN channel, e.g. vcan0")
    p.add_argument("--can-fd", action="store_true", default=None, help="CAN FD frames")
    p.add_argument("--no-progress", dest="progress", action="store_false", default=None,
                   help="no progress line on stderr")


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


def make_signer(args: argparse.Namespace, the_plan: Plan) -> Signer | None:
    """The --sign PKI's signer for this plan, or None (ValueError when it does not fit)."""
    if not args.sign:
        return None
    from hil.pki import load

    return Signer(load(args.sign), len(the_plan.vehicles),
                  list(the_plan.vehicles).index(the_plan.host_id))


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
            encoded = [_encode(ev, the_plan, framing, signer, gen_unix,
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


class Signer:
    """IEEE 1609.2 signing of the RVs' BSMs (``--sign``), one pseudonym per vehicle.

    The signer is the full certificate in a vehicle's first BSM, then at least once per
    second of data time, and in its next BSM after a vehicle it has not heard before
    starts sending (SAE J2945/1's rule: a new neighbour may not know our certificate);
    otherwise its HashedId8 digest.  The decisions follow the data's clock, so a run
    repeats them exactly; generationTime is the wall-clock deadline of the frame.
    """

    CERT_PERIOD_S = 1.0

    def __init__(self, pki, n_vehicles: int, host_index: int) -> None:
        from catc.security import unix_to_time64

        rvs = n_vehicles - 1
        if len(pki.pseudonyms) < rvs:
            raise ValueError(f"--sign {pki.directory}: {len(pki.pseudonyms)} pseudonym "
                             f"certificates for {rvs} remote vehicles (rve pki init "
                             f"--vehicles {rvs})")
        self.to_time64 = unix_to_time64
        others = [i for i in range(n_vehicles) if i != host_index]
        self.identity = {v: pki.pseudonyms[k] for k, v in enumerate(others)}
        self.last_cert: dict = {}
        self.owed: set = set()
        self.heard: set = set()
        self.counts = {"signed": 0, "with_certificate": 0}
        # the attackers' identities: an insider holds the PKI's first pseudonym that no RV
        # uses; an outsider, a pseudonym of the untrusted foreign PKI
        self.insider = pki.pseudonyms[rvs] if len(pki.pseudonyms) > rvs else None
        self.outsider = pki.foreign[0] if pki.foreign else None
        self.directory = pki.directory

    def attacker(self, who: str):
        """The (certificate, key) of an ``insider`` or ``outsider`` attacker."""
        ident = self.insider if who == "insider" else self.outsider
        if ident is None:
            raise ValueError(
                f"--sign {self.directory}: no {who} identity for the attack ("
                + ("rve pki init --vehicles N with N > the number of RVs)" if who == "insider"
                   else "the PKI has no foreign/ directory)"))
        return ident

    def sign(self, vehicle, frame: bytes, t: float, gen_unix: float,
             identity=None) -> bytes:
        """``frame`` signed by ``vehicle``'s pseudonym (or ``identity``, an attacker's
        (certificate, key), for a fabricated sender ``vehicle``)."""
        from catc.security import sign_bsm

        if vehicle not in self.heard:  # a new sender: everybody else owes its certificate
            self.heard.add(vehicle)
            self.owed.update(v for v in self.heard if v != vehicle)
        last = self.last_cert.get(vehicle)
        full = last is None or t - last >= self.CERT_PERIOD_S - 1e-9 or vehicle in self.owed
        if full:
            self.last_cert[vehicle] = t
            self.owed.discard(vehicle)
            self.counts["with_certificate"] += 1
        cert, key = identity or self.identity[vehicle]
        self.counts["signed"] += 1
        return sign_bsm(frame, key, cert, self.to_time64(gen_unix), include_cert=full)


def framing_of(args: argparse.Namespace) -> str:
    """``uper``, ``1609`` or ``wsmp`` from --framing, --ieee1609 and --sign."""
    framing = args.framing or ("1609" if args.ieee1609 or args.sign else "uper")
    if args.sign and framing == "uper":
        raise ValueError("--sign needs an IEEE 1609.2 envelope: --framing 1609 or wsmp")
    return framing


def _frame(ev, the_plan: Plan, framing: bool | str, signer: Signer | None = None,
           gen_unix: float | None = None) -> bytes | None:
    """The wire frame of one event (None when the channel drops it): the UPER
    MessageFrame, in a 1609.2 envelope (signed for RVs with ``signer``) and a WSMP one as
    ``framing`` says (True/False: 1609/uper)."""
    return _encode(ev, the_plan, framing, signer, gen_unix, None)[0]


def _wrap(frame: bytes, framing: str, signed: bytes | None) -> bytes:
    """A UPER frame in the envelopes of ``framing``: ``signed`` (its SignedData) or else
    an unsecured 1609.2 envelope, then WSMP when asked for."""
    if framing == "uper":
        return frame
    frame = signed if signed is not None else wrap_unsecured(frame)
    return wrap_wsmp(frame) if framing == "wsmp" else frame


def _encode(ev, the_plan: Plan, framing: bool | str, signer: Signer | None,
            gen_unix: float | None, attacks) -> tuple[bytes | None, object | None]:
    """:func:`_frame`, with the attacks on this event's vehicle applied: (frame, the
    :class:`catc.attacks.Attack` that changed it or None)."""
    if ev["dropped"]:
        return None, None
    framing = {True: "1609", False: "uper"}.get(framing, framing)
    bsm = the_plan.bsm(ev)
    vehicle, t, label = int(ev["vehicle"]), float(ev["t"]), None
    if attacks is not None and not ev["host"]:
        bsm, label = attacks.modify(vehicle, t, bsm)
    frame = encode_frame(bsm)
    if framing == "uper" or signer is None or ev["host"]:
        return _wrap(frame, framing, None), label
    gen = time.time() if gen_unix is None else gen_unix
    sec = attacks.security(vehicle, t) if attacks is not None else None
    if sec is not None:
        label = sec
        if sec.kind == "unsigned":
            return _wrap(frame, framing, None), label
        if sec.kind == "foreign-cert":
            return _wrap(frame, framing, signer.sign(("foreign", vehicle), frame, t, gen,
                                                     signer.attacker("outsider"))), label
        signed = signer.sign(vehicle, frame, t, gen)  # bad-signature: one bit of sSig
        return _wrap(frame, framing, signed[:-1] + bytes([signed[-1] ^ 0x01])), label
    return _wrap(frame, framing, signer.sign(vehicle, frame, t, gen)), label


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
                out.append((_wrap(frame, self.framing, signed), record))
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
