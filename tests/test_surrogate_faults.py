"""Surrogate training never loses a result: fault injection on the CLI and the save/load code.

Each case compares the outputs against what was there before: a full file system (a 64 KiB
tmpfs, where root may mount one) and a file-size limit (``RLIMIT_FSIZE``, EFBIG) during the
save, SIGKILL between the temporary write and the rename (and between the two renames of the
pair), SIGINT / SIGTERM during training (at a chosen epoch through the script's test hook, and
from outside), a resume that must end with the weights of an uninterrupted run, a ``kill -9``
of the main process while pool workers generate data, usage errors and the ceilings of bounded
work, and a dataset file whose arrays declare gigabytes.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from contextlib import AbstractContextManager
from pathlib import Path

import _proc
import numpy as np
import pytest
import torch
from _work import no_work, torch_work
from numpy.lib import format as npy_format

from selenv.learned.surrogate_data import (
    DatasetTooLargeError,
    generate_dataset,
    load_dataset,
    save_dataset,
)
from selenv.learned.surrogates import Surrogate
from selenv.train import train_surrogate

ROOT = Path(__file__).resolve().parents[1]
PROG = "python -m selenv.train.train_surrogate"
#: a tiny, fast run: 300 rows, one hidden layer of 8, no TensorBoard, no bars
TINY = ["--hidden", "8", "--patience", "1000", "--tensorboard-dir", "", "--no-progress"]


@pytest.fixture(scope="module")
def data_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    ds = generate_dataset(300, seed=3, workers=1, progress=False)
    return save_dataset(ds, tmp_path_factory.mktemp("data") / "d.npz")


@pytest.fixture(scope="module")
def good_pair(data_file: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete run of 6 epochs (the reference for the resume test)."""
    out = tmp_path_factory.mktemp("good") / "ref.pt"
    train_surrogate.main(["--data", str(data_file), "--epochs", "6", "--out", str(out), *TINY])
    return out


def _child(code: str, cwd: Path, **kwargs: object) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return _proc.popen(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        **kwargs,  # type: ignore[call-overload]
    )


def _cli_code(argv: list[str], before: str = "") -> str:
    """A child running the command line ``argv`` after ``before`` (a hook, a patch)."""
    return (
        "import os, signal, sys\n"
        "from selenv.train import train_surrogate as t\n"
        f"{textwrap.dedent(before)}\n"
        f"t.cli({argv!r})\n"
    )


def _one_line(err: bytes) -> str:
    lines = err.decode().strip().splitlines()
    assert len(lines) == 1, lines
    assert "Traceback" not in lines[0]
    return lines[0]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def _copy_pair(src: Path, dst_folder: Path, name: str = "s") -> Path:
    dst = dst_folder / f"{name}.pt"
    dst.write_bytes(src.read_bytes())
    dst.with_suffix(".json").write_bytes(src.with_suffix(".json").read_bytes())
    return dst


def _weights(pt: Path) -> dict[str, torch.Tensor]:
    return Surrogate.load(pt).net.state_dict()


# -- the pair: hash recorded, mismatch refused ----------------------------------------------------
def test_pair_records_the_weights_hash_and_a_mixed_pair_is_refused(
    good_pair: Path, tmp_path: Path
) -> None:
    import hashlib

    meta = json.loads(good_pair.with_suffix(".json").read_text())
    assert meta["weights_sha256"] == hashlib.sha256(good_pair.read_bytes()).hexdigest()
    assert meta["complete"] is True and "interrupted" not in meta
    other = Surrogate.load(good_pair)
    with torch.no_grad():
        next(iter(other.net.parameters())).add_(1.0)
    mixed = other.save(tmp_path / "x.pt")
    mixed.with_suffix(".json").write_bytes(good_pair.with_suffix(".json").read_bytes())
    with pytest.raises(ValueError, match=r"x\.pt and metadata .*x\.json are not a pair"):
        Surrogate.load(mixed)


