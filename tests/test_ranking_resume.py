"""Stopping and resuming the ranking trainers: expert iteration and the clustering DAgger round.

A SIGINT / SIGTERM keeps the last completed step as ``<out stem>.last.zip`` (``"complete":
false``, ``"interrupted"``) and exits 130 / 143 with one line naming the ``--resume`` option; a
``kill -9`` loses at most the step in progress; ``--resume`` continues to the same final weights
as an uninterrupted run with the same options (everything is seeded: compared bit for bit).
The interruptions are triggered deterministically: a hook signals the run at a chosen epoch, or
the test waits for a file the run writes before it signals it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from selenv.learned.families.landmarks import LANDMARK_ID
from selenv.learned.rl import distill
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.ranking import RankingData, load_labels, save_labels
from selenv.learned.rl.safe_load import read_weights
from selenv.learned.rl.training import run_cli
from selenv.train import train_clustering_dagger, train_landmark_expert

ROOT = Path(__file__).resolve().parents[1]
PROG = "prog"
#: a tiny expert-iteration run: 2 rounds of 6 labelled picks, 3 fit epochs, a .last every epoch
LM_ARGS = ["--rounds", "2", "--states-per-round", "6", "--horizon", "1", "--workers", "1",
           "--epochs", "3", "--eval-episodes", "0", "--no-progress",
           "--checkpoint-every", "1"]  # fmt: skip
#: a tiny DAgger round on a 9-receiver clustering: 8 labelled states, 3 fit epochs
DAG_ARGS = ['--env-kwargs={"n_agents": 9, "horizon": 10}', "--states=8", "--epochs=3",
            "--workers=1", "--no-progress", "--eval-episodes=0", "--label-every=2"]  # fmt: skip


def _last(out: Path) -> Path:
    return out.with_name(f"{out.stem}.last.zip")


def _assert_same_weights(a: Path, b: Path) -> None:
    wa, wb = read_weights(a), read_weights(b)
    assert set(wa) == set(wb)
    for key in wa:
        assert torch.equal(wa[key], wb[key]), key


def _run(main: Callable[..., Any], argv: list[str]) -> int:
    """The exit code of a script's command line (usage errors found up front exit directly)."""
    try:
        return run_cli(main, PROG, argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def _stop_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    return err[0]


@pytest.fixture(scope="module")
def lm_reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The uninterrupted expert-iteration run every resumed one must reproduce."""
    out = tmp_path_factory.mktemp("lm_ref") / "p.zip"
    meta = train_landmark_expert.main(["--out", str(out), *LM_ARGS])
    assert meta["complete"] is True and len(meta["expert_iteration"]["rounds_log"]) == 2
    assert not _last(out).exists()  # the resume state is removed once the run completes
    return out


def _signal_in_fit(monkeypatch: pytest.MonkeyPatch, module: Any, fit_seed: int, sig: int) -> None:
    """Make ``module``'s ranking fit with ``seed=fit_seed`` receive ``sig`` as epoch 2 starts."""
    real = module.fit_ranking

    def fit(policy: Any, data: Any, **kw: Any) -> Any:
        after: Callable[[Any], bool] = kw["after_epoch"]

        def hook(state: Any) -> bool:
            stop = after(state)
            if kw["seed"] == fit_seed and state.epochs_done == 1:
                os.kill(os.getpid(), sig)  # arrives mid-run: the epoch in progress completes
            return stop

        return real(policy, data, **{**kw, "after_epoch": hook})

    monkeypatch.setattr(module, "fit_ranking", fit)


def test_sigint_in_a_fit_keeps_the_epoch_and_resumes_bit_identically(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any, lm_reference: Path
) -> None:
    out = tmp_path / "p.zip"
    last = _last(out)
    _signal_in_fit(monkeypatch, distill, fit_seed=1, sig=signal.SIGINT)  # round 1
    code = _run(train_landmark_expert.main, ["--out", str(out), *LM_ARGS])
    assert code == 130
    line = _stop_line(capsys)
    assert line == (
        f"{PROG}: interrupted (SIGINT): saved the last completed step (round 1's labels "
        f"collected, 2 of 3 fit epochs) as {last} (+ .json); continue with the same command "
        f"and --resume {last}"
    )
    meta = json.loads(last.with_suffix(".json").read_text())
    assert meta["complete"] is False and meta["interrupted"] == "SIGINT"
    state = meta["resume_state"]
    assert state["rounds_done"] == 1 and len(state["labels"]) == 2
    assert state["fit"]["epochs_done"] == 2 and last.with_suffix(".fit.pt").is_file()
    assert not out.exists() and (tmp_path / "p_round0.zip").is_file()
    # a fresh run next to the unfinished one is refused (exit 2, one line naming --resume)
    assert _run(train_landmark_expert.main, ["--out", str(out), *LM_ARGS]) == 2
    assert f"continue it with --resume {last}" in _stop_line(capsys)
    monkeypatch.undo()
    meta = train_landmark_expert.main(["--out", str(out), *LM_ARGS, "--resume", str(last)])
    assert [r["round"] for r in meta["expert_iteration"]["rounds_log"]] == [0, 1]
    assert meta["complete"] is True and "resume_state" not in meta
    _assert_same_weights(out, lm_reference)
    _assert_same_weights(tmp_path / "p_round1.zip", lm_reference.with_name("p_round1.zip"))
    assert not last.exists() and not last.with_suffix(".fit.pt").exists()


def test_resume_from_a_round_checkpoint_and_what_is_refused(
    tmp_path: Path, capsys: Any, lm_reference: Path
) -> None:
    for name in ("p_round0.zip", "p_round0.json", "p_round0.labels.npz"):  # a moved run
        shutil.copy(lm_reference.with_name(name), tmp_path / name.replace("p_", "q_"))
    out, round0 = tmp_path / "q.zip", tmp_path / "q_round0.zip"
    base = ["--out", str(out), *LM_ARGS, "--resume", str(round0)]
    refused = {
        "--seed 1": "it was trained with --seed 0, this run has 1",
        "--rounds 3": "it was trained with --rounds 2, this run has 3",
        "--epochs 4": "it was trained with --epochs 3, this run has 4",
        f"--resume {DEFAULT_CHECKPOINTS[LANDMARK_ID]}": "no resume state in its metadata",
        f"--resume {tmp_path / 'none.zip'}": "no such checkpoint",
    }
    for extra, message in refused.items():
        assert _run(train_landmark_expert.main, [*base, *extra.split()]) == 2, extra
        line = _stop_line(capsys)
        assert ": error: --resume " in line and message in line, line
    labels = tmp_path / "q_round0.labels.npz"
    good = labels.read_bytes()
    labels.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))  # one bit flipped
    assert _run(train_landmark_expert.main, base) == 2
    assert "is not the one its checkpoint records" in _stop_line(capsys)
    labels.write_bytes(good)
    meta = train_landmark_expert.main(base)
    assert len(meta["expert_iteration"]["rounds_log"]) == 2
    _assert_same_weights(out, lm_reference)


