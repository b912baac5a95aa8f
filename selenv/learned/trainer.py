"""The trainer base: what every training run shares, whatever its update step.

A training algorithm (PPO / fine-tuning in :mod:`selenv.learned.rl.training`, expert
iteration / DAgger in :mod:`selenv.learned.rl.distill`, the cross-entropy method in
``selenv.train.train_cl_cem``, the surrogate fit, RLlib) brings only its update step; this
module owns the run around it:

* **run options**: :func:`run_arg` declares a shared option (``--out``, ``--force``,
  ``--resume``, ``--seed``, ``--checkpoint-every``, ``--progress``, ``--eval-episodes``,
  ``--eval-seed``, ``--max-minutes``) with its one help text (:data:`RUN_HELP`), and
  :func:`check_run_options` checks the values every trainer shares (a usage error, exit 2,
  one line naming the option);
* **the output lock** (:func:`output_lock`: one run per ``--out``) and the ``.last`` pair of
  an unfinished run (:func:`last_paths`);
* **stopping**: :class:`RunStop` defers SIGINT / SIGTERM to the algorithm's next safe point
  (after an iteration, an epoch, a generation) and turns an expired wall-clock budget
  (``--max-minutes``) into the same kind of stop at the same points; :func:`stop_exception`
  is the one line that ends such a run (:class:`TrainingInterrupted` exit 130,
  :class:`TrainingTerminated` exit 143, :class:`TrainingBudgetReached` exit 75, through
  :func:`run_cli`);
* **resumable checkpoints**: checkpoint pairs written atomically with the zip's SHA-256
  (:func:`save_checkpoint`, :func:`verify_pair`, :func:`read_resume_pair`), and the random
  generators' states (:func:`rng_state`, :func:`set_rng_state`) so that a resumed run
  continues where the stopped one was;
* **held-out evaluation**: :func:`evaluate` plays agents on the same seeds.

The wall-clock budget reads :func:`clock` (a monotonic clock in seconds), looked up when a
:class:`RunStop` is created; a test replaces it to make a budget expire after a given number
of safe points without waiting.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import math
import random
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import gymnasium as gym
import numpy as np
import torch

from selenv.agents import Agent
from selenv.atomic import OutputBusyError, OutputLock, atomic_paths
from selenv.bench.runner import AgentResult, run_episode
from selenv.exits import DeferredSignals, Terminated, UsageError, guarded_main
from selenv.learned.config import arg, parse_config, usage_error
from selenv.learned.resources import read_metadata

__all__ = [
    "BUDGET",
    "MAX_OPTIMIZER_BYTES",
    "RESUME_FREE",
    "RUN_HELP",
    "RunStop",
    "Script",
    "TrainingBudgetReached",
    "TrainingInterrupted",
    "TrainingTerminated",
    "check_max_minutes",
    "check_run_options",
    "clock",
    "evaluate",
    "evaluation_stops",
    "file_sha256",
    "last_paths",
    "output_lock",
    "read_checkpoint_metadata",
    "read_resume_pair",
    "rng_state",
    "run_arg",
    "run_cli",
    "save_checkpoint",
    "save_final",
    "set_rng_state",
    "stop_exception",
    "verify_pair",
    "zip_member",
]

MAX_OPTIMIZER_BYTES = 256 * 2**20
#: the run options a resumed run may change (how long and where it runs, what it writes);
#: every other option must be the stopped run's
RESUME_FREE = (
    "out",
    "force",
    "progress",
    "eval_episodes",
    "eval_seed",
    "resume",
    "checkpoint_every",
    "allow_large",
    "max_minutes",
)
#: the name a stop on the wall-clock budget records (``"interrupted"`` in the ``.last`` JSON)
BUDGET = "max-minutes"

# -- run options ---------------------------------------------------------------------------------
#: the meaning of each shared run option; ``{unit}`` is the trainer's safe point
RUN_HELP: dict[str, str] = {
    "force": "overwrite existing outputs of --out",
    "resume": "continue a run stopped by a signal or --max-minutes (same options) from its {unit}",
    "checkpoint_every": "{unit} between periodic checkpoints <out stem>.last, removed when the "
    "run completes (0: none; a signal or --max-minutes always saves one)",
    "progress": "show tqdm bars",
    "eval_episodes": "held-out episodes on which the result is evaluated (0: none)",
    "eval_seed": "seed of the first held-out episode (then +1, +2, ...)",
    "max_minutes": "wall-clock budget in minutes: at the first safe point ({unit}) after it, "
    'the run stops as on SIGINT, saving <out stem>.last ("interrupted": "max-minutes" in '
    "its JSON) for --resume, and exits 75 (none: no budget)",
}


def run_arg(name: str, default: Any, *, unit: str = "iterations", note: str = "") -> Any:
    """A shared run option ``name`` as a config field: ``default`` and :data:`RUN_HELP`'s text.

    ``unit`` fills the text's ``{unit}``: the trainer's safe point (``"fit epochs"``,
    ``"environment steps"``; for ``resume``, the state file); ``note`` is appended to the
    help (what the option means for this trainer in particular).

    Raises:
        KeyError: ``name`` is not a shared option.
    """
    text = RUN_HELP[name].format(unit=unit)
    return arg(default, f"{text}; {note}" if note else text)


def check_max_minutes(value: object) -> None:
    """Refuse a ``--max-minutes`` that is not a finite number of minutes > 0 (``None``: none).

    Raises:
        UsageError: naming ``--max-minutes`` and the value.
    """
    if value is None:
        return
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not ok or not math.isfinite(float(value)) or float(value) <= 0:  # type: ignore[arg-type]
        raise UsageError(f"--max-minutes must be a finite number of minutes > 0, got {value!r}")


def check_run_options(cfg: Any, prog: str) -> None:
    """Exit 2 with one line when a shared run option of ``cfg`` is out of range.

    ``--max-minutes`` (a finite number > 0 when given), ``--checkpoint-every`` and
    ``--eval-episodes`` (>= 0) where ``cfg`` has them.
    """
    try:
        check_max_minutes(getattr(cfg, "max_minutes", None))
        for name in ("checkpoint_every", "eval_episodes"):
            value = getattr(cfg, name, 0)
            if value < 0:
                option = "--" + name.replace("_", "-")
                raise UsageError(f"{option} must be >= 0, got {value}")
    except UsageError as exc:
        usage_error(prog, exc)


@dataclass(frozen=True)
class Script:
    """A training script's command line: its module, its config dataclass and its doc.

    ``Script("selenv.train.train_cl_ppo", Config, __doc__)`` gives the script its
    :meth:`parse` (``--config FILE`` and the options, usage errors exit 2), its :attr:`prog`
    (how messages name it) and :meth:`command` (its console-script entry point, with the
    exit codes of :func:`run_cli`).
    """

    name: str
    config: type
    doc: str | None

    @property
    def prog(self) -> str:
        """``python -m <module>``: the program named in messages."""
        return f"python -m {self.name}"

    def parse(self, argv: list[str] | None = None) -> Any:
        """The run's config from ``argv`` (``None``: ``sys.argv``) and ``--config FILE``."""
        return parse_config(self.config, argv, (self.doc or "").split("\n")[0], script=self.name)

    def cli(self, main: Callable[..., Any]) -> NoReturn:
        """Run ``main(None)`` as a command: exit 0, 2 (usage), 1 (I/O), 130 / 143 / 75 (stops)."""
        raise SystemExit(run_cli(main, self.prog))

    def command(self, main: Callable[..., Any]) -> Callable[[], NoReturn]:
        """The console-script entry point of ``main`` (:meth:`cli` on ``sys.argv``)."""

        def cli() -> NoReturn:
            """Run the script on ``sys.argv``; exit codes of :func:`run_cli`."""
            self.cli(main)

        return cli


