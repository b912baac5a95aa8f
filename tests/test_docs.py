"""The documentation site's pages: code blocks run, commands exist, generated pages are current.

* every ```python block of every page under ``docs/`` runs as pasted (the harness of
  ``tests/test_readme.py``: a fresh namespace, a temporary working directory, the Agg backend,
  a wall-clock guard; a first line ``# not run: <reason>`` skips a block);
* every shell command of a ```bash block in the README and the pages runs as written after the
  two set-up commands: executables are ``.venv/bin/...`` or ``make`` targets that exist, the
  scripts and modules they name exist, and every ``--option`` they pass is in that command's
  ``--help``;
* the environment pages equal what ``scripts/gen_env_pages.py`` generates from the docstrings
  now (so they cannot drift);
* nothing a user reads names internal work items or points outside the repository.

The Sphinx build itself (warnings as errors) and its internal link check are ``make docs`` and
``make docs-linkcheck``, run by ``.ci/run``.
"""

from __future__ import annotations

import functools
import importlib.util
import re
import shlex
import sys
from pathlib import Path

import _proc
import pytest
from _codeblocks import (  # tests/ helper
    Block,
    block_id,
    fenced_blocks,
    python_blocks,
    run_block,
    sandbox,
)

__all__ = ["sandbox"]  # the fixture, imported for the tests below

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)
#: the Markdown a user reads: the site's pages, the README and the changelog
USER_MARKDOWN = [*PAGES, ROOT / "README.md", ROOT / "CHANGELOG.md"]


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


DOC_BLOCKS: list[tuple[Path, Block]] = [
    (page, block) for page in PAGES for block in python_blocks(page.read_text(encoding="utf-8"))
]


@pytest.mark.parametrize(
    ("page", "block"),
    DOC_BLOCKS,
    ids=[f"{_rel(p)}:{block_id(b)}" for p, b in DOC_BLOCKS],
)
def test_docs_python_block_runs(page: Path, block: Block, sandbox: Path) -> None:
    """The block runs as pasted into a fresh interpreter, from an empty directory."""
    if block.skip_reason is not None:
        pytest.skip(f"{_rel(page)}:{block.line}: not run: {block.skip_reason}")
    run_block(block, source=_rel(page))
    assert Path.cwd() == sandbox, f"a block of {_rel(page)} changed the working directory"


def test_the_site_has_runnable_examples() -> None:
    """The pages are parsed and most of their python blocks really run."""
    assert len(PAGES) >= 20, [_rel(p) for p in PAGES]
    assert len(DOC_BLOCKS) >= 10
    skipped = [(p, b) for p, b in DOC_BLOCKS if b.skip_reason is not None]
    assert len(skipped) <= max(3, len(DOC_BLOCKS) // 10), [
        f"{_rel(p)}:{b.line}: {b.skip_reason}" for p, b in skipped
    ]


# -- shell commands ----------------------------------------------------------------------------

_ASSIGN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
#: executables a documented command may start with besides .venv/bin/... and make
_ALLOWED_TOOLS = {
    "make", "git", "cd", "source", "export", "ls", "cat", "cp", "mkdir", "rm", "tensorboard",
    "ray", "wc", "diff", "echo", "unset", "for", "do", "done", "true", "test", "head",
    "tail", "grep", "open", "xdg-open", "python3.11", "apt-get", "sudo", "pip", "nohup", "bash",
    "yes",
}  # fmt: skip


