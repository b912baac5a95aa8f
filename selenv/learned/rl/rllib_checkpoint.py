"""The resumable state of an RLlib training run, without pickle: snapshot, save, read, restore.

The RLlib plug-in of the trainer base (:mod:`selenv.learned.trainer`) used by
:mod:`selenv.train.train_rllib_marl`. After each completed iteration the run takes a
:class:`Snapshot` of the learner (:func:`snapshot`: the shared module's weights, the Adam
state, RLlib's lifetime counters, this process's random generators); :func:`save` writes it as
the checkpoint group ``<out>.last.json`` + ``.last.pth`` (an export of the module, playable as
``rllib:path=<out>.last.json``), ``.last.optimizer.pth`` (tensors and plain values) and
``.last.metrics.json`` (the metrics so far), in one atomic group whose sizes and sha256 the
JSON records (:func:`selenv.learned.rl.rllib_agent.export_module`). :func:`read` checks such a
group file by file (``torch.load(weights_only=True)``, shapes against the module, the metrics'
iterations, the counters' format) and :func:`restore` puts it into a fresh ``Algorithm``
(``Algorithm.set_state``). RLlib's own (pickled) checkpoints are never written nor read.
"""

from __future__ import annotations

import io
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th

from selenv.learned.resources import CHECKPOINT_LIMITS, json_depth
from selenv.learned.tensor_load import load_tensors
from selenv.learned.trainer import MAX_OPTIMIZER_BYTES, rng_state, set_rng_state

__all__ = [
    "METRICS_FILE",
    "OPTIMIZER_FILE",
    "Resumed",
    "Snapshot",
    "checkpoint_paths",
    "read",
    "read_optimizer_state",
    "remove",
    "restore",
    "save",
    "snapshot",
]

#: the extra files of a checkpoint (:func:`selenv.learned.rl.rllib_agent.export_module`)
OPTIMIZER_FILE = "optimizer.pth"
METRICS_FILE = "metrics.json"


def checkpoint_paths(json_path: str | Path) -> list[Path]:
    """The checkpoint group of the export ``json_path`` (``<stem>.json``).

    ``<stem>.last.json``, ``.last.pth``, ``.last.optimizer.pth``, ``.last.metrics.json``.
    """
    json_path = Path(json_path)
    last = json_path.with_name(f"{json_path.stem}.last.json")
    stem = last.with_suffix("")
    return [last, last.with_suffix(".pth")] + [
        stem.with_name(f"{stem.name}.{key}") for key in (OPTIMIZER_FILE, METRICS_FILE)
    ]


@dataclass
class Snapshot:
    """The learner after a completed iteration: what a checkpoint keeps."""

    iteration: int
    weights: dict[str, np.ndarray]  # the shared module's state, copied
    optimizer: dict[str, Any]  # RLlib's optimizer state, arrays as torch tensors
    lifetime: dict[str, dict[str, Any]]  # RLlib's lifetime counters (metrics logger)
    rng: dict[str, Any]  # this process's generators (:func:`rng_state`)


@dataclass
class Resumed:
    """A checked ``--resume`` checkpoint."""

    path: Path
    snapshot: Snapshot
    records: list[dict[str, Any]]
    wall_seconds: float


def _plain(value: Any) -> Any:
    """``value`` with numpy scalars as Python numbers and arrays as copied torch tensors."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(_plain(v) for v in value)
    if isinstance(value, np.ndarray):
        return th.from_numpy(np.array(value, copy=True))
    if isinstance(value, th.Tensor):
        return value.detach().cpu().clone()
    if isinstance(value, np.generic):
        return value.item()
    return value


def snapshot(algo: Any, iteration: int) -> Snapshot:
    """Copy the learner's module and optimizer, the lifetime counters and the generators."""
    from ray.rllib.core import COMPONENT_LEARNER, COMPONENT_OPTIMIZER, COMPONENT_RL_MODULE

    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID

    components = [f"{COMPONENT_LEARNER}/{COMPONENT_RL_MODULE}/{SHARED_MODULE_ID}",
                  f"{COMPONENT_LEARNER}/{COMPONENT_OPTIMIZER}"]  # fmt: skip
    state = algo.learner_group.get_state(components=components)[COMPONENT_LEARNER]
    module = state[COMPONENT_RL_MODULE][SHARED_MODULE_ID]
    lifetime = {
        key: {k: _plain(v) for k, v in stats.items()}
        for key, stats in algo.metrics.get_state()["stats"].items()
        if stats.get("stats_cls_identifier") == "lifetime_sum"
    }
    return Snapshot(
        iteration=iteration,
        weights={k: np.array(v, copy=True) for k, v in module.items()},
        optimizer=_plain(state[COMPONENT_OPTIMIZER]),
        lifetime=lifetime,
        rng=rng_state(),
    )


