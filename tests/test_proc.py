"""The suite's child processes (tests/_proc.py) and its hang guard hold however it is launched.

A background job of a non-interactive shell (``nohup make test &``) starts with SIGINT and
SIGQUIT ignored; the children of :mod:`_proc` must still start with both at their defaults
(SIGHUP stays as inherited), every wait must end, and no test may start a child another way.
"""

from __future__ import annotations

import ast
import contextlib
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import _proc
import pytest
from conftest import LAUNCH_IGNORED

TESTS = Path(__file__).resolve().parent
#: the only files that may call :mod:`subprocess` themselves (the helper and its own test)
HELPER_FILES = {"_proc.py", "test_proc.py"}
SPAWNERS = {"Popen", "run", "call", "check_call", "check_output", "getoutput", "getstatusoutput"}


def _mask(status: str, field: str) -> int:
    """The hexadecimal signal mask ``field`` (``SigIgn``, ``SigCgt``) of a /proc status text."""
    for line in status.splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1], 16)
    raise AssertionError(f"no {field} in /proc status")


def _bit(signum: int) -> int:
    return 1 << (signum - 1)


@contextlib.contextmanager
def _ignored(*signums: int) -> Iterator[None]:
    """This process ignores ``signums`` while the block runs, as a nohup'ed background job."""
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in signums}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


linux_only = pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc")


@linux_only
def test_children_start_with_default_sigint_and_sigquit_and_inherit_sighup() -> None:
    """With SIGINT, SIGQUIT and SIGHUP ignored here, a child of ``_proc`` (``cat``, which
    changes no disposition) ignores only SIGHUP; a plain ``subprocess`` child ignores all
    three (what the suite saw under ``nohup ... &``)."""
    cmd = ["cat", "/proc/self/status"]
    with _ignored(signal.SIGINT, signal.SIGQUIT, signal.SIGHUP):
        helped = _proc.run(cmd, capture_output=True, text=True, timeout=60, check=True)
        plain = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=True)
    ignored = _mask(helped.stdout, "SigIgn")
    assert ignored & _bit(signal.SIGINT) == 0
    assert ignored & _bit(signal.SIGQUIT) == 0
    assert ignored & _bit(signal.SIGHUP) != 0  # nohup's purpose, kept
    inherited = _mask(plain.stdout, "SigIgn")
    every = _bit(signal.SIGINT) | _bit(signal.SIGQUIT) | _bit(signal.SIGHUP)
    assert inherited & every == every  # the launch this helper exists for


def test_python_children_install_their_keyboard_interrupt_handler() -> None:
    """A Python child of ``_proc.popen`` started while SIGINT is ignored here turns a SIGINT
    into ``KeyboardInterrupt`` (exit 130 through selenv's guarded_main, here: caught)."""
    code = textwrap.dedent(
        """
        import os, signal, sys
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        try:
            os.kill(os.getpid(), signal.SIGINT)
            signal.pause()  # only reached if the signal were lost
        except KeyboardInterrupt:
            sys.exit(130)
        """
    )
    with _ignored(signal.SIGINT, signal.SIGQUIT):
        proc = _proc.popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True)
    _, err = _proc.communicate(proc, 60)
    assert proc.returncode == 130, err


@pytest.mark.skipif(
    os.environ.get("SELENV_EXPECT_DETACHED") != "1", reason="only under make test-detached"
)
def test_the_detached_job_is_launched_with_sigint_ignored() -> None:
    """``make test-detached`` really tests the launch it is for (SIGINT, SIGQUIT ignored)."""
    assert os.environ.get(LAUNCH_IGNORED) == "SIGINT,SIGQUIT"


def test_this_process_runs_with_foreground_dispositions() -> None:
    """conftest.py restores SIGINT / SIGQUIT for the in-process signal tests."""
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.getsignal(signal.SIGQUIT) is not signal.SIG_IGN


