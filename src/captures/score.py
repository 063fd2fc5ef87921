"""``captures score DIR``: join the RVE's ground truth with the OBU's capture and score the run.

* **PTE** (docs/architecture.md, "Metrics"): at every OBU tick, for every tracked RV, the 2-D
  distance between the OBU's estimate and the RV's true position at that tick's time.  Truth
  (``rve.truth.jsonl``) is moved into the OBU's ENU frame (its origin is in
  ``obu.config.json``) and interpolated to the tick.  Tick times are the host's secMark
  clock, which differs from the dataset's time by whole minutes; the offset comes from the
  host's secMark at the first tick.  PTE95 overall and per RV.
* **Warnings, by vehicle** (FCW, EEBL, BSW, LCW): the ground truth is each application's
  output on the true states at PER 0 and 10 Hz: the same dataset through the offline
  simulator (:func:`catc.replay.simulate`, every message delivered, values through UPER
  as on the wire).  At every tick both name the vehicles each application warns on; a
  warning on the wrong vehicle is a false positive on it and a false negative on the
  right one (:mod:`catc.apps.verdict`).  Accuracy = (TP + TN) / (TP + TN + FP + FN);
  ``fcw_accuracy`` and ``fcw`` are FCW's, ``apps`` has every application's.
* **Counts that count the run**: messages sent and dropped by the channel
  (``rve.schedule.jsonl``, the RV channel, an attack's own frames apart); ``received``:
  those of them the OBU took (``obu.rx``, status ``ok``), each message once, joined by
  its key (:func:`hil.capture.schema.message_key`), so received <= sent whatever else
  the RV port heard.  The rest is counted apart (``frames``): later copies of a sent
  message (``duplicate``), frames under a run's id that the RVE never sent as an RV
  message (``unmatched``: a bit-flipped copy), frames of ids the RVE never sent
  (``phantom``; ``phantom_received``), decode errors (``garbage``, by reason), rejected,
  quarantined and unticked frames; and warning events by app.
* **Security** (``obu run --verify log|enforce``): the IEEE 1609.2 verdict of every RV
  frame, ``ok`` or the reason it failed (``unsigned``, ``bad-signature``,
  ``unknown-signer``, ``expired``, ``wrong-psid``, ``stale``, ``chain``, ``unsupported``),
  and how many were rejected (dropped under ``enforce``); ``verification``: when each
  frame was verified (verify on demand) and the warnings on verified data
  (:mod:`captures.verification`).
* **Latency** from the RVE's send to the OBU's decision (the end of the tick that used the
  message), from the two processes' wall clocks on one machine: of the received messages
  only, each from its first copy (a copy replayed seconds later is no latency).
* **The capture**: the OBU's segments (``obu run --capture-max-mb``) and those the cap
  deleted (their ticks are missing: an incomplete run), and the files that end in a torn
  tail, with the byte offset where their whole part ends (also one line on stderr).

Memory: every file is read as a stream (:class:`hil.capture.Capture`); what is kept grows
with the run's real RVs and messages (a float64 (t, x, y) per row of a real RV, the
message keys and send times of the RVE's schedule, a tick time per tick), not with what
else the OBU heard or tracked: a storm of spoofed ids adds one entry per id.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from array import array
from collections import Counter
from pathlib import Path

import numpy as np

from captures.verification import lines as verification_lines
from captures.verification import verification
from catc.apps.verdict import KEYS, Confusion, by_app
from catc.bsm import MINUTE_MS, sec_mark
from catc.geo import EnuFrame
from hil.capture import Capture, TrackBlock, clock_offset, read_capture, torn_line
from hil.capture.schema import hex_id, received_key, scheduled_key
from hil.datasets import load_table

HELP = """\
Score a capture directory written by `rve run --capture DIR` and `obu run --capture DIR`:
PTE95 overall and per RV, the accuracy of each warning (FCW, EEBL, BSW, LCW) with
TP/TN/FP/FN against the application on the true states, vehicle by vehicle (a warning on
the wrong vehicle is an FP on it and an FN on the right one), messages sent / dropped /
received, decode errors, latency from send to decision, and the warning events.  --json
prints the same as one JSON object.