def save(
    paths: list[Path],
    module: Any,
    meta: dict[str, Any],
    snap: Snapshot,
    records: list[dict[str, Any]],
    wall: float,
) -> Path:
    """Write ``snap`` as the checkpoint group ``paths`` (:func:`checkpoint_paths`); its JSON.

    ``module`` holds the snapshot's weights; ``meta`` is the export's JSON content, to which
    the ``resume_state`` (iterations done, wall seconds, lifetime counters, generators) is
    added; ``records`` are the metrics of iterations 1..``snap.iteration``.
    """
    from selenv.learned.rl.rllib_agent import export_module

    meta["resume_state"] = {
        "iterations_done": snap.iteration,
        "wall_seconds": round(wall, 3),
        "metrics_logger": snap.lifetime,
        "rng": snap.rng,
    }
    buffer = io.BytesIO()
    th.save(snap.optimizer, buffer)
    metrics = (json.dumps(records, indent=1) + "\n").encode("utf-8")
    extra = {OPTIMIZER_FILE: buffer.getvalue(), METRICS_FILE: metrics}
    export_module(module, paths[0], meta, extra_files=extra)
    return paths[0]


def remove(paths: list[Path]) -> None:
    """Remove a checkpoint group (the JSON first: no half group looks valid)."""
    for path in paths:
        path.unlink(missing_ok=True)


def read(json_path: Path, module: Any, meta: dict[str, Any], done: int, where: str) -> Resumed:
    """The state of the checkpoint ``json_path`` after ``done`` iterations, every file checked.

    ``module`` and ``meta`` are its loaded module and JSON. The generators are set from the
    record (which checks it); :func:`restore` sets them again.

    Raises:
        ValueError: a file missing, tampered, not plain tensors, of another module, or a
            malformed record; the message starts with ``where``.
    """
    state = meta.get("resume_state")
    state = state if isinstance(state, dict) else {}
    try:
        optimizer = read_optimizer_state(json_path, meta)
        _check_optimizer(optimizer, [tuple(q.shape) for q in module.parameters()], where)
        records = _read_records(json_path, meta, done)
        lifetime = _check_lifetime(state.get("metrics_logger"), where)
        rng = state.get("rng")
        rng = rng if isinstance(rng, dict) else {}
        set_rng_state(rng)  # checked now, set again by restore()
        wall = state.get("wall_seconds", 0.0)
        wall = float(wall) if _finite(wall) else 0.0
    except ValueError as exc:
        raise ValueError(exc if str(exc).startswith(where) else f"{where}: {exc}") from None
    weights = {k: v.numpy().copy() for k, v in module.state_dict().items()}
    return Resumed(json_path, Snapshot(done, weights, optimizer, lifetime, rng), records, wall)


def read_optimizer_state(json_path: str | Path, meta: dict[str, Any]) -> dict[str, Any]:
    """The optimizer state a checkpoint's JSON ``meta`` names, read without executing code.

    The file's size and sha256 are checked against ``meta``, then it is read with
    ``torch.load(weights_only=True)`` (tensors and plain values only).

    Raises:
        ValueError: missing, tampered, not plain tensors, or not an optimizer state;
            the message names the file.
    """
    from selenv.learned.rl.rllib_agent import read_extra_file

    raw = read_extra_file(json_path, meta, OPTIMIZER_FILE, MAX_OPTIMIZER_BYTES)
    state = load_tensors(
        raw, f"{OPTIMIZER_FILE} of {json_path}", kind="plain tensors", junk="plain tensors"
    )
    if not isinstance(state, dict) or not state:
        raise ValueError(f"{OPTIMIZER_FILE} of {json_path} is not an optimizer state")
    return state


def _check_optimizer(state: dict[str, Any], shapes: list[tuple[int, ...]], where: str) -> None:
    """``ValueError`` unless ``state`` is an Adam state of the shared module's parameters."""
    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID

    bad = f"{where}: not an optimizer state of this module"
    for name, entry in state.items():
        if not isinstance(name, str) or not isinstance(entry, dict):
            raise ValueError(bad)
        if entry.get("module_id") != SHARED_MODULE_ID:
            raise ValueError(f"{where}: optimizer {name!r} is not of module {SHARED_MODULE_ID!r}")
        inner = entry.get("state")
        if not isinstance(inner, dict) or not isinstance(inner.get("param_groups"), list):
            raise ValueError(bad)
        per_param = inner.get("state")
        if not isinstance(per_param, dict):
            raise ValueError(bad)
        groups = inner["param_groups"]
        if not all(isinstance(g, dict) and _plain_group(g) for g in groups):
            raise ValueError(f"{where}: malformed optimizer settings (param_groups)")
        indices = [i for g in groups for i in g["params"]]
        if sorted(indices) != list(range(len(shapes))):
            raise ValueError(f"{where}: the optimizer holds other parameters than the module")
        for index, slots in per_param.items():
            if index not in range(len(shapes)) or not isinstance(slots, dict):
                raise ValueError(bad)
            for key, value in slots.items():
                if isinstance(value, th.Tensor) and key != "step":
                    if tuple(value.shape) != shapes[index]:
                        raise ValueError(
                            f"{where}: optimizer slot {key} of parameter {index} has shape "
                            f"{tuple(value.shape)}, the module's is {shapes[index]}"
                        )
                elif not isinstance(value, th.Tensor | float | int):
                    raise ValueError(bad)


