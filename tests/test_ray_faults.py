"""``selenv bench --executor ray`` under real faults, with real Ray (no stand-in).

One test starts five benches at once (each with its own embedded Ray instance: one Ray
start-up costs several CPU-seconds, so they overlap) on a tiny ``FIMSelection-v1`` (agents
greedy and random, 2 episodes, one worker: 4 one-episode Ray tasks, one in flight). The
executor's test hook (``SELENV_TEST_RAY_HOLD_FROM_TASK=1``, see
:mod:`selenv.parallel.executors`) holds the tasks from index 1 on, so when task 1 announces
its worker's PID the bench has received task 0 (greedy's seed 0) and nothing else. Then each
bench gets its fault:

* SIGINT / SIGTERM to the bench: exit 130 / 143, one line, the previous ``--json`` replaced by
  the finished episode marked incomplete;
* SIGKILL of the Ray worker running task 1: exit 1, one line naming the worker's PID, the
  ``--json`` untouched and the episode in ``<json>.partial``;
* SIGKILL of Ray's dashboard agent (the raylet stops the node with it): exit 1, one line
  saying the node stopped because of the dashboard agent, the episode in ``.partial``;
* SIGKILL of the bench itself: Ray's processes die with it.

Every run must leave none of the processes it started (the bench's process tree seen while
the tasks were held, plus anything carrying the run's marker variable) running afterwards.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import _proc
import pytest

ROOT = Path(__file__).resolve().parents[1]
OLD = b'{"old": "valid results"}\n'
SCENARIOS = ("SIGINT", "SIGTERM", "worker", "agent", "main")
START_SECONDS = 180.0  # five Ray instances starting at once on a loaded 2-core machine
END_SECONDS = 60.0
GONE_SECONDS = 20.0


def _stat(pid: int) -> tuple[str, int, str] | None:
    """``(state, ppid, start time)`` of ``pid`` from ``/proc`` (``None``: gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return fields[0], int(fields[1]), fields[19]


def _tree(root: int) -> dict[int, str]:
    """``root`` and its descendants now: PID -> start time."""
    parents: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (st := _stat(int(entry.name))) is not None:
            parents.setdefault(st[1], []).append(int(entry.name))
    out: dict[int, str] = {}
    todo = [root]
    while todo:
        pid = todo.pop()
        st = _stat(pid)
        if st is not None and pid not in out:
            out[pid] = st[2]
            todo.extend(parents.get(pid, []))
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
    except OSError:
        return ""


def _marked(mark: str) -> set[int]:
    """Live processes whose environment holds ``SELENV_FAULT_MARK=<mark>``."""
    pids = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes()
        except OSError:
            continue
        st = _stat(int(entry.name))
        if st is not None and st[0] != "Z" and f"SELENV_FAULT_MARK={mark}".encode() in environ:
            pids.add(int(entry.name))
    return pids


class Run:
    """One ``selenv bench --executor ray`` in ``folder``, held after its first task."""

    def __init__(self, folder: Path) -> None:
        folder.mkdir()
        self.folder, self.out, self.hold = folder, folder / "out.json", folder / "hold"
        self.hold.mkdir()
        self.out.write_bytes(OLD)
        self.mark = uuid.uuid4().hex
        env = {k: v for k, v in os.environ.items() if not k.startswith("SELENV_TEST_")}
        env.update(
            PYTHONPATH=str(ROOT),
            OPENBLAS_NUM_THREADS="1",
            SELENV_FAULT_MARK=self.mark,
            SELENV_TEST_RAY_HOLD_FROM_TASK="1",
            SELENV_TEST_RAY_HOLD_DIR=str(self.hold),
        )
        args = ["bench", "selenv/FIMSelection-v1", "--agents", "greedy,random"]
        args += ["--episodes", "2", "--env-kwargs", '{"n_candidates": 20, "budget": 3}']
        args += ["--no-progress", "--json", str(self.out), "--executor", "ray"]
        args += ["--num-workers", "1"]
        self.proc = _proc.popen(
            [sys.executable, "-m", "selenv", *args],
            cwd=folder,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.tree: dict[int, str] = {}
        self.held = 0  # PID of the Ray worker holding task 1
        self.rc: int | None = None
        self.err = ""

    def is_held(self) -> bool:
        """Task 1 holds (so task 0 was received); then note the process tree."""
        announced = self.hold / "task-1.pid"
        if not announced.exists():
            return False
        self.held = int(announced.read_text())
        self.tree = _tree(self.proc.pid)
        return True

    def inject(self, fault: str) -> None:
        """Apply ``fault`` (one of :data:`SCENARIOS`)."""
        if fault in ("SIGINT", "SIGTERM"):
            self.proc.send_signal(signal.Signals[fault])
        elif fault == "worker":
            os.kill(self.held, signal.SIGKILL)
        elif fault == "agent":
            agents = [p for p in self.tree if _cmdline(p).startswith("ray::DashboardAgent")]
            assert len(agents) == 1, {p: _cmdline(p) for p in self.tree}
            os.kill(agents[0], signal.SIGKILL)
        else:
            self.proc.kill()

    def finish(self) -> None:
        """Wait for the bench's exit and collect its stderr."""
        _, self.err = _proc.communicate(self.proc, END_SECONDS)
        self.rc = self.proc.returncode

    def left(self) -> set[int]:
        """Processes of this run still running (tree snapshot, same start time; marked ones)."""
        alive = {
            pid
            for pid, start in self.tree.items()
            if (st := _stat(pid)) is not None and st[2] == start and st[0] != "Z"
        }
        return alive | _marked(self.mark)

    def wait_gone(self) -> dict[int, str]:
        """Wait up to :data:`GONE_SECONDS` for every process of the run to end; the rest."""
        deadline = time.monotonic() + GONE_SECONDS
        while (left := self.left()) and time.monotonic() < deadline:
            time.sleep(0.1)
        return {pid: _cmdline(pid)[:80] for pid in left}

    def stop(self) -> None:
        """Kill whatever of this run is still running (after a failed assertion)."""
        for pid in self.left() | ({self.proc.pid} if self.proc.poll() is None else set()):
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        if self.proc.poll() is None:
            _proc.wait(self.proc, 10)


def _episodes(path: Path) -> dict[str, int]:
    top = json.loads(path.read_text())
    assert top["complete"] is False
    return top["results"][0]["episodes_done"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_ray_faults_keep_the_finished_episodes_and_leave_no_process(tmp_path: Path) -> None:
    """Five benches on real Ray, each broken once (module docstring)."""
    pytest.importorskip("ray")
    runs = {fault: Run(tmp_path / fault) for fault in SCENARIOS}
    try:
        deadline = time.monotonic() + START_SECONDS
        waiting = dict(runs)
        while waiting and time.monotonic() < deadline:
            for fault, run in list(waiting.items()):
                if run.proc.poll() is not None:
                    err = _proc.communicate(run.proc, 30)[1]
                    pytest.fail(f"{fault}: bench ended early: {err}")
                if run.is_held():
                    run.inject(fault)
                    del waiting[fault]
            time.sleep(0.05)
        assert not waiting, f"not held within {START_SECONDS} s: {sorted(waiting)}"
        for run in runs.values():
            run.finish()
        left = {fault: run.wait_gone() for fault, run in runs.items()}
    finally:
        for run in runs.values():
            run.stop()

    for fault, run in runs.items():
        assert left[fault] == {}, f"{fault}: Ray processes left running: {left[fault]}"
        assert len(run.tree) >= 6, f"{fault}: expected Ray's processes under the bench"
        if fault == "main":
            assert run.rc == -signal.SIGKILL
            assert run.out.read_bytes() == OLD
            continue
        assert "Traceback" not in run.err and "KeyboardInterrupt" not in run.err, run.err
        lines = [ln for ln in run.err.splitlines() if ln.strip()]
        assert len(lines) == 1, f"{fault}: {run.err}"
        line = lines[0]
        if fault in ("SIGINT", "SIGTERM"):
            assert run.rc == (130 if fault == "SIGINT" else 143), run.err
            word = "interrupted (SIGINT)" if fault == "SIGINT" else "terminated (SIGTERM)"
            assert line.startswith(f"selenv: {word}; kept 1 finished episodes in {run.out}"), line
            assert _episodes(run.out) == {"greedy": 1, "random": 0}
            kept = {"out.json"}
        else:
            assert run.rc == 1, run.err
            if fault == "worker":
                assert "a Ray worker died while running task 1" in line, line
                assert f"worker PID {run.held}" in line, line
            else:
                assert "a Ray node stopped while running task 1" in line, line
                assert "dashboard_agent" in line, line
            partial = run.out.with_name("out.json.partial")
            assert f"kept 1 finished episodes in {partial}" in line, line
            assert run.out.read_bytes() == OLD
            assert _episodes(partial) == {"greedy": 1, "random": 0}
            kept = {"out.json", "out.json.partial"}
        assert sorted(p.name for p in run.folder.iterdir()) == sorted(kept | {"hold"})


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_guard_kills_the_listed_processes_when_its_input_ends() -> None:
    """The guard of an embedded Ray instance, on ``sleep`` processes: in a session of its own,
    at the end of its input it kills the process listed with its start time and spares one
    whose start time does not match (a reused PID) and one not listed."""
    from selenv.parallel.ray_session import _spawn_guard, _stop_guard

    listed, reused, other = (_proc.popen(["sleep", "60"]) for _ in range(3))
    guard = _spawn_guard([listed.pid])
    try:
        assert os.getsid(guard.pid) == guard.pid
        assert guard.stdin is not None
        guard.stdin.write(f"{reused.pid} 1\n".encode())  # a start time that is not its own
        time.sleep(0.2)
        assert listed.poll() is None and guard.poll() is None  # nothing before the end of input
        _stop_guard(guard)
        assert guard.returncode == 0
        assert _proc.wait(listed, 10) == -signal.SIGKILL
        assert reused.poll() is None and other.poll() is None
    finally:
        for proc in (listed, reused, other, guard):
            _proc.stop(proc)
