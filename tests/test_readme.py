"""Every ```python block of README.md runs as pasted.

Each fenced block whose info string is exactly ``python`` is one test case (id: the block's
index and its first line). A block runs

* in a fresh namespace (``{"__name__": "__main__"}``): it must import and set up every name it
  uses, so a reader can paste any single block into a new interpreter;
* from a temporary working directory (``monkeypatch.chdir(tmp_path)``), so whatever it writes
  (logs, checkpoints, figures) lands there and never in the repository, and a relative path to
  a repository file (``"checkpoints/ldmv.pt"``) fails as it would for a user of an installed
  package;
* with matplotlib's Agg backend (headless);
* under a wall-clock guard of ``BLOCK_TIMEOUT`` seconds (SIGALRM, where available): README
  blocks are meant to run in seconds.

A block fails the test if it raises (including ``SyntaxError`` and the timeout).

Convention for blocks that must not run: a first line ``# not run: <reason>`` skips the block
with that reason (reported by ``-ra``). Use it sparingly -- for a block that needs a cluster,
network access or legitimately takes more than about 20 s -- and prefer a ``bash`` block for
commands. ``bash`` (and any other non-``python``) blocks are never executed here.
"""

from __future__ import annotations

import os
import re
import signal
from pathlib import Path

import pytest
from _codeblocks import (  # tests/ helper
    Block,
    BlockTimeout,
    block_id,
    fenced_blocks,
    python_blocks,
    run_block,
    sandbox,
)

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = python_blocks(README.read_text(encoding="utf-8"))
_block_id = block_id
__all__ = ["sandbox"]  # the fixture, imported for the tests below


@pytest.mark.parametrize("block", BLOCKS, ids=[_block_id(b) for b in BLOCKS])
def test_readme_python_block_runs(block: Block, sandbox: Path) -> None:
    """The block runs as pasted into a fresh interpreter, from an empty directory."""
    if block.skip_reason is not None:
        pytest.skip(f"README.md:{block.line}: not run: {block.skip_reason}")
    run_block(block)
    assert Path.cwd() == sandbox, "a README block changed the working directory"


# -- the harness itself ---------------------------------------------------------------------------


def test_readme_has_python_blocks_and_skips_are_rare() -> None:
    """The README is parsed (its quick start found) and no block is skipped.

    The README is short (the site's pages hold the examples, run by ``tests/test_docs.py``);
    whatever python it shows must run.
    """
    assert len(BLOCKS) >= 1
    skipped = [b for b in BLOCKS if b.skip_reason is not None]
    assert not skipped, [f"README.md:{b.line}: {b.skip_reason}" for b in skipped]


def test_only_python_fences_are_collected() -> None:
    """``bash``, untagged and other fences are never run; ``python`` ones all are."""
    text = README.read_text(encoding="utf-8")
    infos = [info for info, _, _ in fenced_blocks(text)]
    assert "bash" in infos  # the README has command blocks: they must not be executed
    assert len(BLOCKS) == sum(info.split()[:1] == ["python"] for info in infos)
    sample = (
        "text\n```bash\nrm -rf /\n```\n\n```python\nx = 1\n```\n```\nuntagged\n```\n"
        "````python\ny = '```'\n```\nz = 2\n````\n~~~python\n# not run: needs a cluster\n~~~\n"
    )
    blocks = python_blocks(sample)
    assert [b.source for b in blocks] == [
        "x = 1\n",
        "y = '```'\n```\nz = 2\n",
        "# not run: needs a cluster\n",
    ]
    assert [b.line for b in blocks] == [6, 12, 17]
    assert [b.skip_reason for b in blocks] == [None, None, "needs a cluster"]


def test_a_failing_block_fails(sandbox: Path) -> None:
    """The runner propagates errors: a block using a name it did not define raises."""
    with pytest.raises(NameError):
        run_block(Block(0, 1, "import numpy as np\nprint(np.zeros(2) + undefined_name)\n"))
    with pytest.raises(SyntaxError):
        run_block(Block(0, 1, "def broken(:\n"))


def test_blocks_run_in_fresh_namespaces_and_in_the_sandbox(sandbox: Path) -> None:
    """Names do not leak between blocks; files go to the temporary directory."""
    first = run_block(Block(0, 1, "leaked = 1\nopen('out.txt', 'w').write('x')\n"))
    assert first["leaked"] == 1
    assert (sandbox / "out.txt").is_file()
    with pytest.raises(NameError):
        run_block(Block(1, 5, "leaked\n"))


@pytest.mark.skipif(not hasattr(signal, "SIGALRM"), reason="SIGALRM guard is POSIX-only")
def test_timeout_guard(sandbox: Path) -> None:
    """A block that runs too long is stopped with ``BlockTimeout``."""
    with pytest.raises(BlockTimeout):
        run_block(Block(0, 1, "import time\nwhile True:\n    time.sleep(0.01)\n"), timeout=0.2)
    assert os.getcwd() == str(sandbox)


def test_readme_is_short_and_links_into_the_site() -> None:
    """The README fits on a few screens (<= 12 KB) and its relative links name existing files."""
    text = README.read_text(encoding="utf-8")
    assert len(text.encode("utf-8")) <= 12 * 1024
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if "://" not in link]
    assert any(link.startswith("docs/") for link in local)
    missing = [link for link in local if not (README.parent / link).exists()]
    assert not missing, missing
