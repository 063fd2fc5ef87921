"""``rve flood``: garbage at an OBU's RV port, in real time, from its own process.

What a noisy channel or a broken neighbour puts on the air, made to test that the OBU
counts and drops it and that its warnings do not change (issue 18): a mix, by weight, of

* ``random``: random octets, 1–300 long (almost never a frame);
* ``oversize``: random datagrams of 2,000–65,000 octets (above any BSM; the OBU's
  receiver drops them as ``oversized``);
* ``copy``: a copy of a frame the RVE is sending at about this moment (the host's or an
  RV's, the same replay plan as ``rve run`` with the same dataset, trip, PER and seed),
  with one bit flipped and, half of the time, cut to a random length: garbage that often
  still decodes, with the host's id or an id one bit away from a real one.

The flood follows the data clock of the replay (``--speed`` as ``rve run``): start it with
the RVE.  It sends to 127.0.0.1/::1 or wherever ``--to`` says, at ``--rate`` datagrams/s
for ``--duration`` s (wall clock), and prints what it sent, by kind, as one JSON line.

    rve flood --dataset SPEC --to HOST:PORT [--rate 2000] [--duration S] [--speed 4]
              [--mix random=1,oversize=0.1,copy=1] [--per 50] [--seed 7] [--flood-seed 1]
              [--lag 4] [--until S]
"""

from __future__ import annotations

import argparse
import json
import random
import socket
import sys
import time

from catc.channel import ChannelConfig
from catc.errors import EncodeError

KINDS = ("random", "oversize", "copy")


def _mix(text: str) -> dict[str, float]:
    out = {}
    for part in text.split(","):
        name, _, weight = part.partition("=")
        if name not in KINDS:
            raise argparse.ArgumentTypeError(f"unknown kind {name!r}; known: {', '.join(KINDS)}")
        try:
            out[name] = float(weight or 1.0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"bad weight in {part!r}") from None
        if not out[name] >= 0.0:
            raise argparse.ArgumentTypeError(f"negative weight in {part!r}")
    if not sum(out.values()) > 0.0:
        raise argparse.ArgumentTypeError("the mix needs a positive weight")
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hil.config import destination, percent, positive

    p.add_argument("--dataset", default="scenario:highway-braking",
                   help="the RVE's dataset (copies are of its frames)")
    p.add_argument("--trip", help="the RVE's trip")
    p.add_argument("--to", type=destination, required=True, help="UDP HOST:PORT to flood")
    p.add_argument("--rate", type=positive, default=2000.0, help="datagrams/s (default 2000)")
    p.add_argument("--duration", type=positive, default=10.0, help="seconds (default 10)")
    p.add_argument("--speed", type=positive, default=1.0, help="the RVE's replay speed")
    p.add_argument("--per", type=percent, default=0.0, help="the RVE's PER, %%")
    p.add_argument("--seed", type=int, default=0, help="the RVE's seed")
    p.add_argument("--flood-seed", type=int, default=1, help="seed of the garbage")
    p.add_argument("--lag", type=float, default=4.0,
                   help="copy frames the RVE sent at least this long ago, in data seconds "
                        "(default 4: after the receiver has the originals, whatever the "
                        "start-up skew of the two processes)")
    p.add_argument("--until", type=positive, metavar="S",
                   help="copy only frames of the RVE's first S data seconds (its --duration)")
    p.add_argument("--mix", type=_mix, default=_mix("random=1,oversize=0.1,copy=1"),
                   help="kinds and weights (default random=1,oversize=0.1,copy=1)")


def _frames(args: argparse.Namespace) -> tuple[list[float], list[bytes]]:
    """(data time from the first host sample, frame) of every frame the RVE sends."""
    from catc.j2735 import encode_frame
    from catc.replay import plan
    from hil.datasets import load_table

    table = load_table(args.dataset, args.trip)
    the_plan = plan(table, ChannelConfig(per=args.per / 100.0), args.seed,
                    duration=getattr(args, "until", None))
    ev = the_plan.events
    t0 = float(ev["t"][ev["host"]][0])
    times, frames = [], []
    for e in ev:
        if e["dropped"]:
            continue
        try:
            frames.append(encode_frame(the_plan.bsm(e)))
        except EncodeError:
            continue
        times.append(float(e["time"]) - t0)
    return times, frames


def command(args: argparse.Namespace) -> int:
    if not (args.rate > 0 and args.duration > 0 and args.speed > 0):
        print("rve flood: --rate, --duration and --speed must be positive", file=sys.stderr)
        return 2
    from hil.datasets import DatasetError

    try:
        times, frames = _frames(args) if args.mix.get("copy") else ([], [])
    except DatasetError as err:
        print(f"rve flood: {err}", file=sys.stderr)
        return 2
    print(json.dumps(flood(args, times, frames)), flush=True)
    return 0


def flood(args: argparse.Namespace, times: list[float], frames: list[bytes]) -> dict:
    """Send the flood ``args`` describe (``to``, ``rate``, ``duration``, ``speed``,
    ``mix``, ``flood_seed``, ``lag``), copying ``frames`` (sent by the RVE at data
    ``times``, s from its start); what was sent, by kind."""
    rng = random.Random(args.flood_seed)
    kinds = [k for k in KINDS if args.mix.get(k)]
    weights = [args.mix[k] for k in kinds]
    family = socket.AF_INET6 if ":" in args.to[0] else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    sent = dict.fromkeys(KINDS, 0)
    errors = 0
    start = time.monotonic()
    period = 1.0 / args.rate
    k = 0
    j = 0  # the newest frame the RVE has sent by now
    while True:
        due = start + k * period
        now = time.monotonic()
        if due - start >= args.duration:
            break
        if due > now:
            time.sleep(due - now)
        k += 1
        kind = rng.choices(kinds, weights)[0]
        if kind == "copy":
            data_t = (time.monotonic() - start) * args.speed - args.lag
            while j + 1 < len(times) and times[j + 1] <= data_t:
                j += 1
            if not frames or times[0] > data_t:
                kind = "random"  # nothing old enough to copy yet
        if kind == "copy":
            src = bytearray(frames[max(0, j - rng.randrange(8))])
            bit = rng.randrange(len(src) * 8)
            src[bit // 8] ^= 0x80 >> (bit % 8)
            if rng.random() < 0.5:
                src = src[:rng.randrange(1, len(src) + 1)]
            data = bytes(src)
        elif kind == "random":
            data = rng.randbytes(rng.randrange(1, 301))
        else:
            data = rng.randbytes(rng.randrange(2000, 65001))
        try:
            sock.sendto(data, args.to)
            sent[kind] += 1
        except OSError:
            errors += 1
    sock.close()
    return {"sent": sent, "datagrams": sum(sent.values()), "errors": errors,
            "seconds": round(time.monotonic() - start, 3)}
