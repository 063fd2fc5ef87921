"""The code's shape (docs/architecture.md): no module of ``src/`` over 600 lines, so that
each stays one job that reads in one sitting. The import rules are ``make lint``'s."""

from __future__ import annotations

from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
MAX_LINES = 600


def test_no_module_is_over_600_lines():
    sizes = {str(f.relative_to(SRC)): len(f.read_text(encoding="utf-8").splitlines())
             for f in SRC.rglob("*.py")}
    assert len(sizes) > 50  # the tree was found
    assert {f: n for f, n in sizes.items() if n > MAX_LINES} == {}
