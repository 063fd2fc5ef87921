"""Colours shared by the pictures of ``captures plot``: the warning apps' and the
vehicles'."""

from __future__ import annotations

__all__ = ["APP_COLOURS", "PALETTE"]

#: Colours of the warning apps.
APP_COLOURS = {"fcw": "#d62728", "eebl": "#ff7f0e", "bsw": "#9467bd", "lcw": "#1f77b4"}
#: Vehicle colours, told apart more easily than tab20's pairs; no red (red is a warning).
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf",
           "#bcbd22", "#7f7f7f", "#1b3a6b", "#e6ab02", "#0b6e4f", "#a6cee3", "#6a3d9a",
           "#a6761d", "#66c2a5", "#4d4d4d", "#b3de69")
