"""The RVE's CAN captures (candump log and ASC) decode back to exactly the frames that a
receiver got on the bus, and ``captures decode`` reads both; a broken transfer in a log
is counted, not decoded into garbage."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from captures.canlog import can_log_kind, read_can_log
from tests.test_rve_can import replay_in_process


def _run_rve(tmp_path, fd: bool):
    """The RVE's replay on python-can's virtual bus with a capture, and what a receiver got."""
    counts, got, _stats = replay_in_process("virtual", f"canlog-{fd}", fd, tmp_path)
    return counts, got


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_both_can_logs_reassemble_into_what_the_receiver_got(tmp_path, fd):
    counts, got = _run_rve(tmp_path, fd)
    want = [(ch, data) for ch, data in got]
    assert len(want) == counts["sent"] + counts["host"] > 0
    ids = {"6A0": "rv", "6A1": "host"}
    for name, kind in (("rve.frames.log", "candump"), ("rve.frames.asc", "asc")):
        path = tmp_path / name
        assert can_log_kind(path.read_text()) == kind
        found = read_can_log(path, kind)
        assert not found.isotp_errors
        assert [(ids[f.meta["can_id"]], f.frame) for f in found.frames] == want, name
        assert all(f.meta["fd"] == fd for f in found.frames)
    first = (tmp_path / "rve.frames.log").read_text().splitlines()[0]
    assert f" canlog-{fd} 6A" in first and ("##" in first) == fd


def test_captures_decode_reads_the_candump_log_and_counts_a_broken_transfer(tmp_path):
    counts, _got = _run_rve(tmp_path, False)
    log = tmp_path / "rve.frames.log"
    cli = [sys.executable, "-m", "captures.cli", "decode"]
    ok = subprocess.run([*cli, str(log)], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
    records = [json.loads(line) for line in ok.stdout.splitlines()]
    assert len(records) == counts["sent"] + counts["host"]
    assert all(r["lat"] is not None for r in records)
    # drop the 2nd Consecutive Frame of the first multi-frame transfer on 6A0
    lines = log.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if " 6A0#1" in line)
    cfs = [i for i in range(first + 1, len(lines)) if " 6A0#2" in lines[i]]
    broken = tmp_path / "broken.log"
    broken.write_text("\n".join(lines[:cfs[1]] + lines[cfs[1] + 1:]) + "\n")
    bad = subprocess.run([*cli, str(broken)], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1
    assert "broken ISO-TP transfer(s): wrong_sequence_number" in bad.stderr
    assert len(bad.stdout.splitlines()) == len(records) - 1


def test_a_can_log_that_is_not_one_is_a_one_line_error(tmp_path):
    path = tmp_path / "x.log"
    path.write_text("(1.0) vcan0 6A0#0201\n(2.0) vcan0 zz#\n")
    r = subprocess.run([sys.executable, "-m", "captures.cli", "decode", str(path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode in (1, 2) and len(r.stderr.strip().splitlines()) == 1, r.stderr
