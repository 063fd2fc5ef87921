"""A test PKI's files (``rve pki init DIR``), read by the RVE (``--sign DIR``) and the OBU
(``--trust PATH``).  The certificates and keys themselves are :mod:`catc.security`'s.

The directory holds, for the root CA, the authorization CA (AA) and every pseudonym
``pseudonym-N``: ``LABEL.oer`` (the IEEE 1609.2 certificate, COER) and ``LABEL.key.pem``
(its P-256 private key, PKCS#8 PEM, mode 0600), and ``pki.json``: the labels, each
certificate's HashedId8, the validity period and how the PKI was made.  ``foreign/``
under it (``rve pki init --foreign``) is a second, untrusted PKI of the same shape, for
the ``foreign-cert`` attack.

A trust store is what an OBU is given: a PKI directory (its root is trusted and its AA
known in advance, as an SCMS hands a device its local certificate chain) or a root
certificate file (``.oer``; then every CA certificate must come in the messages).

Files are made, never overwritten: ``rve pki init`` creates DIR (or takes an existing
directory that is not a symbolic link and not group- or world-writable) and writes each
file with ``O_CREAT | O_EXCL | O_NOFOLLOW`` through a descriptor of DIR, so a file or a
symbolic link planted in DIR beforehand is a one-line error, not a file written through;
what the failed run had made is removed again.  Private keys are created mode 0600,
certificates and pki.json 0644 (less if the umask says so).

``--seed`` derives every private key from the seed string, so the seed is as secret as
the keys: it is written nowhere (pki.json says only ``"seeded": true``).  Whoever wants
the same PKI again runs ``rve pki init`` with the same seed; the tests keep theirs in
their code.

A trust store that others could change is refused (:func:`trust_store`): the PKI
directory, its pki.json, root.oer and aa.oer, or a root ``.oer`` file and the directory
that holds it, must not be group- or world-writable (whoever can write them can make the
OBU trust their own root).  There is no flag to accept one: ``chmod go-w`` it.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

from catc.errors import DecodeError
from catc.j2735.ieee1609 import parse_certificate
from hil.errors import InputError, parse_json

__all__ = ["LoadedPki", "PkiError", "init", "load", "trust_store"]

#: pki.json's format version.
FORMAT = 1


class PkiError(InputError):
    """A PKI directory or trust store that cannot be used (one line, for the CLI)."""


@dataclass(frozen=True)
class LoadedPki:
    """What ``rve run --sign`` needs: the chain and every pseudonym with its key."""

    directory: Path
    root: bytes
    aa: bytes
    pseudonyms: tuple[tuple[bytes, object], ...]  # (certificate COER, private key)
    foreign: tuple[tuple[bytes, object], ...] = ()  # the untrusted PKI's pseudonyms


#: How every file of a new PKI is opened: made here or refused, never followed.
_NEW_FILE = (os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_CLOEXEC", 0))
_DIR = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_NOFOLLOW", 0)


def _taken(path: Path, is_link: bool) -> PkiError:
    if is_link:
        return PkiError(f"{path} is a symbolic link: rve pki init writes no file through "
                        "one (remove it or choose a new directory)")
    return PkiError(f"{path} already exists: rve pki init writes only new files (choose a "
                    "new or empty directory)")


def _lstat(name: str, dir_fd: int | None) -> os.stat_result | None:
    try:
        return os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except OSError:
        return None


def _is_link(name: str, dir_fd: int | None) -> bool:
    st = _lstat(name, dir_fd)
    return st is not None and stat.S_ISLNK(st.st_mode)


def _writable_by_others(mode: int) -> str | None:
    """'group', 'world' or 'group and world' when ``mode`` lets them write, else None."""
    who = [w for w, bit in (("group", stat.S_IWGRP), ("world", stat.S_IWOTH)) if mode & bit]
    return " and ".join(who) or None


class _NewFiles:
    """The directories and files one ``init`` makes, opened by descriptor (module
    docstring), and removed again if it fails."""

    def __init__(self) -> None:
        self.made: list[tuple[int | None, str, bool]] = []  # (dir fd, name, is a directory)
        self.fds: list[int] = []

    def directory(self, path: Path, name: str, parent: int | None) -> int:
        """Make directory ``name`` (in ``parent``'s descriptor, or a path when None) unless
        it exists, and open it without following a link; its descriptor."""
        try:
            os.mkdir(name, 0o755, dir_fd=parent)
            self.made.append((parent, name, True))
        except FileExistsError:
            if parent is not None:  # foreign/ is always new
                raise _taken(path, _is_link(name, parent)) from None
        try:
            fd = os.open(name, _DIR, dir_fd=parent)
        except OSError as err:
            if err.errno == errno.ELOOP or _is_link(name, parent):
                raise PkiError(f"{path} is a symbolic link: name the directory itself") \
                    from None
            if err.errno == errno.ENOTDIR:
                raise PkiError(f"{path} is not a directory") from None
            raise
        self.fds.append(fd)
        mode = os.fstat(fd).st_mode
        who = _writable_by_others(mode)
        if who:
            raise PkiError(f"{path} is {who}-writable (mode {stat.S_IMODE(mode):04o}): an OBU "
                           f"would refuse it as a trust store (chmod go-w {path})")
        return fd

    def write(self, dir_fd: int, path: Path, data: bytes, private: bool = False) -> None:
        """A new file ``path.name`` in ``dir_fd`` (``path`` names it in messages)."""
        try:
            fd = os.open(path.name, _NEW_FILE, 0o600 if private else 0o644, dir_fd=dir_fd)
        except OSError as err:
            if err.errno in (errno.EEXIST, errno.ELOOP):
                raise _taken(path, _is_link(path.name, dir_fd)) from None
            raise
        self.made.append((dir_fd, path.name, False))
        with os.fdopen(fd, "wb") as f:
            f.write(data)

    def undo(self) -> None:
        for dir_fd, name, is_dir in reversed(self.made):
            with contextlib.suppress(OSError):
                (os.rmdir if is_dir else os.unlink)(name, dir_fd=dir_fd)

    def close(self) -> None:
        for fd in self.fds:
            os.close(fd)


def init(directory: str | os.PathLike, pseudonyms: int, days: float, *,
         seed: str | None = None, foreign: bool = True, start_unix: float | None = None) -> dict:
    """Create a test PKI in ``directory`` (module docstring); returns pki.json's content.
    :class:`PkiError` for bad arguments and for a directory or file that is in the way."""
    if pseudonyms < 1:
        raise PkiError(f"--vehicles must be at least 1, got {pseudonyms}")
    if not days > 0:
        raise PkiError(f"--days must be > 0, got {days}")
    d = Path(directory)
    files = _NewFiles()
    try:
        d.parent.mkdir(parents=True, exist_ok=True)
        fd = files.directory(d, str(d), None)
        if _is_link("pki.json", fd):
            raise _taken(d / "pki.json", True)
        if _lstat("pki.json", fd) is not None:
            raise PkiError(f"{d} already holds a PKI (pki.json); choose another directory")
        return _make(files, fd, d, pseudonyms, days, seed, foreign, start_unix)
    except BaseException:
        files.undo()
        raise
    finally:
        files.close()


def _make(files: _NewFiles, fd: int, d: Path, pseudonyms: int, days: float,
          seed: str | None, foreign: bool, start_unix: float | None) -> dict:
    from catc.security import make_pki, unix_to_time32

    start = unix_to_time32((time.time() if start_unix is None else start_unix) - 3600)
    duration = int(days * 86400)
    pki = make_pki(pseudonyms, start_time32=start, duration_s=duration, seed=seed)
    manifest = {"format": FORMAT, "made_by": "rve pki init", "created_unix": time.time(),
                "seeded": seed is not None, "start_time32": start, "duration_s": duration,
                "certificates": {}}
    for label, ident in pki.identities().items():
        files.write(fd, d / f"{label}.oer", ident.raw)
        files.write(fd, d / f"{label}.key.pem", ident.private_pem(), private=True)
        manifest["certificates"][label] = ident.hashed_id8.hex()
    manifest["pseudonyms"] = [p.label for p in pki.pseudonyms]
    if foreign:
        sub = files.directory(d / "foreign", "foreign", fd)
        manifest["foreign"] = _make(files, sub, d / "foreign", 1, days,
                                    None if seed is None else f"{seed}/foreign", False,
                                    start_unix)
    files.write(fd, d / "pki.json", json.dumps(manifest, indent=1).encode())  # the last
    return manifest


def _read(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise PkiError(f"cannot read {what} {path}: {err.strerror}") from None


def _certificate(path: Path) -> bytes:
    raw = _read(path, "certificate")
    try:
        parse_certificate(raw)
    except DecodeError as err:
        raise PkiError(f"{path}: not an IEEE 1609.2 certificate ({err})") from None
    return raw


def _manifest(d: Path) -> dict:
    if not d.is_dir():
        raise PkiError(f"{d} is not a directory (make one with `rve pki init DIR`)")
    try:
        manifest = parse_json(_read(d / "pki.json", "PKI manifest"), d / "pki.json")
    except InputError as err:
        raise PkiError(str(err)) from None
    if not isinstance(manifest, dict):
        raise PkiError(f"{d / 'pki.json'}: not a JSON object (not a PKI manifest)")
    if manifest.get("format") != FORMAT:
        raise PkiError(f"{d / 'pki.json'}: unknown format {manifest.get('format')!r}")
    return manifest


def load(directory: str | os.PathLike) -> LoadedPki:
    """The PKI in ``directory`` with the pseudonyms' private keys."""
    from catc.security import load_private_pem

    d = Path(directory)
    manifest = _manifest(d)
    pseudonyms = []
    for label in manifest.get("pseudonyms", []):
        cert = _certificate(d / f"{label}.oer")
        try:
            key = load_private_pem(_read(d / f"{label}.key.pem", "private key"))
        except (ValueError, TypeError) as err:
            raise PkiError(f"{d / (label + '.key.pem')}: not a P-256 private key ({err})") \
                from None
        pseudonyms.append((cert, key))
    if not pseudonyms:
        raise PkiError(f"{d / 'pki.json'} lists no pseudonym certificates")
    foreign = load(d / "foreign").pseudonyms if (d / "foreign" / "pki.json").exists() else ()
    return LoadedPki(d, _certificate(d / "root.oer"), _certificate(d / "aa.oer"),
                     tuple(pseudonyms), foreign)


def _not_writable_by_others(path: Path) -> None:
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return  # reading it says what is wrong
    who = _writable_by_others(mode)
    if who:
        raise PkiError(f"trust store {path} is {who}-writable (mode {stat.S_IMODE(mode):04o}): "
                       f"anyone could make it trust their own root (chmod go-w {path})")


def trust_store(path: str | os.PathLike) -> tuple[list[bytes], list[bytes]]:
    """(trusted roots, known CA certificates) of a PKI directory or a root ``.oer`` file;
    :class:`PkiError` for one that is unusable or that others could write (module
    docstring)."""
    p = Path(path)
    if p.is_dir():
        for part in (p, p / "pki.json", p / "root.oer", p / "aa.oer"):
            _not_writable_by_others(part)
        _manifest(p)
        return [_certificate(p / "root.oer")], [_certificate(p / "aa.oer")]
    if not p.exists():
        raise PkiError(f"{p}: no such trust store (a PKI directory or a root .oer file)")
    for part in (p.parent, p):
        _not_writable_by_others(part)
    return [_certificate(p)], []
