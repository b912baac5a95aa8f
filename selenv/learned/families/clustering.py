"""The learned edit ranking of ``ReceiverClustering-v1`` played by the receivers of its module.

``selenv.multiagent.receiver_clustering_v1`` observes, per receiver, the single-agent env's
observation (the same :func:`~selenv.families.clustering.env.clustering_observation`:
``assignment``, ``sigma``, ``position_var``, ``time``, ...) plus ``self`` and a label mask. So
the single-agent edit view (:class:`~selenv.families.clustering.view.ClusteringEditView`) and
the shipped edit-ranking checkpoint of ``selenv/ReceiverClustering-v1`` (the ``ppo_top8``
policy) apply unchanged to any receiver's observation, and the multi-agent policy is built
from them as the module's ``greedy``
(:class:`~selenv.families.clustering.multiagent_agents.ClusteringGreedyPolicy`) is built from
the single-agent greedy:

1. every ``every`` steps, the policy scores the no-op and the edits the module's resolution
   rule always carries out (:meth:`ClusteringGreedyPolicy.allowed_edits
   <selenv.families.clustering.multiagent_agents.ClusteringGreedyPolicy.allowed_edits>`:
   every allowed move, and a swap only when both clusters have room), the set greedy
   searches; for the per-candidate MLP of the shipped checkpoint (a DeepSets context over the
   allowed candidates) only those rows are scored, in numpy;
2. its ``top_k`` highest-scoring edits are costed exactly (Algorithm 1, one evaluation per
   edit, the no-op free);
3. the lowest-cost one is played if it lowers ``J``, by the receivers concerned (the mover
   answers its target label, both swapped receivers answer each other's label); everyone
   else stays.

When greedy's best edit is among the ``top_k``, this is greedy's joint action at that step;
with ``top_k`` at least the number of allowed edits, the policy is the module's
``greedy:every=<every>``. A decision costs at most ``top_k`` cost evaluations instead of one
per allowed edit.

``greedy_every=G`` (``G >= 1``; 0, the default, turns it off) makes every step ``k`` with
``k % G == 0`` greedy's full search instead: every allowed edit is costed and the best
improving one played, so those steps are exactly the module's ``greedy:every=G`` decision
(myopically never worse than greedy's edit), and the ranking's ``top_k`` fill the steps in
between. Costing greedy's best edit alongside the ``top_k`` at every step would be the
module's ``greedy:every=1`` itself (the ``top_k`` are among the edits greedy costs), at one
evaluation per allowed edit per step.

:func:`make_clustering_marl_learned` is the factory the agent registry calls.

The edit ranking's training labels are collected here too: :func:`collect_clustering_ranking`
labels states of ``ReceiverClustering-v1`` with every edit's exact change of ``J``
(:func:`clustering_edit_deltas`), for :func:`selenv.learned.rl.ranking.fit_ranking`. The
factorised edit scorer is :mod:`selenv.learned.families.clustering_edits`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from tqdm.auto import tqdm

from selenv.agents.multiagent import CLUSTERING_MODULE, MultiAgentPolicy
from selenv.families.clustering.agents import CLUSTERING_ENV_ID
from selenv.families.clustering.env import edit_cost_changes, edit_mask
from selenv.families.clustering.labels import check_int
from selenv.families.clustering.multiagent import ReceiverClusteringParallelEnv
from selenv.families.clustering.multiagent_agents import (
    ClusteringGreedyPolicy,
    best_improving_targets,
)
from selenv.families.clustering.view import ClusteringEditView
from selenv.learned.rl.agent import SB3PolicyAgent
from selenv.learned.rl.candidate_policy import CandidateScorer
from selenv.learned.rl.expert import collect_shares
from selenv.learned.rl.lean import LeanScorer, TopMScorer
from selenv.learned.rl.ranking import RankingData
from selenv.learned.rl.views import view_for

__all__ = [
    "OPTIONS",
    "ClusteringLearnedPolicy",
    "clustering_edit_deltas",
    "collect_clustering_ranking",
    "make_clustering_marl_learned",
]

#: the options of :func:`make_clustering_marl_learned` (those of :class:`ClusteringLearnedPolicy`)
OPTIONS = ("checkpoint", "top_k", "every", "swaps", "greedy_every")


class ClusteringLearnedPolicy(MultiAgentPolicy):
    """The edit ranking's ``top_k`` edits costed, the best improving one played (module doc).

    Args:
        checkpoint: an edit-ranking checkpoint of ``selenv/ReceiverClustering-v1`` (SB3 zip with
            its JSON; ``None``: the shipped one, the policy of ``ppo_top8``).
        top_k: edits costed per decision (>= 1; the no-op, when ranked among them, is free).
        every: steps between decisions (everyone stays in between).
        swaps: offer the swaps that the resolution rule always carries out.
        greedy_every: steps between greedy's full searches (every allowed edit costed) played
            instead of the ranking (>= 0; 0: never).

    Raises:
        ValueError: a bad option value (named), or a checkpoint that is missing, unreadable
            or not trained on ``selenv/ReceiverClustering-v1``.
    """

    name = "learned"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        top_k: int = 8,
        every: int = 1,
        swaps: bool = True,
        greedy_every: int = 0,
    ) -> None:
        self.top_k = check_int(top_k, "top_k", 1)
        self.every = check_int(every, "every", 1)
        self.greedy_every = check_int(greedy_every, "greedy_every", 0)
        if not isinstance(swaps, bool):
            raise ValueError(f"swaps must be a bool, got {type(swaps).__name__}")
        self.swaps = swaps
        if checkpoint is not None and not isinstance(checkpoint, str | Path):
            raise ValueError(f"checkpoint must be a path, got {type(checkpoint).__name__}")
        # loads the weights safely and checks the checkpoint's env id (ValueError naming it)
        self.ranker = SB3PolicyAgent(checkpoint, env_id=CLUSTERING_ENV_ID)
        self.checkpoint = self.ranker.checkpoint
        self.rule = ClusteringGreedyPolicy(every=1, swaps=swaps)
        self.view: ClusteringEditView | None = None
        self.scorer: LeanScorer | TopMScorer | None = None

    def reset(self, env: Any, seed: int | None = None) -> None:
        """Bind the edit view of ``env``'s receivers and the policy for its edit count.

        Raises:
            ValueError: ``env`` is not the ``ParallelEnv`` of ``receiver_clustering_v1`` (or
                v0), or its observations do not fit the checkpoint.
        """
        if not isinstance(env, ReceiverClusteringParallelEnv):
            raise ValueError(
                f"the learned clustering policy plays {CLUSTERING_MODULE}'s parallel_env(), "
                f"got {type(env).__name__}"
            )
        super().reset(env, seed)
        self.view = ClusteringEditView(env.n, env.max_size, "edit")
        space = self.view.space(env.observation_space(env.possible_agents[0]))
        policy = self.ranker.policy_for(space)
        if type(policy.pi_features_extractor) is CandidateScorer:
            # per-candidate MLP with a masked DeepSets context: scoring only the allowed edits
            # in numpy gives its scores (up to float32 rounding) at a fraction of the cost
            self.scorer = TopMScorer(policy, self.view.count)
        else:
            self.scorer = LeanScorer(policy)

    def ranked_edits(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The ``top_k`` highest-scoring of the no-op and the allowed edits (best first).

        ``obs`` is any receiver's observation (the shared fields are the same for all).
        """
        if self.view is None or self.scorer is None:
            raise ValueError("call reset(env) before ranked_edits()")
        bank = self.env.bank
        if not np.array_equal(np.asarray(obs["assignment"]), bank.labels):
            raise ValueError("obs is not the env's current observation (assignment differs)")
        cand = self.view(obs)
        allowed = np.concatenate([[0], self.rule.allowed_edits(bank.labels, self.env.max_size)])
        if isinstance(self.scorer, TopMScorer):
            scores = self.scorer.scores(cand, allowed)
        else:
            mask = np.zeros(self.view.count, bool)
            mask[allowed] = True
            scores = self.scorer.scores(cand, mask)[allowed]
        return allowed[np.argsort(-scores, kind="stable")[: self.top_k]]

    def greedy_step(self, k: int) -> bool:
        """Whether step ``k`` is one of greedy's full searches (``greedy_every``)."""
        return self.greedy_every > 0 and k % self.greedy_every == 0

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """Targets that realise the best improving costed edit (everyone stays if none).

        The costed edits are the ranking's ``top_k``, or every allowed edit at greedy's steps.
        """
        env = self.env
        k = env.bank.k
        edits = np.zeros(0, dtype=np.int64)
        if env.agents and self.greedy_step(k):
            edits = self.rule.allowed_edits(env.bank.labels, env.max_size)
        elif env.agents and k % self.every == 0:
            edits = self.ranked_edits(observations[env.agents[0]])
            edits = edits[edits != 0]
        return best_improving_targets(env, edits)


