"""The learned-policy tables of the docs are generated from the records (and cannot drift)."""

from __future__ import annotations

from pathlib import Path

from conftest import load_script

pt = load_script("policy_tables")


def test_the_choosing_page_agrees_with_the_records() -> None:
    assert pt.main(["--check"]) == 0


def test_a_hand_edited_table_is_caught_and_rewritten(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    text = pt.PAGE.read_text(encoding="utf-8")
    page.write_text(text.replace("| **`learned`** |", "| **`best`** |", 1), encoding="utf-8")
    assert pt.main(["--check", "--page", str(page)]) == 1
    assert pt.main(["--write", "--page", str(page)]) == 0
    assert page.read_text(encoding="utf-8") == text
    assert pt.main(["--check", "--page", str(page)]) == 0


def test_a_page_without_its_markers_is_an_error(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("# no markers\n", encoding="utf-8")
    assert pt.main(["--check", "--page", str(page)]) == 2
