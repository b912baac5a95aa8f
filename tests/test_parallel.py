"""selenv.parallel: executors, Ray start-up/shutdown, and bench results identical on all three.

The equality tests run every env family (four Gymnasium envs, two PettingZoo modules, learned
and stochastic agents included) on the local, process and Ray executors with the same seeds and
require bit-identical returns, final objectives and skip reasons; the Ray instance they use is
started once for the module and must leave no process behind.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
import uuid
from pathlib import Path

import _proc
import numpy as np
import pytest

from selenv.bench import run_bench
from selenv.cli import main
from selenv.parallel import (
    ExecutorError,
    LocalExecutor,
    ProcessExecutor,
    RayExecutor,
    WorkerDiedError,
    check_address,
    make_executor,
    max_pool_workers,
    ray_session,
)

ray = pytest.importorskip("ray")


def _raylet_pids() -> set[int]:
    """PIDs of raylet processes on this machine (Ray's per-node daemon)."""
    pids = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if b"raylet" in cmd.split(b"\0", 1)[0]:
            pids.add(int(entry.name))
    return pids


def _draw(seed: int) -> float:
    return float(np.random.default_rng(seed).normal())


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError(f"task {x} refuses")
    return x * x


def _sleep_then(x: tuple[float, int]) -> int:
    time.sleep(x[0])
    return x[1]


@pytest.fixture(scope="module")
def ray_executor():
    """One embedded Ray instance (2 CPUs) for the module; checks nothing is left after it."""
    before = _raylet_pids()
    ex = RayExecutor(num_workers=2)
    ex.start()
    started = _raylet_pids() - before
    assert started, "an embedded Ray instance should run a raylet"
    yield ex
    ex.close()
    assert not ray.is_initialized()
    deadline = time.monotonic() + 30
    while (_raylet_pids() & started) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not (_raylet_pids() & started), "the raylet we started is still running"


@pytest.fixture(scope="module")
def process_executor():
    with ProcessExecutor(num_workers=2) as ex:
        yield ex


def _executors(process_executor, ray_executor):
    return {"local": LocalExecutor(), "process": process_executor, "ray": ray_executor}


def test_map_keeps_task_order_and_seeds(process_executor, ray_executor):
    tasks = list(range(25))
    want = [_draw(s) for s in tasks]
    for name, ex in _executors(process_executor, ray_executor).items():
        assert ex.map(_draw, tasks, progress=False) == want, name
    # completion order differs from task order: the result order must not
    slow_first = [(0.3, 0), (0.0, 1), (0.0, 2), (0.1, 3)]
    for ex in (process_executor, ray_executor):
        assert ex.map(_sleep_then, slow_first, progress=False) == [0, 1, 2, 3]


def test_worker_exception_is_reraised_as_itself(process_executor, ray_executor):
    for name, ex in _executors(process_executor, ray_executor).items():
        with pytest.raises(ValueError, match="task 3 refuses") as info:
            ex.map(_fail_on_three, [1, 2, 3, 4], progress=False)
        assert type(info.value) is ValueError, name  # Ray's RayTaskError wrapper removed
    # and the executors still work afterwards
    assert ray_executor.map(_fail_on_three, [1, 2], progress=False) == [1, 4]


def test_weights_must_match_tasks():
    with pytest.raises(ValueError, match="weights has 1 entries for 2 tasks"):
        LocalExecutor().map(_draw, [1, 2], weights=[1], progress=False)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"name": "dask"}, "--executor 'dask' is not one of: local, process, ray"),
        ({"name": "local", "address": "1.2.3.4:6379"}, "--address only applies to --executor ray"),
        ({"name": "process", "num_workers": 0}, "--num-workers must be an integer >= 1"),
        ({"name": "ray", "num_workers": 1.5}, "--num-workers must be an integer >= 1"),
    ],
)
def test_make_executor_rejects(kwargs, match):
    name = kwargs.pop("name")
    with pytest.raises(ExecutorError, match=match):
        make_executor(name, **kwargs)


@pytest.mark.parametrize("address", ["nohost", "host:0", "host:port", ":6379", "a:70000", ""])
def test_malformed_address(address):
    with pytest.raises(ExecutorError, match="--address"):
        check_address(address)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_address_fails_fast(monkeypatch):
    """Refused by the TCP probe before ``ray.init`` runs (Ray's own retry loop takes minutes)."""
    before = _raylet_pids()
    addr = f"127.0.0.1:{_free_port()}"
    inits: list[object] = []
    monkeypatch.setattr(ray, "init", lambda *args, **kwargs: inits.append((args, kwargs)))
    with pytest.raises(ExecutorError, match=r"no Ray cluster reachable.*ray start --head"):
        with RayExecutor(address=addr):
            pass
    assert inits == []  # never reached Ray's connection loop
    assert not ray.is_initialized() or _raylet_pids() - before == set()