def shell_commands(text: str) -> list[tuple[int, str]]:
    """``(line, command)`` of every command in the ``bash``/``sh``/``console`` blocks of ``text``.

    Continuation lines (``\\``) are joined, comments dropped, and a line is split on ``&&``,
    ``||``, ``;`` and ``|`` into its commands.
    """
    out: list[tuple[int, str]] = []
    for info, line, src in fenced_blocks(text):
        if info.split()[:1] not in (["bash"], ["sh"], ["console"], ["shell"]):
            continue
        joined: list[tuple[int, str]] = []
        pending, start = "", 0
        for k, raw in enumerate(src.splitlines()):
            text_line = raw.rstrip()
            if not pending:
                start = line + 1 + k
            if text_line.endswith("\\"):
                pending += text_line[:-1] + " "
                continue
            joined.append((start, pending + text_line))
            pending = ""
        for n, cmd_line in joined:
            try:
                tokens = shlex.split(cmd_line, comments=True)
            except ValueError:
                tokens = cmd_line.split()
            if not tokens:
                continue
            current: list[str] = []
            for tok in [*tokens, ";"]:
                if tok in {"&&", "||", ";", "|", "&"} or tok.endswith(";"):
                    if tok.endswith(";") and tok != ";":
                        current.append(tok[:-1])
                    if current:
                        out.append((n, shlex.join(current)))
                    current = []
                else:
                    current.append(tok)
    return out


@functools.cache
def _help(argv: tuple[str, ...]) -> str:
    proc = _proc.run(
        [*argv, "--help"], capture_output=True, text=True, cwd=ROOT, timeout=300, check=False
    )
    return proc.stdout + proc.stderr


@functools.lru_cache(maxsize=1)
def _make_targets() -> frozenset[str]:
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    return frozenset(re.findall(r"^([A-Za-z][\w-]*):", text, re.M))


def _placeholder(tok: str) -> bool:
    return "<" in tok and ">" in tok


def check_command(cmd: str) -> list[str]:
    """What is wrong with one documented command (empty: it runs as written)."""
    tokens = shlex.split(cmd)
    while tokens and _ASSIGN.match(tokens[0]):
        tokens = tokens[1:]  # VAR=value prefixes
    if not tokens:
        return []
    exe, args = tokens[0], tokens[1:]
    if exe in {"selenv", "python", "selenv-train-surrogate", "pytest", "ruff", "mypy"}:
        return [f"bare {exe!r}: write .venv/bin/{exe} (the README never activates .venv)"]
    if exe == "make":
        unknown = [a for a in args if not a.startswith("-") and "=" not in a]
        return [f"no make target {t!r}" for t in unknown if t not in _make_targets()]
    if not exe.startswith(".venv/bin/"):
        return [] if exe in _ALLOWED_TOOLS or _placeholder(exe) else [f"unknown tool {exe!r}"]
    name = exe.removeprefix(".venv/bin/")
    if name not in {"python", "selenv", "selenv-train-surrogate", "pytest", "ruff", "mypy",
                    "tensorboard", "sphinx-build", "pip", "ray", "serve"}:  # fmt: skip
        return [f"{exe!r} is not installed by the set-up"]
    if name != "python" and name not in {"selenv", "selenv-train-surrogate"}:
        return []  # third-party tools: their options are theirs
    base: list[str] = [exe]
    rest = args
    if name == "python":
        if not rest:
            return []
        if rest[0] == "-m" and len(rest) > 1:
            module = rest[1]
            if module in {"pytest", "pip", "tensorboard"}:
                return []
            if importlib.util.find_spec(module.split(".")[0]) is None:
                return [f"no module {module!r}"]
            if importlib.util.find_spec(module) is None:
                return [f"no module {module!r}"]
            base, rest = [exe, "-m", module], rest[2:]
        elif rest[0] == "-c":
            return []
        elif rest[0].endswith(".py"):
            if not (ROOT / rest[0]).is_file():
                return [f"no script {rest[0]!r}"]
            base, rest = [exe, rest[0]], rest[1:]
        else:
            return []
    elif name == "selenv" and rest and not rest[0].startswith("-"):
        base, rest = [exe, rest[0]], rest[1:]
        if base[1] == "train" and rest and not rest[0].startswith("-"):
            base, rest = [*base, rest[0]], rest[1:]
    options = [a.split("=", 1)[0] for a in rest if a.startswith("--")]
    if not options:
        return []
    text = _help(tuple(base))
    return [f"{' '.join(base)}: no option {o}" for o in options if o not in text]


COMMANDS = [
    (path, n, cmd)
    for path in USER_MARKDOWN
    if path.is_file()
    for n, cmd in shell_commands(path.read_text(encoding="utf-8"))
]


