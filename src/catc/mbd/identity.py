"""Which signer holds each TemporaryID, and the ids each signer sends under.

A BSM's TemporaryID is whatever its sender writes; its IEEE 1609.2 signature says which
certificate (HashedId8) signed it.  Nothing in either binds the two, so one pseudonym
could sign messages under any id, and evidence kept per id would fall on the vehicle
whose id was claimed.  Here an id belongs to the first signer heard with it until that
signer has not used it for ``id_hold_s``; a message of another signer (or an unsigned
one) under a held id is an id conflict: the newcomer is the suspect, and the holder's
messages flow on.  A pseudonym change (a new id under a new certificate, the old id
falling silent) binds the new id to the new signer, as SCMS changes both together.

One signer sends under one id at a time: an id it changes (without changing its
certificate) starts after the last message of the old one, on the signer's own clock
(secMark), however the radio reorders them.  Two ids of one signer whose messages
interleave in time are one vehicle posing as two (a Sybil).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable

from catc.mbd.config import MbdConfig
from catc.mbd.state import wrapped_dt

__all__ = ["Identities"]


class _Signer:
    """One signer's clock (its first message: receive time, secMark) and, per id it
    holds, the first and last times its messages there were generated (on that clock)."""

    __slots__ = ("ids", "sm0", "t0")

    def __init__(self, t: float, sm: int | None) -> None:
        self.t0, self.sm0 = t, sm
        self.ids: dict[int, list[float]] = {}


class Identities:
    """The holder of each TemporaryID (an LRU of at most ``max_ids``) and the ids each
    signer holds."""

    def __init__(self, config: MbdConfig, max_ids: int) -> None:
        self.config = config
        self.max_ids = max_ids
        self._holder: OrderedDict[int, list] = OrderedDict()  # id -> [signer, last used]
        self._signers: dict[Hashable, _Signer] = {}  # the signers holding an id

    def __len__(self) -> int:
        return len(self._holder)

    def holder(self, tid: int, t: float) -> Hashable | None:
        """The signer holding ``tid`` at ``t`` (None: nobody)."""
        e = self._holder.get(tid)
        return e[0] if e is not None and t - e[1] < self.config.id_hold_s else None

    def ids_of(self, signer: Hashable) -> frozenset[int]:
        """The ids ``signer`` holds."""
        s = self._signers.get(signer)
        return frozenset(() if s is None else s.ids)

    def claim(self, tid: int, signer: Hashable, t: float, sm: int | None
              ) -> tuple[Hashable | None, bool, int | None]:
        """A message of ``signer`` under ``tid`` received at ``t`` with secMark ``sm``:
        ``(holder, new, twin)``.  ``holder`` is the other signer that holds ``tid`` (an id
        conflict: the message is not ``signer``'s to send; then nothing else is done),
        else None; ``new`` is True when ``tid`` changed hands (its holder fell silent
        ``id_hold_s`` ago): its history is not the new holder's; ``twin`` is another id
        of ``signer`` whose messages interleave in time with this id's (None: none)."""
        held = self._holder
        e = held.get(tid)
        new = False
        if e is not None and e[0] != signer:
            if t - e[1] < self.config.id_hold_s:
                return e[0], False, None
            self._release(tid, e[0])
            new = True
            e = None
        if e is None:
            e = held[tid] = [signer, t]
            while len(held) > self.max_ids:
                old, (s, _) = held.popitem(last=False)
                self._drop(old, s)
        else:
            e[1] = max(e[1], t)
            held.move_to_end(tid)
        s = self._signers.get(signer)
        if s is None:
            s = self._signers[signer] = _Signer(t, sm)
        g = t if sm is None or s.sm0 is None else s.t0 + wrapped_dt(sm, s.sm0, t - s.t0)
        span = s.ids.get(tid)
        if span is None:
            span = s.ids[tid] = [g, g]
        else:
            span[0], span[1] = min(span[0], g), max(span[1], g)
        twin = None
        if len(s.ids) > 1:
            for other, (first, last) in s.ids.items():
                if other != tid and span[0] <= last and first <= span[1]:
                    twin = other
                    break
        return None, new, twin

    def _release(self, tid: int, signer: Hashable) -> None:
        del self._holder[tid]
        self._drop(tid, signer)

    def _drop(self, tid: int, signer: Hashable) -> None:
        s = self._signers.get(signer)
        if s is not None:
            s.ids.pop(tid, None)
            if not s.ids:
                del self._signers[signer]
