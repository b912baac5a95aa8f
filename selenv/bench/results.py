"""What a benchmark run produces: per-agent results, per-env results and their statistics.

:class:`EnvBenchResult` holds every agent's returns on one env (a Gymnasium id or a PettingZoo
module of :mod:`selenv.multiagent`) and derives the comparison of :mod:`selenv.bench.stats`:

* the **baseline** (``baseline=`` of :func:`~selenv.bench.run_bench`, ``selenv bench
  --baseline``; by default the agent with the best mean return, the first one on a tie);
* per agent, the paired comparison with the baseline (:meth:`EnvBenchResult.paired`);
* the **normalised score** ``(R - R_random) / (R_best - R_random)`` of the mean return
  (:meth:`EnvBenchResult.normalized_score`), where ``R_random`` is the mean return of the agent
  ``random`` (or ``fixed_random`` where that is the random baseline, as in
  ``ReceiverClustering-v1``) if it ran, and ``R_best`` the best mean return among the agents
  that ran. A reference agent (``rollout``, ``brute_force``, ``centralized_greedy``,
  ``centralized_swap``) is not treated specially: if it has the best mean return it is the
  best agent. ``None`` when no random agent ran;
* the **direction of the final objective** (:func:`objective_direction`): the return is
  always to be maximised, but ``info["objective"]`` is a gain for some families (``"higher"``
  is better) and a cost for others (``"lower"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from typing import Any

import numpy as np

import selenv
from selenv.agents import AGENTS, parse_spec
from selenv.bench.bounds import gap_to_bound
from selenv.bench.stats import (
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    CONFIDENCE,
    TIE_REL_TOL,
    PairedComparison,
    compare_paired,
    normalized_score,
)
from selenv.envs.resolved import jsonable
from selenv.families import FAMILIES

__all__ = [
    "OBJECTIVE_DIRECTIONS",
    "RANDOM_REFERENCES",
    "AgentRefused",
    "AgentResult",
    "BenchError",
    "EnvBenchResult",
    "EnvKwargsError",
    "objective_direction",
]

#: agent names that serve as the random reference of the normalised score, in order
RANDOM_REFERENCES = ("random", "fixed_random")

#: family name -> whether a ``"higher"`` or ``"lower"`` final ``info["objective"]`` is better,
#: as each env documents it (for every ``objective=`` setting of the env, every version and
#: the family's PettingZoo modules):
#:
#: * ``fim``: ``f(F)``, the information gained (``log det``, nats; or the decrease of the
#:   position MSE bound for ``"trace"`` / ``"max_eig"``); the return is ``f(F)`` itself;
#: * ``landmarks``: the cost eq. (11) of the EKF posterior (CRLB): ``log det P``, ``det P``,
#:   ``tr`` or ``lambda_max`` of its position block; the reward is minus the cost;
#: * ``cooperative``: the team's uncertainty (sum of ``log det P_i`` or of the horizontal
#:   position variances, an MSE-like cost); the reward is its decrease;
#: * ``clustering``: the clustering cost ``J``; the reward is ``-J``.
OBJECTIVE_DIRECTIONS: dict[str, str] = {
    "fim": "higher",
    "landmarks": "lower",
    "cooperative": "lower",
    "clustering": "lower",
}


def objective_direction(env_id: str) -> str | None:
    """``"higher"`` or ``"lower"``: which final objective of ``env_id`` is better.

    ``env_id`` is a Gymnasium id (any version) or a PettingZoo module of a selenv family
    (:data:`OBJECTIVE_DIRECTIONS`); ``None`` for an env of no selenv family (unknown).
    """
    for fam in FAMILIES:
        if env_id in fam.multiagent_modules or any(v.env_id == env_id for v in fam.versions):
            return OBJECTIVE_DIRECTIONS.get(fam.name)
    return None


class BenchError(ValueError):
    """A usage error of the benchmark (bad env id, agent name, baseline, episodes, env kwargs)."""


class EnvKwargsError(BenchError):
    """The env constructor rejected the keyword arguments."""


class AgentRefused(Exception):
    """An agent raised ``ValueError`` in ``reset`` or ``act``: it refuses this env or episode.

    Wrapping it keeps a ``ValueError`` raised by the env itself (e.g. a masked action, a bug
    of the agent that sent it) apart: that one propagates.
    """


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def _std(values: list[float]) -> float:
    return float(np.std(values)) if values else float("nan")


@dataclass
class AgentResult:
    """What one agent achieved over the episodes of one env.

    Attributes:
        name: the agent spec as given (registry name, or ``"name:checkpoint"``).
        returns: undiscounted return (sum of rewards; for a PettingZoo env the sum of the
            shared team reward) of each episode.
        final_objectives: ``info["objective"]`` after the last step of each episode.
        decision_seconds: total wall time spent in ``agent.act``.
        decisions: number of ``agent.act`` calls (one joint decision per step for a
            PettingZoo env).
        cost_evaluations: objective evaluations the agent's searches made, summed over the
            episodes, for envs that count them (``info["cost_evaluations"]`` after the last
            step, e.g. Algorithm 1 calls of ``ReceiverClustering-v1``); ``None`` otherwise.
        skipped: why the agent was not run (``None`` when it ran).
        seeds: the seed of each episode of ``returns`` (filled by the bench runner; in the
            JSON only for an incomplete run, where some seeds are missing).
    """

    name: str
    returns: list[float] = field(default_factory=list)
    final_objectives: list[float] = field(default_factory=list)
    decision_seconds: float = 0.0
    decisions: int = 0
    cost_evaluations: int | None = None
    skipped: str | None = None
    seeds: list[int] = field(default_factory=list)

    @property
    def mean_return(self) -> float:
        """Mean episode return (NaN if skipped)."""
        return _mean(self.returns)

    @property
    def std_return(self) -> float:
        """Population standard deviation of the episode returns."""
        return _std(self.returns)

    @property
    def mean_final_objective(self) -> float:
        """Mean final objective (NaN if skipped)."""
        return _mean(self.final_objectives)

    @property
    def std_final_objective(self) -> float:
        """Population standard deviation of the final objectives."""
        return _std(self.final_objectives)

    @property
    def decision_seconds_mean(self) -> float:
        """Mean wall time of one ``agent.act`` call, over every decision of every episode."""
        return self.decision_seconds / self.decisions if self.decisions else float("nan")

    @property
    def cost_evaluations_per_decision(self) -> float | None:
        """Mean objective evaluations per decision (``None`` if the env does not count them)."""
        if self.cost_evaluations is None or not self.decisions:
            return None
        return self.cost_evaluations / self.decisions

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict: the contract keys, or ``{"skipped": reason}``."""
        if self.skipped is not None:
            return {"skipped": self.skipped}
        extra: dict[str, Any] = {}
        if self.cost_evaluations is not None:
            extra["cost_evaluations_per_decision"] = self.cost_evaluations_per_decision
        return {
            "returns": [float(r) for r in self.returns],
            "mean_return": self.mean_return,
            "std_return": self.std_return,
            "final_objectives": [float(f) for f in self.final_objectives],
            "mean_final_objective": self.mean_final_objective,
            "std_final_objective": self.std_final_objective,
            "decision_seconds_mean": self.decision_seconds_mean,
            "decisions": self.decisions,
            **extra,
        }


