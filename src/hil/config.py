"""Daemon settings from ``--config FILE.toml`` and command-line flags (flags win).

A TOML file holds the same names as the long flags, with ``-`` or ``_`` (``host-to`` or
``host_to``), at the top level or under a table named after the daemon (``[rve]``,
``[obu]``).  Unknown keys, wrong types and unreadable files are errors with a one-line
message, like a bad flag.
"""

from __future__ import annotations

import argparse
import tomllib
from pathlib import Path
from typing import Any

from hil.errors import InputError

__all__ = ["ConfigError", "add_can_arguments", "address", "destination", "merge",
           "non_negative", "percent", "positive", "run_daemon", "web_address"]


def address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:4500`` for IPv6; an empty host is 127.0.0.1) as a pair; the
    argparse ``type`` of the daemons' address flags."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) < 65536:
        raise argparse.ArgumentTypeError(f"not HOST:PORT: {text!r}")
    return host.strip("[]") or "127.0.0.1", int(port)


def destination(text: str) -> tuple[str, int]:
    """``HOST:PORT`` to send to: :func:`address` with a port from 1 (port 0 names no
    receiver)."""
    host, port = address(text)
    if port == 0:
        raise argparse.ArgumentTypeError(f"port 0 names no receiver: {text!r}")
    return host, port


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"a finite number, got {text}")
    return value


def positive(text: str) -> float:
    """A finite number above 0 (durations, speeds, rates)."""
    value = _finite(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"a number above 0, got {text}")
    return value


def non_negative(text: str) -> float:
    """A finite number from 0 (waits, latencies)."""
    value = _finite(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"a number from 0, got {text}")
    return value


def web_address(text: str) -> tuple[str, int]:
    """``PORT`` (on 127.0.0.1) or ``HOST:PORT``: where a web page is served."""
    return address(text if ":" in text else f"127.0.0.1:{text}")


def percent(text: str) -> float:
    """A percentage from 0 to 100 (the argparse ``type`` of ``--per``)."""
    value = _finite(text)
    if not 0.0 <= value <= 100.0:
        raise argparse.ArgumentTypeError(f"a percentage from 0 to 100, got {text}")
    return value


def add_can_arguments(p: argparse.ArgumentParser) -> None:
    """The CAN bus flags that ``rve run`` and ``obu run`` share (``--transport can``)."""
    p.add_argument("--can-interface", choices=("socketcan", "virtual", "udp_multicast"),
                   help="python-can interface for --transport can (default virtual)")
    p.add_argument("--can-channel", metavar="NAME", help="CAN channel, e.g. vcan0")
    p.add_argument("--can-fd", action="store_true", default=None, help="CAN FD frames")


class ConfigError(InputError):
    """A bad config file; ``str()`` is the one-line message."""


def _load(path: Path, section: str) -> dict[str, Any]:
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise ConfigError(f"config {path}: {err.strerror or err}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"config {path}: not valid TOML: {err}") from None
    scoped = data.pop(section, {})
    if not isinstance(scoped, dict):
        raise ConfigError(f"config {path}: [{section}] must be a table")
    data.update(scoped)
    return {k.replace("-", "_"): v for k, v in data.items()}


def merge(parser: argparse.ArgumentParser, args: argparse.Namespace, section: str,
          defaults: dict[str, Any]) -> argparse.Namespace:
    """Fill every option left unset on the command line (``None``) from ``args.config``
    (when given), then from ``defaults``.  Values from the file pass through the option's
    own ``type`` so they are checked like flags."""
    from_file: dict[str, Any] = {}
    if getattr(args, "config", None):
        from_file = _load(Path(args.config), section)
    actions = {a.dest: a for a in parser._actions if a.dest not in ("help", "config")}
    unknown = sorted(set(from_file) - set(actions))
    if unknown:
        raise ConfigError(f"config {args.config}: unknown setting(s) {', '.join(unknown)}")
    for dest, action in actions.items():
        if getattr(args, dest, None) is not None:
            continue
        if dest in from_file:
            value = from_file[dest]
            if action.type is not None and not isinstance(value, bool):
                try:
                    value = action.type(str(value))
                except (ValueError, argparse.ArgumentTypeError) as err:
                    raise ConfigError(f"config {args.config}: {dest}: {err}") from None
            elif isinstance(action, argparse._StoreTrueAction) and not isinstance(value, bool):
                raise ConfigError(f"config {args.config}: {dest} must be true or false")
            if action.choices is not None and value not in action.choices:
                raise ConfigError(f"config {args.config}: {dest} must be one of "
                                  f"{', '.join(map(str, action.choices))}")
            setattr(args, dest, value)
        elif dest in defaults:
            setattr(args, dest, defaults[dest])
    return args


def run_daemon(args: argparse.Namespace, section: str, module) -> int:
    """Merge ``--config`` and the defaults of ``module`` (``DEFAULTS``) into the parsed
    flags (``args.parser`` is the subcommand's parser), then ``module.run(args)``; a bad
    config file is one line and exit status 2."""
    import sys

    try:
        merge(args.parser, args, section, module.DEFAULTS)
    except ConfigError as err:
        print(f"{section} run: {err}", file=sys.stderr)
        return 2
    del args.parser
    return module.run(args)
