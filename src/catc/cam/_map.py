"""The Context-Aware Map: :class:`ContextAwareMap` and its one entry point, ``step``.

Reference paper, section "Context-Aware Target Classification (CA-TC)"; what one step
does, in order, is the docstring of :mod:`catc.cam`.  Here: the step itself, the HV's own
estimate and path (step 4), tracking every RV at ``now`` and ``now + horizon_s`` (step
5) and the classification of both against the HV's paths, with lane estimation along the
trails of the RVs ahead (step 6); the tracks and their admission are
:class:`catc.cam._tracks.TrackTable`'s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence, Set
from itertools import chain

import numpy as np
import numpy.typing as npt

from catc.bsm import BSM
from catc.cam._config import CamConfig
from catc.cam._snapshot import HostEstimate, MapSnapshot, snapshot_of, with_apps
from catc.cam._tracks import COUNTERS, Track, TrackTable
from catc.classify import (
    DIRECTION_CODES,
    LATERAL_CODES,
    HostPath,
    ZoneArrays,
    classify_direction,
    classify_lateral,
    classify_paths,
    hv_radius_m,
    trail_offset,
)
from catc.geo import EnuFrame
from catc.pathhistory import ConcisePathHistory
from catc.predict import make_predictor, predict_columns, prepare
from catc.predict.base import Observation, Predictor


class ContextAwareMap:
    """The CA-TC state: local map, tracks, path histories, HV path; see the module doc.

    ``apps`` is an optional callable ``apps(snapshot) -> (warnings, events)`` (normally a
    :class:`catc.apps.SafetyApps`) run at the end of every step.
    """

    def __init__(self, config: CamConfig | None = None, apps=None,
                 predictor_kwargs: Mapping | None = None) -> None:
        self.config = config or CamConfig()
        self.apps = apps
        self._predictor_kwargs = dict(predictor_kwargs or {})
        self.frame: EnuFrame | None = (EnuFrame(*self.config.origin)
                                       if self.config.origin is not None else None)
        self._host_predictor = make_predictor(self.config.host_predictor)
        self._host_history = ConcisePathHistory(tolerance_m=self.config.ph_tolerance_m)
        self._host_t = -math.inf
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._hgp = hgp_table(self.config, self._predictor_kwargs)
        histories = None
        if self._hgp is not None:  # numba is in use: the histories batched too
            from catc.cam._histories import PathHistories

            histories = PathHistories(self.config.ph_tolerance_m)
        self._histories = histories
        self._table = TrackTable(self.config, self.counters, self._new_predictor,
                                 histories.row if histories is not None else None)

    # -- public ---------------------------------------------------------------------------
    def __len__(self) -> int:
        """Confirmed tracks (the RVs a snapshot has)."""
        return len(self._table)

    @property
    def tentative(self) -> int:
        """Tracks not confirmed yet."""
        return len(self._table.tentative)

    def history(self, temp_id: int) -> list[tuple[float, float]]:
        """Concise path history of an RV, most recent first (ENU m)."""
        return self._table.tracks[temp_id].history.points()

    def host_history(self) -> list[tuple[float, float]]:
        """Concise path history of the HV, most recent first (ENU m)."""
        return self._host_history.points()

    def drop(self, temp_id: int) -> bool:
        """Forget the RV ``temp_id`` now (a misbehaving sender put in quarantine): its track
        and trail go, so it is neither predicted nor warned about; counted ``dropped`` (a
        counter that appears on first use).  False when it was not tracked."""
        if not self._table.forget(temp_id):
            return False
        self.counters["dropped"] = self.counters.get("dropped", 0) + 1
        return True

    def step(self, now: float, host: BSM, messages: Sequence[BSM] = (),
             unverified: Set[int] = frozenset()) -> MapSnapshot:
        """Advance the map to ``now`` (s, the HV's dataset time) with the HV state ``host``
        and the RV messages received since the last step; see the module docstring.

        ``unverified``: the ``id()`` of each message in ``messages`` whose signature was not
        verified (an OBU verifying on demand defers some).  A track remembers whether its
        latest accepted message was verified (the snapshot's ``verified`` column), and the
        applications see only verified rows: no warning rests on an unverified message.
        Empty (the default): every message counts as verified."""
        if not math.isfinite(now) or now <= self._host_t:
            raise ValueError(f"step times must increase: {now} after {self._host_t}")
        if host.lat is None or host.lon is None:
            raise ValueError("the HV state has no position")
        self.counters["ticks"] += 1
        if self.frame is None:
            self.frame = EnuFrame(host.lat, host.lon, 0.0)
        self._table.note_host_id(now, host.temp_id)
        usable = self._table.timed(now, messages)
        ex, ny = self.frame.en_lists([host.lat] + [m.lat for _, m in usable],
                                     [host.lon] + [m.lon for _, m in usable])
        host_est = self._update_host(now, host, ex[0], ny[0])
        self._table.note_host_position(now, ex[0], ny[0])
        for (t, m), x, y in zip(usable, ex[1:], ny[1:], strict=True):
            self._table.apply(now, t, m, x, y, host_est, self.frame, id(m) not in unverified)
        self._table.evict_stale(now)
        snap = self._snapshot(now, host_est)
        if self.apps is not None:
            warnings, events = self.apps(snap)
            if warnings or events:  # else the copy would equal snap, built with () for both
                snap = with_apps(snap, tuple(warnings), tuple(events))
        return snap

    # -- HV ---------------------------------------------------------------------------------
    def _update_host(self, now: float, host: BSM, x: float, y: float) -> HostEstimate:
        c = self.config
        self._host_t = now
        speed = host.speed or 0.0
        heading = host.heading if host.heading is not None else 0.0
        accel = host.accel_long or 0.0
        self._host_predictor.update(Observation(now, x, y, speed, heading, accel,
                                                host.yaw_rate))
        self._host_history.add(now, x, y)
        radius = hv_radius_m(speed, host.yaw_rate)
        history = self._host_history.point_tuple()
        path = HostPath(x, y, heading, radius, history)
        p = self._host_predictor.predict(now + c.horizon_s)
        predicted = HostPath(p.x, p.y, p.heading, radius, ((x, y), *history))
        return HostEstimate(now, x, y, host.lat, host.lon, speed, heading, accel,
                            host.yaw_rate, host.length or c.default_length_m,
                            host.width or c.default_width_m, radius, path, predicted)

    # -- tracking and classification ---------------------------------------------------------
    def _snapshot(self, now: float, host: HostEstimate) -> MapSnapshot:
        c = self.config
        tracks = self._table.confirmed()
        n = len(tracks)
        later = now + c.horizon_s
        predictors = [tr.predictor for tr in tracks]
        table = self._hgp
        if table is not None:  # every RV a row of the table
            table.prepare(predictors, later)
            values, source = table.columns(predictors, now, later)
        else:
            prepare(predictors, later)  # the HGP's forecasts, stacked
            values, source = predict_columns(predictors, now, later)
        # rows x, pred_x, y, pred_y, speed, pred_speed, heading, pred_heading, var_x, var_y
        (x, pred_x, y, pred_y, speed, pred_speed, heading, pred_heading, var_x,
         var_y) = values
        # The rest of the per-RV values, one row per RV; the rows become one flat array,
        # column after column (numpy converts a flat list fastest; filling arrays row by
        # row costs far more), then sliced into the columns.
        rows: list[tuple] = []
        flags: list[tuple[bool, bool, bool]] = []  # (fresh, hard braking, verified)
        for tr, ex, ey in zip(tracks, x.tolist(), y.tolist(), strict=True):
            accel, length, width, hard = tr.bsm_values
            rows.append((now - tr.t, accel, length, width))
            flags.append((tr.fresh_at == now, hard, tr.verified))
            tr.est_x, tr.est_y = ex, ey
        age, accel, length, width = _flat_columns(rows, np.float64).reshape(4, n)
        fresh, hard, verified = _flat_columns(flags, np.bool_).reshape(3, n)
        ids = np.array([tr.temp_id for tr in tracks], dtype=np.int64)
        # now and later, x, y and heading: the rows of both paths, each n long
        zone, predicted_zone = classify_paths(
            (host.path, host.predicted_path), (n, n), values[0:2].reshape(-1),
            values[2:4].reshape(-1), values[6:8].reshape(-1), c.classify)
        if c.trail_lanes and n:
            zone, on_trail = self._trail_lanes(tracks, zone, host)
        else:
            on_trail = np.zeros(n, dtype=bool)
        return snapshot_of(
            t=now, horizon_s=c.horizon_s, host=host, ids=ids, x=x, y=y, speed=speed,
            heading=heading, accel=accel, var_x=var_x, var_y=var_y, source=tuple(source),
            age=age, fresh=fresh, lane=np.rint(zone.d / c.classify.w_lane).astype(np.int64),
            zone=zone, pred_x=pred_x, pred_y=pred_y, pred_heading=pred_heading,
            pred_speed=pred_speed, predicted_zone=predicted_zone, hard_braking=hard,
            length=length, width=width, on_trail=on_trail, verified=verified,
            counters=dict(self.counters), warnings=(), events=())

    def _trail_lanes(self, tracks: list[Track], zone: ZoneArrays, host: HostEstimate
                     ) -> tuple[ZoneArrays, npt.NDArray[np.bool_]]:
        """Offsets and lane heading along the trails of RVs ahead (module docstring, 6).

        Candidates: Ahead within ``trail_range_m`` and not Oncoming.  When the HV lies on
        an RV's trail, ``s`` is the distance along it, ``d`` minus the HV's offset from
        it, and Eq. (tc_heading) compares the HV's heading with the trail's there.  The
        trail starts at the RV's current estimate (``est_x, est_y``, set by _snapshot).
        """
        c = self.config
        cand = (zone.ahead & (zone.direction != 1) & (zone.s <= c.trail_range_m)).nonzero()[0]
        used = np.zeros(len(tracks), dtype=bool)
        found = []
        if self._histories is not None:  # the rows' trails in one compiled loop
            idx = cand.tolist()
            heads = np.array([(tracks[i].est_x, tracks[i].est_y) for i in idx])
            offs = self._histories.trail_offsets([tracks[i].history.slot for i in idx],
                                                 heads.reshape(-1, 2), (host.x, host.y))
            found = [(i, off) for i, off in zip(idx, offs.tolist(), strict=True)
                     if off[0] == off[0]]
        for i in cand.tolist() if self._histories is None else ():
            tr = tracks[i]
            trail = ((float(tr.est_x), float(tr.est_y)), *tr.history.point_tuple())
            off = trail_offset(trail, (host.x, host.y))
            if off is not None:
                found.append((i, off))
        if not found:
            return zone, used
        s, d = zone.s.copy(), zone.d.copy()
        lane, diff = zone.lane_heading_deg.copy(), zone.heading_diff_deg.copy()
        lateral, direction = zone.lateral.copy(), zone.direction.copy()
        cc = c.classify
        for i, (si, di, lane_i) in found:
            s[i], d[i], lane[i] = si, -di, lane_i
            diff[i] = diff_i = abs((host.heading - lane_i + 180.0) % 360.0 - 180.0)
            used[i] = True
            # Eqs. (tc_lateral) and (tc_heading) on the new values: the scalar forms make
            # the same float comparisons as lateral_codes / direction_codes on the arrays.
            lateral[i] = LATERAL_CODES.index(classify_lateral(-di, cc.w_lane))
            direction[i] = DIRECTION_CODES.index(classify_direction(diff_i, cc))
        # ahead stays the HV-path classification.
        return ZoneArrays(zone.ahead, lateral, direction, s, d, lane, diff), used

    def _new_predictor(self) -> Predictor:
        if self._hgp is not None:
            return self._hgp.row()
        return make_predictor(self.config.predictor, **self._predictor_kwargs)


def hgp_table(config: CamConfig, kwargs: Mapping):
    """The :class:`~catc.predict.hgp.table.HgpTable` of the RVs' predictors when ``config``
    asks for the HGP and the table computes it (``batched``; only ``bank`` and ``config``
    given, a configuration :func:`~catc.predict.hgp.table.supported` takes); None: one
    object per RV.  The HGP (and numba) is imported only then: a CA-TC on another
    predictor starts without it."""
    if not (config.batched and config.predictor == "hgp" and set(kwargs) <= {"bank",
                                                                               "config"}):
        return None
    from catc.predict.hgp import HgpConfig
    from catc.predict.hgp.table import HgpTable, supported

    hgp = kwargs.get("config") or HgpConfig()
    return HgpTable(kwargs.get("bank"), hgp) if supported(hgp) else None


def _flat_columns(rows: list[tuple], dtype: type) -> np.ndarray:
    """The columns of ``rows`` one after the other, as one flat array."""
    return np.array(list(chain.from_iterable(zip(*rows, strict=True))), dtype=dtype)

