"""The quarantine rule: which senders' tracks must raise no warning, and until when.

A sender is quarantined when ``quarantine_k`` of its messages fail within
``quarantine_window_s`` (a message counts once, however many checks it fails: a single
GNSS glitch is one failed message), or at once on a strong finding (:func:`is_strong`: a
sudden appearance inside the host's safety range, an intersection, a Sybil).  The
quarantine lasts ``quarantine_s`` from the last detection and is renewed by every new one;
after a strong finding, with ``sticky_strong``, by every message of the sender too (a
fabricated vehicle does not become real by behaving consistently afterwards).  The rule is
ours, not F2MD's; docs/mbd.md explains it.
"""

from __future__ import annotations

from collections import OrderedDict

from catc.mbd.checks import Detection
from catc.mbd.config import MbdConfig
from catc.mbd.state import Sender

__all__ = ["Quarantine", "is_strong"]


def is_strong(d: Detection, c: MbdConfig) -> bool:
    """Whether ``d`` quarantines its sender at once: an intersection, a Sybil, or a sudden
    appearance inside the host's safety range (where a ghost can trigger a forward
    collision warning)."""
    check = d.check
    return check == "intersection" or check == "sybil" or (
        check == "sudden-appearance" and d.evidence["distance_m"] < c.sa_safety_range_m)


class Quarantine:
    """The senders in quarantine (at most ``max_senders``, the oldest forgotten first)."""

    def __init__(self, config: MbdConfig, max_senders: int) -> None:
        self.config = config
        self.max_senders = max_senders
        self._until: OrderedDict[int, float] = OrderedDict()  # id -> until (s)

    def __len__(self) -> int:
        return len(self._until)

    def quarantined(self, tid: int, t: float) -> bool:
        """Whether ``tid`` is in quarantine at ``t``."""
        until = self._until.get(tid)
        return until is not None and t < until

    def punish(self, st: Sender, t: float, strong: bool) -> bool:
        """A message of ``st`` received at ``t`` failed (``strong``: a strong finding):
        count the strike and quarantine or renew; True when ``st`` enters quarantine."""
        c = self.config
        until = self._until.get(st.tid)
        active = until is not None and t < until
        strikes = [s for s in st.strikes if t - s < c.quarantine_window_s]
        strikes.append(t)
        st.strikes = strikes[-c.quarantine_k:]
        if strong or len(strikes) >= c.quarantine_k or active:
            st.strong = st.strong or strong
            self._set(st.tid, t + c.quarantine_s)
            return not active
        return False

    def passed(self, st: Sender, t: float) -> None:
        """A message of ``st`` received at ``t`` passed every check: it renews a
        quarantine on a strong finding (``sticky_strong``)."""
        if st.strong and self.config.sticky_strong and self.quarantined(st.tid, t):
            self._set(st.tid, t + self.config.quarantine_s)

    def _set(self, tid: int, until: float) -> None:
        q = self._until
        q[tid] = until
        q.move_to_end(tid)
        while len(q) > self.max_senders:
            q.popitem(last=False)
