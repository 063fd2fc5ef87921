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
