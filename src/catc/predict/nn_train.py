"""Training the neural baselines of :mod:`catc.predict.nn` on mobility tables.

Examples.  An example is one vehicle at one 10 Hz sample ``i`` (a received BSM, the
forecast's origin), the BSMs received before it, and the truth after it.  The BSMs
received are drawn as the RVE's channel drops them (:mod:`catc.channel`): with
probability ``rate_share`` a reduced rate (5, 3, 2 or 1 Hz, no loss), else independent
loss at a PER drawn from the paper's grid (0 to 95 %), by gaps between received
messages.  The input is the window a predictor would build from them
(:func:`catc.predict.nn.window`, the same code), so training meets the windows the
sweep and the OBU give.  Every epoch draws new examples and new losses; the validation
set is drawn once (fixed seed) from trips that are not trained on: the split is by trip.

Examples whose span (window and horizon) holds a GNSS glitch are left out
(:func:`glitches`: a step whose displacement disagrees with the reported speed by more
than 4 m/s, e.g. a position frozen for a sample or one jumping metres, or that moves
sideways faster than 2 m/s: 90 of 50,158 steps of the OpenACC training runs, 8 of
NGSIM's 89,076).  The examples around them were 1 % of all and 74 % of the direct AE's
squared error, so MSE training spent itself on them.

Targets (in the frame of the origin, as the inputs):

* LSTM: the next :data:`~catc.predict.nn.HORIZON` true states (3 s);
* AE: the true window one step later (its last row is the next state).  Its loss is the
  window's mean squared error plus the next state's: an autoencoder that only
  reconstructed would put 29/30 of its loss on copying its input.

Both are fitted with Adam on the MSE of standardised outputs (each output element
standardised by the training set), the learning rate halved after ``patience // 2``
epochs without a better validation loss, and stopped after ``patience`` (early
stopping); the best epoch's weights are kept.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from catc.mobility import MobilityTable, Track
from catc.predict.forecast import DT, constant_speed
from catc.predict.nn import (
    Network,
    NnConfig,
    build,
    from_state,
    heading_frame,
    roll,
    to_forecast,
    torch_module,
    window,
)

#: The paper's PER grid, as fractions.
PERS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)
#: Reduced transmission rates drawn for ``rate_share`` of the examples, Hz.
RATES = (5.0, 3.0, 2.0, 1.0)


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 80
    steps: int = 0  # stop after this many optimiser steps in all (0: no limit)
    examples: int = 50_000  # drawn per epoch
    val_examples: int = 8_000
    batch: int = 128
    lr: float = 1e-3
    weight_decay: float = 0.0
    patience: int = 6  # epochs without a better validation loss before stopping
    rate_share: float = 0.25
    min_points: int = 4  # BSMs an example's history has at least (the predictor's rule)
    glitch_speed: float = 4.0  # m/s, see glitches()
    seed: int = 0


@dataclass
class Examples:
    """Inputs (N, tw, 2), targets (N, ...) and the origins' states, all float64."""

    x: np.ndarray
    y: np.ndarray
    origin: np.ndarray  # (N, 5): x, y, speed, heading (deg) of the origin BSM, and PER
    future: np.ndarray  # (N, horizon, 2): the true positions after the origin (ENU m)


@dataclass
class TrainResult:
    network: Network
    history: list[dict] = field(default_factory=list)
    best_epoch: int = 0
    steps: int = 0
    seconds: float = 0.0


def _series(tr: Track, direct: bool, i: int, idx: np.ndarray) -> np.ndarray:
    """The true series at sample indices ``idx`` in the frame of sample ``i``."""
    if direct:
        return np.stack(heading_frame(tr.x[idx] - tr.x[i], tr.y[idx] - tr.y[i],
                                      float(tr.heading[i])), axis=1)
    lo, hi = min(int(idx.min()), i), max(int(idx.max()), i)
    head = np.unwrap(np.radians(tr.heading[lo:hi + 1]))
    return np.stack([tr.speed[idx], head[idx - lo] - head[i - lo]], axis=1)


def glitches(tr: Track, tolerance: float = 4.0, lateral: float = 2.0) -> np.ndarray:
    """Per step k → k+1 of ``tr``: does the displacement disagree with the mean reported
    speed by more than ``tolerance`` m/s (a GNSS position that froze or jumped), or move
    sideways to the reported heading faster than ``lateral`` m/s (a lane change moves at
    about 1 m/s)?"""
    dt = np.diff(tr.t)
    dx, dy = np.diff(tr.x), np.diff(tr.y)
    h = np.radians(tr.heading[:-1])
    moved = np.hypot(dx, dy) / dt
    side = np.abs(dx * np.cos(h) - dy * np.sin(h)) / dt
    return (np.abs(moved - 0.5 * (tr.speed[1:] + tr.speed[:-1])) > tolerance) | (side > lateral)


