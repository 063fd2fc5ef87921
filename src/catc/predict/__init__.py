"""Trajectory predictors behind one interface (:mod:`catc.predict.base`), chosen by name.

=========  =====================================================================
name       model
=========  =====================================================================
hold       the BSM-dependent baseline: the last received position
cs         constant speed and heading
ca         constant acceleration along the heading, stopping at zero speed
kf         the paper's Kalman filter, constant-acceleration dynamics
ctrv       constant turn rate (from the yaw rate) and velocity
imm        Interacting Multiple Model filter: constant velocity, acceleration, turn
ae         the paper's autoencoder baseline, indirect (speed and heading)
ae-d       the autoencoder on x and y (direct)
lstm       the paper's LSTM baseline, indirect (speed and heading)
lstm-d     the LSTM on x and y (direct)
hgp        the paper's indirect Hybrid Gaussian Process (speed and heading GPs)
hgp-d      the direct HGP (GPs on x and y)
=========  =====================================================================

The neural baselines (:mod:`catc.predict.nn`) need PyTorch, the ``nn`` extra: without it
:func:`make_predictor` raises :class:`catc.predict.nn.MissingExtra` (a ``ValueError``)
saying how to install it, and :func:`available` leaves them out.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

from catc.predict.base import Observation, Prediction, Predictor, batch_support


def _factories() -> dict[str, Callable[..., Predictor]]:
    from catc.predict.hgp import HgpDirectPredictor, HgpPredictor
    from catc.predict.kinematic_table import KINEMATIC
    from catc.predict.nn import NN_NAMES, NnPredictor

    return {**KINEMATIC, **{n: partial(NnPredictor, n) for n in NN_NAMES},
            "hgp": HgpPredictor, "hgp-d": HgpDirectPredictor}


#: Every predictor, in the order of the paper's tables: kinematic, neural, HGP.
NAMES = ("hold", "cs", "ca", "kf", "ctrv", "imm", "ae", "ae-d", "lstm", "lstm-d", "hgp", "hgp-d")
#: The predictors whose forecasts :func:`prepare` stacks (for the others it does nothing).
STACKED = ("ae", "ae-d", "lstm", "lstm-d", "hgp")


def check(name: str) -> None:
    """Raise ``ValueError`` unless ``make_predictor(name)`` can work here: an unknown name
    (the message lists the known ones), or a neural predictor without PyTorch
    (:class:`catc.predict.nn.MissingExtra`, with the install command) or its weights."""
    if name not in NAMES:
        raise ValueError(f"unknown predictor {name!r}; known: {', '.join(NAMES)}")
    from catc.predict.nn import NN_NAMES, network

    if name in NN_NAMES:
        try:
            network(name)
        except FileNotFoundError as err:
            raise ValueError(str(err)) from None


def available() -> tuple[str, ...]:
    """The predictors that can be made here (all but the neural ones without PyTorch)."""
    out = []
    for n in NAMES:
        try:
            check(n)
        except ValueError:
            continue
        out.append(n)
    return tuple(out)


def make_predictor(name: str, **kwargs) -> Predictor:
    """A new predictor by name; ``kwargs`` go to its constructor.

    Raises ``ValueError`` naming the known predictors for an unknown name, and
    :class:`catc.predict.nn.MissingExtra` (a ``ValueError``) for a neural one without
    PyTorch.
    """
    factories = _factories()
    if name not in factories:
        raise ValueError(f"unknown predictor {name!r}; known: {', '.join(NAMES)}")
    return factories[name](**kwargs)


def prepare(predictors, t: float) -> int:
    """Let predictors that can do it stacked prepare the answers for times up to ``t``
    (one call per tick before the per-RV ``predict`` calls): the HGP family
    (:func:`catc.predict.hgp.forecast_many`) and the neural baselines
    (:func:`catc.predict.nn.forecast_many_at`, one batch per network).  Results are the
    same as without the call.  Returns the number of forecasts made."""
    return prepare_at([(p, t) for p in predictors])


def prepare_at(items) -> int:
    """:func:`prepare` with a time per predictor: ``(predictor, t)`` pairs (predictors on
    different clocks, e.g. the vehicles of many trips replayed in lockstep).  Each kind
    of predictor is prepared by the function its class declared
    (:func:`catc.predict.base.register_batch`), with its own pairs."""
    groups: dict = {}
    for item in items:
        support = batch_support(item[0].__class__)
        if support is not None and support.prepare is not None:
            groups.setdefault(support.prepare, []).append(item)
    return sum(fn(group) for fn, group in groups.items())


def predict_columns(predictors, t0: float, t1: float):
    """Every predictor's state at ``t0`` and at ``t1``, as columns: a (10, n) array whose
    rows are x, y, speed and heading at t0 and t1 interleaved (x(t0), x(t1), y(t0), ...),
    then var_x and var_y at t0; and the sources at t0.  The numbers ``predict(t0)`` and
    ``predict(t1)`` give; forecasts the answers read from (the HGP's, ``plan``) are read
    all at once (:func:`catc.predict.forecast.read_many`), both times of a predictor
    planned in one call where its class is a declared
    :class:`~catc.predict.base.BatchPredictor` (``plan_pair``)."""
    import numpy as np

    from catc.predict.forecast import fill_columns

    n = len(predictors)
    out = np.empty((10, n))
    sources = [""] * n
    # per time t0, t1: the answers given whole (column, values) and those to read
    whole: tuple[list, list] = ([], [])
    reads: tuple[list, list] = ([], [])
    whole0, whole1 = whole
    reads0, reads1 = reads
    for i, p in enumerate(predictors):
        support = batch_support(p.__class__)
        if support is not None and support.plans:
            a, b = p.plan_pair(t0, t1)
        else:
            a, b = p.predict(t0), p.predict(t1)
        if a.__class__ is tuple:  # (forecast, tau): read below, with the others
            reads0.append((i, a))
        else:
            whole0.append((i, a.x, a.y, a.speed, a.heading, a.var_x, a.var_y))
            sources[i] = a.source
        if b.__class__ is tuple:
            reads1.append((i, b))
        else:
            whole1.append((i, b.x, b.y, b.speed, b.heading, b.var_x, b.var_y))
    fill_columns(out, sources, whole, reads)
    return out, sources


__all__ = ["NAMES", "STACKED", "Observation", "Prediction", "Predictor", "available",
           "check", "make_predictor", "predict_columns", "prepare", "prepare_at"]
