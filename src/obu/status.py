"""What the OBU tells of itself: the counters and step times it keeps, the status line on
stderr every second, the live view's panel, the final counters, and log lines that a flood
cannot multiply."""

from __future__ import annotations

import math
import sys
import time
from collections import Counter, deque
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["Lags", "RateLimitedLog", "Status"]


class Lags:
    """Lags in ms (a frame's arrival to the decision of the tick that used it) as a
    histogram of bins 1 % wide from :data:`LOW` ms to 1,000 s: percentiles of a whole run
    in bounded memory, to within 1 %."""

    LOW = 0.01  # ms: the first bin's lower edge; smaller lags count there
    RATIO = 1.01  # a bin's upper edge over its lower
    BINS = math.ceil(math.log(1e6 / LOW) / math.log(RATIO)) + 1  # to 1,000 s, then one more

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, np.int64)
        self.n = 0
        self.max = 0.0

    def add(self, ms: Sequence[float] | np.ndarray) -> None:
        a = np.asarray(ms, dtype=np.float64)
        if not a.size:
            return
        a = a[np.isfinite(a)]
        k = np.log(np.maximum(a, self.LOW) / self.LOW) / math.log(self.RATIO)
        np.add.at(self.counts, np.minimum(k.astype(np.int64), self.BINS - 1), 1)
        self.n += a.size
        self.max = max(self.max, float(a.max(initial=0.0)))

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (ms), a bin's geometric middle; 0 with no lag yet."""
        if not self.n:
            return 0.0
        k = int(np.searchsorted(np.cumsum(self.counts), q / 100.0 * self.n))
        if k == 0:
            return self.LOW
        return min(self.LOW * self.RATIO ** (k + 0.5), self.max)

    def clear(self) -> None:
        self.counts[:] = 0
        self.n = 0
        self.max = 0.0


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
        #: RV messages' lag, arrival to decision: the whole run, and since the last
        #: status line; the host frames' too (a tick's own lateness).
        self.lag, self.lag_recent, self.host_lag = Lags(), Lags(), Lags()
        self.backlog: dict[str, int] = {}  # the receiver's, at the last status line

    def line(self, frames_per_s: float, tracked: int) -> str:
        """The status line: frames/s, decode errors, tracked RVs, tick time p99, the lag
        since the last line (p50/p99), the receive queue, deadline misses, warning
        events."""
        p99 = float(np.percentile(self.step_ms, 99)) if self.step_ms else 0.0
        c, b, lag = self.counters, self.backlog, self.lag_recent
        events = sum(v for k, v in c.items() if k.startswith("events_"))
        return (f"obu: {frames_per_s:7.0f} frames/s  decode errors {c['decode_errors']}  "
                f"tracked {tracked}  tick p99 {p99:.1f} ms  lag p50 "
                f"{lag.percentile(50):.1f} p99 {lag.percentile(99):.1f} ms  queue "
                f"{b.get('queued', 0)} + {b.get('socket_bytes', 0) // 1024} kB  deadline "
                f"misses {c['deadline_misses']}  warning events {events}")

    def panel(self, tentative: int) -> dict[str, Any]:
        """The live view's panel (after a step, so ``step_ms`` has a time)."""
        c = self.counters
        recent = list(self.step_ms)[-600:]  # the last minute of ticks
        return {"frames_per_s": round(self.frames_per_s), "decode_errors":
                c["decode_errors"], "rejected": c["verify_rejected"] + c["mbd_quarantined"],
                "tick_p50": round(float(np.percentile(recent, 50)), 2),
                "tick_p99": round(float(np.percentile(recent, 99)), 2),
                "lag_p50": round(self.lag_recent.percentile(50), 2),
                "lag_p99": round(self.lag_recent.percentile(99), 2),
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
        for name, lags in (("lag", self.lag), ("host_lag", self.host_lag)):
            if lags.n:
                out[f"{name}_ms_p50"] = round(lags.percentile(50), 3)
                out[f"{name}_ms_p99"] = round(lags.percentile(99), 3)
                out[f"{name}_ms_max"] = round(lags.max, 3)
        out.update({f"rx_{k}": v for k, v in self.backlog.items()})
        return out
