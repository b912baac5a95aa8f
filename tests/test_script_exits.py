"""The reproduction scripts end like every selenv command: one line and exit 2 on a usage
error (an output folder that cannot be written is found before any work), never a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((ROOT / "scripts").glob("reproduce_*.py"))


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.stem for s in SCRIPTS])
def test_unwritable_out_is_a_one_line_usage_error(script: Path, tmp_path: Path) -> None:
    """``--out`` under a regular file: exit 2, one line naming --out and the cause."""
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    proc = subprocess.run(
        [sys.executable, str(script), "--out", str(blocker / "figs")],
        capture_output=True, text=True, cwd=ROOT, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith(f"{script.name}: error: --out: cannot write")
    assert "Traceback" not in proc.stderr
    assert blocker.read_text() == "not a folder"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
