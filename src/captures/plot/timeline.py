"""The timeline of ``captures plot`` (``timeline.png``): the PTE of every RV over time (the
join of :mod:`captures.score`, so the pooled 95th percentile is its ``pte95_m``), the
channel's delivered and dropped messages per RV and per second (the RVE's schedule,
:func:`hil.capture.schema.scheduled`), and the warning events per app (the OBU's,
:func:`hil.capture.schema.event`) as spans; FCW spans are shaded on every panel.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from captures.plot.load import Run
from captures.plot.style import APP_COLOURS

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["timeline"]


def timeline(fig: Figure, run: Run) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Draw the PTE, message and warning timelines on ``fig``; returns the PTE samples
    drawn, per RV id: ``(t, pte)``."""
    from matplotlib.patches import Patch

    axes = fig.subplots(4, 1, sharex=True, gridspec_kw={"height_ratios": (3.2, 2.2, 1.2,
                                                                           1.3)})
    a_pte, a_raster, a_count, a_warn = axes
    tr = run.tracks
    t0, t1 = float(run.tick_t[0]), float(run.tick_t[-1])
    ids = run.rv_ids() + sorted(set(tr["id"]) - set(run.truth))

    # PTE
    drawn: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for tid in ids:
        rows = np.flatnonzero((tr["id"] == tid) & np.isfinite(tr["pte"]))
        if not len(rows):
            continue
        drawn[tid] = (tr["t"][rows], tr["pte"][rows])
        a_pte.plot(tr["t"][rows], tr["pte"][rows], lw=0.9,
                   color=run.colours.get(tid, "#555555"), label=run.name(tid))
    a_pte.axhline(0.5, color="black", ls="--", lw=1.0)
    a_pte.text(t0, 0.5, " 0.5 m", va="bottom", ha="left", fontsize=7)
    samples = run.pte_samples()
    p95 = f"{np.percentile(samples, 95):.3f} m" if len(samples) else "n/a"
    top = max(1.0, 1.1 * float(np.percentile(samples, 99.9))) if len(samples) else 1.0
    a_pte.set_ylim(0.0, top)
    clipped = len(samples) and samples.max() > top
    a_pte.set_title(f"{run.dataset}   PER {100 * run.per:g} % at {run.rate_hz:g} Hz   "
                    f"predictor {run.predictor}   PTE95 {p95} over {len(samples)} samples",
                    fontsize=10)
    a_pte.set_ylabel("PTE [m]" + (f"\n(max {samples.max():.1f} m\nis off the top)"
                                  if clipped else ""), fontsize=8)
    if drawn:
        a_pte.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7,
                     frameon=False, ncol=1 + len(drawn) // 14, title="RV", title_fontsize=7)

    # raster of messages per RV
    rv_row = {tid: k for k, tid in enumerate(ids)}
    k = np.array([rv_row.get(s, -1) for s in run.sched_id], dtype=int)
    ok = k >= 0
    for dropped, colour, label in ((False, "#7fb77e", "delivered"),
                                   (True, "#d62728", "dropped by the channel")):
        m = ok & (run.sched_dropped == dropped)
        a_raster.scatter(run.sched_t[m], k[m], marker="|", s=14, lw=0.7, color=colour,
                         label=label, rasterized=True)
    a_raster.set_yticks(range(len(ids)), [run.name(i) for i in ids], fontsize=6)
    a_raster.set_ylim(len(ids) - 0.5, -0.5)
    a_raster.set_ylabel("RV messages", fontsize=8)
    a_raster.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7,
                    frameon=False, markerscale=2)

    # counts per second
    if len(run.sched_t):
        edges = np.arange(math.floor(run.sched_t.min()), math.ceil(run.sched_t.max()) + 1.0)
        if len(edges) < 2:
            edges = np.array([edges[0], edges[0] + 1.0])
        sent, _ = np.histogram(run.sched_t[~run.sched_dropped], edges)
        lost, _ = np.histogram(run.sched_t[run.sched_dropped], edges)
        a_count.bar(edges[:-1], sent, width=1.0, align="edge", color="#7fb77e",
                    label="delivered")
        a_count.bar(edges[:-1], lost, width=1.0, align="edge", bottom=sent,
                    color="#d62728", label="dropped")
        rate = run.sched_dropped.mean()
        a_count.set_title(f"dropped {run.sched_dropped.sum()} of {len(run.sched_t)} "
                          f"({100 * rate:.1f} %)", fontsize=8, loc="right")
    a_count.set_ylabel("messages/s", fontsize=8)
    a_count.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, frameon=False)

    # warning spans
    apps = [a for a in ("fcw", "eebl", "bsw", "lcw") if any(s[0] == a for s in run.spans)]
    apps += sorted({s[0] for s in run.spans} - set(apps))
    for row, app in enumerate(apps):
        colour = APP_COLOURS.get(app, "#555555")
        mine = [s for s in run.spans if s[0] == app]
        a_warn.broken_barh([(s[2], max(s[3] - s[2], 0.1)) for s in mine], (row - 0.35, 0.7),
                           color=colour, alpha=0.85)
        last_end = -math.inf
        for s in mine:
            if s[2] >= last_end:  # names that do not run into each other
                a_warn.text(s[2], row - 0.4, run.name(s[1]), fontsize=6, va="bottom",
                            ha="left", color=colour)
                last_end = s[2] + 0.012 * (t1 - t0) * max(4, len(run.name(s[1])))
    a_warn.set_yticks(range(len(apps)), [a.upper() for a in apps], fontsize=8)
    a_warn.set_ylim(len(apps) - 0.4 if apps else 0.6, -0.9)
    a_warn.set_ylabel("warnings", fontsize=8)
    a_warn.set_xlabel("t [s] (OBU clock)", fontsize=8)
    for s in run.spans:
        if s[0] == "fcw":
            for a in axes:
                a.axvspan(s[2], max(s[3], s[2] + 0.1), color=APP_COLOURS["fcw"], alpha=0.08,
                          lw=0)
    a_warn.legend(handles=[Patch(color=APP_COLOURS["fcw"], alpha=0.2,
                                 label="FCW active\n(all panels)")],
                  loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7, frameon=False)
    for a in axes:
        a.tick_params(labelsize=7)
        a.grid(axis="x", color="#dddddd", lw=0.5)
    a_warn.set_xlim(t0 - 0.5, t1 + 0.5)
    return drawn
