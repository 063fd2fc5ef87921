"""``captures plot DIR``: pictures of an ``rve run`` + ``obu run`` capture.

* ``birdseye_t{T}.png`` (:mod:`~captures.plot.birdseye`): the road around the host vehicle
  at one OBU tick, with the CA-TC zones (:mod:`~captures.plot.zones`), the true tracks,
  the OBU's estimates, the missing RVs and the active warnings.
* ``timeline.png`` (:mod:`~captures.plot.timeline`): PTE, messages and warnings over time.
* ``run.gif`` (``--gif``) / ``run.mp4`` (``--mp4``, needs ffmpeg)
  (:mod:`~captures.plot.movie`): the bird's-eye view of the whole run.

The capture is read by :mod:`~captures.plot.load` through :func:`hil.capture.read_capture`;
the command is :mod:`~captures.plot.cli`.  Times are on the OBU's clock (the ``t`` of its
ticks and warning events; for the built-in scenario it is the dataset's time).  The
drawing functions take matplotlib axes or figures and use the Agg canvas only (never
pyplot), so other reports can reuse them: :func:`load_run`, :func:`birdseye`,
:func:`timeline`, :func:`animate`, :func:`auto_times`, :func:`stills`.
"""

from captures.plot.birdseye import birdseye
from captures.plot.cli import register, run, stills
from captures.plot.load import Run, Truth, auto_times, load_run
from captures.plot.movie import animate
from captures.plot.timeline import timeline

__all__ = ["Run", "Truth", "animate", "auto_times", "birdseye", "load_run", "register", "run",
           "stills", "timeline"]
