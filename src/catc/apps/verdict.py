"""Warnings scored by vehicle: what ``captures score`` and ``captures sweep`` count.

At each tick, for each application, the ground truth (the application on the true
states) names the vehicles it warns on, and the OBU names the ones it warned on.  A
vehicle named by both is a true positive; one the OBU named alone a false positive; one
the truth named alone a false negative; a tick where neither names any vehicle a true
negative.  So a warning on the wrong vehicle (a ghost ahead of the real leader, a
neighbour moved into the lane) is a false positive on that vehicle and a false negative
on the one it should have been, never a true positive.  Accuracy is
(TP + TN) / (TP + TN + FP + FN) over the ticks.

Pure: no I/O.  Vehicle ids may be of any hashable kind (the TemporaryID as an int, or as
the captures' 8 hex digits), the same on both sides.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping

from catc.apps import APPS

__all__ = ["KEYS", "Confusion", "accuracy", "by_app", "tick_confusion"]

#: The confusion counts, in the order the scores list them.
KEYS = ("tp", "tn", "fp", "fn")


def tick_confusion(truth: Iterable[Hashable], warned: Iterable[Hashable]
                   ) -> tuple[int, int, int, int]:
    """(TP, TN, FP, FN) of one application at one tick: the vehicles the ground truth
    warns on against the vehicles warned on (see the module docstring)."""
    t, w = set(truth), set(warned)
    return len(t & w), int(not t and not w), len(w - t), len(t - w)


def accuracy(counts: Mapping[str, int]) -> float | None:
    """(TP + TN) / all, rounded to 4 places; None with nothing counted."""
    total = sum(counts[k] for k in KEYS)
    return round((counts["tp"] + counts["tn"]) / total, 4) if total else None


class Confusion:
    """The confusion counts of each application over the ticks :meth:`add` is given."""

    def __init__(self, apps: Iterable[str] = APPS) -> None:
        self.counts = {a: dict.fromkeys(KEYS, 0) for a in apps}

    def add(self, truth: Mapping[str, Iterable[Hashable]],
            warned: Mapping[str, Iterable[Hashable]]) -> None:
        """One tick: each application's vehicles in the truth and in the warnings (an
        application missing from a mapping names no vehicle)."""
        for app, counts in self.counts.items():
            for key, n in zip(KEYS, tick_confusion(truth.get(app, ()), warned.get(app, ())),
                              strict=True):
                counts[key] += n

    def as_dict(self) -> dict[str, dict[str, int | float | None]]:
        """``{app: {tp, tn, fp, fn, accuracy}}``."""
        return {a: {**c, "accuracy": accuracy(c)} for a, c in self.counts.items()}


def by_app(pairs: Iterable[tuple[str, Hashable]]) -> dict[str, set[Hashable]]:
    """``(app, vehicle)`` pairs (a tick's warnings) grouped as ``{app: vehicles}``."""
    out: dict[str, set[Hashable]] = {}
    for app, vehicle in pairs:
        out.setdefault(app, set()).add(vehicle)
    return out
