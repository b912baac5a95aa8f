"""Agents for ``selenv/ReceiverClustering-v1`` (Greiff et al. 2022 and baselines to test against).

All act on the env's oracle view ``env.unwrapped.bank`` (a
:class:`~selenv.families.clustering.filters.ClusterFilterBank`: current clustering, time,
Algorithm 1 costs of candidates) and return a full assignment (``action_mode="assignment"``);
``greedy`` also plays ``action_mode="edit"``. Randomness comes from the agent's seeded ``rng``.

| name | what |
|---|---|
| ``ga`` | Algorithm 2: one GA generation every ``every`` steps from ``start_step`` on |
| ``greedy`` | best single move or swap by Algorithm 1 cost, if it improves (local search) |
| ``fixed_random`` | a random feasible clustering (clusters filled to the cap), kept all episode |
| ``offline_static`` | the best partition found offline at ``k = 0`` for the base noise levels,
  kept all episode (with time-varying noise: what online re-clustering must beat) |
| ``singletons`` | one receiver per cluster: the worst clustering (Remark 2) |
| ``single_cluster`` | all receivers together: the unconstrained lower bound (refuses when
  the env's ``n_max_states`` forbids it) |
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import Agent, AgentSpec, register_agent
from selenv.families.clustering.env import (
    ReceiverClusteringEnv,
    apply_edit,
    edit_cost_changes,
    edit_mask,
)
from selenv.families.clustering.filters import ClusterFilterBank
from selenv.families.clustering.ga import GAConfig, GeneticClustering
from selenv.families.clustering.labels import check_int, random_feasible_clustering
from selenv.families.clustering.scenario import ClusteringProblem

__all__ = [
    "CLUSTERING_ENV_ID",
    "FixedClusteringAgent",
    "GAAgent",
    "GreedyMoveAgent",
    "OfflineStaticAgent",
    "best_edit",
    "clustering_env",
]

CLUSTERING_ENV_ID = "selenv/ReceiverClustering-v1"


def clustering_env(env: gym.Env[Any, Any], name: str, modes: tuple[str, ...]) -> Any:
    """``env.unwrapped`` if it is ``ReceiverClustering-v1`` in one of ``modes``, else ValueError."""
    base = env.unwrapped
    if not isinstance(base, ReceiverClusteringEnv):
        raise ValueError(f"agent {name!r} needs {CLUSTERING_ENV_ID}, got {type(base).__name__}")
    if base.action_mode not in modes:
        raise ValueError(
            f"agent {name!r} plays action_mode in {modes}, the env uses {base.action_mode!r}"
        )
    return base


class FixedClusteringAgent(Agent):
    """Keeps one clustering all episode (``kind``: fixed_random, singletons, single_cluster)."""

    def __init__(self, kind: str) -> None:
        if kind not in ("fixed_random", "singletons", "single_cluster"):
            raise ValueError(f"unknown fixed clustering kind {kind!r}")
        self.name = kind  # type: ignore[misc]
        self.kind = kind

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Choose the clustering (``ValueError`` if the env's constraint forbids it)."""
        super().reset(env, seed)
        base = clustering_env(env, self.kind, ("assignment",))
        n = base.n
        if self.kind == "singletons":
            self.labels = np.arange(n)
        elif self.kind == "single_cluster":
            if base.max_size < n:
                raise ValueError(
                    f"single_cluster is the unconstrained lower bound: it needs n_max_states=None"
                    f" (or >= {4 * n + 2}) but the env allows {base.max_size} receivers per cluster"
                )
            self.labels = np.zeros(n, np.int64)
        else:
            self.labels = random_feasible_clustering(n, base.max_size, self.rng)

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """The fixed clustering."""
        return self.labels.copy()


