"""PettingZoo -> SB3 with parameter sharing: a multi-agent env played turn by turn by one policy.

SB3 trains single-agent ``gymnasium`` envs. :class:`SharedPolicyEnv` turns a PettingZoo
``ParallelEnv`` whose agents share one observation / action space into one: each Gymnasium
step is **one acting agent's** decision, the agents taking their turns in the order of
``penv.agents``. Agents that wait this round (``infos[agent]["on_turn"]`` false, as in
``fim_selection_v0``) are not asked: they pass with action ``0``, and the ``on_turn`` key is
dropped from the observations (every observation shown is an acting agent's). When every
acting agent of the round has decided, the joint action goes to ``penv.step``. (For the
SuperSuit route, where every agent is a vector-env slot, see docs/guide/multi_agent.md.) The same
network therefore acts for every agent (parameter sharing; the agent's own observation is all it
sees), and MaskablePPO trains it unchanged::

    from selenv.multiagent import fim_selection_v0
    env = SharedPolicyEnv(fim_selection_v0.parallel_env(mode="cooperative"))
    model = make_maskable_ppo(env)       # selenv.learned.rl.candidate_policy

Reward: the team reward of the joint step (shared rewards: the fusion centre's log-det gain)
on the Gymnasium step that completes the round, 0 on the others; the episode return is the
team return. Observations within a round are those of the round's start (simultaneous moves).
``info["objective"]`` and ``info["action_mask"]`` are the current agent's; ``info["agent"]``
names it. :meth:`SharedPolicyEnv.action_masks` serves MaskablePPO.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv

__all__ = ["MARL_FIM_ID", "SharedPPOPolicy", "SharedPolicyEnv", "make_shared_ppo"]

MARL_FIM_ID = "selenv.multiagent.fim_selection_v0"


class SharedPolicyEnv(gym.Env[dict[str, np.ndarray], np.int64]):
    """A ``ParallelEnv`` with homogeneous agents as a turn-based single-agent env.

    Args:
        penv: the PettingZoo parallel env; every agent must have the same observation and
            action spaces (checked).

    Raises:
        ValueError: agents with different spaces (parameter sharing needs one space).
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012

    def __init__(self, penv: ParallelEnv) -> None:
        self.penv = penv
        agents = list(penv.possible_agents)
        obs_spaces = [penv.observation_space(a) for a in agents]
        act_spaces = [penv.action_space(a) for a in agents]
        if any(s != obs_spaces[0] for s in obs_spaces) or any(
            s != act_spaces[0] for s in act_spaces
        ):
            raise ValueError(
                "parameter sharing needs one observation and action space for all agents; "
                f"got {dict(zip(agents, obs_spaces, strict=True))}"
            )
        space = obs_spaces[0]
        if isinstance(space, gym.spaces.Dict) and "on_turn" in space.spaces:
            space = gym.spaces.Dict({k: v for k, v in space.spaces.items() if k != "on_turn"})
        self.observation_space = space
        self.action_space = act_spaces[0]
        self._obs: dict[str, Any] = {}
        self._infos: dict[str, Any] = {}
        self._pending: dict[str, int] = {}
        self._turn: list[str] = []

    def _acting(self) -> list[str]:
        """The live agents that act this round (the others pass with action 0)."""
        live = list(self.penv.agents)
        acting = [a for a in live if self._infos.get(a, {}).get("on_turn", True)]
        self._pending = {a: 0 for a in live if a not in acting}
        return acting

    def _view(self, obs: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in obs.items() if k != "on_turn"}

    @property
    def agent(self) -> str:
        """The agent whose decision the current observation is for."""
        return self._turn[0]

    def _info(self) -> dict[str, Any]:
        info = dict(self._infos.get(self.agent, {}))
        info["agent"] = self.agent
        info["action_mask"] = self.action_masks()
        return info

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Reset the multi-agent env; the first live agent decides first."""
        super().reset(seed=seed)
        self._obs, self._infos = self.penv.reset(seed=seed, options=options)
        self._turn = self._acting()
        return self._view(self._obs[self.agent]), self._info()

    def action_masks(self) -> np.ndarray:
        """The current agent's mask."""
        return np.asarray(self._obs[self.agent]["action_mask"], dtype=bool)

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Record the current agent's action; step the multi-agent env when the round is full."""
        if not self._turn:
            raise RuntimeError("step() called after the episode ended; call reset()")
        self._pending[self._turn.pop(0)] = int(action)
        reward, terminated, truncated = 0.0, False, False
        if not self._turn:  # the round is complete: one joint step
            obs, rewards, terms, truncs, infos = self.penv.step(self._pending)
            self._pending = {}
            reward = float(np.mean(list(rewards.values()))) if rewards else 0.0
            self._obs.update(obs)
            self._infos.update(infos)
            self._turn = self._acting() if self.penv.agents else []
            if not self._turn:
                terminated = any(terms.values()) or not any(truncs.values())
                truncated = not terminated
                last = next(iter(obs)) if obs else None
                info = dict(infos.get(last, {})) if last is not None else {}
                obs_last = obs[last] if last is not None else self.observation_space.sample()
                return self._view(obs_last), reward, terminated, truncated, info
        return self._view(self._obs[self.agent]), reward, terminated, truncated, self._info()


