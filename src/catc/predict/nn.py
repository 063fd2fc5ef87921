"""The paper's neural baselines: autoencoder (AE) and LSTM predictors, each indirect (speed
and heading) and direct (x and y): ``ae``, ``ae-d``, ``lstm``, ``lstm-d``.

Valiente et al., section "Prediction Baseline Models": "For AE, LSTM and GP prediction,
the (x, y) predictions can be obtained following two different approach, i.e, direct (D)
or indirect (I)", subsections "Autoencoder Model" and "LSTM Model".

* **AE**: "an encoder that consists of 3 fully connected (FC) layers with 256, 128, and 64
  units respectively ... the decoder consists of a symmetric version of the encoder",
  trained "to reproduce the state at time t+1 given the state at time t": its input is the
  history window, its output the same window one step (0.1 s) later, whose last row is
  the next state.  "For multiple-step predictions, the predictions are used in a chain":
  the predicted state is appended to the window and the AE run again.
* **LSTM**: "two layers of 256 LSTM cells, ReLu activation, and dropout ... fit using Adam
  and MSE loss function", mapping the history window to the next :data:`HORIZON` states
  in one pass; longer forecasts chain it the same way (the last ``tw`` states of history
  and forecast are the next input).

The series (our reading, the same for both models):

* **History window**: the last ``tw`` = 30 samples (the paper's TW, 3 s) on the 10 Hz grid
  ending at the last received BSM.  Lost messages leave gaps; the grid values are linear
  interpolations between the BSMs received (held before the first).  Training draws the
  same losses (PER 0 to 95 %, rates 10 to 1 Hz), so the models learn from windows like
  the ones they meet.
* **Indirect**: speed (m/s) and the heading change from the last BSM's heading (rad,
  unwrapped).  Positions come from the forecast speed and heading by the HGP's piecewise
  integration (:func:`catc.predict.forecast.integrate`, trapezoid rule).
* **Direct**: the position relative to the last BSM, in the frame of its heading (along
  track, and to the right): translation and rotation are normalised away, as the HGP-D
  puts its GPs on positions relative to the last one.  The heading only orients the
  frame; the series modelled are positions.  Speed and heading of a direct forecast are
  those of its positions' differences.
* Inputs and outputs are standardised with the training set's means and deviations
  (stored with the weights).
* A forecast is made when a prediction is first needed after a BSM and reused until the
  next one: as far as asked, and at least one pass of the model (the LSTM's 3 s, the AE's
  0.5 s), doubled when a gap outgrows it.

Fallbacks, as the HGP's: fewer than ``min_points`` BSMs received: constant speed (source
``"cs"``); a forecast never reverses (indirect: speed clipped at 0); beyond
``horizon_s`` (10 s) constant speed.

The models run in PyTorch, an optional extra (``pip install 'catc-hil[nn]'``).  Weights
trained on the shared real data ship in ``catc/predict/nn/`` (``captures train-nn``
re-creates them; their ``meta`` records how).  :func:`forecast_many_at` makes the
forecasts due at one tick in one batch per model, as the OBU's CA-TC and the sweep's
lockstep replay do.
"""

from __future__ import annotations

import math
import os
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np

from catc.predict.base import Observation, Prediction, register_batch
from catc.predict.forecast import (
    DT,
    Forecast,
    bsm_prediction,
    constant_speed,
    covers,
    integrate,
    read,
)
from catc.predict.kinematic import check_observation, elapsed

#: The names of the neural predictors (indirect, then direct).
NN_NAMES = ("ae", "ae-d", "lstm", "lstm-d")
#: History window, samples (the paper's TW: 3 s at 10 Hz).
TW = 30
#: States an LSTM pass forecasts (3 s).
HORIZON = 30
FORMAT = "catc-nn/1"


class MissingExtra(ImportError, ValueError):
    """A neural predictor was asked for and PyTorch is not installed (a ``ValueError``
    too, so that whatever reports a bad predictor name reports this in one line)."""


