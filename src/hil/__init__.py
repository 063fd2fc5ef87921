"""hil: the I/O shell under the daemons (``rve``, ``obu``) and ``captures``.

Transports (:mod:`hil.transport`), the capture files with their schema and reader
(:mod:`hil.capture`), dataset files and the built-in scenarios (:mod:`hil.datasets`), PKI
files (:mod:`hil.pki`), configuration and command-line helpers (:mod:`hil.config`,
:mod:`hil.cliargs`), real-time pacing and the GC policy live here, so that :mod:`catc`
stays pure: nothing in ``catc`` opens a socket or a file, starts a thread or reads a clock.
"""