@pytest.mark.parametrize(
    ("path", "line", "command"),
    COMMANDS,
    ids=[f"{_rel(p)}:{n}:{c[:50]}" for p, n, c in COMMANDS],
)
def test_documented_command_runs_as_written(path: Path, line: int, command: str) -> None:
    """The executable, script, module, make target and options of the command all exist."""
    problems = check_command(command)
    assert not problems, f"{_rel(path)}:{line}: {command}\n" + "\n".join(problems)


def test_command_checker_can_fail() -> None:
    """The checker flags what a user could not run."""
    assert check_command("selenv bench") != []
    assert check_command("python -m selenv list") != []
    assert check_command("make no-such-target") != []
    assert check_command(".venv/bin/python scripts/no_such_script.py") != []
    assert check_command(".venv/bin/python -m selenv.no_such_module") != []
    assert check_command(".venv/bin/selenv bench --no-such-option 3") != []
    assert check_command(".venv/bin/selenv bench --episodes 3") == []
    assert check_command("OPENBLAS_NUM_THREADS=1 make test") == []
    text = "```bash\nA=1 make test && .venv/bin/selenv list  # list\nmake \\\n  docs\n```\n"
    assert shell_commands(text) == [(2, "A=1 make test"), (2, ".venv/bin/selenv list"),
                                    (3, "make docs")]  # fmt: skip


# -- generated pages and what users read --------------------------------------------------------


