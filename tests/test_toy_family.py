"""A family written from ``docs/guide/adding_a_family.md`` alone: family tests and bench pass.

The guide's files (its ``{code-block}`` blocks captioned ``selenv/families/toy/...``) are written
into a temporary copy of the installed ``selenv`` package, the guide's one line is added to the
copy's ``selenv/families/__init__.py``, and child interpreters that import the copy run
``tests/test_families.py`` on the new family and ``selenv bench`` on its id. A child process
sees the family exactly as a contributor's checkout would: registered at import, by every
module that reads the family records; this process's registries are never touched.
"""

from __future__ import annotations

import ast
import json
import math
import os
import re
import shutil
import sys
from pathlib import Path

import _proc
import pytest
import test_families
from _codeblocks import fenced_blocks

import selenv

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guide" / "adding_a_family.md"
FAMILY_DIR = "selenv/families/toy"
#: the files the guide's step 1 and 2 say a family has at least
REQUIRED = {"__init__.py", "scenario.py", "env.py", "agents.py"}
TOY_ID = "selenv/Toy-v1"
#: the family tests that run on every family (parametrised over the records)
PER_FAMILY_TESTS = sorted(
    name
    for name, test in vars(test_families).items()
    if name.startswith("test_")
    and any(
        m.name == "parametrize" and m.args[0] == "spec" for m in getattr(test, "pytestmark", [])
    )
)


def guide_files(text: str, folder: str = FAMILY_DIR) -> dict[str, str]:
    """``{file name: source}`` of the guide's code blocks captioned ``<folder>/<file>``.

    A MyST ``{code-block}`` carries its options (``:caption: path``, the path in backticks or
    not) on its first lines.
    """
    files: dict[str, str] = {}
    for info, _line, src in fenced_blocks(text):
        if not info.startswith("{code-block}"):
            continue
        lines = src.splitlines(keepends=True)
        options: dict[str, str] = {}
        while lines and (match := re.match(r"^:(\w+):\s*(.*)$", lines[0].strip())):
            options[match[1]] = match[2].strip()
            lines.pop(0)
        caption = options.get("caption", "").strip("`")
        if caption.startswith(folder + "/"):
            files[caption.removeprefix(folder + "/")] = "".join(lines).lstrip("\n")
    return files


def add_family_line(source: str, name: str) -> str:
    """The guide's step 3 on ``selenv/families/__init__.py``: import ``name``, list its record."""
    tree = ast.parse(source)
    imports = [
        node
        for node in tree.body
        if isinstance(node, ast.ImportFrom) and node.module == "selenv.families"
    ]
    records = [
        node.value
        for node in tree.body
        if isinstance(node, ast.AnnAssign | ast.Assign)
        and isinstance(node.value, ast.Tuple)
        and any(
            isinstance(t, ast.Name) and t.id == "FAMILIES"
            for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
        )
    ]
    if len(imports) != 1 or len(records) != 1 or not records[0].elts:
        raise AssertionError(
            "selenv/families/__init__.py no longer has one 'from selenv.families import ...' "
            "and one FAMILIES tuple: update step 3 of the guide and this test"
        )
    lines = source.splitlines(keepends=True)
    last = records[0].elts[-1]
    assert last.end_lineno is not None and last.end_col_offset is not None
    row = lines[last.end_lineno - 1]
    lines[last.end_lineno - 1] = (
        f"{row[: last.end_col_offset]}, {name}.SPEC{row[last.end_col_offset :]}"
    )
    assert imports[0].end_lineno is not None
    lines.insert(imports[0].end_lineno, f"from selenv.families import {name}\n")
    return "".join(lines)


def build_package(tmp_path: Path, files: dict[str, str]) -> Path:
    """A copy of the installed ``selenv`` with the family ``files`` and its line; its parent."""
    src = tmp_path / "src"
    package = src / "selenv"
    shutil.copytree(
        Path(selenv.__file__).parent, package, ignore=shutil.ignore_patterns("__pycache__")
    )
    folder = src / FAMILY_DIR
    folder.mkdir()
    for name, text in files.items():
        (folder / name).write_text(text, encoding="utf-8")
    init = package / "families" / "__init__.py"
    init.write_text(add_family_line(init.read_text(encoding="utf-8"), "toy"), encoding="utf-8")
    return src


def child_env(src: Path) -> dict[str, str]:
    """This process's environment with ``src`` first on the child's path, one BLAS thread."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_XDIST")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(src), env.get("PYTHONPATH")) if p)
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return env


@pytest.fixture(scope="module")
def toy_files() -> dict[str, str]:
    """The family's files exactly as the guide prints them."""
    files = guide_files(GUIDE.read_text(encoding="utf-8"))
    missing = REQUIRED - set(files)
    assert not missing, f"the guide shows no {FAMILY_DIR}/{sorted(missing)}"
    return files