class GAAgent(Agent):
    """Algorithm 2 (Greiff et al.): the genetic algorithm re-clustering online.

    Args:
        every: ``N_T``, steps between generations.
        start_step: first step at which the GA runs (the paper switches it on at ``k = 50``);
            before that the current clustering is kept.
        **ga_kwargs: fields of :class:`~selenv.families.clustering.ga.GAConfig`
            (``population_size``, ``alpha``, ``operators``, ``max_tries``, ``n_labels``,
            ``redraw_partner``, ``variant``); on the command line ``ga:variant=literal`` runs
            Table I's operators as printed.
    """

    name = "ga"

    def __init__(self, every: int = 1, start_step: int = 0, **ga_kwargs: Any) -> None:
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ValueError(f"every (N_T) must be an int >= 1, got {every!r}")
        if isinstance(start_step, bool) or not isinstance(start_step, int) or start_step < 0:
            raise ValueError(f"start_step must be an int >= 0, got {start_step!r}")
        self.every = every
        self.start_step = start_step
        self.config = GAConfig(**ga_kwargs)
        self.ga: GeneticClustering | None = None

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self.base = clustering_env(env, self.name, ("assignment",))
        self.ga = None  # built at the first generation, from the clustering in use then

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """Run a generation when due; play the best clustering found."""
        bank = self.base.bank
        k = bank.k
        if k < self.start_step or (k - self.start_step) % self.every:
            return bank.labels.copy()
        if self.ga is None:
            self.ga = GeneticClustering(
                bank.evaluate, bank.labels, self.base.max_size, self.config, rng=self.rng
            )
        best, _ = self.ga.generation()
        return best


class GreedyMoveAgent(Agent):
    """Local search: each step, the best single move or swap by Algorithm 1 cost, if it helps.

    Evaluates every allowed edit of :func:`~selenv.families.clustering.env.edit_mask` (moves to
    another receiver's cluster or to a new singleton, and swaps) in one batched call and takes
    the best if it beats keeping the clustering. Plays both action modes.

    Args:
        every: steps between searches (keeps the clustering in between).
        swaps: include swaps (needed when every cluster is full, as with ``N_max = 14``).
        max_evaluations: cost only this many allowed edits per search, drawn uniformly without
            replacement from the agent's seeded ``rng`` (``None``: all of them). The
            evaluation-budget baseline of a learned proposal (``ppo_top8`` costs 8 edits):
            ``greedy:max_evaluations=8``.
    """

    name = "greedy"

    def __init__(
        self, every: int = 5, swaps: bool = True, max_evaluations: int | None = None
    ) -> None:
        self.every = check_int(every, "every", 1)
        if not isinstance(swaps, bool):
            raise TypeError(f"swaps must be a bool, got {type(swaps).__name__}")
        self.swaps = swaps
        self.max_evaluations = (
            None if max_evaluations is None else check_int(max_evaluations, "max_evaluations", 1)
        )

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self.base = clustering_env(env, self.name, ("assignment", "edit"))

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        """The best improving edit (as labels or as an edit index, per the env's mode)."""
        bank = self.base.bank
        best_action = 0
        if bank.k % self.every == 0:
            best_action, _ = best_edit(
                bank, self.base.max_size, self.swaps, self.max_evaluations, self.rng
            )
        if self.base.action_mode == "edit":
            return best_action
        return apply_edit(bank.labels, best_action)


