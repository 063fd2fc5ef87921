"""Warning events with hysteresis, shared by every safety application.

An application decides at every tick, per RV, whether its warning condition holds (the
"output" that FCW accuracy is scored on).  :class:`WarningMonitor` turns those flags into
start/end events a driver would see, suppressing flicker; the policy is in its docstring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["AppEvent", "AppWarning", "WarningMonitor"]


@dataclass(frozen=True)
class AppEvent:
    """A warning episode for one RV; ``t_end`` is None while it is still open."""

    kind: str  # "start" or "end"
    rv_id: object
    t_start: float
    t_end: float | None = None
    app: str = ""  # the application that raised it ("fcw", "eebl", "bsw", "lcw")


@dataclass
class _RvState:
    on_count: int = 0  # consecutive warn ticks while idle
    first_on_t: float | None = None  # time of the first of those ticks
    active_start: float | None = None  # t_start of the open event
    last_true_t: float | None = None  # last tick with warn=True while open
    false_since: float | None = None  # first warn=False tick of the current gap


@dataclass
class WarningMonitor:
    """Turns per-tick warn flags into start/end events per RV, with hysteresis (every app).

    Pure: the caller passes the time ``t`` (s, non-decreasing per RV).

    * **Start:** after ``warn`` has been True on ``on_ticks`` consecutive updates of
      that RV; ``t_start`` is the time of the first of those ticks.
    * **End:** once ``warn`` has been False for ``off_time`` seconds, i.e. at an
      update with ``t - (first False tick of the gap) >= off_time``; ``t_end`` is the
      first False tick of the gap (when the warning condition actually stopped).
      A True tick within the gap cancels it (flicker), and the event goes on.

    ``off_time`` defaults to 0.5 s: five ticks at the 10 Hz BSM/FCW rate.  A range
    hovering at r_w (measurement noise, a lost BSM) flips ``warn`` for a tick or two;
    without a hold-off each flip would end the event and start a new one, inflating
    warning counts and chopping their durations.  0.5 s is short against the t_d of
    t_d, so a real release is still reported promptly.
    """

    app: str = ""
    on_ticks: int = 1
    off_time: float = 0.5
    _rv: dict[object, _RvState] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.on_ticks < 1:
            raise ValueError("on_ticks must be >= 1")
        if not (math.isfinite(self.off_time) and self.off_time >= 0.0):
            raise ValueError("off_time must be finite and >= 0")

    def update(self, t: float, rv_id: object, warn: bool) -> list[AppEvent]:
        """Feed one tick for ``rv_id``; returns the events it produced (0 or 1)."""
        st = self._rv.setdefault(rv_id, _RvState())
        if st.active_start is None:  # idle
            if not warn:
                st.on_count, st.first_on_t = 0, None
                return []
            if st.on_count == 0:
                st.first_on_t = t
            st.on_count += 1
            if st.on_count < self.on_ticks:
                return []
            assert st.first_on_t is not None
            st.active_start, st.last_true_t, st.false_since = st.first_on_t, t, None
            st.on_count, st.first_on_t = 0, None
            return [AppEvent("start", rv_id, st.active_start, None, self.app)]
        # event open
        if warn:
            st.last_true_t, st.false_since = t, None
            return []
        if st.false_since is None:
            st.false_since = t
        if t - st.false_since >= self.off_time:
            ev = AppEvent("end", rv_id, st.active_start, st.false_since, self.app)
            self._rv[rv_id] = _RvState()
            return [ev]
        return []

    @property
    def tracking(self) -> bool:
        """Some RV has state: an open event, or warning ticks counting towards one."""
        return bool(self._rv)

    def open_events(self) -> dict[object, float]:
        """rv_id -> t_start of the events still open (e.g. at the end of a capture)."""
        return {k: s.active_start for k, s in self._rv.items() if s.active_start is not None}

    def close_absent(self, t: float, present: set) -> list[AppEvent]:
        """Feed ``warn=False`` at ``t`` for every RV with state that is not in ``present``.

        An RV that left the map (evicted, or no longer a candidate of the app) must still
        see its open event end after ``off_time``.
        """
        out: list[AppEvent] = []
        if not self._rv:  # the usual tick: no RV has state
            return out
        for rv_id in [k for k in self._rv if k not in present]:
            out += self.update(t, rv_id, False)
            if self._rv.get(rv_id) == _RvState():
                del self._rv[rv_id]
        return out


@dataclass(frozen=True, slots=True)
class AppWarning:
    """One application's warning condition holding for one RV at one tick.

    ``range_m``: the distance the app judged (FCW: the bumper-to-bumper gap along the HV
    path; EEBL: the RV's distance ahead); ``threshold_m``: the range it compared with
    (FCW: r_w), NaN when the app has none; ``side``: ``"left"`` / ``"right"`` for
    BSW/LCW, else ``""``.
    """

    app: str
    rv_id: int
    range_m: float = math.nan
    threshold_m: float = math.nan
    side: str = ""
