"""The HGP kernel bank: pairs of GP models (θ_s for speed, θ_h for heading) and its JSON form.

Each θ = (γ, α1, α2) of the paper's kernel.  :mod:`catc.predict.training` builds banks
(the paper's Algorithm 1 and clustering); the package ships one trained on the real data
in ``../shared/data`` as ``default_bank.json``, whose ``meta`` records how it was made.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources

import numpy as np

FORMAT = "catc-kernel-bank/1"


@dataclass(frozen=True, eq=False)
class KernelBank:
    """``speed`` and ``heading`` are (M, 3) arrays of θ = (γ, α1, α2); row i is pair i."""

    speed: np.ndarray
    heading: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.speed.shape != self.heading.shape or self.speed.ndim != 2 \
                or self.speed.shape[1] != 3 or len(self.speed) == 0:
            raise ValueError(f"a bank needs two (M, 3) arrays, got {self.speed.shape} and "
                             f"{self.heading.shape}")
        if not (np.all(np.isfinite(self.speed)) and np.all(self.speed > 0)
                and np.all(np.isfinite(self.heading)) and np.all(self.heading > 0)):
            raise ValueError("bank hyperparameters must be finite and positive")

    def __len__(self) -> int:
        return len(self.speed)

    def to_json(self) -> str:
        return json.dumps({"format": FORMAT, "speed": self.speed.tolist(),
                           "heading": self.heading.tolist(), **self.meta}, indent=1)

    @classmethod
    def from_json(cls, text: str, source: str = "kernel bank") -> KernelBank:
        """The bank in ``text``, the content of ``source`` (a file's name), which each
        ValueError names."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{source}: not valid JSON: line {exc.lineno} col {exc.colno}: "
                             f"{exc.msg}") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ValueError(f"{source}: kernel bank format must be {FORMAT!r}")
        meta = {k: v for k, v in data.items() if k not in ("format", "speed", "heading")}
        try:
            return cls(np.asarray(data["speed"], dtype=float),
                       np.asarray(data["heading"], dtype=float), meta)
        except KeyError as exc:
            raise ValueError(f"{source}: kernel bank has no {exc.args[0]!r}") from None


@lru_cache(maxsize=1)
def default_bank() -> KernelBank:
    """The bank shipped with the package (trained on ../shared/data; see its ``meta``)."""
    path = resources.files("catc.predict").joinpath("default_bank.json")
    return KernelBank.from_json(path.read_text(), str(path))
