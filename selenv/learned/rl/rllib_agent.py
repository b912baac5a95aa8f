"""An RLlib-trained candidate-scoring module: safe export/import, and the bench agent ``rllib``.

RLlib's own checkpoints are pickles (loading one runs code from the file), so selenv never
loads them. :func:`export_module` writes the trained shared module as two plain files::

    <out>.pth    the module's state_dict (tensors only), torch.save
    <out>.json   metadata: format, env module and kwargs, candidate view, obs layout
                 (trained pool size N, per-candidate width W), module class and model_config,
                 weights file name + sha256 + size, training config, versions, eval result

plus, on request, further files next to them in the same atomic group (``extra_files``: a
training run's resume state, :func:`read_extra_file`), and :func:`load_exported` rebuilds the
module **from the JSON** (class and ``model_config``
checked against :mod:`selenv.learned.rl.rllib_module`), then reads the weights with
``torch.load(weights_only=True)`` after checking their size and sha256, and loads them with
``strict=True``. Any malformed, tampered or mismatched file is a ``ValueError`` naming it.

:class:`RLlibPolicy` plays a PettingZoo module of ``selenv bench`` (``--agents rllib:path=
runs/rllib_fim_selection_v0/policy.json``): each acting agent (``infos[a]["on_turn"]``, every
live agent for receiver clustering) takes the module's most likely allowed action on its own
candidate view (:mod:`selenv.learned.rl.rllib_env`), the waiting ones pass with 0: decentralised,
the same information per agent as in training.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch as th

from selenv.agents.multiagent import MultiAgentPolicy
from selenv.atomic import atomic_paths
from selenv.learned.resources import (
    check_parameter_count,
    checkpoint_dir,
    current_class_name,
    read_metadata,
)
from selenv.learned.rl.candidate_policy import OBS_KEYS, obs_layout
from selenv.learned.rl.rllib_env import (
    CLUSTERING_MODULE,
    FIM_MODULE,
    ClusterLabelView,
    TurnView,
    acting_agents,
    resolve_env,
    view_for,
)
from selenv.learned.rl.safe_load import checked_layout, scorer_parameters
from selenv.learned.tensor_load import load_tensors

__all__ = [
    "CHECKPOINT_DIR",
    "FORMAT",
    "MAX_JSON_BYTES",
    "MAX_WEIGHTS_BYTES",
    "RLlibPolicy",
    "default_path",
    "export_module",
    "export_paths",
    "load_exported",
    "make_rllib_policy",
    "read_extra_file",
]

#: ``format`` of the exported JSON (``format_version`` :data:`FORMAT_VERSION`)
FORMAT = "selenv.rllib_module"
FORMAT_VERSION = 1
MAX_JSON_BYTES = 2**20
#: largest weights file accepted (a default module is ~70 KB)
MAX_WEIGHTS_BYTES = 64 * 2**20
CHECKPOINT_DIR = checkpoint_dir()
#: env module -> the candidate view name its module must have been trained with
VIEW_NAMES = {FIM_MODULE: TurnView.name, CLUSTERING_MODULE: ClusterLabelView.name}
#: how an extra file's key must look (it becomes the file name's tail: ``<stem>.<key>``)
_EXTRA_KEY = re.compile(r"[a-z][a-z_]{0,31}\.(pth|json)")


def _rllib_module() -> Any:
    """The RLlib module code, or ``ValueError`` with the install hint when Ray is missing."""
    from selenv.parallel import require_ray

    require_ray("the rllib agent")
    from selenv.learned.rl import rllib_module

    return rllib_module


def export_paths(path: str | Path) -> tuple[Path, Path]:
    """``(json, pth)`` of an export given as its stem, its ``.json`` or its ``.pth``."""
    p = Path(path)
    stem = p.with_suffix("") if p.suffix in (".json", ".pth") else p
    return stem.with_name(stem.name + ".json"), stem.with_name(stem.name + ".pth")


def export_module(
    module: Any,
    out: str | Path,
    metadata: dict[str, Any],
    *,
    extra_files: dict[str, bytes] | None = None,
) -> tuple[Path, Path]:
    """Write ``module``'s weights to ``<out>.pth`` and ``metadata`` + file facts to ``<out>.json``.

    ``metadata`` must hold ``env_id`` and ``env_kwargs``; the format, view, layout, module
    class and config, parameter count and the weights' name, size and sha256 are added here.
    The two files are written as a pair (:func:`selenv.atomic.atomic_paths`: temporaries in
    the same folder, flushed, then both renamed): a failed or interrupted export leaves a
    previous pair byte-identical and no partial file; an ``OSError`` names the output.

    Args:
        module: the :class:`~selenv.learned.rl.rllib_module.CandidateScoringRLModule`.
        out: the export's stem, ``.json`` or ``.pth``.
        metadata: see above.
        extra_files: key (``name.pth`` or ``name.json``, lower case) -> content, written as
            ``<out>.<key>`` in the same atomic group, each recorded in the JSON's
            ``extra_files`` with its size and sha256 (read back with :func:`read_extra_file`).

    Returns:
        The JSON and weights paths.
    """
    rm = _rllib_module()
    if not isinstance(module, rm.CandidateScoringRLModule):
        raise TypeError(f"expected a CandidateScoringRLModule, got {type(module).__name__}")
    json_path, pth_path = export_paths(out)
    extras = dict(extra_files or {})
    for key in extras:
        if not isinstance(key, str) or not _EXTRA_KEY.fullmatch(key):
            raise ValueError(f"extra_files: key {key!r} must look like 'name.pth' or 'name.json'")
    extra_paths = [json_path.with_name(f"{json_path.stem}.{key}") for key in extras]
    state = {k: v.detach().cpu().clone() for k, v in module.state_dict().items()}
    buffer = io.BytesIO()
    th.save(state, buffer)
    raw = buffer.getvalue()
    env_id = resolve_env(metadata["env_id"])
    layout = obs_layout(module.observation_space)
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        **metadata,
        "env_id": env_id,
        "view": VIEW_NAMES[env_id],
        "obs_layout": {
            "n_candidates_trained": layout["n"],
            "whitened_dim": layout["whitened_dim"],
            "n_features": layout["n_features"],
        },
        "module": {
            "class": rm.MODULE_CLASS,
            "module_id": rm.SHARED_MODULE_ID,
            "model_config": module.module_config,
            "n_parameters": int(sum(p.numel() for p in module.parameters())),
            "pool_size_independent": True,
        },
        "weights": {
            "file": pth_path.name,
            "bytes": len(raw),
            "sha256": hashlib.sha256(raw).hexdigest(),
        },
    }
    if extras:
        meta["extra_files"] = {
            key: {"file": path.name, "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
            for (key, data), path in zip(extras.items(), extra_paths, strict=True)
        }
    text = json.dumps(meta, indent=2) + "\n"  # serialised before anything is written
    targets = [pth_path, json_path, *extra_paths]
    try:
        with atomic_paths(targets) as temps:
            temps[0].write_bytes(raw)
            temps[1].write_text(text, encoding="utf-8")
            for temp, data in zip(temps[2:], extras.values(), strict=True):
                temp.write_bytes(data)
    except OSError as exc:  # name the output, not its temporary
        name = Path(str(exc.filename or ""))
        target = next(
            (
                t
                for t in targets
                if name.name.startswith(f".{t.stem}.tmp-") and name.suffix == t.suffix
            ),
            json_path if name.suffix == ".json" else pth_path,
        )
        raise type(exc)(exc.errno or 0, exc.strerror or str(exc), str(target)) from exc
    return json_path, pth_path


def _read_json(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ValueError(f"RLlib export metadata {path} not found")
    if path.stat().st_size > MAX_JSON_BYTES:
        raise ValueError(f"RLlib export metadata {path} is larger than {MAX_JSON_BYTES} bytes")
    meta = read_metadata(path, "RLlib export metadata")
    if not isinstance(meta, dict):
        raise ValueError(f"RLlib export metadata {path} must be a JSON object")
    if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{path} is not an RLlib module export (format={meta.get('format')!r}, "
            f"format_version={meta.get('format_version')!r}; expected {FORMAT!r}, "
            f"{FORMAT_VERSION})"
        )
    return meta


def _positive_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def _checked_file(
    json_path: Path, entry: Any, what: str, suffix: str, limit: int
) -> tuple[Path, bytes]:
    """The path and bytes of the file a JSON ``entry`` (file, bytes, sha256) names, checked.

    The name must be a bare file name with ``suffix`` next to ``json_path``; its size must
    equal the recorded one and stay within ``limit``; its sha256 must match.
    """
    if not isinstance(entry, dict):
        raise ValueError(f"{json_path}: {what!r} must be an object, got {entry!r:.200}")
    name, sha, size = entry.get("file"), entry.get("sha256"), entry.get("bytes")
    if (
        not isinstance(name, str)
        or Path(name).name != name
        or name in ("", ".", "..")
        or not name.endswith(suffix)
    ):
        raise ValueError(
            f"{json_path}: {what} file must be a {suffix} name next to it, got {name!r:.200}"
        )
    if not isinstance(sha, str) or not _positive_int(size):
        raise ValueError(f"{json_path}: {what} need a sha256 string and a byte count")
    path = json_path.with_name(name)
    if not path.is_file():
        raise ValueError(f"{what} {path} (named by {json_path}) not found")
    actual = path.stat().st_size
    if actual > limit or actual != size:
        raise ValueError(
            f"{what} {path} are {actual} bytes; {json_path} says {size} (limit {limit})"
        )
    raw = path.read_bytes()
    if hashlib.sha256(raw).hexdigest() != sha:
        raise ValueError(f"{what} {path} do not match the sha256 recorded in {json_path}")
    return path, raw


def read_extra_file(json_path: str | Path, meta: dict[str, Any], key: str, limit: int) -> bytes:
    """The bytes of the extra file ``key`` an export's JSON ``meta`` records, checked.

    Args:
        json_path: the export's JSON (the extra file lies next to it).
        meta: its parsed content.
        key: the key given to :func:`export_module`'s ``extra_files``.
        limit: the largest size accepted, in bytes.

    Raises:
        ValueError: not recorded, missing, of another size than recorded or above ``limit``,
            or not matching its sha256; the message names the file.
    """
    path = Path(json_path)
    extras = meta.get("extra_files")
    if not isinstance(extras, dict) or key not in extras:
        raise ValueError(f"{path} records no {key!r} file")
    suffix = "." + key.rsplit(".", 1)[-1]
    return _checked_file(path, extras[key], key, suffix, limit)[1]


def _read_weights(json_path: Path, weights: Any) -> dict[str, th.Tensor]:
    """The state_dict named by the JSON's ``weights`` entry, checked (see module docstring)."""
    pth, raw = _checked_file(json_path, weights, "weights", ".pth", MAX_WEIGHTS_BYTES)
    state = load_tensors(raw, f"weights {pth}", verb="are")  # one line if refused
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, th.Tensor) for k, v in state.items()
    ):
        raise ValueError(f"weights {pth} must map parameter names to tensors")
    return state