# -- stopping: signals and the wall-clock budget -------------------------------------------------
def clock() -> float:
    """Seconds of a monotonic clock: what the wall-clock budget is measured with."""
    return time.monotonic()


class RunStop(DeferredSignals):
    """Deferred SIGINT / SIGTERM plus the run's wall-clock budget.

    A run checks :meth:`check_budget` at its safe points: once ``max_minutes`` have passed
    since this object was created (each invocation, a resumed one too, has its own budget),
    :attr:`signal` becomes :data:`BUDGET` and the run stops there as it does on a signal. A
    signal received after that abandons the run at once (as a second signal does).

    Args:
        max_minutes: the budget (``None``: none); anything but a finite number > 0 is a
            :class:`~selenv.exits.UsageError`.
    """

    def __init__(self, max_minutes: float | None = None, *, second_raises: bool = True) -> None:
        super().__init__(second_raises=second_raises)
        check_max_minutes(max_minutes)
        self.max_minutes = max_minutes
        self._clock = clock  # the module's clock when the run starts (a test replaces it)
        self._start = self._clock() if max_minutes is not None else 0.0

    def check_budget(self) -> bool:
        """Whether the run should stop here: a signal arrived or the budget is spent."""
        if self.signal is None and self.max_minutes is not None:
            if self._clock() - self._start >= 60.0 * self.max_minutes:
                self.signal = BUDGET
        return self.signal is not None


