"""Scale-out: the same command on the local, process and Ray executors, wall time and ratio.

Each workload is run as a subprocess once per executor (``--executor local``, then ``process``
and ``ray`` with ``--num-workers``), so the wall time includes everything a user waits for
(imports, spawning the pool, starting and stopping the embedded Ray instance). The JSON outputs
are compared: returns / objectives (bench) or the printed numbers (reproduction) must be
identical on every executor, else the script exits 1.

Workloads (``--workloads``):

* ``bench``: ``selenv bench selenv/CLScheduling-v1 selenv/LandmarkSelection-v1 --episodes 6``
  (every default agent, rollout references included);
* ``greiff``: ``scripts/reproduce_greiff.py --runs 16 --table-runs 4 --steps 200``
  (Monte Carlo of the GA over noise realisations).

    .venv/bin/python benchmarks/bench_executors.py [--num-workers 2] [--workloads bench,greiff]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
SELENV = [PY, "-m", "selenv"]
EXECUTORS = ("local", "process", "ray")


def _bench(out: Path, executor: str, workers: int) -> list[str]:
    return [
        *SELENV, "bench", "selenv/CLScheduling-v1", "selenv/LandmarkSelection-v1",
        "--episodes", "6", "--no-progress", "--json", str(out),
        "--executor", executor, "--num-workers", str(workers),
    ]  # fmt: skip


def _greiff(out: Path, executor: str, workers: int) -> list[str]:
    return [
        PY, str(ROOT / "scripts" / "reproduce_greiff.py"), "--runs", "16", "--table-runs", "4",
        "--steps", "200", "--out", str(out.parent / f"fig_{executor}"),
        "--executor", executor, "--num-workers", str(workers),
    ]  # fmt: skip


def _bench_numbers(out: Path, stdout: str) -> Any:
    doc = json.loads(out.read_text())
    return [
        {name: (a.get("returns"), a.get("final_objectives"), a.get("skipped"))
         for name, a in r["agents"].items()}
        for r in doc["results"]
    ]  # fmt: skip


def _greiff_numbers(out: Path, stdout: str) -> Any:
    # the printed tables (everything but the wall-time line) are the results
    return [line for line in stdout.splitlines() if "wall time" not in line]


WORKLOADS = {"bench": (_bench, _bench_numbers), "greiff": (_greiff, _greiff_numbers)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--num-workers", type=int, default=2, help="pool / Ray workers (default 2)")
    ap.add_argument("--workloads", default="bench,greiff", help="comma-separated: bench,greiff")
    args = ap.parse_args()
    ok = True
    for name in args.workloads.split(","):
        build, numbers = WORKLOADS[name]
        walls: dict[str, float] = {}
        results: dict[str, Any] = {}
        with tempfile.TemporaryDirectory() as tmp:
            for ex in EXECUTORS:
                out = Path(tmp) / f"{ex}.json"
                cmd = build(out, ex, args.num_workers)
                t0 = time.perf_counter()
                proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, check=False)
                walls[ex] = time.perf_counter() - t0
                if proc.returncode != 0:
                    print(proc.stderr[-2000:], file=sys.stderr)
                    return 1
                results[ex] = numbers(out, proc.stdout)
        same = results["process"] == results["local"] and results["ray"] == results["local"]
        ok &= same
        print(f"\n{name}: {' '.join(build(Path('OUT.json'), 'EXECUTOR', args.num_workers))}")
        print(f"{'executor':<10}{'wall s':>9}{'speed-up vs local':>20}")
        for ex in EXECUTORS:
            print(f"{ex:<10}{walls[ex]:>9.1f}{walls['local'] / walls[ex]:>19.2f}x")
        print(f"results identical on all three executors: {same}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