# -- SIGKILL during the save ----------------------------------------------------------------------
@pytest.mark.parametrize("at_replace", [1, 2])
def test_sigkill_during_the_save_keeps_a_loadable_or_refused_pair(
    at_replace: int, good_pair: Path, data_file: Path, tmp_path: Path
) -> None:
    """``--force`` onto a good pair, killed at the first / second ``os.replace`` of the save.

    At the first rename the old pair is byte-identical (the reported bug left a 0-byte
    ``.pt``); between the two renames the new ``.pt`` sits beside the old ``.json`` and the
    loader refuses the mixed pair, naming both files.
    """
    out = _copy_pair(good_pair, tmp_path)
    before = _snapshot(tmp_path)
    patch = f"""
        import selenv.atomic as a
        calls = []
        real = a.os.replace
        def replace(src, dst):
            calls.append(dst)
            if len(calls) == {at_replace}:
                os.kill(os.getpid(), signal.SIGKILL)
            real(src, dst)
        a.os.replace = replace
    """
    argv = ["--data", str(data_file), "--epochs", "2", "--out", str(out), "--force", *TINY]
    child = _child(_cli_code(argv, patch), tmp_path)
    _proc.communicate(child, 120)
    assert child.returncode == -signal.SIGKILL
    visible = {k: v for k, v in _snapshot(tmp_path).items() if not k.startswith(".")}
    if at_replace == 1:
        assert visible == before
        Surrogate.load(out)
    else:
        assert visible["s.json"] == before["s.json"] and visible["s.pt"] != before["s.pt"]
        with pytest.raises(ValueError, match=r"s\.pt and metadata .*s\.json are not a pair"):
            Surrogate.load(out)
    # the next save of the same output removes what the killed one left behind
    train_surrogate.main(["--data", str(data_file), "--epochs", "1", "--out", str(out), "--force",
                          *TINY])  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.json", "s.pt"]
    Surrogate.load(out)


# -- full disk / file-size limit during the save --------------------------------------------------
def test_full_disk_keeps_the_previous_pair(good_pair: Path, data_file: Path, tiny_fs: Path) -> None:
    """ENOSPC while writing a bigger model: one line, exit 1, the old pair byte-identical."""
    out = _copy_pair(good_pair, tiny_fs)
    before = _snapshot(tiny_fs)
    argv = [
        "--data",
        str(data_file),
        "--epochs",
        "1",
        "--out",
        str(out),
        "--force",
        *TINY,
        "--hidden",
        "128,128",
    ]  # fmt: skip  (~80 KB of weights: more than the disk)
    child = _child(_cli_code(argv), tiny_fs.parent)
    _, err = _proc.communicate(child, 120)
    line = _one_line(err)
    assert child.returncode == 1, line
    assert line.startswith(f"{PROG}: cannot write {out}") and "(ENOSPC)" in line
    assert "inline_container" not in line
    assert _snapshot(tiny_fs) == before
    assert sorted(p.name for p in tiny_fs.iterdir()) == ["s.json", "s.pt"]


def test_file_size_limit_keeps_the_previous_pair(
    good_pair: Path, data_file: Path, tmp_path: Path
) -> None:
    """EFBIG (``ulimit -f``): one line, exit 1, the old pair byte-identical, no temporaries."""
    out = _copy_pair(good_pair, tmp_path)
    before = _snapshot(tmp_path)
    limit = """
        import resource
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, 40_000))
    """
    argv = ["--data", str(data_file), "--epochs", "1", "--out", str(out), "--force", *TINY,
            "--hidden", "128,128"]  # fmt: skip
    child = _child(_cli_code(argv, limit), tmp_path)
    _, err = _proc.communicate(child, 120)
    line = _one_line(err)
    assert child.returncode == 1, line
    assert f"cannot write {out}" in line and "(EFBIG)" in line
    assert _snapshot(tmp_path) == before


