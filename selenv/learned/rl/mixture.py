"""One training env that plays another configuration of the same env id each episode.

A policy meant to generalise across presets and budgets (the ``invariant`` view of
``FIMSelection``) is trained on :class:`EnvMixture`: it holds one env per configuration, each in
the same candidate view, and at every ``reset`` draws the configuration and the inner episode's
seed from its own ``np_random``. Same seed, same sequence of configurations and episodes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from selenv.learned.rl.views import CandidateView, view_for
from selenv.untrusted import NotParsedError, loads_json

__all__ = ["MIXTURES", "EnvMixture", "parse_mixture"]

#: named mixtures: the Kirchner presets at a pool of 200 candidates (``n_candidates`` is per
#: sensor and agent), each with budgets 5, 10, 15 and 20 -- 24 configurations
MIXTURES: dict[str, list[dict[str, Any]]] = {
    "kirchner_presets": [
        {"preset": preset, "n_candidates": n, "budget": budget}
        for preset, n in (
            ("example1", 200),
            ("example2", 100),
            ("example3", 50),
            ("example1_moving", 200),
            ("example2_moving", 100),
            ("example3_moving", 50),
        )
        for budget in (5, 10, 15, 20)
    ]
}


def parse_mixture(text: str) -> list[dict[str, Any]]:
    """A mixture from ``--mixture``: a name of :data:`MIXTURES` or a JSON list of objects.

    Raises:
        ValueError: neither a known name nor a non-empty JSON list of objects (the message
            names the known mixtures).
    """
    if text in MIXTURES:
        return [dict(c) for c in MIXTURES[text]]
    try:  # size and nesting bounded before parsing
        value = loads_json(text, "--mixture")
    except NotParsedError:
        value = None
    if not isinstance(value, list) or not value or not all(isinstance(c, dict) for c in value):
        raise ValueError(
            f"--mixture must be one of {sorted(MIXTURES)} or a non-empty JSON list of "
            f"objects of env keywords, got {text!r:.120}"
        )
    return value


class EnvMixture(gym.Env[dict[str, np.ndarray], np.int64]):
    """Each episode one of ``configs`` (uniformly), in candidate view ``view``.

    Args:
        env_id: a registered id with candidate views.
        configs: keyword arguments of ``gymnasium.make(env_id, ...)``, one per configuration.
        view: the candidate view applied to every configuration; its space must be the same
            for all of them (same pool size and width).

    ``info["mixture_index"]`` is the configuration of the episode.

    Raises:
        ValueError: no configuration, or two configurations whose views disagree (the
            message names both).
    """

    metadata = {"render_modes": []}  # noqa: RUF012  (Gymnasium declares it per instance)

    def __init__(self, env_id: str, configs: Sequence[dict[str, Any]], view: str) -> None:
        if not configs:
            raise ValueError("configs: expected at least one configuration")
        self.configs = [dict(c) for c in configs]
        self.envs = [gym.make(env_id, **c) for c in self.configs]
        self.views: list[CandidateView] = [view_for(env_id, e, view) for e in self.envs]
        spaces_ = [v.space(e.observation_space) for v, e in zip(self.views, self.envs, strict=True)]
        for c, sp, env in zip(self.configs, spaces_, self.envs, strict=True):
            if sp != spaces_[0] or env.action_space != self.envs[0].action_space:
                raise ValueError(
                    f"configs: {c} gives the observation space {sp} and actions "
                    f"{env.action_space} in view {view!r}, but {self.configs[0]} gives "
                    f"{spaces_[0]} and {self.envs[0].action_space}; every configuration "
                    "needs the same pool size and view width"
                )
        self.observation_space: spaces.Dict = spaces_[0]
        self.action_space = self.envs[0].action_space
        self.current = 0
        self._raw: dict[str, np.ndarray] | None = None

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Draw the configuration and the inner seed from ``np_random``; reset that env."""
        super().reset(seed=seed)
        self.current = int(self.np_random.integers(len(self.envs)))
        inner_seed = int(self.np_random.integers(2**31 - 1))
        raw, info = self.envs[self.current].reset(seed=inner_seed, options=options)
        self._raw = raw
        return self.views[self.current](raw), {**info, "mixture_index": self.current}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Step the episode's env with the candidate ``action`` (mapped by its view)."""
        if self._raw is None:
            raise ValueError("call reset() before step()")
        view = self.views[self.current]
        raw, reward, terminated, truncated, info = self.envs[self.current].step(
            view.env_action(self._raw, int(action))
        )
        self._raw = raw
        return view(raw), float(reward), terminated, truncated, info

    def action_masks(self) -> np.ndarray:
        """The episode's env's mask (MaskablePPO reads it through the VecEnv)."""
        base = self.envs[self.current].unwrapped
        return np.asarray(base.action_masks(), dtype=bool)  # type: ignore[attr-defined]

    def close(self) -> None:  # noqa: D102
        for env in self.envs:
            env.close()
