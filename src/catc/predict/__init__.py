"""Trajectory predictors behind one interface (:mod:`catc.predict.base`), chosen by name.

=========  =====================================================================
name       model
=========  =====================================================================
hold       the BSM-dependent baseline: the last received position
cs         constant speed and heading
ca         constant acceleration along the heading, stopping at zero speed
kf         the paper's Kalman filter, constant-acceleration dynamics
ctrv       constant turn rate (from the yaw rate) and velocity
hgp        the paper's indirect Hybrid Gaussian Process (speed and heading GPs)
hgp-d      the direct HGP (GPs on x and y)
=========  =====================================================================
"""

from __future__ import annotations

from collections.abc import Callable

from catc.predict.base import Observation, Prediction, Predictor


def _factories() -> dict[str, Callable[..., Predictor]]:
    from catc.predict.hgp import HgpDirectPredictor, HgpPredictor
    from catc.predict.kalman import KalmanPredictor
    from catc.predict.kinematic import (
        ConstantAccelerationPredictor,
        ConstantSpeedPredictor,
        CtrvPredictor,
        HoldPredictor,
    )

    return {"hold": HoldPredictor, "cs": ConstantSpeedPredictor,
            "ca": ConstantAccelerationPredictor, "kf": KalmanPredictor, "ctrv": CtrvPredictor,
            "hgp": HgpPredictor, "hgp-d": HgpDirectPredictor}


NAMES = ("hold", "cs", "ca", "kf", "ctrv", "hgp", "hgp-d")


def make_predictor(name: str, **kwargs) -> Predictor:
    """A new predictor by name; ``kwargs`` go to its constructor.

    Raises ``ValueError`` naming the known predictors for an unknown name.
    """
    factories = _factories()
    if name not in factories:
        raise ValueError(f"unknown predictor {name!r}; known: {', '.join(NAMES)}")
    return factories[name](**kwargs)


def prepare(predictors, t: float) -> int:
    """Let predictors that can do it stacked prepare the answers for times up to ``t``
    (one call per tick before the per-RV ``predict`` calls; today the HGP family:
    :func:`catc.predict.hgp.forecast_many`).  Results are the same as without the call.
    Returns the number of forecasts made."""
    from catc.predict.hgp import forecast_many

    return forecast_many(predictors, t)


__all__ = ["NAMES", "Observation", "Prediction", "Predictor", "make_predictor", "prepare"]