def load_exported(path: str | Path) -> tuple[Any, dict[str, Any]]:
    """Rebuild an exported module from its JSON and load its weights safely.

    Args:
        path: the export's ``.json``, ``.pth`` or common stem.

    Returns:
        ``(module, metadata)``: a :class:`~selenv.learned.rl.rllib_module.CandidateScoringRLModule`
        in eval mode on the CPU, and the JSON.

    Raises:
        ValueError: a missing, malformed or tampered file, an unknown env, view or module
            class, a bad ``model_config`` or weights that do not fit it; the message names
            the file.
    """
    rm = _rllib_module()
    json_path, _ = export_paths(path)
    meta = _read_json(json_path)
    try:
        env_id = resolve_env(str(meta.get("env_id")))
    except ValueError as exc:
        raise ValueError(f"{json_path}: {exc}") from None
    meta["env_id"] = env_id
    if meta.get("view") != VIEW_NAMES[env_id]:
        raise ValueError(
            f"{json_path}: view {meta.get('view')!r} does not match {env_id} "
            f"(expected {VIEW_NAMES[env_id]!r})"
        )
    spec, layout = meta.get("module"), meta.get("obs_layout")
    if not isinstance(spec, dict) or current_class_name(spec.get("class")) != rm.MODULE_CLASS:
        got = spec.get("class") if isinstance(spec, dict) else spec
        raise ValueError(f"{json_path}: module class {got!r}, expected {rm.MODULE_CLASS!r}")
    if not isinstance(layout, dict) or not all(
        _positive_int(layout.get(k)) for k in ("n_candidates_trained", "whitened_dim")
    ):
        raise ValueError(f"{json_path}: obs_layout needs positive integer "
                         f"n_candidates_trained and whitened_dim, got {layout!r:.200}")  # fmt: skip
    sizes = checked_layout(meta, str(json_path))  # every size against its ceiling
    try:
        config = rm.check_model_config(spec.get("model_config"))
    except ValueError as exc:
        raise ValueError(f"{json_path}: {exc}") from None
    check_parameter_count(
        scorer_parameters(sizes["whitened_dim"], config["hidden"], config["vf"]),
        f"{json_path}",
    )
    try:
        module = rm.build_module(sizes["n"], sizes["whitened_dim"], config)
    except ValueError as exc:
        raise ValueError(f"{json_path}: {exc}") from None
    except (RuntimeError, MemoryError) as exc:
        raise ValueError(
            f"{json_path}: cannot build the module its metadata describes: "
            f"{type(exc).__name__}: {str(exc)[:200]}"
        ) from None
    state = _read_weights(json_path, meta.get("weights"))
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"weights named by {json_path} do not fit its module: {exc}") from None
    module.eval()
    return module, meta