def _received(rng: np.random.Generator, i: int, per: float, step: int, keep: int
              ) -> np.ndarray:
    """Indices ≤ i of the BSMs received, newest first (at most ``keep``): every ``step``-th
    sample sent, each lost with probability ``per``; sample i itself is received."""
    out = [i]
    j = i
    while len(out) < keep:
        gap = step * (int(rng.geometric(1.0 - per)) if per > 0 else 1)
        j -= gap
        if j < 0:
            break
        out.append(j)
    return np.array(out[::-1])


def examples(tracks: Sequence[Track], config: NnConfig, n: int, rng: np.random.Generator,
             train: TrainConfig) -> Examples:
    """``n`` examples from ``tracks`` (module docstring), drawn with ``rng``."""
    h = config.horizon
    need = max(h, 1)
    usable = [tr for tr in tracks if len(tr) > need + 1]
    weights = np.array([len(tr) - need - 1 for tr in usable], dtype=float)
    if not usable:
        raise ValueError("no track is long enough for a training example")
    weights /= weights.sum()
    # glitch steps before each sample, to test a span in O(1)
    bad = [np.concatenate(([0], np.cumsum(glitches(tr, train.glitch_speed)))) for tr in usable]
    xs, ys, origin, future = [], [], [], []
    while len(xs) < n:
        k = int(rng.choice(len(usable), p=weights))
        tr = usable[k]
        i = int(rng.integers(0, len(tr) - need - 1))
        if rng.random() < train.rate_share:
            per, step = 0.0, round(10.0 / float(rng.choice(RATES)))
        else:
            per, step = float(rng.choice(PERS)), 1
        idx = _received(rng, i, per, step, config.tw + 1)
        if len(idx) < train.min_points:
            continue
        first = max(0, min(int(idx[0]), i - config.tw))
        if bad[k][i + need] - bad[k][first] > 0:
            continue  # a glitch in the window or the horizon
        t = tr.t[idx]
        if abs((tr.t[i + need] - tr.t[i]) - need * DT) > 1e-3:
            continue  # not on one regular grid (tracks are; be safe)
        xs.append(window(t, tr.x[idx], tr.y[idx], tr.speed[idx], tr.heading[idx],
                         config.direct, config.tw))
        ahead = np.arange(i + 1, i + h + 1)
        if config.kind == "ae":
            back = np.clip(np.arange(i - config.tw + 2, i + 2), 0, None)
            ys.append(_series(tr, config.direct, i, back))
        else:
            ys.append(_series(tr, config.direct, i, ahead))
        origin.append((tr.x[i], tr.y[i], tr.speed[i], tr.heading[i], per))
        future.append(np.stack([tr.x[ahead], tr.y[ahead]], axis=1))
    return Examples(np.array(xs), np.array(ys), np.array(origin), np.array(future))


def split(tables: Sequence[MobilityTable], val_fraction: float, seed: int
          ) -> tuple[list[MobilityTable], list[MobilityTable]]:
    """Trips for training and for validation (by trip, seeded, at least one each)."""
    if len(tables) < 2:
        raise ValueError("a split by trip needs at least two trips")
    order = np.random.default_rng(seed).permutation(len(tables))
    n_val = min(max(1, round(val_fraction * len(tables))), len(tables) - 1)
    val = {int(k) for k in order[:n_val]}
    return ([t for k, t in enumerate(tables) if k not in val],
            [t for k, t in enumerate(tables) if k in val])


def _loss(torch, out, y, kind: str):
    mse = torch.mean((out - y) ** 2)
    if kind == "ae":
        mse = mse + torch.mean((out[:, -1] - y[:, -1]) ** 2)
    return mse


