"""Start-up time of ``selenv --help`` and ``selenv list``, optionally against another checkout.

Each round runs ``python -m selenv ARGS`` in a fresh process from a neutral folder (so the
current directory does not shadow ``PYTHONPATH``), interleaving the checkouts; prints the
median and minimum wall time per command::

    .venv/bin/python benchmarks/bench_cli_start.py --rounds 7
    .venv/bin/python benchmarks/bench_cli_start.py --rounds 7 --compare /tmp/old   # a worktree
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COMMANDS = (("--help",), ("list",))


def wall(root: Path, args: tuple[str, ...], cwd: str) -> float:
    """Seconds of one ``python -m selenv ARGS`` with ``root`` first on ``PYTHONPATH``."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "selenv", *args], cwd=cwd, env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7, help="processes per command and checkout")
    ap.add_argument("--compare", type=Path, help="another checkout's root (e.g. a git worktree)")
    a = ap.parse_args(argv)
    roots = {"this": Path(__file__).resolve().parents[1]}
    if a.compare is not None:
        roots["compare"] = a.compare.resolve()
    times: dict[tuple[str, str], list[float]] = {}
    with tempfile.TemporaryDirectory() as cwd:
        for _ in range(a.rounds):
            for name, root in roots.items():
                for args in COMMANDS:
                    times.setdefault((name, " ".join(args)), []).append(wall(root, args, cwd))
    for (name, cmd), t in sorted(times.items()):
        print(f"{name:8} selenv {cmd:7} median {statistics.median(t):.3f} s  min {min(t):.3f} s")


if __name__ == "__main__":
    main()
