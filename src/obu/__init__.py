"""obu package: the On-Board Unit, the device under test (``obu run``, ``obu frame``).

* :mod:`obu.run`: the daemon's event loop (``serve``, ``run``); its docstring is
  ``obu run --help``.
* :mod:`obu.options`: the flags of ``obu run`` and their defaults.
* :mod:`obu.tick`: the tick rule, a pure object the event loop feeds.
* :mod:`obu.frames`: each received frame decoded, verified, checked, queued.
* :mod:`obu.daemon`: the daemon's state, a frame received and a tick stepped.
* :mod:`obu.capture`: the capture directory, through :mod:`hil.capture.schema`.
* :mod:`obu.status`: counters, step times, the status line and the live view's panel.
* :mod:`obu.web`: the live view (also ``captures view``); :mod:`obu.cli`: the commands.
"""
