"""Kernels compiled when first asked for (numba, ``cache=True``: compiled once per
machine, then loaded): a process that never needs one never imports numba."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

__all__ = ["compiled"]


@functools.cache
def compiled(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` compiled by numba (no fast-math: the same IEEE operations in the same order),
    made on the first call for it and the same object after."""
    from numba import njit

    return njit(cache=True, error_model="numpy")(fn)
