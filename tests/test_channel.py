"""The seeded channel: a pure function of (seed, vehicle, message index)."""

from __future__ import annotations

import numpy as np
import pytest

from catc.channel import bernoulli_received, uniforms


def test_decisions_do_not_depend_on_how_they_are_asked():
    full = uniforms(7, "RV-1", np.arange(1000))
    assert np.array_equal(uniforms(7, "RV-1", np.arange(500, 1000)), full[500:])
    assert np.array_equal(uniforms(7, "RV-1", np.array([999, 3])), full[[999, 3]])
    assert np.array_equal(bernoulli_received(7, "RV-1", 1000, 0.3), full >= 0.3)


def test_seeds_and_vehicles_give_different_patterns():
    a = bernoulli_received(1, "A", 2000, 0.5)
    assert not np.array_equal(a, bernoulli_received(2, "A", 2000, 0.5))
    assert not np.array_equal(a, bernoulli_received(1, "B", 2000, 0.5))
    assert np.array_equal(a, bernoulli_received(1, "A", 2000, 0.5))


@pytest.mark.parametrize("per", [0.0, 0.1, 0.5, 0.9, 0.95, 1.0])
def test_loss_rate_and_independence(per):
    got = bernoulli_received(3, "RV", 100_000, per)
    assert abs((1 - got.mean()) - per) < 0.006
    if 0 < per < 1:  # consecutive losses are independent: P(lost | lost) ≈ PER
        lost = ~got
        assert abs(lost[1:][lost[:-1]].mean() - per) < 0.01


def test_uniforms_are_uniform():
    u = uniforms(11, 42, np.arange(200_000))
    assert u.min() >= 0 and u.max() < 1
    hist, _ = np.histogram(u, bins=20, range=(0, 1))
    assert np.all(np.abs(hist / len(u) - 0.05) < 0.003)


def test_bad_per():
    with pytest.raises(ValueError, match="packet error rate"):
        bernoulli_received(0, "x", 10, 1.5)


# --- the RVE's channel model ------------------------------------------------------------------

from catc.channel import (  # noqa: E402
    ChannelConfig,
    gilbert_lost,
    reception_probability,
    schedule,
    sent_indices,
)

T = np.arange(6000) * 0.1


def test_rate_subsampling_by_hand():
    assert sent_indices(10, 10).tolist() == list(range(10))
    assert sent_indices(10, 5).tolist() == [0, 2, 4, 6, 8]
    # 3 Hz: floor(0.3 i) steps up at i = 0, 4 (1.2), 7 (2.1), 10 (3.0), 14 (4.2), 17 (5.1)
    assert sent_indices(20, 3).tolist() == [0, 4, 7, 10, 14, 17]
    assert sent_indices(30, 1).tolist() == [0, 10, 20]
    for rate in range(1, 11):
        assert len(sent_indices(6000, rate)) == 600 * rate


def test_schedule_bernoulli_equals_the_evaluation_channel():
    sch = schedule(ChannelConfig(per=0.3), 7, "RV-1", T)
    assert np.array_equal(~sch["dropped"], bernoulli_received(7, "RV-1", len(T), 0.3))
    assert np.all(sch["delay"][~sch["dropped"]] == 0.0)
    assert np.all(np.isnan(sch["delay"][sch["dropped"]]))


@pytest.mark.parametrize(("per", "burst"), [(0.5, 4.0), (0.2, 2.0), (0.9, 20.0)])
def test_gilbert_loss_rate_and_mean_burst(per, burst):
    lost = gilbert_lost(5, "RV", 200_000, per, burst)
    assert abs(lost.mean() - per) < 0.02
    edges = np.diff(np.concatenate(([0], lost.astype(int), [0])))
    runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    assert abs(runs.mean() - burst) / burst < 0.05
    # prefix property: the first k decisions do not depend on n
    assert np.array_equal(gilbert_lost(5, "RV", 1000, per, burst), lost[:1000])


def test_gilbert_rejects_impossible_bursts():
    with pytest.raises(ValueError, match="bursts of at least"):
        gilbert_lost(0, "x", 10, 0.9, 2.0)


def test_reception_probability_curve():
    p = reception_probability(np.array([1.0, 100.0, 300.0, 500.0, 1000.0]))
    assert p[0] > 0.9999 and np.all(np.diff(p) < 0)
    assert p[1:] == pytest.approx([0.99, 0.79, 0.41, 0.01], abs=0.01)


def test_distance_losses_follow_the_curve():
    d = np.full(len(T), 500.0)
    sch = schedule(ChannelConfig(distance=True), 1, "RV", T, d)
    assert abs(sch["dropped"].mean() - (1 - 0.408)) < 0.02
    assert set(np.unique(sch["cause"])) == {0, 2}
    with pytest.raises(ValueError, match="distance"):
        schedule(ChannelConfig(distance=True), 1, "RV", T)


def test_latency_jitter_and_reordering():
    cfg = ChannelConfig(latency_s=0.05, jitter_s=0.3)
    sch = schedule(cfg, 2, "RV", T)
    d = sch["delay"]
    assert d.min() >= 0.05 and d.max() <= 0.35
    assert abs(d.mean() - 0.2) < 0.01
    arrival = sch["t"] + d
    assert np.any(np.diff(arrival) < 0)  # some messages overtake their predecessor


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return all(np.array_equal(a[f], b[f], equal_nan=f == "delay") for f in a.dtype.names)


def test_schedule_is_pure_and_prefix_stable():
    cfg = ChannelConfig(per=0.4, burst=3.0, rate_hz=5, latency_s=0.01, jitter_s=0.02)
    a = schedule(cfg, 9, "RV", T)
    assert _same(a, schedule(cfg, 9, "RV", T))
    b = schedule(cfg, 9, "RV", T[:1000])
    assert _same(a[: len(b)], b)
    assert not np.array_equal(a["dropped"], schedule(cfg, 10, "RV", T)["dropped"])


@pytest.mark.parametrize("kwargs", [{"per": 1.2}, {"burst": 0.5}, {"rate_hz": 20},
                                    {"latency_s": -1.0}, {"nakagami_m": 0.1}])
def test_bad_channel_config(kwargs):
    with pytest.raises(ValueError):
        ChannelConfig(**kwargs)