class TrainingBudgetReached(Exception):
    """``--max-minutes`` stopped training after the last completed step was saved (exit 75)."""

    exit_code = 75


def last_paths(out: str | Path) -> list[Path]:
    """The periodic / interrupted checkpoint pair of ``out``: ``<stem>.last.zip`` and ``.json``."""
    path = Path(out)
    last = path.with_name(f"{path.stem}.last.zip")
    return [last, last.with_suffix(".json")]


@contextlib.contextmanager
def output_lock(out: str | Path, prog: str) -> Iterator[None]:
    """Hold :class:`~selenv.atomic.OutputLock` on ``out`` for the block; busy: exit 2, one line."""
    lock = OutputLock(out)
    try:
        lock.acquire()
    except OutputBusyError as exc:
        usage_error(prog, exc)
    try:
        yield
    finally:
        lock.release()


# -- checkpoint pairs ----------------------------------------------------------------------------
def file_sha256(path: str | Path) -> str:
    """The hex SHA-256 of the file at ``path``."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _named(exc: OSError, target: Path, temp: Path) -> OSError:
    """``exc`` naming ``target`` instead of its temporary file."""
    name = exc.filename
    if name is None or str(name) == str(temp) or Path(str(name)).name.startswith("."):
        name = str(target)
    return type(exc)(exc.errno or 0, exc.strerror or str(exc), name)


def save_checkpoint(
    model: Any, meta: dict[str, Any], path: str | Path, *, exclude: list[str] | None = None
) -> Path:
    """Write the SB3 ``model`` to ``path`` (.zip) and ``meta`` to its ``.json``, as a pair.

    Both files go to temporaries in the same folder first (``model.save``, then the JSON
    with the zip's ``checkpoint_sha256``, which is also set in ``meta``); both are renamed
    only when both are written and flushed. Any failure (``ENOSPC``, ``EFBIG``, an
    interruption) leaves the previous pair byte-identical and no temporary behind; an
    ``OSError`` is re-raised naming the target instead of the temporary. Returns ``path``.
    """
    target = Path(path)
    json_path = target.with_suffix(".json")
    try:
        with atomic_paths([target, json_path]) as (tmp_zip, tmp_json):
            try:
                model.save(tmp_zip, exclude=exclude)
            except RuntimeError as exc:  # torch reports some write failures this way
                raise OSError(0, f"writing failed ({exc})", str(target)) from exc
            meta["checkpoint_sha256"] = file_sha256(tmp_zip)
            text = json.dumps(meta, indent=2) + "\n"
            with open(tmp_json, "w", encoding="utf-8") as fh:
                fh.write(text)
    except OSError as exc:
        which = json_path if exc.filename and str(exc.filename).endswith(".json") else target
        raise _named(exc, which, which) from exc
    return target


def read_checkpoint_metadata(path: str | Path) -> dict[str, Any]:
    """The JSON next to checkpoint ``path``, bounded in size and depth.

    Raises:
        ValueError: missing, or refused by :func:`selenv.learned.resources.read_metadata`
            (too large, nested too deep, not JSON), or not an object.
    """
    json_path = Path(path).with_suffix(".json")
    try:
        meta = read_metadata(json_path, "checkpoint metadata")
    except FileNotFoundError as exc:
        raise ValueError(f"cannot read the metadata {json_path}: {exc}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{json_path} must hold a JSON object")
    return meta


def verify_pair(path: str | Path, meta: dict[str, Any]) -> None:
    """Check that checkpoint ``path`` is the zip its metadata ``meta`` describes.

    Metadata without ``checkpoint_sha256`` (written before it was recorded) is accepted.

    Raises:
        ValueError: the zip's SHA-256 differs from ``meta["checkpoint_sha256"]`` (a pair whose
            halves come from different saves).
    """
    recorded = meta.get("checkpoint_sha256")
    if recorded is None:
        return
    actual = file_sha256(path)
    if actual != recorded:
        json_path = Path(path).with_suffix(".json")
        raise ValueError(
            f"{path} and {json_path} do not match (mismatched pair): the metadata records "
            f"sha256 {str(recorded)[:12]}..., the zip has {actual[:12]}...; use a checkpoint "
            "and the metadata written with it"
        )


def zip_member(path: Path, name: str, limit: int) -> bytes:
    """Member ``name`` of the zip ``path``, at most ``limit`` bytes (``ValueError`` otherwise)."""
    try:
        with zipfile.ZipFile(path) as zf:
            try:
                info = zf.getinfo(name)
            except KeyError:
                raise ValueError(f"checkpoint {path} has no {name}") from None
            if info.file_size > limit:
                raise ValueError(f"checkpoint {path}: {name} is {info.file_size} bytes (> {limit})")
            return zf.read(info)
    except (zipfile.BadZipFile, OSError) as exc:
        raise ValueError(f"checkpoint {path} is not a readable zip file: {exc}") from exc


# -- random generators ---------------------------------------------------------------------------
def _b64(array: np.ndarray[Any, Any]) -> str:
    return base64.b64encode(array.tobytes()).decode("ascii")


def _unb64(text: str, dtype: Any) -> np.ndarray[Any, Any]:
    return np.frombuffer(base64.b64decode(text, validate=True), dtype=dtype)


def rng_state() -> dict[str, Any]:
    """The ``random``, ``numpy.random`` and ``torch`` generators' states, as JSON values.

    The Mersenne-Twister words are base64 of little-endian ``uint32`` (a few KB in all).
    """
    version, internal, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state(legacy=True)  # noqa: NPY002
    return {
        "python": [int(version), _b64(np.asarray(internal, dtype="<u4")), gauss],
        "numpy": [
            str(name),
            _b64(np.asarray(keys, dtype="<u4")),
            int(pos),
            int(has_gauss),
            float(cached),
        ],
        "torch": _b64(torch.get_rng_state().numpy()),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` recorded (``ValueError`` on a malformed record)."""
    try:
        version, internal, gauss = state["python"]
        words = tuple(int(x) for x in _unb64(internal, "<u4"))
        random.setstate((int(version), words, gauss))
        name, keys, pos, has_gauss, cached = state["numpy"]
        numpy_state = (str(name), _unb64(keys, "<u4").astype(np.uint32), pos, has_gauss, cached)
        np.random.set_state(numpy_state)  # noqa: NPY002
        raw = bytearray(base64.b64decode(state["torch"], validate=True))
        torch.set_rng_state(torch.frombuffer(raw, dtype=torch.uint8))
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"the checkpoint's random generator states are malformed: {exc}") from exc


