"""Load a candidate-scoring SB3 checkpoint without executing anything from the file.

SB3's ``PPO.load`` / ``MaskablePPO.load`` unpickle (cloudpickle) every ``":serialized:"`` field
of the zip's ``data`` entry, so a crafted zip runs code when it is loaded. selenv never calls
them on a file. Instead:

1. the policy is **rebuilt from the JSON metadata** next to the zip (``training.algorithm``,
   ``architecture``: features extractor widths and activation, value-head ``net_arch``;
   ``obs_layout``: pool size and per-candidate width) — a plain JSON read;
2. only the **weights** ``policy.pth`` are read from the zip, with
   ``torch.load(weights_only=True)`` (tensors and containers only, never arbitrary objects),
   after a size check; the ``data`` entry, the optimizer state and everything else in the zip
   are never read;
3. ``load_state_dict(strict=True)``: every tensor must match the rebuilt architecture.

Untrusted sizes are bounded before anything is built (:mod:`selenv.learned.resources`,
``CHECKPOINT_LIMITS``): the layer widths and their number, the parameter count the architecture
implies, the pool size and per-candidate width of ``obs_layout``; a metadata JSON that records
``checkpoint_sha256`` must match the zip (:func:`check_checkpoint_hash`: a checkpoint and a
JSON from different saves are refused).

Any failure (not a zip, no weights, unreadable or oversized weights, unknown algorithm or
architecture, sizes beyond a ceiling, a mismatched pair, shape mismatch) is a ``ValueError``
naming the file and what was expected; a missing zip is a ``FileNotFoundError``. Nothing here
lets a ``RuntimeError``, ``MemoryError`` or ``RecursionError`` of a crafted file escape.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import math
import re
import zipfile
from collections.abc import Callable, Iterator
from itertools import pairwise
from pathlib import Path
from typing import Any

import torch as th
from gymnasium import spaces
from sb3_contrib import MaskablePPO
from stable_baselines3 import PPO

from selenv.learned.resources import (
    CHECKPOINT_LIMITS,
    bounded_int,
    bounded_widths,
    check_parameter_count,
    current_class_name,
    limit_hint,
    mlp_parameters,
)
from selenv.learned.rl.candidate_policy import (
    CandidateScorer,
    CandidateScoringPolicy,
    CandidateScoringPPOPolicy,
    make_ppo,
)
from selenv.learned.rl.views import N_FEATURES, candidate_space
from selenv.learned.tensor_load import load_tensors

__all__ = [
    "FAMILY_ARCHITECTURES",
    "MAX_CHECKPOINT_BYTES",
    "MAX_WEIGHTS_BYTES",
    "POLICY_CLASSES",
    "build_policy",
    "builder_for",
    "check_checkpoint_hash",
    "checked_layout",
    "load_policy",
    "model_from_checkpoint",
    "policy_spec",
    "read_weights",
    "scorer_parameters",
]

#: largest ``policy.pth`` accepted (the shipped ones are 80-400 KB)
MAX_WEIGHTS_BYTES = 64 * 2**20
#: largest checkpoint zip hashed for ``checkpoint_sha256`` (weights, optimizer state, data)
MAX_CHECKPOINT_BYTES = 4 * MAX_WEIGHTS_BYTES
#: ``training.algorithm`` in the metadata -> the policy class it trains
POLICY_CLASSES: dict[str, type[Any]] = {
    "MaskablePPO": CandidateScoringPolicy,
    "PPO": CandidateScoringPPOPolicy,
}
_EXTRACTOR = f"{CandidateScorer.__module__}.{CandidateScorer.__name__}"
#: a family's own features extractor (its class name as the metadata records it, under its
#: current path) -> ``"module:function"`` of the builder of its untrained policy. A fixed
#: table: the checkpoint's string only selects an entry, the module imported is named here
#: (and is imported only when such a checkpoint is loaded, so this generic layer does not
#: depend on the families' learning code).
FAMILY_ARCHITECTURES: dict[str, str] = {
    "selenv.learned.families.clustering_edits.FactorisedEditScorer": (
        "selenv.learned.families.clustering_edits:build_edit_policy"
    ),
}
#: per-candidate inputs of ``CandidateScorer`` besides ``whitened``: log1p gain, relative
#: gain, the static features, selected, budget
_SCORER_EXTRA_INPUTS = 2 + N_FEATURES + 2
_SHA256 = re.compile(r"[0-9a-f]{64}")
_HASH_CHUNK = 2**20


def checked_layout(metadata: dict[str, Any], name: str = "") -> dict[str, int]:
    """``obs_layout`` of checkpoint metadata, every size held against ``CHECKPOINT_LIMITS``.

    Returns:
        ``{"n": n_candidates_trained, "whitened_dim": W}`` (``n`` is 0 when the metadata
        does not record it: the ``ppo`` agent then takes the pool from the env).

    Raises:
        ValueError: a missing ``obs_layout`` or ``whitened_dim``; ``n_candidates_trained``,
            ``whitened_dim``, ``m``, ``d`` or ``n_features`` not a positive integer or above
            its ceiling; ``n_candidates_trained * whitened_dim`` above
            ``max_observation_entries``; ``whitened_dim != m * d``; ``n_features`` not the
            view's 4. Each message names the field, the value and the ceiling.
    """
    source = f"checkpoint {name}" if name else "checkpoint"
    layout = metadata.get("obs_layout") if isinstance(metadata, dict) else None
    if not isinstance(layout, dict):
        raise ValueError(f"{source}: metadata lacks an obs_layout object")
    if "whitened_dim" not in layout:
        raise ValueError(f"{source}: obs_layout lacks whitened_dim")
    width = bounded_int(
        layout["whitened_dim"], "obs_layout.whitened_dim", "max_candidate_width", source
    )
    n = 0
    if "n_candidates_trained" in layout:
        n = bounded_int(
            layout["n_candidates_trained"], "obs_layout.n_candidates_trained", "max_candidates",
            source,
        )  # fmt: skip
        if n * width > CHECKPOINT_LIMITS["max_observation_entries"]:
            raise ValueError(
                f"{source}: obs_layout n_candidates_trained * whitened_dim = {n:,} * {width:,} "
                f"= {n * width:,} exceeds {limit_hint('max_observation_entries')}"
            )
    m_d = [
        bounded_int(layout[k], f"obs_layout.{k}", "max_candidate_width", source)
        for k in ("m", "d")
        if layout.get(k) is not None
    ]
    if len(m_d) == 2 and m_d[0] * m_d[1] != width:
        raise ValueError(f"{source}: obs_layout whitened_dim={width} != m*d = {m_d[0]}*{m_d[1]}")
    if layout.get("n_features") is not None:
        feats = bounded_int(
            layout["n_features"], "obs_layout.n_features", "max_candidate_width", source
        )
        if feats != N_FEATURES:
            raise ValueError(
                f"{source}: obs_layout n_features={feats}, the candidate view has {N_FEATURES}"
            )
    return {"n": n, "whitened_dim": width}


def scorer_parameters(whitened_dim: int, hidden: list[int], vf: list[int], head: int = 1) -> int:
    """Parameters of a candidate-scoring policy (an upper estimate, before building it).

    ``whitened_dim`` plus 8 per-candidate inputs, the DeepSets chain
    ``hidden`` (each later layer with its context matrix), a score head of ``head`` outputs,
    the value MLP ``vf`` on the pooled ``2 H`` and its output; doubled for the critic's own
    features extractor.
    """
    chain = mlp_parameters([whitened_dim + _SCORER_EXTRA_INPUTS, *hidden]) + sum(
        a * b for a, b in pairwise(hidden)
    )
    scorer = chain + (hidden[-1] + 1) * head + 1
    value = mlp_parameters([2 * hidden[-1], *vf]) + (vf[-1] if vf else 2 * hidden[-1]) + 1
    return 2 * scorer + value


def check_checkpoint_hash(checkpoint: str | Path, metadata: dict[str, Any]) -> None:
    """Refuse a zip that is not the one its metadata's ``checkpoint_sha256`` records.

    Metadata without the field (checkpoints saved before it was written) passes.

    Raises:
        FileNotFoundError: the zip is missing.
        ValueError: a malformed hash, a zip larger than ``MAX_CHECKPOINT_BYTES``, or a
            mismatch (naming both files: the pair comes from different saves).
    """
    recorded = metadata.get("checkpoint_sha256") if isinstance(metadata, dict) else None
    if recorded is None:
        return
    path = Path(checkpoint)
    json_path = path.with_suffix(".json")
    if not isinstance(recorded, str) or not _SHA256.fullmatch(recorded.lower()):
        raise ValueError(
            f"checkpoint metadata {json_path}: checkpoint_sha256 must be 64 hex digits, "
            f"got {recorded!r:.80}"
        )
    try:
        size = path.stat().st_size
        if size > MAX_CHECKPOINT_BYTES:
            raise ValueError(
                f"checkpoint {path} is {size:,} bytes, more than MAX_CHECKPOINT_BYTES = "
                f"{MAX_CHECKPOINT_BYTES:,} of {__name__}"
            )
        digest = hashlib.sha256()
        with path.open("rb") as fh:
            while chunk := fh.read(_HASH_CHUNK):
                digest.update(chunk)
    except FileNotFoundError:
        raise FileNotFoundError(f"checkpoint {path} not found") from None
    except OSError as exc:
        raise ValueError(f"checkpoint {path} is not readable: {exc}") from None
    if digest.hexdigest() != recorded.lower():
        raise ValueError(
            f"checkpoint {path} does not match its metadata {json_path}: the sha256 recorded "
            "there (checkpoint_sha256) is another file's, so the two come from different "
            "saves; use a matching pair"
        )


def read_weights(checkpoint: str | Path) -> dict[str, th.Tensor]:
    """The policy's ``state_dict`` from the SB3 zip ``checkpoint`` (tensors only).

    Raises:
        ValueError: not a zip, no ``policy.pth``, larger than :data:`MAX_WEIGHTS_BYTES`,
            not loadable with ``weights_only=True``, or not a ``{name: tensor}`` mapping.
    """
    path = Path(checkpoint)
    try:
        with zipfile.ZipFile(path) as zf:
            try:
                info = zf.getinfo("policy.pth")
            except KeyError:
                raise ValueError(f"checkpoint {path} has no policy.pth (not an SB3 zip)") from None
            if info.file_size > MAX_WEIGHTS_BYTES:
                raise ValueError(
                    f"checkpoint {path}: policy.pth is {info.file_size} bytes, more than "
                    f"MAX_WEIGHTS_BYTES = {MAX_WEIGHTS_BYTES}"
                )
            raw = zf.read(info)
    except (zipfile.BadZipFile, OSError) as exc:
        raise ValueError(f"checkpoint {path} is not a readable zip file: {exc}") from exc
    state = load_tensors(raw, f"checkpoint {path}: policy.pth")  # one line if refused
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, th.Tensor) for k, v in state.items()
    ):
        raise ValueError(f"checkpoint {path}: policy.pth must map parameter names to tensors")
    return state


def policy_spec(metadata: dict[str, Any], name: str = "") -> tuple[str, dict[str, Any]]:
    """``(algorithm, policy_kwargs)`` of the checkpoint's architecture, from its metadata.

    ``algorithm`` is ``"MaskablePPO"`` or ``"PPO"``; ``policy_kwargs`` are ``net_arch`` and
    ``features_extractor_kwargs`` as :func:`selenv.learned.rl.candidate_policy.make_ppo` takes them.

    Raises:
        ValueError: an unknown algorithm, policy or features extractor, or missing fields.
    """
    algo = _training_algorithm(metadata, name)
    cls = POLICY_CLASSES[algo]
    arch = metadata.get("architecture")
    if not isinstance(arch, dict):
        raise ValueError(f"checkpoint {name}: metadata lacks an 'architecture' object")
    policy_name = f"{cls.__module__}.{cls.__name__}"
    if (
        current_class_name(arch.get("policy", policy_name)) != policy_name
        or current_class_name(arch.get("features_extractor")) != _EXTRACTOR
    ):
        raise ValueError(
            f"checkpoint {name}: architecture policy={arch.get('policy')!r:.120}, "
            f"features_extractor={arch.get('features_extractor')!r:.120}; expected "
            f"{policy_name!r} and {_EXTRACTOR!r}"
        )
    source = f"checkpoint {name}" if name else "checkpoint"
    extractor, net_arch = _common_architecture(arch, source)
    check_parameter_count(
        scorer_parameters(_layout_width(metadata), extractor["hidden"], net_arch["vf"]),
        source,
    )
    return algo, {"net_arch": net_arch, "features_extractor_kwargs": extractor}


def _training_algorithm(metadata: dict[str, Any], name: str) -> str:
    """The checkpoint's ``training.algorithm``, a key of :data:`POLICY_CLASSES`.

    Raises:
        ValueError: a ``training`` that is not an object, or an unknown algorithm.
    """
    training = metadata.get("training", {})
    if not isinstance(training, dict):
        raise ValueError(
            f"checkpoint {name}: metadata 'training' must be an object, got {training!r:.80}"
        )
    algo = training.get("algorithm", "MaskablePPO")
    if not isinstance(algo, str) or algo not in POLICY_CLASSES:
        known = sorted(POLICY_CLASSES)
        raise ValueError(
            f"checkpoint {name}: training.algorithm={algo!r:.80}, expected one of {known}"
        )
    return algo


def _layout_width(metadata: dict[str, Any]) -> int:
    """``obs_layout.whitened_dim`` if it is a bounded int, else 1 (checked elsewhere)."""
    layout = metadata.get("obs_layout")
    width = layout.get("whitened_dim") if isinstance(layout, dict) else None
    if isinstance(width, int) and not isinstance(width, bool):
        return width if 1 <= width <= CHECKPOINT_LIMITS["max_candidate_width"] else 1
    return 1


def _common_architecture(
    arch: dict[str, Any], source: str
) -> tuple[dict[str, Any], dict[str, list[int]]]:
    """``(features_extractor_kwargs, net_arch)`` shared by both scorers, bounded.

    ``hidden`` (the scorer's widths), ``activation``, ``gain_skip_init`` and
    ``net_arch.vf`` (the value MLP), each width and the number of layers within
    ``CHECKPOINT_LIMITS``.

    Raises:
        ValueError: a missing or malformed field, naming it.
    """
    if "hidden" not in arch:
        raise ValueError(f"{source}: incomplete architecture metadata: no 'hidden'")
    hidden = bounded_widths(arch["hidden"], "architecture.hidden", source)
    activation = arch.get("activation")
    if not isinstance(activation, str):
        raise ValueError(
            f"{source}: architecture.activation must be a string, got {activation!r:.80}"
        )
    skip = arch.get("gain_skip_init", 0.0)
    if isinstance(skip, bool) or not isinstance(skip, int | float) or not math.isfinite(skip):
        raise ValueError(
            f"{source}: architecture.gain_skip_init must be a finite number, got {skip!r:.80}"
        )
    net = arch.get("net_arch")
    if not isinstance(net, dict) or "vf" not in net:
        raise ValueError(f"{source}: incomplete architecture metadata: no 'net_arch.vf'")
    vf = bounded_widths(net["vf"], "architecture.net_arch.vf", source, allow_empty=True)
    extractor = {"hidden": hidden, "activation": activation, "gain_skip_init": float(skip)}
    shortlist = arch.get("shortlist", 0)
    limit = CHECKPOINT_LIMITS["max_candidates"]
    if isinstance(shortlist, bool) or not isinstance(shortlist, int) or not 0 <= shortlist <= limit:
        raise ValueError(
            f"{source}: architecture.shortlist must be an int in [0, {limit}], got "
            f"{shortlist!r:.80}"
        )
    if shortlist:
        extractor["shortlist"] = shortlist
    return extractor, {"pi": [], "vf": vf}


def build_policy(
    metadata: dict[str, Any], name: str = ""
) -> CandidateScoringPolicy | CandidateScoringPPOPolicy:
    """A fresh (untrained) policy of the metadata's architecture, for the training pool.

    The pool is ``obs_layout.n_candidates_trained`` candidates of ``whitened_dim`` features
    (the weights do not depend on it).

    Raises:
        ValueError: see :func:`policy_spec`; a missing ``obs_layout``.
    """
    algo, policy_kwargs = policy_spec(metadata, name)
    return build_on_training_pool(POLICY_CLASSES[algo], policy_kwargs, metadata, name)


def build_on_training_pool(
    policy_class: Any, policy_kwargs: dict[str, Any], metadata: dict[str, Any], name: str
) -> CandidateScoringPolicy | CandidateScoringPPOPolicy:
    """``policy_class`` built on the checkpoint's training pool (bounded ``obs_layout``).

    Construction failures (a torch ``RuntimeError``, ``MemoryError``, a ``ValueError`` of the
    class) become a ``ValueError`` naming the checkpoint.
    """
    layout = checked_layout(metadata, name)
    n, width = layout["n"], layout["whitened_dim"]
    if not n:
        raise ValueError(f"checkpoint {name}: obs_layout lacks n_candidates_trained")
    with _build_errors(name):
        space = candidate_space(n, width)
        try:
            policy: CandidateScoringPolicy | CandidateScoringPPOPolicy = policy_class(
                space, spaces.Discrete(n), lambda _: 0.0, **policy_kwargs
            )
        except ValueError as exc:
            raise ValueError(f"checkpoint {name}: {exc}") from exc
    return policy


@contextlib.contextmanager
def _build_errors(name: str) -> Iterator[None]:
    """Turn a failure to allocate the (bounded) architecture into a ``ValueError``.

    The ceilings make this unreachable on ordinary machines; a ``RuntimeError`` of torch
    or a ``MemoryError`` of numpy still never escapes a loader as such.
    """
    try:
        yield
    except (RuntimeError, MemoryError) as exc:
        raise ValueError(
            f"checkpoint {name}: cannot build the architecture its metadata describes: "
            f"{type(exc).__name__}: {str(exc)[:200]}"
        ) from None


def model_from_checkpoint(
    checkpoint: str | Path,
    metadata: dict[str, Any],
    env: Any,
    *,
    spec: Callable[[dict[str, Any], str], tuple[str, dict[str, Any]]] | None = None,
    **ppo_kwargs: Any,
) -> MaskablePPO | PPO:
    """A new SB3 model on ``env`` (a candidate view) holding the checkpoint's weights.

    For code that continues training from a file (DAgger, fine-tuning): the model is built by
    :func:`~selenv.learned.rl.candidate_policy.make_ppo` with the metadata's architecture, then the
    weights are read safely (:func:`read_weights`). The optimizer starts afresh. ``spec``
    reads the architecture from the metadata (default :func:`policy_spec`; the factorised edit
    scorer passes its own).

    Raises:
        ValueError: as :func:`load_policy`.
    """
    name = str(checkpoint)
    algo, policy_kwargs = (spec or policy_spec)(metadata, name)
    check_checkpoint_hash(checkpoint, metadata)
    key = "maskable_ppo" if algo == "MaskablePPO" else "ppo"
    with _build_errors(name):
        model = make_ppo(env, key, policy_kwargs=policy_kwargs, **ppo_kwargs)
    try:
        model.policy.load_state_dict(read_weights(checkpoint), strict=True)
    except RuntimeError as exc:
        raise ValueError(f"checkpoint {name}: weights do not fit its metadata: {exc}") from exc
    return model


def builder_for(
    metadata: dict[str, Any],
) -> Callable[..., CandidateScoringPolicy | CandidateScoringPPOPolicy]:
    """The builder of the untrained policy ``metadata`` describes.

    A family architecture of :data:`FAMILY_ARCHITECTURES` (by the exact features-extractor
    string of ``metadata["architecture"]``) gets its family's builder; anything else
    :func:`build_policy`, which validates it.
    """
    arch = metadata.get("architecture") if isinstance(metadata, dict) else None
    extractor = (
        current_class_name(arch.get("features_extractor")) if isinstance(arch, dict) else None
    )
    target = FAMILY_ARCHITECTURES.get(extractor) if isinstance(extractor, str) else None
    if target is None:
        return build_policy
    module, _, attr = target.partition(":")
    builder: Callable[..., CandidateScoringPolicy | CandidateScoringPPOPolicy]
    builder = getattr(importlib.import_module(module), attr)
    return builder


def load_policy(
    checkpoint: str | Path,
    metadata: dict[str, Any],
    build: Callable[..., CandidateScoringPolicy | CandidateScoringPPOPolicy] | None = None,
) -> CandidateScoringPolicy | CandidateScoringPPOPolicy:
    """The trained policy of ``checkpoint`` (module docstring), in evaluation mode on the CPU.

    ``build(metadata, name=...)`` makes the untrained policy the weights are loaded into
    (default :func:`builder_for` the metadata: :func:`build_policy`, or the family's builder
    of an architecture in :data:`FAMILY_ARCHITECTURES`).

    Raises:
        ValueError: see :func:`read_weights` and :func:`build_policy`; weights that do not fit
            the architecture (missing, unexpected or mis-shaped tensors).
    """
    name = str(checkpoint)
    policy = (build or builder_for(metadata))(metadata, name=name)
    check_checkpoint_hash(checkpoint, metadata)
    state = read_weights(checkpoint)
    try:
        policy.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"checkpoint {name}: weights do not fit its metadata: {exc}") from exc
    policy.set_training_mode(False)
    return policy
