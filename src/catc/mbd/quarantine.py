"""The quarantine rule: whose messages must raise no warning, and until when.

Evidence attaches to a :class:`Principal`: the signer of the message (the HashedId8 of
its certificate, :mod:`catc.mbd.identity`), or its TemporaryID when it is unsigned (then
nothing binds the id to a sender, and whoever claims an id can get it quarantined: the
unsigned mode cannot resist id theft).  Through its signer, a quarantine covers every id
that signer holds.

A principal is quarantined when ``quarantine_k`` of its messages fail within
``quarantine_window_s`` (a message counts once, however many checks it fails: a single
GNSS glitch is one failed message; weak findings spread over the window add up), or at
once on a strong finding (:func:`is_strong`: a sudden appearance inside the host's safety
range, in its path ahead and in its clear line of sight, an intersection, a Sybil, an id
held by another signer). The quarantine lasts ``quarantine_s`` from the last detection and
is renewed by every new one; after a strong finding, with ``sticky_strong``, by every
message of the principal too (a fabricated vehicle does not become real by behaving
consistently afterwards). The rule is ours, the window F2MD's
(:class:`~catc.mbd.config.MbdConfig`); docs/reference/mbd.md explains it.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable

from catc.mbd.checks import Detection, in_path
from catc.mbd.config import MbdConfig

__all__ = ["Principal", "Quarantine", "is_strong"]

#: Findings kept per principal below the reporting threshold (the newest; a sender
#: spraying findings is over the threshold long before).
_PENDING_MAX = 16


def is_strong(d: Detection, c: MbdConfig) -> bool:
    """Whether ``d`` quarantines its sender at once: an intersection, a Sybil, an id
    another signer holds, or a sudden appearance inside the host's safety range, in its
    path ahead (where a ghost can trigger a forward collision warning) and in its clear
    line of sight (one behind another vehicle may have been in its radio shadow).  A
    sudden appearance beside or behind the host is weak: on real traffic honest cars are
    first heard there (docs/log/2026-11-28-mbd-in-path.md)."""
    check = d.check
    return check in ("intersection", "sybil", "id-conflict") or (
        check == "sudden-appearance" and d.evidence["distance_m"] < c.sa_safety_range_m
        and d.evidence["behind"] is None and in_path(d, c))


class Principal:
    """Who evidence attaches to: ``key``, a signer's HashedId8 (bytes) or an unsigned
    TemporaryID (int); the receive times of its failed messages in the window
    (``strikes``), whether a strong finding quarantined it, and until when (s)."""

    __slots__ = ("key", "pending", "strikes", "strong", "until")

    def __init__(self, key: Hashable) -> None:
        self.key = key
        self.strikes: list[float] = []
        #: Its findings in the window not yet reported (below the reporting threshold).
        self.pending: list[Detection] = []
        self.strong = False
        self.until = -float("inf")


class Quarantine:
    """The principals with evidence or in quarantine (at most ``max_senders``, the least
    recently judged forgotten first)."""

    def __init__(self, config: MbdConfig, max_senders: int) -> None:
        self.config = config
        self.max_senders = max_senders
        self._by: OrderedDict[Hashable, Principal] = OrderedDict()

    def __len__(self) -> int:
        return len(self._by)

    def quarantined(self, key: Hashable, t: float) -> bool:
        """Whether principal ``key`` is in quarantine at ``t``."""
        p = self._by.get(key)
        return p is not None and t < p.until

    def punish(self, key: Hashable, t: float, found: list[Detection]
               ) -> tuple[bool, tuple[Detection, ...]]:
        """A message of ``key`` received at ``t`` failed the checks of ``found``: count
        the strike and quarantine or renew.  Returns whether ``key`` enters quarantine,
        and what to report: nothing while the evidence is below the threshold (the
        findings wait, for the window, in ``pending``); once ``key`` is in quarantine,
        its pending findings (on entry) and ``found``."""
        c = self.config
        p = self._get(key)
        active = t < p.until
        strikes = [s for s in p.strikes if t - s < c.quarantine_window_s]
        strikes.append(t)
        p.strikes = strikes[-c.quarantine_k:]
        strong = any(is_strong(d, c) for d in found)
        if strong or len(strikes) >= c.quarantine_k or active:
            p.strong = p.strong or strong
            p.until = t + c.quarantine_s
            earlier = tuple(d for d in p.pending if t - d.t < c.quarantine_window_s)
            p.pending = []
            return not active, (*earlier, *found)
        p.pending = [d for d in p.pending if t - d.t < c.quarantine_window_s] + found
        del p.pending[:-_PENDING_MAX]
        return False, ()

    def passed(self, key: Hashable, t: float) -> None:
        """A message of ``key`` received at ``t`` passed every check: it renews a
        quarantine on a strong finding (``sticky_strong``)."""
        p = self._by.get(key)
        if p is not None and p.strong and self.config.sticky_strong and t < p.until:
            p.until = t + self.config.quarantine_s
            self._by.move_to_end(key)

    def _get(self, key: Hashable) -> Principal:
        by = self._by
        p = by.get(key)
        if p is None:
            p = by[key] = Principal(key)
            while len(by) > self.max_senders:
                by.popitem(last=False)
        else:
            by.move_to_end(key)
        return p
