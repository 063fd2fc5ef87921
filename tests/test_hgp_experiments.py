"""captures.hgp_experiments: the paper's H1 and H2 experiments on the real OpenACC trips."""

from __future__ import annotations

import json
import math
from importlib import resources

import numpy as np
import pytest

from captures import hgp_experiments as hx
from catc.predict.bank import default_bank
from catc.predict.training import persistency
from hil.datasets import load
from tests.conftest import shared_path

SMALL_TRIP = "short_setting_dynamic_part22.csv"  # 33 s, two vehicles
HOLDOUT_SAMPLES = 2500  # samples of held-out tracks walked in the tests (~2 s per walk)


@pytest.fixture(scope="module")
def small_tables():
    return load(str(shared_path("openacc-zalazone", SMALL_TRIP)))


@pytest.fixture(scope="module")
def h1_rows(small_tables):
    pytest.importorskip("sklearn")
    return hx.h1_fit_time(small_tables, tws=(10, 30, 100), windows=6, repeats=2, seed=1)


@pytest.fixture(scope="module")
def holdout_tracks():
    tables = hx.holdout_tables(data_dir=shared_path("openacc-zalazone"))
    tracks, total = [], 0
    for tr in (tr for t in tables for tr in t.tracks.values()):
        if total + len(tr) <= HOLDOUT_SAMPLES:
            tracks.append(tr)
            total += len(tr)
    assert len(tracks) >= 2
    return tracks


@pytest.fixture(scope="module")
def rate(holdout_tracks):
    return hx.h2_new_kernel_rate(holdout_tracks, default_bank(), bin_s=20)


def test_speed_windows_are_real_consecutive_and_seeded(small_tables):
    tracks = [tr for t in small_tables for tr in t.tracks.values()]
    wins = hx.speed_windows(small_tables, 30, 8, seed=3)
    assert len(wins) == 8
    for tau, y in wins:
        assert len(tau) == len(y) == 30 and tau[-1] == 0.0 and y[-1] == 0.0
        np.testing.assert_allclose(np.diff(tau), 0.1, atol=1e-6)
        # a real stretch of some track: its speed differences occur in the data
        assert any(np.allclose(np.diff(y), np.diff(tr.speed[i:i + 30]))
                   for tr in tracks for i in range(len(tr) - 29)
                   if np.isclose(tr.speed[i + 29] - tr.speed[i], y[-1] - y[0]))
    again = hx.speed_windows(small_tables, 30, 8, seed=3)
    other = hx.speed_windows(small_tables, 30, 8, seed=4)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(wins, again, strict=True))
    assert not all(np.array_equal(a[1], b[1]) for a, b in zip(wins, other, strict=True))
    # more windows asked than exist: all of them, each once
    assert len(hx.speed_windows(small_tables, 300, 10_000)) == sum(
        max(0, len(tr) - 299) for tr in tracks)


def test_h1_fit_time_columns(h1_rows):
    assert [r["tw"] for r in h1_rows] == [10, 30, 100]
    for r in h1_rows:
        assert r["windows"] == 6 and r["repeats"] == 2 and r["threshold_ms"] == 100.0
        for side in ("ours", "sklearn"):
            med, p95 = r[f"{side}_median_ms"], r[f"{side}_p95_ms"]
            assert math.isfinite(med) and 0 < med <= p95 < math.inf
            assert r[f"{side}_under_threshold"] == (p95 < 100.0)
        assert r["ratio"] == pytest.approx(r["sklearn_median_ms"] / r["ours_median_ms"])
        assert r["window_s"] == pytest.approx(r["tw"] / 10)


def test_h1_without_sklearn_leaves_its_columns_empty(small_tables):
    (row,) = hx.h1_fit_time(small_tables, tws=(20,), windows=3, repeats=1, sklearn=False)
    assert row["ours_median_ms"] > 0
    assert row["sklearn_median_ms"] is row["sklearn_p95_ms"] is row["ratio"] is None
    assert row["sklearn_under_threshold"] is None