def default_path(env_id: str) -> Path:
    """Where a shipped export of ``env_id`` would live: ``checkpoints/rllib_<env>.json``."""
    return CHECKPOINT_DIR / f"rllib_{resolve_env(env_id).rsplit('.', 1)[1]}.json"


class RLlibPolicy(MultiAgentPolicy):
    """Every acting agent takes the exported module's action on its own candidate view.

    Args:
        env_id: the PettingZoo module played (the export must have been trained on it).
        path: the export (``.json``, ``.pth`` or stem); ``None``: :func:`default_path` if
            that file exists.
        deterministic: the most likely allowed action (default) or a sample from the
            policy (with the agent's seeded generator).

    Raises:
        ValueError: no export, a bad export (:func:`load_exported`), or one trained on another
            env; in ``reset``, an env whose per-candidate width differs from the export's.
    """

    name = "rllib"

    def __init__(
        self, env_id: str = FIM_MODULE, path: str | Path | None = None, deterministic: bool = True
    ) -> None:
        self.env_id = resolve_env(env_id)
        if path is None:
            path = default_path(self.env_id)
            if not path.is_file():
                short = self.env_id.rsplit(".", 1)[1]
                raise ValueError(
                    f"no RLlib export at {path}; train one with `python -m "
                    f"selenv.train.train_rllib_marl --env {short} --out runs/rllib_{short}/policy` "
                    f"and pass rllib:path=runs/rllib_{short}/policy.json"
                )
        if not isinstance(deterministic, bool):
            raise ValueError(f"deterministic must be true or false, got {deterministic!r}")
        self.deterministic = deterministic
        self.path, _ = export_paths(path)
        self.module, self.metadata = load_exported(self.path)
        if self.metadata["env_id"] != self.env_id:
            raise ValueError(
                f"{self.path} was trained on {self.metadata['env_id']}, not {self.env_id}"
            )
        self.width = int(self.metadata["obs_layout"]["whitened_dim"])

    def reset(self, env: Any, seed: int | None = None) -> None:
        """Start an episode; build the env's view and check its width against the export."""
        super().reset(env, seed)
        self.view = view_for(self.env_id, env)
        space = self.view.space(env.observation_space(env.possible_agents[0]))
        width = obs_layout(space)["whitened_dim"]
        if width != self.width:
            raise ValueError(
                f"{self.path} expects per-candidate width {self.width}; this env has {width}"
            )

    def logits(self, views: list[dict[str, np.ndarray]]) -> np.ndarray:
        """``(len(views), N)`` logits of same-size candidate views (masked: -1e8)."""
        batch = {k: th.as_tensor(np.stack([v[k] for v in views])) for k in OBS_KEYS}
        with th.inference_mode():
            features = self.module.features(batch)
        return features[:, : features.shape[1] - self.module.scorer.pooled_dim].numpy()

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """The module's action for each acting agent, 0 for the waiting ones."""
        out: dict[str, Any] = dict.fromkeys(self.env.agents, 0)
        acting = acting_agents(self.env, infos)
        groups: dict[int, list[str]] = {}
        views = {a: self.view(observations[a]) for a in acting}
        for a in acting:  # one forward per pool size (all agents share it in selenv's envs)
            groups.setdefault(views[a]["action_mask"].size, []).append(a)
        for agents in groups.values():
            logits = self.logits([views[a] for a in agents])
            for a, row in zip(agents, logits, strict=True):
                mask = views[a]["action_mask"].astype(bool)
                if self.deterministic:
                    out[a] = int(np.argmax(np.where(mask, row, -np.inf)))
                else:
                    z = np.where(mask, row.astype(np.float64), -np.inf)
                    p = np.exp(z - z.max())
                    out[a] = int(self.rng.choice(row.size, p=p / p.sum()))
        return out


def make_rllib_policy(
    env_id: str = FIM_MODULE,
    path: str | None = None,
    checkpoint: str | None = None,
    deterministic: bool = True,
) -> RLlibPolicy:
    """Registry factory of ``rllib`` (``rllib:path=FILE``; a bare ``rllib:FILE`` is ``checkpoint``).

    Raises:
        ValueError: both ``path`` and ``checkpoint``, or see :class:`RLlibPolicy`.
    """
    if path is not None and checkpoint is not None:
        raise ValueError("rllib: give the export once (path=FILE or a bare FILE), not both")
    return RLlibPolicy(env_id, path if path is not None else checkpoint, deterministic)
