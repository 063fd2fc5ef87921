"""Progress on stderr for long commands: a ``progress(done, total)`` callback over tqdm.

The callers (``sweep``, ``evaluate``, ``replay``, ``train-bank``, ``train-nn``) and the
library loops they drive (:func:`catc.evaluate.evaluate`, ...) report ``(done, total)``;
:class:`Progress` turns that into a :class:`tqdm.tqdm` bar, whose clock starts when the
:class:`Progress` is made and which ends when ``done`` reaches the total or the ``with``
block ends.

* On a terminal: tqdm's bar, drawn from the first report after 0.2 s and redrawn at most
  every 0.2 s.
* Anywhere else (CI, the tests' pipes, ``make report > log``): a redrawn bar would be one
  long line of carriage returns, and ``disable=None`` would say nothing for the 20
  minutes of a report; so one plain line per 10 %, with tqdm's elapsed and remaining
  times (11 lines a command at most).

The meter shows no counts or rate: the callers' units differ (the sweep counts estimated
CPU cost, the others tracks, ticks or steps).  The time left comes from the average
speed since the start (``smoothing=0``): the sweep's tasks finish in bursts, longest
first, and an average over the last bursts jumps.
"""

from __future__ import annotations

import sys
from typing import TextIO

from tqdm import tqdm

#: The bar on a terminal, and the line written per 10 % elsewhere.
BAR = "{l_bar}{bar}| {elapsed} elapsed, {remaining} left"
LINE = "{desc}: {percentage:.0f}% ({elapsed} elapsed, {remaining} left)"


class Progress:
    """Call with ``(done, total)``; cheap enough to call on every item.  ``write(line)``
    prints a line on the same stream without breaking the bar."""

    def __init__(self, label: str, stream: TextIO | None = None) -> None:
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.tty = self.stream.isatty()
        # the total comes with the first report; off a terminal tqdm never draws by
        # itself (delay=inf): the lines are ours
        self._bar = tqdm(desc=label, total=None, file=self.stream, smoothing=0,
                         bar_format=BAR if self.tty else LINE, mininterval=0.2,
                         dynamic_ncols=self.tty, delay=0.2 if self.tty else float("inf"))
        self._decile = -1

    def __call__(self, done: float, total: float) -> None:
        if total <= 0:  # nothing to do is all done
            done, total = 1, 1
        done = min(done, total)
        bar = self._bar
        if bar.disable:  # closed: done reached total before
            return
        bar.total = total
        bar.update(done - bar.n)
        if not self.tty:
            decile = int(10 * done / total)
            if decile != self._decile:
                self._decile = decile
                self.stream.write(f"{bar}\n")
                self.stream.flush()
        if done >= total:
            self.close()

    def write(self, line: str) -> None:
        """``line`` on the stream, the bar (on a terminal) redrawn below it."""
        if self.tty and not self._bar.disable:
            tqdm.write(line, file=self.stream)
        else:
            print(line, file=self.stream, flush=True)

    def close(self) -> None:
        """End the bar where it stands (a terminal keeps its last state)."""
        self._bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
