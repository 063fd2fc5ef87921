"""The kinematic predictors by their :mod:`catc.predict` names.

One table for the two places that make them by name: :func:`catc.predict.make_predictor`
and the HGP's branches (``HgpConfig.branches``: kinematic predictors run beside the GP,
:mod:`catc.predict.hgp`).  It sits below both, so that the HGP does not import
:mod:`catc.predict` back to make its branches (issue 26, "Knots").
"""

from __future__ import annotations

from catc.predict.base import Predictor
from catc.predict.imm import ImmPredictor
from catc.predict.kalman import KalmanPredictor
from catc.predict.kinematic import (
    ConstantAccelerationPredictor,
    ConstantSpeedPredictor,
    CtrvPredictor,
    HoldPredictor,
)

#: name -> class (constructed without arguments: the defaults of the paper's tables).
KINEMATIC: dict[str, type[Predictor]] = {
    "hold": HoldPredictor, "cs": ConstantSpeedPredictor, "ca": ConstantAccelerationPredictor,
    "kf": KalmanPredictor, "ctrv": CtrvPredictor, "imm": ImmPredictor}
