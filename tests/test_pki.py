"""The files of a test PKI (``rve pki init``, :mod:`hil.pki`) and the trust store the OBU
takes (``obu run --trust``), with real files, modes and symbolic links: keys 0600, the
seed written nowhere, nothing written through a planted link or over a planted file, and
a trust store that others could write refused.  Modes are read back with ``os.stat``
(the tests run as root, who reads and writes whatever the bits say)."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from hil.pki import PkiError, init, trust_store
from hil.transport.udp import free_ports

PY = sys.executable
SEED = "the-seed-is-a-secret-1f3a"


def _rve_pki_init(d: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-m", "rve.cli", "pki", "init", str(d), "--vehicles", "2",
                           *args], capture_output=True, text=True, timeout=60)


def _one_line_error(out: subprocess.CompletedProcess, *needles: str) -> str:
    assert out.returncode == 2, (out.returncode, out.stdout, out.stderr)
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def _mode(p: Path) -> int:
    return stat.S_IMODE(os.stat(p, follow_symlinks=False).st_mode)


def _files(d: Path) -> list[Path]:
    return sorted(p for p in d.rglob("*") if not p.is_dir())


def test_keys_are_0600_and_the_seed_is_written_nowhere(tmp_path):
    d = tmp_path / "pki"
    out = _rve_pki_init(d, "--seed", SEED)
    assert out.returncode == 0, out.stderr
    files = _files(d)
    keys = [p for p in files if p.name.endswith(".key.pem")]
    assert len(keys) == 4 + 3  # root, aa, 2 pseudonyms; foreign/: root, aa, 1 pseudonym
    for p in files:
        assert p.is_file() and not p.is_symlink(), p
        assert _mode(p) == (0o600 if p in keys else 0o644), (p, oct(_mode(p)))
        assert SEED.encode() not in p.read_bytes(), p  # nowhere, 0600 or not
    assert _mode(d) & 0o022 == 0 and _mode(d / "foreign") & 0o022 == 0
    manifest = json.loads((d / "pki.json").read_text())
    assert "seed" not in manifest and manifest["seeded"] is True
    assert "seed" not in manifest["foreign"] and manifest["foreign"]["seeded"] is True
    # the seed, given again, makes the same keys: it need not be stored to reproduce a
    # PKI (the certificates differ only by their start, an hour before now)
    again = tmp_path / "again"
    assert _rve_pki_init(again, "--seed", SEED).returncode == 0
    for p in keys:
        assert (again / p.relative_to(d)).read_bytes() == p.read_bytes(), p


def test_an_unseeded_pki_says_so(tmp_path):
    manifest = init(tmp_path / "pki", 1, 1.0, foreign=False)
    assert manifest["seeded"] is False and "seed" not in manifest


@pytest.mark.parametrize("planted", ["pseudonym-1.key.pem", "root.key.pem", "aa.oer",
                                     "pki.json"])
def test_a_planted_symlink_is_refused_and_nothing_is_written_through_it(tmp_path, planted):
    d, elsewhere = tmp_path / "pki", tmp_path / "attacker"
    d.mkdir()
    elsewhere.mkdir()
    dangling, existing = elsewhere / "stolen.pem", elsewhere / "victim"
    existing.write_bytes(b"keep me\n")
    for target in (dangling, existing):
        (d / planted).symlink_to(target)
        out = _rve_pki_init(d, "--seed", SEED)
        line = _one_line_error(out, f"{d / planted}", "symbolic link")
        assert "Traceback" not in line
        assert not dangling.exists(), "a key was written through the planted link"
        assert existing.read_bytes() == b"keep me\n"
        # what the failed run made is gone again: only the planted link is left
        assert [p.name for p in d.iterdir()] == [planted]
        (d / planted).unlink()


def test_a_planted_file_is_refused_not_overwritten(tmp_path):
    d = tmp_path / "pki"
    d.mkdir()
    (d / "aa.key.pem").write_bytes(b"someone's key\n")
    out = _rve_pki_init(d)
    _one_line_error(out, f"{d / 'aa.key.pem'}", "already exists")
    assert (d / "aa.key.pem").read_bytes() == b"someone's key\n"
    assert [p.name for p in d.iterdir()] == ["aa.key.pem"]
    # a directory that holds a PKI keeps its message
    good = tmp_path / "good"
    assert _rve_pki_init(good).returncode == 0
    _one_line_error(_rve_pki_init(good), "already holds a PKI")


def test_the_pki_directory_must_be_a_directory_others_cannot_write(tmp_path):
    real = tmp_path / "real"
    real.mkdir(mode=0o755)
    link = tmp_path / "link"
    link.symlink_to(real)
    _one_line_error(_rve_pki_init(link), str(link), "symbolic link")
    assert list(real.iterdir()) == []
    for mode, who in ((0o777, "group and world-writable"), (0o775, "group-writable"),
                      (0o757, "world-writable")):
        shared = tmp_path / f"shared-{mode:o}"
        shared.mkdir()
        os.chmod(shared, mode)
        _one_line_error(_rve_pki_init(shared), str(shared), who, "chmod go-w")
        assert list(shared.iterdir()) == []
    empty = tmp_path / "empty"  # an existing empty directory of one's own is fine
    empty.mkdir(mode=0o700)
    assert _rve_pki_init(empty).returncode == 0 and (empty / "pki.json").is_file()


@pytest.fixture(scope="module")
def made_pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("trust") / "pki"
    init(d, 1, 1.0, seed="trust", foreign=False)
    return d


def test_a_trust_store_others_can_write_is_refused(made_pki, tmp_path):
    roots, cas = trust_store(made_pki)
    assert roots == [(made_pki / "root.oer").read_bytes()] and cas
    for part, mode in ((made_pki, 0o777), (made_pki, 0o775), (made_pki / "root.oer", 0o666),
                       (made_pki / "aa.oer", 0o646), (made_pki / "pki.json", 0o664)):
        before = _mode(part)
        os.chmod(part, mode)
        try:
            with pytest.raises(PkiError, match=r"writable \(mode 0\d{3}\).*chmod go-w"):
                trust_store(made_pki)
        finally:
            os.chmod(part, before)
    # a root certificate file: the file and the directory that holds it
    holder = tmp_path / "holder"
    holder.mkdir(mode=0o755)
    root = holder / "root.oer"
    root.write_bytes((made_pki / "root.oer").read_bytes())
    os.chmod(root, 0o644)
    assert trust_store(root) == ([root.read_bytes()], [])
    os.chmod(root, 0o666)
    with pytest.raises(PkiError, match=r"root\.oer is group and world-writable"):
        trust_store(root)
    os.chmod(root, 0o644)
    os.chmod(holder, 0o1777)  # sticky or not, others can put a file in it beforehand
    with pytest.raises(PkiError, match=r"holder is group and world-writable \(mode 1777\)"):
        trust_store(root)


def test_obu_run_refuses_a_world_writable_trust_directory_in_one_line(made_pki):
    before = _mode(made_pki)
    os.chmod(made_pki, 0o777)
    try:
        rv, host = free_ports()
        out = subprocess.run([PY, "-m", "obu.cli", "run", "--verify", "enforce", "--trust",
                              str(made_pki), "--listen", f"127.0.0.1:{rv}", "--host-listen",
                              f"127.0.0.1:{host}", "--duration", "1"],
                             capture_output=True, text=True, timeout=60)
    finally:
        os.chmod(made_pki, before)
    _one_line_error(out, str(made_pki), "world-writable", "chmod go-w")
