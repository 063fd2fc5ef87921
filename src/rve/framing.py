"""The wire frame of a scheduled event (``rve run --framing``).

Each BSM is encoded as an SAE J2735 UPER MessageFrame; with ``1609`` it goes in an IEEE
1609.2 ``Ieee1609Dot2Data`` (unsecured, or SignedData for the RVs with ``--sign``:
:class:`rve.signing.Signer`), and with ``wsmp`` that envelope inside an IEEE 1609.3 WAVE
Short Message.  The attacks that change a vehicle's own messages (``--attack`` offset,
speed, and the security ones: unsigned, bad-signature, foreign-cert) are applied here,
on the way from the plan's event to the wire.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from catc.j2735 import encode_frame
from catc.j2735.ieee1609 import wrap_unsecured, wrap_wsmp
from catc.replay import Plan
from rve.signing import Signer

__all__ = ["encode_event", "framing_of", "wire_frame", "wrap"]


def framing_of(args: argparse.Namespace) -> str:
    """``uper``, ``1609`` or ``wsmp`` from --framing, --ieee1609 and --sign."""
    framing = args.framing or ("1609" if args.ieee1609 or args.sign else "uper")
    if args.sign and framing == "uper":
        raise ValueError("--sign needs an IEEE 1609.2 envelope: --framing 1609 or wsmp")
    return framing


def wire_frame(ev: Any, the_plan: Plan, framing: bool | str, signer: Signer | None = None,
               gen_unix: float | None = None) -> bytes | None:
    """The wire frame of one event (None when the channel drops it): the UPER
    MessageFrame, in a 1609.2 envelope (signed for RVs with ``signer``) and a WSMP one as
    ``framing`` says (True/False: 1609/uper)."""
    return encode_event(ev, the_plan, framing, signer, gen_unix, None)[0]


def wrap(frame: bytes, framing: str, signed: bytes | None) -> bytes:
    """A UPER frame in the envelopes of ``framing``: ``signed`` (its SignedData) or else
    an unsecured 1609.2 envelope, then WSMP when asked for."""
    if framing == "uper":
        return frame
    frame = signed if signed is not None else wrap_unsecured(frame)
    return wrap_wsmp(frame) if framing == "wsmp" else frame


def encode_event(ev: Any, the_plan: Plan, framing: bool | str, signer: Signer | None,
                 gen_unix: float | None, attacks: Any) -> tuple[bytes | None, Any]:
    """:func:`wire_frame`, with the attacks (:class:`catc.attacks.Attacks` or None) on
    this event's vehicle applied: (frame, the :class:`catc.attacks.Attack` that changed
    it or None)."""
    if ev["dropped"]:
        return None, None
    framing = {True: "1609", False: "uper"}.get(framing, framing)
    bsm = the_plan.bsm(ev)
    vehicle, t, label = int(ev["vehicle"]), float(ev["t"]), None
    if attacks is not None and not ev["host"]:
        bsm, label = attacks.modify(vehicle, t, bsm)
    frame = encode_frame(bsm)
    if framing == "uper" or signer is None or ev["host"]:
        return wrap(frame, framing, None), label
    gen = time.time() if gen_unix is None else gen_unix
    sec = attacks.security(vehicle, t) if attacks is not None else None
    if sec is not None:
        label = sec
        if sec.kind == "unsigned":
            return wrap(frame, framing, None), label
        if sec.kind == "foreign-cert":
            return wrap(frame, framing, signer.sign(("foreign", vehicle), frame, t, gen,
                                                    signer.attacker("outsider"))), label
        signed = signer.sign(vehicle, frame, t, gen)  # bad-signature: one bit of sSig
        return wrap(frame, framing, signed[:-1] + bytes([signed[-1] ^ 0x01])), label
    return wrap(frame, framing, signer.sign(vehicle, frame, t, gen)), label