@dataclass
class EnvBenchResult:
    """The results of every agent on one env, with the settings that reproduce them.

    Attributes:
        env_id: Gymnasium id or PettingZoo module name.
        env_kwargs: keyword arguments given to the env constructor.
        seed: seed of episode 0 (episode ``e`` uses ``seed + e``).
        episodes: number of episodes per agent.
        agents: agent spec -> result, in the order the agents were given.
        baseline: the baseline of the paired comparison; ``None``: the best by mean return.
        kind: ``"gymnasium"`` or ``"pettingzoo"``.
        timestamp: UTC time the run started (ISO 8601).
        env_config: the resolved configuration of the env the episodes ran on (every
            constructor keyword with its value, :func:`~selenv.envs.resolved.resolved_env_config`);
            ``None`` if no env was built.
        bounds: seed -> certified upper bound on that episode's return (empty: none);
            ``bound_kind`` / ``bound_method`` say what it is (:mod:`selenv.bench.bounds`).
        bound_kind: ``"optimum"`` (the bounds are attained) or ``"bound"``; ``None`` without bounds.
        bound_method: how the bounds were computed (``FamilySpec.return_bound``); ``None`` without.
        complete: ``False`` when the run was stopped (interrupted, a worker died) before every
            agent played every episode: the agents hold the episodes that finished, and every
            statistic is computed on the paired seeds (:meth:`statistics_view`).
    """

    env_id: str
    env_kwargs: dict[str, Any]
    seed: int
    episodes: int
    agents: dict[str, AgentResult] = field(default_factory=dict)
    baseline: str | None = None
    kind: str = "gymnasium"
    timestamp: str = field(
        default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds")
    )
    env_config: dict[str, Any] | None = None
    complete: bool = True
    bounds: dict[int, float] = field(default_factory=dict)
    bound_kind: str | None = None
    bound_method: str | None = None

    def episodes_done(self) -> dict[str, int]:
        """Agent -> episodes it finished (0 for a skipped agent)."""
        return {n: len(r.returns) for n, r in self.agents.items()}

    def paired_seeds(self) -> list[int]:
        """The seeds every agent that ran finished, sorted (agents with none are left out).

        Of an incomplete run, these are the episodes the statistics use.
        """
        ran = [r for r in self._ran().values() if r.returns]
        if not ran:
            return []
        common = set(ran[0].seeds)
        for r in ran[1:]:
            common &= set(r.seeds)
        return sorted(common)

    def statistics_view(self) -> EnvBenchResult:
        """This result if complete; else a copy restricted to :meth:`paired_seeds`.

        In the copy each agent keeps only the episodes of the paired seeds (in seed order), so
        means, paired differences, wins and scores compare the agents on the same episodes;
        an agent that finished no episode is reported as skipped. Decision times and counts
        stay those of every finished episode.
        """
        if self.complete:
            return self
        keep = set(self.paired_seeds())
        agents: dict[str, AgentResult] = {}
        for name, r in self.agents.items():
            if r.skipped is not None:
                agents[name] = r
            elif not r.returns:
                agents[name] = AgentResult(name, skipped="stopped before its first episode ended")
            else:
                idx = sorted((s, k) for k, s in enumerate(r.seeds) if s in keep)
                agents[name] = replace(
                    r,
                    returns=[r.returns[k] for _, k in idx],
                    final_objectives=[r.final_objectives[k] for _, k in idx],
                    seeds=[s for s, _ in idx],
                )
        return replace(self, agents=agents)

    def _ran(self) -> dict[str, AgentResult]:
        return {n: r for n, r in self.agents.items() if r.skipped is None}

    @property
    def best_return(self) -> float | None:
        """Largest mean return among the agents that ran (``None`` if none ran)."""
        ran = [r.mean_return for r in self._ran().values()]
        return max(ran) if ran else None

    @property
    def best_agent(self) -> str | None:
        """The agent with the largest mean return (the first on a tie; ``None`` if none ran)."""
        ran = self._ran()
        return max(ran, key=lambda n: ran[n].mean_return) if ran else None

    @property
    def baseline_name(self) -> str | None:
        """The baseline in use: ``baseline`` if set, else :attr:`best_agent`."""
        return self.baseline if self.baseline is not None else self.best_agent

    def check_baseline(self) -> None:
        """Raise :class:`BenchError` if the baseline is not an agent that ran."""
        name = self.baseline
        if name is None:
            return
        if name not in self.agents:
            raise BenchError(
                f"baseline {name!r} is not among the agents run on {self.env_id}: "
                f"{list(self.agents)}"
            )
        why = self.agents[name].skipped
        if why is not None:
            raise BenchError(f"baseline {name!r} was skipped on {self.env_id}: {why}")

    @property
    def objective_direction(self) -> str | None:
        """Which final objective is better here: ``"higher"``, ``"lower"`` or ``None`` (unknown).

        :func:`objective_direction` of :attr:`env_id`.
        """
        return objective_direction(self.env_id)

    @property
    def random_reference(self) -> str | None:
        """The random agent of the normalised score (first of ``RANDOM_REFERENCES`` that ran)."""
        ran = self._ran()
        return next((n for n in RANDOM_REFERENCES if n in ran), None)

    def gap_percent(self, name: str) -> float | None:
        """Shortfall of agent ``name``'s mean return from the best one, in % of ``|best|``.

        Returns are compared (not objectives) because a return is always to be maximised,
        whereas an objective may be a log det (maximised) or an MSE (minimised). ``None`` for a
        skipped agent; when the best return is 0 the absolute shortfall times 100 is returned.
        """
        res, best = self.agents[name], self.best_return
        if res.skipped is not None or best is None:
            return None
        return 100.0 * (best - res.mean_return) / (abs(best) or 1.0)

    def gap_to_bound(self, name: str) -> tuple[float, float, float] | None:
        """Agent ``name``'s mean ``(bound - return) / |bound|`` and 95 % CI (``None``: no bound)."""
        res = self.agents[name]
        if res.skipped is not None or not self.bounds:
            return None
        seeds = res.seeds or [self.seed + e for e in range(len(res.returns))]
        return gap_to_bound(res.returns, seeds, self.bounds)

    def paired(self, name: str) -> PairedComparison | None:
        """Agent ``name`` against the baseline on the same seeds (``None`` if either skipped)."""
        base = self.baseline_name
        res = self.agents[name]
        if base is None or res.skipped is not None or base not in self._ran():
            return None
        return compare_paired(res.returns, self.agents[base].returns, base)

    def normalized_score(self, name: str) -> float | None:
        """``(R - R_random) / (R_best - R_random)`` of the mean return (module docstring)."""
        res, best, ref = self.agents[name], self.best_return, self.random_reference
        if res.skipped is not None or best is None or ref is None:
            return None
        return normalized_score(res.mean_return, self.agents[ref].mean_return, best)

    def agent_specs(self) -> dict[str, dict[str, Any]]:
        """Each agent spec as given -> registry name and the keyword arguments it was built with.

        The keyword arguments are the registered defaults plus the spec's (``"ppo:path.zip"``
        gives ``{"checkpoint": "path.zip"}``).
        """
        out: dict[str, dict[str, Any]] = {}
        for spec in self.agents:
            name, extra = parse_spec(spec)
            registered = AGENTS.get(name, {}).get(self.env_id)
            kwargs = {**(registered.kwargs if registered else {}), **extra}
            out[spec] = {"agent": name, "kwargs": jsonable(kwargs)}
        return out

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict of this env following the contract of ``DESIGN.md`` section 2.

        ``"complete"`` says whether every agent played every episode. When it is ``False``
        the document also has ``"episodes_done"`` (agent -> episodes finished) and
        ``"paired_seeds"`` (the seeds the statistics use, :meth:`statistics_view`); each
        agent's ``returns`` / ``final_objectives`` list every finished episode, with its
        ``seeds``, while its means, paired comparison, gap and score use the paired seeds.
        """
        view = self.statistics_view()
        agents = {}
        for name, res in view.agents.items():
            agents[name] = res.to_json()
            if res.skipped is None:
                agents[name]["gap_to_best_percent"] = view.gap_percent(name)
                paired = view.paired(name)
                agents[name]["paired"] = None if paired is None else paired.to_json()
                agents[name]["normalized_score"] = view.normalized_score(name)
                gap = view.gap_to_bound(name)
                agents[name]["gap_to_bound"] = (
                    None if gap is None else {"mean": gap[0], "ci95": [gap[1], gap[2]]}
                )
            full = self.agents[name]
            if not self.complete and full.skipped is None:
                agents[name]["returns"] = [float(r) for r in full.returns]
                agents[name]["final_objectives"] = [float(f) for f in full.final_objectives]
                agents[name]["seeds"] = [int(x) for x in full.seeds]
        extra: dict[str, Any] = {}
        if not self.complete:
            extra = {"episodes_done": self.episodes_done(), "paired_seeds": self.paired_seeds()}
        return {
            "env_id": self.env_id,
            "kind": self.kind,
            "env_kwargs": jsonable(self.env_kwargs),
            "env_config": self.env_config,
            "seed": self.seed,
            "episodes": self.episodes,
            "complete": self.complete,
            **extra,
            "baseline": view.baseline_name,
            "baseline_rule": "given" if self.baseline is not None else "best mean return",
            "random_reference": view.random_reference,
            "best_agent": view.best_agent,
            "objective_direction": self.objective_direction,
            "return_bound": None
            if not self.bounds
            else {
                "kind": self.bound_kind,
                "method": self.bound_method,
                "seeds": sorted(self.bounds),
                "values": [self.bounds[k] for k in sorted(self.bounds)],
            },
            "statistics": {
                "confidence": CONFIDENCE,
                "ci95": "percentile bootstrap of the mean paired difference of episode returns",
                "bootstrap_resamples": BOOTSTRAP_RESAMPLES,
                "bootstrap_seed": BOOTSTRAP_SEED,
                "tie_rule": f"|diff| <= {TIE_REL_TOL:g} * max(1, |baseline return|)",
            },
            "agent_specs": self.agent_specs(),
            "agents": agents,
            "selenv_version": selenv.__version__,
            "timestamp": self.timestamp,
        }
