"""The replay's progress on stderr (``rve run``; ``--no-progress`` turns it off): a tqdm
bar over the run's dataset time, with the frames sent and dropped so far and the p99 of
the recent frames' lateness against their deadlines, redrawn once a second.

On a terminal the bar is redrawn in place; elsewhere (a pipe, a log file) each redraw is
one line, without carriage returns.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from typing import TextIO

import numpy as np
from tqdm import tqdm

__all__ = ["Progress"]

_FORMAT = ("{desc}: {percentage:3.0f}%|{bar}| t={n:.1f}/{total:.1f} s "
           "[{elapsed}<{remaining}{postfix}]")


class _Bar(tqdm):
    """tqdm without its monitor thread: the bar is redrawn by :class:`Progress` only."""

    monitor_interval = 0


class _Lines:
    """Where stderr is not a terminal: each redraw of the bar as one line."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        line = text.lstrip("\r").rstrip()
        if line:
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


class Progress:
    """The bar of a replay whose events run from dataset time ``t0`` to ``t_end`` (s);
    nothing is drawn when not ``enabled``."""

    def __init__(self, enabled: bool, t0: float, t_end: float) -> None:
        self.t0 = t0
        self.last = time.monotonic()
        self.late: deque[float] = deque(maxlen=5000)
        self.bar: tqdm | None = None
        if enabled:
            tty = sys.stderr.isatty()
            self.bar = _Bar(total=t_end - t0, desc="rve", unit="s", bar_format=_FORMAT,
                            file=sys.stderr if tty else _Lines(sys.stderr), ascii=not tty,
                            smoothing=0)

    def update(self, t: float, sent: int, dropped: int, late_s: float,
               final: bool = False) -> None:
        """The replay is at dataset time ``t`` after a batch that left ``late_s`` late;
        redrawn when a second has passed since the last time, and closed when ``final``."""
        self.late.append(late_s)
        now = time.monotonic()
        if self.bar is None or (now - self.last < 1.0 and not final):
            return
        self.last = now
        p99 = 1000 * float(np.percentile(self.late, 99)) if self.late else 0.0
        self.bar.n = t - self.t0
        self.bar.set_postfix_str(f"sent {sent}, dropped {dropped}, late p99 {p99:.2f} ms",
                                 refresh=not final)
        if final:
            self.bar.close()