Coverage: the OBU's ticks against every host frame the replay has, the gaps, and how each
daemon ended (rve.end.json, obu.end.json: clean, signal, error; none when killed).  A run
the OBU did not tick whole is incomplete: every figure says its coverage, and the exit
status is 3 unless --partial."""


#: The tick period (ms): a message decided later than this after it was sent is late.
TICK_MS = 100.0

#: The exit status of ``captures score`` on an incomplete run (without ``--partial``).
INCOMPLETE = 3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("score", help="PTE, FCW accuracy and counts of an RVE + OBU capture",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", type=Path, metavar="DIR", help="the shared capture directory")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--partial", action="store_true",
                   help=f"exit 0 on an incomplete run too (without it: exit {INCOMPLETE})")
    p.set_defaults(func=run)


def _ground_truth(rve_cfg: dict) -> dict[float, dict[str, frozenset[str]]]:
    """Tick time -> {app: the RV ids (hex) it warns on}, on the true states (PER 0,
    10 Hz, no latency)."""
    s = rve_cfg["settings"]
    return _ground_truth_of(s["dataset"], s.get("trip"), s.get("host"), s.get("idm_host"),
                            s.get("duration"))


@functools.lru_cache(maxsize=8)  # captures of one run scored again (a replay, a sweep)
def _ground_truth_of(dataset: str, trip, host, idm_host, duration
                     ) -> dict[float, dict[str, frozenset[str]]]:
    from catc.apps import SafetyApps
    from catc.cam import CamConfig, ContextAwareMap
    from catc.channel import ChannelConfig
    from catc.hostsim import with_synthetic_host
    from catc.replay import plan, simulate

    table = load_table(dataset, trip)
    if idm_host:
        table = with_synthetic_host(table, idm_host, vehicle_id="idm-host")
        host = "idm-host"
    the_plan = plan(table, ChannelConfig(), 0, host, duration)
    cam = ContextAwareMap(CamConfig(predictor="ca"), SafetyApps())
    return {round(snap.t, 3): {a: frozenset(v) for a, v in by_app(
                (w.app, hex_id(w.rv_id)) for w in snap.warnings).items()}
            for snap in simulate(the_plan, cam)}


def _truth_tracks(cap: Capture, origin) -> dict[str, tuple[np.ndarray, np.ndarray,
                                                             np.ndarray]]:
    """The RVE's truth in the OBU's ENU frame, ``id -> (t, x, y)``, read as a stream (as
    :func:`hil.capture.truth_in_frame` computes it, without keeping the records)."""
    frame = EnuFrame(*origin)
    cols: dict[str, tuple[array, array, array]] = {}
    for r in cap.iter_truth():
        c = cols.get(r["id"])
        if c is None:
            c = cols[r["id"]] = (array("d"), array("d"), array("d"))
        c[0].append(r["t"])
        c[1].append(r["lat"])
        c[2].append(r["lon"])
    out = {}
    for tid, (t, lat, lon) in cols.items():
        x, y, _ = frame.to_enu(np.array(lat), np.array(lon), 0.0)
        out[tid] = (np.array(t), np.atleast_1d(x), np.atleast_1d(y))
    return out


class _Pte:
    """PTE samples per RV as the track blocks stream by: each row of a vehicle of the run
    within its truth's span kept as (t, x, y) in float64 arrays (24 octets a row of a
    real RV; of the other ids, phantoms, only each one's first and last tick), the errors
    computed at the end, RV by RV in the order of their first row, so the percentiles
    and the mean are those of one pass over the rows."""

    def __init__(self, truth_xy: dict, host_tid: str | None, offset: float) -> None:
        self.truth_xy = truth_xy
        self.offset = offset
        real = [tid for tid in truth_xy if tid != host_tid]
        self.real = np.array([int(tid, 16) for tid in real], dtype=np.uint32)
        self.span = {int(tid, 16): (truth_xy[tid][0][0] - 1e-6, truth_xy[tid][0][-1] + 1e-6)
                     for tid in real}
        self.rows: dict[int, tuple[array, array, array]] = {}
        self.first: dict[int, float] = {}  # phantom id -> first and last tick time
        self.last: dict[int, float] = {}

    def add(self, block: TrackBlock) -> None:
        ids = block.cols["id"]
        mine = np.isin(ids, self.real)
        if mine.any():
            xs, ys = block.cols["x"], block.cols["y"]
            td = block.t - self.offset
            for i in np.flatnonzero(mine).tolist():
                tid = int(ids[i])
                lo, hi = self.span[tid]
                if td < lo or td > hi:
                    continue
                r = self.rows.get(tid)
                if r is None:
                    r = self.rows[tid] = (array("d"), array("d"), array("d"))
                r[0].append(td)
                r[1].append(float(xs[i]))
                r[2].append(float(ys[i]))
        if not mine.all():
            other = ids[~mine].tolist()
            self.first.update(dict.fromkeys(set(other).difference(self.first), block.t))
            self.last.update(dict.fromkeys(other, block.t))

    def errors(self) -> dict[str, np.ndarray]:
        out = {}
        for tid, (rt, rx, ry) in self.rows.items():
            hexid = hex_id(tid)
            t, x, y = self.truth_xy[hexid]
            td = np.array(rt)
            out[hexid] = np.hypot(np.array(rx) - np.interp(td, t, x),
                                  np.array(ry) - np.interp(td, t, y))
        return out


def _frames(cap: Capture, names: dict[str, str], sent: dict) -> dict:
    """Every frame of ``obu.rx`` counted once, by what it was (one pass): ``received``,
    the first accepted copy of a message the RVE sent as an RV (its key among the
    schedule's), with its latency from send to decision; ``duplicate`` a later copy of
    one; ``unmatched`` an accepted frame of a vehicle of the run that the RVE never sent
    as an RV message (a copy with its count or secMark flipped, the host's own frame
    heard on the RV channel); ``phantom`` an accepted frame of an id the RVE never sent;
    ``garbage`` (decode errors, by reason), ``rejected``, ``quarantined``, ``unticked``,
    ``withheld`` (urgent frames the OBU held back unverified: ``obu run --verify-urgent``),
    ``shed`` (frames an OBU behind real time dropped unread: ``--shed-after``).
    The RV channel's frames are the sum of these; ``host_errors`` counts the host
    channel's decode errors, ``host_refused`` its frames the OBU did not believe, by
    reason (:class:`obu.host.HostGate`)."""
    counts = dict.fromkeys(("received", "duplicate", "unmatched", "phantom", "rejected",
                            "quarantined", "unticked", "withheld", "shed"), 0)
    garbage: Counter = Counter()
    security: Counter = Counter()
    host_errors = 0
    host_refused: Counter = Counter()  # host frames the host gate did not believe
    seen: set = set()
    latency = array("d")
    for r in cap.iter_rx():
        status = r.get("status")
        if r.get("verdict"):
            security[r["verdict"]] += 1
        if r.get("channel") != "rv":
            if (status or "").startswith("host_"):
                host_refused[status[5:]] += 1
            elif status not in _STATUSES:
                garbage[status] += 1
                host_errors += 1
            continue
        if status != "ok":
            if status in counts:
                counts[status] += 1
            else:
                garbage[status] += 1
            continue
        key = received_key(r)
        if key in sent:
            if key in seen:
                counts["duplicate"] += 1
            else:
                seen.add(key)
                counts["received"] += 1
                latency.append(r["decided_unix"] - sent[key])
        elif r.get("id") in names:
            counts["unmatched"] += 1
        else:
            counts["phantom"] += 1
    return {**counts, "garbage": dict(garbage), "host_errors": host_errors,
            "host_refused": dict(host_refused),
            "security": dict(security), "latency_s": np.array(latency)}


#: The statuses of an rx record that are not a decode error.
_STATUSES = ("ok", "rejected", "quarantined", "unticked", "withheld", "shed")


def score(directory: Path) -> dict:
    """Every score of a capture directory (see the module docstring), reading each file
    as a stream: memory for the run's real RVs and messages, not for the capture."""
    cap = read_capture(directory)
    rve_cfg, obu_cfg = cap.rve_config, cap.obu_config
    names = {tid: v for v, tid in rve_cfg["vehicles"].items()}
    host_tid = rve_cfg["vehicles"].get(rve_cfg.get("host"))
    real = set(names) - {host_tid}
    offset = clock_offset(cap.iter_truth(), cap.iter_ticks(), directory)
    truth_xy = _truth_tracks(cap, obu_cfg["origin"])

    pte = _Pte(truth_xy, host_tid, offset)
    for block in cap.iter_track_blocks():
        pte.add(block)
    per_rv = pte.errors()
    all_pte = np.concatenate(list(per_rv.values())) if per_rv else np.array([])

    # the warnings against the ground truth, vehicle by vehicle (catc.apps.verdict)
    gt = _ground_truth(rve_cfg)
    confusion = Confusion()
    seen_t: set[float] = set()
    n_ticks = phantom_warning_ticks = 0
    for tk in cap.iter_ticks():
        n_ticks += 1
        seen_t.add(round(tk["t"], 3))
        if any(w[1] not in real for w in tk["warnings"]):
            phantom_warning_ticks += 1
        truth_warn = gt.get(round(tk["t"], 3))  # both on the host's secMark clock
        if truth_warn is None:
            continue
        confusion.add(truth_warn, by_app((w[0], w[1]) for w in tk["warnings"]))
    apps = confusion.as_dict()
    whole = coverage(set(gt), seen_t, cap.rve_end, cap.obu_end)

    # the RVE's RV messages (an attack's own frames apart) and what the OBU made of them
    n_rv = 0
    sent: dict = {}  # message key -> send time, for the join with obu.rx
    for r in cap.iter_schedule():
        if r["channel"] == "rv" and r.get("cause") != "attack":
            n_rv += 1
            if not r["dropped"]:
                sent[scheduled_key(r)] = r["sent_unix"]
    frames = _frames(cap, names, sent)
    lat_ms = frames.pop("latency_s") * 1000.0
    garbage, security = frames["garbage"], frames.pop("security")
    events = cap.events
    attacks = _attacks(cap, names)
    mbr = cap.mbr
    missing = cap.missing_segments()
    result = {
        "pte95_m": round(float(np.percentile(all_pte, 95)), 4) if len(all_pte) else None,
        "pte_mean_m": round(float(all_pte.mean()), 4) if len(all_pte) else None,
        "pte95_per_rv": {names.get(k, k): round(float(np.percentile(v, 95)), 4)
                         for k, v in sorted(per_rv.items())},
        "fcw_accuracy": apps["fcw"]["accuracy"],
        "fcw": {k: apps["fcw"][k] for k in KEYS},
        "apps": apps,
        # received: the RVE's own RV messages the OBU took, each once (<= sent); the
        # other frames are counted apart in "frames"
        "sent": len(sent), "dropped": n_rv - len(sent), "received": frames["received"],
        "decode_errors": garbage,
        "security": security,
        "verification": verification(cap),  # and the warnings on verified data only
        "rejected": frames["rejected"],
        # received after the run's last host frame: never stepped
        "unticked": frames["unticked"],
        "frames": frames,
        "latency_ms": {"p50": round(float(np.percentile(lat_ms, 50)), 3),
                       "p99": round(float(np.percentile(lat_ms, 99)), 3),
                       "max": round(float(lat_ms.max()), 3)} if len(lat_ms) else None,
        # the OBU fell behind: decisions over a tick period after the message was sent
        "late": _late(lat_ms),
        "warnings": dict(Counter(f"{e['app']}" for e in events if e["kind"] == "start")),
        "events": events,
        # accepted frames of ids the RVE never sent
        "phantom_received": frames["phantom"],
        "phantom": _phantoms(pte.first, pte.last, events, phantom_warning_ticks, real),
        "attacks": attacks,
        "mbd": _detection(attacks, cap, names, mbr) if attacks and mbr is not None
        else None,
        "ticks": n_ticks, "run": whole, "complete": whole["coverage"] == 1.0,
        "capture": {"segments": len(cap.segments()), "segments_deleted": missing,
                    "torn": [{"file": p.name, "offset": off, "why": why}
                             for p, off, why in cap.torn]},
        "predictor": obu_cfg["settings"].get("predictor"),
        "per": rve_cfg["channel"]["per"], "rate_hz": rve_cfg["channel"]["rate_hz"],
        "dataset": rve_cfg["dataset"]["name"],
    }
    return result


def _late(lat_ms: np.ndarray) -> dict:
    """The messages decided over a tick period after they were sent, and whether the
    run lagged (latency p99 over the tick period)."""
    late = lat_ms > TICK_MS
    return {"messages": int(late.sum()),
            "share": round(float(late.mean()), 4) if len(lat_ms) else 0.0,
            "lagging": bool(len(lat_ms) and np.percentile(lat_ms, 99) > TICK_MS)}


def _phantoms(first: dict[int, float], last: dict[int, float], events: list[dict],
              warning_ticks: int, real: set[str]) -> dict:
    """Tracks the OBU classified whose id no remote vehicle of the run sent (corrupted
    copies, the host's own id, attackers): how many, how long each lived (s, first to
    last tick it was in the snapshot), and the warnings they raised (events, and ticks
    with a warning condition on them)."""
    life = sorted(round(last[k] - first[k], 3) for k in first)
    fake_events = [e for e in events if e["kind"] == "start" and e["rv"] not in real]
    return {"tracks": len(first), "ids": sorted(hex_id(k) for k in first)[:50],
            "lifetime_s": {"max": life[-1], "median": life[len(life) // 2]} if life else None,
            "warnings": len(fake_events),
            "warning_apps": dict(Counter(e["app"] for e in fake_events)),
            "warning_ticks": warning_ticks}


def _attacks(cap: Capture, names: dict[str, str]) -> dict[str, dict]:
    """Per attack kind (``rve run --attack``): the frames the RVE sent for it, what the
    OBU accepted (tracked), rejected (by verdict) and quarantined, and the warnings raised
    on the ids it fabricated (every one a false alarm: those vehicles do not exist)."""
    kind_of: dict[tuple, str] = {}  # message key -> kind, for the rx join
    fabricated: dict[str, str] = {}
    out: dict[str, dict] = {}
    for r in cap.iter_schedule():
        kind = r.get("attack")
        if kind is None:
            continue
        a = out.setdefault(kind, {"sent": 0, "accepted": 0, "rejected": {}, "warnings": {}})
        a["sent"] += not r["dropped"]
        if r["id"] not in names:
            fabricated[r["id"]] = kind
        else:
            kind_of[scheduled_key(r)] = kind
    if not out:
        return {}
    seen: set[tuple] = set()
    for r in cap.iter_rx():
        if r.get("channel") != "rv" or "id" not in r:
            continue
        kind = fabricated.get(r["id"]) or kind_of.get(received_key(r))
        if kind is None:
            continue
        if r.get("status") == "quarantined":
            out[kind]["quarantined"] = out[kind].get("quarantined", 0) + 1
        elif r.get("status") == "ok":
            key = received_key(r)
            if kind == "replay" and key not in seen:  # the original, not the replay
                seen.add(key)
                continue
            out[kind]["accepted"] += 1
        elif r.get("status") == "rejected":
            rej = out[kind]["rejected"]
            rej[r["verdict"]] = rej.get(r["verdict"], 0) + 1
    for e in cap.events:
        kind = fabricated.get(e["rv"])
        if kind is not None and e["kind"] == "start":
            w = out[kind]["warnings"]
            w[e["app"]] = w.get(e["app"], 0) + 1
    return out


def _detection(out: dict, cap: Capture, names: dict[str, str], mbr: list[dict]) -> dict:
    """Misbehavior detection against the attacks' ground truth: per attack kind (added to
    ``out``), precision and recall over the attacking ids whose frames passed verification
    (the rest never reach the checks; an id is detected when a report names it as the
    suspect, and precision counts the reports' other suspects against it) and the time
    from the attacker's first frame to the message that raised its first report (dataset
    seconds).  Returns the summary: suspects, false suspects, reports."""
    passed = {r.get("id") for r in cap.iter_rx() if r.get("status") in ("ok", "quarantined")}
    attackers = {r["id"]: r["attack"] for r in cap.iter_schedule()  # id -> kind; fabricated
                 if r.get("attack") and r["id"] not in names}  # first
    first_sent: dict[str, float] = {}  # id -> dataset time of its first attack frame
    for r in cap.iter_schedule():
        if r.get("attack") in out and "sent_unix" in r:
            if r["attack"] in ("offset", "speed"):  # a real id misbehaving; a replay's
                attackers.setdefault(r["id"], r["attack"])  # vehicle is its victim
            if r["id"] in attackers and attackers[r["id"]] == r["attack"]:
                first_sent.setdefault(r["id"], r["t"])
    # the first report on each suspect, as the secMark of the message that raised it
    first_report: dict[str, int] = {}
    for m in mbr:
        if m["check"] != "id-conflict":  # that one names the signer, not the id's holder
            first_report.setdefault(m["suspect"], m["sec_mark"])
    false_suspects = sorted(set(first_report) - set(attackers))
    for kind, a in out.items():
        ids = [i for i, k in attackers.items()
               if k == kind and i in first_sent and i in passed]
        if not ids:
            continue
        hit = [i for i in ids if i in first_report]
        a["detection"] = {
            "attackers": len(ids), "detected": len(hit),
            "recall": round(len(hit) / len(ids), 4),
            "precision": round(len(hit) / (len(hit) + len(false_suspects)), 4) if hit else None,
            # dataset seconds from the attacker's first frame to the message that got it
            # reported (secMarks wrap each minute)
            "time_to_detect_s": {
                i: round(((first_report[i] - sec_mark(first_sent[i])) % MINUTE_MS) / 1000, 3)
                for i in hit},
        }
    return {"suspects": len(first_report), "false_suspects": false_suspects,
            "reports": len(mbr)}


def ending(end: dict | None) -> str:
    """How a daemon's run ended, in words, from its end record (None: killed)."""
    if end is None:
        return "no end record (killed, or still running)"
    return end["exit"] + (f" ({end['reason']})" if end.get("reason") else "")


def coverage(expected: set[float], seen: set[float], rve_end: dict | None,
             obu_end: dict | None) -> dict:
    """How whole the run is: the OBU's ticks (``seen``: their times, rounded to the ms)
    against every host frame of the replay (``expected``: their times on the host's
    secMark clock), the gaps (runs of missing consecutive ticks, ``[first, last]`` tick
    time), and how each daemon ended."""
    gaps: list[list[float]] = []
    for t in sorted(expected - seen):
        if gaps and t - gaps[-1][1] <= 0.1 + 1e-6:
            gaps[-1][1] = t
        else:
            gaps.append([t, t])
    longest = max((round(b - a + 0.1, 3) for a, b in gaps), default=0.0)
    n = len(expected)
    return {"expected_ticks": n, "ticks": len(expected & seen),
            "coverage": round(len(expected & seen) / n, 4) if n else 0.0,
            "gaps": len(gaps), "longest_gap_s": longest, "first_gaps": gaps[:5],
            "rve": ending(rve_end), "obu": ending(obu_end)}


def table(r: dict) -> str:
    f, run = r["fcw"], r["run"]
    # beside every figure of an incomplete run: how much of the run it is
    part = "" if r["complete"] else f"  [coverage {100 * run['coverage']:.1f} %]"
    lines = [
        f"run: {r['dataset']}, predictor {r['predictor']}, PER {100 * r['per']:g} %, "
        f"{r['rate_hz']:g} Hz, {r['ticks']} OBU ticks",
        f"coverage: {run['ticks']} of {run['expected_ticks']} host ticks "
        f"({100 * run['coverage']:.1f} %), {run['gaps']} gaps (longest "
        f"{run['longest_gap_s']} s); RVE ended: {run['rve']}; OBU ended: {run['obu']}",
        f"messages: sent {r['sent']}, dropped by the channel {r['dropped']}, "
        f"received {r['received']}, decode errors {sum(r['decode_errors'].values())}",
        "other frames at the RV port: " + ", ".join(
            f"{k} {r['frames'][k]}" for k in ("duplicate", "unmatched", "phantom", "rejected",
                                              "quarantined", "unticked", "withheld",
                                              "shed")),
        f"PTE95 {r['pte95_m']} m (mean {r['pte_mean_m']} m){part}",
        f"FCW accuracy {r['fcw_accuracy']}  (TP {f['tp']}, TN {f['tn']}, FP {f['fp']}, "
        f"FN {f['fn']}; by vehicle){part}",
    ]
    if not r["complete"]:
        lines.insert(0, f"INCOMPLETE RUN: the OBU ticked {run['ticks']} of the replay's "
                        f"{run['expected_ticks']} host frames; every figure below covers "
                        "only those ticks")
    others = [f"{app.upper()} {c['accuracy']} ({c['tp']}/{c['tn']}/{c['fp']}/{c['fn']})"
              for app, c in r["apps"].items() if app != "fcw"]
    lines.append("other warnings, accuracy (TP/TN/FP/FN): " + ", ".join(others) + part)
    if r.get("security"):
        sec = r["security"]
        lines.append(f"IEEE 1609.2: verified {sec.get('ok', 0)}, rejected {r['rejected']}"
                     + "".join(f", {k} {v}" for k, v in sorted(sec.items()) if k != "ok"))
    lines += verification_lines(r.get("verification"))
    if r["latency_ms"]:
        lat, late = r["latency_ms"], r["late"]
        lines.append(f"latency send -> decision: p50 {lat['p50']} ms, p99 {lat['p99']} ms, "
                     f"max {lat['max']} ms")
        if late["lagging"]:
            lines.insert(0, f"LAGGING: {100 * late['share']:.1f} % of the messages were "
                            f"decided over a tick period ({TICK_MS:g} ms) after they were "
                            f"sent (p99 {lat['p99']} ms): the OBU fell behind real time")
    if r["frames"]["host_refused"]:
        lines.append("host frames not believed: " + ", ".join(
            f"{k} {v}" for k, v in sorted(r["frames"]["host_refused"].items())))
    for kind, a in r.get("attacks", {}).items():
        if "detection" in a:
            d = a["detection"]
            ttd = list(d["time_to_detect_s"].values())
            lines.append(f"attack {kind}: detected {d['detected']}/{d['attackers']} ids "
                         f"(recall {d['recall']}, precision {d['precision']})"
                         + (f", time to detect {min(ttd):.2f}-{max(ttd):.2f} s" if ttd else ""))
        lines.append(f"attack {kind}: sent {a['sent']}, accepted {a['accepted']}, rejected "
                     f"{sum(a['rejected'].values())}"
                     + "".join(f" ({k} {v})" for k, v in sorted(a["rejected"].items()))
                     + ", warnings on fabricated ids: "
                     + (", ".join(f"{k} {v}" for k, v in sorted(a["warnings"].items()))
                        or "none"))
    ph = r.get("phantom")
    if ph and ph["tracks"]:
        lines.append(f"phantom tracks (ids no RV of the run sent): {ph['tracks']}, lived up "
                     f"to {ph['lifetime_s']['max']} s, warning events {ph['warnings']}, "
                     f"warning ticks {ph['warning_ticks']}")
    lines.append("warning events: " + (", ".join(f"{k} {v}" for k, v in
                                                 sorted(r["warnings"].items())) or "none"))
    lines.append("PTE95 per RV [m]: " + ", ".join(f"{k} {v}" for k, v in
                                                   r["pte95_per_rv"].items()) + part)
    c = r["capture"]
    if c["segments_deleted"]:
        lines.append(f"capture: {c['segments']} segments kept, "
                     f"{len(c['segments_deleted'])} deleted by the cap (--capture-max-mb: "
                     f"{_ranges(c['segments_deleted'])}); their ticks count as missing")
    for t in c["torn"]:
        lines.append(f"capture: {t['file']} torn at byte {t['offset']} ({t['why']}); "
                     "scored up to there")
    return "\n".join(lines)


def _ranges(ks: list[int]) -> str:
    """``[1, 2, 3, 7]`` as ``1-3, 7``."""
    out: list[list[int]] = []
    for k in ks:
        if out and k == out[-1][1] + 1:
            out[-1][1] = k
        else:
            out.append([k, k])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in out)


def run(args: argparse.Namespace) -> int:
    try:
        result = score(args.dir)
    except (ValueError, KeyError) as err:  # CaptureError and DatasetError included
        print(f"captures score: {err}", file=sys.stderr)
        return 2
    torn = torn_line([(args.dir / t["file"], t["offset"], t["why"])
                      for t in result["capture"]["torn"]], "captures score")
    if torn:
        print(torn, file=sys.stderr)
    if args.json:
        print(json.dumps(result))
    else:
        print(table(result))
    if not result["complete"] and not args.partial:
        cov = result["run"]
        print(f"captures score: {args.dir}: incomplete run, coverage "
              f"{100 * cov['coverage']:.1f} % ({cov['ticks']} of {cov['expected_ticks']} "
              f"ticks; OBU ended: {cov['obu']}); --partial accepts it", file=sys.stderr)
        return INCOMPLETE
    return 0
