"""``captures defence CLEAN ATTACKED``: what an attack cost, measured against its twin, the
same run without the attack (same dataset, trip, host, duration, channel, seed, speed and
OBU defence).

``captures score`` judges one capture by the ids the attack names.  A replay names the
vehicle whose frames it sends again, the honest leader: a detector that quarantines the
leader was scored recall 1.0 and precision 1.0 (issue 28), while the FCW it should have
raised on the leader was lost.  Here the clean twin says what the OBU would have done:

* **Lost warnings**, by app and vehicle.  At every tick both runs have (their ticks are on
  the host's secMark clock, the same data), the vehicles the clean run's OBU warned on
  that the attacked run's did not (``lost``), and the other way round (``added``).
  Against the ground truth (each app on the true states, as ``captures score``): TP ticks
  per app and vehicle in each run, and ``lost`` = clean TP - attacked TP (negative where
  the attacked run had more); ``lost_tp`` sums each app's positive losses.
* **Warnings on the attack's ids** (attacked run, ticks by app): ``fabricated``, the ids
  no vehicle of the run has (its schedule's attack records: ghost, sudden, sybil), every
  warning on them false; ``misbehaving``, the vehicles whose own frames the attack
  changed (``offset``, ``speed``, and the security kinds ``unsigned``, ``bad-signature``,
  ``foreign-cert``); ``replayed``, the vehicles whose frames a replay sends again
  or whose id an impersonator sends under.  For the last two, ``added`` counts the
  warning ticks the clean run did not have at that tick.
* **Honest vehicles suspected or quarantined**: every vehicle of the run but the host and
  the misbehaving ones is honest, the replay's victim and a Sybil's companion included
  (the testbench's Sybil ids are signed by an insider's certificate, nothing ties them to
  that vehicle). Suspected: named as the suspect of a finding (``obu.mbd.jsonl``), with
  the checks and how many of them were reported (``obu.mbr.jsonl``: past the reporting
  threshold; captures before 2026-11-28 reported every finding). Quarantined: its frames
  dropped because their sender was in quarantine (``obu.rx`` status ``quarantined``,
  ``why`` ``quarantine``; a copy, a stale frame or an id conflict is another ``why``,
  counted apart in ``other_drops``; captures before 2026-11-28 have no ``why``, and every
  drop is then taken for a quarantine), with the frames dropped, the RVE's messages it
  never took because of them, and how long: the first to the last dropped frame, in data
  time (the schedule's time of the message the frame carries). The clean twin's figures
  are the baseline (``clean_honest``).
* **Detection** with victims as false positives: flagged are the ids named as suspects
  of a report or quarantined; a flagged id is a true positive when the attack controls it (a
  fabricated id, a misbehaving vehicle), else a false positive.  An id conflict's report
  names the certificate that signed the frame, not the id's holder: an impersonator
  (``impersonate``), which has no id of its own, is ``impersonator`` when the frame was
  its.  Precision = TP / flagged (None when none is flagged), recall = TP / the attack's
  ids whose frames reached the checks (None when none did: a replay has no id of its
  own).  None without ``--mbd``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

from catc.apps import APPS
from catc.apps.verdict import by_app
from catc.attacks import MODIFYING, SECURITY
from hil.capture import Capture, read_capture
from hil.capture.schema import received_key, scheduled_key

__all__ = ["MISBEHAVING", "compare", "register", "table"]

HELP = """\
Compare an attacked capture with its clean twin (the same rve run without --attack:
dataset, trip, host, duration, PER, rate, seed, speed, and the OBU's --verify, --mbd and
--predictor must be the same): the true warnings the attack suppressed, by app and
vehicle (ticks the clean OBU warned on a vehicle and the attacked one did not; TP ticks
against the ground truth in each), the warnings on the attack's fabricated and
misbehaving ids, the honest vehicles suspected or quarantined (frames dropped, how long),
and detection precision and recall in which a quarantined victim (a replayed leader) is
a false positive.  --json prints the same as one JSON object."""

#: Attack kinds whose target vehicle sends the bad frames itself: a misbehaving sender.
MISBEHAVING = (*MODIFYING, *SECURITY)

#: Settings the two runs must share: the RVE's (``rve.config.json``) and the OBU's.
_SAME_RVE = ("dataset", "trip", "host", "idm_host", "duration", "speed", "per", "burst",
             "rate", "latency", "jitter", "seed", "distance", "framing")
_SAME_OBU = ("verify", "mbd", "predictor")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("defence", help="what an attack cost, against the same run without it",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("clean", type=Path, metavar="CLEAN", help="the run without the attack")
    p.add_argument("attacked", type=Path, metavar="ATTACKED", help="the run with it")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=run)


def check_twins(clean: Capture, attacked: Capture) -> None:
    """ValueError (one line) unless ``attacked`` is ``clean`` with an attack."""
    rc, ra = clean.rve_config, attacked.rve_config
    if rc["settings"].get("attack"):
        raise ValueError(f"{clean.directory}: not a clean run (--attack "
                         f"{' '.join(rc['settings']['attack'])})")
    pairs = [(k, rc["settings"].get(k), ra["settings"].get(k)) for k in _SAME_RVE]
    pairs += [("signed", bool(rc["settings"].get("sign")), bool(ra["settings"].get("sign"))),
              ("host vehicle", rc.get("host"), ra.get("host")),
              ("channel", rc.get("channel"), ra.get("channel")),
              ("seed", rc.get("seed"), ra.get("seed"))]
    pairs += [(f"obu {k}", clean.obu_config["settings"].get(k),
               attacked.obu_config["settings"].get(k)) for k in _SAME_OBU]
    for what, a, b in pairs:
        if a != b:
            raise ValueError(f"{clean.directory} and {attacked.directory} are not twins: "
                             f"{what} {a!r} vs {b!r}")


def _warned(cap: Capture) -> dict[float, dict[str, set[str]]]:
    """Tick time (ms) -> {app: the ids (hex) the OBU warned on} (an empty dict for a
    quiet tick)."""
    return {round(tk["t"], 3): by_app((w[0], w[1]) for w in tk["warnings"])
            for tk in cap.iter_ticks()}


def _tp(warned: dict, gt: dict) -> dict[str, Counter]:
    """TP ticks per app and vehicle (hex): the ticks the OBU and the truth both warn on it."""
    out: dict[str, Counter] = {a: Counter() for a in APPS}
    for t, w in warned.items():
        truth = gt.get(t)
        if truth is None:
            continue
        for app, ids in w.items():
            out.setdefault(app, Counter()).update(ids & truth.get(app, frozenset()))
    return out


def _roles(cap: Capture, names: dict[str, str]) -> tuple[dict, dict, dict, dict]:
    """From the schedule: fabricated ids, misbehaving and replayed vehicles (hex -> attack
    kind), and every RV message key -> its data time (the replays' copies share their
    originals' keys)."""
    fabricated: dict[str, str] = {}
    misbehaving: dict[str, str] = {}
    replayed: dict[str, str] = {}
    when: dict = {}
    for r in cap.iter_schedule():
        if r.get("channel") != "rv":
            continue
        when.setdefault(scheduled_key(r), r["t"])
        kind = r.get("attack")
        if kind is None:
            continue
        if r["id"] not in names:
            fabricated.setdefault(r["id"], kind)
        elif kind in MISBEHAVING:
            misbehaving.setdefault(r["id"], kind)
        elif kind in ("replay", "impersonate"):
            replayed.setdefault(r["id"], kind)
    return fabricated, misbehaving, replayed, when


#: How the detection figures name an impersonator (``--attack impersonate``): it sends
#: under another vehicle's id, and a report can name only its certificate.
IMPOSTOR = "impersonator"


def _impostor(cap: Capture) -> tuple[set[str], bool]:
    """The signers (``signer:HEX``) of the id conflicts reported on the impersonator's
    frames, and whether any of its frames reached the checks."""
    keys = {scheduled_key(r) for r in cap.iter_schedule() if r.get("attack") == "impersonate"}
    signers = {f"signer:{m['evidence'].get('signer')}" for m in cap.mbr or []
               if m["check"] == "id-conflict"
               and (m["suspect"], m["msgCnt"], m["sec_mark"]) in keys}
    reached = any(r.get("status") in ("ok", "quarantined") and received_key(r) in keys
                  for r in cap.iter_rx() if r.get("channel") == "rv")
    return signers, reached


def _drops(cap: Capture, when: dict, sent: set) -> tuple[dict[str, dict], set[str]]:
    """Per id (hex), what misbehavior detection dropped of its frames: quarantine drops
    (frames, data times, the RVE's messages never taken because of them) and the other
    drops by why; and the ids whose frames reached the checks (taken or dropped)."""
    out: dict[str, dict] = {}
    taken: set = set()
    dropped: dict[str, set] = {}
    checked: set[str] = set()
    for r in cap.iter_rx():
        if r.get("channel") != "rv" or "id" not in r:
            continue
        status = r.get("status")
        if status == "ok":
            taken.add(received_key(r))
            checked.add(r["id"])
        if status != "quarantined":
            continue
        checked.add(r["id"])
        d = out.setdefault(r["id"], {"frames": 0, "times": [], "other": Counter()})
        why = r.get("why", "quarantine")  # before 2026-11-28: no why
        if why != "quarantine":
            d["other"][why] += 1
            continue
        d["frames"] += 1
        key = received_key(r)
        if key in when:
            d["times"].append(when[key])
        if key in sent:
            dropped.setdefault(r["id"], set()).add(key)
    for tid, d in out.items():
        d["messages"] = len(dropped.get(tid, set()) - taken)
    return out, checked


def _honest(cap: Capture, honest: set[str], label, when: dict, sent: set
            ) -> tuple[dict, set[str], set[str]]:
    """What misbehavior detection did to the honest vehicles: ``suspected`` (label ->
    {findings, reports, checks}), ``quarantined`` (label -> {frames, messages, first_t, last_t,
    duration_s}), ``other_drops`` (label -> {why: frames}: copies, stale frames, id
    conflicts under its id); the ids flagged (reported or quarantined, honest or not)
    and those whose frames reached the checks."""
    suspected: dict[str, dict] = {}
    flagged: set[str] = set()
    for m in cap.findings or []:
        if m["suspect"] in honest and m["check"] != "id-conflict":  # names the signer
            s = suspected.setdefault(label(m["suspect"]),
                                     {"findings": 0, "reports": 0, "checks": {}})
            s["findings"] += 1
            s["checks"][m["check"]] = s["checks"].get(m["check"], 0) + 1
    for m in cap.mbr or []:
        if m["check"] == "id-conflict":  # names the signer, not the id's holder
            flagged.add(f"signer:{m['evidence'].get('signer')}")
            continue
        flagged.add(m["suspect"])
        if m["suspect"] in honest:
            s = suspected.setdefault(label(m["suspect"]),
                                     {"findings": 0, "reports": 0, "checks": {}})
            s["reports"] += 1
    drops, checked = _drops(cap, when, sent)
    quarantined: dict[str, dict] = {}
    other: dict[str, dict] = {}
    for tid, d in sorted(drops.items()):
        if d["frames"]:
            flagged.add(tid)
        if tid not in honest:
            continue
        if d["other"]:
            other[label(tid)] = dict(d["other"])
        if d["frames"]:
            ts = d["times"]
            quarantined[label(tid)] = {
                "frames": d["frames"], "messages": d["messages"],
                "first_t": round(min(ts), 3) if ts else None,
                "last_t": round(max(ts), 3) if ts else None,
                "duration_s": round(max(ts) - min(ts), 3) if ts else None}
    return ({"suspected": suspected, "quarantined": quarantined, "other_drops": other},
            flagged, checked)


def _sent(cap: Capture) -> set:
    """The keys of the RVE's own RV messages that went out (no attack frame)."""
    return {scheduled_key(r) for r in cap.iter_schedule()
            if r.get("channel") == "rv" and r.get("cause") != "attack" and not r["dropped"]}


def compare(clean_dir: Path, attacked_dir: Path) -> dict:
    """The attacked run against its clean twin (module docstring); ValueError (one line)
    when they are not twins (CaptureError for a bad capture)."""
    from captures.score import _ground_truth

    clean, attacked = read_capture(clean_dir), read_capture(attacked_dir)
    check_twins(clean, attacked)
    rve = attacked.rve_config
    names = {tid: v for v, tid in rve["vehicles"].items()}
    host = rve["vehicles"].get(rve.get("host"))

    def label(tid: str) -> str:
        return names.get(tid, tid)

    gt = _ground_truth(rve)
    wc, wa = _warned(clean), _warned(attacked)
    common = wc.keys() & wa.keys()
    lost: dict[str, Counter] = {}
    added: dict[str, Counter] = {}
    for t in common:
        c, a = wc[t], wa[t]
        for app in c.keys() | a.keys():
            ci, ai = c.get(app, set()), a.get(app, set())
            if ci - ai:
                lost.setdefault(app, Counter()).update(label(i) for i in ci - ai)
            if ai - ci:
                added.setdefault(app, Counter()).update(ai - ci)
    tpc, tpa = _tp(wc, gt), _tp(wa, gt)
    tp: dict[str, dict] = {}
    for app in tpc.keys() | tpa.keys():
        c, a = tpc.get(app, Counter()), tpa.get(app, Counter())
        for tid in c.keys() | a.keys():
            n, m = c[tid], a[tid]
            tp.setdefault(app, {})[label(tid)] = {"clean": n, "attacked": m, "lost": n - m}

    fabricated, misbehaving, replayed, when = _roles(attacked, names)
    groups = {}
    for group, ids in (("fabricated", fabricated), ("misbehaving", misbehaving),
                       ("replayed", replayed)):
        ticks: Counter = Counter()
        for w in wa.values():
            ticks.update(app for app, vs in w.items() for _ in vs & ids.keys())
        groups[group] = {
            "ids": sorted(label(i) for i in ids),
            "ticks": dict(ticks),
            "added": {app: n for app, c in added.items()
                      if (n := sum(c[i] for i in ids))}}

    attackers = fabricated.keys() | misbehaving.keys()
    honest = set(names) - {host} - attackers
    sent = _sent(attacked)
    harm, flagged, checked = _honest(attacked, honest, label, when, sent)
    if "impersonate" in replayed.values():  # it has no id of its own: its signer
        signers, reached = _impostor(attacked)
        attackers |= {IMPOSTOR}
        flagged = {IMPOSTOR if i in signers else i for i in flagged}
        if reached:
            checked.add(IMPOSTOR)
    baseline = _honest(clean, honest, label, _roles(clean, names)[3], _sent(clean))[0]
    detection = None
    if attacked.mbr is not None:
        tp_ids = flagged & attackers
        reached = attackers & checked
        fp_ids = flagged - attackers
        detection = {
            "flagged": len(flagged), "true_positives": sorted(label(i) for i in tp_ids),
            "false_positives": sorted(label(i) for i in fp_ids),
            "attackers": len(reached),
            "precision": round(len(tp_ids) / len(flagged), 4) if flagged else None,
            "recall": round(len(tp_ids & reached) / len(reached), 4) if reached else None}
    return {
        "clean": str(clean_dir), "attacked": str(attacked_dir),
        "attacks": rve["settings"].get("attack") or [],
        "ticks": {"compared": len(common), "clean_only": len(wc.keys() - wa.keys()),
                  "attacked_only": len(wa.keys() - wc.keys())},
        "lost": {app: dict(c) for app, c in sorted(lost.items())},
        "added": {app: {label(i): n for i, n in c.items()} for app, c in sorted(added.items())},
        "tp": tp,
        "lost_tp": {app: total for app, vs in sorted(tp.items())
                    if (total := sum(max(0, v["lost"]) for v in vs.values()))},
        "attack_warnings": groups,
        "honest": harm,
        "clean_honest": baseline,
        "detection": detection,
    }


def _apps(counts: dict[str, int]) -> str:
    return ", ".join(f"{app} {n}" for app, n in sorted(counts.items())) or "none"


def table(r: dict) -> str:
    """The comparison as text, one finding a line."""
    t = r["ticks"]
    lines = [f"attacked: {r['attacked']} ({' '.join(r['attacks']) or 'no attack'})",
             f"clean twin: {r['clean']}; {t['compared']} ticks compared"
             + (f" ({t['clean_only']} only clean, {t['attacked_only']} only attacked)"
                if t["clean_only"] or t["attacked_only"] else ""),
             "lost TP ticks (clean TP - attacked TP): " + _apps(r["lost_tp"])]
    for app, vs in sorted(r["tp"].items()):
        moved = {v: x for v, x in vs.items() if x["lost"]}
        if moved:
            lines.append(f"  {app}: " + ", ".join(
                f"{v} {x['clean']} -> {x['attacked']}" for v, x in sorted(moved.items())))
    lines.append("warnings the clean OBU raised and the attacked one did not (ticks): "
                 + ("; ".join(f"{app}: " + _apps(vs) for app, vs in r["lost"].items())
                    or "none"))
    lines.append("warnings the attacked OBU raised and the clean one did not (ticks): "
                 + ("; ".join(f"{app}: " + _apps(vs) for app, vs in r["added"].items())
                    or "none"))
    for group, g in r["attack_warnings"].items():
        if g["ids"]:
            lines.append(f"warnings on {group} ids ({', '.join(g['ids'][:6])}"
                         + (", ..." if len(g["ids"]) > 6 else "") + "): ticks "
                         + _apps(g["ticks"]) + "; not in the clean run " + _apps(g["added"]))
    h = r["honest"]
    lines.append("honest vehicles suspected: " + (", ".join(
        f"{v} ({s['findings']} findings, {s['reports']} reported: {_apps(s['checks'])})"
        for v, s in sorted(h["suspected"].items())) or "none"))
    lines.append("honest vehicles quarantined: " + (", ".join(
        f"{v} ({q['frames']} frames dropped, {q['messages']} messages lost, data time "
        f"{q['first_t']}-{q['last_t']} s: {q['duration_s']} s)"
        for v, q in sorted(h["quarantined"].items())) or "none"))
    if h["other_drops"]:
        lines.append("frames under honest ids dropped as copies, stale or id conflicts: "
                     + "; ".join(f"{v}: {_apps(w)}" for v, w in sorted(h["other_drops"].items())))
    c = r["clean_honest"]
    if c["suspected"] or c["quarantined"]:
        lines.append(f"  in the clean twin: suspected {', '.join(sorted(c['suspected'])) or 'none'}"
                     f"; quarantined {', '.join(sorted(c['quarantined'])) or 'none'}")
    d = r["detection"]
    if d is None:
        lines.append("detection: no misbehavior detection (obu run without --mbd)")
    else:
        lines.append(f"detection (victims count as false positives): precision "
                     f"{d['precision']}, recall {d['recall']}; flagged {d['flagged']}, "
                     f"attack ids flagged {', '.join(d['true_positives']) or 'none'}, others "
                     f"flagged {', '.join(d['false_positives']) or 'none'}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    try:
        result = compare(args.clean, args.attacked)
    except (ValueError, KeyError) as err:  # CaptureError and DatasetError included
        print(f"captures defence: {err}", file=sys.stderr)
        return 2
    print(json.dumps(result) if args.json else table(result))
    return 0
