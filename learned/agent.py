"""A trained MaskablePPO checkpoint as a :class:`selenv.agents.Agent` (registry name ``ppo``).

The checkpoint is a zip saved by SB3 with a JSON of its metadata next to it (same stem), as
written by ``train/train_fim_ppo.py``. The policy's weights do not depend on the pool size, so
one checkpoint plays any ``FIMSelection-v0`` pool with the same whitened width ``m d``::

    agent = selenv.agents.make("ppo", "selenv/FIMSelection-v0")
    obs, info = env.reset(seed=0)
    agent.reset(env, seed=0)
    action = agent.act(obs, info)

Every failure to load or to apply a checkpoint is a ``ValueError`` naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from learned.fim_policy import CandidateScoringPolicy, obs_layout
from selenv.agents.base import Agent
from selenv.envs.fim_selection import fim_observation_space

__all__ = [
    "CHECKPOINT_DIR",
    "DEFAULT_CHECKPOINT",
    "SB3PolicyAgent",
    "load_metadata",
    "make_fim_ppo_agent",
]

FIM_ENV_ID = "selenv/FIMSelection-v0"
CHECKPOINT_DIR = Path(__file__).resolve().parents[1] / "checkpoints"
DEFAULT_CHECKPOINT = CHECKPOINT_DIR / "fim_selection_ppo.zip"

#: objects of the saved model that acting does not need (and that may not unpickle elsewhere)
_CUSTOM_OBJECTS: dict[str, Any] = {
    "learning_rate": 0.0,
    "lr_schedule": lambda _: 0.0,
    "clip_range": lambda _: 0.0,
}


def load_metadata(checkpoint: str | Path) -> dict[str, Any]:
    """Read and check the JSON metadata next to ``checkpoint`` (``foo.zip`` -> ``foo.json``).

    Raises:
        ValueError: the JSON is missing, unreadable, or lacks ``obs_layout`` with integer
            ``m``, ``d`` and ``whitened_dim = m d``.
    """
    path = Path(checkpoint).with_suffix(".json")
    if not path.is_file():
        raise ValueError(f"checkpoint metadata {path} not found (expected next to {checkpoint})")
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"checkpoint metadata {path} is not valid JSON: {exc}") from exc
    layout = meta.get("obs_layout") if isinstance(meta, dict) else None
    if not isinstance(layout, dict) or not all(
        isinstance(layout.get(k), int) for k in ("m", "d", "whitened_dim")
    ):
        raise ValueError(
            f"checkpoint metadata {path} lacks obs_layout with integer m, d, whitened_dim "
            f"(got {layout!r})"
        )
    if layout["whitened_dim"] != layout["m"] * layout["d"]:
        raise ValueError(
            f"checkpoint metadata {path}: obs_layout whitened_dim={layout['whitened_dim']} "
            f"!= m*d = {layout['m']}*{layout['d']}"
        )
    return meta


class SB3PolicyAgent(Agent):
    """Acts with a MaskablePPO :class:`CandidateScoringPolicy` checkpoint (greedy in its logits).

    Args:
        checkpoint: path of the SB3 zip; default ``checkpoints/fim_selection_ppo.zip``.
        deterministic: take the most likely action (default) rather than sample one.

    Raises:
        ValueError: the checkpoint or its JSON is missing or unreadable, or they disagree.
    """

    name = "ppo"

    def __init__(self, checkpoint: str | Path | None = None, deterministic: bool = True) -> None:
        from sb3_contrib import MaskablePPO  # deferred: keeps `import learned.agent` light

        self.checkpoint = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
        self.deterministic = deterministic
        if not self.checkpoint.is_file():
            raise ValueError(f"checkpoint {self.checkpoint} not found")
        self.metadata = load_metadata(self.checkpoint)
        try:
            model = MaskablePPO.load(self.checkpoint, device="cpu", custom_objects=_CUSTOM_OBJECTS)
        except Exception as exc:  # zip, pickle and torch errors alike
            raise ValueError(f"cannot load checkpoint {self.checkpoint}: {exc}") from exc
        policy = model.policy
        if not isinstance(policy, CandidateScoringPolicy):
            raise ValueError(
                f"checkpoint {self.checkpoint} holds a {type(policy).__name__}, "
                "expected a CandidateScoringPolicy"
            )
        layout = obs_layout(policy.observation_space)
        meta_layout = self.metadata["obs_layout"]
        if layout["whitened_dim"] != meta_layout["whitened_dim"]:
            raise ValueError(
                f"checkpoint {self.checkpoint}: the model's whitened width is "
                f"{layout['whitened_dim']} but its metadata says obs_layout "
                f"m={meta_layout['m']}, d={meta_layout['d']}, "
                f"whitened_dim={meta_layout['whitened_dim']}"
            )
        trained_n = meta_layout.get("n_candidates_trained", layout["n"])
        if trained_n != layout["n"]:
            raise ValueError(
                f"checkpoint {self.checkpoint}: the model's pool size is {layout['n']} but its "
                f"metadata says obs_layout n_candidates_trained={trained_n!r}"
            )
        env_id = self.metadata.get("env_id", FIM_ENV_ID)
        if env_id != FIM_ENV_ID:
            raise ValueError(
                f"checkpoint {self.checkpoint} was trained on {env_id!r}, not {FIM_ENV_ID!r}"
            )
        self.whitened_dim = layout["whitened_dim"]
        self._policies: dict[int, CandidateScoringPolicy] = {layout["n"]: policy}

    # -- shape checks and N-independent rebuilds ---------------------------------------------
    def _expected(self) -> str:
        lay = self.metadata["obs_layout"]
        return f"m={lay['m']}, d={lay['d']} (whitened_dim={lay['whitened_dim']}), 4 features"

    def check_space(self, observation_space: spaces.Space, env: Any = None) -> int:
        """Check ``observation_space`` against the checkpoint; return its pool size ``N``.

        Raises:
            ValueError: another whitened width or feature layout, naming both.
        """
        try:
            layout = obs_layout(observation_space)
        except ValueError as exc:
            raise ValueError(
                f"checkpoint {self.checkpoint} expects a FIMSelection observation with "
                f"{self._expected()}: {exc}"
            ) from exc
        if layout["whitened_dim"] != self.whitened_dim:
            actual = f"whitened_dim={layout['whitened_dim']}"
            base = getattr(env, "unwrapped", None)
            m, d = getattr(base, "m", None), getattr(base, "d", None)
            if m is not None and d is not None:
                actual = f"m={m}, d={d} ({actual})"
            raise ValueError(
                f"checkpoint {self.checkpoint} was trained on observations with "
                f"{self._expected()}; this env has {actual}"
            )
        return layout["n"]

    def policy_for(self, n: int) -> CandidateScoringPolicy:
        """The checkpoint's policy for a pool of ``n`` candidates (rebuilt once per new ``n``)."""
        if n not in self._policies:
            src = next(iter(self._policies.values()))
            params = src._get_constructor_parameters()
            lay = self.metadata["obs_layout"]
            obs_space = fim_observation_space(n, lay["m"], lay["d"])
            params.update(observation_space=obs_space, action_space=spaces.Discrete(n))
            policy = CandidateScoringPolicy(**params)
            policy.load_state_dict(src.state_dict())
            policy.set_training_mode(False)
            self._policies[n] = policy
        return self._policies[n]

    # -- Agent protocol ------------------------------------------------------------------------
    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Check the env's observation layout against the checkpoint (``ValueError`` if not)."""
        super().reset(env, seed)
        self.policy_for(self.check_space(env.observation_space, env))

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> int:
        """The policy's action with the env's mask (``info["action_mask"]``) applied."""
        n, width = np.shape(obs["whitened"])
        if width != self.whitened_dim:
            raise ValueError(
                f"checkpoint {self.checkpoint} expects {self._expected()}; "
                f"got an observation with whitened width {width}"
            )
        mask = np.asarray(info.get("action_mask", obs["action_mask"]), dtype=bool)
        action, _ = self.policy_for(n).predict(
            obs, action_masks=mask, deterministic=self.deterministic
        )
        return int(action)


def make_fim_ppo_agent(**kwargs: Any) -> SB3PolicyAgent:
    """Registry factory of the ``ppo`` agent (``checkpoint=``, ``deterministic=``)."""
    return SB3PolicyAgent(**kwargs)
