"""The host on the vehicle side against the private host channel: the same dataset, the
same channel, both through the daemons as separate processes.

``rve run --host-bus`` plays the car: its CAN bus through the RAV4 profile's DBC (as a
serial slcan adapter on a pty) and its GNSS receiver's NMEA (UDP on 127.0.0.1); ``obu run
--host-source vehicle`` reads both, estimates the host (catc.hoststate) and ticks on GNSS
time.  Against the same run on the private channel (the host as a ready-made BSM), at
PER 0 % and 50 %:

* PTE95 within 5 % (the RVs' tracks do not depend on how the host is known);
* the same FCW events, on the same RV, each start within two ticks and each end within
  one tick before to 0.4 s after.  The host is no longer the track itself but its
  estimate: its acceleration is CAN's, low-passed at 1 Hz as SAE J2945/1 asks (time
  constant 0.16 s), so while it brakes hard (8 m/s²) it lags the track's, and CAMP
  Linear's warning range, which shrinks as the host brakes, shrinks later (the end at
  21.0 s comes at 21.3 s); and its speed is the newest wheel-speed frame's (83 Hz), up
  to 0.1 m/s behind while braking.  Where the range is within 0.2 m of the warning
  range (the second start, 15.60 m against 15.77 m) that moves the start by two ticks.

GNSS noise is 0 here, so that what differs is the path itself (the receiver's 0.1 s
latency included); with rve's default 0.5 m of noise the starts move by up to 0.2 s
(the note of issue 29 has both).
"""

from __future__ import annotations

import json

import pytest

from captures.live import run_daemons, vehicle_flags
from captures.score import score

DATASET = "scenario:highway-braking"
SPEED = 4.0
TICK = 0.1


def _run(out, per: int, vehicle: bool) -> tuple[dict, list[tuple[str, str, float]]]:
    rve = ["--dataset", DATASET, "--per", str(per), "--speed", str(SPEED), "--seed", "1",
           "--duration", "30"]
    obu = ["--predictor", "hgp"]
    if vehicle:
        r, o = vehicle_flags(out, SPEED)
        rve += [*r, "--gnss-noise", "0"]
        obu += o
    run_daemons(out, rve, obu)
    events = []
    for line in (out / "obu.events.jsonl").read_text().splitlines():
        e = json.loads(line)
        if e["app"] == "fcw":
            events.append((e["kind"], e["rv"], round(e["t"], 1)))
    return score(out), events


@pytest.mark.parametrize("per", [0, 50])
def test_the_vehicle_path_scores_as_the_private_channel(tmp_path, per):
    channel, ev_channel = _run(tmp_path / "channel", per, vehicle=False)
    car, ev_car = _run(tmp_path / "vehicle", per, vehicle=True)
    assert car["complete"], car["run"]  # a tick at every host sample of the replay
    assert car["pte95_m"] == pytest.approx(channel["pte95_m"], rel=0.05)
    assert ev_channel, "the scenario's leader brakes: FCW must fire"
    assert [(k, rv) for k, rv, _ in ev_car] == [(k, rv) for k, rv, _ in ev_channel]
    for (kind, _, t_car), (_, _, t_ch) in zip(ev_car, ev_channel, strict=True):
        if kind == "start":
            assert abs(t_car - t_ch) <= 2 * TICK + 1e-9, (ev_car, ev_channel)
        else:
            assert -TICK - 1e-9 <= t_car - t_ch <= 0.4 + 1e-9, (ev_car, ev_channel)
    counters = json.loads((tmp_path / "vehicle" / "obu.counters.json").read_text())
    assert counters.get("host_channel_ignored", 0) == 0
    assert counters.get("can_bad_checksum", 0) == 0 and counters["can_SPEED"] > 1_000
    assert counters["nmea_fixes"] >= 290 and counters["slcan_frames"] > 9_000  # 30 s
