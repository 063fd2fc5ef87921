"""Shared fixtures.  Real data is read from ../shared/data and never copied here."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = Path(os.environ.get("CATC_SHARED_DATA", REPO.parent / "shared" / "data"))
VECTORS = SHARED_DATA / "jpo-ode-bsm-vectors"
#: The test files that hold SocketCAN tests (``-m socketcan``): ``tools/vcanvm.py`` runs
#: just these in the VM (collecting the whole suite there takes a minute) and reads them
#: from here; the hook below fails the collection when a SocketCAN test is elsewhere.
SOCKETCAN_FILES = ("tests/test_rve_can.py", "tests/test_transport.py",
                   "tests/test_vcan_interop.py", "tests/test_rve_hostbus.py")


def pytest_collection_modifyitems(config, items):
    stray = sorted({str(Path(item.path).relative_to(REPO)) for item in items
                    if item.get_closest_marker("socketcan")} - set(SOCKETCAN_FILES))
    if stray:
        raise pytest.UsageError(f"SocketCAN tests outside tests/conftest.py SOCKETCAN_FILES "
                                f"(tools/vcanvm.py would not run them): {', '.join(stray)}")


def shared_path(*parts: str) -> Path:
    """Path into ../shared/data, or skip the test with the reason it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not present: {path} (set CATC_SHARED_DATA)")
    return path


@pytest.fixture
def vectors_dir() -> Path:
    return shared_path("jpo-ode-bsm-vectors")
