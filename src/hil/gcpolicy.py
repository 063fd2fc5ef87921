"""The daemons' garbage-collection policy: no full collection in the middle of a tick.

CPython collects its oldest generation when the objects promoted into it since the last
full pass reach a quarter of it.  An OBU tracking 1,000 RVs holds ~180,000 container
objects (observation windows, path histories, forecasts, and the interpreter's own
modules and functions) and promotes a few thousand per second, so a full pass ran every
~4 s and took 40-90 ms, inside whichever tick allocated the object that triggered it:
``bench/step.py --rvs 1000`` had its p99 at 170 ms for a 66 ms median.

The policy, the usual one of latency-bound Python services:

* at start-up, after the daemon has built everything it keeps (modules, compiled
  kernels, the CA-TC), ``gc.freeze()`` moves those objects out of every future pass;
* the young generations are collected as before (cheap; they also find young cycles);
* full passes are the daemon's: :meth:`GcPolicy.after_tick` runs one when ``full_every_s``
  have passed, right after a tick, in the time before the next one; each is timed
  (``gc_full``, ``gc_full_ms_max`` in the counters).
"""

from __future__ import annotations

import gc
import time

#: Generation-2 threshold that the interpreter never reaches (a count of generation-1
#: passes): only :meth:`GcPolicy.after_tick` starts full passes.
_NEVER = 1 << 30


class GcPolicy:
    """See the module docstring.  Construct it once the daemon's start-up is done."""

    def __init__(self, full_every_s: float = 60.0) -> None:
        self.full_every_s = full_every_s
        self.full = 0
        self.full_ms_max = 0.0
        gc.collect()
        gc.freeze()
        self._threshold = gc.get_threshold()
        gc.set_threshold(self._threshold[0], self._threshold[1], _NEVER)
        self._last = time.monotonic()

    def restore(self) -> None:
        """Undo it: the interpreter's thresholds, nothing frozen (a bench's next run)."""
        gc.set_threshold(*self._threshold)
        gc.unfreeze()

    def after_tick(self) -> None:
        """A full pass when one is due (call it when a tick's work is done)."""
        now = time.monotonic()
        if now - self._last < self.full_every_s:
            return
        t0 = time.perf_counter()
        gc.collect()
        self.full_ms_max = max(self.full_ms_max, (time.perf_counter() - t0) * 1e3)
        self.full += 1
        self._last = time.monotonic()

    def counters(self) -> dict[str, float]:
        return {"gc_full": self.full, "gc_full_ms_max": round(self.full_ms_max, 3)}
