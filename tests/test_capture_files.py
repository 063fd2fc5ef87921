"""The capture files of issue 27: compact tracks (``obu.tracks.bin``) equal to the JSON rows
they replace, ``obu.rx.jsonl.gz``, torn tails read up to where they end (hand-made files
cut at every offset, and a real run's files cut at arbitrary ones, through ``captures
decode`` and ``captures score``), the size cap's segments, and scores that count the run
(received <= sent, latency from the RVE's own frames) on a hand-made capture.

The hand-made capture (:func:`make_capture`) is the offline simulator's run of the
built-in scenario written through the capture writers and the schema's builders, as the
two daemons would write it, plus whatever extra frames a test puts at the RV port."""

from __future__ import annotations

import argparse
import dataclasses
import json
import random
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from catc.bsm import BSM, msg_cnt, sec_mark
from catc.cam import CamConfig, ContextAwareMap
from catc.channel import CAUSES, ChannelConfig
from catc.replay import plan, simulate, temp_id
from hil.capture import (
    GzipJsonLines,
    JsonLines,
    TrackWriter,
    block_rows,
    iter_blocks,
    iter_lines,
    read_capture,
    read_rx,
    read_tracks,
    schema,
)
from hil.datasets import load_table
from obu.capture import ObuCapture

PY = sys.executable
T0 = 1_800_000_000.0  # the run's wall clock at dataset time 0
LATENCY_S = 0.010  # every real message is decided 10 ms after it was sent


def _snapshots(duration: float, per: float = 0.0, seed: int = 0):
    table = load_table("scenario:highway-braking", None)
    the_plan = plan(table, ChannelConfig(per=per), seed, None, duration)
    cam = ContextAwareMap(CamConfig(predictor="ca"))
    return table, the_plan, cam, list(simulate(the_plan, cam))


def write_rve_start(directory: Path, table, the_plan, duration: float, channel: dict,
                    **settings) -> tuple[dict, dict[str, int]]:
    """The RVE's config and truth of a run of ``the_plan`` over ``table``'s first
    ``duration`` s, started at ``T0`` (``settings``: more of its flags): the config and
    each vehicle's TemporaryID."""
    ids = {v: temp_id(v) for v in the_plan.vehicles}
    config = schema.rve_config(
        {"dataset": "scenario:highway-braking", "duration": duration, **settings}, {},
        (table.name, table.kind, table.origin), the_plan.host_id, ids, channel, 0, T0,
        schema.new_run_id())
    (directory / schema.RVE_CONFIG).write_text(json.dumps(config, default=str))
    truth = JsonLines(directory / schema.RVE_TRUTH)
    for v in the_plan.vehicles:
        tr = table.tracks[v]
        for i in np.flatnonzero(tr.t <= duration + 1e-9):
            truth.write(schema.truth(v, ids[v], int(i), float(tr.t[i]), float(tr.lat[i]),
                                     float(tr.lon[i]), float(tr.x[i]), float(tr.y[i]),
                                     float(tr.speed[i]), float(tr.heading[i]),
                                     float(tr.accel[i]), float(tr.yaw_rate[i]),
                                     v == the_plan.host_id))
    truth.close()
    return config, ids