def _plain_group(group: dict[Any, Any]) -> bool:
    """Whether an optimizer's param group holds plain settings and a list of parameter indices."""
    params = group.get("params")
    if not isinstance(params, list) or not all(type(i) is int for i in params):
        return False
    for key, value in group.items():
        if not isinstance(key, str):
            return False
        if key in ("lr", "eps", "weight_decay") and not (_finite(value) and value >= 0):
            return False
        if key == "betas" and not (
            isinstance(value, list | tuple) and len(value) == 2 and all(map(_finite, value))
        ):
            return False
        if key != "params" and not isinstance(
            value, bool | int | float | str | tuple | list | None
        ):
            return False
    return True


_LIFETIME_KEY = re.compile(r"[A-Za-z0-9_]+(--[A-Za-z0-9_]+){0,7}")


def _check_lifetime(value: Any, where: str) -> dict[str, dict[str, Any]]:
    """The lifetime counters of a checkpoint's ``resume_state``, checked (``ValueError``)."""
    if not isinstance(value, dict) or len(value) > 10_000:
        raise ValueError(f"{where}: resume_state.metrics_logger must be an object")
    out = {}
    for key, stats in value.items():
        ok = (
            _LIFETIME_KEY.fullmatch(key) is not None
            and isinstance(stats, dict)
            and stats.get("stats_cls_identifier") == "lifetime_sum"
            and all(isinstance(stats.get(k), bool) for k in ("is_root", "is_leaf"))
            and isinstance(stats.get("track_throughputs", False), bool)
            and _finite(stats.get("lifetime_sum"))
            and (stats.get("latest_merged") is None or _finite(stats.get("latest_merged")))
        )
        if not ok:
            raise ValueError(f"{where}: malformed lifetime counter {key!r:.100}")
        out[key] = {k: stats[k] for k in (
            "stats_cls_identifier", "is_root", "is_leaf", "latest_merged", "lifetime_sum",
            "track_throughputs") if k in stats}  # fmt: skip
    return out


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _read_records(json_path: Path, meta: dict[str, Any], done: int) -> list[dict[str, Any]]:
    """The checkpoint's metrics records, which must be iterations 1..``done``."""
    from selenv.learned.rl.rllib_agent import read_extra_file

    raw = read_extra_file(json_path, meta, METRICS_FILE, CHECKPOINT_LIMITS["max_metadata_bytes"])
    try:
        text = raw.decode("utf-8")
        if json_depth(text) > 8:
            raise ValueError("nested too deeply")
        records = json.loads(text)
    except ValueError as exc:  # UnicodeDecodeError, JSONDecodeError
        raise ValueError(f"{METRICS_FILE} of {json_path} is not valid: {exc}") from None
    if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
        raise ValueError(f"{METRICS_FILE} of {json_path} must be a list of objects")
    if [r.get("iteration") for r in records] != list(range(1, done + 1)):
        raise ValueError(f"{METRICS_FILE} of {json_path} does not hold iterations 1..{done}")
    return records


def restore(algo: Any, resumed: Resumed) -> None:
    """Put the checkpoint into the fresh ``algo`` (``Algorithm.set_state``) and the generators.

    The learner gets the module's weights and the optimizer state and syncs the weights to
    the env runners; the metrics logger gets the lifetime counters; the iteration count
    continues.
    """
    from ray.rllib.core import (
        COMPONENT_LEARNER,
        COMPONENT_LEARNER_GROUP,
        COMPONENT_METRICS_LOGGER,
        COMPONENT_OPTIMIZER,
        COMPONENT_RL_MODULE,
    )
    from ray.tune.result import TRAINING_ITERATION

    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID

    snap = resumed.snapshot
    learner = {
        COMPONENT_RL_MODULE: {SHARED_MODULE_ID: snap.weights},
        COMPONENT_OPTIMIZER: snap.optimizer,
    }
    algo.set_state({
        COMPONENT_LEARNER_GROUP: {COMPONENT_LEARNER: learner},
        COMPONENT_METRICS_LOGGER: {"stats": snap.lifetime},
        TRAINING_ITERATION: snap.iteration,
    })  # fmt: skip
    set_rng_state(snap.rng)
