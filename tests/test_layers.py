"""The layers of docs/layout.md hold: pyproject.toml's import-linter contracts, checked on the code as it is."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

from importlinter.cli import lint_imports

ROOT = Path(__file__).resolve().parent.parent


def test_the_import_contracts_are_kept():
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True)
    assert status == 0, out.getvalue()
    assert "0 broken" in out.getvalue() and "3 kept" in out.getvalue()