def make_capture(directory: Path, duration: float = 3.0, *, extra_rx=(), legacy: bool = False,
                 cap_mb: float | None = None) -> dict:
    """A capture directory of the built-in scenario's first ``duration`` s (every message
    delivered, decided 10 ms after it was sent), the OBU's files written by
    :class:`obu.capture.ObuCapture` (``legacy``: as JSON lines under the names of before
    2026-11-27); ``extra_rx`` are more ``obu.rx`` records (frames of a flood).  Returns
    what it wrote: ``sent`` (the RVE's RV messages), ``snaps``."""
    directory.mkdir(parents=True, exist_ok=True)
    table, the_plan, cam, snaps = _snapshots(duration)
    config, ids = write_rve_start(directory, table, the_plan, duration,
                                  dataclasses.asdict(the_plan.config))
    sched = JsonLines(directory / schema.RVE_SCHEDULE)
    sent = []
    for ev in the_plan.events:
        v = the_plan.vehicles[int(ev["vehicle"])]
        host = bool(ev["host"])
        rec = schema.scheduled(v, ids[v], "host" if host else "rv", int(ev["index"]),
                               int(ev["seq"]), float(ev["t"]), bool(ev["dropped"]),
                               CAUSES[int(ev["cause"])], None if ev["dropped"] else 0.0)
        if not ev["dropped"]:
            schema.sent(rec, T0 + float(ev["t"]), 0.0, 40)
            if not host:
                sent.append(rec)
        sched.write(rec)
    sched.close()
    end = schema.end(config["run_id"], "clean", "replayed", T0, T0 + duration)
    (directory / schema.RVE_END).write_text(json.dumps(end))

    args = argparse.Namespace(mbd=False, overwrite=False, capture_max_mb=cap_mb,
                              predictor="ca")
    obu = ObuCapture(directory, args)
    if legacy:  # the files of before: JSON lines, plain
        obu.close()
        for name in (schema.OBU_RX, schema.OBU_TRACKS):
            (directory / name).unlink()
        obu.rx = JsonLines(directory / schema.LEGACY[schema.OBU_RX])
        obu.tracks = JsonLines(directory / schema.LEGACY[schema.OBU_TRACKS])
        obu.ticks = JsonLines(directory / schema.OBU_TICKS)
        obu.events = JsonLines(directory / schema.OBU_EVENTS)
    f = cam.frame
    obu.write_origin([f.lat0, f.lon0, f.h0])
    pending = sorted(sent, key=lambda r: r["t"])
    extra = sorted(extra_rx, key=lambda r: r["rx_unix"])
    for snap in snaps:
        decided = T0 + snap.t + LATENCY_S
        for r in [r for r in extra if r["rx_unix"] <= decided]:
            obu.rx.write(r)
        extra = [r for r in extra if r["rx_unix"] > decided]
        due = [r for r in pending if r["t"] <= snap.t + 1e-9]
        pending = pending[len(due):]
        hsm = sec_mark(snap.t)
        for r in due:
            obu.rx.write(schema.received(
                r["sent_unix"], "rv", bytes(40), "ok",
                sender=(int(r["id"], 16), msg_cnt(r["seq"]), sec_mark(r["t"])), tick=snap.t,
                decided_unix=r["sent_unix"] + LATENCY_S))
        if legacy:
            obu.ticks.write(schema.tick(snap, hsm, 1.0, decided))
            for row in schema.track_rows(snap, hsm):
                obu.tracks.write(row)
        else:
            obu.tick(snap, hsm, 1.0, decided, [])
    for r in extra:
        obu.rx.write(r)
    obu.close()
    obu.write_end("clean", "idle", ticks=len(snaps))
    return {"sent": sent, "snaps": snaps, "ids": ids}


def flood_records(sent: list[dict], ids: dict[str, int], seed: int = 5) -> tuple[list, dict]:
    """What a flood at the RV port leaves in ``obu.rx``: copies of real messages seconds
    later, copies with their msgCnt flipped, frames of ids no vehicle sent, garbage and
    rejected frames.  Returns the records and how many of each."""
    rng = random.Random(seed)
    out = []
    real = set(ids.values())
    counts = {"duplicate": 30, "unmatched": 20, "phantom": 25, "garbage": 10, "rejected": 5}
    for r in rng.sample(sent, counts["duplicate"]):  # replayed 4 s later, whole
        out.append(schema.received(
            r["sent_unix"] + 4.0, "rv", bytes(40), "ok",
            sender=(int(r["id"], 16), msg_cnt(r["seq"]), sec_mark(r["t"])),
            tick=r["t"] + 4.0, decided_unix=r["sent_unix"] + 4.0))
    for r in rng.sample(sent, counts["unmatched"]):  # a bit of its msgCnt flipped
        out.append(schema.received(
            r["sent_unix"] + 4.0, "rv", bytes(40), "ok",
            sender=(int(r["id"], 16), msg_cnt(r["seq"]) ^ 64, sec_mark(r["t"])),
            tick=r["t"] + 4.0, decided_unix=r["sent_unix"] + 4.0))
    for k in range(counts["phantom"]):
        tid = rng.getrandbits(32)
        assert tid not in real
        out.append(schema.received(T0 + 0.1 * k, "rv", bytes(40), "ok",
                                   sender=(tid, 1, 1000), tick=0.1 * k,
                                   decided_unix=T0 + 0.1 * k + 0.01))
    for k in range(counts["garbage"]):
        out.append(schema.received(T0 + 0.05 * k, "rv", rng.randbytes(30), "garbage"))
    for r in rng.sample(sent, counts["rejected"]):
        out.append(schema.received(
            r["sent_unix"] + 0.001, "rv", bytes(40), "rejected",
            sender=(int(r["id"], 16), msg_cnt(r["seq"]) ^ 1, sec_mark(r["t"])),
            verdict="bad-signature"))
    return out, counts


