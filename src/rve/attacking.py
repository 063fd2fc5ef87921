"""The RVE's side of ``rve run --attack``: the frames of fabricated and replayed senders.

:mod:`catc.attacks` builds the fabricated BSMs (ghost, sudden, sybil) and the changed
values, and says which frames a replay attacker sends again; this module turns them into
wire frames (signed by an insider's or outsider's certificate with ``--sign``) at each
batch of the replay, each with its ``rve.schedule.jsonl`` record labelled with its attack
(:func:`hil.capture.schema.scheduled`).  The attacks on a vehicle's own messages are
applied where its frames are made (:func:`rve.framing.encode_event`).
"""

from __future__ import annotations

import argparse
from typing import Any

from catc.j2735 import encode_frame
from catc.replay import Plan, temp_id
from hil.capture import schema
from rve.framing import wrap
from rve.signing import Signer

__all__ = ["Attacking"]


class Attacking:
    """The RVE's side of ``--attack``: fabricated and replayed frames for each batch, and
    their schedule records.  Raises ValueError, in one line, for an attack that cannot
    run (a security attack without ``--sign``, a signer's identity missing)."""

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
                if a.kind in ("ghost", "sudden", "impersonate"):
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

    def frames(self, batch: Any, frames: list[bytes | None], gen_unix: float
               ) -> list[tuple[bytes, dict[str, Any]]]:
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
                    out.append((old[0], self._record(a, name, temp_id(name),
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
                record = self._record(inj.attack, f"attack-{inj.index}", inj.bsm.temp_id, t,
                                      inj.bsm.msg_cnt)
                out.append((wrap(frame, self.framing, signed), record))
        self.counts["attack_frames"] += len(out)
        return out

    @staticmethod
    def _record(a: Any, vehicle: str, tid: int, t: float, seq: int | None
                ) -> dict[str, Any]:
        """The schedule record of an attack's own frame (sample index -1, never dropped)."""
        return schema.scheduled(vehicle, tid, "rv", -1, -1 if seq is None else seq, t, False,
                                "attack", 0.0, attack=a.kind,
                                **({"signer": a["signer"]} if "signer" in a.params else {}))
