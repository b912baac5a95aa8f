"""Time from exec until ``selenv bench`` handles SIGTERM, optionally against another checkout.

A SIGTERM before the handler is installed kills the process without a message. Each round
starts ``python -m selenv bench`` in a fresh process and polls ``/proc/PID/status`` (Linux)
until ``SigCgt`` has SIGTERM's bit; a bare Python that installs a handler as its first
statement is the floor. Prints the median and maximum per command::

    .venv/bin/python benchmarks/bench_signal_window.py --rounds 7
    .venv/bin/python benchmarks/bench_signal_window.py --rounds 7 --compare /tmp/old  # a checkout
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ("-m", "selenv", "bench", "selenv/FIMSelection-v1", "--episodes", "30", "--no-progress")
FLOOR = ("-c", "import signal, time; signal.signal(signal.SIGTERM, print); time.sleep(60)")


def _caught(pid: int) -> int:
    """The ``SigCgt`` mask of ``pid`` (0 if it cannot be read)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return int(line.split()[1], 16)
    except OSError:
        pass
    return 0


def window(args: tuple[str, ...], root: Path, cwd: str, deadline: float = 120.0) -> float:
    """Seconds from ``Popen`` until the child catches SIGTERM (``root`` first on the path)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    bit = 1 << (signal.SIGTERM - 1)
    start = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        while not _caught(proc.pid) & bit:
            if proc.poll() is not None or time.perf_counter() - start > deadline:
                raise RuntimeError(f"{' '.join(args)}: no SIGTERM handler (exit {proc.poll()})")
            time.sleep(0.001)
        return time.perf_counter() - start
    finally:
        proc.kill()
        proc.wait(timeout=60)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="processes per command")
    parser.add_argument("--compare", type=Path, help="another checkout to measure too")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error(f"--rounds: expected an integer >= 1, got {args.rounds}")
    if not Path("/proc/self/status").exists():
        parser.error("reads /proc/PID/status: Linux only")
    runs = {"python (floor)": (FLOOR, ROOT), "selenv bench": (BENCH, ROOT)}
    if args.compare is not None:
        runs[f"selenv bench ({args.compare})"] = (BENCH, args.compare.resolve())
    times: dict[str, list[float]] = {name: [] for name in runs}
    with tempfile.TemporaryDirectory() as cwd:
        for _ in range(args.rounds):  # interleaved: the machine's load hits every command
            for name, (cmd, root) in runs.items():
                times[name].append(window(cmd, root, cwd))
    for name, values in times.items():
        print(f"{name:<40} median {statistics.median(values):6.3f} s   max {max(values):6.3f} s")


if __name__ == "__main__":
    main()