# --- compact tracks ---------------------------------------------------------------------

def test_compact_tracks_are_the_json_rows_and_the_estimates_to_1e_6_m(tmp_path):
    """obu.tracks.bin read back gives exactly the rows schema.track_rows made (the JSON
    lines of before), and the map's positions to 1e-6 m, at a fraction of their size."""
    _, _, _, snaps = _snapshots(30.0, per=0.4, seed=3)
    w = TrackWriter(tmp_path / schema.OBU_TRACKS)
    for snap in snaps:
        w.write(snap.t, sec_mark(snap.t), schema.track_columns(snap))
    w.close()
    blocks = list(iter_blocks(tmp_path / schema.OBU_TRACKS))
    with_rows = [s for s in snaps if len(s)]
    assert len(blocks) == len(with_rows) > 250
    json_bytes = rows = 0
    for snap, block in zip(with_rows, blocks, strict=True):
        expected = schema.track_rows(snap, sec_mark(snap.t))
        assert block_rows(block) == expected
        assert np.abs(block.cols["x"] - snap.x).max() <= 1e-6
        assert np.abs(block.cols["predicted_y"] - snap.pred_y).max() <= 1e-6
        json_bytes += sum(len(json.dumps(r, separators=(",", ":"))) + 1 for r in expected)
        rows += len(expected)
    size = (tmp_path / schema.OBU_TRACKS).stat().st_size
    assert size < json_bytes / 10, (size / rows, json_bytes / rows)


def test_a_table_of_predicted_ghosts_takes_a_few_octets_a_row(tmp_path):
    """1,000 tracks moved by a constant-velocity prediction (a storm that fills the
    table): residuals of zero but for rounding, under 8 octets a row, values exact."""
    rng = np.random.default_rng(1)
    n = 1000
    ids = rng.choice(2**32, n, replace=False)
    x0, y0 = rng.uniform(-400, 400, n), rng.uniform(-400, 400, n)
    vx, vy = rng.uniform(-25, 25, n), rng.uniform(-25, 25, n)
    w = TrackWriter(tmp_path / "t.bin")
    written = []
    for k in range(50):
        t = 10.0 + 0.1 * k
        cols = {"id": ids, "x": x0 + vx * 0.1 * k, "y": y0 + vy * 0.1 * k,
                "speed": np.hypot(vx, vy), "heading": np.degrees(np.arctan2(vx, vy)) % 360,
                "source": ("ca",) * n, "age": np.full(n, 0.1 * k), "fresh": np.zeros(n, bool),
                "lane": rng.integers(-3, 4, n) * 0 + 2, "ahead": x0 > 0,
                "lateral": np.full(n, 4), "direction": np.full(n, 2), "s": x0 + 2.5 * k,
                "d": y0 - 0.01 * k, "predicted_x": x0 + vx * (0.1 * k + 2),
                "predicted_y": y0 + vy * (0.1 * k + 2), "p_ahead": x0 > 0,
                "p_lateral": np.full(n, 4), "p_direction": np.full(n, 2)}
        if k == 20:
            cols["x"] = cols["x"].copy()
            cols["x"][7] = np.nan  # a non-finite estimate survives as NaN
        w.write(t, int(t * 1000) % 60000, cols)
        written.append(cols)
    w.close()
    assert (tmp_path / "t.bin").stat().st_size / (50 * n) < 8
    for cols, block in zip(written, iter_blocks(tmp_path / "t.bin"), strict=True):
        assert (block.cols["id"] == ids).all()
        np.testing.assert_array_equal(block.cols["x"], np.round(cols["x"], 7))
        np.testing.assert_array_equal(block.cols["s"], np.round(cols["s"], 3))