def make_clustering_marl_learned(**options: Any) -> ClusteringLearnedPolicy:
    """Registry factory of the learned policy of ``receiver_clustering_v1``.

    Args:
        **options: ``checkpoint``, ``top_k``, ``every``, ``swaps``, ``greedy_every`` of
            :class:`ClusteringLearnedPolicy`.

    Raises:
        ValueError: an unknown option (named, with the known ones) or a bad value.
    """
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise ValueError(
            f"the learned clustering policy has no option(s) {unknown}; "
            f"its options: {', '.join(OPTIONS)}"
        )
    return ClusteringLearnedPolicy(**options)


# -- the edit ranking's labels: every edit's exact cost change along an expert's trajectories --


def clustering_edit_deltas(env: gym.Env[Any, Any]) -> np.ndarray:
    """``(1 + n^2 + n(n-1)/2,)`` change of the Algorithm 1 cost ``J`` by each edit, now.

    ``dJ_a = J(apply_edit(labels, a)) - J(labels)`` at the env's current time (what the
    greedy search compares); 0 for the no-op, ``+inf`` for masked edits. Costs one
    evaluation per allowed edit (counted by the env's filter bank).
    """
    base = env.unwrapped
    bank = base.bank  # type: ignore[attr-defined]
    mask = edit_mask(bank.labels, base.max_size)  # type: ignore[attr-defined]
    out = np.full(mask.size, np.inf)
    allowed = np.flatnonzero(mask)
    out[allowed] = edit_cost_changes(bank, allowed)
    return out


