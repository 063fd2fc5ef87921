"""The neural baselines (ae, ae-d, lstm, lstm-d): their series, the chained forecasts, the
batched forecasts, training (a smoke run of a few hundred steps) and the shipped weights
on real trips they were not trained on."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from catc.predict.base import Observation
from catc.predict.nn import NN_NAMES, Network, NnConfig, roll, to_forecast, window
from tests.conftest import shared_path

torch = pytest.importorskip("torch", reason="the nn extra (PyTorch) is not installed")


def random_network(name: str, seed: int = 0) -> Network:
    """A real model of ``name``'s architecture with random weights (no training)."""
    from catc.predict.nn import build

    torch.manual_seed(seed)
    c = NnConfig.for_name(name)
    m = build(c).eval()
    out = (c.tw if c.kind == "ae" else c.horizon, c.channels)
    return Network(c, m, np.zeros(2), np.ones(2), np.zeros(out), np.full(out, 0.5))


# --- the series ------------------------------------------------------------------------------


def test_direct_window_is_along_and_right_of_the_last_heading() -> None:
    """A vehicle driving east at 10 m/s, 0.5 m right of its path 1 s ago; BSMs at 0.1 s
    steps with two lost: the window is along-track distance (negative: behind) and
    offset to the right, interpolated across the losses."""
    t = np.array([0.0, 0.1, 0.2, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0])
    x = 100.0 + 10.0 * t
    y = 50.0 - 0.5 * (1.0 - t)  # south of the final lane line = right of an eastbound car
    w = window(t, x, y, np.full(9, 10.0), np.full(9, 90.0), direct=True, tw=11)
    np.testing.assert_allclose(w[:, 0], -10.0 * (1.0 - np.arange(11) * 0.1), atol=1e-9)
    np.testing.assert_allclose(w[:, 1], 0.5 * (1.0 - np.arange(11) * 0.1), atol=1e-9)


def test_indirect_window_unwraps_the_heading_across_north() -> None:
    t = np.arange(4) * 0.1
    w = window(t, np.zeros(4), np.zeros(4), np.array([5.0, 6.0, 7.0, 8.0]),
               np.array([350.0, 355.0, 0.0, 5.0]), direct=False, tw=6)
    np.testing.assert_allclose(w[:, 0], [5.0, 5.0, 5.0, 6.0, 7.0, 8.0])
    np.testing.assert_allclose(np.degrees(w[:, 1]), [-15, -15, -15, -10, -5, 0], atol=1e-9)


def test_indirect_forecast_integrates_speed_and_heading() -> None:
    """Speed 10 m/s, heading turning 1°/step from 90°: positions by the trapezoid rule."""
    n = 20
    series = np.stack([np.full(n, 10.0), np.radians(np.arange(1, n + 1))], axis=1)
    last = Observation(0.0, 5.0, 7.0, 10.0, 90.0)
    f = to_forecast(series, last, direct=False, source="lstm")
    h = np.radians(90.0 + np.arange(n + 1))
    vx, vy = 10.0 * np.sin(h), 10.0 * np.cos(h)
    x = 5.0 + np.concatenate(([0.0], np.cumsum(0.05 * (vx[1:] + vx[:-1]))))
    y = 7.0 + np.concatenate(([0.0], np.cumsum(0.05 * (vy[1:] + vy[:-1]))))
    np.testing.assert_allclose(f.x, x, atol=1e-9)
    np.testing.assert_allclose(f.y, y, atol=1e-9)
    assert f.heading[-1] == pytest.approx(110.0)
    assert f.source == ["bsm"] + ["lstm"] * n


def test_direct_forecast_rotates_back_and_derives_speed() -> None:
    """Along-track 1.5 m per step, heading 0 (north): y grows 1.5 m per step, 15 m/s."""
    n = 10
    series = np.stack([1.5 * np.arange(1, n + 1), np.zeros(n)], axis=1)
    f = to_forecast(series, Observation(0.0, 1.0, 2.0, 15.0, 0.0), direct=True,
                    source="ae-d")
    np.testing.assert_allclose(f.x, 1.0, atol=1e-9)
    np.testing.assert_allclose(f.y, 2.0 + 1.5 * np.arange(n + 1), atol=1e-9)
    np.testing.assert_allclose(f.speed, 15.0, atol=1e-9)
    np.testing.assert_allclose(f.heading % 360.0, 0.0, atol=1e-9)


def reference(series: np.ndarray, direct: bool) -> np.ndarray:
    """What is subtracted from each row to put a window in the frame of its last row: the
    whole position (direct), the heading alone (indirect; speed stays absolute)."""
    ref = series[..., -1, :].copy()
    if not direct:
        ref[..., 0] = 0.0
    return ref


