"""Pre-training a candidate-scoring policy to rank actions by their exact one-step value.

Where an env has a cheap exact oracle of the objective after each candidate action (the
Algorithm 1 cost of every local edit in ``ReceiverClustering-v1``), the oracle's values are
a far denser training signal than PPO's return: one labelled state scores *every* candidate.
A family's learned module collects such labels along an expert's trajectories; this module
fits the policy's logits to them with a listwise (ListNet, Cao et al. 2007) cross-entropy

    q_k = softmax_k(-dJ_k / (tau * std_allowed(dJ)))      over the allowed candidates k
    loss = - sum_k q_k log pi_k                            (pi = the policy's masked softmax)

where ``dJ_k = J(after k) - J(keep)`` (the no-op has ``dJ = 0``). The result is an ordinary
(Maskable)PPO checkpoint: it plays on its own (zero oracle calls per decision, the ranking's
top action) or as the proposal of a verified top-``k`` search
(:class:`selenv.learned.rl.agent.SB3PolicyAgent` with ``verify_top_k``), and PPO may fine-tune it.

The labels come from a family's labeller (e.g.
:func:`selenv.learned.families.clustering.collect_clustering_ranking`)::

    data = collect_clustering_ranking({"n_agents": 30}, n_states=3000, seed=0, workers=2)
    stats = fit_ranking(model.policy, data, epochs=15)
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from tqdm.auto import tqdm

from selenv.atomic import atomic_path
from selenv.learned.rl._moved import moved_attr
from selenv.learned.tensor_load import load_tensors
from selenv.untrusted import NotParsedError, loads_json

__all__ = [
    "LABELS_FORMAT",
    "FitState",
    "RankingData",
    "fit_ranking",
    "fit_state_path",
    "listnet_targets",
    "load_labels",
    "read_fit_state",
    "read_resume",
    "save_labels",
    "save_resumable",
]


@dataclass
class RankingData:
    """Labelled states: candidate-view observations and the oracle's value of every action.

    Attributes:
        obs: candidate-view observations stacked over the ``S`` states (``key -> (S, ...)``).
        deltas: ``(S, N)`` objective change of each action (lower is better), ``+inf`` where
            the action is masked; the no-op (if any) has 0.
    """

    obs: dict[str, np.ndarray]
    deltas: np.ndarray

    def __post_init__(self) -> None:
        s = self.deltas.shape[0]
        bad = [k for k, v in self.obs.items() if v.shape[0] != s]
        if self.deltas.ndim != 2 or bad:
            raise ValueError(
                f"RankingData: deltas must be (S, N) and every obs entry have S={s} rows; "
                f"deltas {self.deltas.shape}, mismatched keys {bad}"
            )

    def __len__(self) -> int:
        return int(self.deltas.shape[0])

    @staticmethod
    def concatenate(parts: list[RankingData]) -> RankingData:
        """Stack several collections (same pool size)."""
        keys = parts[0].obs.keys()
        obs = {k: np.concatenate([p.obs[k] for p in parts]) for k in keys}
        return RankingData(obs, np.concatenate([p.deltas for p in parts]))


def listnet_targets(deltas: np.ndarray, temperature: float) -> np.ndarray:
    """ListNet target distribution ``q`` ``(S, N)`` from the oracle's ``dJ`` (lower is better).

    ``q = softmax(-dJ / (temperature * s))`` over the allowed actions of each state, with ``s``
    the spread (std) of that state's allowed ``dJ`` (so ``temperature`` is scale-free); masked
    actions get 0. A state whose allowed actions all tie gets the uniform distribution.

    Raises:
        ValueError: ``temperature <= 0`` or a state without any allowed action.
    """
    if not temperature > 0.0:
        raise ValueError(f"temperature must be > 0, got {temperature!r}")
    d = np.asarray(deltas, dtype=np.float64)
    allowed = np.isfinite(d)
    if not np.all(allowed.any(axis=1)):
        raise ValueError("every state needs at least one allowed action (a finite delta)")
    dz = np.where(allowed, d, 0.0)
    count = allowed.sum(axis=1, keepdims=True)
    mean = dz.sum(axis=1, keepdims=True) / count
    spread = np.sqrt((np.where(allowed, d - mean, 0.0) ** 2).sum(axis=1, keepdims=True) / count)
    z = -(dz - dz.min(axis=1, keepdims=True, initial=np.inf, where=allowed))
    z = z / (temperature * np.where(spread > 0.0, spread, 1.0))
    w = np.where(allowed, np.exp(z), 0.0)
    return w / w.sum(axis=1, keepdims=True)


@dataclass
class FitState:
    """Where a ranking fit stands after a completed epoch (what a resumed fit continues from).

    Attributes:
        epochs_done: completed epochs.
        optimizer: the Adam ``state_dict`` after that epoch.
    """

    epochs_done: int
    optimizer: dict[str, Any]


def fit_ranking(
    policy: Any,
    data: RankingData,
    *,
    epochs: int = 15,
    batch_size: int = 32,
    learning_rate: float = 1e-3,
    temperature: float = 0.1,
    val_fraction: float = 0.1,
    seed: int = 0,
    progress: bool = True,
    start: FitState | None = None,
    after_epoch: Callable[[FitState], bool] | None = None,
) -> dict[str, Any]:
    """Fit the policy's action logits to the ListNet targets of ``data`` (Adam, in place).

    Only the actor's path (the features extractor's scores) is trained; the value head is
    left for PPO. Returns metrics on the held-out ``val_fraction`` of the states: the
    cross-entropy, ``top1`` (the policy's top action is the oracle's best), ``regret``
    (mean ``dJ`` of the policy's top action minus the oracle's best, >= 0, over the states
    where the oracle scored that action; ``None`` if it scored none of them),
    ``top_unlabelled`` (the fraction of states where the policy's top action has no score,
    ``dJ = +inf``: a labeller that scores only its own candidates) and ``epochs_done``.

    Resumable: ``after_epoch`` is called with the :class:`FitState` after every completed
    epoch; when it returns ``True`` the fit stops there and returns only ``{"epochs_done":
    e}`` (no metrics). ``start`` (the policy holding the weights of that moment) continues
    such a fit: the batch order is replayed from ``seed`` and Adam's state restored, so the
    result equals the uninterrupted fit's, bit for bit.

    Raises:
        ValueError: ``epochs < 1``, ``batch_size < 1``, ``val_fraction`` outside [0, 1), or a
            ``start`` beyond ``epochs``.
    """
    if epochs < 1 or batch_size < 1 or not 0.0 <= val_fraction < 1.0:
        raise ValueError(
            f"need epochs >= 1, batch_size >= 1, 0 <= val_fraction < 1; got {epochs}, "
            f"{batch_size}, {val_fraction}"
        )
    done = 0 if start is None else start.epochs_done
    if not 0 <= done <= epochs:
        raise ValueError(f"start: {done} epochs done, the fit has {epochs}")
    q_all = listnet_targets(data.deltas, temperature)
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(data))
    n_val = round(val_fraction * len(data))
    val, train = order[:n_val], order[n_val:]
    if train.size == 0:
        raise ValueError(
            f"no training states left: {len(data)} states, val_fraction {val_fraction}"
        )
    for _ in range(done):  # replay the batch orders of the epochs already done
        rng.shuffle(train)
    extractor = policy.pi_features_extractor
    optim = th.optim.Adam(extractor.parameters(), lr=learning_rate)
    if start is not None and done:
        optim.load_state_dict(start.optimizer)
    n = data.deltas.shape[1]

    def logits(idx: np.ndarray) -> th.Tensor:
        obs = {k: th.as_tensor(v[idx], dtype=th.float32) for k, v in data.obs.items()}
        return th.log_softmax(extractor(obs)[:, :n], dim=1)

    policy.set_training_mode(True)
    bar = tqdm(
        total=epochs * train.size,
        initial=done * train.size,
        desc="ranking fit",
        unit="state",
        disable=not progress,
    )
    for epoch in range(done, epochs):
        rng.shuffle(train)
        for begin in range(0, train.size, batch_size):
            idx = train[begin : begin + batch_size]
            q = th.as_tensor(q_all[idx], dtype=th.float32)
            loss = -(q * logits(idx)).sum(dim=1).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
            bar.update(idx.size)
            bar.set_postfix(loss=f"{loss.item():.4f}")
        if after_epoch is not None and after_epoch(FitState(epoch + 1, optim.state_dict())):
            if epoch + 1 < epochs:
                bar.close()
                policy.set_training_mode(False)
                return {"epochs_done": epoch + 1}
    bar.close()
    policy.set_training_mode(False)
    eval_idx = val if val.size else train
    with th.no_grad():
        logp = th.cat([logits(eval_idx[s : s + 256]) for s in range(0, eval_idx.size, 256)])
    q = th.as_tensor(q_all[eval_idx], dtype=th.float32)
    ce = float(-(q * logp).sum(dim=1).mean())
    top = logp.argmax(dim=1).numpy()
    d = data.deltas[eval_idx]
    best = np.min(d, axis=1)
    picked = d[np.arange(top.size), top]
    labelled = np.isfinite(picked)  # the oracle scored the policy's top action
    return {
        "states_train": int(train.size),
        "states_eval": int(eval_idx.size),
        "cross_entropy": round(ce, 5),
        "top1": round(float(np.mean(top == np.argmin(d, axis=1))), 4),
        "regret": float(np.mean(picked[labelled] - best[labelled])) if labelled.any() else None,
        "top_unlabelled": round(float(np.mean(~labelled)), 4),
        "epochs_done": epochs,
    }


# -- resumable runs: the labels, the fit's optimizer and the checkpoints that continue ---------
#: format tag in the header of a labels file (:func:`save_labels`)
LABELS_FORMAT = "selenv-ranking-labels-v1"
#: header of a labels file: at most this many bytes
_MAX_HEADER_BYTES = 1 << 16


def save_labels(data: RankingData, path: str | Path) -> str:
    """Write ``data`` as a compressed ``.npz`` atomically; return the file's SHA-256.

    Members: ``deltas`` ``(S, N)``, ``obs_<key>`` ``(S, ...)`` per observation entry and a JSON
    ``header`` (format, row count). A killed or failed write leaves a previous file intact.
    """
    from selenv.learned.rl.training import file_sha256

    header = {"format": LABELS_FORMAT, "rows": len(data), "keys": sorted(data.obs)}
    arrays: dict[str, Any] = {"header": np.array(json.dumps(header)), "deltas": data.deltas}
    arrays.update({f"obs_{k}": v for k, v in data.obs.items()})
    target = Path(path)
    try:
        with atomic_path(target) as temp:
            np.savez_compressed(temp, **arrays)
            return file_sha256(temp)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from exc


def load_labels(
    path: str | Path,
    *,
    sha256: str,
    rows: int,
    row_shapes: dict[str, tuple[int, ...]],
    n_actions: int,
) -> RankingData:
    """Read a labels file of :func:`save_labels`, checked before anything is inflated.

    The file's SHA-256 must be ``sha256`` (the checkpoint's record); its members must be
    exactly ``header``, ``deltas`` and ``obs_<key>`` for the keys of ``row_shapes``, and each
    ``.npy`` header (read alone, from the zip) must declare ``rows`` rows of the expected
    shape (``deltas``: ``(rows, n_actions)``) and a numeric dtype; arrays are then loaded
    with ``allow_pickle=False``.

    Raises:
        ValueError: a missing or mismatched file, or any declaration that differs (names the
            file and the array).
    """
    import zipfile

    from selenv.learned.rl.training import file_sha256
    from selenv.learned.surrogate_data import _npy_header

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"labels file {path} is missing")
    actual = file_sha256(path)
    if actual != sha256:
        raise ValueError(
            f"labels file {path} is not the one its checkpoint records (sha256 {actual[:12]}..., "
            f"recorded {str(sha256)[:12]}...)"
        )
    expected = {"header": (), "deltas": (rows, n_actions)}
    expected.update({f"obs_{k}": (rows, *shape) for k, shape in row_shapes.items()})
    try:
        with zipfile.ZipFile(path) as zf:
            members = {info.filename: info for info in zf.infolist()}
            if set(members) != {f"{k}.npy" for k in expected}:
                raise ValueError(
                    f"labels file {path} holds arrays {sorted(members)}, expected "
                    f"{sorted(f'{k}.npy' for k in expected)}"
                )
            for name, shape in expected.items():
                got, dtype = _npy_header(zf, members[f"{name}.npy"])
                if name == "header":
                    ok = got == () and dtype.kind == "U" and dtype.itemsize <= _MAX_HEADER_BYTES
                else:
                    ok = got == shape and dtype.kind in "biuf"
                if not ok:
                    raise ValueError(
                        f"labels file {path}: array {name!r} declares shape {got} of {dtype}, "
                        f"expected {shape or 'a short JSON string'}"
                    )
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(str(z["header"]))
            deltas = np.asarray(z["deltas"], dtype=np.float64)
            obs = {k: z[f"obs_{k}"] for k in row_shapes}
    except (OSError, EOFError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise ValueError(f"labels file {path} is not readable: {exc}") from None
    if not isinstance(header, dict) or header.get("format") != LABELS_FORMAT:
        raise ValueError(f"labels file {path}: header format is not {LABELS_FORMAT!r}")
    return RankingData(obs, deltas)


def fit_state_path(checkpoint: str | Path) -> Path:
    """The fit's optimizer state next to a checkpoint: ``<stem>.fit.pt``."""
    return Path(checkpoint).with_suffix(".fit.pt")


