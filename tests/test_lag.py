"""Load you can see (issue 27): the OBU measures the lag from a frame's arrival (the
kernel's stamp) to the decision of the tick that used it, counts a tick decided more than
a tick period after its host frame arrived as a deadline miss, and its lag is the latency
that ``captures score`` measures from the RVE's and the OBU's captures.

Before, an OBU 1 s behind real time reported tick p99 20.5 ms and no deadline miss: the
step was fast, the wait in the socket buffer was invisible.  Here the OBU process is
stopped (SIGSTOP) for 0.6 s in the middle of a real run, the frames wait in its socket."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from hil.transport.udp import free_ports
from tests.test_obu import finish, score, start_obu

PY = sys.executable


@pytest.mark.slow
def test_a_stalled_obu_reports_its_lag_and_the_score_agrees(tmp_path):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca")
    rve = subprocess.Popen(
        [PY, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}", "--host-to",
         f"127.0.0.1:{ports[1]}", "--no-progress", "--dataset", "scenario:highway-braking",
         "--speed", "4", "--duration", "24", "--capture", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)  # in the run (6 s of wall time at speed 4)
    os.kill(obu.pid, signal.SIGSTOP)
    try:
        time.sleep(0.6)
    finally:
        os.kill(obu.pid, signal.SIGCONT)
    _, err = rve.communicate(timeout=120)
    assert rve.returncode == 0, err
    finish(obu)
    c = json.loads((tmp_path / "obu.counters.json").read_text())
    s = score(tmp_path)
    # the stall is seen: lag over the stall, late ticks counted as deadline misses
    assert c["lag_ms_max"] > 400 and c["host_lag_ms_max"] > 400, c
    assert c["deadline_misses_late"] >= 4 and c["deadline_misses"] >= c["deadline_misses_late"]
    assert c["rx_socket_drops"] == 0
    # the OBU's lag is the score's latency (send -> decision), within 10 %
    lat = s["latency_ms"]
    for q in ("p50", "p99"):
        assert c[f"lag_ms_{q}"] == pytest.approx(lat[q], rel=0.10), (q, c, lat)
    assert c["lag_ms_max"] == pytest.approx(lat["max"], rel=0.10)
    # and the score says the OBU fell behind, on its first line
    assert s["late"]["lagging"] and s["late"]["messages"] > 0, s["late"]
    text = subprocess.run([PY, "-m", "captures.cli", "score", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert text.returncode == 0 and text.stdout.startswith("LAGGING: "), text.stdout