# -- interruptions -------------------------------------------------------------------------------
class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT stopped training after the last completed iteration was saved (exit 130)."""

    exit_code = 130


class TrainingTerminated(Terminated):
    """SIGTERM stopped training after the last completed iteration was saved (exit 143)."""

    exit_code = 143


def evaluate(
    make_env: Callable[[], gym.Env[Any, Any]], agents: dict[str, Agent], seeds: list[int]
) -> dict[str, dict[str, Any]]:
    """Each agent on one episode per seed: returns, final objectives, decision seconds.

    Envs that count objective evaluations also give ``cost_evaluations_per_decision``.
    """
    out: dict[str, dict[str, Any]] = {}
    for name, agent in agents.items():
        env = make_env()
        res = AgentResult(name)
        for seed in seeds:
            ret, obj = run_episode(env, agent, seed, res)
            res.returns.append(ret)
            res.final_objectives.append(obj)
        env.close()
        out[name] = {
            "mean_return": round(float(np.mean(res.returns)), 5),
            "mean_final_objective": round(float(np.mean(res.final_objectives)), 5),
            "returns": [round(r, 5) for r in res.returns],
            "decision_seconds_mean": res.decision_seconds / max(res.decisions, 1),
        }
        if res.cost_evaluations is not None:
            out[name]["cost_evaluations_per_decision"] = res.cost_evaluations_per_decision
    return out


def stop_exception(name: str, what: str) -> BaseException:
    """The exception that ends a run stopped by ``name`` (a signal or :data:`BUDGET`)."""
    if name == BUDGET:
        return TrainingBudgetReached(f"stopped at its --max-minutes budget: {what}")
    if name == "SIGINT":
        return TrainingInterrupted(f"interrupted (SIGINT): {what}")
    return TrainingTerminated(f"terminated (SIGTERM): {what}")


def save_final(
    model: Any, meta: dict[str, Any], out: Path, stale: list[Path], flag: RunStop
) -> None:
    """Write the complete checkpoint pair ``out``, then remove the run's resume files ``stale``.

    Signals are held while the files are written; one that arrived meanwhile (or before)
    ends the run now, the result saved, its evaluation skipped.
    """
    with flag:
        save_checkpoint(model, meta, out)
        for path in stale:  # superseded by the result
            path.unlink(missing_ok=True)
    if flag.signal is not None:
        raise stop_exception(
            flag.signal,
            f"training had completed: saved {out} (+ .json); its evaluation was skipped",
        )


@contextlib.contextmanager
def evaluation_stops(out: Path) -> Iterator[None]:
    """A SIGINT / SIGTERM during the held-out evaluation of ``out``: the run's stop line."""
    try:
        yield
    except (KeyboardInterrupt, Terminated) as exc:
        name = "SIGINT" if isinstance(exc, KeyboardInterrupt) else "SIGTERM"
        raise stop_exception(
            name, f"during the evaluation: {out} (+ .json) is complete, without metrics"
        ) from None


