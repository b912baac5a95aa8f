"""Outputs that are never half-written, and one writer per output.

Every file selenv produces (bench JSON and plots, checkpoints and their metadata, surrogate
weights, datasets, figures) goes through this module:

* :func:`atomic_path` / :func:`atomic_paths` hand out temporary paths in the target's own
  folder (same file system, same suffix, so writers that append one, like SB3's ``save``, keep
  the name); when the block ends without an exception each file is flushed to disk (``fsync``)
  and renamed over its target (``os.replace``, atomic on POSIX), the targets of a group only
  after all of them were written; on an exception the temporaries are removed and the previous
  files are untouched, byte for byte. A process killed at any moment leaves either the old or
  the new file, plus at most a hidden ``.<name>.tmp-*`` file that the next write of the same
  target removes.
* :func:`write_bytes`, :func:`write_text`, :func:`write_json`, :func:`save_figure`: the
  one-call forms.
* :class:`OutputLock`: an exclusive lock file next to an output (``.<name>.lock``, holding
  the owner's PID); a second run aiming at the same output is refused with
  :class:`OutputBusyError`; a lock whose process is gone is taken over.
* :func:`probe_writable`: a real write (create, write, ``fsync``, remove) in the output's
  folder, for checks made before a long run (``os.access`` says yes to root on a full disk),
  and :func:`probe_replaceable`: an existing output that cannot be replaced (immutable or
  append-only) is found then too.
* :func:`describe_os_error`: the one line a command prints for an ``OSError`` on a path.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import secrets
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "OutputBusyError",
    "OutputLock",
    "atomic_path",
    "atomic_paths",
    "describe_os_error",
    "probe_replaceable",
    "probe_writable",
    "save_figure",
    "write_bytes",
    "write_json",
    "write_text",
]

_TMP_MARK = ".tmp-"


def _temp_for(target: Path) -> Path:
    """A fresh hidden name next to ``target`` with the same suffix (``.x.tmp-<pid><hex>.zip``)."""
    token = f"{os.getpid()}{secrets.token_hex(4)}"
    return target.with_name(f".{target.stem}{_TMP_MARK}{token}{target.suffix}")


def _stale_temps(target: Path) -> list[Path]:
    """Temporaries an interrupted earlier write of ``target`` left behind."""
    prefix = f".{target.stem}{_TMP_MARK}"
    if not target.parent.is_dir():
        return []
    return [
        p
        for p in target.parent.iterdir()
        if p.name.startswith(prefix) and p.name.endswith(target.suffix)
    ]


def _fsync_file(path: Path) -> None:
    if path.is_dir():  # a writer that produced a folder (rare): nothing to flush here
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system lets a folder be fsync'ed
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _remove(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        path.unlink()


@contextlib.contextmanager
def atomic_paths(targets: Sequence[str | os.PathLike[str]]) -> Iterator[list[Path]]:
    """Temporary paths for ``targets``, renamed over them together when the block succeeds.

    Write each output to the path handed out for it (the writer may not create it: a target
    whose temporary was never written is left as it was). Parent folders are created. On an
    exception (including ``KeyboardInterrupt``) the temporaries are removed and every target is
    unchanged. The renames happen only after all files were written and flushed, so a group
    (a checkpoint and its metadata) is replaced as a whole except for a crash between two
    ``os.replace`` calls; readers of a pair check that its halves match.
    """
    paths = [Path(t) for t in targets]
    if len({p.resolve() for p in paths}) != len(paths):
        raise ValueError(f"atomic_paths: the targets must differ, got {[str(p) for p in paths]}")
    for p in paths:
        p.parent.mkdir(parents=True, exist_ok=True)
        for stale in _stale_temps(p):
            _remove(stale)
    temps = [_temp_for(p) for p in paths]
    try:
        yield temps
        written = [(t, p) for t, p in zip(temps, paths, strict=True) if t.exists()]
        for t, _ in written:
            _fsync_file(t)
        for t, p in written:
            os.replace(t, p)
        for folder in {p.parent for _, p in written}:
            _fsync_dir(folder)
    finally:
        for t in temps:
            _remove(t)


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike[str]) -> Iterator[Path]:
    """One output: :func:`atomic_paths` for a single target."""
    with atomic_paths([target]) as (temp,):
        yield temp


def write_bytes(target: str | os.PathLike[str], data: bytes) -> Path:
    """Replace ``target`` with ``data`` atomically; return the target's path."""
    with atomic_path(target) as temp:
        with open(temp, "wb") as fh:
            fh.write(data)
    return Path(target)


def write_text(target: str | os.PathLike[str], text: str) -> Path:
    """Replace ``target`` with ``text`` (UTF-8) atomically."""
    return write_bytes(target, text.encode("utf-8"))


