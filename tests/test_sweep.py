"""`captures sweep`: the grid, the engines (in process, local processes, Dask), the live
spot checks through the real daemons, and the figures, on the shared real data."""

from __future__ import annotations

import json
import subprocess
import sys
from functools import partial

import numpy as np
import pytest

from captures.sweep import SweepError, load_datasets, sweep
from captures.sweep_tables import summary
from catc.evaluate import evaluate
from catc.predict import make_predictor
from catc.sweep import (
    Cell,
    cam_run,
    cells,
    fcw_scene,
    lockstep_errors,
    pool,
    run_cell,
    track_errors,
    truth_fcw,
    vehicle_ahead,
)
from hil.datasets import load, load_table
from tests.conftest import shared_path


@pytest.fixture(scope="module")
def ngsim():
    return load(f"ngsim:{shared_path('ngsim-i80-pairs')}")


def test_paper_grid_is_per_at_top_rate_plus_rate_at_lowest_per():
    grid = cells([0, 0.5, 0.9], [10, 5, 1])
    assert grid == [Cell(0.0, 1.0), Cell(0.0, 5.0), Cell(0.0, 10.0), Cell(0.5, 10.0),
                    Cell(0.9, 10.0)]
    assert len(cells([0, 0.5, 0.9], [10, 5, 1], grid="cross")) == 9
    for bad in ([1.0], [-0.1]):
        with pytest.raises(ValueError, match="PER"):
            cells(bad, [10])
    with pytest.raises(ValueError, match="rate"):
        cells([0], [20])


def test_track_engine_at_10_hz_is_the_bernoulli_evaluation(ngsim):
    """The sweep's channel (rate subsampling, then loss) at 10 Hz draws exactly the losses
    of `captures evaluate`, so both give the same PTE samples."""
    tabs = ngsim[:4]
    for name in ("ca", "hgp"):
        ref = evaluate(tabs, {name: partial(make_predictor, name)}, [0.6], [3])[0]
        rows = pool("ngsim", [run_cell(t, name, Cell(0.6), 3, fcw=False) for t in tabs])
        assert rows.n_ticks == ref.n_ticks
        assert rows.pte95_m == pytest.approx(ref.pte95_m, abs=1e-4)
        # all trips' vehicles in lockstep, HGP forecasts stacked: the same samples
        errors, _, _ = lockstep_errors([(f"{t.name}/{v}", tr) for t in tabs
                                        for v, tr in t.tracks.items()], name, Cell(0.6), 3)
        one_by_one = [track_errors(t, name, Cell(0.6), 3)[0] for t in tabs]
        np.testing.assert_allclose(np.concatenate(errors), np.concatenate(one_by_one),
                                   atol=1e-5)