def save_resumable(
    model: Any, meta: dict[str, Any], path: str | Path, fit: FitState | None
) -> None:
    """Write checkpoint ``path`` (+ ``.json``) and, mid-fit, the fit's Adam state, as a group.

    ``meta["resume_state"]`` receives ``fit`` (``{"epochs_done", "optimizer_sha256"}``, or
    ``None``); the optimizer goes to :func:`fit_state_path` (``torch.save`` of tensors, read
    back with ``weights_only=True``). All files are written to temporaries first and renamed
    together (:func:`selenv.atomic.atomic_path` around
    :func:`~selenv.learned.rl.training.save_checkpoint`).
    """
    from selenv.learned.rl.training import file_sha256, save_checkpoint

    state = meta["resume_state"]
    extra = fit_state_path(path)
    if fit is None or fit.epochs_done == 0:
        state["fit"] = None if fit is None else {"epochs_done": 0}
        save_checkpoint(model, meta, path)
        extra.unlink(missing_ok=True)  # a stale state of an earlier save: not referenced
        return
    try:
        with atomic_path(extra) as temp:
            th.save(fit.optimizer, temp)
            state["fit"] = {"epochs_done": fit.epochs_done, "optimizer_sha256": file_sha256(temp)}
            save_checkpoint(model, meta, path)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), exc.filename or str(extra)) from exc


