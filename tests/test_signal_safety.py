"""Signals never raise into native code, reach the ``selenv`` process early, keep SIGINT ignored.

In this process: a signal received inside :func:`selenv.exits.hold_signals` (imports, agent
building) is raised when the region ends, not where it arrived; a process that
ignores SIGINT keeps ignoring it. In real ``python -m selenv bench`` children (every one with
explicit signal dispositions and a deadline on every wait, see ``_proc``): SIGTERM at several
points of the start-up always ends with exit 143, one line and no lock or temporary file; a
child started with SIGINT ignored keeps it ignored and stops on SIGTERM.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import _proc
import pytest

from selenv import _signals
from selenv.agents import AGENTS
from selenv.agents.base import AgentSpec, make
from selenv.exits import DeferredSignals, Terminated, hold_signals, sigterm_raises

ROOT = Path(__file__).resolve().parents[1]
ENV = "selenv/FIMSelection-v1"
KWARGS = '{"n_candidates": 20, "budget": 3}'
PROC_STATUS = Path("/proc/self/status")
linux_only = pytest.mark.skipif(not PROC_STATUS.exists(), reason="reads /proc/PID/status")


@pytest.fixture(autouse=True)
def _clean_signal_state() -> Iterator[None]:
    """Each test starts and ends with no held region, nothing pending, the handlers restored."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    assert not _signals.held() and not _signals._pending
    yield
    for signum, handler in saved.items():
        signal.signal(signum, handler)
    assert not _signals.held(), "a hold_signals region leaked"
    _signals._pending.clear()


# -- in this process -----------------------------------------------------------------------------


def _module_sending(tmp_path: Path, name: str, signum: int) -> str:
    """A module on ``sys.path`` whose body signals this process, then sets ``DONE``."""
    (tmp_path / f"{name}.py").write_text(
        f"import os\nDONE = False\nos.kill(os.getpid(), {int(signum)})\nDONE = True\n"
    )
    return name


@pytest.fixture
def on_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


@pytest.mark.parametrize(
    ("signum", "exc"), [(signal.SIGTERM, Terminated), (signal.SIGINT, KeyboardInterrupt)]
)
def test_a_signal_during_a_held_import_is_raised_after_it(
    on_path: Path, signum: int, exc: type[BaseException]
) -> None:
    """The module body runs to its end; the exception comes when the region ends."""
    name = _module_sending(on_path, f"held_import_{signum}", signum)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    with sigterm_raises(), pytest.raises(exc), hold_signals():
        __import__(name)
        assert sys.modules[name].DONE is True
        assert _signals._pending == [signum]
    assert sys.modules[name].DONE is True
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


def test_without_a_hold_the_signal_interrupts_the_import(on_path: Path) -> None:
    """The control: outside a region the exception lands inside the module's body."""
    name = _module_sending(on_path, "unheld_import", signal.SIGTERM)
    with sigterm_raises(), pytest.raises(Terminated):
        __import__(name)
    assert name not in sys.modules  # the import failed half-way


def test_nested_regions_raise_once_at_the_outermost_end() -> None:
    reached = []
    with sigterm_raises(), pytest.raises(Terminated):
        with hold_signals():
            with hold_signals():
                signal.raise_signal(signal.SIGTERM)
                signal.raise_signal(signal.SIGTERM)
            reached.append("inner ended without raising")
    assert reached == ["inner ended without raising"]
    assert not _signals._pending


def test_a_failing_region_still_reports_the_signal() -> None:
    with sigterm_raises(), pytest.raises(Terminated) as info, hold_signals():
        signal.raise_signal(signal.SIGTERM)
        raise ImportError("a broken import")
    assert isinstance(info.value.__context__, ImportError)


def test_make_holds_signals_while_the_agent_is_built(monkeypatch: pytest.MonkeyPatch) -> None:
    """``selenv.agents.make`` (torch imports, checkpoint loads) finishes, then raises."""
    built = []

    def factory() -> Any:
        os.kill(os.getpid(), signal.SIGTERM)
        built.append("finished")  # a handler raising here would abandon the build
        return object()

    monkeypatch.setitem(AGENTS, "signal_probe", {ENV: AgentSpec("signal_probe", (ENV,), factory)})
    with sigterm_raises(), pytest.raises(Terminated):
        make("signal_probe", ENV)
    assert built == ["finished"]


def test_deferred_signals_second_signal_waits_for_a_held_region() -> None:
    with DeferredSignals() as stop, pytest.raises(Terminated), hold_signals():
        signal.raise_signal(signal.SIGTERM)
        assert stop.signal == "SIGTERM"
        signal.raise_signal(signal.SIGTERM)  # the second: raised when the region ends
        assert _signals._pending == [signal.SIGTERM]


def test_deferred_signals_keeps_an_ignored_sigint_ignored() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with DeferredSignals() as stop:
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGTERM)
    assert stop.received == [signal.SIGTERM]
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_hold_leaves_an_ignored_sigint_ignored() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with hold_signals():
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        signal.raise_signal(signal.SIGINT)
    assert not _signals._pending


