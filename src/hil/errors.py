"""Errors of one line (docs/architecture.md, "Command-line contracts"): what went wrong,
and with which file.

* :class:`InputError`: a file or value the user gave that the commands cannot use (not
  JSON, not UTF-8 text, the wrong shape).  The project's own input errors derive from it
  (:class:`hil.datasets.DatasetError`, :class:`hil.config.ConfigError`,
  :class:`hil.pki.PkiError`, :class:`hil.capture.CaptureError`...), so
  :func:`hil.cliargs.dispatch` prints any that a command did not catch in one line.
* :class:`WriteError`: an output file that could not be written while a run went on (a
  full disk, a file size limit, an I/O error), with the file's name: the daemons end the
  run on it, flushed, with exit status 1.
* :func:`describe`: any :class:`OSError` as ``FILE: reason``.
* :func:`read_text`, :func:`load_json` (and :func:`decode`, :func:`parse_json` of content
  read elsewhere): a user's file as text or JSON, whose errors name it and say where the
  decoding or the parse stopped.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

__all__ = ["InputError", "WriteError", "decode", "describe", "load_json", "parse_json",
           "read_bytes", "read_text", "write_error"]


class InputError(ValueError):
    """A file or value the user gave that cannot be used; ``str()`` is the one-line
    message, naming the file."""


class WriteError(OSError):
    """An output file that could not be written during a run; ``str()`` is
    ``FILE: reason``."""

    def __str__(self) -> str:
        return describe(self)


def describe(err: OSError) -> str:
    """``FILE: reason`` (``FILE -> OTHER: reason`` for a rename), or the error's own
    message when it names no file (e.g. a one-line :class:`FileExistsError` of ours)."""
    reason = err.strerror or str(err)
    if err.filename is None:
        return reason
    where = _name(err.filename)
    if err.filename2 is not None:
        where += f" -> {_name(err.filename2)}"
    return f"{where}: {reason}"


def _name(filename: Any) -> str:
    return os.fsdecode(filename) if isinstance(filename, (str, bytes, os.PathLike)) \
        else str(filename)  # a file descriptor


def write_error(err: OSError, path: str | os.PathLike) -> WriteError:
    """``err`` (raised while writing ``path``, which it may not name) as a
    :class:`WriteError` that names it."""
    return WriteError(err.errno, err.strerror or str(err), os.fspath(path))


def read_bytes(path: str | os.PathLike) -> bytes:
    """The file's bytes; an OSError names ``path`` even when the read (not the open)
    failed, which Python's own does not."""
    try:
        return Path(path).read_bytes()
    except OSError as err:
        if err.filename is not None:
            raise
        raise type(err)(err.errno, err.strerror or str(err), os.fspath(path)) from None


def read_text(path: str | os.PathLike) -> str:
    """The file's text (UTF-8): :class:`InputError` naming ``path`` when it is not text,
    an :class:`OSError` naming it when it cannot be read."""
    return decode(read_bytes(path), path)


def decode(data: bytes, source: str | os.PathLike) -> str:
    """``data`` (the content of ``source``) as UTF-8 text (a byte-order mark dropped);
    :class:`InputError` naming ``source`` and the first byte that is not."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise InputError(f"{os.fspath(source)}: not UTF-8 text (byte "
                         f"{err.object[err.start]:#04x} at offset {err.start})") from None


def parse_json(data: str | bytes, source: str | os.PathLike) -> Any:
    """``data`` (the content of ``source``) as JSON; :class:`InputError` naming ``source``
    and, for a syntax error, its line and column."""
    try:
        return json.loads(decode(data, source) if isinstance(data, bytes) else data)
    except json.JSONDecodeError as err:
        raise InputError(f"{os.fspath(source)}: not valid JSON: line {err.lineno} col "
                         f"{err.colno}: {err.msg}") from None


def load_json(path: str | os.PathLike) -> Any:
    """The JSON file at ``path``: :class:`InputError` when it is not JSON, an
    :class:`OSError` naming it when it cannot be read."""
    return parse_json(read_bytes(path), path)
