"""Fault injection on PPO training: kill and resume, SIGINT / SIGTERM, full disks, file-size
limits, busy outputs, mismatched checkpoint pairs and oversized runs.

Training runs are tiny (FIMSelection with 8 candidates, 2 envs x 16 steps per iteration) and run
in a child process through the script's console entry point. The moment of a kill or a signal is
deterministic: the child wraps ``training.save_checkpoint`` and, right after the first periodic
checkpoint pair is written, sends itself the signal (no sleeps).
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import _proc
import pytest

from selenv.atomic import describe_os_error
from selenv.learned.rl import training
from selenv.learned.rl.training import last_paths, run_cli, save_checkpoint
from selenv.train import train_fim_ppo

ROOT = Path(__file__).resolve().parents[1]
PROG = "python -m selenv.train.train_fim_ppo"
TINY = [
    "--n-envs=2",
    "--n-steps=16",
    "--batch-size=32",
    "--n-epochs=1",
    "--hidden=8",
    "--no-progress",
    "--total-timesteps=256",
    "--checkpoint-every=64",
    '--env-kwargs={"n_candidates": 8, "budget": 3}',
    "--eval-episodes=0",
    "--tensorboard-dir=",
]

#: the child: optionally signal itself right after the first periodic checkpoint, then run cli()
CHILD = """
import os, signal, sys
from selenv.atomic import describe_os_error
from selenv.learned.rl import training
from selenv.train import train_fim_ppo
sig = int(sys.argv[1])
kill_at = os.environ.get("KILL_AT_REPLACE")  # SIGKILL when os.replace targets this file
if kill_at:
    import selenv.atomic as atomic
    real_replace = atomic.os.replace
    def replace(src, dst):
        if str(dst) == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        real_replace(src, dst)
    atomic.os.replace = replace
if sig:
    real = training.save_checkpoint
    def save_then_signal(model, meta, path, **kw):
        out = real(model, meta, path, **kw)
        if ".last." in str(path) and "interrupted" not in meta:
            os.kill(os.getpid(), sig)
        return out
    training.save_checkpoint = save_then_signal
