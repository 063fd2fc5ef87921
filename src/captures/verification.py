"""``captures score``: how the OBU verified the RV frames, and whether every warning rests
on verified data (``obu run --verify``; issue 30, verify on demand).

From the capture alone, not from the OBU's counters:

* **Per frame** (``obu.rx``'s ``verify`` and ``verdict``, :func:`hil.capture.schema.received`):
  verified ``at_once`` (on arrival), verified from the queue before its tick (``queue``),
  stepped unverified (``deferred``), ``withheld`` (urgent, held back by the OBU's
  limiter and still unverified at its tick: not stepped), rejected (on arrival or from
  the queue, by reason),
  and what became of the frames stepped unverified or dropped from the queue
  (``obu.verify.jsonl``: verified ``ok`` or rejected later, ``skipped``, ``pending`` at the
  end).  Under ``--verify-policy all`` (or ``log``) every frame has its verdict from
  arrival: ``at_once``.
* **Warnings on verified data**: a warning (each tick's condition on an RV, and each
  warning event's start) rests on verified data when the newest message of that RV that
  the OBU stepped at or before that tick (the highest generation time at the latest
  tick) was verified by its tick (verdict ``ok`` in its ``obu.rx`` record).  Every warning
  must: ``on_unverified`` lists the first that do not.
* **Unverified tracks**: the RVs each tick kept without a verified message (``obu.ticks``
  ``unverified``), in tick-RV pairs.
"""

from __future__ import annotations

import bisect
from collections import Counter
from typing import Any

from catc.bsm import MINUTE_MS

__all__ = ["lines", "verification"]


def _gen_ms(sec_mark: int | None, tick: float) -> int:
    """A message's generation time in ms relative to its tick (secMark wraps each minute)."""
    if sec_mark is None:
        return 0
    half = MINUTE_MS // 2
    return (sec_mark - round(tick * 1000.0) + half) % MINUTE_MS - half


def verification(cap: Any) -> dict[str, Any] | None:
    """The verification section of ``captures score`` (module docstring); None when the
    OBU did not verify (no record has a verdict)."""
    settings = (cap.obu_config or {}).get("settings", {})
    mode = settings.get("verify")
    if mode in (None, "off"):
        return None
    policy = settings.get("verify_policy", "all") if mode == "enforce" else "all"
    frames: Counter[str] = Counter()
    rejected: Counter[str] = Counter()
    # RV id -> tick -> (generation ms relative to the tick, verified by its tick)
    newest: dict[str, dict[float, tuple[int, bool]]] = {}
    for r in cap.iter_rx():
        if r.get("channel") != "rv":
            continue
        status = r.get("status")
        how = r.get("verify") or ("at_once" if r.get("verdict") else None)
        if status == "withheld":  # urgent, over the limiter, unverified at its tick
            frames["withheld"] += 1
            continue
        if status == "rejected":
            rejected[r.get("verdict", "?")] += 1
            frames[f"rejected_{(how or 'at_once').replace('-', '_')}"] += 1
            continue
        if status not in ("ok", "unticked") or how is None:
            continue
        frames[how.replace("-", "_")] += 1
        if status != "ok" or "tick" not in r:
            continue
        tick = round(r["tick"], 3)
        entry = (_gen_ms(r.get("sec_mark"), tick), r.get("verdict") == "ok")
        by_tick = newest.setdefault(r["id"], {})
        if tick not in by_tick or entry[0] >= by_tick[tick][0]:
            by_tick[tick] = entry
    late: Counter[str] = Counter()
    for r in cap.iter_verify():
        late[r["outcome"] if r.get("stepped") else f"{r['outcome']}_before_tick"] += 1
    ticks = {rv: sorted(by_tick) for rv, by_tick in newest.items()}

    def verified_at(rv: str, t: float) -> bool:
        ts = ticks.get(rv)
        if not ts:
            return False
        k = bisect.bisect_right(ts, round(t, 3) + 1e-9) - 1
        return k >= 0 and newest[rv][ts[k]][1]

    conditions = on_verified = unverified_pairs = 0
    bad: list[list[Any]] = []
    for tk in cap.iter_ticks():
        unverified_pairs += len(tk.get("unverified", ()))
        for w in tk["warnings"]:
            conditions += 1
            if verified_at(w[1], tk["t"]):
                on_verified += 1
            elif len(bad) < 20:
                bad.append([tk["t"], w[0], w[1]])
    starts = [e for e in cap.events if e["kind"] == "start"]
    events_verified = sum(verified_at(e["rv"], e["t"]) for e in starts)
    return {
        "policy": policy,
        "frames": dict(frames),
        "rejected": dict(rejected),
        "later": dict(late),
        "warning_ticks": conditions, "warning_ticks_on_verified": on_verified,
        "warning_events": len(starts), "warning_events_on_verified": events_verified,
        "on_unverified": bad,
        "all_on_verified": on_verified == conditions and events_verified == len(starts),
        "unverified_track_ticks": unverified_pairs,
    }


def lines(v: dict[str, Any] | None) -> list[str]:
    """The section as lines of ``captures score``'s table."""
    if v is None:
        return []
    f = v["frames"]
    out = [f"verification ({v['policy']}): at once {f.get('at_once', 0)}, from the queue "
           f"before its tick {f.get('queue', 0)}, stepped unverified {f.get('deferred', 0)}, "
           f"withheld {f.get('withheld', 0)}, rejected {sum(v['rejected'].values())}"
           + "".join(f" ({k} {n})" for k, n in sorted(v["rejected"].items()))]
    if v["later"]:
        out.append("  after deferral: " + ", ".join(
            f"{k.replace('_', ' ')} {n}" for k, n in sorted(v["later"].items())))
    out.append(f"  warnings on verified data: {v['warning_ticks_on_verified']} of "
               f"{v['warning_ticks']} warning ticks, {v['warning_events_on_verified']} of "
               f"{v['warning_events']} warning events"
               + ("" if v["all_on_verified"] else "  NOT ALL: first "
                  + ", ".join(f"{a} {rv} at {t}" for t, a, rv in v["on_unverified"][:5]))
               + f"; unverified tracks: {v['unverified_track_ticks']} tick-RV pairs")
    return out
