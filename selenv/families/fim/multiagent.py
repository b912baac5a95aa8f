"""Multi-agent FIM measurement selection (PettingZoo ``ParallelEnv``).

Kirchner, Hespanha & Garagić (2020), Example 3 and "Cooperative Measurement Selection":
``n`` sensing agents each hold their own pool of camera/TOA/Doppler candidates and their own
channel budget ``B_i``. Every step, each agent that still has budget picks one candidate of its
own pool; all picks go to the fusion centre, whose information is
``FIM = Q0 + sum_i sum_{k in F_i} Q_k`` (eq. 2).

| | |
|---|---|
| Import | ``from selenv.multiagent import fim_selection_v0`` |
| API | ``parallel_env(...)`` (native ``ParallelEnv``), ``env(...)`` (AEC with the standard |
| | wrappers), ``raw_env(...)`` (unwrapped AEC), as in PettingZoo's own parallel modules |
| Agents | ``agent_0 ... agent_{n-1}`` (``n`` from the preset, 2 for ``example3*``), all live |
| | from ``reset`` until the episode ends |
| Action | ``Discrete(N_i)``: index into the agent's own pool (masked once selected) |
| Observation | ``Dict`` as in ``selenv/FIMSelection-v1`` over the agent's own pool, plus |
| | ``on_turn (1,)``: 1 if the agent's pick counts this step |
| Reward | shared: the fusion centre's log-det gain over the step (nats) |
| State | ``Box``: centre gains and selection of every candidate, budgets left, turns |

Modes (``mode=``):

* ``"independent"``: every agent with budget left picks each step, against its own
  ``Q0 + FIM(F_i)`` (no communication; Algorithm 1 run by every agent at once).
* ``"cooperative"``: the paper's cooperative selection. Agents take turns: ``agent_0`` spends
  its whole budget, then ``agent_1`` picks with the centre's FIM of every earlier pick as its
  prior (``FIM(F_1*)`` replaces ``Q0``), and so on.
  :func:`selenv.agents.fim_solvers.cooperative_greedy` is the same scheme as a plain solver.

## Turns: every agent is present, waiting agents pass
Every agent stays in ``env.agents`` from ``reset`` until the episode ends, so the agent set
never changes (what SuperSuit's ``pettingzoo_env_to_vec_env_v1`` and most MARL trainers need;
``black_death_v3`` is not needed, and could not be used: it requires ``Box`` observations).
An agent **acts** when ``obs["on_turn"] == 1`` (``infos[agent]["on_turn"]``): in cooperative
mode the agent whose turn it is, in independent mode every agent with budget left. Any other
agent **waits**: its action is accepted and ignored (a no-op, not an invalid action), and its
``action_mask`` allows only action ``0``, so a masked policy passes with probability one and
contributes no gradient. The episode ends for all agents together when every budget is spent
(or at an invalid action with ``invalid_action="terminate"``).

## Invalid actions
A masked pick of an acting agent is handled by ``invalid_action`` (:mod:`selenv.envs.actions`):
``"noop"`` (default) spends that agent's budget slot without a pick
(``infos[agent]["invalid_action"]``, ``["invalid_code"]``; ``invalid_action_penalty`` is
added to that agent's reward), ``"raise"`` raises ``ValueError``, ``"terminate"`` ends the
episode for everyone (the offender's reward is the penalty, the others' 0). A step must give an
action for exactly the live agents; a missing one, a non-integer or an out-of-range action is
a ``ValueError`` / ``TypeError`` in every mode.

``infos[agent]`` holds ``objective`` (the centre's ``f``), ``on_turn`` and
``invalid_action``; the mask is ``obs[agent]["action_mask"]`` only (see Version History).
``render_mode="rgb_array"`` / ``"human"`` draws the centre's picture
(:class:`selenv.families.fim.env.FIMSelectionEnv`'s frame).

## Version History
* v0, since release 0.1: the same picks give the same gains (tested against 0.1's recorded
  episodes). The turn API changed under the same name: in 0.1 only the acting agent was in
  ``env.agents`` and rewarded (both agents at a change of turn); now every agent is present,
  waiting agents pass, ``on_turn`` is observed and every agent receives the team's step
  reward. Code written against 0.1's API needs the pass actions; a ``_v1`` name for this
  change was not introduced. Since release 0.2 the mask is observed only
  (``obs[agent]["action_mask"]``), no longer repeated in ``infos``: TorchRL's
  ``PettingZooWrapper`` reads a mask from the observation or the info, not both.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils import wrappers
from pettingzoo.utils.conversions import parallel_to_aec

from selenv.core.information import LogDetGainState
from selenv.envs.actions import INVALID_CODES, InvalidActionRule, check_discrete
from selenv.envs.conventions import KnownKeywords, check_render_mode
from selenv.envs.cycles import MaxCycles
from selenv.envs.rendering import Renderer
from selenv.families.fim.env import (
    candidate_features,
    check_sensors,
    fim_observation,
    fim_observation_space,
)
from selenv.families.fim.scenario import config_from, make_problem
from selenv.scenarios.validation import ArgumentTypeError, check_choice, check_integer, describe

__all__ = ["FIMSelectionParallelEnv", "env", "parallel_env", "raw_env"]

MODES = ("independent", "cooperative")


class FIMSelectionParallelEnv(MaxCycles, KnownKeywords, ParallelEnv):
    """Parallel multi-agent FIM selection; see the module docstring for the manual.

    Args:
        preset: scenario preset, a key of
            :data:`~selenv.families.fim.scenario.PRESETS`. Default ``"example3_moving"``:
            two agents with camera + Doppler and a moving target, the v0 benchmark (the
            earlier ``example3``, kept so v0 trajectories do not change); ``"example3"``
            is the paper's Example 3 (stationary target).
        n_candidates: candidates per sensor per agent.
        budgets: ``B_i``, one int for all agents or one per agent.
        mode: ``"independent"`` or ``"cooperative"``.
        n_agents: override the preset's number of agents.
        sensors: override the preset's sensors (same for every agent).
        randomize: draw a new geometry per reset.
        invalid_action: ``"noop"``, ``"raise"`` or ``"terminate"`` (module docstring).
        invalid_action_penalty: reward added for an invalid pick (float, default 0).
        render_mode: ``None``, ``"rgb_array"`` or ``"human"``.
        max_cycles: ``None`` (default: the episode ends as the env says) or an int ``N >= 1``:
            PettingZoo's cap, every live agent truncated after ``N`` parallel steps.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        "name": "fim_selection_v0",
        "render_modes": ["rgb_array", "human"],
        "render_fps": 4,
        "is_parallelizable": True,
        "invalid_codes": INVALID_CODES,
    }

    def __init__(
        self,
        *,
        preset: str = "example3_moving",
        n_candidates: int = 50,
        budgets: int | Sequence[int] = 5,
        mode: str = "cooperative",
        n_agents: int | None = None,
        sensors: Sequence[str] | None = None,
        randomize: bool = True,
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        max_cycles: int | None = None,
    ) -> None:
        self.render_mode = check_render_mode(render_mode, self.metadata)
        self._set_max_cycles(max_cycles)
        self.invalid_rule = InvalidActionRule(invalid_action, invalid_action_penalty)
        check_choice(mode, "mode", MODES)
        overrides: dict[str, Any] = {"n_candidates": n_candidates, "randomize": randomize}
        if n_agents is not None:
            overrides["n_agents"] = n_agents
        if sensors is not None:
            overrides["sensors"] = check_sensors(sensors)
        if not isinstance(budgets, int | np.integer | tuple | list) or isinstance(budgets, bool):
            raise ArgumentTypeError(
                f"budgets must be an int or a sequence of ints (one per agent), "
                f"got {describe(budgets)}"
            )
        self.config = config_from(preset, **overrides)
        self.mode = mode
        probe = make_problem(self.config, np.random.default_rng(0))
        n_ag = self.config.n_agents
        self.possible_agents = [f"agent_{i}" for i in range(n_ag)]
        self._pools = {a: probe.pool(i) for i, a in enumerate(self.possible_agents)}
        b = list(budgets) if isinstance(budgets, tuple | list) else [budgets] * n_ag
        if len(b) != n_ag:
            raise ValueError(f"budgets must be an int or {n_ag} ints (one per agent), got {b}")
        self.budgets: dict[str, int] = {}
        for i, (a, B) in enumerate(zip(self.possible_agents, b, strict=True)):
            size = len(self._pools[a])
            self.budgets[a] = check_integer(B, f"budgets[{i}] (budget of {a})", 1, size)
        _, m, d = probe.G.shape
        self._action_spaces: dict[str, spaces.Discrete] = {
            a: spaces.Discrete(len(p)) for a, p in self._pools.items()
        }
        self._observation_spaces: dict[str, spaces.Space[Any]] = {}
        for a, p in self._pools.items():
            space = fim_observation_space(len(p), m, d)
            space.spaces["on_turn"] = spaces.MultiBinary(1)
            self._observation_spaces[a] = space
        n_total = probe.G.shape[0]
        #: global state for centralised critics: centre gains (N,), selection (N,), budget left
        #: fraction (n_agents,), on-turn flags (n_agents,)
        self.state_space = spaces.Box(0.0, np.inf, (2 * n_total + 2 * n_ag,), np.float32)
        self.agents: list[str] = []
        self._np_random: np.random.Generator | None = None
        self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        """The (fixed) observation space of ``agent``."""
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space[Any]:
        """The (fixed) action space of ``agent``."""
        return self._action_spaces[agent]

    def on_turn(self, agent: str) -> bool:
        """Whether ``agent``'s pick counts this step (module docstring, "Turns")."""
        if self._count[agent] >= self.budgets[agent]:
            return False
        if self.mode == "independent":
            return True
        first = next(a for a in self.possible_agents if self._count[a] < self.budgets[a])
        return agent == first

    def action_mask(self, agent: str) -> np.ndarray:
        """Boolean mask of ``agent``'s allowed actions (only ``0`` while it waits)."""
        if not self.on_turn(agent):
            mask = np.zeros(len(self._pools[agent]), bool)
            mask[0] = True
            return mask
        return ~self._centre.selected[self._pools[agent]]

    def state(self) -> np.ndarray:
        """Global state (see ``state_space``) as one float32 array."""
        c = self._centre
        assert c.gains is not None  # tracked by construction
        gains = c.gains
        left = [1.0 - self._count[a] / self.budgets[a] for a in self.possible_agents]
        turn = [float(self.on_turn(a)) for a in self.possible_agents]
        return np.concatenate([np.where(c.selected, 0.0, gains), c.selected, left, turn]).astype(
            np.float32
        )

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Draw a new scenario (from ``seed`` if given) and clear every selection."""
        if seed is not None or self._np_random is None:
            self._np_random, _ = seeding.np_random(seed)
        self.problem = make_problem(self.config, self._np_random)
        P = self.problem
        coop = self.mode == "cooperative"
        # gains always tracked: the global state() shows the centre's gains in both modes
        self._centre = LogDetGainState(P.Q0, P.G, track_gains=True, track_whitened=coop)
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
        self.agents = list(self.possible_agents)
        self._start_cycles()
        return (
            {a: self._obs(a) for a in self.agents},
            {a: self._info(a) for a in self.agents},
        )

    def _step_once(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        """Apply the acting agents' picks; the shared reward is the centre's log-det gain."""
        if not self.agents:
            raise RuntimeError("episode is over: call reset()")
        missing = set(self.agents) - set(actions)
        extra = set(actions) - set(self.agents)
        if missing or extra:
            raise ValueError(
                f"actions must hold exactly the live agents {self.agents}; "
                f"missing {sorted(missing)}, unexpected {sorted(extra)}"
            )
        rule = self.invalid_rule
        picks: dict[str, int] = {}
        reasons: dict[str, str] = {}
        for a in self.agents:
            k = check_discrete(actions[a], len(self._pools[a]), f"action of {a}")
            if not self.on_turn(a):
                continue  # waiting: accepted and ignored
            if self._centre.selected[self._pools[a][k]]:
                reasons[a] = f"masked: candidate {k} of {a}'s pool is already selected"
                rule.check(f"action {k} of {a}", reasons[a])
            else:
                picks[a] = k
        live = list(self.agents)
        if reasons and rule.terminates:
            self.agents = []
            rewards = {a: rule.penalty if a in reasons else 0.0 for a in live}
            return self._result(live, rewards, dict.fromkeys(live, True), reasons)
        before = self._centre.objective
        for a in live:
            if a in picks:
                self._centre.add(int(self._pools[a][picks[a]]))
                if self._own:
                    self._own[a].add(picks[a])
            if a in picks or a in reasons:
                self._count[a] += 1
        gain = float(self._centre.objective - before)
        done = all(self._count[a] >= self.budgets[a] for a in live)
        if done:
            self.agents = []
        rewards = {a: gain + (rule.penalty if a in reasons else 0.0) for a in live}
        return self._result(live, rewards, dict.fromkeys(live, done), reasons)

    def _result(
        self,
        live: list[str],
        rewards: dict[str, float],
        terms: dict[str, bool],
        reasons: dict[str, str],
    ) -> tuple[dict[str, Any], ...]:
        obs = {a: self._obs(a) for a in live}
        truncs = dict.fromkeys(live, False)
        infos = {a: self._info(a, reasons.get(a)) for a in live}
        return obs, rewards, terms, truncs, infos

    def render(self) -> np.ndarray | None:
        """The fusion centre's frame (``render_mode`` ``"rgb_array"``: ``(H, W, 3)`` uint8)."""
        c, problem = self._centre, self.problem
        title = f"fim_selection_v0 ({self.mode})"
        from selenv.families.fim.rendering import draw_fim_selection  # matplotlib: first frame

        return self._renderer.render(
            lambda fig: draw_fim_selection(fig, problem, c.selected, c.information, title)
        )

    def close(self) -> None:
        """Close the render window, if any."""
        self._renderer.close()

    def _obs(self, agent: str) -> dict[str, np.ndarray]:
        pool = self._pools[agent]
        view = self._centre if self.mode == "cooperative" else self._own[agent]
        idx = pool if self.mode == "cooperative" else slice(None)
        assert view.gains is not None and view.Z is not None
        frac = 1.0 - self._count[agent] / self.budgets[agent]
        sel = self._centre.selected[pool]
        obs = fim_observation(view.gains[idx], view.Z[idx], sel, self._features[pool], frac)
        obs["action_mask"] = self.action_mask(agent).astype(np.int8)
        obs["on_turn"] = np.array([self.on_turn(agent)], np.int8)
        return obs

    def _info(self, agent: str, reason: str | None = None) -> dict[str, Any]:
        return {
            "objective": float(self._centre.objective),
            "on_turn": self.on_turn(agent),
            **InvalidActionRule.info(reason),
        }


def parallel_env(**kwargs: Any) -> FIMSelectionParallelEnv:
    """The native ``ParallelEnv`` (keywords: :class:`FIMSelectionParallelEnv`)."""
    return FIMSelectionParallelEnv(**kwargs)


def raw_env(**kwargs: Any) -> AECEnv:
    """The unwrapped AEC version (agents act in turn), via ``parallel_to_aec``."""
    return parallel_to_aec(parallel_env(**kwargs))


def env(**kwargs: Any) -> AECEnv:
    """The AEC version with PettingZoo's standard wrappers (bounds check, call order)."""
    aec = wrappers.AssertOutOfBoundsWrapper(raw_env(**kwargs))
    return wrappers.OrderEnforcingWrapper(aec)
