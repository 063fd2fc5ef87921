"""Signing ahead of the schedule (``rve run --sign PKI_DIR --sign-workers N``).

An RVE that signs every BSM in its sending loop falls behind at 1,000 RVs (10,000
ECDSA P-256 signatures/s, issue 30).  The schedule is known before the run
(:func:`catc.replay.plan`) and each frame's IEEE 1609.2 generationTime is its wall-clock
deadline (``start + (due - t0) / speed``), so the signatures can be made before they are
due:

* The decisions stay in the main process, in schedule order, as on the inline path:
  :meth:`rve.signing.Signer.decide` (which pseudonym, full certificate or digest), and
  the UPER encoding of the BSM.  A run's frames are those of the inline path apart from
  the signature octets (ECDSA is randomized anyway).
* The ECDSA and the envelopes are made by a pool of worker processes (``spawn``; each
  loads the PKI once from its directory, :func:`hil.pki.load`), one batch per deadline
  (a 10 Hz tick), handed out ``--sign-lookahead`` s of schedule ahead of the sending
  loop.  The loop only takes finished frames.
* Before the clock starts, the first lookahead window is prepared and its signing
  time estimated from the workers' own warm-up rate; the clock starts when that much
  time has passed, so the first frames do not wait.
* A batch not finished at its deadline is waited for (``sign_ahead_waits``, the longest
  wait ``sign_ahead_wait_ms_max``): a frame is never sent unsigned, only late.

Not ahead: ``--asap`` (no deadline to sign for) and ``--attack`` runs (the attackers'
frames and the security attacks change or replay signed frames as they are made), which
sign inline as before, and ``--sign-workers 0``.

The workers run at a lower priority (``nice`` +10): they have the lookahead to catch up,
the sending loop and an OBU on the same cores do not.

How many workers: one (the default), measured on this 2-core machine with the OBU
beside (``bench/obu_load.py --rvs 500,1000 --per 0 --predictors hgp --verify on,signed
--seconds 15 --sign-workers 0,1,2``, 2026-12-06; workers 0 is the inline path, the old
code; "on": the OBU verifies every frame, "signed": it does not).  RVE CPU is the sending
process's + its workers', in % of a core (the rows of 1 and 2 workers from a second run,
with the workers at nice +10)::

    RVs   verify  workers  RVE late p99/max ms  RVE CPU %  socket loss  tick p99 ms
    500   on      0          6.6 /  54.6         42 + 0     0            54.0
    500   on      1          6.2 /   7.1         18 + 21    0            53.5
    500   on      2          6.3 /   7.4         17 + 24    0            41.1
    500   signed  0          7.3 /  55.4         46 + 0     0            58.4
    500   signed  1          7.6 /  10.6         19 + 22    0            53.0
    500   signed  2          6.6 /   7.3         19 + 27    0            45.8
    1000  on      0        300.9 / 311.3         91 + 0     0           117.7
    1000  on      1         13.5 /  17.2         33 + 39    0           101.1
    1000  on      2         14.0 /  18.3         32 + 43    0            98.5
    1000  signed  0         74.9 / 112.6         77 + 0     0            90.2
    1000  signed  1         13.3 /  17.7         31 + 36    0           111.1
    1000  signed  2         14.6 /  22.1         32 + 42    0            96.7

No batch was waited for in any run (``sign_ahead_waits`` 0).  One worker signs 10,000
BSMs/s with 39 % of a core, 2.5 times what 1,000 RVs need; a second one adds no
lateness margin and costs CPU that the OBU needs.  Without ``nice`` the workers took the
sending loop's core away during its bursts: 1,000 RVs verified, p99 17.3 ms with one
worker and 27.9 ms with two.

The rest of the lateness was the sending loop itself: every RV frame of a 10 Hz tick is
due at the same instant, and asyncio-dgram's send took 7 us a frame (its drained event
awaited after each), so the p99 frame of a 1,000-frame burst left 7 ms late before any
contention.  :meth:`hil.transport.Sender.send_many` puts a burst onto the datagram
transport back to back (3.5 us a frame); after it, with one worker (same bench, rows
where the rest of the machine used under 5 % of a core)::

    RVs   verify  workers  RVE late p99/max ms  RVE CPU %  socket loss  tick p99 ms
    1000  on      1          7.4 /  10.9         24 + 34    0            77.9
    1000  signed  1          7.2 /  10.7         26 + 34    0            75.1
    1000  on      0        110.9 / 125.3         75 + 0     0            80.3

and in a second run, the machine otherwise idle throughout::

    500   on      1          8.9 /  32.0         18 + 24    0            53.7
    500   signed  1          3.9 /   6.5         18 + 23    0            55.1
    1000  on      1         10.4 /  13.4         29 + 39    0            81.6
    1000  signed  1         10.1 /  12.6         29 + 38    0            96.6

No batch was waited for.  Issue 30's 5 ms p99 is not met at 1,000 RVs (7-10 ms): the
burst of 1,000 sends is 3.5 ms on an idle core, and the OBU's ticks preempt it.

Under foreign load the niced worker is the one that loses: with a VM test taking a
whole core meanwhile, 1,000 RVs verified gave 137 waited batches (the longest 429 ms)
and seconds of lateness, as the inline path did (4.5 s, signed, with the same load).
Nothing on 2 cores keeps 10,000 signed BSMs/s, their verification and a third busy
process on time; a benchmark run must have the machine to itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import os
import signal
import time
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

from catc.j2735 import encode_frame
from catc.replay import Plan
from rve.framing import encode_event, wrap
from rve.signing import Signer

__all__ = ["SignAhead", "sign_ahead"]

#: how much lower a worker's priority is than the sending loop's (os.nice): the workers
#: have the lookahead to catch up, the sending loop and an OBU on the same cores do not
_NICE = 10

#: the worker's pseudonyms ((certificate, key) by index), loaded by :func:`_init`
_PSEUDONYMS: tuple = ()


def _init(directory: str) -> None:
    """A worker's start: the PKI's pseudonyms, once; ^C is the main process's to handle."""
    global _PSEUDONYMS
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):  # the sending loop and the OBU come first
        os.nice(_NICE)
    from hil.pki import load

    _PSEUDONYMS = load(directory).pseudonyms