def _fork_run(argv: list[str], patch: Callable[[], None], err: Path) -> int:
    """Run the expert script's command line in a forked child (everything already imported).

    The child applies ``patch``, writes its stderr to ``err`` and leaves with the run's exit
    code, never returning into pytest. Returns the child's PID.
    """
    pid = os.fork()
    if pid:
        return pid
    code = 1
    try:  # pragma: no cover - runs in the child
        sys.stdout = open(os.devnull, "w")
        sys.stderr = open(err, "w", buffering=1)
        patch()
        code = run_cli(train_landmark_expert.main, PROG, argv)
    except BaseException:  # pragma: no cover - shown by the test through `err`
        import traceback

        traceback.print_exc()
    finally:
        sys.stderr.flush()
        os._exit(code)


def _block_in_round1_fit(ready: Path) -> None:
    """Patch: after round 1's first fit epoch (its .last written), wait to be killed."""
    real = distill.fit_ranking

    def fit(policy: Any, data: Any, **kw: Any) -> Any:
        after = kw["after_epoch"]

        def hook(state: Any) -> bool:
            stop = after(state)
            if kw["seed"] == 1 and state.epochs_done == 1:
                ready.touch()
                while True:
                    time.sleep(0.05)
            return bool(stop)

        return real(policy, data, **{**kw, "after_epoch": hook})

    distill.fit_ranking = fit