def read_fit_state(path: str | Path, fit: Any) -> FitState | None:
    """The :class:`FitState` a checkpoint's ``resume_state["fit"]`` record describes.

    Raises:
        ValueError: a malformed record, or an optimizer file that is missing, differs from
            the recorded SHA-256, is too large, or is not plain tensors.
    """
    from selenv.learned.rl.training import MAX_OPTIMIZER_BYTES, file_sha256

    if fit is None:
        return None
    done = fit.get("epochs_done") if isinstance(fit, dict) else None
    if isinstance(done, bool) or not isinstance(done, int) or done < 0:
        raise ValueError(f"malformed fit state {fit!r}")
    if done == 0:
        return FitState(0, {})
    extra = fit_state_path(path)
    if not extra.is_file():
        raise ValueError(f"the fit's optimizer state {extra} is missing")
    if file_sha256(extra) != fit.get("optimizer_sha256"):
        raise ValueError(f"{extra} is not the optimizer state its checkpoint records")
    if extra.stat().st_size > MAX_OPTIMIZER_BYTES:
        raise ValueError(f"{extra} is larger than {MAX_OPTIMIZER_BYTES} bytes")
    optimizer = load_tensors(extra, str(extra), kind="plain tensors", junk="plain tensors")
    if not isinstance(optimizer, dict):
        raise ValueError(f"{extra} does not hold an optimizer state")
    return FitState(done, optimizer)


