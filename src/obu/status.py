"""What the OBU tells of itself: the counters and step times it keeps, the status line on
stderr every second, the live view's panel, the final counters, and log lines that a flood
cannot multiply."""

from __future__ import annotations

import sys
import time
from collections import Counter, deque
from typing import Any

import numpy as np

__all__ = ["RateLimitedLog", "Status"]


class RateLimitedLog:
    """At most one stderr line per key per second (a flood of garbage must not flood)."""

    def __init__(self) -> None:
        self.last: dict[str, float] = {}
        self.suppressed: Counter[str] = Counter()

    def __call__(self, key: str, message: str) -> None:
        now = time.monotonic()
        if now - self.last.get(key, -1e9) < 1.0:
            self.suppressed[key] += 1
            return
        extra = f" (+{self.suppressed.pop(key)} more)" if self.suppressed.get(key) else ""
        self.last[key] = now
        print(f"obu: {message}{extra}", file=sys.stderr, flush=True)


class Status:
    """The OBU's counters (by name: ``frames``, ``decode_<reason>``, ``verify_<verdict>``,
    ``mbd_<check>``, ``ticks``, ``deadline_misses``, ``events_<app>`` ...) and its step
    times."""

    def __init__(self) -> None:
        self.counters: Counter[str] = Counter()
        self.step_ms: deque[float] = deque(maxlen=6000)  # the last 10 min of ticks
        self.frames_per_s = 0.0  # in the last second, for the live view's panel

    def line(self, frames_per_s: float, tracked: int) -> str:
        """The status line: frames/s, decode errors, tracked RVs, tick time p99, deadline
        misses, warning events."""
        p99 = float(np.percentile(self.step_ms, 99)) if self.step_ms else 0.0
        c = self.counters
        events = sum(v for k, v in c.items() if k.startswith("events_"))
        return (f"obu: {frames_per_s:7.0f} frames/s  decode errors {c['decode_errors']}  "
                f"tracked {tracked}  tick p99 {p99:.1f} ms  deadline misses "
                f"{c['deadline_misses']}  warning events {events}")

    def panel(self, tentative: int) -> dict[str, Any]:
        """The live view's panel (after a step, so ``step_ms`` has a time)."""
        c = self.counters
        recent = list(self.step_ms)[-600:]  # the last minute of ticks
        return {"frames_per_s": round(self.frames_per_s), "decode_errors":
                c["decode_errors"], "rejected": c["verify_rejected"] + c["mbd_quarantined"],
                "tick_p50": round(float(np.percentile(recent, 50)), 2),
                "tick_p99": round(float(np.percentile(recent, 99)), 2),
                "deadline_misses": c["deadline_misses"], "tentative": tentative}

    def all_counters(self, pending: int, tentative: int, cam_counters: dict[str, int],
                     transport_stats: dict[str, int], gc_counters: dict[str, Any] | None
                     ) -> dict[str, Any]:
        """Every counter (``obu.counters.json`` and the last line on stderr): the OBU's,
        the messages still ``pending`` a tick, the CAM's (``cam_``), the transport's
        (``transport_``), the collector's, and the step time percentiles."""
        out: dict[str, Any] = dict(self.counters)
        out["pending"] = pending  # received, not yet due at a tick
        out["cam_tentative"] = tentative
        out.update({f"cam_{k}": v for k, v in cam_counters.items()})
        out.update({f"transport_{k}": v for k, v in transport_stats.items()})
        if gc_counters is not None:
            out.update(gc_counters)
        if self.step_ms:
            out["tick_ms_p50"] = round(float(np.percentile(self.step_ms, 50)), 3)
            out["tick_ms_p99"] = round(float(np.percentile(self.step_ms, 99)), 3)
            out["tick_ms_max"] = round(float(max(self.step_ms)), 3)
        return out
