"""Live spot checks: a sweep cell through the real daemons, next to the offline simulator.

``obu run`` and ``rve run`` start as two processes talking UDP on 127.0.0.1 (ports from
the OS), the RVE replays one trip at a chosen PER and rate, and ``captures score`` scores
the shared capture.  The same trip, cell, seed and predictor go through the offline
CA-TC (:func:`catc.sweep.cam_run`, values through UPER as on the wire, in the live OBU's
ENU frame).  With zero latency the two must agree (the OBU's tick rule is the
simulator's): the same ticks and tracks, every estimated position within 1e-6 m (the
precision ``obu.tracks.jsonl`` keeps is 1e-7 m), and the scores with them.  A difference
is a bug, and the report shows both.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import TextIO

import numpy as np

from catc.mobility import MobilityTable
from catc.sweep import Cell, cam_run
from hil.capture import read_capture
from hil.transport.udp import free_ports, wait_bound

#: How far a live track position may be from the offline one (m): round-off only.
POSITION_TOL_M = 1e-6


def vehicle_flags(capture: Path, speed: float, gnss_delay: float = 0.1
                  ) -> tuple[list[str], list[str]]:
    """The ``rve run`` and ``obu run`` flags that put the host on the vehicle side: the
    RVE plays the car's serial CAN adapter (slcan on a pty beside ``capture``) and sends
    NMEA by UDP to 127.0.0.1; the OBU reads both at ``--time-scale speed``.  Loopback
    and a pty only: no root, no network namespace."""
    pty = str(capture.parent / f"{capture.name}.can")
    (gnss,) = free_ports(1)
    rve = ["--host-bus", "--host-can-interface", "slcan", "--host-can-channel", pty,
           "--nmea", f"udp:127.0.0.1:{gnss}", "--gnss-latency", str(gnss_delay * 1000.0)]
    obu = ["--host-source", "vehicle", "--vehicle-can-interface", "slcan",
           "--vehicle-can-channel", pty, "--gnss", f"udp:127.0.0.1:{gnss}",
           "--gnss-delay", str(gnss_delay), "--time-scale", str(speed)]
    return rve, obu


class LiveError(RuntimeError):
    """A daemon failed; ``str()`` is one line with its exit status and last error line."""


def run_daemons(capture: Path, rve_flags: list[str], obu_flags: list[str],
                timeout: float = 600.0) -> str:
    """Start ``obu run`` (listening on two free loopback ports), then ``rve run`` sending
    to them, both writing into ``capture``; wait for both.  Returns the OBU's stdout (its
    warning events as JSON lines)."""
    ports = free_ports()
    py = sys.executable
    obu = subprocess.Popen(
        [py, "-m", "obu.cli", "run", "--listen", f"127.0.0.1:{ports[0]}", "--host-listen",
         f"127.0.0.1:{ports[1]}", "--capture", str(capture), "--idle-exit", "2",
         "--no-progress", *obu_flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    try:
        wait_bound(ports, alive=lambda: obu.poll() is None)
        if obu.poll() is not None:
            raise LiveError("the OBU did not start: " + obu.communicate()[1].strip())
        rve = subprocess.run(
            [py, "-m", "rve.cli", "run", "--to", f"127.0.0.1:{ports[0]}", "--host-to",
             f"127.0.0.1:{ports[1]}", "--capture", str(capture), "--no-progress",
             *rve_flags], capture_output=True, text=True,
            timeout=timeout)
        out, err = obu.communicate(timeout=120)
    finally:
        if obu.poll() is None:
            obu.kill()
            obu.wait()
    if rve.returncode or obu.returncode:
        last = (rve.stderr.strip() or err.strip()).splitlines()[-1:] or [""]
        raise LiveError(f"rve exit {rve.returncode}, obu exit {obu.returncode}: {last[0]}")
    return out


def live_checks(spec: str, table: MobilityTable, predictor: str, cells: list[Cell], *,
                seed: int = 0, speed: float = 8.0, keep: Path | None = None,
                progress: TextIO | None = None) -> list[dict]:
    """Each cell live and offline on ``table`` (a trip of dataset ``spec``); one dict a
    cell with both scores and their differences."""
    from captures.score import score

    out = []
    root = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="catc-live-"))
    try:
        for cell in cells:
            cap = root / f"per{100 * cell.per:g}_rate{cell.rate_hz:g}"
            if cap.exists():
                shutil.rmtree(cap)
            if progress:
                print(f"live: {cell.label}, {predictor}, trip {table.name} ...", file=progress,
                      flush=True)
            run_daemons(cap, ["--dataset", spec, "--trip", table.name, "--per",
                              f"{100 * cell.per:g}", "--rate", f"{cell.rate_hz:g}",
                              "--burst", f"{cell.burst:g}", "--seed", str(seed), "--speed",
                              f"{speed:g}"], ["--predictor", predictor])
            live = score(cap)
            captured = read_capture(cap, rx=False)
            positions: dict[tuple[float, int], tuple[float, float]] = {}
            off = cam_run(table, predictor, cell, seed, wire=True, positions=positions,
                          origin=tuple(captured.obu_config["origin"]))
            pte95 = float(np.percentile(off.pte, 95)) if len(off.pte) else None
            total = sum(off.fcw.values())
            acc = (off.fcw["tp"] + off.fcw["tn"]) / total if total else None
            row = {"trip": table.name, "predictor": predictor, "per": 100 * cell.per,
                   "rate": cell.rate_hz, "seed": seed,
                   "live": {"pte95_m": live["pte95_m"], "fcw_accuracy": live["fcw_accuracy"],
                            "fcw": live["fcw"], "sent": live["sent"],
                            "dropped": live["dropped"], "received": live["received"],
                            "ticks": live["ticks"]},
                   "offline": {"pte95_m": None if pte95 is None else round(pte95, 4),
                               "fcw_accuracy": None if acc is None else round(acc, 4),
                               "fcw": off.fcw, "sent": off.sent, "dropped": off.dropped,
                               "ticks": off.ticks}}
            row["agree"] = agreement(row["live"], row["offline"],
                                     track_differences(captured.tracks, positions))
            if keep is not None:
                row["capture"] = str(cap)
            out.append(row)
    finally:
        if keep is None:
            shutil.rmtree(root, ignore_errors=True)
    return out


def track_differences(live_tracks: list[dict],
                      offline: dict[tuple[float, int], tuple[float, float]]) -> dict:
    """The live OBU's per-tick track positions (``obu.tracks.jsonl`` rows) against the
    offline ones (``cam_run``'s ``positions``), keyed by tick time (1 ms) and RV: how many
    (tick, RV) pairs both have, how many only one has, and the largest absolute difference
    of x or y over the common ones (m; None when there are none)."""
    live = {(round(r["t"], 3), int(r["id"], 16)): (r["x"], r["y"]) for r in live_tracks}
    common = live.keys() & offline.keys()
    diff = max((abs(a - b) for k in common for a, b in zip(live[k], offline[k], strict=True)),
               default=None)
    return {"compared": len(common), "live_only": len(live.keys() - common),
            "offline_only": len(offline.keys() - common),
            "max_abs_diff_m": None if diff is None else float(diff)}


def agreement(live: dict, offline: dict, tracks: dict | None = None,
              pte_tol_m: float = 1e-4, fcw_tol: float = 1e-4,
              pos_tol_m: float = POSITION_TOL_M) -> dict:
    """Differences live − offline and whether they agree: the channel's counts equal,
    PTE95 within ``pte_tol_m``, FCW accuracy within ``fcw_tol`` (both scores are rounded
    to 4 decimals: one unit of the last) and, with ``tracks`` (:func:`track_differences`),
    the same (tick, RV) pairs with every position within ``pos_tol_m``.  The defaults ask
    for round-off only: a live run at zero latency steps the same frames at the same
    ticks as the offline one."""
    d_pte = (None if live["pte95_m"] is None or offline["pte95_m"] is None
             else round(live["pte95_m"] - offline["pte95_m"], 7))
    d_fcw = (None if live["fcw_accuracy"] is None or offline["fcw_accuracy"] is None
             else round(live["fcw_accuracy"] - offline["fcw_accuracy"], 7))
    counts = live["sent"] == offline["sent"] and live["dropped"] == offline["dropped"]
    ok = counts and d_pte is not None and abs(d_pte) <= pte_tol_m \
        and (d_fcw is None or abs(d_fcw) <= fcw_tol)
    out = {"pte95_m": d_pte, "fcw_accuracy": d_fcw, "counts_equal": counts}
    if tracks is not None:
        ok = ok and tracks["compared"] > 0 and not tracks["live_only"] \
            and not tracks["offline_only"] and tracks["max_abs_diff_m"] <= pos_tol_m
        out["tracks"] = tracks
    return dict(out, ok=bool(ok))


#: The OBU's defences an attack cell runs against: flags of ``obu run``.
DEFENCES = {"none": [], "enforce": ["--verify", "enforce"],
            "enforce+mbd": ["--verify", "enforce", "--mbd"],
            # enforce's policy is on demand (obu run --verify-policy); this one verifies
            # every frame on arrival, the reference of issue 30's security table
            "enforce-all": ["--verify", "enforce", "--verify-policy", "all"]}
#: The defences a sweep runs when none are named.
DEFAULT_DEFENCES = ("none", "enforce", "enforce+mbd")


def attack_checks(spec: str, table: MobilityTable, predictor: str, attacks: list[str],
                  pers: list[float], *, defences: list[str] | None = None, speed: float = 8.0,
                  seed: int = 0, duration: float | None = None,
                  progress: TextIO | None = None) -> list[dict]:
    """Each attack (``rve run --attack`` text) × PER × defence, live: the RVE signs with a
    fresh test PKI (one pseudonym per RV and one for an insider), the OBU runs with the
    defence's flags; one row per run with the FCW false alarms and missed warnings (FP and
    FN ticks against the ground truth), what the OBU accepted, rejected and quarantined of
    the attack's frames, and detection recall, precision and time to detect.  Against the
    clean twin (the same run without the attack, run once per PER and defence,
    :func:`captures.defence.compare`, the whole of it in ``vs_clean``): the TP ticks lost
    by app, the warning ticks on fabricated ids and the ones on the attack's named
    vehicles the clean run did not have, the honest vehicles suspected and quarantined,
    and precision and recall in which a flagged victim is a false positive.
    ``duration``: only the first S s of the trip (``rve run --duration``)."""
    from captures.defence import compare
    from captures.score import score
    from hil.pki import init

    defences = list(DEFAULT_DEFENCES) if defences is None else defences
    rows = []
    root = Path(tempfile.mkdtemp(prefix="catc-attack-"))
    twins: dict[tuple[float, str], Path] = {}

    def daemons(cap: Path, per: float, defence: str, *attack: str) -> None:
        # the clean twin signs in the sending loop, as an attacked run must (rve.signahead
        # does not sign attacks ahead): signed ahead, a twin that falls behind sends its
        # frames with their scheduled generationTime, and a verifying OBU rejects those
        # over 2 s late as stale (1,000 RVs beside the OBU on 2 cores); signed inline,
        # both runs slow down alike and stay comparable
        run_daemons(cap, ["--dataset", spec, "--trip", table.name, "--per", f"{per:g}",
                          "--seed", str(seed), "--speed", f"{speed:g}", "--sign",
                          str(root / "pki"), "--sign-workers", "0", *attack,
                          *([] if duration is None else ["--duration", f"{duration:g}"])],
                    ["--predictor", predictor, "--trust", str(root / "pki"),
                     *DEFENCES[defence]])

    try:
        init(root / "pki", max(2, len(table.tracks) + 1), 1.0, seed=f"sweep-{seed}")
        for k, attack in enumerate(attacks):
            kind = attack.partition(":")[0]
            for per in pers:
                for defence in defences:
                    clean = twins.get((per, defence))
                    if clean is None:
                        clean = twins[per, defence] = root / f"clean-{per:g}-{defence}"
                        if progress:
                            print(f"attack: clean twin, PER {per:g} %, defence {defence}, "
                                  f"trip {table.name} ...", file=progress, flush=True)
                        daemons(clean, per, defence)
                    cap = root / f"{k}-{kind}-{per:g}-{defence}"  # a new directory a run
                    if progress:
                        print(f"attack: {attack}, PER {per:g} %, defence {defence}, trip "
                              f"{table.name} ...", file=progress, flush=True)
                    daemons(cap, per, defence, "--attack", attack)
                    s = score(cap)
                    vs = compare(clean, cap)
                    det = vs["detection"] or {}
                    warned = vs["attack_warnings"]
                    a = s["attacks"].get(kind, {})
                    d = a.get("detection", {})
                    ttd = list(d.get("time_to_detect_s", {}).values())
                    rows.append({
                        "attack": attack, "kind": kind, "per": per, "defence": defence,
                        "trip": table.name, "predictor": predictor,
                        "fcw_accuracy": s["fcw_accuracy"], "false_alarms": s["fcw"]["fp"],
                        "missed": s["fcw"]["fn"], "sent": a.get("sent", 0),
                        "accepted": a.get("accepted", 0),
                        "rejected": sum(a.get("rejected", {}).values()),
                        "quarantined": a.get("quarantined", 0),
                        "warnings_on_fabricated": a.get("warnings", {}),
                        "recall": d.get("recall"), "precision": d.get("precision"),
                        "time_to_detect_s": max(ttd) if ttd else None,
                        "pte95_m": s["pte95_m"],
                        # issue 30: every warning on verified data (verify on demand)
                        "verification": _verification_summary(s.get("verification")),
                        "lost_tp": vs["lost_tp"],
                        "warning_ticks_fabricated": sum(warned["fabricated"]["ticks"].values()),
                        "warning_ticks_misbehaving": sum(
                            n for g in ("misbehaving", "replayed")
                            for n in warned[g]["added"].values()),
                        "honest_suspected": sorted(vs["honest"]["suspected"]),
                        "honest_quarantined": vs["honest"]["quarantined"],
                        "precision_victims_fp": det.get("precision"),
                        "recall_victims_fp": det.get("recall"),
                        # the directories are temporary: gone with the sweep
                        "vs_clean": {k: v for k, v in vs.items()
                                     if k not in ("clean", "attacked")}})
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return rows


def _verification_summary(v: dict | None) -> dict | None:
    """What an attack row keeps of ``captures score``'s verification section."""
    if v is None:
        return None
    return {k: v[k] for k in ("policy", "frames", "warning_ticks", "warning_ticks_on_verified",
                              "warning_events", "warning_events_on_verified",
                              "all_on_verified", "unverified_track_ticks")}


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:g}"