def test_a_caller_preexec_fn_still_runs() -> None:
    code = "import signal; print(signal.getsignal(signal.SIGUSR1) is signal.SIG_IGN)"

    def ignore_usr1() -> None:
        signal.signal(signal.SIGUSR1, signal.SIG_IGN)

    out = _proc.run(
        [sys.executable, "-c", code],
        preexec_fn=ignore_usr1,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert out.stdout.strip() == "True"


def test_a_silent_child_fails_the_read_instead_of_blocking() -> None:
    """``readline`` past its deadline: the test fails naming the command; the child is gone."""
    proc = _proc.popen(["sleep", "60"], stderr=subprocess.PIPE, text=True)
    with pytest.raises(pytest.fail.Exception, match=r"sleep 60: waiting for a line"):
        _proc.readline(proc, timeout=0.5)
    assert proc.returncode is not None  # killed and reaped


@pytest.mark.parametrize("how", ["run", "communicate", "wait"])
def test_every_wait_has_a_deadline(how: str) -> None:
    with pytest.raises(pytest.fail.Exception, match=r"sleep 60: .* took longer than 0.5 s"):
        if how == "run":
            _proc.run(["sleep", "60"], timeout=0.5)
        else:
            proc = _proc.popen(["sleep", "60"], stdout=subprocess.PIPE)
            try:
                getattr(_proc, how)(proc, 0.5)
            finally:
                _proc.stop(proc)


def test_readline_then_communicate_loses_nothing() -> None:
    code = "import sys; sys.stderr.write('first\\nsecond\\nthird\\n')"
    proc = _proc.popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True)
    assert _proc.readline(proc, timeout=60) == "first\n"
    _, rest = _proc.communicate(proc, 60)
    assert rest == "second\nthird\n"
    assert _proc.readline(_proc.popen(["true"], stderr=subprocess.PIPE, text=True), timeout=60) in (
        "",
    )  # end of file


def _direct_spawns(path: Path) -> list[str]:
    """``subprocess.<spawner>(...)`` calls and calls of spawners imported from subprocess."""
    tree = ast.parse(path.read_text(), str(path))
    imported = {
        alias.asname or alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module == "subprocess"
        for alias in node.names
        if alias.name in SPAWNERS
    }
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        direct = isinstance(f, ast.Attribute) and f.attr in SPAWNERS
        direct = direct and isinstance(f.value, ast.Name) and f.value.id == "subprocess"
        if direct or (isinstance(f, ast.Name) and f.id in imported):
            found.append(f"{path.relative_to(TESTS)}:{node.lineno}")
    return found


def test_no_test_starts_a_child_without_the_helper() -> None:
    """Every child the tests start goes through tests/_proc.py (defaults and deadlines)."""
    found = [
        where
        for path in sorted(TESTS.rglob("*.py"))
        if path.name not in HELPER_FILES
        for where in _direct_spawns(path)
    ]
    assert found == [], f"start these children with tests/_proc.py: {found}"


def test_the_spawn_check_sees_a_direct_call(tmp_path: Path) -> None:
    bad = tmp_path / "test_bad.py"
    bad.write_text("import subprocess\nfrom subprocess import run as r\nr(['x'])\n")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sys.modules[__name__], "TESTS", tmp_path)
        assert _direct_spawns(bad) == ["test_bad.py:3"]


# -- the hang guard ------------------------------------------------------------------------------


def test_the_hang_guard_is_configured(pytestconfig: pytest.Config) -> None:
    """pyproject.toml sets a per-test timeout (a hang guard, far above any test's duration)."""
    assert pytestconfig.pluginmanager.hasplugin("timeout")
    assert float(pytestconfig.getini("timeout")) >= 600


def test_the_hang_guard_ends_a_hanging_test_under_xdist(tmp_path: Path) -> None:
    """A pytest run with two xdist workers and ``--timeout 3``: the hanging test fails with
    pytest-timeout's message, the other passes, and the session ends."""
    (tmp_path / "test_hang.py").write_text(
        "import time\n\ndef test_hangs():\n    time.sleep(600)\n\ndef test_ok():\n    pass\n"
    )
    args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2"]
    args += ["--timeout", "3", "--rootdir", str(tmp_path), "-c", "/dev/null", "test_hang.py"]
    done = _proc.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    out = done.stdout + done.stderr
    assert done.returncode == 1, out
    assert "Timeout" in out and "1 failed, 1 passed" in out, out