def test_dataset_write_failure_keeps_the_previous_file(tmp_path: Path, data_file: Path) -> None:
    """``--save-data`` onto a file-size limit: exit 1, one line naming the .npz, old file kept."""
    old = tmp_path / "g.npz"
    old.write_bytes(b"previous dataset")
    limit = """
        import resource
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))
    """
    argv = ["--samples", "300", "--workers", "1", "--epochs", "1", "--save-data", str(old),
            "--out", str(tmp_path / "g.pt"), "--force", *TINY]  # fmt: skip
    child = _child(_cli_code(argv, limit), tmp_path)
    _, err = _proc.communicate(child, 120)
    line = _one_line(err)
    assert child.returncode == 1 and f"cannot write {old}" in line and "(EFBIG)" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.npz"]
    assert old.read_bytes() == b"previous dataset"


# -- SIGINT / SIGTERM during training, and resuming ----------------------------------------------
@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_keeps_best_weights_and_resume_equals_an_uninterrupted_run(
    sig: signal.Signals, code: int, good_pair: Path, data_file: Path, tmp_path: Path
) -> None:
    """A signal at epoch 2 of 6: exit 130/143, one line, the best weights so far saved as an
    incomplete pair with the resume state; ``--resume`` ends with the reference's weights."""
    out = tmp_path / "b.pt"
    hook = f"t._after_epoch = lambda done: os.kill(os.getpid(), {int(sig)}) if done == 2 else None"
    argv = ["--data", str(data_file), "--epochs", "6", "--out", str(out), *TINY]
    child = _child(_cli_code(argv, hook), tmp_path)
    out_text, err = _proc.communicate(child, 120)
    line = _one_line(err)
    assert child.returncode == code, line
    word = "interrupted (SIGINT)" if sig == signal.SIGINT else "terminated (SIGTERM)"
    assert line.startswith(f"{PROG}: {word} after 2 of 6 epochs") and "--resume" in line
    assert out_text == b""
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["complete"] is False and meta["interrupted"] == sig.name
    assert meta["training"]["epochs_run"] == 2 and meta["metrics"]["test"] is None
    state = tmp_path / "b.resume.pt"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.json", "b.pt", "b.resume.pt"]
    Surrogate.load(out)  # a loadable pair
    if sig == signal.SIGTERM:
        return  # one resume is enough (the state is the same)
    meta = train_surrogate.main([*argv, "--resume", str(state)])
    ref = json.loads(good_pair.with_suffix(".json").read_text())
    assert meta["complete"] is True and meta["training"]["epochs_run"] == 6
    assert meta["training"]["best_val_loss"] == ref["training"]["best_val_loss"]
    assert meta["training"]["best_epoch"] == ref["training"]["best_epoch"]
    assert meta["metrics"]["test"] == ref["metrics"]["test"]
    got, want = _weights(out), _weights(good_pair)
    assert all(torch.equal(got[k], want[k]) for k in want)
    assert not state.exists()  # complete: the resume state is obsolete


