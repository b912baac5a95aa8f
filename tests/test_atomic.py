"""``selenv.atomic``: outputs replaced whole or not at all, one writer per output.

Fault injection on real file systems: a tiny tmpfs (where the machine lets root mount one)
that fills up, a file-size limit (``RLIMIT_FSIZE``: EFBIG), a child process killed between the
temporary write and the rename, an exception inside the writer. Each checks that the previous
output is byte-identical and that no partial file is left.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import sys
import textwrap
import time
from pathlib import Path
from subprocess import PIPE, Popen

import _proc
import pytest

from selenv.atomic import (
    OutputBusyError,
    OutputLock,
    atomic_path,
    atomic_paths,
    describe_os_error,
    probe_writable,
    write_bytes,
    write_json,
)

OLD = b'{"old": "results"}\n'


def _leftovers(folder: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


def test_write_replaces_and_leaves_no_temporary(tmp_path: Path) -> None:
    """A successful write replaces the target and leaves nothing else."""
    target = tmp_path / "out.json"
    target.write_bytes(OLD)
    write_json(target, {"new": [1, 2]})
    assert json.loads(target.read_text()) == {"new": [1, 2]}
    assert _leftovers(tmp_path, {"out.json"}) == []


def test_exception_in_the_writer_keeps_the_old_file(tmp_path: Path) -> None:
    """An error (or Ctrl-C) while writing: the old bytes stay, the temporary goes."""
    target = tmp_path / "policy.zip"
    target.write_bytes(OLD)
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)), atomic_path(target) as temp:
            temp.write_bytes(b"half a checkpoint")
            raise exc
        assert target.read_bytes() == OLD
        assert _leftovers(tmp_path, {"policy.zip"}) == []


def test_unserialisable_json_writes_nothing(tmp_path: Path) -> None:
    """The JSON is built before the file is touched."""
    target = tmp_path / "out.json"
    target.write_bytes(OLD)
    with pytest.raises(TypeError):
        write_json(target, {"x": object()})
    assert target.read_bytes() == OLD
    assert _leftovers(tmp_path, {"out.json"}) == []


def test_temporary_keeps_the_suffix_and_lives_next_to_the_target(tmp_path: Path) -> None:
    """SB3 appends ``.zip`` to a path without it: the temporary must keep the target's suffix."""
    target = tmp_path / "sub" / "policy.zip"
    with atomic_path(target) as temp:
        assert temp.parent == target.parent and temp.suffix == ".zip"
        assert temp.name.startswith(".policy")
        temp.write_bytes(b"zip")
    assert target.read_bytes() == b"zip"


def test_a_pair_is_replaced_together_or_not_at_all(tmp_path: Path) -> None:
    """Checkpoint and metadata: a failure after the first half is written changes neither."""
    zip_, meta = tmp_path / "p.zip", tmp_path / "p.json"
    zip_.write_bytes(b"old zip")
    meta.write_bytes(b"old json")
    with pytest.raises(OSError), atomic_paths([zip_, meta]) as (tz, tm):
        tz.write_bytes(b"new zip")
        raise OSError(errno.ENOSPC, "No space left on device", str(tm))
    assert zip_.read_bytes() == b"old zip" and meta.read_bytes() == b"old json"
    with atomic_paths([zip_, meta]) as (tz, tm):
        tz.write_bytes(b"new zip")
        tm.write_bytes(b"new json")
    assert zip_.read_bytes() == b"new zip" and meta.read_bytes() == b"new json"
    assert _leftovers(tmp_path, {"p.zip", "p.json"}) == []
    with pytest.raises(ValueError, match="must differ"), atomic_paths([zip_, zip_]):
        pass


def test_full_disk_keeps_the_old_file(tiny_fs: Path) -> None:
    """ENOSPC on a real (tiny) file system: old output intact, no partial file, clear line."""
    target = tiny_fs / "out.json"
    target.write_bytes(OLD)
    with pytest.raises(OSError) as info:
        write_bytes(target, b"x" * 200_000)
    assert info.value.errno == errno.ENOSPC
    assert target.read_bytes() == OLD
    assert _leftovers(tiny_fs, {"out.json"}) == []
    line = describe_os_error(info.value, target)
    assert str(target) in line and "ENOSPC" in line and "\n" not in line
    with pytest.raises(OSError):
        (tiny_fs / "filler").write_bytes(b"x" * 70_000)  # fill what is left
    with pytest.raises(OSError) as probe:
        probe_writable(tiny_fs / "next.json")
    assert probe.value.errno == errno.ENOSPC


def _run_child(code: str, cwd: Path, **kwargs: object) -> Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return _proc.popen(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=cwd,
        env=env,
        stdout=PIPE,
        stderr=PIPE,
        **kwargs,  # type: ignore[call-overload]
    )


def test_file_size_limit_keeps_the_old_file(tmp_path: Path) -> None:
    """EFBIG (``ulimit -f``) in a child process: the old file is byte-identical."""
    target = tmp_path / "out.json"
    target.write_bytes(OLD)
    child = _run_child(
        """
        import resource, signal, sys
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (8192, 8192))
        from selenv.atomic import write_bytes
        try:
            write_bytes("out.json", b"x" * 100_000)
        except OSError as exc:
            print(exc.errno)
        """,
        tmp_path,
    )
    out, err = _proc.communicate(child)
    assert out.decode().strip() == str(errno.EFBIG), err.decode()
    assert target.read_bytes() == OLD
    assert _leftovers(tmp_path, {"out.json"}) == []