@pytest.fixture(scope="module")
def toy_src(tmp_path_factory: pytest.TempPathFactory, toy_files: dict[str, str]) -> Path:
    """The package copy with the guide's family (shared: the children only read it)."""
    return build_package(tmp_path_factory.mktemp("toy"), toy_files)


def run_bench(src: Path, tmp_path: Path) -> tuple[int, str, str, Path]:
    """``python -m selenv bench selenv/Toy-v1`` (2 episodes, random and greedy) on ``src``."""
    out = tmp_path / "bench.json"
    argv = ["--agents", "random,greedy", "--baseline", "random", "--episodes", "2", "--seed", "0"]
    proc = _proc.run(
        [sys.executable, "-m", "selenv", "bench", TOY_ID, *argv, "--json", out, "--no-progress"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=child_env(src),
        timeout=300,
    )
    return proc.returncode, proc.stdout, proc.stderr, out


def test_the_guides_family_passes_every_family_test(tmp_path: Path, toy_src: Path) -> None:
    """``tests/test_families.py`` on the copy: every per-family test passes for ``toy``."""
    assert PER_FAMILY_TESTS, "no per-family test found in tests/test_families.py"
    tests = ROOT / "tests" / "test_families.py"
    options = ["-q", "-rA", "-p", "no:cacheprovider", "-k", "toy or unique_and_in"]
    proc = _proc.run(
        [sys.executable, "-m", "pytest", *options, tests],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=child_env(toy_src),
        timeout=300,
    )
    output = proc.stdout + proc.stderr
    passed = set(re.findall(r"PASSED \S*test_families\.py::(\w+)\[toy\]", output))
    assert proc.returncode == 0 and passed == set(PER_FAMILY_TESTS), output[-6000:]
    assert re.search(r"PASSED \S*::test_families_are_unique_and_in_selenv_list_order", output)


def test_the_guides_family_plays_in_selenv_bench(tmp_path: Path, toy_src: Path) -> None:
    """Both agents play the same seeds; greedy, optimal on this family, never trails random."""
    rc, stdout, stderr, out = run_bench(toy_src, tmp_path)
    assert rc == 0, stderr[-4000:]
    assert "greedy" in stdout and "random" in stdout
    (doc,) = json.loads(out.read_text(encoding="utf-8"))["results"]
    assert doc["env_id"] == TOY_ID and doc["episodes"] == 2
    agents = doc["agents"]
    assert set(agents) == {"random", "greedy"}
    for result in agents.values():
        assert len(result["returns"]) == len(result["final_objectives"]) == 2
        assert all(math.isfinite(v) for v in result["final_objectives"])
    greedy, rand = agents["greedy"]["final_objectives"], agents["random"]["final_objectives"]
    assert all(g >= r for g, r in zip(greedy, rand, strict=True))
    assert agents["greedy"]["paired"]["baseline"] == "random"


def test_an_env_without_invalid_action_is_refused_in_one_line(
    tmp_path: Path, toy_files: dict[str, str]
) -> None:
    """The bench plays a family strictly; an env without the keyword is a usage error naming it."""
    loose = (
        "\n\nclass LooseToyEnv(ToyEnv):\n    def __init__(self, n: int = 6, k: int = 2) -> None:\n"
    )
    loose += "        super().__init__(n=n, k=k)\n"
    files = {
        **toy_files,
        "env.py": toy_files["env.py"] + loose,
        "__init__.py": toy_files["__init__.py"].replace("env:ToyEnv", "env:LooseToyEnv"),
    }
    assert files["__init__.py"] != toy_files["__init__.py"]
    src = build_package(tmp_path, files)
    rc, stdout, stderr, _ = run_bench(src, tmp_path)
    assert rc == 2, stdout + stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "invalid_action='raise'" in lines[0], stderr
    assert "adding an env family" in lines[0] and "--env-kwargs" not in lines[0], stderr


def test_the_one_line_edit_and_the_guide_reader() -> None:
    """The helpers above do what the guide says, and fail loudly when it no longer applies."""
    source = (
        "from selenv.families import a, b\n\nFAMILIES: tuple = (\n    a.SPEC,\n    b.SPEC,\n)\n"
    )
    edited = add_family_line(source, "toy")
    assert "from selenv.families import toy\n" in edited
    tree = ast.parse(edited)
    assert [ast.unparse(e) for e in tree.body[-1].value.elts] == ["a.SPEC", "b.SPEC", "toy.SPEC"]  # type: ignore[attr-defined]
    with pytest.raises(AssertionError, match="step 3"):
        add_family_line("FAMILIES = ()\n", "toy")
    text = "```{code-block} python\n:caption: `selenv/families/toy/x.py`\n\nX = 1\n```\n"
    assert (
        guide_files(text)
        == {"x.py": "X = 1\n"}
        == guide_files(text.replace("`selenv/families/toy/x.py`", "selenv/families/toy/x.py"))
    )
    assert guide_files(text.replace("toy/", "other/")) == {}