def test_external_sigterm_with_periodic_checkpoints(data_file: Path, tmp_path: Path) -> None:
    """SIGTERM from outside once the first periodic checkpoint exists: exit 143, kept pair."""
    out = tmp_path / "e.pt"
    argv = ["--data", str(data_file), "--epochs", "10000", "--checkpoint-every", "1",
            "--out", str(out), *TINY]  # fmt: skip
    child = _child(_cli_code(argv), tmp_path)
    state = tmp_path / "e.resume.pt"
    deadline = time.monotonic() + 60
    while not state.exists() and time.monotonic() < deadline and child.poll() is None:
        time.sleep(0.05)
    if not state.exists():
        child.kill()
        pytest.fail(f"no resume state: {_proc.communicate(child, 30)[1].decode()}")
    done = torch.load(state, weights_only=True)["epochs_done"]
    child.send_signal(signal.SIGTERM)
    _, err = _proc.communicate(child, 60)
    line = _one_line(err)
    assert child.returncode == 143, line
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["complete"] is False and meta["interrupted"] == "SIGTERM"
    assert meta["training"]["epochs_run"] >= done >= 1
    assert torch.load(state, weights_only=True)["epochs_done"] == meta["training"]["epochs_run"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.json", "e.pt", "e.resume.pt"]


def test_resume_of_another_run_is_refused(
    good_pair: Path, data_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r.pt"
    hook = "t._after_epoch = lambda done: os.kill(os.getpid(), signal.SIGINT)"
    argv = ["--data", str(data_file), "--epochs", "3", "--out", str(out), *TINY]
    child = _child(_cli_code(argv, hook), tmp_path)
    _proc.communicate(child, 120)
    assert child.returncode == 130
    state = tmp_path / "r.resume.pt"
    before = _snapshot(tmp_path)
    for extra, needle in (
        (["--hidden", "9"], "--hidden"),
        (["--lr", "0.5"], "--lr"),
        (["--resume", str(tmp_path / "r.json")], "not a readable resume state"),
    ):
        with pytest.raises(SystemExit) as info:
            train_surrogate.cli([*argv, "--resume", str(state), *extra])
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and needle in err, err
    assert _snapshot(tmp_path) == before


# -- usage errors and ceilings ------------------------------------------------------------------
# Each refusal comes before the work it guards against, observed through the calls that would
# do it (tests/_work.py); how long a refusal takes is measured by benchmarks/bench_refusals.py.
#: generating data and starting a training run
_TRAINING_WORK: list[tuple[object, str]] = [
    (train_surrogate, "generate_dataset"),
    (train_surrogate, "SummaryWriter"),
]


def _inflating_nothing() -> AbstractContextManager[None]:
    """No ``.npy`` member of a dataset is read (its header alone decides)."""
    return no_work([(np, "load"), (npy_format, "read_array")])


def _bomb(path: Path, name: str = "P_i", shape: tuple[int, ...] = (3_400_000, 9, 9)) -> Path:
    """A small .npz whose ``name`` member declares ``shape`` float64 (>= 2 GiB) in its header."""
    from numpy.lib import format as npy_format

    ds = generate_dataset(20, seed=0, workers=1, progress=False)
    save_dataset(ds, path)
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    import io

    buf = io.BytesIO()
    npy_format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": shape})
    members[f"{name}.npy"] = buf.getvalue() + b"\0" * 1_000_000  # the data is never read
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for n, blob in members.items():
            zf.writestr(n, blob)
    return path


def test_dataset_bomb_is_refused_from_its_headers(tmp_path: Path) -> None:
    for name, shape, needle in (
        ("P_i", (3_400_000, 9, 9), "over the limit of 200,000 rows"),
        ("C", (20, 8192, 8192), "over the limit of 4096 bytes per row"),
        ("R", (16384, 16384), "over the limit of 1 MiB"),
    ):
        bomb = _bomb(tmp_path / f"{name}.npz", name, shape)
        assert bomb.stat().st_size < 3_000_000
        with _inflating_nothing(), pytest.raises(DatasetTooLargeError, match=needle) as info:
            load_dataset(bomb)
        assert f"array {name!r}" in str(info.value)


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--samples", str(10**9)], "--samples 1,000,000,000 is over the ceiling of 200,000 rows"),
        (["--epochs", str(10**7)], "raise it with --max-epochs 10000000"),
        (["--hidden", "100000"], "raise it with --max-width 100000"),
        (["--hidden", "4096,4096,4096,4096"], "parameters, over the limit"),
        (["--batch-size", str(10**8)], "raise it with --max-batch-size"),
        (["--workers", "100000"], "--workers 100000 is over the limit of 256"),
        (["--kind", "nope"], "--kind must be one of"),
        (["--hidden", "8,x"], "--hidden must be comma-separated integers"),
        (["--data", "missing.npz"], "--data: cannot read surrogate dataset missing.npz"),
        (["--resume", "missing.resume.pt"], "--resume missing.resume.pt: no such file"),
        (["--executor", "nope"], "--executor 'nope' is not one of"),
    ],
)
def test_usage_errors_exit_2_with_one_line_before_any_work(
    extra: list[str],
    needle: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.chdir(tmp_path)
    with no_work([*torch_work(), *_TRAINING_WORK]), pytest.raises(SystemExit) as info:
        train_surrogate.cli(["--out", "u.pt", "--workers", "1", "--no-progress", *extra])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"{PROG}: error: "), err
    assert needle in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_bad_and_oversized_data_files_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    junk = tmp_path / "bad.npz"
    junk.write_bytes(b"not a zip")
    bomb = _bomb(tmp_path / "bomb.npz")
    for path, needle in ((junk, "bad.npz"), (bomb, "raise it with --max-samples")):
        with no_work([*torch_work(), *_TRAINING_WORK]), pytest.raises(SystemExit) as info:
            with _inflating_nothing():
                train_surrogate.cli(["--data", str(path), "--out", str(tmp_path / "o.pt"), *TINY])
        assert info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err
    assert not (tmp_path / "o.pt").exists()


