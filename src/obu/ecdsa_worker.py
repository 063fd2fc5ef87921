"""Verify on demand's worker process (``obu run --verify-workers N``): the ECDSA of queued
frames on another core, at a lower priority (``nice`` +10).

Why a process and not a thread (measured on the 2-core test machine, docs/reference/
security.md, "Verify on demand"): ``cryptography`` releases the GIL during a
verification, but a thread must take it back between two, and a busy main thread hands
it over only every switch interval; a worker thread verified 3,000-4,800 signatures/s and
took 9-33 % of the main thread's Python throughput, and at 1,000 RVs the main thread is
what is short.  A process costs the main thread only the batches' pickling (three short
octet strings a frame), and while the OBU and the RVE ran at 1,000 RVs a nice +10 process
still verified ~6,000 signatures/s without slowing either.

The main thread stays the verifier's only user: it runs the cheap checks, and afterwards
:meth:`catc.security.Verifier.settle` with the worker's answer (replays, the verdict);
the worker only computes ECDSA over (public key point, r || s, digest).  Batches of
:data:`BATCH` frames, at most :data:`IN_FLIGHT` of them at once, taken from the queue
most threatening first, over a plain pipe: answers are picked up without blocking
(:meth:`EcdsaWorker.done`), and no helper thread of the OBU's needs the GIL (a
``ProcessPoolExecutor``'s does, and a saturated main thread let its worker verify only
~1,100 frames/s).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

from cryptography.hazmat.primitives import serialization

__all__ = ["BATCH", "IN_FLIGHT", "EcdsaWorker"]

#: Frames per batch sent to a worker (~9 ms of ECDSA; ~22 kB pickled).
BATCH = 128
#: Batches in flight per worker: one at work, two in the pipe (within its 64 kB buffer,
#: so that sending never blocks).
IN_FLIGHT = 3
#: The longest wait for a worker to start (s).
STARTUP_S = 30.0
#: How much lower a worker's priority is than the OBU's (os.nice).
_NICE = 10

_keys: dict[bytes, Any] = {}  # in the worker: public keys by their point


def _verify(batch: list[tuple[bytes, bytes | None, bytes]]) -> list[bool]:
    """In the worker: ECDSA P-256 of each (key point, r || s, digest)."""
    from cryptography.hazmat.primitives.asymmetric import ec

    from catc.security._crypto import verify_digest

    out: list[bool] = []
    for point, signature, digest in batch:
        key = _keys.get(point)
        if key is None:
            key = _keys[point] = ec.EllipticCurvePublicKey.from_encoded_point(
                ec.SECP256R1(), point)
            if len(_keys) > 8192:
                _keys.clear()
        out.append(verify_digest(key, signature, digest))
    return out


def _serve(conn: Any) -> None:
    """The worker process: batches in, answers out, until None (or the pipe closes)."""
    os.nice(_NICE)
    try:
        while (batch := conn.recv()) is not None:
            conn.send(_verify(batch))
    except (EOFError, OSError, KeyboardInterrupt):
        pass


class EcdsaWorker:
    """``workers`` processes verifying batches (module docstring)."""

    def __init__(self, workers: int = 1) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.workers = workers
        self.conns: list[Any] = []
        self.procs: list[Any] = []
        for _ in range(workers):
            mine, theirs = ctx.Pipe()
            proc = ctx.Process(target=_serve, args=(theirs,), daemon=True,
                               name="obu-ecdsa")
            proc.start()
            theirs.close()
            self.conns.append(mine)
            self.procs.append(proc)
        #: per worker, the batches sent and not answered yet, oldest first
        self.flying: list[deque[list[Any]]] = [deque() for _ in range(workers)]
        self._points: dict[bytes, bytes] = {}  # signer cert hash -> its key's point
        for conn in self.conns:  # started and warm (imports done) before the first frame:
            conn.send([])  # else the first ticks' frames wait for it, unverified
        for conn in self.conns:
            if not conn.poll(STARTUP_S):
                self.close()
                raise RuntimeError(f"the ECDSA worker did not start within {STARTUP_S} s")
            conn.recv()

    def _point(self, signer: Any) -> bytes:
        point = self._points.get(signer.cert_hash)
        if point is None:
            point = self._points[signer.cert_hash] = signer.key.public_bytes(
                serialization.Encoding.X962, serialization.PublicFormat.UncompressedPoint)
            if len(self._points) > 8192:
                self._points.clear()
        return point

    def feed(self, take: Callable[[], Any]) -> int:
        """Send batches while fewer than :data:`IN_FLIGHT` fly at a worker, each of the
        entries ``take()`` gives (a queued frame with ``checked``; None: none left)."""
        sent = 0
        for conn, flying in zip(self.conns, self.flying, strict=True):
            while len(flying) < IN_FLIGHT:
                entries = []
                while len(entries) < BATCH:
                    e = take()
                    if e is None:
                        break
                    entries.append(e)
                if not entries:
                    return sent
                items = []
                for e in entries:
                    _, signature, digest = e.checked.ecdsa_input()
                    items.append((self._point(e.checked.signer), signature, digest))
                conn.send(items)
                flying.append(entries)
                sent += len(entries)
        return sent

    def done(self) -> Iterator[tuple[Any, bool]]:
        """(entry, ECDSA ok) of every batch answered so far (never blocks)."""
        for conn, flying in zip(self.conns, self.flying, strict=True):
            while flying and conn.poll():
                yield from zip(flying.popleft(), conn.recv(), strict=True)

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for an answer; whether one came (False: none flies)."""
        from multiprocessing.connection import wait

        busy = [c for c, f in zip(self.conns, self.flying, strict=True) if f]
        return bool(busy) and bool(wait(busy, max(0.0, timeout)))

    def in_flight(self) -> list[Any]:
        """The entries sent and not answered yet."""
        return [e for flying in self.flying for entries in flying for e in entries]

    def close(self) -> None:
        for conn, proc in zip(self.conns, self.procs, strict=True):
            with contextlib.suppress(OSError):
                conn.send(None)
            proc.join(1.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(1.0)
            conn.close()
        self.conns, self.procs, self.flying = [], [], []
