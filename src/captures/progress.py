"""Progress on stderr for long commands: a bar on a terminal, a line per 10 % otherwise."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Call with ``(done, total)``; cheap enough to call on every item."""

    def __init__(self, label: str, stream: TextIO = sys.stderr) -> None:
        self.label = label
        self.stream = stream
        self.start = time.monotonic()
        self.last = 0.0
        self.last_decile = -1
        self.tty = stream.isatty()

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        frac = min(done / total, 1.0) if total else 1.0
        elapsed = now - self.start
        eta = elapsed / frac - elapsed if frac > 0 else 0.0
        if self.tty:
            if now - self.last < 0.2 and done < total:
                return
            self.last = now
            self.stream.write(f"\r{self.label} [{'#' * int(30 * frac):<30}] {100 * frac:5.1f}% "
                              f"{elapsed:5.0f}s elapsed, {eta:5.0f}s left")
            if done >= total:
                self.stream.write("\n")
        else:
            decile = int(10 * frac)
            if decile == self.last_decile:
                return
            self.last_decile = decile
            self.stream.write(f"{self.label}: {10 * decile}% ({elapsed:.0f}s elapsed, "
                              f"{eta:.0f}s left)\n")
        self.stream.flush()
