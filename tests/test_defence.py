"""``captures defence`` (issue 28 part 4, "the score measures the defence"): an attacked
run against its clean twin.  The score reported a replay of the leader as detection
recall 1.0 and precision 1.0, because the id it quarantined was the one the attack named,
the honest victim's; and it did not count the warnings the attack suppressed.

* The OBU's rx record says why misbehavior detection dropped a frame (its sender's
  quarantine, a copy, a stale frame, an id conflict), so a capture tells a quarantined
  vehicle from a dropped copy.
* A hand-made pair of captures (the offline simulator's run of the built-in scenario
  written through the capture writers, as in ``tests/test_capture_files.py``): the
  attacked run lost the FCW on the leader and quarantined the leader.
* Live, ``attack_checks`` with a replay of the leader against ``enforce+mbd`` (the
  verifier's replay cache drops every copy: nothing lost, nobody quarantined) and
  against no defence.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import pytest

from catc.apps import SafetyApps
from catc.bsm import BSM, msg_cnt, sec_mark
from catc.cam import CamConfig, ContextAwareMap, SecMarkClock
from catc.channel import CAUSES, ChannelConfig
from catc.replay import plan, simulate, temp_id
from hil.capture import JsonLines, schema
from hil.datasets import load_table
from obu.capture import ObuCapture
from obu.frames import Frames
from obu.status import RateLimitedLog
from tests.test_capture_files import T0, write_rve_start

DURATION = 30.0  # the leader brakes at 20 s
REPLAY = "replay:vehicle=lead,delay=1,start=10"
QUARANTINE_T = 15.0  # the attacked OBU quarantines the leader from here on
LEAD = f"{temp_id('lead'):08X}"


# --- the rx record says why a frame was dropped --------------------------------------------


class _Capture:
    def __init__(self) -> None:
        self.frames: list[tuple[str, dict]] = []

    def frame(self, rx_unix, channel, data, status, **details) -> None:
        self.frames.append((status, details))

    def finding(self, *args) -> None:
        pass

    def report(self, *args) -> None:
        pass


def test_the_rx_record_tells_a_quarantined_sender_from_a_dropped_copy():
    args = argparse.Namespace(verify="off", trust=None, mbd=True, host_id=None)
    cap = _Capture()
    fr = Frames(args, Counter(), RateLimitedLog(), SecMarkClock(), cap, lambda _id: False)
    host = BSM(msg_cnt=0, temp_id=1, sec_mark=0, lat=47.0, lon=19.0, speed=0.0, heading=0.0,
               length=5.0, width=1.8)
    fr.last_host = (host, 100.0, 10.0)
    fr.last_signer = b"A" * 8

    def rv(tid: int, k: int) -> BSM:  # 2.2 km from the host: out of range, a weak finding
        return BSM(msg_cnt=k, temp_id=tid, sec_mark=10_000 + 100 * k, lat=47.02, lon=19.0,
                   speed=0.0, heading=0.0, length=4.5, width=1.8)

    dropped = [fr.misbehaves(rv(7, k), 100.0, b"", "ok") for k in range(3)]
    assert dropped == [False, False, True]  # 3 weak findings in 10 s: quarantined
    assert fr.misbehaves(rv(7, 2), 100.0, b"", "ok")  # the same message again
    fr.last_signer = b"B" * 8  # another certificate under the same id
    assert fr.misbehaves(rv(7, 3), 100.0, b"", "ok")
    assert [(st, d["why"]) for st, d in cap.frames] == [
        ("quarantined", "quarantine"), ("quarantined", "copy"),
        ("quarantined", "id-conflict")]
    rec = schema.received(1.0, "rv", b"", "quarantined", sender=(7, 3, 10_300),
                          why="copy")
    assert rec["status"] == "quarantined" and rec["why"] == "copy"
    assert "why" not in schema.received(1.0, "rv", b"", "ok", sender=(7, 3, 10_300))


# --- a hand-made pair: the attacked run lost the leader's FCW and quarantined the leader ---


@pytest.fixture(scope="module")
def scene():
    table = load_table("scenario:highway-braking", None)
    the_plan = plan(table, ChannelConfig(), 0, None, DURATION)
    cam = ContextAwareMap(CamConfig(predictor="ca"), SafetyApps())
    snaps = list(simulate(the_plan, cam))
    return table, the_plan, cam, snaps


def _write(directory: Path, scene, attacked: bool) -> dict:
    """One capture of ``scene`` (every message delivered, decided 10 ms after it was
    sent).  ``attacked``: with ``--attack REPLAY``, every leader frame 1 s late again from
    10 s on (dropped as copies), the leader reported at 15 s and its frames dropped from
    then on (its sender quarantined), so no warning on it.  What it wrote."""
    table, the_plan, cam, snaps = scene
    directory.mkdir(parents=True)
    config, ids = write_rve_start(directory, table, the_plan, DURATION,
                                  {"per": 0.0, "rate_hz": 10.0},
                                  attack=[REPLAY] if attacked else None)
    sched = JsonLines(directory / schema.RVE_SCHEDULE)
    sent, copies = [], []
    lead_seq: dict[float, int] = {}
    for ev in the_plan.events:
        v = the_plan.vehicles[int(ev["vehicle"])]
        host = bool(ev["host"])
        t = float(ev["t"])
        rec = schema.scheduled(v, ids[v], "host" if host else "rv", int(ev["index"]),
                               int(ev["seq"]), t, False, CAUSES[int(ev["cause"])], 0.0)
        schema.sent(rec, T0 + t, 0.0, 40)
        sched.write(rec)
        if host:
            continue
        sent.append(rec)
        if v == "lead":
            lead_seq[round(t, 3)] = int(ev["seq"])
            old = lead_seq.get(round(t - 1.0, 3))
            if attacked and t >= 10.0 - 1e-9 and old is not None:
                copy = schema.scheduled("lead", ids["lead"], "rv", -1, old, t - 1.0, False,
                                        "attack", 0.0, attack="replay")
                schema.sent(copy, T0 + t, 0.0, 40)
                sched.write(copy)
                copies.append(copy)
    sched.close()
    (directory / schema.RVE_END).write_text(json.dumps(schema.end(
        config["run_id"], "clean", "replayed", T0, T0 + DURATION)))

    obu = ObuCapture(directory, argparse.Namespace(mbd=True, overwrite=False,
                                                   capture_max_mb=None, predictor="ca"))
    f = cam.frame
    obu.write_origin([f.lat0, f.lon0, f.h0])
    pending = sorted(sent + copies, key=lambda r: r["sent_unix"])
    quarantined = 0
    for snap in snaps:
        due = [r for r in pending if r["sent_unix"] <= T0 + snap.t + 1e-9]
        pending = pending[len(due):]
        for r in due:
            sender = (int(r["id"], 16), msg_cnt(r["seq"]), sec_mark(r["t"]))
            if r.get("attack"):
                obu.rx.write(schema.received(r["sent_unix"], "rv", bytes(40), "quarantined",
                                             sender=sender, why="copy"))
            elif attacked and r["vehicle"] == "lead" and r["t"] >= QUARANTINE_T - 1e-9:
                quarantined += 1
                obu.rx.write(schema.received(r["sent_unix"], "rv", bytes(40), "quarantined",
                                             sender=sender, why="quarantine"))
            else:
                obu.rx.write(schema.received(r["sent_unix"], "rv", bytes(40), "ok",
                                             sender=sender, tick=snap.t,
                                             decided_unix=r["sent_unix"] + 0.01))
        hsm = sec_mark(snap.t)
        tick = schema.tick(snap, hsm, 1.0, T0 + snap.t + 0.01)
        if attacked and snap.t >= QUARANTINE_T - 1e-9:  # the leader's track is gone
            tick["warnings"] = [w for w in tick["warnings"] if w[1] != LEAD]
        obu.ticks.write(tick)
        obu.tracks.write(snap.t, hsm, schema.track_columns(snap))
        if attacked and abs(snap.t - QUARANTINE_T) < 1e-6:
            finding = {"t_unix": T0 + snap.t, "t": snap.t, "reporter": None,
                       "suspect": LEAD, "check": "frequency", "score": 2.0,
                       "evidence": {}, "other": None, "msgCnt": 0, "sec_mark": hsm,
                       "hex": ""}
            obu.mbd_log.write(finding)
            obu.mbr.write({**finding, "found_t": snap.t})
    obu.close()
    obu.write_end("clean", "idle", ticks=len(snaps))
    fcw_on_lead = sum(1 for s in snaps for w in s.warnings
                      if w.app == "fcw" and w.rv_id == ids["lead"])
    lead = [r for r in sent if r["vehicle"] == "lead" and r["t"] >= QUARANTINE_T - 1e-9]
    return {"fcw_on_lead": fcw_on_lead, "quarantined": quarantined, "copies": len(copies),
            "lead_last_t": max(r["t"] for r in lead)}


@pytest.fixture(scope="module")
def pair(scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("pair")
    _write(root / "clean", scene, attacked=False)
    made = _write(root / "attacked", scene, attacked=True)
    return root / "clean", root / "attacked", made


def test_a_quarantined_replay_victim_is_a_false_positive_and_its_fcw_is_counted_lost(pair):
    from captures.defence import compare

    clean, attacked, made = pair
    n = made["fcw_on_lead"]
    assert n >= 10 and made["quarantined"] > 100 and made["copies"] > 100
    r = compare(clean, attacked)
    # the warnings the attack suppressed: the clean OBU's, and the true positives
    assert r["lost"]["fcw"] == {"lead": n}
    assert r["tp"]["fcw"]["lead"] == {"clean": n, "attacked": 0, "lost": n}
    assert r["lost_tp"]["fcw"] == n
    assert r["added"] == {}
    # the leader, honest, quarantined: for how long and how many of its frames
    q = r["honest"]["quarantined"]
    assert list(q) == ["lead"]
    assert q["lead"]["frames"] == q["lead"]["messages"] == made["quarantined"]
    assert q["lead"]["first_t"] == QUARANTINE_T
    assert q["lead"]["last_t"] == made["lead_last_t"]
    assert q["lead"]["duration_s"] == pytest.approx(made["lead_last_t"] - QUARANTINE_T)
    # the replayed copies were dropped as copies: not a quarantine
    assert r["honest"]["other_drops"] == {"lead": {"copy": made["copies"]}}
    assert r["honest"]["suspected"] == {
        "lead": {"findings": 1, "reports": 1, "checks": {"frequency": 1}}}
    assert r["clean_honest"] == {"suspected": {}, "quarantined": {}, "other_drops": {}}
    # a replay has no id of its own: the one flagged id is the victim's
    d = r["detection"]
    assert d["precision"] == 0.0 and d["recall"] is None
    assert d["false_positives"] == ["lead"] and d["true_positives"] == []
    w = r["attack_warnings"]
    assert w["replayed"]["ids"] == ["lead"] and w["replayed"]["added"] == {}
    assert w["fabricated"] == {"ids": [], "ticks": {}, "added": {}}
    # the clean twin against itself: nothing lost, nobody harmed
    same = compare(clean, clean)
    assert same["lost"] == same["added"] == same["lost_tp"] == {}
    assert same["honest"] == same["clean_honest"]


def test_captures_score_no_longer_credits_the_victim_s_quarantine(pair):
    """Before: recall 1.0 and precision 1.0 for the replay, the leader its 'attacker'."""
    from captures.score import score

    _, attacked, _ = pair
    s = score(attacked)
    assert "detection" not in s["attacks"]["replay"]
    assert s["mbd"]["false_suspects"] == [LEAD]


def test_captures_defence_cli(pair, capsys):
    from captures.cli import main

    clean, attacked, made = pair
    assert main(["defence", str(clean), str(attacked)]) == 0
    out = capsys.readouterr().out
    (line,) = [x for x in out.splitlines() if x.startswith("lost TP ticks")]
    assert f"fcw {made['fcw_on_lead']}" in line  # and the leader's EEBL
    assert f"  fcw: lead {made['fcw_on_lead']} -> 0" in out
    assert "honest vehicles quarantined: lead (" in out
    assert "precision 0.0, recall None" in out
    assert main(["defence", str(clean), str(attacked), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["lost_tp"]["fcw"] == made["fcw_on_lead"]
    # the wrong way round, or two runs that are not twins: one line, status 2
    assert main(["defence", str(attacked), str(clean)]) == 2
    err = capsys.readouterr().err
    assert "not a clean run" in err and len(err.strip().splitlines()) == 1


def test_runs_that_are_not_twins_are_refused(pair, tmp_path):
    import shutil

    from captures.defence import compare

    clean, attacked, _ = pair
    other = tmp_path / "other"
    shutil.copytree(attacked, other)
    cfg = json.loads((other / schema.RVE_CONFIG).read_text())
    cfg["channel"]["per"] = 0.3
    (other / schema.RVE_CONFIG).write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="not twins: channel"):
        compare(clean, other)


# --- live: captures sweep's attack cells against their clean twins --------------------------


def test_attack_checks_measure_a_replay_against_its_clean_twin():
    """A replay of the leader, 1 s late from 10 s on, in the first 30 s of the default
    scenario at 8x.  Under enforce+mbd the verifier's replay cache drops every copy: no
    FCW tick lost, no honest vehicle suspected or quarantined.  Without a defence the
    report is whatever the copies do, but consistent."""
    from captures.live import attack_checks, attack_table

    table = load_table("scenario:highway-braking", None)
    rows = attack_checks("scenario:highway-braking", table, "ca", [REPLAY], [0.0],
                         defences=["enforce+mbd", "none"], speed=8.0, duration=30.0)
    mbd, none = rows
    assert (mbd["defence"], none["defence"]) == ("enforce+mbd", "none")
    vs = mbd["vs_clean"]
    assert mbd["lost_tp"].get("fcw", 0) == 0 and "fcw" not in vs["lost"]
    assert vs["tp"]["fcw"]["lead"]["clean"] > 0
    assert mbd["honest_quarantined"] == {} and mbd["honest_suspected"] == []
    assert mbd["precision_victims_fp"] is None  # nothing flagged
    assert mbd["rejected"] == mbd["sent"] > 100  # every copy a replay
    for r in rows:
        vs = r["vs_clean"]
        assert vs["ticks"]["compared"] > 250
        for app, vehicles in vs["tp"].items():
            for x in vehicles.values():
                assert x["clean"] >= 0 and x["attacked"] >= 0
                assert x["lost"] == x["clean"] - x["attacked"]
            assert r["lost_tp"].get(app, 0) == sum(max(0, x["lost"])
                                                   for x in vehicles.values())
        assert all(n > 0 for c in vs["lost"].values() for n in c.values())
        assert r["warning_ticks_fabricated"] == 0  # a replay makes no id
        assert vs["attack_warnings"]["replayed"]["ids"] == ["lead"]
    assert none["vs_clean"]["detection"] is None  # no detector to measure
    assert none["honest_quarantined"] == {} and none["honest_suspected"] == []
    text = attack_table(rows)
    assert "lost TP" in text and "P/R vict FP" in text and len(text.splitlines()) == 3
