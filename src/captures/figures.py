"""Figures of a sweep (matplotlib, PNG): the paper's H3 panels and its exceedance grid.

* ``<dataset>_h3.png``: PTE95 against PER and against rate, FCW accuracy against PER and
  against rate, one line per predictor (the paper's "PTE and FCW_accuracy vs PER and
  Rate" figures).
* ``<dataset>_exceedance.png``: the number of ticks with PTE > PTE_th against PER, one
  panel per threshold from 0.2 to 1.6 m (the paper's threshold-exceedance grid).
* :func:`targets_figure` (the report's ``hgp_vs_kinematic.png``): HGP's PTE95 over the best
  kinematic tracker's against PER and rate, one line per dataset, issue 17's targets drawn.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt

from captures.sweep_tables import POOLED, low_per, top_rate

#: One colour and marker per predictor, the same in every figure.
STYLE = {
    "hold": ("#7f7f7f", "x"), "cs": ("#bcbd22", "v"), "ca": ("#1f77b4", "s"),
    "kf": ("#ff7f0e", "D"), "ctrv": ("#9467bd", "^"), "imm": ("#393b79", "d"),
    "hgp": ("#d62728", "o"),
    "hgp-d": ("#e377c2", "P"), "ae": ("#8c564b", "<"), "ae-d": ("#c49c94", ">"),
    "lstm": ("#2ca02c", "*"), "lstm-d": ("#98df8a", "h"),
}


def _style(name: str) -> dict:
    color, marker = STYLE.get(name, ("#17becf", "."))
    return {"color": color, "marker": marker, "lw": 2.2 if name == "hgp" else 1.3,
            "ms": 5, "label": name, "zorder": 3 if name == "hgp" else 2}


def _series(rows: list[dict], axis: str, metric: str) -> dict[str, tuple[list, list]]:
    """predictor -> (x, y) of ``metric`` against ``axis`` (PER at the top rate, or rate at
    the lowest PER)."""
    if axis == "per":
        top = top_rate(rows)
        rows = [r for r in rows if r["rate"] == top]
    else:
        low = low_per(rows)
        rows = [r for r in rows if r["per"] == low]
    out: dict[str, tuple[list, list]] = {}
    for r in sorted(rows, key=lambda r: r[axis]):
        v = r["exceedances"].get(metric[7:]) if metric.startswith("exceed:") else r[metric]
        if v is None:
            continue
        xs, ys = out.setdefault(r["predictor"], ([], []))
        xs.append(r[axis])
        ys.append(v)
    return out


def plot_metric(ax, rows: list[dict], axis: str, metric: str, *, log: bool = False) -> int:
    """One panel: ``metric`` per predictor against ``axis``; returns the lines drawn."""
    n = 0
    for name, (xs, ys) in _series(rows, axis, metric).items():
        if log:
            ys = [max(y, 1e-3) for y in ys]  # PER 0 gives PTE 0: show it at the floor
        ax.plot(xs, ys, **_style(name))
        n += 1
    ax.set_xlabel("PER [%]" if axis == "per" else "Rate [Hz]")
    if axis == "rate":
        ax.invert_xaxis()  # from 10 Hz (no loss) to 1 Hz, like PER from 0
    if log:
        ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    return n


def h3_figure(rows: list[dict], dataset: str, path: Path) -> Path:
    mine = [r for r in rows if r["dataset"] == dataset]
    fcw = any(r["fcw_accuracy"] is not None for r in mine)
    fig, axes = plt.subplots(2 if fcw else 1, 2, figsize=(11, 8 if fcw else 4.2),
                             squeeze=False)
    top, low = max(r["rate"] for r in mine), min(r["per"] for r in mine)
    plot_metric(axes[0, 0], mine, "per", "pte95_m", log=True)
    axes[0, 0].set(ylabel="PTE95 [m]", title=f"PTE95 against PER ({top:g} Hz)")
    plot_metric(axes[0, 1], mine, "rate", "pte95_m", log=True)
    axes[0, 1].set(ylabel="PTE95 [m]", title=f"PTE95 against rate (PER {low:g} %)")
    if fcw:
        plot_metric(axes[1, 0], mine, "per", "fcw_accuracy")
        axes[1, 0].set(ylabel="FCW accuracy", title=f"FCW accuracy against PER ({top:g} Hz)")
        plot_metric(axes[1, 1], mine, "rate", "fcw_accuracy")
        axes[1, 1].set(ylabel="FCW accuracy",
                       title=f"FCW accuracy against rate (PER {low:g} %)")
    axes[0, 0].legend(loc="upper left", fontsize=8, ncol=2)
    fig.suptitle(f"{dataset}: position tracking error and FCW accuracy")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def exceedance_figure(rows: list[dict], dataset: str, path: Path) -> Path:
    mine = [r for r in rows if r["dataset"] == dataset]
    ths = list(mine[0]["exceedances"])
    ncol = 4
    nrow = -(-len(ths) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(13, 3.1 * nrow), squeeze=False,
                             sharex=True)
    for ax, th in zip(axes.flat, ths, strict=False):
        plot_metric(ax, mine, "per", f"exceed:{th}")
        ax.set_title(f"PTE > {th} m")
        ax.set_yscale("symlog", linthresh=10)  # counts from 0 to 10^5: the baselines apart
    for ax in axes[:, 0]:
        ax.set_ylabel("ticks")
    for ax in list(axes.flat)[len(ths):]:
        ax.set_visible(False)
    axes[0, 0].legend(loc="upper left", fontsize=7, ncol=2)
    fig.suptitle(f"{dataset}: ticks with PTE above the threshold, against PER")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def sweep_figures(doc: dict, out: Path) -> list[Path]:
    """Every figure of a sweep document (``captures sweep --json``) into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    rows = doc["rows"]
    paths = []
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        mine = [r for r in rows if r["dataset"] == ds]
        if len({r["per"] for r in mine}) + len({r["rate"] for r in mine}) > 2:
            paths.append(h3_figure(rows, ds, out / f"{ds}_h3.png"))
            paths.append(exceedance_figure(rows, ds, out / f"{ds}_exceedance.png"))
    return paths


