"""Quick offline evaluation of predictors: replay tracks through a seeded Bernoulli channel.

For every track (one remote vehicle) and every tick of its 10 Hz time base: if that
tick's BSM arrived, the predictor is updated with it; then the predictor is asked
for the position at the tick's time, and the position tracking error (PTE) is the 2-D
distance to the true position (docs/architecture.md, "Metrics").  A tick that has just received
a fresh BSM counts too, so PER 0 gives PTE 0.  Ticks before the first received BSM
are not scored (the RV is not yet known).  PTE95 is the 95th percentile over all
scored ticks of all tracks and seeds.

Every predictor sees the same loss pattern: :func:`catc.channel.bernoulli_received`
depends only on (seed, vehicle, message index).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from catc.channel import bernoulli_received
from catc.mobility import MobilityTable, Track
from catc.predict.base import Observation, Predictor

#: PTE thresholds (m) for the paper's threshold-exceedance counts.
PTE_THRESHOLDS = (0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6)


def observations(track: Track) -> list[Observation]:
    """The observation each of the track's BSMs would carry."""
    return [Observation(t, x, y, s, h, a, w) for t, x, y, s, h, a, w in zip(
        track.t.tolist(), track.x.tolist(), track.y.tolist(), track.speed.tolist(),
        track.heading.tolist(), track.accel.tolist(), track.yaw_rate.tolist(), strict=True)]


def replay_track(track: Track, predictor: Predictor, received: np.ndarray) -> np.ndarray:
    """PTE (m) at every tick of ``track``; NaN before the first received message."""
    predictor.reset()
    obs = observations(track)
    errors = np.full(len(obs), np.nan)
    started = False
    for i, o in enumerate(obs):
        if received[i]:
            predictor.update(o)
            started = True
        if started:
            p = predictor.predict(o.t)
            errors[i] = np.hypot(p.x - o.x, p.y - o.y)
    return errors


@dataclass(frozen=True)
class Score:
    """PTE statistics of one predictor at one PER."""

    predictor: str
    per: float
    pte95_m: float
    pte_mean_m: float
    n_ticks: int
    exceedances: dict[float, int]


def score(errors: np.ndarray, predictor: str, per: float) -> Score:
    e = errors[~np.isnan(errors)]
    return Score(predictor=predictor, per=per,
                 pte95_m=float(np.percentile(e, 95)) if len(e) else float("nan"),
                 pte_mean_m=float(e.mean()) if len(e) else float("nan"), n_ticks=len(e),
                 exceedances={th: int((e > th).sum()) for th in PTE_THRESHOLDS})


def evaluate(
    tables: Iterable[MobilityTable],
    predictors: dict[str, Callable[[], Predictor]],
    pers: Sequence[float],
    seeds: Sequence[int] = (0,),
    progress: Callable[[int, int], None] | None = None,
) -> list[Score]:
    """PTE scores for every (predictor, PER), each over all tracks and seeds.

    ``predictors`` maps a name to a factory; ``progress(done, total)`` is called after
    each track replay when given.
    """
    # The channel key names the trip too: vehicle ids repeat across NGSIM pairs.
    tracks = [(f"{table.name}/{tr.vehicle_id}", tr) for table in tables
              for tr in table.tracks.values()]
    total = len(tracks) * len(pers) * len(seeds) * len(predictors)
    done = 0
    scores = []
    for per in pers:
        for name, factory in predictors.items():
            predictor = factory()
            errors = []
            for seed in seeds:
                for key, tr in tracks:
                    received = bernoulli_received(seed, key, len(tr), per)
                    errors.append(replay_track(tr, predictor, received))
                    done += 1
                    if progress is not None:
                        progress(done, total)
            scores.append(score(np.concatenate(errors), name, per))
    return scores


def hindsight_offset(later_x: np.ndarray, later_y: np.ndarray, px: float,
                     py: float) -> float | None:
    """Signed offset (m, positive right) of (px, py) from the path a vehicle actually drove
    next (``later_x/y``: its positions from now on), or None when that path does not reach
    (px, py) in the window.  The ground truth of "same lane" that lane estimation is
    scored against (tests/test_cam_data.py, bench/lanes.py)."""
    bx, by = np.diff(later_x), np.diff(later_y)
    seg2 = bx * bx + by * by
    keep = seg2 > 1e-6
    if not keep.any():
        return None
    bx, by, seg2 = bx[keep], by[keep], seg2[keep]
    x0, y0 = later_x[:-1][keep], later_y[:-1][keep]
    t = np.clip(((px - x0) * bx + (py - y0) * by) / seg2, 0.0, 1.0)
    ex, ey = px - (x0 + t * bx), py - (y0 + t * by)
    d2 = ex * ex + ey * ey
    j = int(np.argmin(d2))
    if j == len(bx) - 1 and t[j] >= 1.0:
        return None
    return float(np.copysign(np.sqrt(d2[j]), ex[j] * by[j] - ey[j] * bx[j]))



@dataclass(frozen=True)
class LaneScore:
    """Lane estimation against the hindsight truth (:func:`lane_agreement`)."""

    ticks: int  # ticks scored
    agree: int  # the CAM's lateral class = the truth's
    agree_straight: int  # a straight-line projection's lateral class = the truth's
    ahead_ongoing: int  # the RV classified Ahead and Ongoing


def lane_agreement(table: MobilityTable, config, *, horizon: int = 100) -> LaneScore:
    """Each vehicle of a platoon seen from the one behind it (no loss), through a
    :class:`catc.cam.ContextAwareMap` with ``config``: at every tick the host moves
    (>= 1 m/s), is the lead's lateral class the class of its offset from the host's own
    path over the next ``horizon`` samples (:func:`hindsight_offset`)?  Vehicles split
    into pieces (ids with ``#``) are left out."""
    from catc.cam import ContextAwareMap
    from catc.classify import HostPath, lateral_codes
    from catc.replay import run_offline, temp_id

    w = config.classify.w_lane
    ids = [v for v in table.tracks if "#" not in v]
    n = agree = straight = ahead = 0
    for lead, host in itertools.pairwise(ids):
        h = table.tracks[host]
        for k, snap in enumerate(run_offline(table, ContextAwareMap(config), host_id=host)):
            if snap.host.speed < 1.0:
                continue
            try:
                i = snap.index(temp_id(lead))
            except KeyError:
                continue
            d = hindsight_offset(h.x[k:k + horizon], h.y[k:k + horizon], snap.x[i], snap.y[i])
            if d is None:
                continue
            truth = lateral_codes(np.array([d]), w)[0]
            sd = HostPath(snap.host.x, snap.host.y, snap.host.heading).to_path_frame(
                (snap.x[i], snap.y[i]))[1]
            n += 1
            agree += int(snap.zone.lateral[i] == truth)
            straight += int(lateral_codes(np.array([sd]), w)[0] == truth)
            ahead += int(bool(snap.zone.ahead[i]) and snap.zone.direction[i] == 0)
    return LaneScore(n, agree, straight, ahead)