def test_ray_not_installed(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    monkeypatch.delitem(__import__("sys").modules, "ray")
    with pytest.raises(ExecutorError, match=r"needs Ray.*pip install 'selenv\[ray\]'"):
        make_executor("ray")


def test_session_reuses_a_running_instance(ray_executor):
    # ray_executor's instance is running: a nested session must neither restart nor stop it
    with ray_session() as r:
        assert r.is_initialized()
    assert ray.is_initialized()


# -- bench: identical results on every executor ---------------------------------------------

CASES = [
    ("selenv/FIMSelection-v1", {"n_candidates": 16, "budget": 4}, None),
    ("selenv/LandmarkSelection-v1", {"n_landmarks": 7, "horizon": 4}, None),
    ("selenv/ReceiverClustering-v1", {"horizon": 6}, "ga,greedy,fixed_random,ppo"),
    ("selenv/CLScheduling-v1", {"horizon": 6}, "greedy,random,round_robin,rollout"),
    ("selenv.multiagent.fim_selection_v0", {"n_candidates": 10, "budgets": 3}, None),
    ("selenv.multiagent.receiver_clustering_v1", {"horizon": 6}, None),
]


def _summary(result):
    return {
        name: (a.returns, a.final_objectives, a.skipped, a.decisions, a.cost_evaluations)
        for name, a in result.agents.items()
    }


@pytest.mark.parametrize(("env_id", "kwargs", "agents"), CASES, ids=[c[0] for c in CASES])
def test_bench_identical_on_every_executor(env_id, kwargs, agents, process_executor, ray_executor):
    names = None if agents is None else agents.split(",")
    runs = {
        label: _summary(
            run_bench(
                env_id, names, episodes=5, seed=11, env_kwargs=kwargs, progress=False, executor=ex
            )
        )
        for label, ex in _executors(process_executor, ray_executor).items()
    }
    local = runs["local"]
    assert any(v[0] for v in local.values()), "nothing was played"
    assert all(len(v[0]) == 5 for v in local.values() if v[2] is None)
    assert runs["process"] == local
    assert runs["ray"] == local


def test_bench_cli_json_records_executor(tmp_path, ray_executor):
    out = tmp_path / "b.json"
    argv = [
        "bench",
        "selenv/FIMSelection-v1",
        "--agents",
        "greedy,random",
        "--episodes",
        "3",
        "--env-kwargs",
        '{"n_candidates": 12, "budget": 3}',
        "--no-progress",
    ]
    assert main([*argv, "--json", str(out), "--executor", "ray", "--num-workers", "2"]) == 0
    doc = json.loads(out.read_text())
    assert doc["provenance"]["executor"] == {"executor": "ray", "num_workers": 2, "address": None}
    assert ray.is_initialized()  # the module's instance was reused, not shut down
    local = tmp_path / "l.json"
    assert main([*argv, "--json", str(local)]) == 0
    res = [json.loads(p.read_text())["results"][0]["agents"] for p in (out, local)]
    strip = [
        {
            k: {f: v for f, v in a.items() if "second" not in f and "ms" not in f}
            for k, a in r.items()
        }
        for r in res
    ]
    assert strip[0] == strip[1]


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--executor", "dask"], "--executor"),
        (["--address", "127.0.0.1:1"], "--address only applies to --executor ray"),
        (["--executor", "ray", "--address", "127.0.0.1:PORT"], "no Ray cluster reachable"),
        (["--executor", "process", "--num-workers", "0"], "--num-workers"),
    ],
)
def test_bench_cli_bad_executor_options(tmp_path, capsys, extra, needle):
    extra = [e.replace("PORT", str(_free_port())) for e in extra]
    out = tmp_path / "x.json"
    argv = [
        "bench",
        "selenv/FIMSelection-v1",
        "--agents",
        "greedy",
        "--episodes",
        "1",
        "--no-progress",
        "--json",
        str(out),
        *extra,
    ]
    assert main(argv) == 2
    assert needle in capsys.readouterr().err
    assert not out.exists()


