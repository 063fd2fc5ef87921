"""bench/mbd_honest.py runs offline and prints its JSON: smoke checks only (the figures
are the script's to print, never asserted; they change with the detector)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests.conftest import shared_path

BENCH = Path(__file__).resolve().parent.parent / "bench" / "mbd_honest.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(BENCH), *args], capture_output=True, text=True,
                          timeout=120)


def test_mbd_honest_json_on_the_default_scenario():
    out = _run("--json", "--dataset", "scenario:highway-braking", "--per", "30")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    (r,) = result["datasets"]
    assert result["mode"] == "offline" and r["per"] == 30
    assert r["host"] == "host" and r["rvs"] == 16 and 0 < r["rv_frames"] < 8000
    assert r["reports"] == sum(r["reports_by_check"].values())
    assert r["quarantined_frames"] == sum(q["frames"] for q in r["quarantines"].values())
    assert set(r["warnings"]) == {"fcw", "eebl", "bsw", "lcw"}
    for w in r["warnings"].values():
        assert w["ticks_lost"] == sum(w["lost_by_vehicle"].values())


def test_mbd_honest_on_the_ngsim_scene_and_settings():
    spec = f"scene:ngsim:{shared_path('ngsim-i80-pairs')}"
    out = _run("--no-apps", "--dataset", spec, "--set", "sa_safety_range_m=5")
    assert out.returncode == 0, out.stderr
    assert "host 232, 45 RVs, 67.8 s" in out.stdout and "sa_safety_range_m=5" in out.stdout
    bad = _run("--set", "no_such_threshold=1")
    assert bad.returncode != 0 and "expected KEY=VALUE" in bad.stderr


def test_mbd_honest_skips_absent_data(tmp_path):
    out = _run("--json", "--dataset", f"scene:ngsim:{tmp_path / 'absent'}")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["datasets"] == [] and "not present" in next(iter(result["skipped"].values()))


def test_mbd_honest_draws_hosts_of_a_scene():
    spec = f"scene:ngsim:{shared_path('ngsim-i80-pairs')}"
    out = _run("--json", "--dataset", spec, "--hosts", "2", "--seed", "5")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    (summary,) = result["hosts"].values()
    assert summary["hosts"] == len(result["datasets"]) == 2
    assert len({r["host"] for r in result["datasets"]}) == 2
    assert summary["rv_frames"] == sum(r["rv_frames"] for r in result["datasets"])
    assert "warnings" not in result["datasets"][0]  # --hosts skips the apps