def test_oversized_checkpoint_metadata_is_refused_before_allocation(
    good_pair: Path, tmp_path: Path
) -> None:
    out = _copy_pair(good_pair, tmp_path)
    js = out.with_suffix(".json")
    meta = json.loads(js.read_text())
    for hidden, needle in (
        ([20000, 20000], "parameters, over the limit"),
        ([10**6], "width of 1,000,000, over the limit"),
        ([8] * 100, "100 layers, over the limit"),
    ):
        meta["architecture"]["hidden"] = hidden
        js.write_text(json.dumps(meta))
        with no_work(torch_work()), pytest.raises(ValueError, match=needle):
            Surrogate.load(out)
    js.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match="nested deeper than"):
        Surrogate.load(out)


def test_second_run_on_the_same_output_is_refused(
    data_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from selenv.atomic import OutputLock

    out = tmp_path / "busy.pt"
    sleeper = _proc.popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = OutputLock(out)
        lock.lock_path.write_text(f"{sleeper.pid}\n")  # held by a live process
        with pytest.raises(SystemExit) as info:
            train_surrogate.cli(["--data", str(data_file), "--out", str(out), *TINY])
        assert info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "is being written by another run" in err
    finally:
        _proc.stop(sleeper)


# -- pool workers die with the main process -----------------------------------------------------
def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry.name))
    out: set[int] = set()
    todo = [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc (Linux)")
def test_kill_9_of_the_main_process_ends_the_pool_workers(tmp_path: Path) -> None:
    argv = ["--samples", "20000", "--workers", "2", "--epochs", "1", "--out",
            str(tmp_path / "k.pt"), *TINY]  # fmt: skip
    child = _child(_cli_code(argv), tmp_path)
    deadline = time.monotonic() + 60
    workers: set[int] = set()
    while time.monotonic() < deadline and child.poll() is None:
        workers = {
            p for p in _descendants(child.pid)
            if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()
        }  # fmt: skip
        if len(workers) >= 2:
            break
        time.sleep(0.1)
    assert len(workers) >= 2, "the pool did not start"
    time.sleep(1.0)  # the workers run their initializer before their first task
    family = _descendants(child.pid)  # workers and multiprocessing's resource tracker
    child.kill()
    _proc.communicate(child, 30)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(_alive(p) for p in family):
        time.sleep(0.1)
    survivors = [p for p in family if _alive(p)]
    for pid in survivors:  # do not leave orphans behind when the check fails
        os.kill(pid, signal.SIGKILL)
    assert survivors == []
    assert not (tmp_path / "k.pt").exists()


def test_saved_dataset_is_replaced_atomically(tmp_path: Path) -> None:
    ds = generate_dataset(20, seed=1, workers=1, progress=False)
    path = save_dataset(ds, tmp_path / "x")  # numpy's rule: .npz appended
    assert path.name == "x.npz" and sorted(p.name for p in tmp_path.iterdir()) == ["x.npz"]
    back = load_dataset(path)
    assert np.array_equal(back.P_i, ds.P_i) and back.header == ds.header
