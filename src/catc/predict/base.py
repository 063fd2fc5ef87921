"""The predictor interface: one remote vehicle's received history in, its state at any later
time out; and the optional second interface of the predictors that answer many RVs at
once (:class:`BatchPredictor`, :func:`register_batch`).

A predictor is fed the observations decoded from one RV's BSMs, in arrival order, with
the dataset time each was generated at.  When messages are lost the times are
irregular.  It answers the RV's ENU position, speed and heading at any time at or after
the last observation, with a position variance where the model has one.  Every
predictor registered in :mod:`catc.predict` implements this protocol.

Conventions (the same as :mod:`catc.bsm`): ENU metres (x east, y north) in the run's
local frame, speed in m/s, heading in degrees clockwise from north, longitudinal
acceleration in m/s², yaw rate in deg/s positive clockwise (J2735 YawRate).  Velocity
is therefore ``(speed·sin h, speed·cos h)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import NamedTuple, Protocol, runtime_checkable


class Observation(NamedTuple):
    """What one BSM tells a predictor about the RV, already in the run's ENU frame.

    A named tuple: immutable like a frozen dataclass, and made in 0.25 µs against 0.8 µs
    (one per accepted BSM: 10,000/s at 1,000 RVs)."""

    t: float
    x: float
    y: float
    speed: float
    heading: float
    accel: float = 0.0
    yaw_rate: float = 0.0


@dataclass(slots=True)
class Prediction:
    """The predicted state; ``var_x``/``var_y`` are NaN for models without uncertainty.

    ``source`` names what produced it (for example ``"gp"`` or ``"ca"`` when HGP's
    hybrid switch fell back), so that captures can show when each model was in use.

    Mutable, unlike :class:`Observation`: every ``predict`` returns a new one, ~1,500
    a tick at 500 RVs, and a frozen dataclass's ``__init__`` (one ``object.__setattr__``
    per field) costs 1.8 µs against 0.4 µs here (~2 ms a tick).
    """

    x: float
    y: float
    speed: float
    heading: float
    var_x: float = math.nan
    var_y: float = math.nan
    source: str = ""


@runtime_checkable
class Predictor(Protocol):
    name: str

    def update(self, obs: Observation) -> None:
        """Add one received observation (times must not decrease; duplicates are ignored)."""

    def predict(self, t: float) -> Prediction:
        """The state at time ``t`` (normally ``t >= `` the last observation's time).

        Raises ``LookupError`` before the first observation.
        """

    def reset(self) -> None:
        """Forget all history."""


#: An answer as :meth:`BatchPredictor.plan` gives it: the Prediction, or ``(forecast, tau)``
#: to read with :func:`catc.predict.forecast.read_many` (a
#: :class:`catc.predict.forecast.Forecast`, not named here: that module imports this one).
Plan = Prediction | tuple[object, float]

#: Makes, stacked, the forecasts a kind of predictor needs to answer ``predict(t)`` for
#: ``(predictor, t)`` pairs (others in the list are left alone); returns how many it made.
Preparer = Callable[[Iterable[tuple[Predictor, float]]], int]


class BatchPredictor(Predictor, Protocol):
    """A predictor whose answers can be planned, then read many at once.

    The CA-TC asks every RV for its state at now and now + 2 s each tick (500-1,000 RVs);
    a predictor that answers from a forecast table returns the table and the time to read
    instead of reading it, and :func:`catc.predict.predict_columns` reads all of them in
    one call.  ``plan(t)`` and ``plan_pair(t0, t1)`` answer exactly what ``predict`` would
    (the same numbers, bit for bit, once read).  Declared with :func:`register_batch`.
    """

    def plan(self, t: float) -> Plan:
        """What ``predict(t)`` answers: the Prediction, or ``(forecast, tau)``."""

    def plan_pair(self, t0: float, t1: float) -> tuple[Plan, Plan]:
        """``(plan(t0), plan(t1))`` in one call (``t0 <= t1``)."""


@dataclass(frozen=True, slots=True)
class BatchSupport:
    """What a predictor class declares beyond :class:`Predictor` (:func:`register_batch`)."""

    #: makes its forecasts stacked, over all the predictors of a tick (or None)
    prepare: Preparer | None = None
    #: it is a :class:`BatchPredictor` (``plan`` and ``plan_pair``)
    plans: bool = False


#: The declarations, by class (filled by the modules that define the classes).
_DECLARED: dict[type, BatchSupport] = {}
#: Every class asked about so far, with what it inherits (None: nothing declared).
_RESOLVED: dict[type, BatchSupport | None] = {}


def register_batch(cls: type, prepare: Preparer | None = None, *, plans: bool = False) -> None:
    """Declare that predictors of class ``cls`` (and its subclasses) are prepared stacked
    by ``prepare`` (:func:`catc.predict.prepare_at`) and, with ``plans``, implement
    :class:`BatchPredictor` (:func:`catc.predict.predict_columns`)."""
    if plans and not (callable(getattr(cls, "plan", None))
                      and callable(getattr(cls, "plan_pair", None))):
        raise TypeError(f"{cls.__name__} declares plans without plan and plan_pair")
    _DECLARED[cls] = BatchSupport(prepare, plans)
    _RESOLVED.clear()


def batch_support(cls: type) -> BatchSupport | None:
    """What ``cls`` declared with :func:`register_batch`, or inherits from the nearest
    class that did (None: a plain :class:`Predictor`).  A dictionary lookup once a class
    was asked about (the per-RV loops of a tick ask for every predictor)."""
    try:
        return _RESOLVED[cls]
    except KeyError:
        found = next((_DECLARED[k] for k in cls.__mro__ if k in _DECLARED), None)
        _RESOLVED[cls] = found
        return found


def heading_velocity(speed: float, heading_deg: float) -> tuple[float, float]:
    """ENU velocity (east, north) of a vehicle moving at ``speed`` on ``heading_deg``."""
    h = math.radians(heading_deg)
    return speed * math.sin(h), speed * math.cos(h)