def read_resume(
    path: str | Path, *, env_id: str, block: str, ours: dict[str, Any]
) -> dict[str, Any]:
    """The metadata of a ``--resume`` checkpoint of a ranking run, checked against this run.

    The pair must match (:func:`~selenv.learned.rl.training.verify_pair`), be of ``env_id``,
    hold a ``resume_state``, and its ``meta[block]`` (the options it ran with) must equal
    ``ours`` on every key (``env_kwargs`` compared as JSON).

    Raises:
        selenv.exits.UsageError: one line naming the file and the first mismatch.
    """
    from selenv.exits import UsageError
    from selenv.learned.config import option_name
    from selenv.learned.rl.training import read_resume_pair

    path = Path(path)
    meta = read_resume_pair(path)
    state = meta.get("resume_state")
    options = meta.get(block)
    if not isinstance(state, dict) or not isinstance(options, dict):
        raise UsageError(
            f"--resume {path}: no resume state in its metadata (resume from the run's "
            "<out stem>.last.zip or one of its round checkpoints)"
        )
    if meta.get("env_id") != env_id:
        raise UsageError(f"--resume {path}: it was trained on {meta.get('env_id')!r}, not {env_id}")

    def norm(key: str, value: Any) -> Any:
        if key == "env_kwargs" and isinstance(value, str):
            try:  # bounded: a string of the metadata may hold anything
                return loads_json(value, f"--resume {path}: env_kwargs")
            except NotParsedError:
                return value
        return value

    for key, value in ours.items():
        theirs = options.get(key)
        if norm(key, theirs) != norm(key, value) or isinstance(theirs, bool) != isinstance(
            value, bool
        ):
            raise UsageError(
                f"--resume {path}: it was trained with {option_name(key)} {theirs!r}, this run "
                f"has {value!r}; resume with the options of the interrupted run"
            )
    return meta


