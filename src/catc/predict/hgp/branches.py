"""The data-driven hybrid (issue 17; docs/log/2026-11-25-hgp-branches.md): kinematic predictors run
beside the GP, each scored at every BSM that ends a gap, and the best of a gap class
answers it (or a blend of them does).  See ``HgpConfig.branches`` for the rule and the
measurements behind it.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable

from catc.predict.base import Observation, Prediction, Predictor
from catc.predict.forecast import DT, Forecast, covers, read_xy
from catc.predict.hgp.config import HgpConfig
from catc.predict.kinematic_table import KINEMATIC


def position_of(predictor: Predictor) -> Callable[[float], tuple[float, float]]:
    """(x, y) of ``predictor.predict(t)``, for a branch without a ``position`` method."""
    def position(t: float) -> tuple[float, float]:
        p = predictor.predict(t)
        return p.x, p.y
    return position


class Branches:
    """The kinematic predictors that run beside the GP (``HgpConfig.branches``) and their
    running scores per gap class: which one answers a gap, or the blend's weights (issue
    17; docs/log/2026-11-25-hgp-branches.md).  Made from
    :data:`catc.predict.kinematic_table.KINEMATIC`."""

    def __init__(self, c: HgpConfig) -> None:
        self.config = c
        self.kin: list[Predictor] = [KINEMATIC[name]() for name in c.branches]
        # where each branch puts the vehicle at t, for its score (position() where a
        # predictor has it: the x, y of predict() without the rest)
        self.xy = [getattr(k, "position", None) or position_of(k) for k in self.kin]
        # per gap class: GP, then each kinematic branch
        self.score = [[0.0] * (len(self.kin) + 1) for _ in range(len(c.branch_edges) + 1)]
        self.scored = [0] * (len(c.branch_edges) + 1)
        # per gap class, the branch that answers (kept up to date by add) and the margin
        # a kinematic branch must beat the GP by
        self.choice = [0] * (len(c.branch_edges) + 1)
        self.margins = c.margins()
        # per gap class, the blend's weights (branch_blend; None: the GP alone)
        self.weights: list[list[float] | None] = [None] * (len(c.branch_edges) + 1)

    def reset(self) -> None:
        """Forget the branches' histories and every score."""
        for k in self.kin:
            k.reset()
        self.score = [[0.0] * len(row) for row in self.score]
        self.scored = [0] * len(self.scored)
        self.choice = [0] * len(self.choice)
        self.weights = [None] * len(self.weights)

    def update(self, obs: Observation) -> None:
        """Feed every branch the received observation."""
        for k in self.kin:
            k.update(obs)

    def gap_class(self, tau: float) -> int:
        """The gap class of ``tau``: the number of ``branch_edges`` below it."""
        return bisect.bisect_left(self.config.branch_edges, tau)

    def score_gap(self, obs: Observation, gap: float, f: Forecast | None) -> None:
        """Score each branch at ``obs``, the BSM that ends a gap of ``gap`` s, the GP by
        its forecast ``f`` over the gap (nothing when no BSM was lost or the GP has no
        forecast over the gap).  Call it before the branches see ``obs``."""
        if gap <= DT + 1e-6:
            return
        if f is None or not covers(f, gap, self.config.horizon_s):
            return
        gx, gy = read_xy(f, gap)
        x, y = obs.x, obs.y
        errs = [(gx - x) ** 2 + (gy - y) ** 2]
        for position in self.xy:
            px, py = position(obs.t)
            errs.append((px - x) ** 2 + (py - y) ** 2)
        self.add(bisect.bisect_left(self.config.branch_edges, gap), errs)

    def add(self, g: int, errs: list[float]) -> None:
        """Enter one squared error per branch (the GP first) into gap class ``g``'s
        scores, and renew that class's choice (and blend weights)."""
        c = self.config
        d = c.branch_decay
        row = [d * old + (1.0 - d) * e for old, e in zip(self.score[g], errs, strict=True)]
        self.score[g] = row
        self.scored[g] += 1
        k = min(range(1, len(row)), key=row.__getitem__)
        self.choice[g] = k if row[k] < self.margins[g] * row[0] else 0
        if c.branch_blend:
            lim = c.branch_blend * max(min(row), 1e-12)
            inv = [max(e, 1e-12) ** -c.blend_power if e <= lim else 0.0 for e in row]
            total = sum(inv)
            self.weights[g] = [v / total for v in inv]

    def blend(self, t: float, gp: Prediction, w: list[float]) -> Prediction:
        """The branches' answers at ``t`` averaged with weights ``w`` (GP first); heading
        by its differences from the GP's, variances the GP's."""
        x, y, speed, dh = w[0] * gp.x, w[0] * gp.y, w[0] * gp.speed, 0.0
        for k, wk in zip(self.kin, w[1:], strict=True):
            if wk:
                p = k.predict(t)
                x += wk * p.x
                y += wk * p.y
                speed += wk * p.speed
                dh += wk * ((p.heading - gp.heading + 180.0) % 360.0 - 180.0)
        return Prediction(x, y, speed, (gp.heading + dh) % 360.0, gp.var_x, gp.var_y,
                          gp.source)