class SharedPPOPolicy:
    """The shared (parameter-sharing) policy as a PettingZoo agent of ``selenv bench``.

    Registered as ``ppo`` for ``selenv.multiagent.fim_selection_v0``: every acting agent
    (``infos[agent]["on_turn"]``) takes the checkpoint's deterministic action on **its own**
    observation (``on_turn`` dropped, as :class:`SharedPolicyEnv` shows it during training),
    through :class:`~selenv.learned.rl.lean.LeanScorer`; waiting agents pass with 0. So it is
    decentralised exactly like the ``greedy`` floor (same information per agent), unlike the
    centralised references.

    Args:
        checkpoint: SB3 zip + JSON (default ``checkpoints/fim_marl_ppo.zip``), loaded without
            unpickling (:mod:`selenv.learned.rl.safe_load`).

    Raises:
        ValueError: the checkpoint was trained on another env, or its per-candidate width
            differs from the env's.
    """

    name = "ppo"

    def __init__(self, checkpoint: str | Path | None = None) -> None:
        from selenv.learned.rl.agent import CHECKPOINT_DIR, load_metadata
        from selenv.learned.rl.lean import LeanScorer
        from selenv.learned.rl.safe_load import load_policy

        path = CHECKPOINT_DIR / "fim_marl_ppo.zip" if checkpoint is None else checkpoint
        self.checkpoint = str(path)
        self.metadata = load_metadata(path)
        if self.metadata.get("env_id") != MARL_FIM_ID:
            raise ValueError(
                f"checkpoint {path} was trained on {self.metadata.get('env_id')!r}, "
                f"not {MARL_FIM_ID!r}"
            )
        self.scorer = LeanScorer(load_policy(path, self.metadata))
        self.width = int(self.metadata["obs_layout"]["whitened_dim"])

    def reset(self, env: Any, seed: int | None = None) -> None:
        """Start an episode; checks the env's per-candidate width against the checkpoint."""
        self.env = env
        self.rng = np.random.default_rng(seed)
        width = env.observation_space(env.possible_agents[0])["whitened"].shape[1]
        if width != self.width:
            raise ValueError(
                f"checkpoint {self.checkpoint} expects whitened width {self.width}; "
                f"this env has {width}"
            )

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """The policy's action for each acting agent, 0 for the waiting ones."""
        out: dict[str, Any] = {}
        for a in self.env.agents:
            if not infos.get(a, {}).get("on_turn", True):
                out[a] = 0
                continue
            obs = {k: v for k, v in observations[a].items() if k != "on_turn"}
            mask = np.asarray(infos.get(a, {}).get("action_mask", obs["action_mask"]), bool)
            out[a] = self.scorer.action(obs, mask)
        return out


def make_shared_ppo(shipped: str | None = None, **kwargs: Any) -> SharedPPOPolicy:
    """Registry factory of the multi-agent ``ppo`` agents (``checkpoint=``).

    Args:
        shipped: file name of a shipped checkpoint in ``checkpoints/`` (``ppo_independent``);
            ``checkpoint=`` then must not be given.
        **kwargs: keyword arguments of :class:`SharedPPOPolicy`.

    Raises:
        ValueError: ``shipped`` is not a plain file name, or both are given.
    """
    from selenv.learned.resources import with_shipped

    return SharedPPOPolicy(**with_shipped(shipped, kwargs))
