"""Input bounds checked before any work: one line / a ``ValueError`` naming the input.

Nested JSON and TOML (every reader of the CLIs), the memory of ``make_vec`` and of the raw FIM
solvers, the pre-flight write probe of ``--json``, the ``--num-workers`` ceiling before any
heavy import, the refusal of a hostile ``.pth`` file and a killed resource tracker.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import pickle
import shutil
import sys
import zipfile
from pathlib import Path
from typing import Any

import pytest
from _proc import run

from selenv import untrusted
from selenv.agents import parse_spec
from selenv.cli import main
from selenv.learned.config import ConfigFileError, arg, parse_config, read_config_file

DEEP = 2000


def _nested_json(depth: int = DEEP) -> str:
    return '{"a": ' + "[" * depth + "]" * depth + "}"


def _one_error_line(err: str, *needles: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


# --- 1. nesting and size of every JSON / TOML the CLIs read ---------------------------------


@pytest.mark.parametrize(
    "text",
    [
        "[" * DEEP + "]" * DEEP,
        '{"k": ' * 100_000 + "1" + "}" * 100_000,
        '["' + "[" * 100 + '", ' + "[" * 70 + "]" * 70 + "]",
    ],
    ids=["arrays", "objects-1e5", "brackets-in-strings-then-deep"],
)
def test_deep_json_is_a_value_error_naming_the_input(text: str) -> None:
    with pytest.raises(ValueError, match=r"^--env-kwargs: nested deeper than 64 levels"):
        untrusted.loads_json(text, "--env-kwargs")


def test_brackets_inside_strings_do_not_count_and_limits_are_read_at_call_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    text = json.dumps({"s": "[" * 500, "v": [[[1]]]})
    assert untrusted.loads_json(text, "x") == json.loads(text)
    monkeypatch.setitem(untrusted.LIMITS, "max_depth", 3)
    with pytest.raises(ValueError, match="x: nested deeper than 3 levels"):
        untrusted.loads_json(text, "x")
    monkeypatch.setitem(untrusted.LIMITS, "max_argument_bytes", 10)
    with pytest.raises(ValueError, match=r"x: \d+ bytes, more than the ceiling of 10"):
        untrusted.loads_json(json.dumps({"s": "y" * 20}), "x")


@pytest.mark.parametrize(
    "text",
    [
        "x = " + "[" * DEEP + "]" * DEEP,
        "x = " + "{a = " * DEEP + "1" + "}" * DEEP,
        "x." * 300 + "y = 1",
        "[" + "t." * 300 + "u]\nv = 1",
    ],
    ids=["arrays", "inline-tables", "dotted-keys", "table-header"],
)
def test_deep_toml_is_a_value_error_naming_the_input(text: str) -> None:
    with pytest.raises(ValueError, match=r"^--config f\.toml: nested deeper than 64 levels"):
        untrusted.loads_toml(text, "--config f.toml")


def test_toml_strings_and_comments_do_not_count() -> None:
    text = 's = "[[[[[["\nm = """\n[[[[[[\n"""\n# [[[[[[[[\n[t]\nv = [[1], [2]]\n'
    assert untrusted.loads_toml(text, "f") == {
        "s": "[[[[[[",
        "m": "[[[[[[\n",
        "t": {"v": [[1], [2]]},
    }


def test_bench_env_kwargs_nested_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["bench", "selenv/FIMSelection-v1", "--env-kwargs", _nested_json()])
    assert code == 2
    captured = capsys.readouterr()
    _one_error_line(captured.err, "--env-kwargs", "nested deeper than 64")
    assert captured.out == ""


@pytest.mark.parametrize("text", ["[1]", "{oops"])
def test_bench_env_kwargs_not_an_object_is_one_line_exit_2(
    text: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "selenv/FIMSelection-v1", "--env-kwargs", text]) == 2
    _one_error_line(capsys.readouterr().err, "--env-kwargs")


def test_agent_spec_option_nested_is_refused_and_plain_text_stays_a_string() -> None:
    with pytest.raises(ValueError, match="agent spec 'rollout': option top_k: nested deeper"):
        parse_spec("rollout:top_k=" + "[" * DEEP + "]" * DEEP)
    assert parse_spec("rollout:top_k=5:mode=fast") == ("rollout", {"top_k": 5, "mode": "fast"})


def test_bench_agent_spec_nested_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    spec = "greedy:x=" + "[" * DEEP + "]" * DEEP
    assert main(["bench", "selenv/FIMSelection-v1", "--agents", spec]) == 2
    _one_error_line(capsys.readouterr().err, "--agents", "nested deeper than 64")


@dataclasses.dataclass
class _Cfg:
    steps: int = arg(3, "steps")
    env_kwargs: str = arg("{}", "env keywords")


def test_config_toml_nested_is_refused_before_parsing(tmp_path: Path) -> None:
    path = tmp_path / "deep.toml"
    path.write_text("steps = 5\nx = " + "[" * DEEP + "]" * DEEP + "\n")
    with pytest.raises(ConfigFileError, match=r"--config .*deep\.toml: nested deeper than 64"):
        read_config_file(path, _Cfg)


def test_config_toml_nested_exits_2_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "deep.toml"
    path.write_text("x = " + "{a = " * DEEP + "1" + "}" * DEEP + "\n")
    with pytest.raises(SystemExit) as stop:
        parse_config(_Cfg, ["--config", str(path)], "test", script="tests.cfg")
    assert stop.value.code == 2
    _one_error_line(capsys.readouterr().err, "--config", "nested deeper than 64")


def test_config_toml_too_large_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(untrusted.LIMITS, "max_bytes", 100)
    path = tmp_path / "big.toml"
    path.write_text("steps = 5\n" + "# padding\n" * 20)
    with pytest.raises(ConfigFileError, match="more than the ceiling of 100"):
        read_config_file(path, _Cfg)


def test_training_env_kwargs_nested_is_a_usage_error() -> None:
    pytest.importorskip("torch")
    from selenv.exits import UsageError
    from selenv.learned.rl.training import PPOConfig

    cfg = PPOConfig(env_kwargs=_nested_json())
    with pytest.raises(UsageError, match=r"^--env-kwargs: nested deeper than 64"):
        cfg.kwargs()
    assert PPOConfig(env_kwargs='{"budget": 3}').kwargs() == {"budget": 3}


def test_checkpoint_metadata_reader_shares_the_scan(tmp_path: Path) -> None:
    from selenv.learned.resources import json_depth, read_metadata

    assert json_depth is untrusted.json_depth
    path = tmp_path / "m.json"
    path.write_text(_nested_json())
    with pytest.raises(ValueError, match="nested deeper than 64"):
        read_metadata(path)


# --- 4. the pre-flight write probe finds an output that cannot be replaced ------------------


def _no_episode(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Record every ``run_bench`` call (the refusal must come before the first one)."""
    import selenv.bench

    calls: list[str] = []

    def recorded(env_id: str, *args: Any, **kwargs: Any) -> Any:
        calls.append(env_id)
        raise AssertionError("an episode ran")

    monkeypatch.setattr(selenv.bench, "run_bench", recorded)
    return calls


def _chattr(flag: str, path: Path) -> bool:
    """``chattr flag path``; False where the file system or the user cannot."""
    if shutil.which("chattr") is None:
        return False
    done = run(["chattr", flag, str(path)], capture_output=True, timeout=30)
    return done.returncode == 0


@pytest.mark.parametrize("flag", ["+i", "+a"])
def test_immutable_json_is_refused_before_any_episode(
    flag: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "out.json"
    out.write_text("{}")
    if not _chattr(flag, out):
        pytest.skip(f"chattr {flag} does not work here (the mocked-syscall test covers it)")
    calls = _no_episode(monkeypatch)
    try:
        code = main(["bench", "selenv/FIMSelection-v1", "--agents", "greedy", "--json", str(out)])
    finally:
        _chattr(flag.replace("+", "-"), out)
    assert code == 2 and calls == []
    _one_error_line(capsys.readouterr().err, f"--json {out}", "EPERM")
    assert out.read_text() == "{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def _eperm_on_write_open(monkeypatch: pytest.MonkeyPatch, target: Path) -> None:
    """``os.open(target, O_WRONLY...)`` fails with EPERM, as on an immutable file."""
    real_open = os.open

    def refusing(path: Any, flags: int, *args: Any, **kwargs: Any) -> int:
        if Path(path) == target and flags & os.O_WRONLY:
            raise PermissionError(errno.EPERM, "Operation not permitted", str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", refusing)


def test_unreplaceable_json_mocked_is_refused_before_any_episode(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.json"
    out.write_text("{}")
    calls = _no_episode(monkeypatch)
    _eperm_on_write_open(monkeypatch, out)
    code = main(["bench", "selenv/FIMSelection-v1", "--agents", "greedy", "--json", str(out)])
    assert code == 2 and calls == []
    _one_error_line(capsys.readouterr().err, f"--json {out}", "immutable", "EPERM")


def test_probe_replaceable_passes_plain_and_read_only_files(tmp_path: Path) -> None:
    from selenv.atomic import probe_replaceable

    plain, missing = tmp_path / "a.json", tmp_path / "none.json"
    plain.write_text("{}")
    probe_replaceable(plain)
    probe_replaceable(missing)
    assert plain.read_text() == "{}" and not missing.exists()


def test_training_outputs_forced_onto_an_unreplaceable_file_exit_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from selenv.learned.config import check_outputs

    out = tmp_path / "p.zip"
    out.write_bytes(b"old")
    _eperm_on_write_open(monkeypatch, out)
    with pytest.raises(SystemExit) as stop:
        check_outputs("prog", [out], force=True)
    assert stop.value.code == 2
    _one_error_line(capsys.readouterr().err, f"--out {out}", "EPERM")
    assert out.read_bytes() == b"old"


# --- 5. ceilings before any import-heavy work ----------------------------------------------

_CHILD = """
import sys
from selenv.cli import main
code = main(sys.argv[1:])
heavy = sorted(m for m in ("torch", "ray", "stable_baselines3") if m in sys.modules)
print(code, ",".join(heavy) or "-")
"""


def test_num_workers_ceiling_is_checked_before_agents_or_executors_load() -> None:
    argv = ["bench", "--executor", "process", "--num-workers", "100000", "--episodes", "1"]
    done = run([sys.executable, "-c", _CHILD, *argv], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["2", "-"], done.stdout
    _one_error_line(done.stderr, "--num-workers 100000", "ceiling")


@pytest.mark.parametrize(
    ("script", "option"),
    [
        ("train_cl_cem", "--workers"),
        ("train_cl_expert", "--workers"),
        ("train_clustering_dagger", "--workers"),
        ("train_landmark_expert", "--workers"),
        ("train_clustering_ppo", "--rank-workers"),
    ],
)
def test_training_worker_counts_are_refused_before_any_process_starts(
    script: str,
    option: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A worker count above the pool's ceiling: exit 2, one line, no pool, nothing written."""
    import importlib
    import multiprocessing.pool

    import selenv.parallel.executors as executors
    from selenv.learned.rl.training import run_cli

    module = importlib.import_module(f"selenv.train.{script}")
    started: list[object] = []
    monkeypatch.setattr(executors.ProcessExecutor, "__init__", lambda *a, **k: started.append(a))
    monkeypatch.setattr(multiprocessing.pool.Pool, "__init__", lambda *a, **k: started.append(a))
    ceiling = executors.max_pool_workers()
    out = tmp_path / "run" / ("out.json" if script == "train_cl_cem" else "out.zip")
    argv = ["--out", str(out), option, str(ceiling + 1), "--no-progress"]
    try:  # train_cl_cem's checks exit through SystemExit(2), the others return 2
        code = run_cli(module.main, f"python -m {module.SCRIPT}", argv)
    except SystemExit as stop:
        code = stop.code
    assert code == 2
    _one_error_line(capsys.readouterr().err, f"{option}: must be in [1, {ceiling}]")
    assert started == []
    assert not (tmp_path / "run").exists()


# --- 6. a hostile torch file is refused in one line naming the file ------------------------


class _Payload:
    """Unpickling this creates ``marker``: stands in for an arbitrary shell command."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("saver", ["pickle", "torch.save"])
def test_hostile_tensor_file_is_one_line_and_never_run(saver: str, tmp_path: Path) -> None:
    th = pytest.importorskip("torch")
    from selenv.learned.tensor_load import load_tensors

    marker, pth = tmp_path / "pwned", tmp_path / "m.pth"
    if saver == "pickle":
        pth.write_bytes(pickle.dumps({"w": _Payload(marker)}))
    else:
        th.save({"w": _Payload(marker)}, pth)
    with pytest.raises(ValueError) as err:
        load_tensors(pth, f"weights {pth}", verb="are")
    message = str(err.value)
    assert "\n" not in message and len(message) < 400, message
    assert message.startswith(f"weights {pth} are not a plain tensor file (")
    assert "nothing in it was run" in message and "Weights only load failed" not in message
    assert not marker.exists()


def test_junk_tensor_file_is_one_line(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    from selenv.learned.tensor_load import load_tensors

    for junk in (b"", b"PK\x03\x04junk", b"\x80\x02"):  # empty, a broken zip, a cut pickle
        with pytest.raises(ValueError, match=r"^x\.pt is not a readable tensor file \(") as err:
            load_tensors(junk, "x.pt")
        assert "\n" not in str(err.value)


def test_bench_with_a_hostile_policy_pth_exits_2_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("sb3_contrib")
    from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS

    shipped = DEFAULT_CHECKPOINTS["selenv/FIMSelection-v1"]
    marker, bad = tmp_path / "pwned", tmp_path / "hostile.zip"
    with zipfile.ZipFile(shipped) as src, zipfile.ZipFile(bad, "w") as dst:
        for item in src.infolist():
            if item.filename == "policy.pth":
                dst.writestr(item.filename, pickle.dumps({"w": _Payload(marker)}))
            else:
                dst.writestr(item, src.read(item))
    shutil.copy(shipped.with_suffix(".json"), bad.with_suffix(".json"))
    calls = _no_episode(monkeypatch)
    code = main(["bench", "selenv/FIMSelection-v1", "--agents", f"ppo:{bad}", "--episodes", "1"])
    assert code == 2 and calls == []
    _one_error_line(capsys.readouterr().err, str(bad), "policy.pth is not a plain tensor file")
    assert not marker.exists()


# --- 2. make_vec estimates its memory before allocating ------------------------------------


@pytest.mark.parametrize(
    "env_id", ["selenv/FIMSelection-v1", "selenv/ReceiverClustering-v1", "selenv/CLScheduling-v1"]
)
def test_make_vec_refuses_a_batch_that_does_not_fit_before_allocating(
    env_id: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    import gymnasium as gym

    from selenv.envs import vector_memory

    cls = type(gym.make_vec(env_id, num_envs=1))
    built: list[int] = []
    init = cls.__init__

    def recorded(self: Any, num_envs: int = 1, *args: Any, **kwargs: Any) -> None:
        built.append(num_envs)
        init(self, num_envs, *args, **kwargs)

    monkeypatch.setattr(cls, "__init__", recorded)
    monkeypatch.setattr(vector_memory, "available_memory", lambda: (64 * 2**20, "MemAvailable"))
    with pytest.raises(ValueError) as err:
        gym.make_vec(env_id, num_envs=65536)
    message = str(err.value)
    assert message.startswith("num_envs=65536: ") and "\n" not in message
    assert "would need about" in message and "64.0 MB of memory available" in message
    assert built == [1, 2, 8]  # only the warm-up and the two small probes were built


def test_make_vec_builds_a_batch_that_fits_and_small_batches_are_not_probed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import gymnasium as gym

    from selenv.envs import vector_memory

    estimates: list[int | None] = []
    check = vector_memory.check_vector_memory

    def spy(*args: Any, **kwargs: Any) -> int | None:
        estimates.append(check(*args, **kwargs))
        return estimates[-1]

    monkeypatch.setattr("selenv.envs.vector.check_vector_memory", spy)
    monkeypatch.setattr(vector_memory, "available_memory", lambda: (2**40, "MemAvailable"))
    venv = gym.make_vec("selenv/FIMSelection-v1", num_envs=vector_memory.PROBE_ABOVE)
    assert venv.num_envs == vector_memory.PROBE_ABOVE and estimates == []
    venv = gym.make_vec("selenv/FIMSelection-v1", num_envs=vector_memory.PROBE_ABOVE + 1)
    assert venv.num_envs == vector_memory.PROBE_ABOVE + 1
    assert len(estimates) == 1 and estimates[0] is not None and estimates[0] > 0


def test_available_memory_reads_the_machine() -> None:
    from selenv.envs.vector_memory import available_memory, human_bytes

    free, source = available_memory()
    assert free is None or free > 0
    assert source in ("MemAvailable", "the cgroup's memory.max")
    assert human_bytes(1536) == "1.5 KB" and human_bytes(3 * 2**30) == "3.0 GB"


# --- 3. the raw-array FIM solvers estimate their memory before copying ---------------------

_N = 10**8


def _solver_calls() -> list[tuple[str, tuple[Any, ...]]]:
    import numpy as np

    Q0 = np.eye(4)
    H = np.broadcast_to(np.ones((1, 4)), (_N, 4))  # 32 bytes until something copies it
    R = np.broadcast_to(np.ones(1), (_N,))
    G = np.broadcast_to(np.ones((1, 2, 4)), (_N, 2, 4))
    raw, white = (Q0, H, R, 3), (Q0, G, 3)
    return [
        ("greedy", raw),
        ("lazy_greedy", raw),
        ("swap", raw),
        ("brute_force", raw),
        ("greedy_whitened", white),
        ("lazy_greedy_whitened", white),
        ("swap_whitened", white),
        ("brute_force_whitened", white),
    ]


@pytest.mark.parametrize(
    ("name", "args"), _solver_calls(), ids=lambda v: v if isinstance(v, str) else ""
)
def test_fim_solvers_refuse_a_huge_broadcast_pool_before_copying(
    name: str, args: tuple[Any, ...], monkeypatch: pytest.MonkeyPatch
) -> None:
    import tracemalloc

    from selenv import memory
    from selenv.agents import fim_solvers

    monkeypatch.setattr(memory, "available_memory", lambda: (2**30, "MemAvailable"))
    tracemalloc.start()
    try:
        with pytest.raises(ValueError) as err:
            getattr(fim_solvers, name)(*args)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(err.value)
    assert f"N={_N:,} candidates" in message and "need about" in message, message
    assert "1.0 GB of memory available" in message
    assert peak < 32 * 2**20, f"{name} allocated {peak:,} bytes before refusing"


def test_small_pools_never_read_the_available_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    import numpy as np

    from selenv import memory
    from selenv.agents import fim_solvers

    def unread() -> tuple[int | None, str]:
        raise AssertionError("a small pool read the available memory")

    monkeypatch.setattr(memory, "available_memory", unread)
    H = np.arange(20.0).reshape(10, 2) / 10 + np.eye(10, 2)
    assert len(fim_solvers.greedy(np.eye(2), H, np.ones(10), 2).indices) == 2
    assert fim_solvers.working_bytes(_N, 1, 4) == 8 * _N * (16 + 3 + 32 + 4)


# --- 7. a killed resource tracker: no stdlib tracebacks ------------------------------------

_TRACKER_SCRIPT = """
import os, signal
from multiprocessing import resource_tracker

from selenv.parallel import ProcessExecutor


def square(x):
    return x * x


if __name__ == "__main__":
    with ProcessExecutor(num_workers=2) as pool:
        first = pool.map(square, [1, 2, 3], progress=False)
        os.kill(resource_tracker._resource_tracker._pid, signal.SIGKILL)
        second = pool.map(square, [4, 5], progress=False)
    print(first + second)
"""


def test_a_killed_resource_tracker_prints_no_traceback(tmp_path: Path) -> None:
    if sys.platform == "win32":  # pragma: no cover
        pytest.skip("no resource tracker on Windows")
    script = tmp_path / "tracker_killed.py"
    script.write_text(_TRACKER_SCRIPT)
    done = run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[1,", "4,", "9,", "16,", "25]"]
    assert "Traceback" not in done.stderr and "KeyError" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) <= 1 and all("resource tracker" in line for line in lines), done.stderr