def torch_module():
    """``torch``, or :class:`MissingExtra` with the command that installs it."""
    try:
        import torch
    except ImportError:
        raise MissingExtra("the neural predictors (ae, ae-d, lstm, lstm-d) need PyTorch, "
                           "which is not installed: pip install 'catc-hil[nn]' "
                           "(torch==2.13.0, CPU build)") from None
    return torch


@dataclass(frozen=True)
class NnConfig:
    """What a model is: its kind, its series and its size (stored with its weights)."""

    kind: str  # "ae" or "lstm"
    direct: bool  # positions (x, y) rather than speed and heading
    tw: int = TW
    horizon: int = HORIZON  # LSTM output states; the AE forecasts one
    hidden: tuple[int, ...] = (256, 128, 64)  # AE encoder; LSTM: (cells,) * layers
    dropout: float = 0.2

    @property
    def name(self) -> str:
        return self.kind + ("-d" if self.direct else "")

    @property
    def channels(self) -> int:
        return 2

    @property
    def n_in(self) -> int:
        return self.tw * self.channels

    @property
    def n_out(self) -> int:
        return self.tw * self.channels if self.kind == "ae" else self.horizon * self.channels

    @staticmethod
    def for_name(name: str, **kw) -> NnConfig:
        if name not in NN_NAMES:
            raise ValueError(f"unknown neural predictor {name!r}; known: {', '.join(NN_NAMES)}")
        kind, direct = name.removesuffix("-d"), name.endswith("-d")
        if kind == "lstm":
            kw.setdefault("hidden", (256, 256))
        return NnConfig(kind, direct, **kw)


# --- the series (numpy only) ---------------------------------------------------------------------


def window(t: np.ndarray, x: np.ndarray, y: np.ndarray, speed: np.ndarray,
           heading_deg: np.ndarray, direct: bool, tw: int = TW) -> np.ndarray:
    """The model input (tw, 2) from received samples (times increasing, the last one the
    forecast's origin): on the 10 Hz grid ending at ``t[-1]``, interpolated between them.

    Direct: (along, right) position relative to the last sample in the frame of its
    heading.  Indirect: (speed, heading change from the last sample in rad)."""
    grid = t[-1] + (np.arange(tw) - (tw - 1)) * DT
    if direct:
        a, b = heading_frame(x - x[-1], y - y[-1], float(heading_deg[-1]))
    else:
        a = speed
        b = np.unwrap(np.radians(heading_deg))
        b = b - b[-1]
    return np.stack([np.interp(grid, t, a), np.interp(grid, t, b)], axis=1)