def _warm_up(n: int) -> float:
    """Seconds per signature in this worker, over ``n`` signatures."""
    from catc.security import sign_bsm

    cert, key = _PSEUDONYMS[0]
    frame = bytes(40)
    t = time.perf_counter()
    for _ in range(n):
        sign_bsm(frame, key, cert, 0, include_cert=False)
    return (time.perf_counter() - t) / n


def _sign(framing: str, gen64: int, jobs: list[tuple[int, bytes, bool]]) -> list[bytes]:
    """The wire frames of one batch: each (pseudonym index, UPER frame, full certificate)
    signed with generationTime ``gen64`` and wrapped as ``framing`` says."""
    from catc.security import sign_bsm

    out = []
    for k, frame, full in jobs:
        cert, key = _PSEUDONYMS[k]
        out.append(wrap(frame, framing, sign_bsm(frame, key, cert, gen64, include_cert=full)))
    return out


class SignAhead:
    """The replay's frames, tick by tick, signed by ``workers`` processes ``lookahead_s``
    of schedule ahead (module docstring).  :meth:`prime` before the clock, :meth:`fill`
    before each deadline, :meth:`take` at it; :meth:`close` at the end."""

    def __init__(self, the_plan: Plan, signer: Signer, framing: str, host_bus: bool,
                 workers: int, lookahead_s: float, speed: float) -> None:
        self.plan, self.signer, self.framing = the_plan, signer, framing
        self.host_bus, self.workers = host_bus, workers
        self.lookahead_s, self.speed = lookahead_s, speed
        self.events = the_plan.events
        times = self.events["time"].tolist()
        self.bounds: list[tuple[int, int]] = []
        i, n = 0, len(times)
        while i < n:
            j = i
            while j < n and times[j] == times[i]:
                j += 1
            self.bounds.append((i, j))
            i = j
        self.dues = [times[i] for i, _ in self.bounds]
        self.t0 = self.dues[0] if self.dues else 0.0
        self.next = 0  # the next tick to prepare
        self.wall0 = 0.0  # wall-clock time of t0
        #: tick -> (encoded events, the batch's future or None, positions of its frames)
        self.pending: dict[int, tuple[list, Future | None, list[int]]] = {}
        self.pool: ProcessPoolExecutor | None = None
        self.counts: dict[str, Any] = {"sign_ahead_batches": 0, "sign_ahead_waits": 0,
                                       "sign_ahead_wait_ms_max": 0.0}

    def _prepare(self, k: int) -> tuple[list, list, list[int]]:
        """Tick ``k``'s events: the encoded ones that need no signature, and the jobs of
        the others (decided now, in schedule order) with their positions."""
        plan, signer, framing = self.plan, self.signer, self.framing
        i, j = self.bounds[k]
        encoded: list = []
        jobs: list[tuple[int, bytes, bool]] = []
        where: list[int] = []
        for ev in self.events[i:j]:
            if ev["host"] or ev["dropped"]:
                encoded.append((None, None) if self.host_bus and ev["host"] else
                               encode_event(ev, plan, framing, signer, None, None))
                continue
            v = int(ev["vehicle"])
            frame = encode_frame(plan.bsm(ev))
            full = signer.decide(v, float(ev["t"]))
            where.append(len(encoded))
            encoded.append(None)
            jobs.append((signer.pseudonym[v], frame, full))
        return encoded, jobs, where

    def _submit(self, k: int, encoded: list, jobs: list, where: list[int]) -> None:
        gen64 = self.signer.to_time64(self.wall0 + (self.dues[k] - self.t0) / self.speed)
        fut = self.pool.submit(_sign, self.framing, gen64, jobs) if jobs else None
        if fut is not None:
            self.counts["sign_ahead_batches"] += 1
        self.pending[k] = (encoded, fut, where)

    def prime(self) -> float:
        """Start the workers, prepare the first lookahead window and hand it out; the
        monotonic time at which the clock must start (``t0`` is due) for the window to be
        signed by then.  Counted: ``sign_ahead_lead_s``, from this call to that start, and
        ``sign_ahead_prepare_cpu_s``, this process's CPU time meanwhile (what a load
        measurement leaves out of the run's)."""
        began, cpu0 = time.monotonic(), time.process_time()
        self.pool = ProcessPoolExecutor(self.workers, multiprocessing.get_context("spawn"),
                                        initializer=_init,
                                        initargs=(str(self.signer.directory),))
        per_sig = max(f.result() for f in [self.pool.submit(_warm_up, 200)
                                           for _ in range(self.workers)])
        first = []
        while self.next < len(self.dues) and \
                self.dues[self.next] <= self.t0 + self.lookahead_s:
            first.append((self.next, *self._prepare(self.next)))
            self.next += 1
        n_jobs = sum(len(jobs) for _, _, jobs, _ in first)
        lead = 0.05 + 1.5 * n_jobs * per_sig / self.workers
        start = time.monotonic() + lead
        self.wall0 = time.time() + lead
        for k, encoded, jobs, where in first:
            self._submit(k, encoded, jobs, where)
        self.counts["sign_ahead_lead_s"] = round(start - began, 3)
        self.counts["sign_ahead_prepare_cpu_s"] = round(time.process_time() - cpu0, 3)
        return start

    def fill(self, due: float) -> None:
        """Hand out every tick due within the lookahead of ``due`` (and ``due``'s own)."""
        while self.next < len(self.dues) and (
                self.dues[self.next] <= due + self.lookahead_s or self.dues[self.next] <= due):
            self._submit(self.next, *self._prepare(self.next))
            self.next += 1

    async def take(self, k: int) -> list[tuple[bytes | None, Any]]:
        """Tick ``k``'s (frame, label) per event, once its batch is signed (waited for
        and counted when it is not yet)."""
        encoded, fut, where = self.pending.pop(k)
        if fut is not None:
            if not fut.done():
                t = time.monotonic()
                await asyncio.wrap_future(fut)
                waited = (time.monotonic() - t) * 1e3
                self.counts["sign_ahead_waits"] += 1
                self.counts["sign_ahead_wait_ms_max"] = round(
                    max(self.counts["sign_ahead_wait_ms_max"], waited), 3)
            for pos, frame in zip(where, fut.result(), strict=True):
                encoded[pos] = (frame, None)
        return encoded

    def close(self) -> None:
        """Stop the workers (what they still had to sign is dropped)."""
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None


def sign_ahead(args: Any, the_plan: Plan, signer: Signer | None, framing: str,
               host_bus: bool) -> SignAhead | None:
    """The run's :class:`SignAhead`, or None when it signs inline (no ``--sign``,
    ``--asap``, ``--attack`` or ``--sign-workers 0``)."""
    from rve.options import DEFAULTS

    workers = getattr(args, "sign_workers", None)
    workers = DEFAULTS["sign_workers"] if workers is None else workers
    if signer is None or framing == "uper" or args.asap or args.attack or workers <= 0:
        return None
    lookahead = getattr(args, "sign_lookahead", None)
    lookahead = DEFAULTS["sign_lookahead"] if lookahead is None else lookahead
    return SignAhead(the_plan, signer, framing, host_bus, workers, lookahead,
                     args.speed or 1.0)
