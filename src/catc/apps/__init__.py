"""Cooperative safety applications on the CA-TC's map (pure library code: no I/O, no clocks).

Each application is a function ``app(snapshot, config) -> list[AppWarning]``: the
conditions that hold at this tick (what FCW accuracy is scored on).  :class:`SafetyApps`
runs them all on every :class:`catc.cam.MapSnapshot` and turns the per-tick conditions
into start/end events with one :class:`~catc.apps.events.WarningMonitor` per application
(hysteresis documented there).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from catc.apps.bsw import BswConfig, blind_spot
from catc.apps.eebl import EeblConfig, eebl
from catc.apps.events import AppEvent, AppWarning, WarningMonitor
from catc.apps.fcw import FcwConfig, forward_collision
from catc.cam._snapshot import rows_of

__all__ = ["APPS", "AppEvent", "AppWarning", "AppsConfig", "SafetyApps"]

#: Application names, in the order their warnings are listed.
APPS = ("fcw", "eebl", "bsw", "lcw")


@dataclass(frozen=True)
class AppsConfig:
    fcw: FcwConfig = field(default_factory=FcwConfig)
    eebl: EeblConfig = field(default_factory=EeblConfig)
    bsw: BswConfig = field(default_factory=BswConfig)
    #: Which applications run.
    enabled: tuple[str, ...] = APPS
    #: Hysteresis of every event monitor (see WarningMonitor).
    on_ticks: int = 1
    off_time: float = 0.5

    def __post_init__(self) -> None:
        unknown = set(self.enabled) - set(APPS)
        if unknown:
            raise ValueError(f"unknown application(s) {sorted(unknown)}; known: {APPS}")


class SafetyApps:
    """Runs the enabled applications on each snapshot: ``apps(snapshot) -> (warnings,
    events)``; pass it to :class:`catc.cam.ContextAwareMap` as ``apps``.  ``muted``: RV
    ids on which no warning is raised (set by the caller before a step: the unconfirmed
    newcomers of :meth:`catc.mbd.MisbehaviorDetector.muted`)."""

    #: RV ids whose warnings are withheld (their tracks are kept and classified).
    muted: frozenset[int] = frozenset()

    def __init__(self, config: AppsConfig | None = None) -> None:
        self.config = config or AppsConfig()
        c = self.config
        self.monitors = {a: WarningMonitor(app=a, on_ticks=c.on_ticks, off_time=c.off_time)
                         for a in c.enabled}
        self._fcw, self._eebl = "fcw" in c.enabled, "eebl" in c.enabled
        self._side = "bsw" in c.enabled or "lcw" in c.enabled

    def __call__(self, snap) -> tuple[list[AppWarning], list[AppEvent]]:
        c = self.config
        found: list[AppWarning] = []
        verified = getattr(snap, "verified", None)
        if verified is not None and not verified.all():  # unverified rows: not seen
            snap = rows_of(snap, verified)
        if self._fcw:
            found += forward_collision(snap, c.fcw)
        if self._eebl:
            found += eebl(snap, c.eebl)
        if self._side:
            side = blind_spot(snap, c.bsw)
            if side:
                found += [w for w in side if w.app in c.enabled]
        if self.muted and found:
            found = [w for w in found if w.rv_id not in self.muted]
        events: list[AppEvent] = []
        for app, mon in self.monitors.items():
            if not (found or mon.tracking):  # the usual tick: nothing to update or close
                continue
            on = {w.rv_id for w in found if w.app == app}
            for rv_id in sorted(on):
                events += mon.update(snap.t, rv_id, True)
            events += mon.close_absent(snap.t, on)
        return found, events
