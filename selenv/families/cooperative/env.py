"""``selenv/CLScheduling-v1``: which relative measurements to process (cooperative localization)."""

from __future__ import annotations

import dataclasses
from itertools import permutations
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from selenv.core.linalg import logdet_spd
from selenv.core.objectives import get_objective, objective_names
from selenv.envs.actions import INVALID_CODES, InvalidActionRule, check_discrete
from selenv.envs.conventions import (
    EpisodeLengthSpec,
    check_known_keywords,
    check_render_mode,
    named_parameters,
)
from selenv.envs.rendering import Renderer
from selenv.families.cooperative import batched
from selenv.families.cooperative.scenario import (
    FUSION_METHODS,
    MAX_AGENTS,
    CLConfig,
    CLProblem,
    CLSimulation,
    check_learned_fusion,
    make_cl_problem,
)
from selenv.scenarios.validation import check_choice, check_integer

__all__ = [
    "OBJECTIVES",
    "PRESETS",
    "TOPOLOGIES",
    "CLSchedulingEnv",
    "agent_objective",
    "relative_pairs",
]

#: the objectives the presets use (every registered one is accepted: ``objective_names()``)
OBJECTIVES = ("logdet", "trace")
TOPOLOGIES = ("all", "chain")

#: a mixed team: tracks and input noise cycled over the agents, links every step
_TEAM: dict[str, Any] = {
    "topology": "all",
    "relative_every": 1,
    "tracks": ("rectangle", "circle", "lemniscate"),
    "input_sigma": ((0.02, 0.05), (0.06, 0.2)),
}

#: Named configurations: env keywords and :class:`CLConfig` fields. Explicit keywords override
#: the preset's values. ``"benchmark"`` is the default (see the class docstring for why).
PRESETS: dict[str, dict[str, Any]] = {
    "benchmark": {**_TEAM, "n_agents": 6, "budget": 1, "horizon": 60, "objective": "trace"},
    # the configuration of v0 before the benchmark preset: decisions barely matter
    "dense": {**_TEAM, "n_agents": 4, "budget": 2, "horizon": 200, "objective": "logdet"},
    # Chen & Kia's two pedestrians (CLConfig defaults), both pairs processed
    "paper": {"n_agents": 2, "budget": 2, "horizon": 600, "objective": "logdet", "topology": "all"},
}


def agent_objective(P: np.ndarray, objective: str) -> np.ndarray:
    """Each agent's term of the objective: ``log det P_i`` or ``tr P_i[:2, :2]`` (m^2).

    ``P`` is ``(..., n, n)``; returns ``(...)``. The env's objective is the sum over agents. A
    unit-invariant registered objective (``logdet``, ``det``) scores the whole state; any other
    (``trace``, ``max_eig``, the user's own) the horizontal position block ``P_i[:2, :2]``.

    Raises:
        TypeError, ValueError: ``objective`` not a registered name.
    """
    obj = get_objective(objective)
    if obj.name == "logdet":
        return np.asarray(logdet_spd(P, "P"))
    return obj.value(P if obj.unit_invariant else P[..., :2, :2])


def relative_pairs(n_agents: int, topology: str) -> tuple[tuple[int, int], ...]:
    """Directed measurement pairs ``(i, j)`` (``i`` measures ``j``) of a link topology.

    ``"all"``: every ordered pair; ``"chain"``: neighbours ``i, i + 1`` both ways (a column
    walking through a corridor, each agent in radio / line-of-sight range of its neighbours).
    """
    check_choice(topology, "topology", TOPOLOGIES)
    n_agents = check_integer(n_agents, "n_agents", 1, MAX_AGENTS)
    if topology == "all":
        return tuple(permutations(range(n_agents), 2))
    fwd = [(i, i + 1) for i in range(n_agents - 1)]
    return tuple(fwd + [(j, i) for i, j in fwd])


