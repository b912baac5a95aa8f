"""Check every internal link of the built documentation site (no network).

Scans the HTML that ``make docs`` wrote (default ``docs/_build/html``): every ``href`` and
``src`` that points inside the site must name a file that exists, and a ``#fragment`` must
name an ``id`` on the target page. External links (``http(s)``, ``mailto``) are not followed
(``make docs-linkcheck-external`` runs Sphinx's linkcheck on them where there is a network).
Exit 1 with one line per broken link.

    .venv/bin/python scripts/check_doc_links.py [docs/_build/html]
"""

from __future__ import annotations

import argparse
import sys
from functools import cache
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

#: generated folders whose pages are Sphinx's own (search, sources) and link by script
_SKIP_DIRS = {"_static", "_sources", "_images", "_modules"}


class _Collector(HTMLParser):
    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.ids: set[str] = set()
        self.links: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for name, value in attrs:
            if value is None:
                continue
            if name in {"id", "name"}:
                self.ids.add(value)
            elif (name == "href" and tag in {"a", "link"}) or (name == "src" and tag == "img"):
                self.links.append(value)


@cache
def _parse(path: Path) -> _Collector:
    collector = _Collector()
    collector.feed(path.read_text(encoding="utf-8", errors="replace"))
    return collector


def broken_links(root: Path) -> list[str]:
    """``page: link (reason)`` for every internal link of the site under ``root`` that is broken."""
    problems: list[str] = []
    pages = sorted(p for p in root.rglob("*.html") if not _SKIP_DIRS & set(p.parts))
    if not pages:
        raise FileNotFoundError(f"no HTML pages under {root}: run make docs first")
    for page in pages:
        for link in _parse(page).links:
            parts = urlsplit(link)
            if parts.scheme or parts.netloc or link.startswith(("mailto:", "javascript:")):
                continue
            target = page if not parts.path else (page.parent / unquote(parts.path)).resolve()
            if target.is_dir():
                target = target / "index.html"
            where = f"{page.relative_to(root)}: {link}"
            if not target.exists():
                problems.append(f"{where} (no file {target.relative_to(root.resolve())})")
                continue
            if parts.fragment and target.suffix == ".html":
                if unquote(parts.fragment) not in _parse(target).ids:
                    problems.append(f"{where} (no id #{parts.fragment} on the page)")
    return problems


def main(argv: list[str] | None = None) -> int:
    """Print the broken links; exit 1 if there are any."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("root", nargs="?", default="docs/_build/html", help="the built site")
    args = ap.parse_args(argv)
    root = Path(args.root)
    problems = broken_links(root)
    for line in problems:
        print(line)
    n_pages = sum(1 for p in root.rglob("*.html") if not _SKIP_DIRS & set(p.parts))
    print(f"check_doc_links: {len(problems)} broken internal links in {n_pages} pages")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