def heading_frame(dx: np.ndarray, dy: np.ndarray, heading_deg: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """East/north offsets as (along, right) in the frame of a heading (degrees clockwise
    from north): the direct models' series."""
    h = math.radians(heading_deg)
    sh, ch = math.sin(h), math.cos(h)
    return dx * sh + dy * ch, dx * ch - dy * sh


def to_forecast(series: np.ndarray, last: Observation, direct: bool,
                source: str) -> Forecast:
    """A forecast table from the forecast series (n, 2) after ``last`` (row 0 is τ = DT);
    ``source`` names the model in the predictions read from it."""
    n = len(series)
    tau = np.arange(n + 1) * DT
    if direct:
        h = math.radians(last.heading)
        sh, ch = math.sin(h), math.cos(h)
        a = np.concatenate(([0.0], series[:, 0]))
        b = np.concatenate(([0.0], series[:, 1]))
        px, py = last.x + a * sh + b * ch, last.y + a * ch - b * sh
        vx, vy = np.gradient(px, DT), np.gradient(py, DT)
        speed = np.hypot(vx, vy)
        heading = np.where(speed > 0.5, np.degrees(np.arctan2(vx, vy)) % 360.0, last.heading)
        speed[0] = last.speed
        heading[0] = last.heading
    else:
        speed = np.maximum(np.concatenate(([last.speed], series[:, 0])), 0.0)
        head = math.radians(last.heading) + np.concatenate(([0.0], series[:, 1]))
        px, py = integrate(last.x, last.y, tau, speed, head, np.zeros(n + 1))
        heading = np.degrees(head) % 360.0
    nan = np.full(n + 1, np.nan)
    return Forecast(tau, np.array([px, py, speed, heading, nan, nan]),
                    ["bsm"] + [source] * n)


# --- models (PyTorch) ----------------------------------------------------------------------------


def build(config: NnConfig):
    """The untrained torch module of ``config``."""
    torch = torch_module()
    nn = torch.nn

    class AutoEncoder(nn.Module):
        """FC encoder (256, 128, 64) and its mirror as decoder: window → next window."""

        def __init__(self, c: NnConfig) -> None:
            super().__init__()
            layers, d = [], c.n_in
            for width in c.hidden:
                layers += [nn.Linear(d, width), nn.ReLU()]
                d = width
            for width in reversed(c.hidden[:-1]):
                layers += [nn.Linear(d, width), nn.ReLU()]
                d = width
            layers.append(nn.Linear(d, c.n_out))
            self.net = nn.Sequential(*layers)

        def forward(self, x):  # (B, tw, C) -> (B, tw, C)
            return self.net(x.flatten(1)).view(x.shape)

    class Lstm(nn.Module):
        """Two LSTM layers of 256 cells (dropout between), ReLU, dropout, linear head:
        window → the next ``horizon`` states."""

        def __init__(self, c: NnConfig) -> None:
            super().__init__()
            self.lstm = nn.LSTM(c.channels, c.hidden[0], num_layers=len(c.hidden),
                                batch_first=True, dropout=c.dropout)
            self.head = nn.Sequential(nn.ReLU(), nn.Dropout(c.dropout),
                                      nn.Linear(c.hidden[0], c.n_out))
            self.horizon, self.channels = c.horizon, c.channels

        def forward(self, x):  # (B, tw, C) -> (B, horizon, C)
            out, _ = self.lstm(x)
            return self.head(out[:, -1]).view(len(x), self.horizon, self.channels)

    if config.kind == "ae":
        return AutoEncoder(config)
    if config.kind == "lstm":
        return Lstm(config)
    raise ValueError(f"unknown model kind {config.kind!r}")


@dataclass
class Network:
    """A trained model: its config, the module (eval mode, float32) and the
    standardisation of its inputs and outputs."""

    config: NnConfig
    module: object
    x_mean: np.ndarray  # (C,)
    x_std: np.ndarray  # (C,)
    y_mean: np.ndarray  # n_out, shaped like the output
    y_std: np.ndarray
    meta: dict = field(default_factory=dict)

    def __call__(self, windows: np.ndarray) -> np.ndarray:
        """Raw (un-standardised) outputs for raw windows (B, tw, C)."""
        torch = torch_module()
        z = (windows - self.x_mean) / self.x_std
        with torch.inference_mode():
            out = self.module(torch.from_numpy(z.astype(np.float32))).numpy()
        return out.astype(np.float64) * self.y_std + self.y_mean

    def state(self) -> dict:
        """What :func:`save` writes: weights as float16 (half the size; :func:`load`
        restores float32) plus everything needed to rebuild the model."""
        torch = torch_module()
        return {"format": FORMAT, "config": asdict(self.config),
                "norm": {k: getattr(self, k).tolist()
                         for k in ("x_mean", "x_std", "y_mean", "y_std")},
                "weights": {k: v.detach().to(torch.float16)
                            for k, v in self.module.state_dict().items()},
                "meta": self.meta}


def from_state(state: dict) -> Network:
    torch = torch_module()
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise ValueError(f"not a {FORMAT} model file")
    cfg = dict(state["config"])
    cfg["hidden"] = tuple(cfg["hidden"])
    config = NnConfig(**cfg)
    module = build(config)
    module.load_state_dict({k: v.to(torch.float32) for k, v in state["weights"].items()})
    module.eval()
    norm = {k: np.asarray(v, dtype=np.float64) for k, v in state["norm"].items()}
    return Network(config, module, meta=dict(state.get("meta", {})), **norm)


def save(net: Network, path: Path) -> None:
    torch_module().save(net.state(), path)


def load(path: Path | str) -> Network:
    """A model written by :func:`save` (``captures train-nn``)."""
    import pickle

    torch = torch_module()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{path}: cannot read the model: {first}") from None
    return from_state(state)


def weights_dir() -> Path:
    """Where the shipped weights are (``CATC_NN_DIR`` overrides it)."""
    env = os.environ.get("CATC_NN_DIR")
    return Path(env) if env else Path(str(resources.files("catc.predict").joinpath("nn")))


@cache
def _network(name: str, folder: str) -> Network:
    path = Path(folder) / f"{name}.pt"
    if not path.is_file():
        raise FileNotFoundError(f"no weights for {name!r} in {folder} (make nn trains them)")
    net = load(path)
    if net.config.name != name:
        raise ValueError(f"{path} holds a {net.config.name!r} model, not {name!r}")
    return net


def network(name: str) -> Network:
    """The shipped (or ``CATC_NN_DIR``'s) model ``name``, loaded once per process.

    Forecasts are small batches, where torch's threads cost more than they give: the
    command-line tools run with ``OMP_NUM_THREADS=1``, which torch follows."""
    torch_module()
    return _network(name, str(weights_dir()))


# --- the predictor -------------------------------------------------------------------------------


@dataclass(frozen=True)
class NnPredictorConfig:
    min_points: int = 4  # fewer received samples: constant speed
    horizon_s: float = 10.0  # longest forecast; constant speed beyond it


class NnPredictor:
    """A neural baseline behind the predictor interface (:mod:`catc.predict.base`)."""

    def __init__(self, name: str, network: Network | None = None,
                 config: NnPredictorConfig | None = None) -> None:
        self.net = network if network is not None else globals()["network"](name)
        if self.net.config.name != name:
            raise ValueError(f"a {self.net.config.name!r} network given to {name!r}")
        self.name = name
        self.config = config or NnPredictorConfig()
        self._obs: deque[Observation] = deque(maxlen=self.net.config.tw + 1)
        self._forecast: Forecast | None = None

    def reset(self) -> None:
        self._obs.clear()
        self._forecast = None

    def update(self, obs: Observation) -> None:
        check_observation(obs)
        if self._obs and obs.t <= self._obs[-1].t:
            return
        self._obs.append(obs)
        self._forecast = None

    def predict(self, t: float) -> Prediction:
        if not self._obs:
            raise LookupError("no observation yet")
        last = self._obs[-1]
        tau = elapsed(last.t, t)
        if tau == 0.0:
            return bsm_prediction(last)
        if len(self._obs) < self.config.min_points:
            return constant_speed(last, tau)
        f = self._forecast
        if f is None or not covers(f, tau, self.config.horizon_s):
            forecast_many_at([(self, t)])
            f = self._forecast
        return read(f, tau)

    def _window(self) -> np.ndarray:
        o = self._obs
        return window(np.array([b.t for b in o]), np.array([b.x for b in o]),
                      np.array([b.y for b in o]), np.array([b.speed for b in o]),
                      np.array([b.heading for b in o]), self.net.config.direct,
                      self.net.config.tw)


def _steps(p: NnPredictor, tau: float) -> int:
    """Forecast states (0.1 s each) for ``p``'s forecast reaching ``tau``: at least one
    pass of its model (the LSTM's 3 s; the AE's chain 0.5 s, each of its states being a
    pass), and twice the forecast it replaces, so that a gap outgrowing its forecasts
    costs at most about twice its length.  The states do not depend on how far a
    forecast goes (a chain's first states are those of a shorter chain)."""
    c, net = p.config, p.net.config
    shortest = 0.5 if net.kind == "ae" else net.horizon * DT
    before = p._forecast.end if p._forecast is not None else 0.0
    return math.ceil(min(max(tau, shortest, 2.0 * before), c.horizon_s) / DT - 1e-9)


def roll(net: Network, windows: np.ndarray, steps: int) -> np.ndarray:
    """The next ``steps`` states after each window (B, tw, C), chaining the model: the
    AE one state per pass, the LSTM ``horizon`` per pass; each pass sees the last ``tw``
    states of history and forecast, in the frame of its own last state (direct: its
    position; indirect: its heading).  The chain stays in torch (float32): the AE's 30 passes for a
    3 s forecast cost the module calls, not numpy round trips."""
    torch = torch_module()
    c = net.config
    per = 1 if c.kind == "ae" else c.horizon
    passes = math.ceil(steps / per)
    f32 = torch.float32
    x_mean, x_std = torch.tensor(net.x_mean, dtype=f32), torch.tensor(net.x_std, dtype=f32)
    y_mean, y_std = torch.tensor(net.y_mean, dtype=f32), torch.tensor(net.y_std, dtype=f32)
    mask = torch.tensor([1.0, 1.0] if c.direct else [0.0, 1.0], dtype=f32)
    forward = _mlp(net) if c.kind == "ae" else net.module
    seq = torch.empty((len(windows), c.tw + passes * per, c.channels), dtype=f32)
    seq[:, :c.tw] = torch.from_numpy(windows.astype(np.float32))
    with torch.inference_mode():
        for k in range(passes):
            at = k * per
            win = seq[:, at:at + c.tw]
            ref = win[:, -1:] * mask
            out = forward((win - ref - x_mean) / x_std) * y_std + y_mean
            seq[:, c.tw + at:c.tw + at + per] = (out[:, -1:] if c.kind == "ae" else out) + ref
    return seq[:, c.tw:c.tw + steps].numpy().astype(np.float64)


def _mlp(net: Network):
    """The AE's forward pass as plain ``linear``/``relu`` calls on its weights: the same
    arithmetic as the module, without the module-call overhead, which at the small
    batches of a tick was half of each of the 30 chained passes of a 3 s forecast."""
    torch = torch_module()
    layers = [m for m in net.module.net if isinstance(m, torch.nn.Linear)]
    weights = [(m.weight, m.bias) for m in layers]
    linear, relu = torch.nn.functional.linear, torch.relu

    def forward(x):
        z = x.flatten(1)
        for w, b in weights[:-1]:
            z = relu(linear(z, w, b))
        w, b = weights[-1]
        return linear(z, w, b).view(x.shape)

    return forward


def forecast_many_at(items: Iterable[tuple[object, float]]) -> int:
    """Make the forecasts that neural predictors among ``items`` (``(predictor, t)``
    pairs) need to answer ``predict(t)``: one batch per network.  Predictors whose
    forecast already reaches ``t``, with too little data, or not neural, are left alone.
    Returns the number of forecasts made."""
    groups: dict[int, list[tuple[NnPredictor, int]]] = {}
    for p, t in items:
        if not isinstance(p, NnPredictor) or not p._obs:
            continue
        tau = t - p._obs[-1].t
        if not tau > 0.0 or len(p._obs) < p.config.min_points:
            continue
        f = p._forecast
        if f is not None and covers(f, tau, p.config.horizon_s):
            continue
        groups.setdefault(id(p.net), []).append((p, _steps(p, tau)))
    for group in groups.values():
        preds: Sequence[NnPredictor] = [p for p, _ in group]
        net = preds[0].net
        steps = max(n for _, n in group)
        series = roll(net, np.stack([p._window() for p in preds]), steps)
        for (p, n), s in zip(group, series, strict=True):
            p._forecast = to_forecast(s[:n], p._obs[-1], net.config.direct, p.name)
    return sum(len(g) for g in groups.values())


register_batch(NnPredictor, forecast_many_at)
