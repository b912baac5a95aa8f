"""How long selenv takes to refuse work beyond its ceilings (the tests check *that* it does).

The tests assert that each refusal comes before the work it bounds; this measures how fast it
comes. Cases: ``selenv bench ... --episodes 1000000000`` in-process with the local and the process
executor (imports done) and as a fresh ``python -m selenv`` process; a PPO checkpoint whose
metadata declares ``hidden=[20000, 20000]`` and one nested 100,000 deep; a surrogate dataset
whose ``.npy`` header declares 3.4 million rows; ``selenv-train-surrogate --samples 10**9``;
a surrogate checkpoint declaring ``hidden=[20000, 20000]``; ``--executor ray --address`` at a
closed port. Each round checks that the refusal happened (exit code 2 or the expected error),
then prints the median and the maximum::

    .venv/bin/python benchmarks/bench_refusals.py --rounds 5
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = "selenv/FIMSelection-v1"
HUGE = ["bench", ENV, "--agents", "greedy,random", "--episodes", "1000000000",
        "--env-kwargs", '{"n_candidates": 20, "budget": 3}', "--no-progress"]  # fmt: skip


def _quiet(call: Callable[[], object]) -> object:
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        return call()


def _expect_exit_2(call: Callable[[], object]) -> None:
    try:
        rc = _quiet(call)
    except SystemExit as exc:
        rc = exc.code
    if rc != 2:
        raise RuntimeError(f"expected a refusal with exit 2, got {rc!r}")


def _expect_error(kind: type[BaseException], call: Callable[[], object]) -> Callable[[], None]:
    def refused() -> None:
        try:
            call()
        except kind:
            return
        raise RuntimeError(f"expected {kind.__name__}, nothing was raised")

    return refused


def _bench_in_process(executor: str) -> Callable[[], None]:
    from selenv.cli import main

    return lambda: _expect_exit_2(lambda: main([*HUGE, "--executor", executor]))


def _bench_subprocess(cwd: str) -> Callable[[], None]:
    def run() -> None:
        proc = subprocess.run([sys.executable, "-m", "selenv", *HUGE], cwd=cwd,
                              capture_output=True, timeout=300, check=False)  # fmt: skip
        if proc.returncode != 2:
            raise RuntimeError(f"expected exit 2, got {proc.returncode}: {proc.stderr!r}")

    return run


def _ppo_cases(folder: Path) -> dict[str, Callable[[], None]]:
    from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent

    shipped = DEFAULT_CHECKPOINTS[ENV]
    meta = json.loads(shipped.with_suffix(".json").read_text())
    cases = {}
    wide = {**meta, "architecture": {**meta["architecture"], "hidden": [20000, 20000]}}
    deep = '{"obs_layout": ' + "[" * 100_000 + "]" * 100_000 + "}"
    for name, text in (("wide", json.dumps(wide)), ("deep", deep)):
        out = folder / f"ppo_{name}.zip"
        shutil.copy(shipped, out)
        out.with_suffix(".json").write_text(text)
        cases[f"ppo checkpoint, {name} metadata"] = _expect_error(
            ValueError, lambda out=out: SB3PolicyAgent(out, env_id=ENV)
        )
    return cases


def _surrogate_cases(folder: Path) -> dict[str, Callable[[], None]]:
    from numpy.lib import format as npy_format

    from selenv.learned.surrogate_data import generate_dataset, load_dataset, save_dataset
    from selenv.learned.surrogates import Surrogate
    from selenv.train import train_surrogate

    data = save_dataset(generate_dataset(300, seed=3, workers=1, progress=False), folder / "d")
    with zipfile.ZipFile(data) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    header = io.BytesIO()
    npy_format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (3_400_000, 9, 9)}
    )
    members["P_i.npy"] = header.getvalue() + b"\0" * 1_000_000
    bomb = folder / "bomb.npz"
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf:
        for n, blob in members.items():
            zf.writestr(n, blob)
    pair = folder / "s.pt"
    tiny = ["--hidden", "8", "--epochs", "2", "--tensorboard-dir", "", "--no-progress"]
    _quiet(lambda: train_surrogate.main(["--data", str(data), "--out", str(pair), *tiny]))
    meta = json.loads(pair.with_suffix(".json").read_text())
    meta["architecture"]["hidden"] = [20000, 20000]
    pair.with_suffix(".json").write_text(json.dumps(meta))
    usage = ["--out", str(folder / "u.pt"), "--workers", "1", "--no-progress"]
    return {
        "surrogate dataset, 3.4M-row header": _expect_error(ValueError, lambda: load_dataset(bomb)),
        "selenv-train-surrogate --samples 10**9": lambda: _expect_exit_2(
            lambda: train_surrogate.cli([*usage, "--samples", str(10**9)])
        ),
        "surrogate checkpoint, wide metadata": _expect_error(
            ValueError, lambda: Surrogate.load(pair)
        ),
    }


def _ray_case() -> dict[str, Callable[[], None]]:
    try:
        import ray  # noqa: F401  (imported before timing)
    except ImportError:
        return {}
    from selenv.parallel import ExecutorError, RayExecutor

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def enter() -> None:
        with RayExecutor(address=f"127.0.0.1:{port}"):
            pass

    return {"--executor ray --address <closed port>": _expect_error(ExecutorError, enter)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5, help="refusals timed per case")
    a = ap.parse_args(argv)
    if a.rounds < 1:
        ap.error(f"--rounds must be >= 1, got {a.rounds}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cases: dict[str, Callable[[], None]] = {
            "selenv bench --episodes 10**9 (in-process, local)": _bench_in_process("local"),
            "selenv bench --episodes 10**9 (in-process, process)": _bench_in_process("process"),
            "selenv bench --episodes 10**9 (python -m selenv)": _bench_subprocess(tmp),
        }
        cases |= _ppo_cases(folder)
        cases |= _surrogate_cases(folder)
        cases |= _ray_case()
        for case in cases.values():  # imports and first-call work outside the timings
            case()
        print(f"{'case':58} {'median':>9} {'max':>9}   ({a.rounds} rounds)")
        for name, case in cases.items():
            times = []
            for _ in range(a.rounds):
                start = time.perf_counter()
                case()
                times.append(time.perf_counter() - start)
            print(f"{name:58} {statistics.median(times):8.3f}s {max(times):8.3f}s")


if __name__ == "__main__":
    main()