@pytest.mark.parametrize(
    ("argv", "orig", "expected"),
    [
        (["-m", "bench"], ["python", "-m", "selenv", "bench"], True),
        (["-m"], ["python", "-X", "importtime", "-m", "selenv.cli"], True),
        (["-m"], ["python", "-mselenv"], True),
        (["/venv/bin/selenv", "list"], ["python", "/venv/bin/selenv", "list"], True),
        (["-m", "tests"], ["python", "-m", "pytest", "tests"], False),
        (["-m"], ["python", "-m", "selenv.train.train_surrogate"], False),
        (["script.py"], ["python", "script.py"], False),
        (["-c"], ["python", "-c", "import selenv"], False),
        ([], [], False),
    ],
)
def test_is_cli_process(
    monkeypatch: pytest.MonkeyPatch, argv: list[str], orig: list[str], expected: bool
) -> None:
    monkeypatch.setattr(sys, "argv", argv)
    monkeypatch.setattr(sys, "orig_argv", orig)
    assert _signals.is_cli_process() is expected


# -- real children -------------------------------------------------------------------------------


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SELENV_TEST_")}
    env["PYTHONPATH"] = str(ROOT)
    env.update(extra)
    return env


def _mask(pid: int, field: str) -> int:
    """The ``SigCgt`` / ``SigIgn`` mask of ``pid`` (0 once it has exited)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0
    for line in text.splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1], 16)
    return 0


def _bit(signum: int) -> int:
    return 1 << (signum - 1)


def _wait_for_handler(proc: subprocess.Popen[str], deadline: float = 60.0) -> None:
    """Until the child catches SIGTERM (its handler is installed); a hang guard only."""
    end = time.monotonic() + deadline
    while not _mask(proc.pid, "SigCgt") & _bit(signal.SIGTERM):
        if proc.poll() is not None:
            pytest.fail(f"the child exited ({proc.returncode}) before installing its handler")
        if time.monotonic() > end:
            _proc.stop(proc)
            pytest.fail(f"no SIGTERM handler after {deadline:g} s")
        time.sleep(0.002)


def _bench(out: Path, agents: str, **popen: Any) -> subprocess.Popen[str]:
    """``python -m selenv bench`` on ``agents`` that pauses after its first episode."""
    args = [sys.executable, "-m", "selenv", "bench", ENV, "--agents", agents]
    args += ["--episodes", "3", "--env-kwargs", KWARGS, "--no-progress", "--json", str(out)]
    return _proc.popen(
        args,
        cwd=out.parent,
        env=_env(SELENV_TEST_PAUSE_AFTER_EPISODES="1"),
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        **popen,
    )


def _lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln and not ln.startswith("selenv: test hook")]


#: seconds after the handler is installed: 0 is during ``import selenv`` (before the agents
#: load); the later ones fall in the agents' imports and checkpoint loads or after the first
#: episode, wherever this machine's speed puts them (the outcome must not depend on it)
DELAYS = (0.0, 1.2, 2.5)


@linux_only
@pytest.mark.parametrize("delay", DELAYS)
def test_sigterm_during_start_up_is_one_line_and_exit_143(tmp_path: Path, delay: float) -> None:
    out = tmp_path / "out.json"
    proc = _bench(out, "greedy,ppo")  # ppo: torch and a checkpoint load at start-up
    try:
        _wait_for_handler(proc)
        time.sleep(delay)  # a point of the start-up; nothing is asserted about time
        proc.send_signal(signal.SIGTERM)
        _, err = _proc.communicate(proc, 60)
    finally:
        _proc.stop(proc)
    lines = _lines(err)
    assert proc.returncode == 143, err
    assert len(lines) == 1 and lines[0].startswith("selenv: terminated (SIGTERM)"), err
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left in ([], ["out.json"]), left  # no .out.json.lock, no temporary file
    if delay == 0.0:
        assert "before any episode ran; nothing written" in lines[0], err
    if left:
        assert json.loads(out.read_text())["complete"] is False


@linux_only
def test_sigint_ignored_on_entry_stays_ignored_and_sigterm_keeps_the_episodes(
    tmp_path: Path,
) -> None:
    out = tmp_path / "out.json"
    proc = _bench(out, "greedy", preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        line = _proc.readline(proc, 90)
        assert "paused after 1 episodes" in line, line
        assert _mask(proc.pid, "SigIgn") & _bit(signal.SIGINT)
        assert not _mask(proc.pid, "SigCgt") & _bit(signal.SIGINT)
        proc.send_signal(signal.SIGINT)  # ignored: a handled one would end the run with 130
        proc.send_signal(signal.SIGTERM)
        _, err = _proc.communicate(proc, 60)
    finally:
        _proc.stop(proc)
    assert proc.returncode == 143, err
    lines = _lines(err)
    assert len(lines) == 1 and "terminated (SIGTERM)" in lines[0], err
    assert "kept 1 finished episodes" in lines[0], err
    assert json.loads(out.read_text())["complete"] is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_importing_selenv_elsewhere_leaves_the_handlers_alone() -> None:
    code = "import signal, selenv; print(signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)"
    done = _proc.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=90)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"