@pytest.mark.parametrize("name", NN_NAMES)
def test_chained_forecasts_see_their_own_frame(name: str) -> None:
    """roll(): the second pass of a chain is the model applied to the last ``tw`` states
    of history and first pass, moved into the frame of its last state and back."""
    net = random_network(name)
    c = net.config
    rng = np.random.default_rng(1)
    w = np.cumsum(rng.normal(0.0, 0.3, (3, c.tw, 2)), axis=1)
    w -= reference(w, c.direct)[:, None, :]
    per = 1 if c.kind == "ae" else c.horizon
    both = roll(net, w, 2 * per)
    first = roll(net, w, per)
    np.testing.assert_allclose(both[:, :per], first, rtol=1e-6, atol=1e-9)
    seq = np.concatenate([w, first], axis=1)[:, -c.tw:]
    ref = reference(seq, c.direct)[:, None, :]
    out = net(seq - ref) + ref
    np.testing.assert_allclose(both[:, per:], out[:, -1:] if c.kind == "ae" else out,
                               rtol=1e-6, atol=1e-9)


# --- the predictor ---------------------------------------------------------------------------


def _feed(p, n: int = 40, drop: int = 3) -> float:
    t = 0.0
    for k in range(n):
        t = 0.1 * k
        if k % drop:
            p.update(Observation(t, 10.0 * t, 2.0 + 0.01 * k * k, 10.0, 89.0, 0.2, 0.5))
    return t


@pytest.mark.parametrize("name", NN_NAMES)
def test_batched_forecasts_are_the_one_by_one_forecasts(name: str) -> None:
    from catc.predict.nn import NnPredictor, forecast_many_at

    net = random_network(name, seed=3)
    alone = [NnPredictor(name, net) for _ in range(4)]
    batch = [NnPredictor(name, net) for _ in range(4)]
    ends = []
    for k, (a, b) in enumerate(zip(alone, batch, strict=True)):
        ends.append(_feed(a, 30 + 5 * k, drop=2 + k))
        _feed(b, 30 + 5 * k, drop=2 + k)
    assert forecast_many_at([(b, e + 2.5) for b, e in zip(batch, ends, strict=True)]) == 4
    for a, b, e in zip(alone, batch, ends, strict=True):
        for dt in (0.05, 0.1, 1.0, 2.5, 7.0):
            pa, pb = a.predict(e + dt), b.predict(e + dt)
            assert (pa.x, pa.y) == (pytest.approx(pb.x, abs=1e-5), pytest.approx(pb.y, abs=1e-5))
            assert pa.source == name


def test_forecasts_grow_by_doubling_and_keep_their_first_states() -> None:
    """An AE forecast starts 0.5 s long (each state is a pass of the chain) and doubles
    when the gap outgrows it; the LSTM's is one pass (3 s).  A longer forecast's first
    states are the shorter one's."""
    from catc.predict.nn import NnPredictor

    p = NnPredictor("ae", random_network("ae", seed=5))
    _feed(p)
    end = p._obs[-1].t
    a = p.predict(end + 0.1)
    assert p._forecast.end == pytest.approx(0.5)
    early = [p.predict(end + k * 0.1) for k in range(1, 6)]
    p.predict(end + 0.7)
    assert p._forecast.end == pytest.approx(1.0)
    p.predict(end + 2.5)
    assert p._forecast.end == pytest.approx(2.5)
    again = [p.predict(end + k * 0.1) for k in range(1, 6)]
    for e, g in zip(early, again, strict=True):
        assert (e.x, e.y) == (pytest.approx(g.x, abs=1e-6), pytest.approx(g.y, abs=1e-6))
    assert a.source == "ae"
    q = NnPredictor("lstm", random_network("lstm"))
    end = _feed(q)
    q.predict(end + 0.1)
    assert q._forecast.end == pytest.approx(3.0)


def test_prepare_stacks_exactly_the_predictors_it_says() -> None:
    """catc.predict.STACKED (which the sweep's lockstep replay uses to skip the call) names
    every predictor for which prepare_at makes forecasts, and no other."""
    from catc.predict import NAMES, STACKED, make_predictor, prepare_at

    for name in NAMES:
        p = make_predictor(name)
        end = _feed(p)
        assert (prepare_at([(p, end + 1.0)]) > 0) == (name in STACKED), name


def test_too_few_bsms_is_constant_speed_and_a_fresh_bsm_is_itself() -> None:
    from catc.predict.nn import NnPredictor

    p = NnPredictor("lstm", random_network("lstm"))
    with pytest.raises(LookupError):
        p.predict(0.0)
    p.update(Observation(0.0, 0.0, 0.0, 10.0, 90.0))
    q = p.predict(1.0)
    assert (q.x, q.y, q.source) == (pytest.approx(10.0), pytest.approx(0.0), "cs")
    _feed(p)
    r = p.predict(3.8)
    assert (r.source, r.x) == ("bsm", pytest.approx(38.0))
    with pytest.raises(ValueError):
        p.update(Observation(9.0, math.nan, 0.0, 1.0, 0.0))


#: Python source that makes ``import torch`` fail as on a machine without the extra.
NO_TORCH = """
import sys
class NoTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ModuleNotFoundError("No module named 'torch'")
sys.meta_path.insert(0, NoTorch())
"""