def position_errors(net: Network | None, ex: Examples,
                    horizons_s: Sequence[float] = (0.5, 1.0, 3.0)) -> dict[str, dict]:
    """Mean and 95th percentile of the forecast position error (m) at each horizon over
    ``ex``: the model as the predictor runs it (chained, integrated, in ENU), or with
    ``net`` None constant speed and heading from the origin BSM (the reference a user
    reads the model's numbers against)."""
    from catc.predict.base import Observation

    steps = max(round(h / DT) for h in horizons_s)
    series = roll(net, ex.x, steps) if net is not None else [None] * len(ex.x)
    err: dict[str, list[float]] = {f"{h:g}s": [] for h in horizons_s}
    for s, o, fut in zip(series, ex.origin, ex.future, strict=True):
        last = Observation(0.0, o[0], o[1], o[2], o[3])
        f = None if net is None else to_forecast(s, last, net.config.direct, net.config.name)
        for h in horizons_s:
            k = round(h / DT)
            if k > len(fut):
                continue
            if f is None:
                p = constant_speed(last, h)
                px, py = p.x, p.y
            else:
                px, py = f.x[k], f.y[k]
            err[f"{h:g}s"].append(math.hypot(px - fut[k - 1, 0], py - fut[k - 1, 1]))
    return {k: {"mean": round(float(np.mean(v)), 4), "p95": round(float(np.percentile(v, 95)), 4)}
            for k, v in err.items() if v}


def train(config: NnConfig, train_tracks: Sequence[Track], val_tracks: Sequence[Track],
          tc: TrainConfig = TrainConfig(),
          progress: Callable[[int, int], None] | None = None,
          log: Callable[[str], None] | None = None) -> TrainResult:
    """Fit ``config``'s model (module docstring); returns the best epoch's network with
    its weights rounded as :func:`catc.predict.nn.save` stores them."""
    torch = torch_module()
    torch.manual_seed(tc.seed)
    rng = np.random.default_rng(tc.seed)
    val = examples(val_tracks, config, tc.val_examples, np.random.default_rng(tc.seed + 1), tc)
    first = examples(train_tracks, config, tc.examples, rng, tc)
    x_mean = first.x.reshape(-1, config.channels).mean(0)
    x_std = np.maximum(first.x.reshape(-1, config.channels).std(0), 1e-3)
    y_mean, y_std = first.y.mean(0), np.maximum(first.y.std(0), 1e-3)
    module = build(config)
    net = Network(config, module, x_mean, x_std, y_mean, y_std)
    opt = torch.optim.Adam(module.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5,
                                                       patience=max(tc.patience // 2 - 1, 0))

    def tensors(ex: Examples):
        return (torch.from_numpy(((ex.x - x_mean) / x_std).astype(np.float32)),
                torch.from_numpy(((ex.y - y_mean) / y_std).astype(np.float32)))

    vx, vy = tensors(val)

    def val_loss() -> float:
        module.eval()
        with torch.inference_mode():
            return float(sum(_loss(torch, module(vx[k:k + 1024]), vy[k:k + 1024], config.kind)
                             * len(vx[k:k + 1024]) for k in range(0, len(vx), 1024)) / len(vx))

    result = TrainResult(net, history=[{"epoch": 0, "val_loss": round(val_loss(), 6)}])
    best, best_state, bad = result.history[0]["val_loss"], None, 0
    per_epoch = math.ceil(tc.examples / tc.batch)
    total = tc.steps or tc.epochs * per_epoch
    t0 = time.monotonic()
    ex = first
    for epoch in range(1, tc.epochs + 1):
        if epoch > 1:
            ex = examples(train_tracks, config, tc.examples, rng, tc)
        tx, ty = tensors(ex)
        module.train()
        order = torch.from_numpy(rng.permutation(len(tx)))
        running = 0.0
        for b in range(per_epoch):
            sel = order[b * tc.batch:(b + 1) * tc.batch]
            opt.zero_grad()
            loss = _loss(torch, module(tx[sel]), ty[sel], config.kind)
            loss.backward()
            opt.step()
            running += loss.item()
            result.steps += 1
            if progress is not None:
                progress(min(result.steps, total), total)
            if tc.steps and result.steps >= tc.steps:
                break
        v = val_loss()
        sched.step(v)
        result.history.append({"epoch": epoch, "train_loss": round(running / (b + 1), 6),
                               "val_loss": round(v, 6), "lr": opt.param_groups[0]["lr"],
                               "seconds": round(time.monotonic() - t0, 1)})
        if log is not None:
            log(f"{config.name} epoch {epoch}: train {running / (b + 1):.4f}, val {v:.4f}")
        if v < best:
            best, bad, result.best_epoch = v, 0, epoch
            best_state = {k: t.detach().clone() for k, t in module.state_dict().items()}
        else:
            bad += 1
        if bad >= tc.patience or (tc.steps and result.steps >= tc.steps):
            break
    if best_state is not None:
        module.load_state_dict(best_state)
    module.eval()
    result.seconds = time.monotonic() - t0
    # what is shipped: the weights as save() rounds them
    result.network = from_state(net.state())
    result.network.meta = {"val_loss": best,
                           "val_position_error_m": position_errors(result.network, val),
                           "val_position_error_m_cs": position_errors(None, val)}
    return result