sys.argv = [train_fim_ppo.SCRIPT, *sys.argv[2:]]
train_fim_ppo.cli()
"""


def _run(
    argv: list[str], sig: int = 0, fsize: int | None = None, kill_at: Path | None = None
) -> subprocess.CompletedProcess[str]:
    def limit() -> None:  # in the child: a file-size limit, SIGXFSZ ignored (EFBIG instead)
        if fsize is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    env = {**os.environ, "PYTHONWARNINGS": "ignore", "OPENBLAS_NUM_THREADS": "1"}
    if kill_at is not None:
        env["KILL_AT_REPLACE"] = str(kill_at)
    return _proc.run(
        [sys.executable, "-c", CHILD, str(sig), *argv],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
        preexec_fn=limit,
        timeout=120,
        check=False,
    )


def _one_line(proc: subprocess.CompletedProcess[str]) -> str:
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return lines[0]


def _temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp-" in p.name)


def _meta(path: Path) -> Any:
    return json.loads(path.with_suffix(".json").read_text())


def _snapshot(paths: list[Path]) -> list[bytes]:
    return [p.read_bytes() for p in paths]


# -- kill, then resume ---------------------------------------------------------------------------
def test_sigkill_after_a_periodic_checkpoint_then_resume_reaches_the_same_step_count(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "p.zip"
    last, last_json = last_paths(out)
    killed = _run([*TINY, f"--out={out}"], sig=signal.SIGKILL)
    assert killed.returncode == -signal.SIGKILL
    assert not out.exists() and last.exists() and last_json.exists()
    assert _temporaries(tmp_path) == []
    saved = _meta(last)
    assert saved["complete"] is False and saved["num_timesteps"] == 64
    assert saved["checkpoint_sha256"] == training.file_sha256(last)
    log_before = saved["training_log"]
    assert [e["timesteps"] for e in log_before] == [32, 64]

    # a new run on the same --out without --resume is refused: it would discard the interval
    with pytest.raises(SystemExit) as exc:
        train_fim_ppo.main([*TINY, f"--out={out}"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1
    assert f"continue it with --resume {last}" in err

    resumed = _run([*TINY, f"--out={out}", f"--resume={last}"])
    assert resumed.returncode == 0, resumed.stderr
    meta = _meta(out)
    assert meta["complete"] is True and meta["num_timesteps"] == 256
    assert meta["training"]["timesteps_done"] == 256
    log = meta["training_log"]
    assert log[: len(log_before)] == log_before  # the metrics continue where they stopped
    assert [e["timesteps"] for e in log] == list(range(32, 257, 32))
    assert meta["resume_state"]["n_updates"] == 8  # 8 iterations x 1 epoch, none lost or doubled
    assert not last.exists() and not last_json.exists()  # superseded by the final pair
    assert _temporaries(tmp_path) == []


# -- SIGINT / SIGTERM ----------------------------------------------------------------------------
@pytest.mark.parametrize(("sig", "code", "name"), [(signal.SIGINT, 130, "SIGINT"),
                                                   (signal.SIGTERM, 143, "SIGTERM")])  # fmt: skip
def test_signal_saves_the_last_completed_iteration_and_names_resume(
    sig: int, code: int, name: str, tmp_path: Path
) -> None:
    out = tmp_path / "p.zip"
    last = last_paths(out)[0]
    proc = _run([*TINY, f"--out={out}"], sig=sig)
    assert proc.returncode == code, proc.stderr
    line = _one_line(proc)
    assert line.startswith(f"{PROG}: ") and name in line
    assert str(last) in line and f"--resume {last}" in line
    meta = _meta(last)
    assert meta["complete"] is False and meta["interrupted"] == name
    assert meta["num_timesteps"] == 64 and meta["resume_state"]["num_timesteps"] == 64
    assert meta["checkpoint_sha256"] == training.file_sha256(last)
    assert not out.exists() and _temporaries(tmp_path) == []
    assert last.stat().st_size > 1000  # never a 0-byte or truncated zip


def test_file_size_limit_while_saving_keeps_the_previous_pair(tmp_path: Path) -> None:
    """EFBIG on a periodic checkpoint: exit 1, one line, the previous pair byte-identical."""
    out = tmp_path / "p.zip"
    pair = last_paths(out)
    assert _run([*TINY, f"--out={out}"], sig=signal.SIGTERM).returncode == 143
    before = _snapshot(pair)
    # the resumed run's first periodic checkpoint (128 steps) is larger than the limit
    proc = _run([*TINY, f"--out={out}", f"--resume={pair[0]}"], fsize=8192)
    assert proc.returncode == 1, proc.stderr
    line = _one_line(proc)
    assert line.startswith(f"{PROG}: cannot write {pair[0]}") and "EFBIG" in line, line
    assert _snapshot(pair) == before
    assert _temporaries(tmp_path) == [] and not out.exists()


def test_full_disk_at_the_final_save_keeps_the_previous_checkpoint(tiny_fs: Path) -> None:
    """ENOSPC on the final pair (``--force`` over a previous run): exit 1, old pair intact."""
    out = tiny_fs / "p.zip"
    old = [b"PK old checkpoint", b'{"old": true}\n']
    out.write_bytes(old[0])
    out.with_suffix(".json").write_bytes(old[1])
    proc = _run([*TINY, "--checkpoint-every=0", f"--out={out}", "--force"])
    assert proc.returncode == 1, proc.stderr
    line = _one_line(proc)
    assert f"cannot write {out}" in line and "ENOSPC" in line, line
    assert _snapshot([out, out.with_suffix(".json")]) == old
    assert _temporaries(tiny_fs) == []


# -- in-process: the pair writer, the up-front checks --------------------------------------------
@pytest.fixture(scope="module")
def tiny_model() -> Any:
    import gymnasium as gym

    import selenv  # noqa: F401  (registers the envs)
    from selenv.learned.rl.candidate_policy import make_ppo

    env = gym.make("selenv/FIMSelection-v1", n_candidates=4, budget=2)
    return make_ppo(env, "maskable_ppo", seed=0, n_steps=8, batch_size=8,
                    policy_kwargs={"features_extractor_kwargs": {"hidden": [4]}})  # fmt: skip


def test_save_checkpoint_on_a_full_disk_leaves_the_previous_pair(
    tiny_fs: Path, tiny_model: Any
) -> None:
    target = tiny_fs / "c.zip"
    save_checkpoint(tiny_model, {"n": 1}, target)
    before = _snapshot([target, target.with_suffix(".json")])
    filler = tiny_fs / "filler"
    free = os.statvfs(tiny_fs).f_bavail * os.statvfs(tiny_fs).f_frsize
    filler.write_bytes(b"\0" * max(free - len(before[0]) // 2, 0))  # room for half a zip
    with pytest.raises(OSError) as exc:
        save_checkpoint(tiny_model, {"n": 2}, target)
    assert exc.value.filename == str(target) and "ENOSPC" in describe_os_error(exc.value)
    assert _snapshot([target, target.with_suffix(".json")]) == before
    assert _temporaries(tiny_fs) == []


def test_sigkill_during_the_final_save_with_force_keeps_a_loadable_or_refused_pair(
    tmp_path: Path, tiny_model: Any
) -> None:
    """``--force`` onto a good pair, SIGKILL at the rename of the new JSON, then of the zip.

    Killed between the two renames, the new zip sits beside the old JSON and the pair check
    refuses it; the next ``--force`` run replaces both and leaves nothing behind; killed before
    the zip's rename, the old pair is byte-identical and loads (the reported bug left a 0-byte
    ``policy.zip``).
    """
    out = tmp_path / "p.zip"
    pair = [out, out.with_suffix(".json")]
    save_checkpoint(tiny_model, {"a previous": "run"}, out)
    before = _snapshot(pair)
    quick = [*TINY, "--checkpoint-every=0", "--total-timesteps=32", f"--out={out}", "--force"]

    assert _run(quick, kill_at=pair[1]).returncode == -signal.SIGKILL
    assert pair[1].read_bytes() == before[1] and pair[0].read_bytes() != before[0]
    with pytest.raises(ValueError, match="do not match"):
        training.verify_pair(out, training.read_checkpoint_metadata(out))

    assert _run(quick).returncode == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.json", "p.zip"]
    training.verify_pair(out, training.read_checkpoint_metadata(out))
    before = _snapshot(pair)

    assert _run(quick, kill_at=pair[0]).returncode == -signal.SIGKILL
    assert _snapshot(pair) == before
    training.verify_pair(out, training.read_checkpoint_metadata(out))


def test_a_mismatched_pair_is_refused(
    tmp_path: Path, tiny_model: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    a, b = tmp_path / "a.zip", tmp_path / "b.zip"
    save_checkpoint(tiny_model, {"resume_state": {"num_timesteps": 0}}, a)
    tiny_model.policy.features_extractor.gain_skip.data += 1.0  # another save: another zip
    save_checkpoint(tiny_model, {}, b)
    b.replace(a)  # a's JSON beside b's zip
    with pytest.raises(ValueError, match="do not match"):
        training.verify_pair(a, training.read_checkpoint_metadata(a))
    code = run_cli(train_fim_ppo.main, PROG, [*TINY, f"--out={tmp_path / 'o.zip'}",
                                               f"--resume={a}"])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "do not match" in err and str(a) in err


def test_full_output_folder_is_found_before_any_work(
    tiny_fs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tiny_fs / "filler").write_bytes(b"\0" * (os.statvfs(tiny_fs).f_bavail * 4096))
    with pytest.raises(SystemExit) as exc:
        train_fim_ppo.main([*TINY, f"--out={tiny_fs / 'sub' / 'p.zip'}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ENOSPC" in err and str(tiny_fs) in err, err


def test_second_run_on_the_same_out_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "p.zip"
    lock = tmp_path / ".p.zip.lock"
    lock.write_text("1\n")  # PID 1 is alive: another run holds --out
    with pytest.raises(SystemExit) as exc:
        train_fim_ppo.main([*TINY, f"--out={out}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "being written by another run" in err
    assert lock.read_text() == "1\n" and not out.exists()


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--n-envs=5000"], "--n-envs 5000 is above its ceiling 1024: pass --allow-large"),
        (["--hidden=20000,20000"], "--hidden (width) 20000 is above its ceiling 4096"),
        (["--total-timesteps=2000000000"], "--total-timesteps 2000000000 is above"),
        (["--eval-episodes=1000000"], "--eval-episodes 1000000 is above"),
        (["--n-steps=0"], "--n-steps must be >= 1"),
        (["--batch-size=10000000"], "--batch-size 10000000 is above"),
        (["--checkpoint-every=-1"], "--checkpoint-every must be >= 0"),
        (["--curve-every=-1"], "--curve-every must be >= 0"),
        (["--curve-episodes=0"], "--curve-episodes must be >= 1"),
        (["--curve-episodes=10001"], "--curve-episodes 10001 is above its ceiling"),
        (["--curve-every=2000000000"], "--curve-every 2000000000 is above its ceiling"),
        (["--critic-warmup=-1"], "--critic-warmup must be >= 0"),
        (["--target-kl=-0.1"], "--target-kl must be a finite number >= 0"),
        (["--target-kl=nan"], "--target-kl must be a finite number >= 0"),
        (["--init-from=nowhere/policy.zip"], "--init-from nowhere/policy.zip: no such"),
    ],
)
def test_sizes_beyond_their_ceilings_exit_2_naming_the_option(
    argv: list[str], needle: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        train_fim_ppo.main([*TINY, *argv, f"--out={tmp_path / 'p.zip'}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert list(tmp_path.iterdir()) == []


def test_memory_estimate_is_checked_before_the_model_is_built(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [*TINY, "--n-steps=65536", "--max-memory-gb=0.25", f"--out={tmp_path / 'p.zip'}"]
    assert run_cli(train_fim_ppo.main, PROG, argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--max-memory-gb 0.25" in err and "GB" in err, err
    # --allow-large lifts the ceilings, not the estimate
    argv = [*argv, "--allow-large", "--n-envs=4096"]
    assert run_cli(train_fim_ppo.main, PROG, argv) == 2
    assert "--max-memory-gb" in capsys.readouterr().err
