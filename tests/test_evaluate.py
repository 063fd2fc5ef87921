"""Offline PTE evaluation and kernel bank training on synthetic and real trips."""

from __future__ import annotations

import hashlib
import io
import json
import math
import subprocess
import sys
import time
from functools import partial

import numpy as np
import pytest

from captures.progress import Progress
from catc.channel import bernoulli_received
from catc.evaluate import evaluate, replay_track
from catc.mobility import MobilityTable, Track
from catc.predict import NAMES, make_predictor
from catc.predict.bank import KernelBank, default_bank
from catc.predict.training import TrainConfig, cluster, persistency, train
from tests.conftest import shared_path


def circle_track(name: str = "RV", n: int = 400, v: float = 12.0, radius: float = 150.0,
                 accel_period: float = 20.0) -> Track:
    """A vehicle on a circle whose speed oscillates (like the ZalaZONE dynamic platform)."""
    t = np.arange(n) * 0.1
    speed = v + 2.0 * np.sin(2 * np.pi * t / accel_period)
    accel = 2.0 * 2 * np.pi / accel_period * np.cos(2 * np.pi * t / accel_period)
    s = np.concatenate(([0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * 0.1)))
    phi = s / radius  # clockwise around the centre
    x, y = radius * np.sin(phi), radius * np.cos(phi) - radius
    heading = (np.degrees(phi) + 90.0) % 360.0
    yaw = np.degrees(speed / radius)
    nan = np.full(n, np.nan)
    return Track(name, t, x, y, nan, nan, nan, speed, heading, accel, yaw)


def table(*tracks: Track) -> MobilityTable:
    return MobilityTable("synthetic", "synthetic", (0.0, 0.0, 0.0),
                         {tr.vehicle_id: tr for tr in tracks})


@pytest.mark.parametrize("name", NAMES)
def test_per_zero_gives_zero_error(name):
    tr = circle_track(n=120)
    errors = replay_track(tr, make_predictor(name), np.ones(len(tr), dtype=bool))
    assert np.nanmax(errors) < 1e-9


def test_hold_error_is_the_distance_travelled_since_the_last_bsm():
    tr = circle_track(n=200)
    received = bernoulli_received(0, "RV", len(tr), 0.5)
    errors = replay_track(tr, make_predictor("hold"), received)
    last = None
    for i in range(len(tr)):
        if received[i]:
            last = i
        if last is None:
            assert math.isnan(errors[i])
        else:
            assert errors[i] == pytest.approx(math.hypot(tr.x[i] - tr.x[last],
                                                         tr.y[i] - tr.y[last]), abs=1e-9)


def test_evaluate_scores_every_predictor_on_the_same_losses():
    trips = [table(circle_track("A"), circle_track("B", v=8.0))]
    scores = evaluate(trips, {n: partial(make_predictor, n) for n in ("hold", "cs", "hgp")},
                      [0.0, 0.8], seeds=(0, 1))
    by = {(s.predictor, s.per): s for s in scores}
    assert by["hold", 0.0].pte95_m == 0.0
    assert by["hold", 0.8].n_ticks == by["hgp", 0.8].n_ticks  # same ticks scored
    assert by["hgp", 0.8].pte95_m < by["cs", 0.8].pte95_m < by["hold", 0.8].pte95_m
    assert by["hold", 0.8].exceedances[0.2] >= by["hold", 0.8].exceedances[1.6]


def test_training_builds_a_bank_and_clusters_it():
    tracks = [circle_track("A", n=300), circle_track("B", n=300, v=6.0, accel_period=8.0)]
    result = train(tracks, TrainConfig(horizon_s=1.0, pte_th=0.05))
    assert result.new_models >= 1 and len(result.bank) == result.new_models
    assert result.steps == 2 * (300 - 30 - 10 + 1)
    assert all(mp >= 0 for mp in result.mp_s)
    small = cluster(result.bank, 1)
    assert len(small) == 1
    p = persistency(tracks, result.bank, TrainConfig(pte_th=0.05))
    assert p["mp_mean_s"] > 0 and 0 <= p["new_kernel_rate"] <= 1


def test_bank_json_round_trip_and_errors():
    bank = KernelBank(np.array([[1.0, 2.0, 3.0]]), np.array([[4.0, 5.0, 6.0]]), {"k": "v"})
    again = KernelBank.from_json(bank.to_json())
    assert np.array_equal(again.speed, bank.speed) and again.meta == {"k": "v"}
    for bad in ("nope", json.dumps({"format": "other"}),
                json.dumps({"format": "catc-kernel-bank/1", "speed": [[1, 2, 3]]})):
        with pytest.raises(ValueError):
            KernelBank.from_json(bad)
    with pytest.raises(ValueError):
        KernelBank(np.array([[1.0, -2.0, 3.0]]), np.array([[1.0, 2.0, 3.0]]))


def test_default_bank_is_trained_and_says_how():
    bank = default_bank()
    assert len(bank) == 16
    assert bank.meta["command"].startswith("captures train-bank")
    assert bank.meta["stats"]["pairs_before_clustering"] > 16
    assert bank.meta["trained_on"]


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_is_a_line_per_tenth_off_a_terminal_and_a_tqdm_bar_on_one():
    log = io.StringIO()
    with Progress("job", log) as progress:
        for done in range(1, 41):
            progress(done * 0.25, 10.0)  # the sweep counts fractional costs
            if done == 20:
                progress.write("a line of the command")
        progress(10.0, 10.0)  # after the end: nothing more
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and lines[6] == "a line of the command"
    assert [line.split("%")[0] for line in lines if line.startswith("job: ")] == [
        f"job: {p}" for p in (2, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100)]
    assert lines[-1].startswith("job: 100% (") and len(lines) == 12
    tty = _Terminal()
    with Progress("job", tty) as progress:
        time.sleep(0.25)  # a bar from the first report after 0.2 s
        progress(3, 10)  # left early: the bar stays at its last state
    assert tty.getvalue().startswith("\rjob:  30%|") and tty.getvalue().endswith("\n")


def test_cli_evaluate_and_train_bank_on_real_data(tmp_path):
    data = shared_path("openacc-zalazone", "short_setting_dynamic_part22.csv")
    out = subprocess.run(
        [sys.executable, "-m", "captures.cli", "evaluate", "--dataset", str(data),
         "--per", "0,80", "--predictors", "ca,hgp", "--json", str(tmp_path / "rows.json")],
        capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stderr
    progress = [line for line in out.stderr.splitlines() if line.startswith("evaluate: ")]
    assert "\r" not in out.stderr and 2 <= len(progress) <= 11  # a pipe: a line per 10 %
    assert progress[-1].startswith("evaluate: 100% (")
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert {(r["predictor"], r["per"]) for r in rows} == {("ca", 0), ("ca", 80), ("hgp", 0),
                                                         ("hgp", 80)}
    assert all(r["pte95_m"] == 0 for r in rows if r["per"] == 0)
    bank = tmp_path / "bank.json"
    out = subprocess.run(
        [sys.executable, "-m", "captures.cli", "train-bank", "--dataset", str(data),
         "--cluster", "4", "--h2-tracks", "2", "--out", str(bank)],
        capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stderr
    assert "bank before clustering" in out.stdout
    trained = KernelBank.from_json(bank.read_text())
    assert len(trained) <= 4
    assert trained.meta["trained_on"] == {data.name: hashlib.sha256(data.read_bytes()).hexdigest()}
    bad = subprocess.run([sys.executable, "-m", "captures.cli", "evaluate", "--dataset",
                          str(tmp_path / "missing.csv")], capture_output=True, text=True,
                         timeout=60, check=False)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
