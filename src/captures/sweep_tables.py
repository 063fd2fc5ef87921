"""The tables of a sweep's rows (``captures sweep --json``), shared by ``captures sweep``,
``captures report`` and the sweep's figures.

A row is one (dataset, predictor, PER, rate) cell pooled over trips and seeds
(:func:`catc.sweep.pool`); the paper's grid reads it along two axes: against PER at the
top rate (the paper's SPMD table) and against rate at the lowest PER.  :data:`POOLED` names
the rows over every dataset of a sweep.
"""

from __future__ import annotations

#: The dataset label of the rows that pool every dataset of a sweep (when it has several):
#: all their ticks in one percentile and all their FCW ticks in one accuracy, so a dataset
#: with more ticks weighs more (issue 17's targets are per dataset and pooled).
POOLED = "pooled"


def top_rate(rows: list[dict]) -> float:
    """The highest rate of ``rows``: where the PER axis is read."""
    return max(r["rate"] for r in rows)


def low_per(rows: list[dict]) -> float:
    """The lowest PER of ``rows``: where the rate axis is read."""
    return min(r["per"] for r in rows)


def grid_table(rows: list[dict], dataset: str, metric: str, axis: str = "per",
               ratios_to: str | None = "hgp") -> tuple[list[str], list[list[str]]]:
    """(header, body) of ``metric`` per predictor against ``axis`` for one dataset: against
    PER at the top rate (the paper's SPMD table), or against rate at the lowest PER.
    ``metric`` is a row key (``pte95_m``, ``fcw_accuracy``, ...) or ``exceed:TH``.  With
    ``ratios_to``, rows ``X/hgp`` follow for CA, KF, CTRV and the LSTM."""
    mine = [r for r in rows if r["dataset"] == dataset]
    if axis == "per":
        mine = [r for r in mine if r["rate"] == top_rate(mine)]
        keys = sorted({r["per"] for r in mine})
        header = ["PER [%]", *(f"{k:g}" for k in keys)]
    else:
        mine = [r for r in mine if r["per"] == low_per(mine)]
        keys = sorted({r["rate"] for r in mine}, reverse=True)
        header = ["Rate [Hz]", *(f"{k:g}" for k in keys)]
    by = {(r["predictor"], r[axis]): r for r in mine}
    names = list(dict.fromkeys(r["predictor"] for r in mine))

    def value(r: dict | None):
        if r is None:
            return None
        if metric.startswith("exceed:"):
            return r["exceedances"].get(metric.split(":", 1)[1])
        return r.get(metric)

    def fmt(v) -> str:
        if v is None:
            return "-"
        return f"{v:d}" if isinstance(v, int) else f"{v:.3f}"

    body = [[n, *(fmt(value(by.get((n, k)))) for k in keys)] for n in names
            if any(value(by.get((n, k))) is not None for k in keys)]
    if ratios_to and ratios_to in names and metric == "pte95_m":
        for n in names:
            if n in ("ca", "kf", "ctrv", "imm", "lstm"):
                cells_ = []
                for k in keys:
                    a, b = value(by.get((n, k))), value(by.get((ratios_to, k)))
                    cells_.append(f"{a / b:.2f}" if a is not None and b else "-")
                body.append([f"{n}/{ratios_to}", *cells_])
    return header, body


def text_table(header: list[str], body: list[list[str]]) -> str:
    """A (header, body) of :func:`grid_table` as aligned plain text."""
    widths = [max(len(r[i]) for r in [header, *body]) for i in range(len(header))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in
                       enumerate(zip(row, widths, strict=True))) for row in [header, *body]]
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """The tables ``captures sweep`` prints."""
    out = []
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        mine = [r for r in rows if r["dataset"] == ds]
        fcw = any(r["fcw_accuracy"] is not None for r in mine)
        axes = (("per", {r["per"] for r in mine if r["rate"] == top_rate(mine)},
                 f"PER at {top_rate(mine):g} Hz"),
                ("rate", {r["rate"] for r in mine if r["per"] == low_per(mine)},
                 f"rate at PER {low_per(mine):g} %"))
        for axis, values, against in axes:
            if len(values) < 2:
                continue
            for metric, title in (("pte95_m", "PTE95 [m]"), ("fcw_accuracy", "FCW accuracy")):
                if metric == "pte95_m" or fcw:
                    out.append(f"{ds}: {title} against {against}")
                    out.append(text_table(*grid_table(rows, ds, metric, axis)))
        out.append("")
    return "\n".join(out)
