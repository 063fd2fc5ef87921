"""Real-time pacing against absolute deadlines (no drift), with a speed factor.

Dataset time ``t`` is due at ``start + (t - t0) / speed`` on the monotonic clock.  Each
wait is computed from that absolute deadline, never from the previous wake-up, so errors
do not accumulate over a long replay.  The wait sleeps with asyncio until
``spin_s`` before the deadline and then spins on the clock: asyncio's timer resolution
(about 1 ms) alone would put every frame up to a millisecond late.  ``speed=None`` is
as fast as possible (no waiting).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

__all__ = ["Pacer"]


class Pacer:
    """Deadlines for dataset times; :meth:`wait` returns how late the wake-up was (s)."""

    def __init__(self, t0: float, speed: float | None = 1.0, spin_s: float = 0.002,
                 clock: Callable[[], float] = time.monotonic,
                 start: float | None = None) -> None:
        """``t0`` is due at ``start`` on ``clock`` (default: now)."""
        if speed is not None and not speed > 0.0:
            raise ValueError(f"speed factor must be > 0, got {speed}")
        self.t0 = t0
        self.speed = speed
        self.spin_s = spin_s
        self.clock = clock
        self.start = clock() if start is None else start

    def deadline(self, t: float) -> float:
        """Monotonic-clock time at which dataset time ``t`` is due."""
        if self.speed is None:
            return self.clock()
        return self.start + (t - self.t0) / self.speed

    async def wait(self, t: float) -> float:
        """Sleep until dataset time ``t`` is due; the lateness of the wake-up in s (>= 0
        when on time or late; a frame is never sent early)."""
        if self.speed is None:
            await asyncio.sleep(0)
            return 0.0
        due = self.deadline(t)
        ahead = due - self.clock()
        if ahead > self.spin_s:
            await asyncio.sleep(ahead - self.spin_s)
        while self.clock() < due:
            pass
        return self.clock() - due