def test_sigkill_between_write_and_rename_keeps_the_old_file(tmp_path: Path) -> None:
    """A run killed with the new file written but not renamed: old file intact; the next write
    of the same target removes the orphaned temporary."""
    target = tmp_path / "policy.zip"
    target.write_bytes(OLD)
    child = _run_child(
        """
        import time
        from selenv.atomic import atomic_path
        with atomic_path("policy.zip") as temp:
            temp.write_bytes(b"new" * 1000)
            print("written", flush=True)
            time.sleep(60)
        """,
        tmp_path,
    )
    assert child.stdout is not None
    assert _proc.readline(child, stream=child.stdout).strip() == b"written"
    child.send_signal(signal.SIGKILL)
    _proc.wait(child, 30)
    assert target.read_bytes() == OLD
    orphans = _leftovers(tmp_path, {"policy.zip"})
    assert len(orphans) == 1 and orphans[0].startswith(".policy.tmp-")
    write_bytes(target, b"newer")
    assert target.read_bytes() == b"newer"
    assert _leftovers(tmp_path, {"policy.zip"}) == []


def test_lock_refuses_a_second_writer_and_takes_over_a_dead_ones(tmp_path: Path) -> None:
    """One writer per output: a live owner blocks, a dead owner's lock is stale."""
    target = tmp_path / "same.json"
    child = _run_child(
        """
        import time
        from selenv.atomic import OutputLock
        with OutputLock("same.json"):
            print("locked", flush=True)
            time.sleep(60)
        """,
        tmp_path,
    )
    assert child.stdout is not None
    assert _proc.readline(child, stream=child.stdout).strip() == b"locked"
    try:
        with pytest.raises(OutputBusyError, match=f"PID {child.pid}"), OutputLock(target):
            pass
    finally:
        child.send_signal(signal.SIGKILL)
        _proc.wait(child, 30)
    deadline = time.monotonic() + 10
    while True:  # the child is reaped: its PID is gone, its lock file remains
        try:
            with OutputLock(target) as lock:
                assert lock.lock_path.read_text().strip() == str(os.getpid())
            break
        except OutputBusyError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
    assert _leftovers(tmp_path, set()) == []


def test_probe_refuses_a_folder_and_creates_parents(tmp_path: Path) -> None:
    """A folder is not a file output; a missing parent is created."""
    with pytest.raises(IsADirectoryError):
        probe_writable(tmp_path)
    probe_writable(tmp_path / "a" / "b" / "out.json")
    assert (tmp_path / "a" / "b").is_dir()
    assert _leftovers(tmp_path / "a" / "b", set()) == []


def test_save_figure_is_atomic(tmp_path: Path) -> None:
    """A figure that fails to render leaves the old PNG; a good one replaces it."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    from selenv.atomic import save_figure

    target = tmp_path / "fig.png"
    target.write_bytes(OLD)
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    with pytest.raises(ValueError):
        save_figure(fig, target, dpi=-5)  # matplotlib refuses a negative dpi
    assert target.read_bytes() == OLD
    save_figure(fig, target, dpi=50)
    plt.close(fig)
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert _leftovers(tmp_path, {"fig.png"}) == []


def test_guarded_main_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    """Each way a command can end maps to its exit code and one line."""
    from selenv.exits import Terminated, UsageError, guarded_main

    def raises(exc: BaseException) -> None:
        raise exc

    cases = [
        (KeyboardInterrupt(), 130, "interrupted (SIGINT)"),
        (Terminated(), 143, "terminated (SIGTERM)"),
        (UsageError("--episodes must be <= 100000"), 2, "error: --episodes"),
        (OSError(errno.ENOSPC, "No space left on device", "x.json"), 1, "(ENOSPC)"),
        (OutputBusyError("out.json is being written"), 2, "error: out.json"),
    ]
    for exc, code, text in cases:
        assert guarded_main(raises, "prog", exc) == code
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("prog: ") and text in err
    assert guarded_main(lambda: None, "prog") == 0
    assert guarded_main(lambda: 3, "prog") == 3


def test_sigterm_becomes_terminated_in_a_child(tmp_path: Path) -> None:
    """A real SIGTERM to a guarded command: exit 143 and one line."""
    child = _run_child(
        """
        import sys, time
        from selenv.exits import guarded_main
        def main():
            print("running", flush=True)
            time.sleep(60)
        sys.exit(guarded_main(main, "prog"))
        """,
        tmp_path,
    )
    assert child.stdout is not None and child.stderr is not None
    assert _proc.readline(child, stream=child.stdout).strip() == b"running"
    child.send_signal(signal.SIGTERM)
    _, err = _proc.communicate(child, 30)
    assert child.returncode == 143
    assert err.decode() == "prog: terminated (SIGTERM)\n"


def test_deferred_signals_record_then_raise_on_the_second(tmp_path: Path) -> None:
    """The first SIGINT / SIGTERM is recorded; a second one raises (or is recorded too)."""
    from selenv.exits import DeferredSignals, Terminated

    before = signal.getsignal(signal.SIGTERM)
    with DeferredSignals() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.signal == "SIGTERM" and stop.received == [signal.SIGTERM]
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
    with DeferredSignals() as stop, pytest.raises(Terminated):
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)
    with DeferredSignals(second_raises=False) as late:
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)
    assert late.signal == "SIGINT" and late.received == [signal.SIGINT, signal.SIGTERM]
    assert signal.getsignal(signal.SIGTERM) is before  # restored