def _long_round1_collection(ready: Path) -> None:
    """Patch: round 1 labels with 2 workers, far more than they could finish."""
    real = train_landmark_expert.collect_landmark_rollout_labels

    def collect(kwargs: Any, n_states: int, seed: int, **kw: Any) -> Any:
        if seed == 1:
            ready.touch()
            return real(kwargs, 10**6, seed, **{**kw, "workers": 2})
        return real(kwargs, n_states, seed, **kw)

    train_landmark_expert.collect_landmark_rollout_labels = collect


def _wait_for(what: Callable[[], bool], pid: int, err: Path, timeout: float = 120) -> None:
    """Wait until ``what()`` holds; fail (with the child's stderr) if the child ends first."""
    deadline = time.monotonic() + timeout
    while not what():
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done:
            pytest.fail(f"the run ended early: {err.read_text()}")
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            pytest.fail("the run never reached the point to interrupt")
        time.sleep(0.02)


def _exit_code(pid: int) -> int:
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def _pool_workers(pid: int) -> list[int]:
    """The process-pool workers among ``pid``'s children (Linux ``/proc``)."""
    kids = Path(f"/proc/{pid}/task/{pid}/children")
    out = []
    for child in kids.read_text().split() if kids.exists() else []:
        try:
            cmdline = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmdline:
            out.append(int(child))
    return out