def test_without_pytorch_the_predictors_say_how_to_install_it() -> None:
    """With torch unimportable: make_predictor and every command that takes a predictor
    answer in one line with the install command, and the default predictor list leaves
    the neural ones out."""
    code = NO_TORCH + """
from catc.predict import available, make_predictor
print(",".join(available()))
try:
    make_predictor("lstm")
except ValueError as err:
    print(type(err).__name__, err)
from captures.cli import main
sys.exit(main(["sweep", "--dataset", "scenario:highway-braking", "--predictors", "ae-d"]))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    lines = done.stdout.splitlines()
    assert lines[0] == "hold,cs,ca,kf,ctrv,imm,hgp,hgp-d"
    assert lines[1].startswith("MissingExtra ") and "pip install 'catc-hil[nn]'" in lines[1]
    assert done.returncode == 2
    err = done.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("captures sweep: ") and "catc-hil[nn]" in err[0]
    obu = subprocess.run([sys.executable, "-c", NO_TORCH + "from obu.cli import main\n"
                          "sys.exit(main(['run', '--predictor', 'lstm', '--duration', '1']))"],
                         capture_output=True, text=True, timeout=60)
    assert obu.returncode == 2
    assert obu.stderr.strip().startswith("obu run: ") and "catc-hil[nn]" in obu.stderr


# --- training ----------------------------------------------------------------------------------


def test_training_smoke_run_learns_and_writes_loadable_models(tmp_path) -> None:
    """A few hundred optimiser steps of the AE and the direct LSTM on NGSIM pairs, split by
    trip: the validation loss falls below the untrained model's, and the files load as
    predictors through CATC_NN_DIR (CI runs this, not the full training)."""
    data = shared_path("ngsim-i80-pairs")
    done = subprocess.run(
        [sys.executable, "-m", "captures.cli", "train-nn", "--dataset", f"ngsim:{data}",
         "--max-trips", "20", "--models", "ae,lstm-d", "--steps", "300", "--examples",
         "2400", "--val-examples", "400", "--batch", "16", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads((tmp_path / "train-nn.json").read_text())
    assert set(summary) == {"ae", "lstm-d"}
    for name in ("ae", "lstm-d"):
        from catc.predict.nn import load

        net = load(tmp_path / f"{name}.pt")
        hist = net.meta["history"]
        assert net.meta["steps"] == 300
        assert net.meta["val_loss"] < 0.8 * hist[0]["val_loss"], hist
        assert len(net.meta["validation_trips"]) == 3  # 15 % of 20 trips, by trip
    code = ("from catc.predict import make_predictor; from catc.predict.base import "
            "Observation as O; p = make_predictor('lstm-d'); "
            "[p.update(O(0.1 * k, 2.0 * k, 0.0, 20.0, 90.0)) for k in range(30)]; "
            "print(p.predict(3.9).x)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=dict(os.environ, CATC_NN_DIR=str(tmp_path)), timeout=60)
    assert out.returncode == 0, out.stderr
    assert 58.0 + 5.0 < float(out.stdout) < 58.0 + 40.0  # 1 s on at 20 m/s: about 78 m


def test_training_flags_are_checked(tmp_path) -> None:
    for flags, words in ((["--models", "gru"], "unknown model 'gru'"),
                         (["--val-fraction", "1.5"], "--val-fraction"),
                         (["--dataset", str(tmp_path / "nope")], "no such file")):
        cmd = [sys.executable, "-m", "captures.cli", "train-nn", "--out", str(tmp_path)]
        if "--dataset" not in flags:
            cmd += ["--dataset", "scenario:highway-braking"]
        done = subprocess.run(cmd + flags, capture_output=True, text=True, timeout=60)
        assert done.returncode == 2
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], lines


# --- the shipped weights on real trips they were not trained on ------------------------------


def test_shipped_models_on_a_held_out_run() -> None:
    """On an OpenACC handling run held out of training (tight curves, unlike the training
    runs), at PER 50 % and 90 %: every neural baseline tracks far better than holding the
    last BSM, and the indirect LSTM better than constant speed and heading at PER 90 %:
    it learned more than the last speed and heading."""
    from dataclasses import replace
    from functools import partial

    from catc.evaluate import evaluate
    from catc.predict import make_predictor
    from hil.datasets import load

    table = load(str(shared_path("openacc-zalazone", "no_ACC_handling_part40.csv")))[0]
    for name in NN_NAMES:
        meta = make_predictor(name).net.meta
        assert "no_ACC_handling_part40.csv" in meta["holdout"]
        assert "no_ACC_handling_part40.csv" not in meta["trained_on"]
    table = replace(table, tracks=dict(list(table.tracks.items())[:5]))
    names = ("hold", "cs", *NN_NAMES)
    scores = evaluate([table], {n: partial(make_predictor, n) for n in names}, [0.5, 0.9])
    pte = {(s.predictor, s.per): s.pte95_m for s in scores}
    for per in (0.5, 0.9):
        for name in NN_NAMES:
            assert pte[name, per] < 0.2 * pte["hold", per], (name, per, pte)
    assert pte["lstm", 0.9] < pte["cs", 0.9], pte
