"""Sphinx configuration of the selenv documentation (furo theme, MyST Markdown, autodoc).

Build: ``make docs`` (warnings are errors) -> ``docs/_build/html/index.html``.
"""

from __future__ import annotations

import sys
from importlib.metadata import version as _version
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # selenv from the work tree even without an install

project = "selenv"
author = "the selenv authors"
copyright = "2026, the selenv authors"
release = _version("selenv")
version = ".".join(release.split(".")[:2])

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "sphinx.ext.mathjax",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "README.md"]

# MyST: $...$ maths, ::: fences, heading anchors for [text](page.md#anchor) links
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 4

# autodoc (Google-style docstrings through napoleon; type hints in the descriptions)
autodoc_typehints = "description"
autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# the API pages' classes and functions stay anchors and cross-reference targets but are not
# table-of-contents entries: with them, every page's sidebar (furo renders the whole tree on
# each of ~150 pages, the viewcode ones included) held every documented object, and building
# the site took twice as long (114 s vs 59 s on the 2-core CI machine)
toc_object_entries = False

html_theme = "furo"
html_title = f"selenv {release}"
html_static_path = ["_static"]
# code blocks wrap (commands, Python) or scroll with a visible bar (text output): no long
# line is cut off at the page edge
html_css_files = ["selenv.css"]
html_theme_options = {"navigation_with_keys": True}

# linkcheck (make docs-linkcheck-external) follows the external links; the internal ones are
# checked offline by scripts/check_doc_links.py (make docs-linkcheck, run by CI)
linkcheck_timeout = 15


# -- docstrings in Gymnasium's manual form -----------------------------------------------------
# Env and module docstrings use "## Heading" sections and Markdown pipe tables (they are also
# the generated env pages, scripts/gen_env_pages.py). For autodoc, which reads docstrings as
# reStructuredText, headings become rubrics and pipe tables become list-tables.


def _cells(row: str) -> list[str]:
    return [c.strip() for c in row.strip().strip("|").split("|")]


def _md_to_rst(lines: list[str]) -> list[str]:
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        heading = line.startswith("## ") and not line.startswith("###")
        if heading:
            out += [f".. rubric:: {line[3:].strip()}", ""]
            i += 1
            continue
        is_table = line.lstrip().startswith("|") and i + 1 < len(lines)
        if is_table and set(lines[i + 1].replace("|", "").strip()) <= set("-: "):
            indent = line[: len(line) - len(line.lstrip())]
            header, rows = _cells(line), []
            i += 2
            while i < len(lines) and lines[i].strip():
                if lines[i].lstrip().startswith("|"):
                    rows.append(_cells(lines[i]))
                elif rows:  # a wrapped row: its text continues the last non-empty cell
                    last = max(k for k, c in enumerate(rows[-1]) if c) if any(rows[-1]) else 0
                    rows[-1][last] += " " + lines[i].strip().rstrip("|").strip()
                else:
                    break
                i += 1
            width = len(header)
            has_header = any(header)
            if out and out[-1].strip():
                out.append("")
            out += [f"{indent}.. list-table::", f"{indent}   :header-rows: {int(has_header)}", ""]
            for row in ([header] if has_header else []) + rows:
                row = (row + [""] * width)[:width]
                out.append(f"{indent}   * - {row[0] or ' '}")
                out += [f"{indent}     - {c or ' '}" for c in row[1:]]
            out.append("")
            continue
        out.append(line)
        i += 1
    return out


def _process_docstring(app, what, name, obj, options, lines):
    lines[:] = _md_to_rst(list(lines))


def setup(app):
    """Register the docstring hook."""
    app.connect("autodoc-process-docstring", _process_docstring)
