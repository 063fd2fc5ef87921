"""The OBU's tick rule: which frames a host frame's step takes, and when it steps.

A step at host frame ``T`` takes every RV message received so far that was generated at
or before ``T`` (:func:`catc.replay.split_due`, the offline simulator's rule too); newer
ones wait for a later tick.  Before stepping it takes every frame that reached the
receiver before the host frame (in the OBU's queue, or still in the receiver's queue or
socket buffer: :meth:`hil.transport.Receiver.waiting`) for up to :data:`DRAIN_S` (50 ms),
then lets the RV channel go quiet (no RV frame for :data:`QUIET_S`) for up to
``--collect-ms``, and it stops at the next host frame that the host channel believes
(:class:`obu.host.HostGate`): a frame at the host port that is not believed is taken,
counted and dropped like garbage, and the collection goes on.  So frames sent just before the
host's are in its tick, as a radio's would be within one 100 ms slot: which tick a frame
joins depends on the order of the frames, not on how fast the OBU reads them.

:class:`TickRule` is the second half as a pure object, like h11's connection: the event
loop (:func:`obu.run.serve`) tells it when a host frame starts a tick and when an RV frame
arrives, and asks it, with the time and what is waiting, what to do next: :data:`TAKE`
the next frame of the queue (when it is a believed host frame, the loop calls
:meth:`TickRule.next_host` and steps), :data:`WAIT` (yield to the event loop, which reads
the sockets, then ask again) or :data:`STEP` now.  It reads no clock and touches no socket, so
a test drives it with a fake clock.
"""

from __future__ import annotations

import enum
from typing import Literal

__all__ = ["DRAIN_S", "QUIET_S", "STEP", "TAKE", "TICK_S", "WAIT", "Action", "TickRule"]

#: The host's BSM period: a step slower than this misses its deadline.
TICK_S = 0.1

#: The longest a tick waits (s) for the frames that reached the receiver before its host
#: frame, when that is longer than --collect-ms: half the 100 ms tick period, so a flood
#: delays a tick but never stops it.
DRAIN_S = 0.05

#: The RV channel is quiet once no RV frame has arrived for this long (s).
QUIET_S = 0.001


class Action(enum.Enum):
    """What the event loop does next while a tick collects its frames."""

    TAKE = "take"  #: handle the next frame of the queue
    WAIT = "wait"  #: yield to the event loop (it reads the sockets), then ask again
    STEP = "step"  #: step the CAM at the host frame now


TAKE, WAIT, STEP = Action.TAKE, Action.WAIT, Action.STEP


class TickRule:
    """When the step at a host frame happens (see the module docstring).

    Times are seconds on any monotonic clock, given by the caller.  :meth:`rv_frame` at
    every RV frame handled (decodable or not: the channel is not quiet), :meth:`host_frame`
    when a host frame starts a tick, then :meth:`next` until it answers :data:`STEP`.
    """

    def __init__(self, collect_ms: float, drain_s: float = DRAIN_S,
                 quiet_s: float = QUIET_S) -> None:
        #: ``--collect-ms`` in s: the longest wait for the RV channel to go quiet.
        self.collect_s = max(0.0, collect_ms) / 1000.0
        self.drain_s = drain_s
        self.quiet_s = quiet_s
        self.last_rv = 0.0  # when the newest RV frame was handled
        self.deadline: float | None = None  # collecting: quiet or not, step from then on
        self.limit: float | None = None  # collecting: step from then on, whatever waits

    def rv_frame(self, now: float) -> None:
        """An RV frame was handled at ``now``."""
        self.last_rv = now

    def host_frame(self, now: float) -> None:
        """A host frame that starts a tick was handled at ``now``: collect its frames."""
        self.deadline = now + self.collect_s
        self.limit = now + max(self.collect_s, self.drain_s)

    def next(self, now: float, head: Literal["rv", "host"] | None, waiting: bool) -> Action:
        """What to do at ``now``, with ``head`` the channel of the next frame in the
        OBU's queue (None when it is empty) and ``waiting`` whether a frame still waits in
        the receiver (only asked when the queue is empty)."""
        if self.limit is None or self.deadline is None:
            raise RuntimeError("no host frame is collecting its frames")
        if head is not None:  # an RV frame, or a host frame that may not be believed
            return TAKE
        if now >= self.limit:
            return self._step()
        if waiting:
            return WAIT
        if now >= self.deadline or now - self.last_rv > self.quiet_s:
            return self._step()
        return WAIT

    def next_host(self) -> Action:
        """The frame just taken was a believed host frame: this tick steps now (the
        next starts at that frame)."""
        if self.limit is None:
            raise RuntimeError("no host frame is collecting its frames")
        return self._step()

    def _step(self) -> Action:
        self.deadline = self.limit = None
        return STEP
