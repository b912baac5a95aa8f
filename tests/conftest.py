"""Shared fixtures: random SPD matrices, candidate pools, and the reproduction scripts."""

from __future__ import annotations

import atexit
import importlib.util
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(name: str) -> ModuleType:
    """Import ``scripts/<name>.py`` as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load scripts/{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses and pickling look the module up by name
    spec.loader.exec_module(module)
    return module


def random_spd(rng: np.random.Generator, d: int, scale: float = 1.0) -> np.ndarray:
    A = rng.normal(size=(d, d))
    return scale * (A @ A.T / d + 0.5 * np.eye(d))


def random_pool(
    rng: np.random.Generator, N: int, d: int, m: int = 1, pad: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """``H (N, m, d)``, ``R (N, m, m)``; with ``pad`` every other candidate has one zero row."""
    H = rng.normal(size=(N, m, d))
    R = np.stack([random_spd(rng, m, 0.5) for _ in range(N)])
    if pad and m > 1:
        H[::2, 1:, :] = 0.0
        R[::2, 1:, :] = 0.0
        R[::2, :, 1:] = 0.0
        for k in range(0, N, 2):
            R[k, 1:, 1:] = np.eye(m - 1)
    return H, R


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


# -- torch threads under pytest-xdist ------------------------------------------------------------

_torch_threads_set = False


@pytest.fixture(autouse=True)
def _torch_threads_per_xdist_worker() -> None:
    """Under pytest-xdist: torch's intra-op threads = this machine's CPUs / the workers.

    torch starts one thread per core in every worker: with ``make test``'s 2 workers on 2 cores
    that is 4 busy threads on 2 cores, and a torch-heavy test ran several times slower than
    alone (its threads wait for each other). Set once, as soon as torch is imported (this never
    imports it); a plain ``pytest`` run (no workers) keeps torch's default.
    """
    global _torch_threads_set
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT", "")
    if _torch_threads_set or not workers.isdigit() or "torch" not in sys.modules:
        return
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    sys.modules["torch"].set_num_threads(max(1, (cpus or 1) // max(1, int(workers))))
    _torch_threads_set = True


# -- hypothesis profiles of the fuzz suite (tests/test_fuzz_*.py) ---------------------------------
#
# ``fuzz-ci`` (default): derandomized (same examples on every run and machine), no example
# database, few examples: the whole fuzz suite runs in well under two minutes.
# ``fuzz-long``: the same tests with many more examples, plus the tests marked ``fuzz_long``
# (skipped otherwise). Select it with ``SELENV_FUZZ=long`` or ``-m fuzz_long``:
#
#     .venv/bin/python -m pytest tests/test_fuzz_core.py tests/test_fuzz_envs.py   # fuzz-ci
#     SELENV_FUZZ=long .venv/bin/python -m pytest -m fuzz tests                    # fuzz-long
#     .venv/bin/python -m pytest -m fuzz_long tests                 # only the long-only tests
#
# The names are namespaced: Hypothesis loads its built-in ``ci`` profile by itself on CI, so a
# profile called ``ci`` would change every other property test of the repository there.
FUZZ_ENV = "SELENV_FUZZ"
_FUZZ_COMMON = settings(
    derandomize=True,
    database=None,
    deadline=None,
    print_blob=True,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
        HealthCheck.filter_too_much,
        HealthCheck.large_base_example,
    ],
)
settings.register_profile("fuzz-ci", _FUZZ_COMMON, max_examples=12)
settings.register_profile("fuzz-long", _FUZZ_COMMON, max_examples=300)
_LONG_BY_MARKER = False


def fuzz_long_selected() -> bool:
    """Whether the long fuzz profile is selected (``SELENV_FUZZ=long`` or ``-m fuzz_long``)."""
    return _LONG_BY_MARKER or os.environ.get(FUZZ_ENV, "").strip().lower() == "long"


def fuzz_settings(weight: float = 1.0) -> settings:
    """Settings of one fuzz test: the selected profile, ``weight`` times its example count."""
    profile = settings.get_profile("fuzz-long" if fuzz_long_selected() else "fuzz-ci")
    return settings(profile, max_examples=max(1, round(profile.max_examples * weight)))


#: environment variable: the signals the suite's launch left ignored (``"SIGINT,SIGQUIT"`` for a
#: background job of a non-interactive shell, ``""`` in a terminal)
LAUNCH_IGNORED = "SELENV_SUITE_LAUNCH_IGNORED"


def _foreground_signals() -> None:
    """SIGINT and SIGQUIT as in a terminal, whatever the launcher left ignored.

    A background job of a non-interactive shell (``nohup make test &``, some CI runners)
    starts with both ignored. The in-process signal tests send SIGINT to this process and
    expect the product's handlers to see it as they do in a foreground run; children get
    their defaults from tests/_proc.py. SIGHUP stays as inherited (``nohup``'s purpose).
    The first process of a run (xdist's controller) records what the launch ignored in the
    environment variable :data:`LAUNCH_IGNORED`, which its workers inherit and the check of
    ``make test-detached`` reads (tests/test_proc.py).
    """
    ignored = [
        s.name for s in (signal.SIGINT, signal.SIGQUIT) if signal.getsignal(s) is signal.SIG_IGN
    ]
    os.environ.setdefault(LAUNCH_IGNORED, ",".join(ignored))
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGQUIT) is signal.SIG_IGN:
        signal.signal(signal.SIGQUIT, signal.SIG_DFL)


def _sb3_log_folder() -> None:
    """One folder for every SB3 logger of the run, removed when the run ends.

    SB3's ``learn()`` creates ``<tmp>/SB3-<date and time>`` for its logger unless
    ``SB3_LOGDIR`` names one, so each test that trains would leave a folder in ``/tmp``. The
    first process of a run (xdist's controller) creates the folder and removes it at exit; its
    workers and the CLI subprocesses inherit the variable.
    """
    if "SB3_LOGDIR" in os.environ:
        return
    folder = tempfile.mkdtemp(prefix="selenv-tests-sb3-")
    os.environ["SB3_LOGDIR"] = folder
    atexit.register(shutil.rmtree, folder, True)


def pytest_configure(config: pytest.Config) -> None:
    global _LONG_BY_MARKER
    _foreground_signals()
    _sb3_log_folder()
    _LONG_BY_MARKER = "fuzz_long" in (config.getoption("markexpr", "") or "")


#: test files whose verdicts depend on floating-point rounding (decisions near ties, refusals of
#: near-singular inputs, values compared to tolerances, references vs faster code): CI runs
#: them a second time under another OpenBLAS kernel (``make test-numerics``), see
#: docs/guide/testing.md
NUMERICS_FILES = frozenset(
    {
        "test_cl_fast_rollout.py",
        "test_cl_scorer.py",
        "test_cl_vector.py",
        "test_cl_vector_previews.py",
        "test_clustering_ga.py",
        "test_clustering_regimes.py",
        "test_clustering_speed_identity.py",
        "test_clustering_vector.py",
        "test_env_speed_identity.py",
        "test_estimation.py",
        "test_fim_fast_paths.py",
        "test_fim_vector.py",
        "test_fim_solvers.py",
        "test_fusion.py",
        "test_fusion_accuracy.py",
        "test_information.py",
        "test_kalman.py",
        "test_landmark_vector.py",
        "test_numpy_fallbacks.py",
        "test_objective_registry.py",
        "test_objectives.py",
        "test_spd_contract.py",
        "test_speed_identity_core.py",
        "test_speed_identity_greedy.py",
        "test_validation.py",
        "test_vector_base.py",
    }
)


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """With exactly ``-m numerics`` (``make test-numerics``), import only the numerics files.

    Every other test file would be deselected anyway; not importing them saves the ~20 s of
    collecting the whole suite (torch, Ray, SB3 imports) in every xdist worker.
    """
    if config.getoption("markexpr", "") != "numerics":
        return None
    name = collection_path.name
    if collection_path.suffix == ".py" and name.startswith("test_") and name not in NUMERICS_FILES:
        return True
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    numerics = pytest.mark.numerics
    for item in items:
        if item.path.name in NUMERICS_FILES:
            item.add_marker(numerics)
    if fuzz_long_selected():
        return
    skip = pytest.mark.skip(reason=f"long fuzz test: run with {FUZZ_ENV}=long or -m fuzz_long")
    for item in items:
        if "fuzz_long" in item.keywords:
            item.add_marker(skip)


# -- a real full file system for the fault-injection tests -------------------------------------


@pytest.fixture
def tmpfs_of_size(tmp_path: Path):
    """``make(size)``: a fresh tmpfs of ``size`` (``"64k"``) mounted under ``tmp_path``.

    Root only: skips where mounting is not allowed. Unmounted at teardown (lazily if a file is
    still open, e.g. referenced by a failed save's traceback).
    """
    import gc

    from _proc import run

    mounts: list[Path] = []

    def make(size: str = "64k") -> Path:
        mnt = tmp_path / f"tmpfs{len(mounts)}"
        mnt.mkdir()
        proc = run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)],
            capture_output=True,
            timeout=60,
        )
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}")
        mounts.append(mnt)
        return mnt

    yield make
    gc.collect()
    for mnt in mounts:
        if run(["umount", str(mnt)], capture_output=True, timeout=60).returncode:
            run(["umount", "-l", str(mnt)], capture_output=True, timeout=60)


@pytest.fixture
def tiny_fs(tmpfs_of_size) -> Path:
    """A 64 KiB tmpfs: writes of more than that fail with ENOSPC."""
    return tmpfs_of_size("64k")
