"""The replay cache of :class:`catc.security.Verifier`: the messages already accepted,
each until it leaves the freshness window (see :mod:`catc.security`, "Replays").

A key is the SHA-256 of a message's ``ToBeSignedData`` (32 octets), a value the last
instant (Time64 µs) at which the message could still be accepted.  Entries are kept in
the order they were added; since the verifier adds them as it accepts messages, at their
receive time, and every lifetime is the same freshness window, that order is nearly the
order of their ends.  Expired entries are dropped from the oldest on whenever one is
added, and at most ``max_entries`` are kept: beyond that the oldest goes, expired or not
(:attr:`ReplayCache.evicted` counts the live ones lost that way).  Both operations are
O(1) per entry (:class:`collections.OrderedDict`).
"""

from __future__ import annotations

from collections import OrderedDict


class ReplayCache:
    """A bounded set of message hashes, each with the instant it expires (Time64 µs)."""

    def __init__(self, max_entries: int = 200_000) -> None:
        if max_entries < 1:
            raise ValueError("max_entries must be positive")
        self.max_entries = max_entries
        self.evicted = 0  # entries dropped by the cap before they expired
        self._until: OrderedDict[bytes, int] = OrderedDict()

    def __len__(self) -> int:
        return len(self._until)

    def seen(self, key: bytes, now_us: int) -> bool:
        """Whether ``key`` was added and has not expired at ``now_us``."""
        until = self._until.get(key)
        return until is not None and now_us <= until

    def add(self, key: bytes, until_us: int, now_us: int) -> None:
        """Remember ``key`` until ``until_us``; drop what expired before ``now_us``, and
        the oldest entries beyond :attr:`max_entries`."""
        until = self._until
        while until:
            oldest = next(iter(until))
            if until[oldest] >= now_us:
                break
            del until[oldest]
        until.pop(key, None)  # an expired entry of the same key: renewed, at the end
        until[key] = until_us
        while len(until) > self.max_entries:
            _, end = until.popitem(last=False)
            if end >= now_us:
                self.evicted += 1