def attack_table(rows: list[dict]) -> str:
    """The attack rows as a text table.  Against the clean twin: ``lost TP`` (TP ticks by
    app), ``warned fab/mis`` (warning ticks on fabricated ids / ones on the attack's named
    vehicles the clean run did not have), ``honest S/Q`` (honest vehicles suspected /
    quarantined) and ``P/R vict FP`` (precision / recall with victims as false
    positives)."""
    head = ["attack", "PER %", "defence", "FCW acc", "false alarms", "missed", "sent",
            "accepted", "rejected", "quarantined", "recall", "precision", "detect s",
            "lost TP", "warned fab/mis", "honest S/Q", "P/R vict FP"]
    body = [[r["attack"], f"{r['per']:g}", r["defence"], f"{r['fcw_accuracy']}",
             str(r["false_alarms"]), str(r["missed"]), str(r["sent"]), str(r["accepted"]),
             str(r["rejected"]), str(r["quarantined"]), _num(r["recall"]),
             _num(r["precision"]),
             "-" if r["time_to_detect_s"] is None else f"{r['time_to_detect_s']:.2f}",
             ", ".join(f"{a} {n}" for a, n in r["lost_tp"].items()) or "0",
             f"{r['warning_ticks_fabricated']}/{r['warning_ticks_misbehaving']}",
             f"{len(r['honest_suspected'])}/{len(r['honest_quarantined'])}",
             f"{_num(r['precision_victims_fp'])}/{_num(r['recall_victims_fp'])}"]
            for r in rows]
    widths = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(head)]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(line, widths, strict=True))
                     for line in [head, *body])
