"""``rve run --attack``: the misbehaving senders (catc.attacks) and what the OBU makes of
them over UDP with ``--verify enforce``.

* The ghost is where the issue puts it: ``ahead`` m ahead of the host along the host's
  own path at ``start``, with the host's speed, then braking at ``decel``.
* Every attack frame is labelled in ``rve.schedule.jsonl`` and ``captures score``
  accounts for it per kind.
* Security attacks are rejected with their reason; a ghost signed by an outsider raises
  no warning (enforce), one signed by an insider passes verification (misbehavior
  detection is what must catch it).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time

import numpy as np
import pytest

from catc.attacks import KINDS, Attacks, parse
from catc.channel import ChannelConfig
from catc.replay import plan
from hil.datasets import load_table
from hil.transport.udp import free_ports
from tests.test_obu import finish, rve, score, start_obu
from tests.test_security_e2e import pki  # noqa: F401  (fixture)


def test_parse_fills_defaults_and_names_what_is_wrong():
    a = parse("ghost:ahead=25,signer=outsider")
    assert a.kind == "ghost" and a["ahead"] == 25.0 and a["decel"] == 6.0
    assert a["signer"] == "outsider" and a["start"] == 5.0 and a["duration"] == math.inf
    assert parse("sybil:count=4")["count"] == 4
    for bad, needle in (("teleport", "unknown kind"), ("ghost:ahead", "KEY=VALUE"),
                        ("ghost:speed=3", "KEY=VALUE"), ("offset:dx=east", "number"),
                        ("ghost:signer=mallory", "insider or outsider"),
                        ("sybil:count=0", "count"), ("speed:duration=0", "duration")):
        with pytest.raises(ValueError, match=needle):
            parse(bad)
    assert len(KINDS) == len(set(KINDS)) == 10 and "impersonate" in KINDS


def _default_plan():
    return plan(load_table("scenario:highway-braking", None), ChannelConfig(), 0, None, None)


def test_the_ghost_is_ahead_of_the_host_on_its_path_and_brakes():
    the_plan = _default_plan()
    attacks = Attacks([parse("ghost:start=4,ahead=20,decel=6")], the_plan)
    host = the_plan.table.tracks[the_plan.host_id]
    t0 = float(the_plan.events["t"][0])
    got = {}
    for t in (t0 + 3.9, t0 + 4.0, t0 + 5.0, t0 + 6.0):
        inj = attacks.injected(t)
        got[round(t - t0, 1)] = inj
    assert got[3.9] == []  # not yet
    g0, g1 = (got[k][0].bsm for k in (4.0, 5.0))
    assert g0.temp_id == g1.temp_id == Attacks.ID_BASE and g1.msg_cnt == g0.msg_cnt + 1
    v0 = float(np.interp(t0 + 4.0, host.t, host.speed))
    assert g0.speed == pytest.approx(v0) and g1.speed == pytest.approx(max(0, v0 - 6.0))
    assert g0.accel_long == -6.0
    # 20 m ahead of the host at the start, along its path (the host drives straight here)
    from catc.geo import bearing_deg, distance_m, heading_diff_deg

    hlat, hlon, hdg = (float(np.interp(t0 + 4.0, host.t, c))
                       for c in (host.lat, host.lon, host.heading))
    assert float(distance_m(hlat, hlon, g0.lat, g0.lon)) == pytest.approx(20.0, abs=0.5)
    assert abs(float(heading_diff_deg(bearing_deg(hlat, hlon, g0.lat, g0.lon), hdg))) < 3.0
    assert abs(float(heading_diff_deg(g0.heading, hdg))) < 3.0


def test_an_impersonator_sends_under_its_victim_s_id_where_it_is_told():
    """``impersonate``: an insider sending under another vehicle's TemporaryID (issue 28:
    nothing but the receiver binds an id to the certificate that signs it), on the host
    (``ahead=0``) at its speed, with a message count of its own."""
    from catc.geo import distance_m
    from catc.replay import temp_id

    the_plan = _default_plan()
    attacks = Attacks([parse("impersonate:vehicle=lead,start=10,duration=0.2")], the_plan)
    host = the_plan.table.tracks[the_plan.host_id]
    t0 = float(the_plan.events["t"][0])
    assert attacks.injected(t0 + 9.9) == [] and attacks.injected(t0 + 10.2) == []
    (a,), (b,) = attacks.injected(t0 + 10.0), attacks.injected(t0 + 10.1)
    assert a.bsm.temp_id == b.bsm.temp_id == temp_id("lead") and a.attack.kind == "impersonate"
    assert (a.bsm.msg_cnt, b.bsm.msg_cnt) == (0, 1)
    hlat, hlon, v = (float(np.interp(t0 + 10.0, host.t, c))
                     for c in (host.lat, host.lon, host.speed))
    assert float(distance_m(hlat, hlon, a.bsm.lat, a.bsm.lon)) < 0.5
    assert a.bsm.speed == pytest.approx(v)
    assert parse("impersonate").params["signer"] == "insider"


def test_sybil_ids_follow_their_sender_and_modifications_are_bounded():
    the_plan = _default_plan()
    attacks = Attacks([parse("sybil:vehicle=lead,count=3,spacing=8,start=2"),
                       parse("offset:vehicle=lead,dy=30,start=2,duration=1")], the_plan)
    t0 = float(the_plan.events["t"][0])
    inj = attacks.injected(t0 + 2.0)
    assert [i.bsm.temp_id & 0xFF for i in inj] == [1, 2, 3]
    assert len({i.bsm.temp_id for i in inj}) == 3
    lead = list(the_plan.vehicles).index("lead")
    ev = next(e for e in the_plan.events if int(e["vehicle"]) == lead
              and abs(float(e["t"]) - (t0 + 2.5)) < 1e-6)
    bsm = the_plan.bsm(ev)
    moved, label = attacks.modify(lead, float(ev["t"]), bsm)
    assert label.kind == "offset" and moved.lat - bsm.lat == pytest.approx(30 / 111_320)
    later = next(e for e in the_plan.events if int(e["vehicle"]) == lead
                 and abs(float(e["t"]) - (t0 + 3.5)) < 1e-6)
    assert attacks.modify(lead, float(later["t"]), the_plan.bsm(later))[1] is None
    with pytest.raises(ValueError, match="not an RV"):
        Attacks([parse("offset:vehicle=host")], the_plan)


def test_attacks_over_udp_into_an_enforcing_obu(pki, tmp_path):  # noqa: F811
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca", "--verify", "enforce",
                    "--trust", str(pki))
    attacks = ["ghost:start=4,duration=4,signer=outsider", "ghost:start=10,duration=3",
               "bad-signature:start=2,duration=1", "foreign-cert:start=3,duration=1",
               "unsigned:start=5,duration=1", "replay:start=6,duration=1,delay=2",
               "sybil:start=2,duration=1,count=2"]
    summary = rve(ports, "--sign", str(pki), "--per", "0", "--speed", "8", "--duration", "16",
                  "--capture", str(tmp_path), *[x for a in attacks for x in ("--attack", a)])
    out, _ = finish(obu)
    assert summary["attack_frames"] > 0
    labels = [json.loads(line).get("attack") for line in (tmp_path / "rve.schedule.jsonl").open()]
    assert {x for x in labels if x} == {"ghost", "bad-signature", "foreign-cert", "unsigned",
                                       "replay", "sybil"}
    s = score(tmp_path)
    a = s["attacks"]
    assert a["bad-signature"]["rejected"] == {"bad-signature": a["bad-signature"]["sent"]}
    assert a["unsigned"]["rejected"] == {"unsigned": a["unsigned"]["sent"]}
    assert sum(a["foreign-cert"]["rejected"].values()) == a["foreign-cert"]["sent"] > 0
    assert set(a["foreign-cert"]["rejected"]) <= {"chain", "unknown-signer"}
    assert a["sybil"]["accepted"] == a["sybil"]["sent"] > 0  # an insider: MBD's job
    assert a["replay"]["sent"] > 0
    ghost = a["ghost"]  # the outsider's 40 frames rejected, the insider's 30 accepted
    assert ghost["sent"] == 70 and ghost["accepted"] == 30
    assert set(ghost["rejected"]) <= {"chain", "unknown-signer"}
    warned = {json.loads(line)["rv"] for line in out.splitlines()}
    outsider = f"{Attacks.ID_BASE:08X}"
    insider = f"{Attacks.ID_BASE | 1 << 8:08X}"
    assert outsider not in warned  # enforce: the forged ghost raises no warning
    assert insider in warned  # signed by an insider it passes: misbehavior detection's case
    # the real vehicles' messages all arrived: attacks on the security layer drop only theirs
    assert s["received"] == s["sent"] - a["bad-signature"]["sent"] \
        - a["foreign-cert"]["sent"] - a["unsigned"]["sent"]


def test_misbehavior_detection_quarantines_the_insider_ghost_before_any_warning(
        pki, tmp_path):  # noqa: F811
    """The ghost signed with a valid certificate passes verification; ``--mbd`` catches it
    at its first message (sudden appearance 20 m ahead of the host) and it raises no
    warning.  The Sybil ids are caught too, and no honest vehicle is reported."""
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca", "--verify", "enforce", "--trust",
                    str(pki), "--mbd")
    rve(ports, "--sign", str(pki), "--per", "30", "--seed", "2", "--speed", "4",
        "--duration", "30", "--capture", str(tmp_path),
        "--attack", "ghost:start=12,duration=6",
        "--attack", "ghost:start=20,duration=3,signer=outsider",
        "--attack", "sybil:vehicle=lead,start=24,duration=3,count=2")
    out, _ = finish(obu)
    warned = {json.loads(line)["rv"] for line in out.splitlines()}
    assert not {w for w in warned if w.startswith("6A7A")}  # no warning on a fabricated id
    s = score(tmp_path)
    ghost, sybil = s["attacks"]["ghost"], s["attacks"]["sybil"]
    insider = f"{Attacks.ID_BASE:08X}"
    assert ghost["detection"]["time_to_detect_s"][insider] <= 0.1  # its first message
    assert ghost["accepted"] == 0 and ghost["quarantined"] > 0
    assert sybil["detection"]["recall"] == 1.0
    assert s["mbd"]["false_suspects"] == []
    reports = [json.loads(line) for line in (tmp_path / "obu.mbr.jsonl").open()]
    first = next(r for r in reports if r["suspect"] == insider)
    assert first["check"] == "sudden-appearance" and first["msgCnt"] == 0
    assert first["found_t"] == first["t"]  # a strong finding: reported at once
    assert {"reporter", "suspect", "check", "evidence", "hex"} <= set(first)


def test_misbehavior_detection_reports_nothing_on_a_clean_run(tmp_path):
    """On the default scenario at PER 30 % the checks stay silent and the scores equal
    those of the same run without them."""
    with_mbd, without = tmp_path / "mbd", tmp_path / "plain"
    for cap, extra in ((with_mbd, ("--mbd",)), (without, ())):
        ports = free_ports()
        obu = start_obu(cap, ports, "--predictor", "ca", *extra)
        rve(ports, "--per", "30", "--seed", "2", "--speed", "8", "--duration", "30",
            "--capture", str(cap))
        finish(obu)
    assert (with_mbd / "obu.mbd.jsonl").read_text() == ""  # no finding, so no report
    assert (with_mbd / "obu.mbr.jsonl").read_text() == ""
    counters = json.loads((with_mbd / "obu.counters.json").read_text())
    assert not [k for k in counters if k.startswith("mbd_") and k != "mbd_no_host_yet"]
    a, b = score(with_mbd), score(without)
    for key in ("fcw_accuracy", "fcw", "warnings", "received", "pte95_m", "pte95_per_rv"):
        assert a[key] == b[key], key


def test_captures_sweep_puts_an_attack_beside_per(tmp_path):
    """``captures sweep --attack`` runs the attack live at each PER against each defence
    and reports it in the table and the JSON."""
    import subprocess
    import sys

    from tests.conftest import shared_path

    data = shared_path("openacc-zalazone", "short_setting_dynamic_part22.csv")
    out = subprocess.run(
        [sys.executable, "-m", "captures.cli", "sweep", "--dataset", f"openacc:{data}",
         "--predictors", "ca", "--per", "0", "--rate", "10", "--attack",
         "bad-signature:start=10,duration=3", "--defences", "none,enforce",
         "--json", str(tmp_path / "sweep.json")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    rows = json.loads((tmp_path / "sweep.json").read_text())["attacks"]
    assert [(r["kind"], r["per"], r["defence"]) for r in rows] == [
        ("bad-signature", 0.0, "none"), ("bad-signature", 0.0, "enforce")]
    none, enforce = rows
    assert none["sent"] == enforce["sent"] == 30  # 3 s of one RV at 10 Hz, PER 0
    assert none["accepted"] == 30 and none["rejected"] == 0  # nobody checks
    assert enforce["accepted"] == 0 and enforce["rejected"] == 30
    assert "bad-signature:start=10,duration=3" in out.stdout and "enforce" in out.stdout
    bad = subprocess.run([sys.executable, "-m", "captures.cli", "sweep", "--dataset",
                          f"openacc:{data}", "--attack", "teleport"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "unknown kind" in bad.stderr


# --- issue 28: what an attacker can make the detector do to an honest vehicle -----------


def _mbd_run(pki, tmp_path, *attacks, relay=None):  # noqa: F811
    """The default scenario's first 30 s (the leader brakes at 20 s: 20 FCW ticks), signed,
    into ``obu run --verify enforce --mbd``, with ``attacks``; ``relay(sock, rv_port,
    host_bsm)`` sees each host frame on its way, before the OBU (an attacker listening to
    the host, who may send on ``sock`` to the OBU's RV port).  The score, and the OBU's
    counters."""
    import socket
    import threading

    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca", "--verify", "enforce", "--trust",
                    str(pki), "--mbd")
    host_port = ports[1]
    if relay is not None:
        from catc.j2735 import decode_frame, open_envelope

        inbound = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        inbound.bind(("127.0.0.1", 0))
        inbound.settimeout(5.0)
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

        def forward():
            with inbound, out:
                while True:
                    try:
                        data = inbound.recv(65536)
                    except TimeoutError:
                        return
                    relay(out, ports[0], decode_frame(open_envelope(data)[0]))
                    out.sendto(data, ("127.0.0.1", ports[1]))

        thread = threading.Thread(target=forward, daemon=True)
        thread.start()
        host_port = inbound.getsockname()[1]
    run_ports = [ports[0], host_port]
    rve(run_ports, "--sign", str(pki), "--per", "0", "--speed", "4", "--duration", "30",
        "--capture", str(tmp_path), *[x for a in attacks for x in ("--attack", a)])
    finish(obu)
    if relay is not None:
        thread.join(10.0)
    return score(tmp_path), json.loads((tmp_path / "obu.counters.json").read_text())


def test_an_insider_claiming_the_leader_s_id_does_not_silence_it(pki, tmp_path):  # noqa: F811
    """Issue 28: one correctly signed frame of an insider pseudonym claiming the leader's
    id at the host's position quarantined the leader (an intersection with the host,
    sticky) for the rest of the run.  The id is bound to the leader's certificate: the
    frame is an id conflict against the insider, and the leader's FCW fires on all 20
    of its ticks."""
    from catc.j2735 import encode_frame
    from catc.replay import temp_id
    from catc.security import sign_bsm, unix_to_time64
    from hil.pki import load
    from rve.framing import wrap

    cert, key = load(pki).pseudonyms[19]  # the default scenario's 16 RVs use 0-15
    lead = temp_id("lead")
    seen = []

    def steal(sock, rv_port, host):
        seen.append(host)
        if len(seen) == 100:  # 10 s: on the host, as its last frame placed it
            last = seen[-2]
            bsm = dataclasses.replace(last, temp_id=lead, sec_mark=host.sec_mark)
            frame = encode_frame(bsm)
            signed = sign_bsm(frame, key, cert, unix_to_time64(time.time()),
                              include_cert=True)
            sock.sendto(wrap(frame, "1609", signed), ("127.0.0.1", rv_port))

    s, counters = _mbd_run(pki, tmp_path, relay=steal)
    assert counters["mbd_id-conflict"] == 1 and counters["verify_ok"] == s["sent"] + 1
    assert "mbd_quarantined" not in counters
    assert s["received"] == s["sent"]
    assert (s["fcw"]["tp"], s["fcw"]["fp"], s["fcw"]["fn"]) == (20, 0, 0)
    (report,) = [json.loads(line) for line in (tmp_path / "obu.mbr.jsonl").open()]
    assert report["check"] == "id-conflict" and report["suspect"] == f"{lead:08X}"


def test_a_ghost_in_the_first_second_raises_no_warning(pki, tmp_path):  # noqa: F811
    """Issue 28: a ghost starting within F2MD's blind 2.1 s warm-up raised a 22-tick FCW
    false alarm.  Checked from the first host fix, it is a sudden appearance 20 m ahead at
    its first frame, and quarantined before it can warn."""
    s, _ = _mbd_run(pki, tmp_path, "ghost:start=1")
    ghost = s["attacks"]["ghost"]
    assert ghost["accepted"] == 0 and ghost["warnings"] == {}
    assert ghost["detection"]["time_to_detect_s"] == {f"{Attacks.ID_BASE:08X}": 0.0}
    assert (s["fcw"]["tp"], s["fcw"]["fp"], s["fcw"]["fn"]) == (20, 0, 0)
    assert s["mbd"]["false_suspects"] == []


@pytest.fixture(scope="module")
def clean_mbd(pki, tmp_path_factory):  # noqa: F811
    """The clean twin of the :func:`_mbd_run` attacks: the same run without one."""
    directory = tmp_path_factory.mktemp("clean_mbd")
    _mbd_run(pki, directory)
    return directory


def test_an_impersonator_is_named_by_its_certificate_not_by_its_victim(
        pki, clean_mbd, tmp_path):  # noqa: F811
    """``rve run --attack impersonate``: an insider sends under the leader's id, on the
    host, signed by its own pseudonym.  Under ``--verify enforce --mbd`` each of its frames
    is an id conflict against its signer: the leader is neither suspected nor
    quarantined, its FCW fires on every tick the clean twin's did, and ``captures
    defence`` counts the impersonator, not the leader, as the one flagged."""
    from captures.defence import compare

    s, counters = _mbd_run(pki, tmp_path, "impersonate:vehicle=lead,start=10,duration=2")
    assert counters["mbd_id-conflict"] == s["attacks"]["impersonate"]["sent"] == 20
    assert "mbd_quarantined" not in counters
    assert (s["fcw"]["tp"], s["fcw"]["fp"], s["fcw"]["fn"]) == (20, 0, 0)
    r = compare(clean_mbd, tmp_path)
    assert r["lost_tp"] == {} and r["honest"]["quarantined"] == {}
    assert r["honest"]["suspected"] == {}  # the id conflicts name the signer
    assert r["detection"]["true_positives"] == ["impersonator"]
    assert r["detection"]["false_positives"] == []
    assert (r["detection"]["precision"], r["detection"]["recall"]) == (1.0, 1.0)
