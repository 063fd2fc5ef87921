"""The HGP table (issue 30, item 3): rows of shared arrays that answer what
:class:`catc.predict.hgp.HgpPredictor` objects answer, bit for bit, and the CA-TC on it
against the CA-TC on objects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from catc.predict.base import Observation
from catc.predict.forecast import read
from catc.predict.hgp import HgpConfig, HgpPredictor
from catc.predict.hgp.table import HgpTable, supported


def _tracks(n: int, samples: int, per: float, seed: int) -> list[list[Observation]]:
    """``n`` vehicles' received observations: a weave with speed changes and full turns
    (headings through north), messages lost with probability ``per`` (bursts too), times
    on the 0.1 s grid with the odd ms of jitter."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        v0, w = rng.uniform(5.0, 30.0), rng.uniform(-0.4, 0.4)
        x = y = 0.0
        heading = rng.uniform(0.0, 360.0)
        obs = []
        burst = 0
        for k in range(samples):
            speed = max(0.0, v0 + 3.0 * math.sin(0.05 * k + i))
            accel = 0.15 * math.cos(0.05 * k + i)
            yaw = math.degrees(w) * math.cos(0.02 * k)
            heading = (heading + 0.1 * yaw) % 360.0
            x += 0.1 * speed * math.sin(math.radians(heading))
            y += 0.1 * speed * math.cos(math.radians(heading))
            if burst:
                burst -= 1
                continue
            if rng.random() < per:
                burst = int(rng.integers(0, 25)) if rng.random() < 0.1 else 0
                continue
            t = round(0.1 * k + (0.001 * rng.integers(-1, 2) if k % 7 == 3 else 0.0), 3)
            obs.append(Observation(t, x, y, speed, heading, accel, yaw))
        out.append(out_of_order(obs, rng))
    return out


def out_of_order(obs: list[Observation], rng) -> list[Observation]:
    """Some observations repeated late (ignored by both: not newer than the last)."""
    out = []
    for o in obs:
        out.append(o)
        if len(out) > 3 and rng.random() < 0.03:
            out.append(out[-3])
    return out


def _same(a, b) -> None:
    if isinstance(a, tuple):
        a = read(*a)
    if isinstance(b, tuple):
        b = read(*b)
    fa = (a.x, a.y, a.speed, a.heading, a.var_x, a.var_y, a.source)
    fb = (b.x, b.y, b.speed, b.heading, b.var_x, b.var_y, b.source)
    assert all(p == q or (p != p and q != q) for p, q in zip(fa, fb, strict=True)), (fa, fb)


@pytest.mark.parametrize("fit", [0.0, 0.05], ids=["gaps-reselect", "fit-keeps"])
@pytest.mark.parametrize("per", [0.0, 0.5, 0.9])
def test_rows_answer_what_the_objects_answer_bit_for_bit(per: float, fit: float) -> None:
    """Vehicles fed in lockstep, read every other tick (so a row often has two queued
    observations), forecasts prepared stacked, answers read at the tick and 2 s ahead,
    and one by one at odd times: every number the same as the objects', with and without
    a fit that lets a selection survive a gap (``reselect_fit_m``)."""
    tracks = _tracks(40, 400, per, seed=int(per * 10))
    c = HgpConfig(reselect_fit_m=fit)
    table = HgpTable(capacity=8, config=c)  # grows
    rows = [table.row() for _ in tracks]
    objs = [HgpPredictor(config=c) for _ in tracks]
    pos = [0] * len(tracks)
    for tick in range(1, 400):
        now = round(0.1 * tick, 3)
        live = []
        for i, obs in enumerate(tracks):
            while pos[i] < len(obs) and obs[pos[i]].t <= now:
                rows[i].update(obs[pos[i]])
                objs[i].update(obs[pos[i]])
                pos[i] += 1
            if pos[i]:
                live.append(i)
        if not live or tick % 2:  # two ticks' observations queued before a read
            continue
        later = now + 2.0
        if tick % 10:
            table.prepare([rows[i] for i in live], later)
            vals, src = table.columns([rows[i] for i in live], now, later)
            from catc.predict import predict_columns, prepare

            prepare([objs[i] for i in live], later)
            ref, ref_src = predict_columns([objs[i] for i in live], now, later)
            assert src == ref_src
            np.testing.assert_array_equal(vals, ref)
        else:  # one by one, at odd times, before any stacked forecast
            for i in live[::3]:
                t = now + 0.37 * (i % 4)
                _same(rows[i].predict(t), objs[i].predict(t))
    assert [r.stats for r in rows] == [o.stats for o in objs]
    # the branches' scores at every gap's end, every bit (they choose who answers)
    table.flush()  # the last tick's updates are still queued
    assert [table._scores[r.slot].score for r in rows] == [o._branches.score for o in objs]
    if per:  # (no gap at PER 0: nothing scored)
        assert sum(sum(o._branches.scored) for o in objs) > 100


def test_a_released_row_comes_back_empty_and_its_queued_updates_are_dropped() -> None:
    table = HgpTable(capacity=2)
    a, b = table.row(), table.row()
    for k in range(10):
        a.update(Observation(0.1 * k, 0.0, 2.0 * k, 20.0, 0.0, 0.0, 0.0))
    first = Observation(0.0, 5.0, 0.0, 10.0, 90.0, 0.0, 0.0)
    b.update(first)
    a.release()
    c = table.row()  # a's row, once its updates are dropped
    assert c.slot == a.slot and not a.alive
    fresh = HgpPredictor()
    for k in range(3):
        o = Observation(5.0 + 0.1 * k, 1.0, 1.0 + k, 10.0, 10.0, 0.5, 1.0)
        c.update(o)
        fresh.update(o)
    _same(c.predict(6.0), fresh.predict(6.0))
    other = HgpPredictor()
    other.update(first)
    _same(b.predict(1.0), other.predict(1.0))  # its neighbour's release changed nothing
    with pytest.raises(LookupError):
        table.row().predict(1.0)


def test_only_the_configurations_it_computes() -> None:
    assert supported(HgpConfig())
    for c in (HgpConfig(online=True), HgpConfig(branch_blend=1.0), HgpConfig(slopes=False),
              HgpConfig(branches=("ctrv",)), HgpConfig(window_s=3.0)):
        assert not supported(c)
        with pytest.raises(ValueError):
            HgpTable(config=c)
    assert supported(HgpConfig(branches=())) and supported(HgpConfig(branches=("kf",)))


def test_the_ca_tc_on_the_table_is_the_ca_tc_on_objects() -> None:
    """The step scene of bench/step.py (TemporaryIDs as the RVE makes them) at PER 50 %:
    every snapshot's columns and warnings the same with the table as with objects."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import step
    from catc.apps import SafetyApps
    from catc.cam import CamConfig, ContextAwareMap

    scene = step.scene(120, 160)
    maps = [ContextAwareMap(CamConfig(origin=step.ORIGIN, batched=flag), SafetyApps())
            for flag in (True, False)]
    assert maps[0]._hgp is not None and maps[1]._hgp is None
    for now, host, msgs in scene:
        a, b = (m.step(now, host, msgs) for m in maps)
        for name in ("ids", "x", "y", "speed", "heading", "var_x", "var_y", "pred_x",
                     "pred_y", "pred_speed", "pred_heading", "lane"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert a.source == b.source and a.warnings == b.warnings
    assert a.counters == b.counters
