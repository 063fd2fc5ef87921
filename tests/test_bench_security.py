"""The 1609.2 bench scripts run: ``bench/security.py`` gives positive rates next to
``openssl speed`` (or says why it skipped it), ``bench/obu_load.py`` takes ``--verify``.
Smoke checks only; the figures themselves are the scripts' to print, never asserted."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "bench"


def _run(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    # a subprocess: bench/security.py pins itself to one CPU
    return subprocess.run([sys.executable, *args], capture_output=True, text=True,
                          timeout=timeout)


def test_security_bench_json():
    out = _run(str(BENCH / "security.py"), "--json", "--seconds", "0.05")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["signatures_per_s"] > 0 and result["verifications_per_s"] > 0
    for name in ("sign_digest", "sign_certificate", "verify_digest_cached",
                 "verify_certificate_cached", "verify_new_pseudonym", "unwrap_digest",
                 "unwrap_certificate"):
        row = result["rows"][name]
        assert row["ops_per_s"] > 0 and row["us_per_op"] > 0
    assert result["rows"]["verify_new_pseudonym"]["ecdsa_per_op"] == 2  # the chain ran
    peer = result["openssl"]
    if "skipped" in peer:
        assert peer["skipped"]
    else:
        assert peer["sign_per_s"] > 0 and peer["verify_per_s"] > 0
        assert result["rows"]["sign_digest"]["ratio_to_openssl"] > 0


def test_obu_load_verify_option():
    out = _run(str(BENCH / "obu_load.py"), "--help")
    assert out.returncode == 0 and "--verify" in out.stdout
    bad = _run(str(BENCH / "obu_load.py"), "--verify", "maybe")
    assert bad.returncode == 2 and "maybe" in bad.stderr
