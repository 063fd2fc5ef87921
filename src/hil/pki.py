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
"""

from __future__ import annotations

import json
import os
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


def _write(path: Path, data: bytes, private: bool = False) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def init(directory: str | os.PathLike, pseudonyms: int, days: float, *,
         seed: str | None = None, foreign: bool = True, start_unix: float | None = None) -> dict:
    """Create a test PKI in ``directory`` (module docstring); returns pki.json's content."""
    from catc.security import make_pki, unix_to_time32

    if pseudonyms < 1:
        raise PkiError(f"--vehicles must be at least 1, got {pseudonyms}")
    if not days > 0:
        raise PkiError(f"--days must be > 0, got {days}")
    d = Path(directory)
    if (d / "pki.json").exists():
        raise PkiError(f"{d} already holds a PKI (pki.json); choose another directory")
    d.mkdir(parents=True, exist_ok=True)
    start = unix_to_time32((time.time() if start_unix is None else start_unix) - 3600)
    duration = int(days * 86400)
    pki = make_pki(pseudonyms, start_time32=start, duration_s=duration, seed=seed)
    manifest = {"format": FORMAT, "made_by": "rve pki init", "created_unix": time.time(),
                "seed": seed, "start_time32": start, "duration_s": duration,
                "certificates": {}}
    for label, ident in pki.identities().items():
        _write(d / f"{label}.oer", ident.raw)
        _write(d / f"{label}.key.pem", ident.private_pem(), private=True)
        manifest["certificates"][label] = ident.hashed_id8.hex()
    manifest["pseudonyms"] = [p.label for p in pki.pseudonyms]
    if foreign:
        manifest["foreign"] = init(d / "foreign", 1, days, seed=None if seed is None
                                   else f"{seed}/foreign", foreign=False,
                                   start_unix=start_unix)
    (d / "pki.json").write_text(json.dumps(manifest, indent=1))
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


def trust_store(path: str | os.PathLike) -> tuple[list[bytes], list[bytes]]:
    """(trusted roots, known CA certificates) of a PKI directory or a root ``.oer`` file."""
    p = Path(path)
    if p.is_dir():
        _manifest(p)
        return [_certificate(p / "root.oer")], [_certificate(p / "aa.oer")]
    if not p.exists():
        raise PkiError(f"{p}: no such trust store (a PKI directory or a root .oer file)")
    return [_certificate(p)], []