def write_json(target: str | os.PathLike[str], obj: Any, *, indent: int | None = 2) -> Path:
    """Replace ``target`` with ``obj`` as JSON (and a final newline) atomically.

    The JSON is serialised before anything is written, so an object that cannot be serialised
    leaves the target untouched.
    """
    return write_text(target, json.dumps(obj, indent=indent) + "\n")


def save_figure(fig: Any, target: str | os.PathLike[str], **kwargs: Any) -> Path:
    """``fig.savefig`` (a matplotlib figure) onto ``target`` atomically.

    The format comes from the target's suffix unless ``format=`` is given; other keywords go to
    ``savefig``.
    """
    path = Path(target)
    kwargs.setdefault("format", path.suffix.lstrip(".") or None)
    with atomic_path(path) as temp:
        fig.savefig(temp, **kwargs)
    return path


def probe_replaceable(target: str | os.PathLike[str]) -> None:
    """Check that an existing regular file ``target`` may be replaced (renamed over).

    The file is opened for writing (no truncation, nothing written, closed at once): an
    immutable or append-only file (``chattr +i`` / ``+a``) refuses that with ``EPERM``, as it
    refuses the final ``os.replace``. A missing or non-regular ``target`` and ``EACCES``
    (permission bits, which do not stop a rename in a writable folder) pass.

    Raises:
        PermissionError: ``EPERM``, naming the file.
    """
    path = Path(target)
    if not path.is_file():
        return
    try:
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except PermissionError as exc:
        if exc.errno == errno.EPERM:
            raise PermissionError(
                errno.EPERM,
                "operation not permitted (an immutable or append-only file cannot be replaced)",
                str(path),
            ) from None
        return
    except OSError:  # e.g. ETXTBSY: not what this probe checks
        return
    os.close(fd)


def probe_writable(target: str | os.PathLike[str]) -> None:
    """Check that an output can really be written where ``target`` points, now.

    Creates the parent folders, writes, flushes and removes a small hidden file next to
    ``target``, and checks that an existing target is a file that may be replaced
    (:func:`probe_replaceable`). Raises the ``OSError`` of the first step that fails
    (``ENOSPC`` on a full disk, ``EROFS``, ``EACCES``, ``EPERM`` for an immutable file, ...)
    or ``IsADirectoryError``.
    """
    path = Path(target)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a folder, expected a file path", str(path))
    probe_replaceable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    probe = _temp_for(path)
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, b"\0" * 4096)
            os.fsync(fd)
        finally:
            os.close(fd)
    finally:
        _remove(probe)


def describe_os_error(exc: OSError, path: str | os.PathLike[str] | None = None) -> str:
    """One line for a failed file operation: the file, the cause and its errno name.

    ``cannot write runs/p.zip: no space left on device (ENOSPC)``.
    """
    where = path if path is not None else exc.filename
    cause = exc.strerror or str(exc) or type(exc).__name__
    code = errno.errorcode.get(exc.errno or 0, "")
    suffix = f" ({code})" if code else ""
    return f"cannot write {where}: {cause.lower()}{suffix}"


class OutputBusyError(RuntimeError):
    """Another live process holds the output's lock."""


class OutputLock:
    """An exclusive lock on an output path, held while a run writes it.

    ``with OutputLock("out.json"):`` creates ``.out.json.lock`` next to the output with
    ``O_EXCL`` (atomic on local file systems) and the owner's PID; it is removed on exit. A
    lock left by a process that no longer exists is taken over; one held by a live process
    raises :class:`OutputBusyError` naming the output and the PID.

    Args:
        target: the output path (file or folder) to protect.
    """

    def __init__(self, target: str | os.PathLike[str]) -> None:
        path = Path(target)
        self.target = path
        self.lock_path = path.with_name(f".{path.name}.lock")
        self._held = False

    def acquire(self) -> None:
        """Take the lock or raise :class:`OutputBusyError`."""
        self.lock_path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):
            try:
                fd = os.open(self.lock_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                owner = self._owner()
                if owner is not None and owner != os.getpid() and _alive(owner):
                    raise OutputBusyError(
                        f"{self.target} is being written by another run (PID {owner}, lock "
                        f"{self.lock_path}); wait for it or choose another output"
                    ) from None
                _remove(self.lock_path)  # stale: its process is gone
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(f"{os.getpid()}\n")
            self._held = True
            return
        raise OutputBusyError(f"could not lock {self.target} ({self.lock_path})")

    def release(self) -> None:
        """Remove the lock file if this object holds it."""
        if self._held:
            _remove(self.lock_path)
            self._held = False

    def _owner(self) -> int | None:
        try:
            return int(self.lock_path.read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return None

    def __enter__(self) -> OutputLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
