"""Multi-agent FIM measurement selection (PettingZoo ``ParallelEnv``).

Kirchner, Hespanha & Garagić (2020), Example 3 and "Cooperative Measurement Selection":
``n`` sensing agents each hold their own pool of camera/TOA/Doppler candidates and their own
channel budget ``B_i``. Every step, each agent that still has budget picks one candidate of its
own pool; all picks go to the fusion centre, whose information is
``FIM = Q0 + sum_i sum_{k in F_i} Q_k`` (eq. 2).

| | |
|---|---|
| Import | ``from selenv.multiagent import fim_selection_v0`` |
| API | ``fim_selection_v0.parallel_env(...)`` (native), ``fim_selection_v0.env(...)`` (AEC) |
| Agents | ``agent_0 ... agent_{n-1}`` (``n`` from the preset, 2 for ``example3``) |
| Action | ``Discrete(N_i)``: index into the agent's own pool (masked once selected) |
| Observation | ``Dict`` as in ``selenv/FIMSelection-v0`` over the agent's own pool |
| Reward | shared: the fusion centre's log-det gain over the step (nats) |

Modes (``mode=``):

* ``"independent"``: every agent with budget left picks each step, against its own
  ``Q0 + FIM(F_i)`` (no communication; Algorithm 1 run by every agent at once).
* ``"cooperative"``: the paper's cooperative selection. Agents take turns: ``agent_0`` spends
  its whole budget, then ``agent_1`` joins ``env.agents`` with the centre's FIM of every earlier
  pick as its prior (``FIM(F_1*)`` replaces ``Q0``), and so on. Only the agent whose turn it is
  is live; the others are not in ``env.agents`` yet (PettingZoo allows agents to join).
  :func:`selenv.agents.fim_solvers.cooperative_greedy` is the same scheme as a plain solver.

An agent whose budget is spent terminates and leaves ``env.agents``; the episode ends when all
have. ``infos[agent]`` holds ``objective`` (the centre's ``f``) and ``action_mask``.
A step must give an action for exactly the live agents; masked, out-of-range or missing
actions raise ``ValueError``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from selenv.core.information import LogDetGainState
from selenv.envs.fim_selection import (
    candidate_features,
    fim_observation,
    fim_observation_space,
    parse_action,
)
from selenv.scenarios.fim_selection import config_from, make_problem

__all__ = ["env", "parallel_env", "raw_env"]

MODES = ("independent", "cooperative")


class raw_env(ParallelEnv):
    """Parallel multi-agent FIM selection; see the module docstring for the manual.

    Args:
        preset: scenario preset (``"example3"``: two agents with camera + Doppler).
        n_candidates: candidates per sensor per agent.
        budgets: ``B_i``, one int for all agents or one per agent.
        mode: ``"independent"`` or ``"cooperative"``.
        n_agents: override the preset's number of agents.
        sensors: override the preset's sensors (same for every agent).
        randomize: draw a new geometry per reset.
        render_mode: must be ``None``.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        "name": "fim_selection_v0",
        "render_modes": [],
        "is_parallelizable": True,
    }

    def __init__(
        self,
        *,
        preset: str = "example3",
        n_candidates: int = 50,
        budgets: int | Sequence[int] = 5,
        mode: str = "cooperative",
        n_agents: int | None = None,
        sensors: Sequence[str] | None = None,
        randomize: bool = True,
        render_mode: str | None = None,
    ) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        overrides: dict[str, Any] = {"n_candidates": n_candidates, "randomize": randomize}
        if n_agents is not None:
            overrides["n_agents"] = n_agents
        if sensors is not None:
            overrides["sensors"] = tuple(sensors)
        self.config = config_from(preset, **overrides)
        self.mode = mode
        self.render_mode = None
        probe = make_problem(self.config, np.random.default_rng(0))
        n_ag = self.config.n_agents
        self.possible_agents = [f"agent_{i}" for i in range(n_ag)]
        self._pools = {a: probe.pool(i) for i, a in enumerate(self.possible_agents)}
        b = [budgets] * n_ag if isinstance(budgets, int | np.integer) else list(budgets)
        if len(b) != n_ag:
            raise ValueError(f"budgets must be an int or {n_ag} ints (one per agent), got {b}")
        self.budgets: dict[str, int] = {}
        for a, B in zip(self.possible_agents, b, strict=True):
            size = len(self._pools[a])
            if isinstance(B, bool) or not isinstance(B, int | np.integer) or not 1 <= B <= size:
                raise ValueError(f"budget of {a} must be an int in [1, {size}], got {B!r}")
            self.budgets[a] = int(B)
        _, m, d = probe.G.shape
        self._action_spaces = {a: spaces.Discrete(len(p)) for a, p in self._pools.items()}
        self._observation_spaces = {
            a: fim_observation_space(len(p), m, d) for a, p in self._pools.items()
        }
        self.agents: list[str] = []
        self._np_random: np.random.Generator | None = None

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        """The (fixed) observation space of ``agent``."""
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space[Any]:
        """The (fixed) action space of ``agent``."""
        return self._action_spaces[agent]

    def action_mask(self, agent: str) -> np.ndarray:
        """Boolean mask of ``agent``'s allowed actions."""
        return ~self._centre.selected[self._pools[agent]]

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Draw a new scenario (from ``seed`` if given) and clear every selection."""
        if seed is not None or self._np_random is None:
            self._np_random, _ = seeding.np_random(seed)
        self.problem = make_problem(self.config, self._np_random)
        P = self.problem
        coop = self.mode == "cooperative"
        self._centre = LogDetGainState(P.Q0, P.G, track_gains=coop, track_whitened=coop)
        self._own = (
            {}
            if coop
            else {
                a: LogDetGainState(P.Q0, P.G[p], track_gains=True, track_whitened=True)
                for a, p in self._pools.items()
            }
        )
        self._features = candidate_features(P)
        self._count = dict.fromkeys(self.possible_agents, 0)
        self.agents = self.possible_agents[:1] if coop else list(self.possible_agents)
        return (
            {a: self._obs(a) for a in self.agents},
            {a: self._info(a) for a in self.agents},
        )

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        """Apply every live agent's pick; the shared reward is the centre's log-det gain."""
        if not self.agents:
            raise RuntimeError("episode is over: call reset()")
        missing = set(self.agents) - set(actions)
        extra = set(actions) - set(self.agents)
        if missing or extra:
            raise ValueError(
                f"actions must hold exactly the live agents {self.agents}; "
                f"missing {sorted(missing)}, unexpected {sorted(extra)}"
            )
        picks = {
            a: parse_action(actions[a], len(self._pools[a]), self.action_mask(a), f"action of {a}")
            for a in self.agents
        }
        before = self._centre.objective
        for a, k in picks.items():
            self._centre.add(int(self._pools[a][k]))
            if self._own:
                self._own[a].add(k)
            self._count[a] += 1
        gain = self._centre.objective - before
        live = list(self.agents)
        terms = {a: self._count[a] >= self.budgets[a] for a in live}
        self.agents = [a for a in live if not terms[a]]
        if self.mode == "cooperative" and not self.agents:  # next agent's turn
            nxt = self.possible_agents.index(live[-1]) + 1
            if nxt < len(self.possible_agents):
                self.agents = [self.possible_agents[nxt]]
                live.append(self.agents[0])
                terms[self.agents[0]] = False
        obs = {a: self._obs(a) for a in live}
        rewards = dict.fromkeys(live, float(gain))
        truncs = dict.fromkeys(live, False)
        infos = {a: self._info(a) for a in live}
        return obs, rewards, terms, truncs, infos

    def _obs(self, agent: str) -> dict[str, np.ndarray]:
        pool = self._pools[agent]
        view = self._centre if self.mode == "cooperative" else self._own[agent]
        idx = pool if self.mode == "cooperative" else slice(None)
        assert view.gains is not None and view.Z is not None
        frac = 1.0 - self._count[agent] / self.budgets[agent]
        sel = self._centre.selected[pool]
        return fim_observation(view.gains[idx], view.Z[idx], sel, self._features[pool], frac)

    def _info(self, agent: str) -> dict[str, Any]:
        return {"objective": float(self._centre.objective), "action_mask": self.action_mask(agent)}


def parallel_env(**kwargs: Any) -> raw_env:
    """The native parallel env (see :class:`raw_env` for the keywords)."""
    return raw_env(**kwargs)


def env(**kwargs: Any) -> Any:
    """The AEC version (agents act in turn), converted with ``parallel_to_aec``."""
    return parallel_to_aec(raw_env(**kwargs))
