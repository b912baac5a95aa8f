"""Fine-tuning a trained policy with PPO: start from its weights, let the critic learn first.

A policy distilled from a reference (expert iteration, DAgger, ranking fits) has a trained actor
and an untrained value head. PPO from such a checkpoint (``--init-from``) would take its first
steps on the advantages of a random critic and can undo the imitation before the critic is any
good. :class:`CriticWarmup` (``--critic-warmup N``) freezes every parameter but the value head's
for the updates of the first ``N`` environment steps; then the whole policy trains.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from stable_baselines3.common.callbacks import BaseCallback

from selenv.learned.resources import read_metadata
from selenv.learned.rl.safe_load import check_checkpoint_hash, read_weights

__all__ = ["CRITIC_PREFIXES", "CriticWarmup", "init_from_checkpoint"]

#: parameter-name prefixes of the value head of the candidate-scoring policies
CRITIC_PREFIXES = ("mlp_extractor.value_net.", "value_net.")


def init_from_checkpoint(model: Any, path: str | Path, env_id: str, view: str) -> dict[str, Any]:
    """Load the policy weights of checkpoint ``path`` into ``model`` (the optimizer is new).

    The checkpoint's JSON must name the same ``env_id`` and candidate ``view`` and its zip must
    be the file that JSON describes (SHA-256); the weights are read without unpickling
    (:func:`~selenv.learned.rl.safe_load.read_weights`) and must fit the model exactly.

    Returns:
        ``{"path", "checkpoint_sha256", "env_id", "view"}`` for the run's metadata.

    Raises:
        ValueError: a missing or unreadable pair, another env id or view, or weights that do
            not fit ``model``'s architecture (the message names the file and the difference).
    """
    path = Path(path)
    meta = read_metadata(path.with_suffix(".json"), "checkpoint metadata")
    if not isinstance(meta, dict):
        raise ValueError(f"{path.with_suffix('.json')} must hold a JSON object")
    theirs = {"env_id": meta.get("env_id"), "view": meta.get("view") or "identity"}
    ours = {"env_id": env_id, "view": view}
    if theirs != ours:
        raise ValueError(f"checkpoint {path} was trained on {theirs}, this run trains {ours}")
    check_checkpoint_hash(path, meta)
    try:
        model.policy.load_state_dict(read_weights(path), strict=True)
    except RuntimeError as exc:
        raise ValueError(
            f"checkpoint {path}: its weights do not fit this run's policy (--hidden, "
            f"--activation, --algo): {exc}"
        ) from exc
    return {"path": str(path), "checkpoint_sha256": meta.get("checkpoint_sha256"), **ours}


class CriticWarmup(BaseCallback):
    """Train only the value head in the updates of the first ``steps`` environment steps.

    An update follows each rollout; the updates of rollouts that end at or before ``steps``
    leave every parameter outside :data:`CRITIC_PREFIXES` untouched (``requires_grad=False``,
    so Adam gets no gradient for them). Resumed runs recompute the phase from
    ``num_timesteps``.
    """

    def __init__(self, steps: int) -> None:
        super().__init__()
        self.steps = int(steps)
        self.frozen = False

    def _set(self, frozen: bool) -> None:
        for name, param in self.model.policy.named_parameters():
            if not name.startswith(CRITIC_PREFIXES):
                param.requires_grad_(not frozen)
        self.frozen = frozen

    def _on_rollout_end(self) -> None:
        # the update of this rollout comes next
        self._set(self.model.num_timesteps <= self.steps)

    def _on_training_end(self) -> None:
        if self.frozen:
            self._set(False)

    def _on_step(self) -> bool:
        return True
