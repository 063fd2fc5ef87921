"""Shared fixtures.  Real data is read from ../shared/data and never copied here."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = Path(os.environ.get("CATC_SHARED_DATA", REPO.parent / "shared" / "data"))
VECTORS = SHARED_DATA / "jpo-ode-bsm-vectors"


def shared_path(*parts: str) -> Path:
    """Path into ../shared/data, or skip the test with the reason it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not present: {path} (set CATC_SHARED_DATA)")
    return path


@pytest.fixture
def vectors_dir() -> Path:
    return shared_path("jpo-ode-bsm-vectors")