# --- torn tails -------------------------------------------------------------------------

def _records(k: int) -> list[dict]:
    return [{"k": k, "i": i, "hex": f"{k * 1000 + i:08x}" * 5} for i in range(7)]


@pytest.mark.parametrize("gz", [False, True])
def test_json_lines_cut_anywhere_read_up_to_the_cut(tmp_path, gz):
    """A JSON-lines file, plain or gzip (flushed per tick), cut at every offset, reads as
    the records before the cut, in order, and says where its whole part ends."""
    path = tmp_path / ("f.jsonl.gz" if gz else "f.jsonl")
    w = GzipJsonLines(path) if gz else JsonLines(path)
    written, flushes = [], [0]
    for k in range(6):
        for r in _records(k):
            w.write(r)
            written.append(r)
        w.flush()
        flushes.append(path.stat().st_size)
    data = path.read_bytes()  # gz: unterminated, as a killed OBU leaves it
    cut = tmp_path / path.name.replace("f.", "cut.")
    for off in range(len(data) + 1):
        cut.write_bytes(data[:off])
        torn: list[int] = []
        got = list(iter_lines(cut, lambda p, o, why, torn=torn: torn.append(o)))
        assert got == written[:len(got)], off
        start = data[:off].rfind(b"\n") + 1  # of the last line, maybe cut
        rest = data[start:off]
        whole = off in flushes if gz else not rest or data[off:off + 1] == b"\n"
        if whole:
            assert not torn, off
        else:
            assert len(torn) == 1 and torn[0] <= off, (off, torn)
        if gz:  # at least every record flushed before the cut
            assert len(got) >= 7 * sum(1 for f in flushes[1:] if f <= off), off
        else:  # every whole line (the last one may lack its end); a torn one's offset
            assert len(got) == data[:off].count(b"\n") + bool(rest and whole), off
            if torn:
                assert torn[0] == start, off
    w.close()
    assert [r for r in iter_lines(path)] == written


def test_tracks_cut_anywhere_read_the_whole_blocks(tmp_path):
    _, _, _, snaps = _snapshots(5.0, per=0.3, seed=1)
    path = tmp_path / schema.OBU_TRACKS
    w = TrackWriter(path)
    ends = []
    for snap in snaps:
        w.write(snap.t, sec_mark(snap.t), schema.track_columns(snap))
        w.flush()
        if len(snap):
            ends.append(path.stat().st_size)
    w.close()
    data = path.read_bytes()
    whole = list(iter_blocks(path))
    assert len(whole) == len(ends) > 30
    starts = [8, *ends[:-1]]  # after the 8-octet magic, each block after the one before
    for off in sorted(random.Random(2).sample(range(len(data)), 300)):
        cut = tmp_path / "cut.bin"
        cut.write_bytes(data[:off])
        torn: list[int] = []
        got = list(iter_blocks(cut, lambda p, o, why, torn=torn: torn.append(o)))
        n = sum(1 for e in ends if e <= off)
        assert len(got) == n and all(block_rows(a) == block_rows(b)
                                     for a, b in zip(got, whole, strict=False)), off
        if off < 8:
            assert torn == [0], off
        elif off == 8 or off in ends:
            assert torn == [], off
        else:
            assert torn == [starts[n]], off


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """A real run: obu run and rve run as processes over UDP (as tests/test_obu.py)."""
    from hil.transport.udp import free_ports
    from tests.test_obu import finish, rve, start_obu

    cap = tmp_path_factory.mktemp("live")
    ports = free_ports()
    obu = start_obu(cap, ports, "--predictor", "ca")
    rve(ports, "--per", "30", "--seed", "3", "--speed", "8", "--duration", "20", "--capture",
        str(cap))
    finish(obu)
    return cap


