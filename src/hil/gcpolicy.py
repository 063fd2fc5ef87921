"""The daemons' garbage-collection policy: no collection in the middle of a tick.

CPython collects its oldest generation when the objects promoted into it since the last
full pass reach a quarter of it.  An OBU tracking 1,000 RVs holds ~180,000 container
objects (observation windows, path histories, forecasts, and the interpreter's own
modules and functions) and promotes a few thousand per second, so a full pass ran every
~4 s and took 40-90 ms, inside whichever tick allocated the object that triggered it:
``bench/step.py --rvs 1000`` had its p99 at 170 ms for a 66 ms median.

The young generations cost ticks too: at 500 RVs with hgp, a generation-0 pass (about
one a tick) took 0.46 ms and a generation-1 pass (every tenth) 1.9 ms, inside whichever
tick crossed the allocation threshold: ~0.6 ms of a 25 ms median and 2 ms on the ticks
that decide the p99 (measured with ``gc.callbacks``, 200 ticks of ``bench/step.py``).

The policy, the usual one of latency-bound Python services:

* at start-up, after the daemon has built everything it keeps (modules, compiled
  kernels, the CA-TC), ``gc.freeze()`` moves those objects out of every future pass;
* the interpreter's automatic collection is off (``gc.disable()``): no pass ever starts
  inside a tick;
* every pass is the daemon's, right after a tick, in the time before the next one
  (:meth:`GcPolicy.after_tick`): generation 0 after every tick, generations 0-1 after
  every ``young_every``-th (the interpreter's own ratio, 10), a full pass when
  ``full_every_s`` have passed.  Each is timed (``gc_young``, ``gc_young_ms_mean``,
  ``gc_young_ms_max``, ``gc_full``, ``gc_full_ms_max`` in the counters), so the time moved
  out of the ticks is reported, not hidden.

Between ticks a daemon allocates little (a tick's frames), so nothing piles up: the next
tick's pass finds it.  When no tick comes (the HV's channel is quiet while RV frames keep
arriving, malformed ones raising exceptions, whose tracebacks are cycles), the daemon calls
:meth:`GcPolicy.idle` from its status loop: a young pass when none ran for a second.
"""

from __future__ import annotations

import gc
import time


class GcPolicy:
    """See the module docstring.  Construct it once the daemon's start-up is done."""

    def __init__(self, full_every_s: float = 60.0, young_every: int = 10) -> None:
        self.full_every_s = full_every_s
        self.young_every = young_every
        self.full = 0
        self.full_ms_max = 0.0
        self.young = 0
        self.young_ms_total = 0.0
        self.young_ms_max = 0.0
        gc.collect()
        gc.freeze()
        self._enabled = gc.isenabled()
        gc.disable()
        self._last = self._last_pass = time.monotonic()

    def restore(self) -> None:
        """Undo it: automatic collection as before, nothing frozen (a bench's next run)."""
        if self._enabled:
            gc.enable()
        gc.unfreeze()

    def after_tick(self) -> None:
        """The passes due after a tick (call it when a tick's work is done)."""
        now = self._last_pass = time.monotonic()
        t0 = time.perf_counter()
        if now - self._last >= self.full_every_s:
            gc.collect()
            self.full_ms_max = max(self.full_ms_max, (time.perf_counter() - t0) * 1e3)
            self.full += 1
            self._last = time.monotonic()
            return
        self.young += 1
        gc.collect(1 if self.young % self.young_every == 0 else 0)
        ms = (time.perf_counter() - t0) * 1e3
        self.young_ms_total += ms
        self.young_ms_max = max(self.young_ms_max, ms)

    def idle(self, after_s: float = 1.0) -> None:
        """A young pass (counted as one after a tick) when none ran for ``after_s``."""
        if time.monotonic() - self._last_pass >= after_s:
            self.after_tick()

    def reset_counters(self) -> None:
        """Start the counts again (a bench's timed part after its warm-up)."""
        self.full = self.young = 0
        self.full_ms_max = self.young_ms_total = self.young_ms_max = 0.0

    def counters(self) -> dict[str, float]:
        return {"gc_full": self.full, "gc_full_ms_max": round(self.full_ms_max, 3),
                "gc_young": self.young,
                "gc_young_ms_mean": round(self.young_ms_total / max(self.young, 1), 3),
                "gc_young_ms_max": round(self.young_ms_max, 3)}
