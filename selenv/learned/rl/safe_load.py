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

Any failure (not a zip, no weights, unreadable or oversized weights, unknown algorithm or
architecture, shape mismatch) is a ``ValueError`` naming the file and what was expected.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch as th
from gymnasium import spaces
from sb3_contrib import MaskablePPO
from stable_baselines3 import PPO

from selenv.learned.resources import current_class_name
from selenv.learned.rl.candidate_policy import (
    CandidateScorer,
    CandidateScoringPolicy,
    CandidateScoringPPOPolicy,
    make_ppo,
)
from selenv.learned.rl.views import candidate_space

__all__ = [
    "MAX_WEIGHTS_BYTES",
    "POLICY_CLASSES",
    "build_policy",
    "load_policy",
    "model_from_checkpoint",
    "policy_spec",
    "read_weights",
]

#: largest ``policy.pth`` accepted (the shipped ones are 80-400 KB)
MAX_WEIGHTS_BYTES = 64 * 2**20
#: ``training.algorithm`` in the metadata -> the policy class it trains
POLICY_CLASSES: dict[str, type[Any]] = {
    "MaskablePPO": CandidateScoringPolicy,
    "PPO": CandidateScoringPPOPolicy,
}
_EXTRACTOR = f"{CandidateScorer.__module__}.{CandidateScorer.__name__}"


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
    try:
        state = th.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    except Exception as exc:  # unpickling errors of every kind: refuse, never fall back
        raise ValueError(
            f"checkpoint {path}: policy.pth is not a plain tensor file: {exc}"
        ) from exc
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
    training = metadata.get("training", {})
    if not isinstance(training, dict):
        raise ValueError(
            f"checkpoint {name}: metadata 'training' must be an object, got {training!r}"
        )
    algo = training.get("algorithm", "MaskablePPO")
    if algo not in POLICY_CLASSES:
        known = sorted(POLICY_CLASSES)
        raise ValueError(f"checkpoint {name}: training.algorithm={algo!r}, expected one of {known}")
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
            f"checkpoint {name}: architecture policy={arch.get('policy')!r}, features_extractor="
            f"{arch.get('features_extractor')!r}; expected {policy_name!r} and {_EXTRACTOR!r}"
        )
    try:
        extractor = {
            "hidden": [int(h) for h in arch["hidden"]],
            "activation": str(arch["activation"]),
            "gain_skip_init": float(arch.get("gain_skip_init", 0.0)),
        }
        net_arch = {"pi": [], "vf": [int(v) for v in arch["net_arch"]["vf"]]}
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"checkpoint {name}: incomplete architecture metadata: {exc!r}") from exc
    return algo, {"net_arch": net_arch, "features_extractor_kwargs": extractor}


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
    try:
        layout = metadata["obs_layout"]
        n, width = int(layout["n_candidates_trained"]), int(layout["whitened_dim"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"checkpoint {name}: incomplete obs_layout metadata: {exc!r}") from exc
    space = candidate_space(n, width)
    return POLICY_CLASSES[algo](space, spaces.Discrete(n), lambda _: 0.0, **policy_kwargs)


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
    key = "maskable_ppo" if algo == "MaskablePPO" else "ppo"
    model = make_ppo(env, key, policy_kwargs=policy_kwargs, **ppo_kwargs)
    try:
        model.policy.load_state_dict(read_weights(checkpoint), strict=True)
    except RuntimeError as exc:
        raise ValueError(f"checkpoint {name}: weights do not fit its metadata: {exc}") from exc
    return model


def load_policy(
    checkpoint: str | Path, metadata: dict[str, Any]
) -> CandidateScoringPolicy | CandidateScoringPPOPolicy:
    """The trained policy of ``checkpoint`` (module docstring), in evaluation mode on the CPU.

    Raises:
        ValueError: see :func:`read_weights` and :func:`build_policy`; weights that do not fit
            the architecture (missing, unexpected or mis-shaped tensors).
    """
    name = str(checkpoint)
    policy = build_policy(metadata, name=name)
    state = read_weights(checkpoint)
    try:
        policy.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"checkpoint {name}: weights do not fit its metadata: {exc}") from exc
    policy.set_training_mode(False)
    return policy
