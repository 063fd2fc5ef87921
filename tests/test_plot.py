"""``captures plot`` on a real capture: ``obu run`` and ``rve run`` as separate processes over
UDP on 127.0.0.1 (the helpers of tests/test_obu.py), 25 s of the default scenario, whose
leader brakes at 20 s, so there is an FCW."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image

from captures import plot
from captures.score import score
from hil.capture import read_lines, schema
from hil.cliargs import dispatch, make_parser
from hil.transport.udp import free_ports
from tests.test_cli import read_only_dir
from tests.test_obu import finish, rve, start_obu


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    cap = tmp_path_factory.mktemp("capture")
    ports = free_ports()
    obu = start_obu(cap, ports, "--predictor", "hgp")
    rve(ports, "--per", "30", "--seed", "2", "--speed", "4", "--duration", "25",
        "--capture", str(cap))
    finish(obu)
    return cap


def cli(*argv) -> int:
    """``captures plot ...`` through this module's own register (the CLI's parser)."""
    parser, sub = make_parser("captures", "test")
    plot.register(sub)
    return dispatch(parser, ["plot", *map(str, argv)])


def fcw_starts(cap) -> list[float]:
    events = read_lines(cap / schema.OBU_EVENTS)
    return [e["t"] for e in events if e["app"] == "fcw" and e["kind"] == "start"]


def test_plot_writes_the_pictures_and_the_gif(capture, tmp_path, capsys):
    out = tmp_path / "plots"
    assert cli(capture, "--out", out, "--gif", "--max-frames", "40") == 0
    printed = [Path(p) for p in capsys.readouterr().out.splitlines()]
    assert printed and all(p.parent == out and p.is_file() for p in printed)
    names = {p.name for p in printed}
    assert {"timeline.png", "run.gif"} <= names
    fcw = fcw_starts(capture)
    assert fcw and 19.9 <= fcw[0] <= 21.5, fcw  # the leader brakes at 20 s
    assert f"birdseye_t{fcw[0]:.1f}.png" in names  # chosen automatically
    for name in names - {"run.gif"}:
        with Image.open(out / name) as im:
            im.verify()
        with Image.open(out / name) as im:
            assert im.format == "PNG" and im.width >= 1000 and im.height >= 700, im.size
    with Image.open(out / "run.gif") as gif:
        assert gif.format == "GIF" and gif.size == (640, 448)
        assert 20 <= gif.n_frames <= 40  # 250 ticks, at most 40 frames
        gif.seek(gif.n_frames - 1)  # every frame decodes


def test_at_times_snap_to_ticks(capture, tmp_path, capsys):
    assert cli(capture, "--out", tmp_path, "--at", "3.04,12") == 0
    printed = capsys.readouterr().out.splitlines()
    assert [Path(p).name for p in printed] == ["birdseye_t3.0.png",
                                                      "birdseye_t12.0.png", "timeline.png"]


def test_timeline_pte_is_the_scores(capture):
    run = plot.load_run(capture)
    fig = Figure()
    FigureCanvasAgg(fig)
    drawn = plot.timeline(fig, run)
    pooled = np.concatenate([pte for _, pte in drawn.values()])
    s = score(capture)
    assert abs(np.percentile(pooled, 95) - s["pte95_m"]) <= 1e-3
    assert len(pooled) == len(run.pte_samples())
    per_rv = {run.name(tid): float(np.percentile(pte, 95)) for tid, (_, pte) in drawn.items()}
    assert per_rv.keys() == s["pte95_per_rv"].keys()
    for name, value in per_rv.items():
        assert abs(value - s["pte95_per_rv"][name]) <= 1e-3, name


def test_birdseye_at_the_fcw_start_shows_the_warning(capture):
    run = plot.load_run(capture)
    fcw = fcw_starts(capture)[0]
    assert round(fcw, 3) in [round(t, 3) for t in plot.auto_times(run)]
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    i = plot.birdseye(ax, run, fcw)
    assert abs(run.tick_t[i] - fcw) < 1e-6
    assert any(w[0] == "fcw" for w in run.tick_warnings[i])
    texts = [t.get_text() for t in ax.texts]
    assert any(t.startswith("FCW") and "lead" in t for t in texts), texts
    assert any(t.startswith(f"t = {fcw:.1f} s") for t in [ax.get_title()])
    # every RV in view carries its zone and whether its estimate is fresh or predicted
    assert any("ahead, same lane" in t and ("fresh BSM" in t or "predicted" in t)
               for t in texts), texts


def test_missing_rvs_are_marked(capture):
    """At the first tick, RVs whose first BSM was lost are in the truth, not in the map."""
    run = plot.load_run(capture)
    t0 = float(run.tick_t[0])
    first = [run.tracks["id"][r] for r in range(run.tick_rows[0], run.tick_rows[1])]
    absent = [tid for tid in run.rv_ids()
              if tid not in first and run.truth[tid].at(t0) is not None]
    assert absent  # PER 30 %: some of the 13 first BSMs were lost
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    plot.birdseye(ax, run, t0, window=2000.0)  # everyone in view
    texts = [t.get_text() for t in ax.texts]
    for tid in absent:
        assert f"{run.name(tid)} missing" in texts, (run.name(tid), texts)


@pytest.mark.parametrize(("argv", "needle"), [
    (["--at", "abc"], "not a time"),
    (["--at", "400"], "no OBU tick"),
    (["--max-frames", "1"], "--max-frames"),
    (["--window", "0"], "--window"),
    (["--fps", "-2", "--gif"], "--fps"),
])
def test_bad_flags_are_one_line_and_exit_2(capture, tmp_path, capsys, argv, needle):
    assert cli(capture, "--out", tmp_path, *argv) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("captures plot: ") and needle in lines[0]
    assert out == "" and not any(tmp_path.iterdir())


def test_bad_directories_are_one_line_and_exit_2(capture, tmp_path, capsys, monkeypatch):
    rve_only = tmp_path / "rve-only"
    rve_only.mkdir()
    for name in (schema.RVE_CONFIG, schema.RVE_TRUTH, schema.RVE_SCHEDULE, schema.RVE_PCAPNG):
        shutil.copy(capture / name, rve_only / name)
    cases = [(tmp_path / "nope", "not a directory"), (rve_only, f"{schema.OBU_CONFIG}: missing")]
    for directory, needle in cases:
        assert cli(directory) == 2
        out, err = capsys.readouterr()
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("captures plot: ") \
            and needle in lines[0], lines
        assert out == ""
    assert not (rve_only / "plots").exists()
    monkeypatch.setenv("PATH", "")  # no ffmpeg
    assert cli(capture, "--mp4", "--out", tmp_path / "x") == 2
    assert "ffmpeg" in capsys.readouterr().err


def test_an_out_that_cannot_be_written_is_one_line_and_exit_1(capture, tmp_path, capsys):
    """Issue 27: --out in a directory nobody may write to ended in a traceback (the others
    in a line that said exit 2, bad usage, for what is a failed write)."""
    regular = tmp_path / "file"
    regular.write_text("")
    for out in (read_only_dir(tmp_path), regular / "sub", Path("/proc/x.png")):
        assert cli(capture, "--out", out) == 1
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"captures plot: {out}"), err
        assert "Traceback" not in err


def test_gif_is_the_same_drawn_by_one_or_two_processes(capture, tmp_path):
    run = plot.load_run(capture)
    n = [plot.animate(run, tmp_path / f"{w}.gif", max_frames=20, workers=w) for w in (1, 2)]
    assert n[0] == n[1] <= 20
    assert (tmp_path / "1.gif").read_bytes() == (tmp_path / "2.gif").read_bytes()
