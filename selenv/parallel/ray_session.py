"""Start, join and stop Ray on behalf of selenv: :func:`ray_session`, :func:`require_ray`.

``ray_session(address=None)`` starts an embedded local Ray instance (``num_cpus`` CPUs, no
dashboard) and shuts it down when the block ends; ``ray_session(address="HOST:PORT")`` joins
the running cluster at that address (started with ``ray start --head``), ``"auto"`` the one
``ray start`` recorded on this machine. A session that finds Ray already initialised in the
process reuses it and leaves it running (the caller owns it). So the project never leaves a
Ray instance it started behind, and never stops one it did not start.

An embedded instance dies with the process that started it, however that process ends: Ray
ties its GCS server, raylet and monitors to it (the kernel kills them when it dies; the workers
follow the raylet), and a small guard process (:mod:`selenv.parallel._ray_guard`, Linux) kills
what Ray leaves behind, the raylet's dashboard and runtime-env agents, which otherwise wait
about a minute for the dead GCS server. No dashboard is started (``include_dashboard=False``);
Ray still runs its minimal dashboard head and agents, and its raylet stops the node when one
of its agents dies (the executors report that in one line).

Ray's own ``ray.init(address=...)`` retries an unreachable address for minutes; the address is
therefore checked first with a plain TCP connection (``connect_timeout`` seconds) and an
unreachable one is an :class:`~selenv.parallel.errors.ExecutorError` at once.

Workers of an embedded instance get this process's ``sys.path`` (so functions defined in a
script or a test module resolve, as with a spawned process pool); the nodes of a joined
cluster import from their own installation: install selenv on every node.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from selenv.parallel.errors import ExecutorError

__all__ = ["INSTALL_HINT", "check_address", "ray_session", "require_ray"]

#: seconds the guard of an embedded instance gets to finish after the session ends
GUARD_WAIT_SECONDS = 5.0

#: what to install when Ray is missing
INSTALL_HINT = "pip install 'selenv[ray]' (or: pip install 'ray[rllib,tune]>=2.60,<3')"


def require_ray(option: str = "--executor ray") -> ModuleType:
    """Import and return :mod:`ray`.

    Raises:
        ExecutorError: Ray is not installed; the message names ``option`` and what to install.
    """
    try:
        return importlib.import_module("ray")
    except ImportError as exc:
        raise ExecutorError(f"{option} needs Ray, which is not installed: {INSTALL_HINT}") from exc


def _host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of ``"HOST:PORT"`` / ``"ray://HOST:PORT"``; ``None`` for ``"auto"``."""
    if address == "auto":
        return None
    rest = address.removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ExecutorError(
            f"--address {address!r}: expected HOST:PORT (e.g. 10.0.0.5:6379, the address "
            "printed by `ray start --head`), ray://HOST:PORT or auto"
        )
    return host.strip("[]"), int(port)


def check_address(address: str, connect_timeout: float = 5.0) -> None:
    """Fail fast unless a TCP connection to ``address`` opens within ``connect_timeout`` s.

    Raises:
        ExecutorError: malformed or unreachable address (the message says how to start Ray).
    """
    if isinstance(address, bool) or not isinstance(address, str) or not address:
        raise ExecutorError(f"--address must be a non-empty string, got {address!r}")
    hp = _host_port(address)
    if hp is None:
        return
    try:
        with socket.create_connection(hp, timeout=connect_timeout):
            pass
    except OSError as exc:
        raise ExecutorError(
            f"--address {address!r}: no Ray cluster reachable ({exc.strerror or exc}); start "
            "one with `ray start --head` and pass the address it prints, or omit --address "
            "to start a local Ray instance"
        ) from None