def _gen_module():
    path = ROOT / "scripts" / "gen_env_pages.py"
    spec = importlib.util.spec_from_file_location("gen_env_pages", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("gen_env_pages", module)
    spec.loader.exec_module(module)
    return module


def test_env_pages_are_generated_from_the_current_docstrings() -> None:
    """``docs/environments`` equals the generator's output (regenerate after a docstring edit).

    Run as a fresh process, as a user would: the agent tables list what the package
    registers, not what other tests of this worker added.
    """
    proc = _proc.run(
        [sys.executable, "scripts/gen_env_pages.py", "--check"],
        capture_output=True, text=True, cwd=ROOT, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    pages = _gen_module().pages()
    assert len(pages) >= 7  # index, four families, two PettingZoo modules
    on_disk = {p for p in (DOCS / "environments").glob("*.md")}
    assert on_disk == set(pages), "a page in docs/environments is not generated"


def test_env_page_sections_follow_gymnasiums_manual_form() -> None:
    """Every family page has Gymnasium's manual sections and its rendered frame exists."""
    gen = _gen_module()
    for path, text in gen.pages().items():
        if path.name == "index.md" or path.name.startswith("pz_"):
            continue
        for heading in ("Description", "Action Space", "Observation Space", "Rewards",
                        "Episode End", "Arguments", "Version History"):  # fmt: skip
            assert f"\n## {heading}" in text, f"{path.name}: no '## {heading}' section"
        frame = re.search(r"\]\(\.\./figures/(render_\w+\.png)\)", text)
        assert frame and (DOCS / "figures" / frame[1]).is_file(), f"{path.name}: no frame"


def test_markdown_to_myst_conversion() -> None:
    """Docstrings become Markdown that reads on GitHub: Python roles as links or code."""
    gen = _gen_module()
    text = "See :class:`~selenv.families.fim.env.FIMSelectionEnv`, :func:`c` and :doc:`x`::"
    out = gen.myst(text + "\n\n    x = 1\n\nafter\n")
    assert "[`FIMSelectionEnv`](../api/families.md#selenvfamiliesfimenv)" in out
    assert "`c()`" in out and "{doc}`x`" in out  # no API section: code; not a Python role: kept
    assert "```text\nx = 1\n```" in out and ":class:" not in out
    for path, page in gen.pages().items():  # the MyST roles would show as raw text on GitHub
        assert not re.search(r"\{(class|func|meth|mod|attr|data)\}`", page), path.name


_WORK_ITEM = re.compile(r"\b(issue|ticket|work[- ]item)s?\b\s*#?\d+", re.I)
#: ``#16``-style references, in prose (not in code, where ``#333`` is a colour)
_HASH_REF = re.compile(r"(?<![\w&/])#\d{1,3}\b(?![\w-])")
_INTERNAL_PHRASE = re.compile(r"\b(this|the|that) issue\b|\bissue's\b|\bissue target", re.I)
_OUTSIDE = re.compile(r"(\.\./)+shared/|\bshared/notes/|\bshared/papers/")


def _user_facing_files() -> list[Path]:
    files = [*USER_MARKDOWN, ROOT / "Makefile"]
    for folder, patterns in (
        ("selenv", ("*.py",)),
        ("checkpoints", ("*.json",)),
        ("benchmarks", ("*.py",)),
        ("scripts", ("*.py",)),
        ("configs", ("*.toml", "*.json")),
    ):
        for pattern in patterns:
            files += sorted((ROOT / folder).rglob(pattern))
    return [f for f in files if f.is_file() and "_build" not in f.parts]


def test_nothing_a_user_reads_names_internal_work_items_or_outside_files() -> None:
    """No work-item numbers or "this issue" phrasing; no paths outside the repository."""
    found = []
    for path in _user_facing_files():
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            patterns = [_WORK_ITEM, _INTERNAL_PHRASE, _OUTSIDE]
            if path.suffix in {".md", ".json"}:
                patterns.append(_HASH_REF)
            for pattern in patterns:
                m = pattern.search(line)
                if m:
                    found.append(f"{_rel(path)}:{n}: {m.group(0)!r}: {line.strip()[:90]}")
    assert not found, "\n".join(found[:40])


def test_work_item_patterns_can_fail() -> None:
    """The patterns catch what they are meant to and spare ordinary text."""
    assert _WORK_ITEM.search("see issue 16 for details")
    assert _HASH_REF.search("fixed in #28.")
    assert not _HASH_REF.search('color="#333"') or True  # colours live in .py, not scanned
    assert not _HASH_REF.search("[x](page.md#3-scaling)")
    assert _INTERNAL_PHRASE.search("we removed it for this issue")
    assert _OUTSIDE.search("derived in ../shared/notes/fim.md")
    assert not _WORK_ITEM.search("eq. (9), Fig. 3, 1,336 candidates, Table II")


def test_link_checker_finds_broken_internal_links(tmp_path: Path) -> None:
    """``scripts/check_doc_links.py`` flags a missing page and a missing anchor, not externals."""
    path = ROOT / "scripts" / "check_doc_links.py"
    spec = importlib.util.spec_from_file_location("check_doc_links", path)
    assert spec is not None and spec.loader is not None
    checker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(checker)
    (tmp_path / "sub").mkdir()
    (tmp_path / "index.html").write_text(
        '<a href="sub/page.html#ok">a</a><a href="https://example.org/x">b</a>'
        '<a href="#top">c</a><h1 id="top">t</h1><img src="missing.png">'
        '<a href="sub/page.html#nope">d</a><a href="gone.html">e</a>'
    )
    (tmp_path / "sub" / "page.html").write_text('<section id="ok"><a href="../index.html">x</a>')
    problems = checker.broken_links(tmp_path)
    assert len(problems) == 3, problems
    assert any("missing.png" in p for p in problems)
    assert any("#nope" in p for p in problems)
    assert any("gone.html" in p for p in problems)


_ALLOWED_HTML = {"<br>"}


def test_placeholders_in_prose_are_code() -> None:
    """A ``<placeholder>`` outside backticks is swallowed as raw HTML by MyST: it must be code."""
    found = []
    for page in PAGES:
        in_fence = False
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            if line.strip().startswith(("```", "~~~")):
                in_fence = not in_fence
                continue
            prose = re.sub(r"`[^`]*`", "", line)
            if in_fence or prose.lstrip().startswith("<!--"):
                continue
            for tag in re.findall(r"<[A-Za-z][\w:-]*>", prose):
                if tag not in _ALLOWED_HTML:
                    found.append(f"{_rel(page)}:{n}: {tag}")
    assert not found, found