def test_h2_cluster_size_reproduces_the_shipped_bank():
    text = resources.files("catc.predict").joinpath("default_bank.json").read_text()
    recorded = json.loads(text)["stats"]["mp_vs_cluster_size"]
    for meta in (None, default_bank().meta, json.loads(text)):
        rows = hx.h2_cluster_size(meta)
        assert [{k: v for k, v in r.items() if k != "source"} for r in rows] == recorded
        assert all("make bank" in r["source"] for r in rows)
    with pytest.raises(ValueError, match="mp_vs_cluster_size"):
        hx.h2_cluster_size({"command": "hand-made"})


def test_holdout_tables_are_the_banks_held_out_files():
    meta = default_bank().meta
    tables = hx.holdout_tables(meta, shared_path("openacc-zalazone"))
    names = {t.name for t in tables}
    assert names == {n.removesuffix(".csv") for n in meta["holdout"]}
    assert not names & {n.removesuffix(".csv") for n in meta["trained_on"]}
    with pytest.raises(FileNotFoundError):
        hx.holdout_tables(meta, shared_path("openacc-zalazone") / "no-such-folder")


def test_h2_rate_totals_equal_persistency(rate, holdout_tracks):
    assert rate["totals"] == persistency(holdout_tracks, default_bank(), hx.TRAIN)
    assert rate["totals"]["new_kernel_events"] > 0  # the slice is not trivial
    events = rate["events"]
    assert len(events) == rate["totals"]["switches"]
    assert sum(e["new"] for e in events) == rate["totals"]["new_kernel_events"]
    # the per-minute rate is on the same driving clock as persistency's
    assert rate["totals"]["new_kernels_per_min"] == pytest.approx(
        rate["totals"]["new_kernel_events"] / (rate["driven_s"] / 60))
    assert rate["tracks"] == len(holdout_tracks) and rate["bank_pairs"] == len(default_bank())


def test_h2_rate_bins_and_cumulative_count(rate, holdout_tracks):
    bins, events, total = rate["bins"], rate["events"], rate["totals"]["new_kernel_events"]
    assert bins[0]["start_s"] == 0 and bins[-1]["end_s"] == pytest.approx(rate["driven_s"])
    assert all(b["end_s"] - b["start_s"] == pytest.approx(20) for b in bins[:-1])
    assert 0 < bins[-1]["end_s"] - bins[-1]["start_s"] <= 20 + 1e-9
    cum = [b["cumulative"] for b in bins]
    assert np.all(np.diff(cum) >= 0) and cum[-1] == total
    assert sum(b["new_kernels"] for b in bins) == total
    assert bins[-1]["cumulative_switches"] == rate["totals"]["switches"]
    for b in bins:
        minutes = (b["end_s"] - b["start_s"]) / 60
        assert b["rate_per_min"] * minutes == pytest.approx(b["new_kernels"])
        assert b["new_kernels"] <= b["switches"]
    times = [e["driven_s"] for e in events]
    assert times == sorted(times) and times[0] >= 0 and times[-1] <= rate["driven_s"]
    lengths = [tr.t[-1] - tr.t[0] for tr in holdout_tracks]
    assert all(0 <= e["t_trip_s"] <= lengths[e["track"]] for e in events)
    assert sum(lengths) == pytest.approx(rate["driven_s"])


def test_figures_draw(h1_rows, rate):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3)
    try:
        hx.plot_h1(axes[0], h1_rows)
        assert len(axes[0].lines) == 3  # ours, sklearn, the 100 ms line
        assert len(axes[0].collections) == 2  # the two median-to-p95 bands
        assert axes[0].get_yscale() == "log" and axes[0].get_legend() is not None
        assert 100.0 in axes[0].lines[-1].get_ydata()

        rows = hx.h2_cluster_size()
        twin = hx.plot_h2_cluster(axes[1], rows)
        assert len(axes[1].lines[0].get_xdata()) == len(rows) == len(twin.lines[0].get_xdata())
        assert axes[1].get_xscale() == "log" and axes[1].get_legend() is not None

        twin = hx.plot_h2_rate(axes[2], rate)
        assert len(axes[2].patches) == len(rate["bins"])
        assert twin.lines[0].get_ydata()[-1] == rate["totals"]["new_kernel_events"]
        assert axes[2].get_legend() is not None
        for ax in axes:
            assert ax.get_xlabel() and ax.get_ylabel() and ax.get_title()
        fig.canvas.draw()
    finally:
        plt.close(fig)
