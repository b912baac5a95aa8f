"""Fenced code blocks of Markdown files: parsing, and running ``python`` blocks as pasted.

Shared by ``tests/test_readme.py`` (README.md) and ``tests/test_docs.py`` (the site's pages).
A block runs in a fresh namespace (``{"__name__": "__main__"}``), from a temporary working
directory, with matplotlib's Agg backend and under a wall-clock guard of ``BLOCK_TIMEOUT``
seconds (SIGALRM, where available). A first line ``# not run: <reason>`` skips a block.
"""

from __future__ import annotations

import linecache
import re
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import pytest

NOT_RUN = re.compile(r"^#\s*not run:\s*(?P<reason>\S.*)$")
BLOCK_TIMEOUT = 60  # seconds of wall clock per block (a slow shared CI box, not a target)
_FENCE_OPEN = re.compile(r"^(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`]*)$")


@dataclass(frozen=True)
class Block:
    """One fenced code block: its index among the python blocks, first line number, source."""

    index: int
    line: int
    source: str

    @property
    def first_line(self) -> str:
        """The first non-empty line of the source (for the test id)."""
        return next((s.strip() for s in self.source.splitlines() if s.strip()), "<empty>")

    @property
    def skip_reason(self) -> str | None:
        """The reason of a ``# not run: <reason>`` first line, else ``None``."""
        match = NOT_RUN.match(self.first_line)
        return match["reason"].strip() if match else None


def fenced_blocks(text: str) -> Iterator[tuple[str, int, str]]:
    """``(info string, 1-based line of the opening fence, source)`` of every fenced block.

    A fence closes on a line of the same character, at least as long, and nothing else
    (CommonMark); an unclosed fence runs to the end of the text.
    """
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        match = _FENCE_OPEN.match(lines[i].strip()) if not lines[i].startswith("    ") else None
        if match is None:
            i += 1
            continue
        fence, info, start = match["fence"], match["info"].strip(), i
        body: list[str] = []
        i += 1
        while i < len(lines):
            stripped = lines[i].strip()
            if stripped and set(stripped) == {fence[0]} and len(stripped) >= len(fence):
                break
            body.append(lines[i])
            i += 1
        i += 1
        yield info, start + 1, "\n".join(body) + "\n"


def python_blocks(text: str) -> list[Block]:
    """The blocks fenced as ``python`` (the info string's first word), in order."""
    found = [
        (line, src) for info, line, src in fenced_blocks(text) if info.split()[:1] == ["python"]
    ]
    return [Block(k, line, src) for k, (line, src) in enumerate(found)]


def block_id(block: Block) -> str:
    """A short pytest id: the block's index, line and first line."""
    first = re.sub(r"[^\w.=()\"',:/ -]", "", block.first_line)[:60].strip()
    return f"{block.index:02d}-L{block.line}-{first}"


class BlockTimeout(Exception):
    """A block ran longer than ``BLOCK_TIMEOUT``."""


def run_block(
    block: Block, timeout: float = BLOCK_TIMEOUT, source: str = "README.md"
) -> dict[str, object]:
    """Execute ``block`` (from file ``source``) in a fresh namespace under a SIGALRM guard."""
    filename = f"{source}:{block.line}(python block {block.index})"
    # tracebacks show the README's lines instead of "???"
    linecache.cache[filename] = (len(block.source), None, block.source.splitlines(True), filename)
    code = compile(block.source, filename, "exec")
    namespace: dict[str, object] = {"__name__": "__main__"}
    use_alarm = hasattr(signal, "SIGALRM") and threading.current_thread() is threading.main_thread()
    previous = None
    if use_alarm:

        def _expire(signum: int, frame: FrameType | None) -> None:
            raise BlockTimeout(f"{source}:{block.line}: the block ran longer than {timeout} s")

        previous = signal.signal(signal.SIGALRM, _expire)
        # the per-test hang guard (pytest-timeout) may have its own alarm armed: re-armed after
        outer_left, _ = signal.setitimer(signal.ITIMER_REAL, timeout)
        armed_at = time.monotonic()
    try:
        exec(code, namespace)
    finally:
        if use_alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, signal.SIG_DFL if previous is None else previous)
            if outer_left > 0:
                left = outer_left - (time.monotonic() - armed_at)
                signal.setitimer(signal.ITIMER_REAL, max(left, 1e-3))
    return namespace


@pytest.fixture
def sandbox(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A temporary cwd, the Agg backend, no pyplot figures left behind, sys.path unchanged.

    The process-wide registries a block may extend (selenv's agents and objectives,
    Gymnasium's ids) are restored afterwards, so an example that registers its own agent
    cannot change what later tests in the same worker see.
    """
    import gymnasium as gym
    import matplotlib

    from selenv.agents import base as agent_base
    from selenv.core import objective_registry

    agents = {name: dict(by_env) for name, by_env in agent_base.AGENTS.items()}
    order = {env_id: list(names) for env_id, names in agent_base._ORDER.items()}
    objectives = dict(objective_registry._REGISTRY)
    env_ids = dict(gym.registry)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    matplotlib.use("Agg", force=True)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    try:
        yield tmp_path
    finally:
        import matplotlib.pyplot as plt

        plt.close("all")
        agent_base.AGENTS.clear()
        agent_base.AGENTS.update(agents)
        agent_base._ORDER.clear()
        agent_base._ORDER.update(order)
        objective_registry._REGISTRY.clear()
        objective_registry._REGISTRY.update(objectives)
        for env_id in set(gym.registry) - set(env_ids):
            del gym.registry[env_id]