def best_edit(
    bank: ClusterFilterBank,
    max_size: int,
    swaps: bool = True,
    max_evaluations: int | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[int, float]:
    """The edit with the lowest Algorithm 1 cost change now, and that change (the greedy step).

    ``(0, 0.0)`` (the no-op) unless an allowed edit of :func:`edit_mask` lowers ``J``. With
    ``max_evaluations``, only that many allowed edits (drawn by ``rng`` without replacement)
    are costed.
    """
    labels = bank.labels
    n = labels.size
    mask = edit_mask(labels, max_size)
    if not swaps:
        mask[1 + n * n :] = False
    actions = np.flatnonzero(mask[1:]) + 1
    if max_evaluations is not None and actions.size > max_evaluations:
        if rng is None:
            raise ValueError("best_edit: max_evaluations needs rng (a numpy Generator)")
        actions = np.sort(rng.choice(actions, size=max_evaluations, replace=False))
    if actions.size:
        d = edit_cost_changes(bank, actions)
        j = int(np.argmin(d))
        if d[j] < 0.0:
            return int(actions[j]), float(d[j])
    return 0, 0.0


class OfflineStaticAgent(Agent):
    """A baseline to test against: one partition solved offline at ``k = 0``, kept all episode.

    At its first decision it solves the static problem with the noise held at fixed levels:
    a private filter bank (the env is not touched) starts from the env's clustering, runs
    ``warmup`` filter steps with a greedy edit (best move or swap by Algorithm 1) every step,
    then applies greedy edits at that time until none improves (at most ``max_edits``), and
    plays the result from then on. With fixed noise (``preset="paper"``) this is the best
    static clustering the local search finds; with time-varying noise it is what online
    re-clustering has to beat.

    Args:
        levels: noise levels of the static problem: ``"base"`` (open-sky ``sigma``),
            ``"rms"`` (``sigma sqrt(1 + pi (f^2 - 1))``, the stationary RMS level) or
            ``"current"`` (the levels at ``k = 0``).
        warmup: filter steps before the final search, >= 0; ``None``: ``tau + 5`` (the
            Algorithm 1 window is full; longer warm-ups gave the same partitions).
        max_edits: cap on the edits of the final search, >= 0.
    """

    name = "offline_static"
    LEVELS = ("base", "rms", "current")

    def __init__(
        self, levels: str = "base", warmup: int | None = None, max_edits: int = 200
    ) -> None:
        if levels not in self.LEVELS:
            raise ValueError(f"levels must be one of {self.LEVELS}, got {levels!r}")
        for name, v in (("warmup", warmup), ("max_edits", max_edits)):
            if v is None and name == "warmup":
                continue
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be an int >= 0, got {v!r}")
        self.levels, self.warmup, self.max_edits = levels, warmup, max_edits

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self.base = clustering_env(env, self.name, ("assignment",))
        self.labels: np.ndarray | None = None

    def static_problem(self, problem: ClusteringProblem) -> ClusteringProblem:
        """The fixed-noise problem the partition is solved for (known at ``k = 0``)."""
        model = problem.config.regimes
        if self.levels == "current":
            sigma = problem.sigma_at(0)
        elif self.levels == "rms" and model is not None:
            f = float(model.degraded_factor)
            sigma = problem.sigma * np.sqrt(1.0 + model.degraded_fraction * (f * f - 1.0))
        else:
            sigma = problem.sigma
        config = dataclasses.replace(problem.config, regimes=None)
        return ClusteringProblem(config=config, sigma=np.asarray(sigma, dtype=float))

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """Solve at the first call, then play the solution."""
        if self.labels is None:
            bank = ClusterFilterBank(
                self.static_problem(self.base.bank.problem), self.base.bank.labels
            )
            cap = self.base.max_size
            warmup = bank.tau + 5 if self.warmup is None else self.warmup
            for _ in range(warmup):
                bank.recluster(apply_edit(bank.labels, best_edit(bank, cap)[0]))
                bank.step()
            for _ in range(self.max_edits):
                action, _ = best_edit(bank, cap)
                if action == 0:
                    break
                bank.recluster(apply_edit(bank.labels, action))
            self.labels = bank.labels.copy()
        return self.labels.copy()


def _fixed(kind: str) -> Any:
    def factory(**kwargs: Any) -> FixedClusteringAgent:
        return FixedClusteringAgent(kind, **kwargs)

    return factory


_ID = (CLUSTERING_ENV_ID,)
register_agent(AgentSpec("ga", _ID, GAAgent, "Algorithm 2 genetic algorithm (Greiff et al.)"))
register_agent(AgentSpec("greedy", _ID, GreedyMoveAgent, "best single move/swap if it improves"))
register_agent(
    AgentSpec("fixed_random", _ID, _fixed("fixed_random"), "random feasible clustering, kept")
)
register_agent(
    AgentSpec(
        "offline_static",
        _ID,
        OfflineStaticAgent,
        "best partition for the base noise found offline at k = 0, kept",
    )
)
register_agent(AgentSpec("singletons", _ID, _fixed("singletons"), "one receiver per cluster"))
register_agent(
    AgentSpec(
        "single_cluster", _ID, _fixed("single_cluster"), "all in one cluster (unconstrained bound)"
    )
)