@dataclass(frozen=True)
class _RankingJob:
    env_kwargs: dict[str, Any]
    n_states: int
    seed: int
    label_every: int
    explore: float
    progress: bool
    behaviour: str | None
    behaviour_top_k: int


def _ranking_share(job: _RankingJob) -> RankingData:
    env = gym.make(CLUSTERING_ENV_ID, **{**job.env_kwargs, "action_mode": "edit"})
    view = view_for(CLUSTERING_ENV_ID, env)
    rng = np.random.default_rng(job.seed)
    agent = None
    if job.behaviour is not None:
        th.set_num_threads(1)  # one worker per core

        agent = SB3PolicyAgent(
            job.behaviour, env_id=CLUSTERING_ENV_ID, verify_top_k=job.behaviour_top_k
        )
    rows: list[dict[str, np.ndarray]] = []
    deltas: list[np.ndarray] = []

    def reset() -> tuple[Any, dict[str, Any]]:
        seed = int(rng.integers(2**31))
        out = env.reset(seed=seed)
        if agent is not None:
            agent.reset(env, seed=seed)
        return out

    obs, info = reset()
    bar = tqdm(total=job.n_states, desc="ranking labels", unit="state", disable=not job.progress)
    while len(rows) < job.n_states:
        action = 0
        if env.unwrapped.bank.k % job.label_every == 0:  # type: ignore[attr-defined]
            d = clustering_edit_deltas(env)
            rows.append(view(obs))
            deltas.append(d)
            bar.update(1)
            action = int(np.argmin(d)) if d.min() < 0.0 else 0  # the greedy expert's edit
        if agent is not None:  # DAgger: the learner's own states, the expert's labels
            action = int(agent.act(obs, info))
        if rng.random() < job.explore:  # visit states off the behaviour's path too
            allowed = np.flatnonzero(obs["action_mask"])
            action = int(rng.choice(allowed))
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            obs, info = reset()
    bar.close()
    env.close()
    stacked = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    return RankingData(stacked, np.stack(deltas))


def collect_clustering_ranking(
    env_kwargs: dict[str, Any],
    n_states: int,
    seed: int,
    *,
    label_every: int = 5,
    explore: float = 0.05,
    workers: int | None = None,
    progress: bool = True,
    behaviour: str | None = None,
    behaviour_top_k: int = 0,
) -> RankingData:
    """Label ``n_states`` states of ``ReceiverClustering-v1`` with every edit's ``dJ``.

    States come from the greedy expert's trajectories (the best improving edit every
    ``label_every`` steps, keep in between) or, with ``behaviour`` (a checkpoint path), from
    that policy's own trajectories (DAgger, Ross et al. 2011: the learner visits the states,
    the exact costs label them; it acts every step, as
    ``SB3PolicyAgent(behaviour, verify_top_k=behaviour_top_k)``); a random allowed edit
    replaces the action with probability ``explore``. Episodes are seeded from ``seed``;
    ``workers`` processes (spawned: safe after torch has started threads; so a script calling
    this with ``workers > 1`` needs the ``if __name__ == "__main__":`` guard) share the work;
    they die with this process, and a SIGINT / SIGTERM here stops them at once (the
    collection is abandoned).

    Raises:
        ValueError: ``n_states < 1``, ``label_every < 1``, ``explore`` outside [0, 1].
    """
    if n_states < 1 or label_every < 1 or not 0.0 <= explore <= 1.0:
        raise ValueError(
            f"need n_states >= 1, label_every >= 1, 0 <= explore <= 1; got {n_states}, "
            f"{label_every}, {explore}"
        )
    workers = max(1, min(workers or os.cpu_count() or 1, n_states))
    seeds = np.random.SeedSequence(seed).generate_state(workers)
    shares = [n_states // workers + (w < n_states % workers) for w in range(workers)]
    jobs = [
        _RankingJob(
            env_kwargs,
            shares[w],
            int(seeds[w]),
            label_every,
            explore,
            progress and w == 0,
            behaviour,
            behaviour_top_k,
        )
        for w in range(workers)
    ]
    return collect_shares(_ranking_share, jobs)  # workers die with this process
