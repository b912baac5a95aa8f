"""``selenv bench`` never loses a result: fault injection on the real command.

Each test runs ``python -m selenv bench`` (or :func:`selenv.cli.main`) on a tiny
``FIMSelection-v1`` (20 candidates, budget 3, agents greedy and random) and breaks it on
purpose: a full file system (a 64 KiB tmpfs, where root may mount one), a file-size limit
(``RLIMIT_FSIZE``: EFBIG), SIGINT / SIGTERM after a chosen episode (the runner's test hooks
``SELENV_TEST_SIGNAL_AFTER_EPISODES`` / ``SELENV_TEST_PAUSE_AFTER_EPISODES``, see
:mod:`selenv.bench.runner`), a second bench on the same outputs, a process-pool worker killed
with SIGKILL, a huge ``--episodes``. Each asserts the exit code, the one line on stderr, that
the previous output is byte-identical (or replaced by the kept results) and that no temporary
file is left.
"""

from __future__ import annotations

import errno
import json
import os
import resource
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import _proc
import pytest

from selenv.atomic import OutputLock
from selenv.bench.results import AgentResult, EnvBenchResult
from selenv.cli import main

ROOT = Path(__file__).resolve().parents[1]
ENV = "selenv/FIMSelection-v1"
KWARGS = '{"n_candidates": 20, "budget": 3}'
OLD = b'{"old": "valid results"}\n'


def _bench_args(*extra: str, episodes: int = 4) -> list[str]:
    return [
        "bench",
        ENV,
        "--agents",
        "greedy,random",
        "--episodes",
        str(episodes),
        "--env-kwargs",
        KWARGS,
        "--no-progress",
        *extra,
    ]


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SELENV_TEST_")}
    env["PYTHONPATH"] = str(ROOT)
    env.update(extra)
    return env