def targets_figure(targets: dict[str, list[dict]], path: Path) -> Path:
    """HGP's PTE95 over the best kinematic tracker's, one line per dataset: against PER
    (left, issue 17's targets dashed: 1 from 10 %, 0.8 from 80 to 95 %) and against rate
    (right, when the sweep has rates).  ``targets``: dataset -> the entries of
    :func:`captures.report.hgp_targets` (the report owns the comparison; this only draws)."""
    with_rates = any(e["axis"] == "rate" for v in targets.values() for e in v)
    fig, axes = plt.subplots(1, 2 if with_rates else 1, figsize=(12 if with_rates else 6.5,
                                                                 4.2), squeeze=False)
    left, right = axes[0, 0], axes[0, -1]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (ds, entries) in enumerate(targets.items()):
        style = {"color": colors[i % len(colors)], "marker": "o", "ms": 4, "label": ds,
                 "lw": 2.2 if ds == POOLED else 1.4}
        per = [e for e in entries if e["axis"] == "per"]
        rate = sorted((e for e in entries if e["axis"] == "rate"), key=lambda e: -e["rate"])
        left.plot([e["per"] for e in per], [e["ratio"] for e in per], **style)
        if with_rates:
            right.plot([e["rate"] for e in rate], [e["ratio"] for e in rate], **style)
    left.plot([10, 95], [1.0, 1.0], "k--", lw=1, label="target ≤ 1")
    left.plot([80, 95], [0.8, 0.8], "k:", lw=1.5, label="target ≤ 0.8 (80–95 %)")
    left.set_xlabel("PER [%] (top rate)")
    if with_rates:
        right.axhline(1.0, color="k", ls="--", lw=1)
        right.set_xlabel("Rate [Hz] (lowest PER)")
        right.invert_xaxis()
    for ax in {left, right}:
        ax.set_ylabel("HGP PTE95 / best kinematic PTE95")
        ax.grid(True, alpha=0.3)
    left.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