def test_hold_error_at_half_rate_is_the_distance_since_the_last_message(ngsim):
    """5 Hz, no loss: every other tick has no message; hold's error there is exactly the
    distance the vehicle moved in 0.1 s, and 0 on the ticks with a message."""
    t = ngsim[0]
    e, sent, dropped = track_errors(t, "hold", Cell(0.0, 5.0), 0)
    expect = []
    for tr in t.tracks.values():
        step = np.hypot(np.diff(tr.x), np.diff(tr.y))
        ex = np.zeros(len(tr))
        ex[1::2] = step[0::2]
        expect.append(ex)
    np.testing.assert_allclose(e, np.concatenate(expect).astype(np.float32), atol=1e-5)
    assert dropped == 0 and sent == sum((len(tr) + 1) // 2 for tr in t.tracks.values())


def test_fcw_is_exact_on_the_true_states_and_degrades_with_loss(ngsim):
    """At PER 0 and 10 Hz every predictor reproduces the truth's FCW (accuracy 1 with real
    warnings in it); at PER 90 % the BSM-dependent baseline (hold) gets ticks wrong."""
    tabs = [t for t in ngsim[:12] if any(truth_fcw(fcw_scene(t)))][:3]
    assert tabs, "no FCW in the first NGSIM pairs"
    for name in ("hold", "hgp"):
        r = pool("ngsim", [run_cell(t, name, Cell(0.0), 0) for t in tabs])
        assert r.fcw_accuracy == 1.0 and r.fcw["tp"] > 0 and r.fcw["fp"] == r.fcw["fn"] == 0
    bad = pool("ngsim", [run_cell(t, "hold", Cell(0.9), 0) for t in tabs])
    assert bad.fcw_accuracy < 1.0 and bad.fcw["fp"] + bad.fcw["fn"] > 0


def test_cam_engine_scores_like_the_track_engine_on_the_same_vehicle(ngsim):
    """The CA-TC's PTE of the leader (as the OBU sees it) against the track engine's PTE of
    the same vehicle with the same losses: the same to J2735 quantisation.  The CA-TC
    scores the leader once its track is confirmed (CamConfig.confirm_near accepted BSMs:
    it starts near the host), the track engine from its first BSM."""
    t = ngsim[1]
    lead = next(iter(t.tracks))
    only = fcw_scene(t)
    from dataclasses import replace

    lead_only = replace(t, tracks={lead: t.tracks[lead]})
    e_track, *_ = track_errors(lead_only, "ca", Cell(0.5), 7)
    e_cam = cam_run(only, "ca", Cell(0.5), 7, wire=True).pte
    assert 0 <= len(e_track) - len(e_cam) <= 12  # 4 BSMs at PER 50 %, seed 7
    assert abs(np.percentile(e_cam, 95) - np.percentile(e_track, 95)) < 0.02


def _rows(**kw):
    datasets, _ = load_datasets([f"ngsim:{shared_path('ngsim-i80-pairs')}"], max_trips=3)
    return [r.as_dict() for r in sweep(datasets, ["hold", "ca", "hgp"],
                                       cells([0, 0.7], [10, 3]), [0, 1],
                                       fcw_predictors=["ca"], **kw)]


@pytest.mark.slow
def test_rows_are_the_same_in_process_in_local_processes_and_on_dask():
    distributed = pytest.importorskip("distributed")
    one = _rows(workers=1)
    assert _rows(workers=1) == one  # reproducible
    assert _rows(workers=2) == one
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        assert _rows(dask=cluster.scheduler_address) == one
    by = {(r["predictor"], r["per"], r["rate"]): r for r in one}
    assert by["ca", 70.0, 10.0]["fcw_accuracy"] is not None
    assert by["hgp", 70.0, 10.0]["fcw_accuracy"] is None  # not asked for
    assert by["hold", 0.0, 10.0]["pte95_m"] == 0.0
    assert by["hold", 70.0, 10.0]["pte95_m"] > by["hgp", 70.0, 10.0]["pte95_m"]
    assert by["hold", 0.0, 3.0]["pte95_m"] > 0.0
    for r in one:
        ex = list(r["exceedances"].values())
        assert ex == sorted(ex, reverse=True) and ex[0] <= r["n_ticks"]
    assert "PER [%]" in summary(one) and "Rate [Hz]" in summary(one)


def test_pooled_rows_put_every_dataset_in_one_percentile(tmp_path):
    """With two datasets, each (predictor, cell) has a third row, ``pooled``: the 95th
    percentile of both datasets' PTE samples together and the FCW counts added up.  The
    expected numbers are made here from the per-trip errors (track_errors), not by pool()."""
    ng = f"ngsim:{shared_path('ngsim-i80-pairs')}"
    datasets, _ = load_datasets([ng], max_trips=2)
    (tmp_path / "b").mkdir()  # the same trips again under another name: a second dataset
    (tmp_path / "b" / "ngsim-copy").symlink_to(shared_path("ngsim-i80-pairs"))
    more, _ = load_datasets([f"ngsim:{tmp_path / 'b' / 'ngsim-copy'}"], max_trips=3)
    datasets.update(more)
    cell = Cell(0.6, 10.0)
    rows = {(r.dataset, r.predictor): r for r in sweep(datasets, ["ca"], [cell], [0],
                                                       fcw_predictors=["ca"])}
    assert set(rows) == {("ngsim-i80-pairs", "ca"), ("ngsim-copy", "ca"), ("pooled", "ca")}
    errors = np.concatenate([track_errors(t, "ca", cell, 0)[0]
                             for tabs in datasets.values() for t in tabs])
    pooled = rows["pooled", "ca"]
    assert pooled.n_ticks == len(errors) == sum(rows[d, "ca"].n_ticks for d in datasets)
    assert pooled.pte95_m == round(float(np.percentile(errors.astype(np.float64), 95)), 4)
    assert pooled.trips == 5
    for k in ("tp", "tn", "fp", "fn"):
        assert pooled.fcw[k] == sum(rows[d, "ca"].fcw[k] for d in datasets)
    assert pooled.fcw_accuracy == round(
        (pooled.fcw["tp"] + pooled.fcw["tn"]) / sum(pooled.fcw.values()), 5)
    # one dataset: no pooled rows; a dataset named like them is refused
    one = sweep(more, ["ca"], [cell], [0])
    assert [r.dataset for r in one] == ["ngsim-copy"]
    (tmp_path / "pooled").symlink_to(shared_path("ngsim-i80-pairs"))
    with pytest.raises(SweepError, match="pooled"):
        load_datasets([f"ngsim:{tmp_path / 'pooled'}"], max_trips=1)


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "captures.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_cli_sweep_writes_rows_with_version_and_params_and_figures(tmp_path):
    data = shared_path("ngsim-i80-pairs")
    out = tmp_path / "rows.json"
    r = _cli("sweep", "--dataset", f"ngsim:{data}", "--max-trips", "2", "--per", "0,50,90",
             "--rate", "10,5", "--predictors", "hold,ca", "--workers", "1", "--json", str(out),
             "--plots", str(tmp_path / "fig"))
    assert r.returncode == 0, r.stderr
    assert "PTE95 [m] against PER" in r.stdout and "ca/hgp" not in r.stdout
    doc = json.loads(out.read_text())
    assert len(doc["rows"]) == 2 * 4
    assert doc["params"]["per"] == [0, 50, 90] and doc["params"]["seeds"] == 1
    assert doc["version"]["catc-hil"] and doc["rows"][0]["version"]
    ds = doc["datasets"]["ngsim-i80-pairs"]
    assert len(ds["trips"]) == 2 and all(len(h) == 64 for h in ds["files"].values())
    keys = {"dataset", "predictor", "per", "rate", "pte95_m", "fcw_accuracy", "n_ticks"}
    assert keys <= set(doc["rows"][0])
    from PIL import Image

    for name in ("ngsim-i80-pairs_h3.png", "ngsim-i80-pairs_exceedance.png"):
        with Image.open(tmp_path / "fig" / name) as im:
            assert im.size[0] > 800 and im.size[1] > 300


@pytest.mark.parametrize("args, message", [
    ([], "--dataset"),
    (["--dataset", "nowhere/at/all"], "no such file"),
    (["--predictors", "magic"], "unknown predictor"),
    (["--per", "100"], "PER"),
    (["--rate", "0"], "rate"),
    (["--live", "fifty"], "PER@RATE"),
])
def test_cli_sweep_bad_flags_fail_in_one_line(args, message):
    data = ["--dataset", f"ngsim:{shared_path('ngsim-i80-pairs')}"] \
        if "--dataset" not in args and args else []
    r = _cli("sweep", *data, *args, "--max-trips", "1", "--workers", "1", timeout=120)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and lines[0].startswith("captures sweep:")


@pytest.mark.slow
def test_live_cells_through_the_daemons_agree_with_the_offline_simulator(tmp_path):
    """rve and obu as separate processes over UDP on 127.0.0.1, then `captures score`,
    against the offline CA-TC on the same trip, cell, seed and predictor: the same
    (tick, RV) pairs, every estimated position equal to 1e-6 m (what the OBU's own
    live-equals-offline test asks), the scores equal to their last decimal."""
    data = shared_path("ngsim-i80-pairs")
    out = tmp_path / "rows.json"
    r = _cli("sweep", "--dataset", f"ngsim:{data}", "--max-trips", "1", "--per", "0,60",
             "--rate", "10", "--predictors", "hgp", "--workers", "1", "--live", "60@10,0@4",
             "--json", str(out))
    assert r.returncode == 0, r.stderr
    live = json.loads(out.read_text())["live"]
    assert [(c["per"], c["rate"]) for c in live] == [(60.0, 10.0), (0.0, 4.0)]
    for c in live:
        tracks = c["agree"]["tracks"]
        assert tracks["compared"] > 100, tracks
        assert tracks["live_only"] == tracks["offline_only"] == 0, tracks
        assert tracks["max_abs_diff_m"] <= 1e-6, tracks
        assert abs(c["agree"]["pte95_m"]) <= 1e-4 and abs(c["agree"]["fcw_accuracy"]) <= 1e-4
        assert c["agree"]["ok"], c
        assert c["live"]["dropped"] > 0 if c["per"] else c["live"]["dropped"] == 0
        assert c["live"]["received"] == c["live"]["sent"]


def test_live_agreement_fails_on_positions_rounded_to_a_centimetre():
    """`agree.ok` is round-off only: track positions 1 cm coarse fail it, though PTE95 and
    the FCW accuracy (rounded to 4 decimals) and the counts agree."""
    from captures.live import agreement, track_differences

    rng = np.random.default_rng(0)
    offline = {(round(0.1 * k, 3), 0x1A2B): (float(x), float(y))
               for k, (x, y) in enumerate(rng.uniform(-200, 200, (50, 2)))}
    scores = {"pte95_m": 0.1234, "fcw_accuracy": 0.98, "sent": 40, "dropped": 10}

    def rows(digits):
        return [{"t": t, "id": f"{tid:08X}", "x": round(x, digits), "y": round(y, digits)}
                for (t, tid), (x, y) in offline.items()]

    exact = track_differences(rows(7), offline)
    assert exact["compared"] == 50 and exact["max_abs_diff_m"] <= 5e-8
    assert agreement(scores, scores, exact)["ok"]
    coarse = track_differences(rows(2), offline)
    assert 1e-3 < coarse["max_abs_diff_m"] <= 5e-3
    assert not agreement(scores, scores, coarse)["ok"]
    assert not agreement(scores, scores, track_differences(rows(7)[1:], offline))["ok"]
    assert not agreement(scores, dict(scores, pte95_m=0.1237), exact)["ok"]


def test_report_from_a_sweep_is_self_contained_and_states_the_verdict(tmp_path):
    data = shared_path("ngsim-i80-pairs")
    rows = tmp_path / "rows.json"
    r = _cli("sweep", "--dataset", f"ngsim:{data}", "--max-trips", "2", "--per", "0,50,90",
             "--rate", "10,5", "--predictors", "ca,kf,hgp", "--fcw-predictors", "hgp",
             "--workers", "1", "--json", str(rows))
    assert r.returncode == 0, r.stderr
    out = tmp_path / "report"
    published = tmp_path / "docs" / "results.md"
    (tmp_path / "docs" / "results").mkdir(parents=True)
    (tmp_path / "docs" / "results" / "stale.png").write_bytes(b"old")
    r = _cli("report", "--sweep", str(rows), "--no-hgp", "--out", str(out), "--results",
             str(published))
    assert r.returncode == 0, r.stderr
    md = (out / "report.md").read_text()
    # published (make report: docs/results.md): the same text, figures in results/ beside it
    assert published.read_text() == md.replace("](figures/", "](results/")
    figures = sorted(f.name for f in (tmp_path / "docs" / "results").iterdir())
    assert figures == sorted(f.name for f in (out / "figures").glob("*.png"))
    doc = json.loads(rows.read_text())
    by = {(x["predictor"], x["per"], x["rate"]): x for x in doc["rows"]}
    # the H3 row as measured, and the paper's peer table next to it
    assert "| kf | 0.000 | " + f"{by['kf', 50.0, 10.0]['pte95_m']:.3f}" in md
    assert "| HGP | 0.000 | 0.047 |" in md
    ratio = by["kf", 90.0, 10.0]["pte95_m"] / by["hgp", 90.0, 10.0]["pte95_m"]
    word = "HGP has the lower PTE95 at" if ratio > 1 else "**it does not** at"
    assert f"×{ratio:.2f}" in md and word in md
    assert "The paper's target at PER 90 %" in md
    for ref in ("figures/ngsim-i80-pairs_h3.png", "figures/ngsim-i80-pairs_exceedance.png"):
        assert f"]({ref})" in md and (out / ref).is_file()
    # issue 17's comparison: HGP over the best of CA and KF here, cell by cell
    for per, limit in ((50.0, 1.0), (90.0, 0.8)):
        best = min(by["ca", per, 10.0]["pte95_m"], by["kf", per, 10.0]["pte95_m"])
        ratio = by["hgp", per, 10.0]["pte95_m"] / best
        assert f"| {per:g} % | {by['hgp', per, 10.0]['pte95_m']:.4f} | {best:.4f} (" in md
        assert f"| {ratio:.4f} | ≤ {limit:g} | {'met' if ratio <= limit else '**not met**'} |" \
            in md
    assert "](figures/hgp_vs_kinematic.png)" in md
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") == 3 and "src='figures" not in page
    assert doc["datasets"]["ngsim-i80-pairs"]["files"]  # provenance carried over
    bad = _cli("report", "--sweep", str(tmp_path / "none.json"), "--out", str(out))
    assert bad.returncode == 2 and bad.stderr.startswith("captures report:")


def _row(predictor, per, rate, pte, fcw=None, dataset="d"):
    return {"dataset": dataset, "predictor": predictor, "per": per, "rate": rate,
            "pte95_m": pte, "fcw_accuracy": fcw}


def test_hgp_targets_compare_with_the_best_kinematic_tracker_cell_by_cell():
    """Hand-made rows: the best kinematic tracker differs by cell, the bound is 1 below
    PER 80 % and 0.8 from there, the rate axis has no bound, FCW is against the better of
    CA and KF (CTRV's and IMM's FCW are not the target's)."""
    from captures.report import hgp_targets

    rows = [
        _row("ca", 0.0, 10.0, 0.0), _row("hgp", 0.0, 10.0, 0.0),
        _row("ca", 30.0, 10.0, 0.030, 0.999), _row("kf", 30.0, 10.0, 0.020, 0.998),
        _row("imm", 30.0, 10.0, 0.025), _row("hgp", 30.0, 10.0, 0.021, 0.9985),
        _row("ca", 90.0, 10.0, 4.0, 0.99), _row("ctrv", 90.0, 10.0, 1.0, 0.5),
        _row("hgp", 90.0, 10.0, 0.79, 0.991), _row("lstm", 90.0, 10.0, 0.1),
        _row("ca", 0.0, 2.0, 0.20), _row("kf", 0.0, 2.0, 0.10), _row("hgp", 0.0, 2.0, 0.09),
        _row("ca", 50.0, 10.0, 0.1, dataset="other"),
    ]
    by = {(e["axis"], e["per"], e["rate"]): e for e in hgp_targets(rows, "d")}
    assert list(by) == [("per", 30.0, 10.0), ("per", 90.0, 10.0), ("rate", 0.0, 2.0)]
    e = by["per", 30.0, 10.0]
    assert (e["best_name"], e["best"], e["limit"], e["met"]) == ("kf", 0.020, 1.0, False)
    assert e["ratio"] == pytest.approx(1.05)
    assert (e["fcw_peer_name"], e["fcw_peer"], e["fcw_met"]) == ("ca", 0.999, False)
    e = by["per", 90.0, 10.0]  # CTRV is the best kinematic one; the LSTM is not kinematic
    assert (e["best_name"], e["limit"], e["met"]) == ("ctrv", 0.8, True)
    assert (e["fcw_peer_name"], e["fcw_met"]) == ("ca", True)
    e = by["rate", 0.0, 2.0]
    assert (e["best_name"], e["limit"], e["met"], e["fcw_met"]) == ("kf", None, None, None)
    assert e["ratio"] == pytest.approx(0.9)
    assert hgp_targets(rows, "other") == []  # no HGP row there
    assert hgp_targets(rows, "absent") == []


def test_the_vehicle_ahead_is_found_by_where_it_drives(ngsim):
    """A sweep scores the FCW on the host and the vehicle ahead.  Two-vehicle trips list
    the leader first; a SUMO scenario lists the host first and a scene by id, so the
    vehicle ahead is the one most often nearest ahead in the host's lane."""
    for t in ngsim[:20]:
        names = list(t.tracks)
        assert vehicle_ahead(t, t.default_host) == names[names.index(t.default_host) - 1]
    default = load_table("scenario:highway-braking", None)
    assert next(iter(default.tracks)) == default.default_host
    assert vehicle_ahead(default, default.default_host) == "lead"
    assert set(fcw_scene(default).tracks) == {"lead", default.default_host}
    (scene,) = load(f"scene:ngsim:{shared_path('ngsim-i80-pairs')}")
    assert vehicle_ahead(scene, scene.default_host) == "216"  # the truck ahead of 232