def test_bench_cli_ray_missing(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    argv = [
        "bench",
        "selenv/FIMSelection-v1",
        "--agents",
        "greedy",
        "--episodes",
        "1",
        "--no-progress",
        "--executor",
        "ray",
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--executor ray needs Ray" in err and "pip install" in err


def test_thread_caps_restored_after_pool(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    with ProcessExecutor(num_workers=1) as ex:
        assert ex.map(_draw, [1], progress=False) == [_draw(1)]
    assert os.environ["OMP_NUM_THREADS"] == "7"


# -- the other users of the executors: surrogate datasets and the reproduction scripts --------


def test_surrogate_dataset_identical_on_every_executor(process_executor, ray_executor):
    from selenv.learned.surrogate_data import GenerationConfig, generate_dataset

    gen = GenerationConfig(per_task=40)
    sets = {
        name: generate_dataset(130, seed=5, gen=gen, progress=False, executor=ex)
        for name, ex in _executors(process_executor, ray_executor).items()
    }
    ref = sets["local"]
    assert len(ref) == 130
    for name in ("process", "ray"):
        for key in ("P_i", "P_j", "H_i", "H_j", "omega", "C", "C_diag"):
            np.testing.assert_array_equal(getattr(sets[name], key), getattr(ref, key), name)
    # and the task seeds really matter: another master seed gives other rows
    other = generate_dataset(130, seed=6, gen=gen, progress=False)
    assert not np.array_equal(other.P_i, ref.P_i)


def _load_script(name: str):
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_reproduction_script_identical_on_ray(tmp_path, ray_executor):
    script = _load_script("reproduce_chen_kia")
    runs = {
        ex: script.main(["--quick", "--out", str(tmp_path / ex), "--executor", ex])
        for ex in ("local", "ray")
    }
    assert runs["ray"]["executor"]["executor"] == "ray"
    for method, res in runs["local"]["results"].items():
        other = runs["ray"]["results"][method]
        np.testing.assert_array_equal(other["rmse"], res["rmse"], method)
        np.testing.assert_array_equal(other["mean_nees"], res["mean_nees"], method)


def test_reproduction_script_bad_executor(tmp_path, capsys):
    """A bad executor choice is a usage error of the script: exit 2, one line."""
    from selenv.exits import guarded_main

    script = _load_script("reproduce_chen_kia")
    argv = ["--quick", "--out", str(tmp_path), "--address", "127.0.0.1:1"]
    assert guarded_main(script.main, "reproduce_chen_kia.py", argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--address only applies to --executor ray" in err[0]


def _signal_parent_twice(x: int) -> str:
    """Task 0: SIGTERM to the parent, then a second one while the parent collects; finish."""
    from selenv.parallel.executors import stop_requested

    if x != 0:
        return f"done {x}"
    os.kill(os.getppid(), signal.SIGTERM)
    deadline = time.monotonic() + 10
    while not stop_requested() and time.monotonic() < deadline:  # the parent's stop request
        time.sleep(0.01)
    os.kill(os.getppid(), signal.SIGTERM)  # the second signal, during the parent's collection
    time.sleep(0.3)
    return "stopped 0" if stop_requested() else "not stopped"


def test_a_second_signal_while_the_workers_hand_back_keeps_their_results():
    """SIGTERM, then another while the pool's workers hand back what they have: the map still
    collects them (the second signal waits), then raises ``Terminated``."""
    from selenv.exits import Terminated, sigterm_raises

    got: dict[int, str] = {}
    with sigterm_raises(), pytest.raises(Terminated):
        ProcessExecutor(2).map(_signal_parent_twice, [0, 1], on_result=got.__setitem__)
    assert got.get(0) == "stopped 0"


def _die_on_one(x: int) -> int:
    if x == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.2)
    return x


def test_dead_pool_worker_is_one_worker_died_error():
    """A worker killed mid-map: WorkerDiedError naming its PID and signal; finished results
    were handed to on_result; the next map gets a fresh pool."""
    got: dict[int, int] = {}
    with ProcessExecutor(num_workers=2) as ex:
        with pytest.raises(WorkerDiedError, match=r"PID \d+ killed by SIGKILL"):
            ex.map(_die_on_one, [0, 1, 2, 3], progress=False, on_result=got.__setitem__)
        assert set(got) <= {0, 2, 3} and all(got[k] == k for k in got)
        assert ex.map(abs, [-1, -2], progress=False) == [1, 2]


def test_pool_size_ceiling():
    with pytest.raises(ExecutorError, match="--num-workers 100000 exceeds the ceiling"):
        ProcessExecutor(num_workers=100_000)
    assert max_pool_workers() >= 16


def _marked(mark: str) -> list[int]:
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


def test_pool_workers_die_with_their_parent(tmp_path):
    """SIGKILL of the process that owns a pool: its workers do not outlive it."""
    mark = uuid.uuid4().hex
    code = (
        "import time\n"
        "from selenv.parallel import ProcessExecutor\n"
        "with ProcessExecutor(num_workers=2) as ex:\n"
        "    ex.map(time.sleep, [60, 60], progress=False)\n"
    )
    env = {
        **os.environ,
        "SELENV_FAULT_MARK": mark,
        "PYTHONPATH": str(Path(__file__).resolve().parents[1]),
    }
    parent = _proc.popen([sys.executable, "-c", code], env=env, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 30
        while len(set(_marked(mark)) - {parent.pid}) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        workers = set(_marked(mark)) - {parent.pid}
        assert len(workers) >= 2, "the pool's workers did not start"
        parent.kill()
        _proc.wait(parent, 10)
        deadline = time.monotonic() + 10
        while set(_marked(mark)) & workers and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not set(_marked(mark)) & workers, "pool workers outlived their parent"
    finally:
        _proc.stop(parent)