def _run(args: list[str], cwd: Path, timeout: float = 60, **kwargs: object) -> tuple[int, str]:
    proc = _proc.run(
        [sys.executable, "-m", "selenv", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kwargs,  # type: ignore[call-overload]
    )
    return proc.returncode, proc.stderr


def _lines(stderr: str) -> list[str]:
    """stderr without the test hook's own lines."""
    return [ln for ln in stderr.splitlines() if ln and not ln.startswith("selenv: test hook")]


def _leftovers(folder: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


def _fill(folder: Path, leave_pages: int) -> None:
    """Fill ``folder``'s file system with 4 KiB files, then free ``leave_pages`` of them."""
    fillers = []
    for i in range(100):
        f = folder / f"filler{i}"
        try:
            f.write_bytes(b"x" * 4096)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
            f.unlink(missing_ok=True)
            break
        fillers.append(f)
    for f in fillers[:leave_pages]:
        f.unlink()


# -- full disk, file-size limit ------------------------------------------------------------------


def test_full_disk_keeps_the_old_json_and_says_the_results_could_not_be_kept(
    tiny_fs: Path,
) -> None:
    """Room for the up-front probe and the lock, not for the JSON: exit 1, one line, old intact."""
    out = tiny_fs / "out.json"
    out.write_bytes(OLD)
    _fill(tiny_fs, leave_pages=2)
    before = set(p.name for p in tiny_fs.iterdir())
    rc, err = _run(_bench_args("--json", str(out)), tiny_fs.parent, env=_env())
    assert rc == 1, err
    lines = _lines(err)
    assert len(lines) == 1, err
    assert f"cannot write {out}" in lines[0] and "ENOSPC" in lines[0]
    assert "could not be kept" in lines[0] and "Traceback" not in err
    assert out.read_bytes() == OLD
    assert _leftovers(tiny_fs, before) == []  # no temporary, no .partial, no lock


def test_file_size_limit_keeps_the_old_json(tmp_path: Path) -> None:
    """RLIMIT_FSIZE (EFBIG) at the final write: exit 1, one line, old JSON byte-identical."""
    out = tmp_path / "out.json"
    out.write_bytes(OLD)

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

    rc, err = _run(_bench_args("--json", str(out)), tmp_path, env=_env(), preexec_fn=limit)
    assert rc == 1, err
    lines = _lines(err)
    assert len(lines) == 1 and "EFBIG" in lines[0] and str(out) in lines[0], err
    assert out.read_bytes() == OLD
    assert _leftovers(tmp_path, {"out.json"}) == []


def test_failed_json_write_keeps_the_results_in_a_partial_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """ENOSPC on the JSON only (patched): the results go to ``<json>.partial``, exit 1."""
    import selenv.cli as cli

    out = tmp_path / "out.json"
    out.write_bytes(OLD)
    real = cli.atomic_write_json

    def failing(target: Path, doc: object) -> Path:
        if Path(target) == out:
            raise OSError(errno.ENOSPC, "No space left on device", str(out))
        return real(target, doc)

    monkeypatch.setattr(cli, "atomic_write_json", failing)
    rc = main(_bench_args("--json", str(out), episodes=2))
    err = capsys.readouterr().err
    assert rc == 1
    lines = _lines(err)
    assert len(lines) == 1 and f"kept in {out}.partial" in lines[0] and "ENOSPC" in lines[0]
    assert out.read_bytes() == OLD
    doc = json.loads((tmp_path / "out.json.partial").read_text())
    assert doc["complete"] is True
    assert doc["results"][0]["agents"]["greedy"]["returns"]
    assert _leftovers(tmp_path, {"out.json", "out.json.partial"}) == []


def test_plot_failure_is_one_line_and_the_json_is_still_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A PNG that cannot be written (a folder in its place): one line, exit 1, no traceback."""
    figs = tmp_path / "figs"
    (figs / "FIMSelection-v1.png").mkdir(parents=True)
    out = tmp_path / "out.json"
    rc = main(_bench_args("--json", str(out), "--plot", str(figs), episodes=2))
    err = capsys.readouterr().err
    assert rc == 1
    bad = [ln for ln in err.splitlines() if ln.startswith("selenv:")]
    assert len(bad) == 1 and f"cannot write {figs / 'FIMSelection-v1.png'}" in bad[0], err
    assert json.loads(out.read_text())["complete"] is True
    assert _leftovers(figs, {"FIMSelection-v1.png"}) == []


# -- SIGINT / SIGTERM ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("sig", "code", "word"), [("INT", 130, "SIGINT"), ("TERM", 143, "SIGTERM")]
)
def test_signal_keeps_the_finished_episodes(tmp_path: Path, sig: str, code: int, word: str) -> None:
    """A signal after episode 6 (greedy's 4 and random's 2): exit 130/143, JSON incomplete."""
    out = tmp_path / "out.json"
    out.write_bytes(OLD)
    env = _env(SELENV_TEST_SIGNAL_AFTER_EPISODES="6", SELENV_TEST_SIGNAL=sig)
    rc, err = _run(_bench_args("--json", str(out)), tmp_path, env=env)
    assert rc == code, err
    lines = _lines(err)
    assert len(lines) == 1 and word in lines[0] and "kept 6 finished episodes" in lines[0], err
    top = json.loads(out.read_text())
    assert top["complete"] is False
    doc = top["results"][0]
    assert doc["complete"] is False
    assert doc["episodes_done"] == {"greedy": 4, "random": 2}
    assert doc["paired_seeds"] == [0, 1]
    assert doc["agents"]["greedy"]["seeds"] == [0, 1, 2, 3]
    assert len(doc["agents"]["greedy"]["returns"]) == 4
    assert doc["agents"]["random"]["paired"]["n"] == 2  # statistics on the paired seeds
    assert _leftovers(tmp_path, {"out.json"}) == []


def test_ctrl_c_from_outside_keeps_the_finished_episode(tmp_path: Path) -> None:
    """SIGINT sent by another process while the bench waits after its first episode."""
    out = tmp_path / "out.json"
    out.write_bytes(OLD)
    env = _env(SELENV_TEST_PAUSE_AFTER_EPISODES="1")
    proc = _proc.popen(
        [sys.executable, "-m", "selenv", *_bench_args("--json", str(out))],
        cwd=tmp_path,
        env=env,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    assert proc.stderr is not None
    try:
        line = _proc.readline(proc, 60)
        assert "paused after 1 episodes" in line
        proc.send_signal(signal.SIGINT)
        _, err = _proc.communicate(proc, 30)
    finally:
        _proc.stop(proc)
    assert proc.returncode == 130, err
    assert "kept 1 finished episodes" in err
    assert json.loads(out.read_text())["results"][0]["episodes_done"] == {"greedy": 1, "random": 0}


def _marked(mark: str) -> list[int]:
    """PIDs of live processes whose environment holds ``SELENV_FAULT_MARK=<mark>``."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes()
        except OSError:
            continue
        if f"SELENV_FAULT_MARK={mark}".encode() in environ.split(b"\0"):
            pids.append(int(entry.name))
    return pids


def _wait_gone(mark: str, seconds: float = 10.0) -> list[int]:
    deadline = time.monotonic() + seconds
    while (left := _marked(mark)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return left


def test_sigterm_with_a_process_pool_keeps_episodes_and_leaves_no_worker(tmp_path: Path) -> None:
    """--executor process: SIGTERM after a worker's 2nd episode; workers hand back theirs."""
    out = tmp_path / "out.json"
    mark = uuid.uuid4().hex
    env = _env(
        SELENV_TEST_SIGNAL_AFTER_EPISODES="2", SELENV_TEST_SIGNAL="TERM", SELENV_FAULT_MARK=mark
    )
    args = _bench_args(
        "--json", str(out), "--executor", "process", "--num-workers", "2", episodes=40
    )
    rc, err = _run(args, tmp_path, env=env)
    assert rc == 143, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    lines = _lines(err)
    assert len(lines) == 1 and "terminated (SIGTERM)" in lines[0], err
    assert out.exists(), err  # the stderr says what the run kept
    doc = json.loads(out.read_text())["results"][0]
    assert doc["complete"] is False
    assert doc["episodes_done"]["greedy"] >= 2
    assert sum(doc["episodes_done"].values()) < 80
    assert _wait_gone(mark) == []
    assert _leftovers(tmp_path, {"out.json"}) == []


def test_ctrl_c_to_the_process_group_with_a_pool(tmp_path: Path) -> None:
    """Ctrl-C reaches the bench and its pool workers (paused after their first episode): the
    workers hand back their episode, nothing prints a traceback, exit 130, no worker left."""
    out = tmp_path / "out.json"
    mark = uuid.uuid4().hex
    args = _bench_args(
        "--json", str(out), "--executor", "process", "--num-workers", "2", episodes=40
    )
    proc = _proc.popen(
        [sys.executable, "-m", "selenv", *args],
        cwd=tmp_path,
        env=_env(SELENV_TEST_PAUSE_AFTER_EPISODES="1", SELENV_FAULT_MARK=mark),
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    try:
        assert proc.stderr is not None
        for _ in range(2):  # both workers paused
            assert "paused" in _proc.readline(proc, 60)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = _proc.communicate(proc, 30)
        rc = proc.returncode
    finally:
        _proc.stop(proc)
    assert rc == 130, err
    assert "Traceback" not in err
    lines = _lines(err)
    assert len(lines) == 1 and "kept 2 finished episodes" in lines[0], err
    assert json.loads(out.read_text())["results"][0]["episodes_done"] == {"greedy": 2, "random": 0}
    assert _wait_gone(mark) == []


# -- one writer per output ------------------------------------------------------------------------


def test_second_bench_on_the_same_outputs_exits_2(tmp_path: Path) -> None:
    """A running bench holds its --json and --plot; a second one aiming at either is refused."""
    out = tmp_path / "out.json"
    figs = tmp_path / "figs"
    proc = _proc.popen(
        [sys.executable, "-m", "selenv", *_bench_args("--json", str(out), "--plot", str(figs))],
        cwd=tmp_path,
        env=_env(SELENV_TEST_PAUSE_AFTER_EPISODES="1"),
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stderr is not None
        assert "paused" in _proc.readline(proc, 60)
        for extra in (["--json", str(out)], ["--plot", str(figs)]):
            rc, err = _run(_bench_args(*extra), tmp_path, env=_env())
            lines = _lines(err)
            assert rc == 2 and len(lines) == 1, err
            assert lines[0].startswith("selenv: error:") and "being written by another run" in err
        proc.send_signal(signal.SIGTERM)
        assert _proc.wait(proc, 30) == 143
    finally:
        _proc.stop(proc)
    assert json.loads(out.read_text())["complete"] is False
    assert _leftovers(tmp_path, {"out.json", "figs"}) == []  # the locks are gone


def test_lock_held_by_a_live_process_refuses_the_bench(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The lock file of another live process (here ``sleep``) refuses the run up front."""
    out = tmp_path / "out.json"
    out.write_bytes(OLD)
    lock = OutputLock(out).lock_path
    owner = _proc.popen(["sleep", "60"])
    try:
        lock.write_text(f"{owner.pid}\n")
        rc = main(_bench_args("--json", str(out), episodes=1))
    finally:
        _proc.stop(owner)
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "being written" in err
    assert out.read_bytes() == OLD


# -- dead workers, executors -----------------------------------------------------------------------


def test_killed_pool_worker_exits_1_with_one_line(tmp_path: Path) -> None:
    """SIGKILL of a paused pool worker: exit 1 naming its PID, old --json untouched."""
    out = tmp_path / "out.json"
    out.write_bytes(OLD)
    mark = uuid.uuid4().hex
    args = _bench_args("--json", str(out), "--executor", "process", "--num-workers", "2")
    proc = _proc.popen(
        [sys.executable, "-m", "selenv", *args],
        cwd=tmp_path,
        env=_env(SELENV_TEST_PAUSE_AFTER_EPISODES="1", SELENV_FAULT_MARK=mark),
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = _proc.readline(proc, 60)
        assert "paused" in line, line
        pid = int(line.rsplit("PID ", 1)[1].rstrip(")\n"))
        os.kill(pid, signal.SIGKILL)
        _, err = _proc.communicate(proc, 30)
        rc = proc.returncode
    finally:
        _proc.stop(proc)
    assert rc == 1, err
    assert "Traceback" not in err
    lines = _lines(err)
    assert len(lines) == 1, err
    assert f"PID {pid} killed by SIGKILL" in lines[0] and "process-pool worker died" in lines[0]
    assert out.read_bytes() == OLD
    assert _wait_gone(mark) == []
    assert _leftovers(tmp_path, {"out.json", "out.json.partial"}) == []


def test_ray_worker_crash_becomes_worker_died_error() -> None:
    """Ray's WorkerCrashedError (a non-task RayError) -> WorkerDiedError, results so far kept."""
    from selenv.parallel import RayExecutor, WorkerDiedError

    class RayError(Exception):
        pass

    class RayTaskError(RayError):
        pass

    class WorkerCrashedError(RayError):
        pass

    class FakeRay:
        class exceptions:
            pass

        def __init__(self) -> None:
            self.exceptions.RayError = RayError  # type: ignore[attr-defined]
            self.exceptions.RayTaskError = RayTaskError  # type: ignore[attr-defined]

        def remote(self, **kw: object):
            class R:
                @staticmethod
                def remote(fn: object, task: int) -> int:
                    return task

            return lambda f: R

        def put(self, x: object) -> object:
            return x

        def wait(self, refs: list[int], num_returns: int) -> tuple[list[int], list[int]]:
            return [min(refs)], []

        def get(self, ref: int) -> int:
            if ref == 2:
                raise WorkerCrashedError("The worker died unexpectedly while executing this task.")
            return ref * 10

        def cancel(self, ref: int, force: bool) -> None:
            pass

    ex = RayExecutor(num_workers=1)
    ex._ray = FakeRay()
    got: dict[int, int] = {}
    with pytest.raises(WorkerDiedError, match="Ray worker died while running task 2"):
        ex.map(abs, [0, 1, 2, 3], progress=False, on_result=got.__setitem__)
    assert got == {0: 0, 1: 10}
    ex._ray = None


def test_unreachable_address_exits_2_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("ray")
    rc = main(_bench_args("--executor", "ray", "--address", "127.0.0.1:1", episodes=1))
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--address" in err


def test_too_many_pool_workers_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(_bench_args("--executor", "process", "--num-workers", "100000", episodes=1))
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--num-workers 100000" in err


# -- bounded work, usage errors -------------------------------------------------------------------


def _record_work(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every env built, bench run, episode played or executor started from now on."""
    import gymnasium

    import selenv.bench
    import selenv.bench.runner as runner
    from selenv.parallel.executors import Executor, ProcessExecutor

    work: list[str] = []

    def recorded(owner: object, name: str) -> None:
        real = getattr(owner, name)

        def call(*args: object, **kwargs: object) -> object:
            work.append(name)
            return real(*args, **kwargs)

        monkeypatch.setattr(owner, name, call)

    recorded(gymnasium, "make")
    recorded(gymnasium, "make_vec")
    recorded(selenv.bench, "run_bench")
    recorded(runner, "run_bench")
    recorded(runner, "run_episode")
    recorded(Executor, "__enter__")
    recorded(ProcessExecutor, "_get_pool")
    return work


@pytest.mark.parametrize("executor", ["local", "process"])
def test_huge_episodes_refused_before_any_work(
    executor: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """No env is built, no executor starts, no episode runs: the refusal costs the checks only
    (how long that takes: ``benchmarks/bench_refusals.py``)."""
    work = _record_work(monkeypatch)
    rc = main(_bench_args("--executor", executor, episodes=1_000_000_000))
    err = capsys.readouterr().err
    assert rc == 2 and work == [], work
    assert len(err.strip().splitlines()) == 1
    assert "--episodes 1,000,000,000" in err and "100,000" in err and "--max-episodes" in err


def test_the_work_recorder_sees_a_run(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The recorder above does see a bench that runs (so an empty record means no work)."""
    work = _record_work(monkeypatch)
    assert main(_bench_args(episodes=1)) == 0
    capsys.readouterr()
    assert "run_bench" in work and "run_episode" in work and "__enter__" in work, work


#: what a refused ``selenv bench`` child reports: its exit code and the heavy modules it loaded
_REFUSED_CHILD = """
import sys
from selenv.cli import main
rc = main(sys.argv[1:])
print(sorted(m for m in ("torch", "ray", "matplotlib") if m in sys.modules))
sys.exit(rc)
"""


def test_huge_episodes_subprocess_exits_2_before_heavy_imports(tmp_path: Path) -> None:
    """A real process: exit 2 and one line, with neither torch, Ray nor matplotlib imported."""
    proc = _proc.run(
        [sys.executable, "-c", _REFUSED_CHILD, *_bench_args(episodes=1_000_000_000)],
        cwd=tmp_path,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,  # a hang guard: the refusal takes ~1 s (benchmarks/bench_refusals.py)
    )
    assert proc.returncode == 2 and len(_lines(proc.stderr)) == 1, proc.stderr
    assert "--max-episodes" in proc.stderr
    assert proc.stdout.strip() == "[]", proc.stdout


def test_max_episodes_raises_the_ceiling(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(_bench_args("--max-episodes", "2", episodes=3))
    assert rc == 2 and "ceiling of 2 episodes" in capsys.readouterr().err
    rc = main(_bench_args("--max-episodes", "2", episodes=2))
    assert rc == 0


@pytest.mark.parametrize(
    ("spec", "needle"),
    [("ppo:a.zip:b.zip", "names two checkpoints"), ("greedy:1x=2", "is not an option name")],
)
def test_bad_agent_specs_exit_2_with_one_line(
    spec: str, needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["bench", ENV, "--agents", f"{spec},random", "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith("selenv: error: --agents:") and needle in err


# -- the statistics of an incomplete result ----------------------------------------------------


def test_incomplete_result_pairs_only_the_common_seeds() -> None:
    r = EnvBenchResult("selenv/FIMSelection-v1", {}, 0, 4, complete=False)
    r.agents["a"] = AgentResult("a", [1.0, 2.0, 3.0], [1.0, 2.0, 3.0], 0.3, 9, seeds=[0, 1, 2])
    r.agents["b"] = AgentResult("b", [0.5, 1.0], [0.5, 1.0], 0.2, 6, seeds=[1, 0])
    r.agents["c"] = AgentResult("c")  # never finished an episode
    assert r.paired_seeds() == [0, 1]
    view = r.statistics_view()
    assert view.agents["a"].returns == [1.0, 2.0] and view.agents["b"].returns == [1.0, 0.5]
    assert view.agents["c"].skipped is not None
    doc = r.to_json()
    assert doc["episodes_done"] == {"a": 3, "b": 2, "c": 0}
    assert doc["agents"]["a"]["returns"] == [1.0, 2.0, 3.0]  # every finished episode kept
    assert doc["agents"]["a"]["mean_return"] == pytest.approx(1.5)  # stats on seeds 0, 1
    assert doc["agents"]["b"]["paired"]["n"] == 2


@pytest.mark.parametrize(("exc", "code"), [(KeyboardInterrupt, 130), ("term", 143)])
def test_interrupt_before_the_run_is_one_line(
    exc: object, code: int, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C / SIGTERM while the arguments are checked (e.g. a checkpoint loads): one line."""
    import selenv.cli as cli

    def stop(args: object) -> int:
        if exc == "term":
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "cmd_bench", stop)
    assert main(_bench_args(episodes=1)) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "before any episode ran; nothing written" in err[0]
