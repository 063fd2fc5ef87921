"""hil: the I/O shell that the daemons (``rve``, ``obu``) share.

Transports (:mod:`hil.transport`), capture files, real-time pacing and configuration
live here, so that :mod:`catc` stays pure: nothing in ``catc`` opens a socket, starts a
thread or reads a clock.
"""