#: the ranking trainers' sizes: Config field -> (lowest valid value, ceiling lifted by
#: ``--allow-large``; ``None``: none). Checked by :func:`check_ranking_sizes` before any work.
RANKING_SIZES: dict[str, tuple[float, float | None]] = {
    "rounds": (1, 100),
    "states_per_round": (1, 1_000_000),
    "states": (1, 1_000_000),
    "epochs": (1, 10_000),
    "label_every": (1, 100_000),
    "eval_episodes": (0, 100_000),
    "checkpoint_every": (0, None),
    "edit_rank": (1, 4096),
}
#: the labeller's sizes, bounded by the ``rollout`` agent's own ceilings (``top_k`` 256,
#: ``horizon`` 10,000) and the process pool's; ``--allow-large`` does not lift these
RANKING_LIMITS: dict[str, int] = {"top_k": 256, "behaviour_top_k": 256, "horizon": 10_000}


def check_ranking_sizes(cfg: Any) -> None:
    """Every size of a ranking trainer's ``cfg`` in its range and under its ceiling.

    The fields of :data:`RANKING_SIZES` that ``cfg`` has (each a ``--kebab-case`` option);
    ``cfg.allow_large`` lifts those ceilings, never the lower bounds nor
    :data:`RANKING_LIMITS`; ``workers`` is at most the process pool's
    :func:`~selenv.parallel.executors.max_pool_workers`. ``explore`` must lie in [0, 1];
    ``learning_rate`` and ``temperature`` must be finite and > 0.

    Raises:
        selenv.exits.UsageError: the option, its bound or ceiling and how to lift it (exit 2).
    """
    from selenv.exits import UsageError, check_size
    from selenv.parallel.executors import max_pool_workers

    def option(field: str) -> str:
        return "--" + field.replace("_", "-")

    lifted = bool(getattr(cfg, "allow_large", False))
    for field, (low, ceiling) in RANKING_SIZES.items():
        if hasattr(cfg, field):
            check_size(option(field), getattr(cfg, field), low=low, ceiling=ceiling, lifted=lifted)
    for field, high in RANKING_LIMITS.items():
        if hasattr(cfg, field):
            check_size(option(field), getattr(cfg, field), low=1, high=high)
    if hasattr(cfg, "workers"):
        check_size("--workers", cfg.workers, low=1, high=max_pool_workers(),
                   note=" (labelling processes on this machine)")  # fmt: skip
    if hasattr(cfg, "explore"):
        check_size("--explore", cfg.explore, low=0.0, high=1.0)
    for field in ("learning_rate", "temperature"):
        value = getattr(cfg, field, None)
        if value is not None and not (np.isfinite(value) and value > 0):
            raise UsageError(f"{option(field)}: must be finite and > 0, got {value}")


#: names that moved to the family's learned module (deprecated here, for one release)
_MOVED = dict.fromkeys(
    ("clustering_edit_deltas", "collect_clustering_ranking"), "selenv.learned.families.clustering"
)


def __getattr__(name: str) -> Any:
    """A moved name (``_MOVED``), with a ``DeprecationWarning`` naming its new module."""
    return moved_attr(__name__, name, _MOVED)