def _decode(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-m", "captures.cli", "decode", str(path)], capture_output=True,
                          text=True, timeout=120)


@pytest.mark.parametrize("name", [schema.RVE_PCAPNG, schema.OBU_RX])
def test_decode_of_a_real_capture_cut_anywhere_gives_every_whole_frame(live, tmp_path, name):
    """Issue 27: `captures decode` of a pcapng or obu.rx cut at the end (a kill, a full
    disk) gave nothing.  Now: every frame before the cut, and one line on stderr with
    the file and the byte offset where the whole part ends."""
    full = _decode(live / name)
    assert full.returncode == 0, full.stderr
    frames = full.stdout.splitlines()
    data = (live / name).read_bytes()
    for off in random.Random(name).sample(range(len(data) // 4, len(data) - 1), 4):
        cut = tmp_path / name
        cut.write_bytes(data[:off])
        out = _decode(cut)
        got = out.stdout.splitlines()
        assert got == frames[:len(got)] and len(got) > len(frames) // 5, off
        if out.stderr:
            (line,) = out.stderr.splitlines()
            assert line.startswith(f"captures decode: {cut}: torn at byte ") and out.returncode == 1
            assert int(line.split("torn at byte ")[1].split()[0]) <= off


@pytest.mark.parametrize("name", [schema.OBU_TRACKS, schema.OBU_RX, schema.OBU_TICKS])
def test_score_of_a_real_capture_cut_anywhere_scores_what_is_whole(live, tmp_path, name):
    """A capture whose OBU file ends torn scores what is whole: the figures of the ticks
    before the cut, the torn file and its offset in the JSON and on stderr (one line),
    exit 3 for the ticks missing (0 with --partial)."""
    import shutil

    data = (live / name).read_bytes()
    for off in random.Random(name).sample(range(len(data) // 3, len(data) - 1), 2):
        cap = tmp_path / f"cut{off}"
        shutil.copytree(live, cap)
        (cap / name).write_bytes(data[:off])
        out = subprocess.run([PY, "-m", "captures.cli", "score", str(cap), "--json",
                              "--partial"], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        s = json.loads(out.stdout)
        torn = s["capture"]["torn"]
        if not torn:  # cut where a tick's flush ended: nothing torn
            assert not out.stderr
            continue
        assert [t["file"] for t in torn] == [name] and torn[0]["offset"] <= off
        (line,) = out.stderr.splitlines()
        assert line.startswith("captures score: read up to a torn tail") and name in line
        assert s["ticks"] > 10 and s["pte95_m"] is not None


# --- the cap ----------------------------------------------------------------------------

def test_a_capped_capture_keeps_its_start_and_latest_segments(tmp_path):
    """obu run --capture-max-mb: segments of a tenth of the cap; over it, the oldest but
    the first are deleted.  The reader reads what is left in order; the score names the
    deleted segments and counts their ticks as missing."""
    cap = tmp_path / "cap"
    made = make_capture(cap, 50.0, cap_mb=0.1)
    obu_bytes = sum(p.stat().st_size for p in cap.glob("obu.*"))
    assert obu_bytes <= 0.1e6 + 3000, obu_bytes  # the cap, and at most a tick's records
    c = read_capture(cap)
    kept, missing = c.segments(), c.missing_segments()
    assert kept[0] == 0 and missing and set(kept).isdisjoint(missing)
    assert kept == sorted(kept) and max(kept) == len(kept) + len(missing) - 1
    ticks = [tk["t"] for tk in c.iter_ticks()]
    assert ticks == sorted(ticks) and ticks[0] == made["snaps"][0].t
    assert ticks[-1] == made["snaps"][-1].t and len(ticks) < len(made["snaps"])
    rows = read_tracks(cap)
    assert {round(r["t"], 3) for r in rows} <= {round(t, 3) for t in ticks}
    end = json.loads((cap / schema.OBU_END).read_text())
    assert end["capture_segments"] == max(kept) + 1
    assert end["capture_segments_deleted"] == len(missing)
    out = subprocess.run([PY, "-m", "captures.cli", "score", str(cap)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 3, out.stderr
    assert f"{len(missing)} deleted by the cap" in out.stdout


# --- counts that count the run ----------------------------------------------------------

@pytest.mark.parametrize("legacy", [True, False])
def test_received_counts_only_the_rves_own_messages(tmp_path, legacy):
    """Issue 27: under a flood at the RV port the score said "received 18,860 > sent
    11,075" and latency p50 1,332 ms.  received now counts the RVE's own RV messages the
    OBU took, once each; copies, frames of ids no vehicle sent, garbage and rejected
    frames are counted apart; the latency is of the real frames only."""
    from captures.score import score

    made = make_capture(tmp_path / "clean", legacy=legacy)
    clean = score(tmp_path / "clean")
    extra, n = flood_records(made["sent"], made["ids"])
    make_capture(tmp_path / "flood", extra_rx=extra, legacy=legacy)
    s = score(tmp_path / "flood")
    assert s["sent"] == len(made["sent"]) == s["received"] == clean["received"]
    assert s["frames"]["duplicate"] == n["duplicate"]
    assert s["frames"]["unmatched"] == n["unmatched"]
    assert s["phantom_received"] == s["frames"]["phantom"] == n["phantom"]
    assert sum(s["decode_errors"].values()) == n["garbage"]
    assert s["rejected"] == n["rejected"] and s["security"] == {"bad-signature": 5}
    assert s["latency_ms"] == clean["latency_ms"]
    assert s["latency_ms"]["max"] == pytest.approx(1000 * LATENCY_S, abs=1e-3)
    rv_frames = sum(1 for r in read_rx(tmp_path / "flood") if r["channel"] == "rv")
    f = s["frames"]
    apart = ("garbage", "host_errors", "host_refused")
    assert rv_frames == sum(v for k, v in f.items() if k not in apart) \
        + sum(f["garbage"].values())
    for key in ("pte95_m", "pte95_per_rv", "fcw", "apps", "ticks"):
        assert s[key] == clean[key], key


def test_a_flood_at_the_rv_port_leaves_received_and_latency_to_the_real_frames(tmp_path):
    """A real run under `rve flood` at the RV port (bit-flipped and cut copies of the
    run's frames 1 s of data after them, random octets), at a pace the OBU keeps up with:
    received is the clean run's, <= sent, the copies are counted apart, and the latency
    p50 is the clean run's, not the copies' (the score before took the last copy's)."""
    from hil.transport.udp import free_ports
    from tests.test_obu import finish, rve, score, start_obu

    run = ("--per", "20", "--seed", "5", "--speed", "2", "--duration", "14")
    out = {}
    for name in ("clean", "flood"):
        cap = tmp_path / name
        ports = free_ports()
        obu = start_obu(cap, ports, "--predictor", "ca")
        flooder = None
        if name == "flood":
            flooder = subprocess.Popen(
                [PY, "-m", "rve.cli", "flood", "--to", f"127.0.0.1:{ports[0]}", "--rate",
                 "1000", "--duration", "7.5", "--per", "20", "--seed", "5", "--speed", "2",
                 "--lag", "1", "--mix", "copy=3,random=1"], stdout=subprocess.PIPE, text=True)
        rve(ports, *run, "--capture", str(cap))
        if flooder is not None:
            assert flooder.wait(60) == 0
        finish(obu)
        out[name] = score(cap)
    clean, flood = out["clean"], out["flood"]
    assert flood["received"] == clean["received"] == clean["sent"] == flood["sent"] > 0
    f = flood["frames"]
    assert f["duplicate"] > 100 and f["duplicate"] + f["unmatched"] + f["phantom"] > 200, f
    p50, clean_p50 = flood["latency_ms"]["p50"], clean["latency_ms"]["p50"]
    assert p50 <= max(3 * clean_p50, clean_p50 + 30.0), (p50, clean_p50)


def test_the_score_of_compact_files_is_the_score_of_the_json_lines(tmp_path):
    from captures.score import score

    make_capture(tmp_path / "json", 20.0, legacy=True)
    make_capture(tmp_path / "compact", 20.0)
    a, b = score(tmp_path / "json"), score(tmp_path / "compact")
    assert a["pte95_m"] is not None and a["ticks"] == 201  # 0 to 20 s
    for key in ("pte95_m", "pte_mean_m", "pte95_per_rv", "fcw", "apps", "sent", "received",
                "latency_ms", "phantom", "run"):
        assert a[key] == b[key], key
    assert read_tracks(tmp_path / "json") == read_tracks(tmp_path / "compact")
    rx_a, rx_b = read_rx(tmp_path / "json"), read_rx(tmp_path / "compact")
    assert rx_a == rx_b and len(rx_a) == a["sent"]
    gz = (tmp_path / "compact" / schema.OBU_RX).read_bytes()
    assert zlib.decompress(gz, 31).decode().splitlines()[0] == json.dumps(
        rx_b[0], separators=(",", ":"))  # zcat reads it


def test_obu_capture_files_per_tick_are_flushed_and_whole(tmp_path):
    """ObuCapture flushes every file at each tick: a reader during the run (a running
    OBU's gzip stream has no end yet) reads every tick so far, nothing torn."""
    _, _, cam, snaps = _snapshots(3.0)
    obu = ObuCapture(tmp_path, argparse.Namespace(mbd=False, overwrite=False))
    obu.write_origin([cam.frame.lat0, cam.frame.lon0, cam.frame.h0])
    for k, snap in enumerate(snaps):
        m = BSM(msg_cnt=k % 128, temp_id=0x1234, sec_mark=sec_mark(snap.t), lat=46.9,
                lon=16.8, speed=10.0, heading=0.0)
        obu.tick(snap, sec_mark(snap.t), 1.0, T0 + snap.t,
                 [(m, T0 + snap.t, b"\0" * 9, None, None)])
        torn: list[tuple] = []
        rx = list(iter_lines(tmp_path / schema.OBU_RX, lambda *a, torn=torn: torn.append(a)))
        assert len(rx) == k + 1 and not torn
        assert len(list(iter_blocks(tmp_path / schema.OBU_TRACKS))) == \
            sum(1 for s in snaps[:k + 1] if len(s))
    obu.close()


def test_captures_tracks_prints_the_json_lines_of_before(tmp_path):
    make_capture(tmp_path / "json", 4.0, legacy=True)
    make_capture(tmp_path / "compact", 4.0)
    out = [subprocess.run([PY, "-m", "captures.cli", "tracks", str(tmp_path / d)],
                          capture_output=True, text=True, timeout=60) for d in ("json", "compact")]
    assert out[0].returncode == out[1].returncode == 0, out[1].stderr
    assert out[0].stdout == (tmp_path / "json" / "obu.tracks.jsonl").read_text()
    rows = [[json.loads(line) for line in o.stdout.splitlines()] for o in out]
    assert rows[1] == rows[0] and len(rows[0]) > 500  # -0.0 of the JSON reads 0.0 now
    csv = subprocess.run([PY, "-m", "captures.cli", "tracks", str(tmp_path / "compact"), "--csv",
                          "--id", json.loads(out[1].stdout.splitlines()[0])["id"]],
                         capture_output=True, text=True, timeout=60).stdout.splitlines()
    assert csv[0].startswith("t,sec_mark,id,x,y,") and len(csv) > 30


def test_the_clock_offset_is_the_one_most_first_ticks_agree_on():
    """An OBU reading its own car ticks from its first GNSS fix, which can come before
    the replay's first host sample: on a trip of a minute, that first tick's secMark
    names the sample a minute later.  The offset is the one most first ticks agree on."""
    from catc.bsm import sec_mark
    from hil.capture.reader import CaptureError, clock_offset

    truth = [{"host": True, "t": round(48.4 + 0.1 * k, 1)} for k in range(600)]
    ticks = [{"t": round(48.3 + 0.1 * k, 1), "sec_mark": sec_mark(48.3 + 0.1 * k)}
             for k in range(60)]
    assert clock_offset(truth, ticks, Path(".")) == 0.0
    assert clock_offset(truth, ticks[0], Path(".")) == -60.0  # one tick alone: fooled
    with pytest.raises(CaptureError, match="matches no host sample"):
        clock_offset(truth, [{"t": 1.05, "sec_mark": 1050}], Path("."))