class CLSchedulingEnv(EpisodeLengthSpec, gym.Env[dict[str, np.ndarray], np.int64]):
    r"""Schedule relative-measurement processing under a budget in cooperative localization.

    ## Description
    ``n_agents`` walkers localise with local filters (Chen & Kia 2022 setting, see
    :mod:`selenv.families.cooperative.scenario`); agent 0 ranges to beacons. Every step each
    directed
    pair ``(i, j)`` can yield a relative range that agent ``i`` would process with agent ``j``'s
    belief using the ``fusion`` method (``naive``, ``ci``, ``dmv``, ``pecmv``, or the learned
    ``ldmv``, ``lpecmv``, ``lpecmv_full``, ``lpecmv_objective``: the shipped surrogate
    trained for the scenario's noise, range only or range + bearing at
    ``bearing_sigma_deg=2``, else a ``ValueError`` naming ``fusion`` and
    ``bearing_sigma_deg``) without the cross-covariance. A processing budget
    allows only ``budget`` of them per step: the agent picks them one at a time, or stops early.

    ## Presets
    ``preset="benchmark"`` (default): a cold start of six pedestrians with ZUPT-aided INS on
    rectangle / circle / lemniscate tracks: 60 filter steps (6 s at 10 Hz) from the initial
    uncertainty, only ``agent_0`` ranging to the two beacons (the others drift between
    relative updates), every directed pair measurable every step, but a processing and
    communication budget of **one** relative update per step; the objective is the team's
    horizontal position MSE (``"trace"``: sum of the agents' horizontal position variances),
    which is what localization is for. Here the decision matters: on 30 held-out seeds greedy
    gets a clearly larger return than random, and the non-myopic ``rollout`` agent beats greedy
    on every seed (docs/benchmarks/references.md; on longer episodes its edge fades: tied at
    100 steps, behind at 200). ``preset="dense"`` is the v0
    configuration before this preset (four agents, budget two, ``log det`` over all states),
    where random scheduling gets 99.7 % of greedy's return; ``preset="paper"`` Chen & Kia's two
    pedestrians (:class:`~selenv.families.cooperative.scenario.CLConfig` defaults, relative ranges
    every fifth step, both processed). Explicit keywords override a preset's values.

    ## Action Space
    ``Discrete(P + 1)`` with ``P = n_agents (n_agents - 1)`` directed pairs (the order of
    ``env.unwrapped.pairs``): pick pair ``p``, or ``P`` = stop processing for this step.
    Pairs already processed this step, or without a measurement now, are masked
    (:meth:`action_masks`, ``info["action_mask"]``, ``obs["action_mask"]``; stop is always
    allowed). A masked pair is handled by ``invalid_action`` (:mod:`selenv.envs.actions`):
    ``"noop"`` (default) spends one of the step's ``budget`` slots without processing
    anything, ``"raise"`` raises ``ValueError``, ``"terminate"`` ends the episode. A
    non-integer or out-of-range action is a ``TypeError`` / ``ValueError`` in every mode.

    ## Observation Space
    ``Dict``: ``logdet (A,)`` each agent's ``log det P``, ``pos_std (A,)`` its horizontal
    position std (m), ``pair_gain (P,)`` the naive-EKF information gain of each pair now
    (``log det(I + H_i P_i H_i^T (H_j P_j H_j^T + R)^-1)``, a cheap proxy, 0 when masked),
    ``budget_left (1,)``, ``time (1,)``, ``action_mask (P + 1,)``.

    ## Rewards
    The decrease of the objective (``objective="logdet"``: the sum over agents of
    ``log det P``; ``"trace"``: the sum of the horizontal position variances) caused by the
    step: the processed pair's update, plus, on the action that ends a filter step, the change
    from the next propagation and its ZUPT and beacon updates. Rewards telescope: the return
    is the objective at the first step minus the final one, so maximising it minimises the
    final uncertainty. ``info["objective"]`` is the objective now (lower is better); the
    other keys, the same with the same shapes at every step: ``k``, ``position_errors (A,)``
    (m), ``processed (P,)`` bool (the pairs processed in the open filter step),
    ``action_mask (P + 1,)``, ``invalid_action`` and ``invalid_code``
    (:data:`~selenv.envs.actions.INVALID_CODES`).

    ## Starting State
    A new seeded realisation per reset (input, measurement noise and initial errors); tracks
    are rectangles, circles and lemniscates cycled over the agents; the first step is
    propagated.

    ## Episode End
    Terminates after ``horizon`` filter steps, or at an invalid action with
    ``invalid_action="terminate"``. A filter step takes 1 to ``budget`` env steps (a stop
    ends it early), so an episode has at most ``budget * horizon`` steps
    (``env.spec.max_episode_steps``, an upper bound). Never truncates.

    ## Rendering
    ``render_mode="rgb_array"`` or ``"human"``: each agent's true and estimated position with
    its 2-sigma ellipse, the beacons, and the links processed in the current step.

    ## Arguments
    ``gymnasium.make("selenv/CLScheduling-v1", preset="benchmark", n_agents=None,
    budget=None, fusion="dmv", horizon=None, objective=None, topology=None, model="ins",
    invalid_action="noop", invalid_action_penalty=0.0, render_mode=None)``; ``None`` takes the
    preset's value (benchmark: 6 agents, budget 1, horizon 60, ``"trace"``, ``"all"``).
    ``topology``: ``"all"`` directed pairs or ``"chain"`` (neighbours only); or give
    ``relative_pairs`` directly. Other :class:`~selenv.families.cooperative.scenario.CLConfig`
    fields
    pass through (their ranges are in its docstring: e.g. ``dt`` in ``[1e-3, 1]`` s,
    ``range_sigma`` in ``[1e-3, 100]`` m, ``horizon`` in ``[1, 100000]``). ``n_agents`` is an
    int in ``[2, 32]``, ``budget`` an int in ``[1, P]``.

    An unknown keyword raises ``TypeError`` ("got an unexpected keyword argument ...; known:
    [...]"); a known keyword with a value of the wrong type a ``TypeError`` naming it and the
    expected type and range (e.g. "dt must be a real number in [0.001, 1] s, got 'x'"); a value
    out of range a ``ValueError`` naming it and the range.

    ## Vector Env
    ``gymnasium.make_vec("selenv/CLScheduling-v1", num_envs=B, **kwargs)`` returns the native
    :class:`~selenv.families.cooperative.vector.CLSchedulingVectorEnv`: the filters of all
    ``B`` sub-envs in arrays with a leading batch axis, stepped together by the batched core
    :mod:`selenv.families.cooperative.batched` (which this env calls with one realisation).
    Sub-env ``b`` replays this env reset with seed ``s + b`` under the same actions
    (Gymnasium ``NEXT_STEP`` autoreset); ``action_masks()`` is ``(B, P + 1)``.
    ``vectorization_mode="sync"`` still gives the loop over single envs.

    ## Version History
    * v1: the default configuration is ``preset="benchmark"`` (6 agents, budget 1, horizon
      60, trace); ``invalid_action`` modes, rendering, presets, ``topology`` and every
      registered ``objective``.
    * v0: release 0.1 (4 agents, budget 2, horizon 200, log det): ``CLScheduling-v0`` is this
      class with ``preset="dense"`` by default, replaying 0.1's episodes (tested against
      recordings); deprecated in favour of v1.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "invalid_codes": INVALID_CODES,
    }

    def __init__(
        self,
        *,
        preset: str = "benchmark",
        n_agents: int | None = None,
        budget: int | None = None,
        fusion: str = "dmv",
        horizon: int | None = None,
        objective: str | None = None,
        topology: str | None = None,
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        **config: Any,
    ) -> None:
        fields = {f.name for f in dataclasses.fields(CLConfig)}
        check_known_keywords(
            config,
            fields - {"n_agents", "horizon"},
            "CLScheduling-v1",
            named_parameters(type(self)),
        )
        self.render_mode = check_render_mode(render_mode, self.metadata)
        self.invalid_rule = InvalidActionRule(invalid_action, invalid_action_penalty)
        self.preset = check_choice(preset, "preset", sorted(PRESETS))
        given: dict[str, Any] = {"n_agents": n_agents, "budget": budget, "horizon": horizon}
        given |= {"objective": objective, "topology": topology}
        merged = {**PRESETS[preset], **{k: v for k, v in given.items() if v is not None}, **config}
        n_agents, budget, horizon = (
            merged.pop("n_agents"),
            merged.pop("budget"),
            merged.pop("horizon"),
        )
        objective, topology = merged.pop("objective"), merged.pop("topology")
        check_choice(fusion, "fusion", FUSION_METHODS[1:])
        check_choice(objective, "objective", objective_names())
        budget = check_integer(budget, "budget", 1)
        n_agents = check_integer(n_agents, "n_agents (relative measurements need 2)", 2, MAX_AGENTS)
        if "relative_pairs" in config and given["topology"] is not None:
            raise ValueError("give topology or relative_pairs, not both")
        if "relative_pairs" not in config:
            merged["relative_pairs"] = relative_pairs(n_agents, topology)
        self.topology: str | None = None if "relative_pairs" in config else topology
        self.config = CLConfig(n_agents=n_agents, horizon=horizon, **merged)
        check_learned_fusion(self.config, fusion)  # ldmv / lpecmv: a surrogate for this noise
        self.pairs: tuple[tuple[int, int], ...] = self.config.relative_pairs
        self._pair_index = np.asarray(self.pairs, dtype=np.intp).reshape(-1, 2)
        #: (bytes of sim.P, log det P_i per agent, their sum as a float)
        self._logdet_cache: tuple[bytes, np.ndarray, float] | None = None
        self.n_pairs = len(self.pairs)
        if self.n_pairs == 0:
            raise ValueError("relative_pairs must hold at least one (i, j) pair to schedule")
        check_integer(budget, f"budget (pairs processed per step; {self.n_pairs} pairs)", 1,
                      self.n_pairs)  # fmt: skip
        self.budget, self.fusion, self.objective = int(budget), fusion, objective
        self.horizon = int(horizon)
        self.max_episode_steps = self.budget * self.horizon
        A = int(n_agents)
        self.action_space = spaces.Discrete(self.n_pairs + 1)
        self.observation_space = spaces.Dict(  # type: ignore[assignment, unused-ignore]
            {
                "logdet": spaces.Box(-np.inf, np.inf, (A,), np.float32),
                "pos_std": spaces.Box(0.0, np.inf, (A,), np.float32),
                "pair_gain": spaces.Box(0.0, np.inf, (self.n_pairs,), np.float32),
                "budget_left": spaces.Box(0.0, 1.0, (1,), np.float32),
                "time": spaces.Box(0.0, 1.0, (1,), np.float32),
                "action_mask": spaces.MultiBinary(self.n_pairs + 1),
            }
        )
        self.problem: CLProblem | None = None
        self._sim: CLSimulation | None = None
        self._done_pairs: set[int] = set()
        self._available: list[int] = []
        self._slots = 0
        self._done = False
        self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])

    # -- oracle view -------------------------------------------------------------------------
    @property
    def sim(self) -> CLSimulation:
        """The simulation (needs ``reset``)."""
        if self._sim is None:
            raise RuntimeError("call reset() before using the environment")
        return self._sim

    @property
    def budget_left(self) -> int:
        """Pairs that may still be processed in this step (an invalid no-op spends a slot)."""
        return self.budget - self._slots

    def action_masks(self) -> np.ndarray:
        """(P + 1,) bool: available, unprocessed pairs; stop is always allowed."""
        mask = np.zeros(self.n_pairs + 1, bool)
        if self.budget_left > 0:
            mask[[p for p in self._available if p not in self._done_pairs]] = True
        mask[-1] = True
        return mask

    def objective_value(self) -> float:
        """Sum over agents of :func:`agent_objective` (``log det P_i``, horizontal variance)."""
        if self.objective == "logdet":  # the sum of the same agent_objective values, cached
            return self._logdet_entry()[2]
        return float(np.sum(agent_objective(self.sim.P, self.objective)))

    # -- Gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """New realisation; propagate to the first step."""
        super().reset(seed=seed)
        self.problem = make_cl_problem(self.config, self.np_random)
        self._sim = CLSimulation(self.problem, self.fusion)
        self._done = False
        self._advance()
        return self._obs(), self._info()

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Process one pair (or stop); the step ends after ``budget`` pairs or a stop."""
        sim = self.sim
        if self._done:
            raise RuntimeError("episode is over: call reset()")
        p = check_discrete(action, self.n_pairs + 1)
        reason = None if self.action_masks()[p] else self._masked_reason(p)
        rule = self.invalid_rule
        if rule.check(f"action {p}", reason) and rule.terminates:
            self._done = True
            return self._obs(), rule.penalty, True, False, self._info(reason)
        reward = rule.penalty if reason else 0.0
        if reason is None and p < self.n_pairs:
            before = self.objective_value()
            sim.apply_relative(p)  # relative_update without its unused log det return
            reward = before - self.objective_value()
            self._done_pairs.add(p)
        if p < self.n_pairs:
            self._slots += 1
        if p == self.n_pairs or self.budget_left == 0 or not self.action_masks()[:-1].any():
            if sim.k >= self.horizon:
                self._done = True
                return self._obs(), reward, True, False, self._info(reason)
            before = self.objective_value()
            self._advance()  # propagation and the uncontrolled updates: their change counts too
            reward += before - self.objective_value()
        return self._obs_info(reward, False, reason)

    def _obs_info(
        self, reward: float, terminated: bool, reason: str | None
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """The step's return tuple, with the action mask formed once for obs and info."""
        mask = self.action_masks()
        return self._obs(mask), reward, terminated, False, self._info(reason, mask.copy())

    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        """A frame of the team (``render_mode`` ``"rgb_array"``: ``(H, W, 3)`` uint8)."""
        sim, done = self.sim, sorted(self._done_pairs)
        title = f"CLScheduling-v1 ({self.fusion})"
        from selenv.families.cooperative.rendering import (
            draw_cl_scheduling,  # matplotlib: first frame
        )

        return self._renderer.render(
            lambda fig: draw_cl_scheduling(fig, sim, self.pairs, done, title)
        )

    def close(self) -> None:
        """Close the render window, if any."""
        self._renderer.close()

    def _masked_reason(self, p: int) -> str:
        if p in self._done_pairs:
            return f"masked: pair {self.pairs[p]} was already processed in this step"
        return f"masked: pair {self.pairs[p]} has no relative measurement in this step"

    # -- helpers -----------------------------------------------------------------------------
    def _advance(self) -> None:
        """One simulation step (propagation, ZUPT and beacon updates); open its pairs."""
        sim = self.sim
        sim.predict()
        sim.zupt_updates()
        sim.beacon_updates()
        self._available = sim.available()
        self._done_pairs = set()
        self._slots = 0

    def preview_gain(self, p: int) -> float:
        """Decrease of the objective if pair ``p`` were processed now (previewed, no change).

        One ``fusion`` update of agent ``i``'s belief with pair ``p``'s measurement, undone:
        ``log det P_i - log det P_i+`` (``objective="logdet"``) or the drop of its horizontal
        position variance (``"trace"``); negative when the update would raise it.
        """
        sim = self.sim
        i = self.pairs[p][0]
        _, P_new = sim.preview(int(p))
        drop = agent_objective(sim.P[i], self.objective) - agent_objective(P_new, self.objective)
        return float(drop)

    def _pair_gains(self, mask: np.ndarray | None = None) -> np.ndarray:
        """(P,) ``log det(I + N^-1 A)`` of every open pair (0 when masked), batched.

        ``A = H_i P_i H_i^T``, ``N = H_j P_j H_j^T + R``: one stacked matmul / solve / slogdet
        over the open pairs (:func:`selenv.families.cooperative.batched.pair_gains`, on the
        position blocks), equal to the former per-pair loop to rounding (rtol 1e-9; some
        BLAS kernels round the stacked calls differently in the last bit), which
        tests/test_env_speed_identity.py keeps as the reference.
        """
        sim = self.sim
        out = np.zeros(self.n_pairs)
        ps = np.flatnonzero((self.action_masks() if mask is None else mask)[:-1])
        if ps.size == 0:
            return out
        H_i, H_j = sim.relative_jacobians(ps)
        ij = self._pair_index[ps]
        dim = sim.model.dim
        out[ps] = batched.pair_gains(sim.P[ij[:, 0]], sim.P[ij[:, 1]], H_i, H_j, sim.R_rel, dim)
        return out

    def _logdets(self) -> np.ndarray:
        """(A,) ``log det P_i``, cached on the bytes of ``sim.P`` (recomputed when it changes)."""
        return self._logdet_entry()[1]

    def _logdet_entry(self) -> tuple[bytes, np.ndarray, float]:
        """The cache entry ``(bytes of sim.P, log det P_i per agent, their sum)``, up to date."""
        P = self.sim.P
        key = P.tobytes()
        entry = self._logdet_cache
        if entry is None or entry[0] != key:
            ld = np.asarray(logdet_spd(P, "P"))
            entry = self._logdet_cache = (key, ld, float(np.sum(ld)))
        return entry

    def _obs(self, mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
        sim = self.sim
        mask = self.action_masks() if mask is None else mask
        return {
            "logdet": np.asarray(self._logdets(), np.float32),
            "pos_std": np.sqrt(np.trace(sim.P[:, :2, :2], axis1=1, axis2=2)).astype(np.float32),
            "pair_gain": self._pair_gains(mask).astype(np.float32),
            "budget_left": np.array([self.budget_left / self.budget], np.float32),
            "time": np.array([sim.k / self.horizon], np.float32),
            "action_mask": mask.astype(np.int8),
        }

    def _processed_mask(self) -> np.ndarray:
        """``(P,)`` bool: the pairs processed in the current filter step."""
        out = np.zeros(self.n_pairs, dtype=np.bool_)
        out[sorted(self._done_pairs)] = True
        return out

    def _info(self, reason: str | None = None, mask: np.ndarray | None = None) -> dict[str, Any]:
        sim = self.sim
        return {
            "objective": self.objective_value(),
            "k": sim.k,
            "position_errors": sim.position_errors(),
            "processed": self._processed_mask(),
            "action_mask": self.action_masks() if mask is None else mask,
            **self.invalid_rule.info(reason),
        }