@contextlib.contextmanager
def ray_session(
    address: str | None = None, num_cpus: int | None = None, *, connect_timeout: float = 5.0
) -> Iterator[ModuleType]:
    """Run the block with Ray initialised; yield the :mod:`ray` module.

    Args:
        address: ``None`` starts an embedded local instance; ``"HOST:PORT"``, ``"ray://..."``
            or ``"auto"`` joins a running cluster.
        num_cpus: CPUs of the embedded instance (``None``: all of this machine's); ignored
            when joining a cluster (its nodes declare their own).
        connect_timeout: seconds allowed for the reachability check of ``address``.

    Raises:
        ExecutorError: Ray missing, ``address`` malformed or unreachable, or ``num_cpus`` not a
            positive integer.
    """
    if num_cpus is not None and (
        isinstance(num_cpus, bool) or not isinstance(num_cpus, int) or num_cpus < 1
    ):
        raise ExecutorError(f"--num-workers must be an integer >= 1, got {num_cpus!r}")
    ray = require_ray("--executor ray" if address is None else "--address")
    if address is not None:
        check_address(address, connect_timeout)
    if ray.is_initialized():
        yield ray
        return
    # Workers inherit these: one BLAS/torch thread per task (Ray's own default for num_cpus=1
    # tasks), and no usage-stats prompt or upload.
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    kwargs: dict[str, object] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "logging_level": "ERROR",
        "configure_logging": True,
    }
    try:
        if address is None:
            # Like a spawned process pool, local workers import from this process's sys.path
            # (scripts, test folders, a source checkout), not only from site-packages.
            paths = [p for p in sys.path if p and os.path.isdir(p)]
            env = {"PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}
            ray.init(num_cpus=num_cpus, runtime_env={"env_vars": env}, **kwargs)
        else:
            ray.init(address=address, **kwargs)
    except ConnectionError as exc:
        raise ExecutorError(f"--address {address!r}: cannot join the Ray cluster: {exc}") from None
    guard = None
    try:
        if address is None:
            guard = _start_guard(ray)
        yield ray
    finally:
        ray.shutdown()
        _stop_guard(guard)


def _descendants(roots: list[int]) -> list[int]:
    """``roots`` and every process below them (Linux ``/proc``), parents first."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    out, todo = [], list(roots)
    while todo:
        pid = todo.pop(0)
        if pid not in out:
            out.append(pid)
            todo.extend(children.get(pid, []))
    return out


def _instance_processes(ray: ModuleType) -> list[int]:
    """The processes of the embedded instance just started: Ray's own list and their children.

    Raises:
        AttributeError: Ray's internal list of the node's processes is not where it is in
            Ray 2.60.
    """
    node = ray._private.worker._global_node
    roots = [info.process.pid for infos in node.all_processes.values() for info in infos]
    return _descendants(roots)


def _start_guard(ray: ModuleType) -> subprocess.Popen[bytes] | None:
    """Start :mod:`selenv.parallel._ray_guard` over the instance's processes (Linux only).

    Ray's kernel fate-sharing ends the GCS server, the raylet, the monitors and (through the
    raylet) the workers with this process, but not the raylet's agents; the guard SIGKILLs
    whatever of the instance still runs once this process ends the session or dies.
    """
    if not os.path.isdir("/proc/self"):
        return None
    try:
        return _spawn_guard(_instance_processes(ray))
    except (OSError, AttributeError):  # no guard: Ray's own fate-sharing only
        return None


def _spawn_guard(pids: list[int]) -> subprocess.Popen[bytes]:
    """A guard process over ``pids`` (with their start times), in a session of its own.

    Its own session: a Ctrl-C or a hang-up that reaches this process's group (the guard's
    job is to outlive this process) or a kill of that whole group does not reach it.

    Raises:
        OSError: the guard could not be started or given its list.
    """
    from selenv.parallel._ray_guard import start_time

    lines = [f"{pid} {start}\n" for pid in pids if (start := start_time(pid)) is not None]
    guard = subprocess.Popen(
        [sys.executable, "-I", "-S", str(Path(__file__).with_name("_ray_guard.py"))],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        start_new_session=True,
    )
    if guard.stdin is not None:  # always, with stdin=PIPE
        guard.stdin.write("".join(lines).encode("ascii"))
        guard.stdin.flush()
    return guard


def _stop_guard(guard: subprocess.Popen[bytes] | None) -> None:
    """End the guard (it kills what of the instance Ray left running) and reap it."""
    if guard is None:
        return
    with contextlib.suppress(OSError):
        if guard.stdin is not None:
            guard.stdin.close()
    try:
        guard.wait(GUARD_WAIT_SECONDS)
    except subprocess.TimeoutExpired:
        guard.kill()
        guard.wait()