def _gone(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True
    return "\nState:\tZ" in status  # a zombie: dead, waiting to be reaped


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and /proc")
def test_killed_and_terminated_runs_resume_to_the_uninterrupted_weights(
    tmp_path: Path, lm_reference: Path
) -> None:
    """SIGKILL mid-fit and SIGTERM mid-collection (2 workers), in child processes, then resume."""
    runs = {}
    for mode, patch in (("fit", _block_in_round1_fit), ("collect", _long_round1_collection)):
        out, ready, err = (
            tmp_path / mode / "p.zip",
            tmp_path / f"{mode}.ready",
            tmp_path / f"{mode}.err",
        )
        pid = _fork_run(["--out", str(out), *LM_ARGS], lambda p=patch, r=ready: p(r), err)
        runs[mode] = (pid, out, ready, err)
    # kill -9 once round 1's first fit epoch is saved: at most the epoch in progress is lost
    pid, out, ready, err = runs["fit"]
    _wait_for(ready.exists, pid, err)
    os.kill(pid, signal.SIGKILL)
    assert _exit_code(pid) == -signal.SIGKILL
    killed = json.loads(_last(out).with_suffix(".json").read_text())
    assert killed["resume_state"]["fit"]["epochs_done"] == 1 and "interrupted" not in killed
    # SIGTERM while the workers label round 1: they are stopped, round 0's state is kept
    pid, out_t, ready, err = runs["collect"]
    _wait_for(lambda: ready.exists() and len(_pool_workers(pid)) == 2, pid, err)
    workers = _pool_workers(pid)
    os.kill(pid, signal.SIGTERM)
    assert _exit_code(pid) == 143, err.read_text()
    last = _last(out_t)
    assert err.read_text().strip().splitlines() == [
        f"{PROG}: terminated (SIGTERM): saved the last completed step (1 of 2 rounds done) as "
        f"{last} (+ .json); continue with the same command and --resume {last}"
    ]
    deadline = time.monotonic() + 30
    while not all(_gone(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert all(_gone(w) for w in workers), "a labelling worker outlived the stopped run"
    terminated = json.loads(last.with_suffix(".json").read_text())
    assert terminated["interrupted"] == "SIGTERM" and terminated["complete"] is False
    assert terminated["resume_state"]["rounds_done"] == 1
    # both resume to the uninterrupted run's weights
    for path in (out, out_t):
        train_landmark_expert.main(["--out", str(path), *LM_ARGS, "--resume", str(_last(path))])
        _assert_same_weights(path, lm_reference)


def test_dagger_stops_after_an_epoch_and_resumes_bit_identically(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any
) -> None:
    ref = tmp_path / "ref.zip"
    reference = train_clustering_dagger.main([f"--out={ref}", *DAG_ARGS])
    assert reference["complete"] is True and not _last(ref).exists()
    out = tmp_path / "d.zip"
    last = _last(out)
    _signal_in_fit(monkeypatch, distill, fit_seed=1, sig=signal.SIGTERM)
    assert _run(train_clustering_dagger.main, [f"--out={out}", *DAG_ARGS]) == 143
    assert _stop_line(capsys) == (
        f"{PROG}: terminated (SIGTERM): saved the labels and the fit after 2 of 3 epochs as "
        f"{last} (+ .json); continue with the same command and --resume {last}"
    )
    meta = json.loads(last.with_suffix(".json").read_text())
    assert meta["interrupted"] == "SIGTERM" and meta["resume_state"]["fit"]["epochs_done"] == 2
    monkeypatch.undo()
    resume = [f"--out={out}", *DAG_ARGS, f"--resume={last}"]
    assert _run(train_clustering_dagger.main, [*resume, "--seed=2"]) == 2
    assert "it was trained with --seed 1, this run has 2" in _stop_line(capsys)
    meta = train_clustering_dagger.main(resume)
    assert meta["dagger"]["epochs_done"] == 3 and meta["dagger"]["states_train"] == 7
    _assert_same_weights(out, ref)
    assert not any(p.name.startswith("d.last") for p in tmp_path.iterdir())


def test_dagger_stopped_while_collecting_keeps_nothing_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any
) -> None:
    def collect(*args: Any, **kwargs: Any) -> Any:
        os.kill(os.getpid(), signal.SIGINT)
        raise AssertionError("SIGINT did not interrupt the collection")

    monkeypatch.setattr(train_clustering_dagger, "collect_clustering_ranking", collect)
    out = tmp_path / "d.zip"
    assert _run(train_clustering_dagger.main, [f"--out={out}", *DAG_ARGS]) == 130
    assert _stop_line(capsys) == (
        f"{PROG}: interrupted (SIGINT): while collecting the labels: nothing complete to keep; "
        "run it again"
    )
    assert list(tmp_path.iterdir()) == []


def test_labels_file_is_checked_before_it_is_inflated(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    data = RankingData(
        {"x": rng.normal(size=(4, 3, 2)).astype(np.float32)}, rng.normal(size=(4, 3))
    )
    path = tmp_path / "l.npz"
    sha = save_labels(data, path)
    back = load_labels(path, sha256=sha, rows=4, row_shapes={"x": (3, 2)}, n_actions=3)
    assert np.array_equal(back.obs["x"], data.obs["x"]) and np.array_equal(back.deltas, data.deltas)
    with pytest.raises(ValueError, match=r"'deltas' declares shape \(4, 3\).*expected \(5, 3\)"):
        load_labels(path, sha256=sha, rows=5, row_shapes={"x": (3, 2)}, n_actions=3)
    with pytest.raises(
        ValueError, match=r"'obs_x' declares shape \(4, 3, 2\).*expected \(4, 2, 3\)"
    ):
        load_labels(path, sha256=sha, rows=4, row_shapes={"x": (2, 3)}, n_actions=3)
    with pytest.raises(ValueError, match="holds arrays"):
        load_labels(path, sha256=sha, rows=4, row_shapes={"y": (3, 2)}, n_actions=3)
    evil = tmp_path / "evil.npz"  # an object array (would need pickle): refused from its header
    np.savez(evil, header=np.array("{}"), deltas=np.zeros((4, 3)),
             obs_x=np.array([object()] * 24, dtype=object).reshape(4, 3, 2))  # fmt: skip
    from selenv.learned.rl.training import file_sha256

    with pytest.raises(ValueError, match="'obs_x' declares shape"):
        load_labels(evil, sha256=file_sha256(evil), rows=4, row_shapes={"x": (3, 2)}, n_actions=3)