def read_resume_pair(path: Path) -> dict[str, Any]:
    """The metadata of the ``--resume`` checkpoint ``path``, its pair verified.

    Raises:
        UsageError: ``"--resume <path>: <why>"`` for an unreadable or mismatched pair.
    """
    try:
        meta = read_checkpoint_metadata(path)
        verify_pair(path, meta)
    except ValueError as exc:
        raise UsageError(f"--resume {path}: {exc}") from None
    return meta


def run_cli(main: Callable[..., Any], prog: str, argv: list[str] | None = None) -> int:
    """Run a training script's ``main(argv)``; the exit code of :mod:`selenv.exits`.

    A stopped run (:class:`TrainingInterrupted` / :class:`TrainingTerminated` /
    :class:`TrainingBudgetReached`) prints its line (what was saved, how to resume) and
    returns 130 / 143 / 75; everything else as
    :func:`selenv.exits.guarded_main` (usage 2, I/O failure 1, SIGINT 130, SIGTERM 143).
    """
    try:
        return guarded_main(_unwrap_stops, prog, main, argv)
    except _Stopped as stop:
        print(f"{prog}: {stop.args[0]}", file=sys.stderr)
        return int(stop.args[1])


class _Stopped(Exception):
    """(message, exit code) of a stopped run, carried past :func:`guarded_main`."""


def _unwrap_stops(main: Callable[..., Any], argv: list[str] | None) -> Any:
    try:
        return main(argv)
    except (TrainingInterrupted, TrainingTerminated, TrainingBudgetReached) as exc:
        raise _Stopped(str(exc), exc.exit_code) from None
