"""Time from secMark: a BSM's generation time, and the HV's clock across minute rollovers.

J2735 DSecond ``secMark`` is the milliseconds within the UTC minute (0-59999), so a BSM
carries no date and a receiver must place it against its own time (:mod:`catc.cam`,
step 1).
"""

from __future__ import annotations

from catc.bsm import MINUTE_MS
from catc.bsm import sec_mark as bsm_sec_mark


def message_time(now: float, sec_mark: int) -> float:
    """Generation time of a BSM with ``sec_mark`` (ms within the minute) seen at ``now``.

    The age is ``(secMark(now) - sec_mark) mod 60000`` ms, so a message from second 59.9
    read at second 0.1 of the next minute is 0.2 s old.  secMark cannot tell an age of
    40 s from one of -20 s: ages over 30 s are read as from the future (a clock offset),
    and the result is then after ``now``.  Either reading is rejected by the CAM (late or
    future), since ``stale_after_s`` is at most 30 s.
    """
    age_ms = (bsm_sec_mark(now) - sec_mark) % MINUTE_MS
    if age_ms > MINUTE_MS // 2:
        age_ms -= MINUTE_MS
    return now - age_ms / 1000.0


class SecMarkClock:
    """The HV's time in seconds from its BSMs' secMarks, across minute rollovers.

    The OBU knows no date: its clock is the host vehicle's (DESIGN.md).  The first secMark
    sets the origin (``t = secMark / 1000`` there); a secMark more than 30 s below the
    previous one starts the next minute.  The live OBU and the offline simulator both
    take ``now`` from here, so they step the CAM at identical times; the clock differs
    from the dataset's own time by a whole number of minutes (:attr:`minutes`).
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self.minutes = 0

    def __call__(self, sec_mark: int) -> float:
        if self._last is not None and sec_mark < self._last - 30_000:
            self.minutes += 1
        self._last = sec_mark
        return (self.minutes * 60_000 + sec_mark) / 1000.0

