"""Expert iteration for ``CLScheduling-v0``: the non-myopic ``rollout`` reference as labeller.

The ``rollout`` agent (:class:`selenv.agents.rollout.CLRolloutAgent`) scores stop and the
``top_k`` open pairs of a decision by simulating ``horizon`` filter steps of greedy on the
forecast covariance recursion (no truth, no future noise). Its scores are a dense label of a
state: each evaluated action gets ``dJ = -score`` (the objective drop, negated, so lower is
better, the convention of :class:`learned.rl.ranking.RankingData`); the actions it did not
evaluate (one-step gain below its ``top_k``) get ``+inf`` -- ListNet's target is then 0 on
them, so the policy learns to rank them last. A policy fitted to these labels
(:func:`learned.rl.ranking.fit_ranking`) plays rollout's choice for the price of one network
evaluation.

DAgger (Ross et al. 2011): round 0 follows the labeller's own choices; later rounds follow
the current learner (``behaviour``), so the labels cover the states the learner visits.
Only decisions whose evaluated actions differ are labelled: stop-only steps carry no choice,
and early in an episode every pair's fused update is a no-op (DMV's ``w* = 1``), so stop and
the pairs tie exactly (about the first ten steps of the benchmark preset).

Seeds: training episodes are seeded ``10**6 * (seed + 1) + k`` (``k = 0, 1, ...`` per
worker stride), disjoint from the held-out evaluation seeds ``< 10**6`` of the docs.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from tqdm.auto import tqdm

import selenv  # noqa: F401  (registers the envs, also in worker processes)
from learned.rl.ranking import RankingData
from learned.rl.views import view_for
from selenv.agents.rollout import CLRolloutAgent

__all__ = [
    "CL_ID",
    "LANDMARK_ID",
    "TRAIN_SEED_BASE",
    "collect_cl_rollout_labels",
    "collect_landmark_rollout_labels",
    "train_seed",
]

CL_ID = "selenv/CLScheduling-v0"
LANDMARK_ID = "selenv/LandmarkSelection-v0"
#: training episode seeds start at ``TRAIN_SEED_BASE * (seed + 1)``
TRAIN_SEED_BASE = 10**6


def train_seed(seed: int, worker: int, workers: int, episode: int) -> int:
    """Seed of a worker's ``episode``-th training episode (disjoint from ``[0, 10**6)``)."""
    return TRAIN_SEED_BASE * (seed + 1) + episode * workers + worker


@dataclass
class _Job:
    env_kwargs: dict[str, Any]
    view: str | None
    n_states: int
    seed: int
    worker: int
    workers: int
    top_k: int
    horizon: int
    explore: float
    behaviour: str | None
    progress: bool


def _collect(job: _Job) -> RankingData:
    th.set_num_threads(1)  # one worker per core
    env = gym.make(CL_ID, **job.env_kwargs)
    view = view_for(CL_ID, env, job.view)
    labeller = CLRolloutAgent(top_k=job.top_k, horizon=job.horizon)
    agent = None
    if job.behaviour is not None:
        from learned.rl.agent import SB3PolicyAgent

        agent = SB3PolicyAgent(job.behaviour, env_id=CL_ID)
    rng = np.random.default_rng([job.seed, job.worker])
    rows: list[dict[str, np.ndarray]] = []
    deltas: list[np.ndarray] = []
    episode = 0
    mismatches = 0

    def reset() -> tuple[Any, dict[str, Any]]:
        nonlocal episode
        s = train_seed(job.seed, job.worker, job.workers, episode)
        episode += 1
        out = env.reset(seed=s)
        labeller.reset(env, seed=s)
        if agent is not None:
            agent.reset(env, seed=s)
        return out

    obs, info = reset()
    n_actions = int(np.shape(obs["action_mask"])[0])
    bar = tqdm(total=job.n_states, desc="rollout labels", unit="state", disable=not job.progress)
    while len(rows) < job.n_states:
        mask = np.asarray(obs["action_mask"], dtype=bool)
        if mask[:-1].any():
            choice, scores = labeller.scores()
            values = list(scores.values())
            if max(values) > min(values):  # ties (every pair a no-op) carry no label
                row = view(obs)
                allowed = np.asarray(row["action_mask"], dtype=bool)
                d = np.full(n_actions, np.inf)
                for a, s in scores.items():
                    if allowed[a]:  # a restricted view (top-k) may differ on exact gain ties
                        d[a] = -s
                mismatches += int(set(np.flatnonzero(allowed)) != set(scores))
                if np.isfinite(d).sum() > 1:
                    rows.append(row)
                    deltas.append(d)
                    bar.update(1)
            action = choice if agent is None else int(agent.act(obs, info))
            if rng.random() < job.explore:
                action = int(rng.choice(np.flatnonzero(mask)))
        else:
            action = n_actions - 1  # stop: the only allowed action
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            obs, info = reset()
    bar.close()
    env.close()
    if mismatches:
        print(f"worker {job.worker}: {mismatches} decisions where the view's candidates differ")
    stacked = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    return RankingData(stacked, np.stack(deltas))


def collect_cl_rollout_labels(
    env_kwargs: dict[str, Any],
    n_states: int,
    seed: int,
    *,
    view: str | None = "cl_pairs_fused_top3",
    top_k: int = 3,
    horizon: int = 5,
    explore: float = 0.05,
    behaviour: str | None = None,
    workers: int = 1,
    progress: bool = True,
) -> RankingData:
    """Label ``n_states`` CL decisions with the ``rollout`` reference's scores.

    Args:
        env_kwargs: ``CLScheduling-v0`` keyword arguments (``{}``: the benchmark preset).
        n_states: labelled decisions to collect (each with actions of different scores).
        seed: training seed (episode seeds: :func:`train_seed`).
        view: candidate view of the policy; ``cl_pairs_fused_top3`` allows exactly the
            labeller's candidates (stop and the ``top_k`` pairs by previewed gain).
        top_k: pairs the labeller scores per decision (besides stop).
        horizon: filter steps the labeller simulates after the current one.
        explore: probability of a random allowed action instead of the behaviour's.
        behaviour: checkpoint whose (deterministic) actions drive the trajectories (DAgger);
            ``None``: the labeller's own choices.
        workers: processes (spawned; the caller needs the ``__main__`` guard if > 1).
        progress: tqdm bar (first worker).

    Raises:
        ValueError: ``n_states``, ``workers``, ``top_k`` < 1, ``horizon`` < 0, or ``explore``
            outside [0, 1].
    """
    for name, value, low in (("n_states", n_states, 1), ("workers", workers, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if not 0.0 <= explore <= 1.0:
        raise ValueError(f"explore must be in [0, 1], got {explore!r}")
    CLRolloutAgent(top_k=top_k, horizon=horizon)  # validates top_k / horizon
    workers = min(workers, n_states)
    shares = [n_states // workers + (w < n_states % workers) for w in range(workers)]
    jobs = [
        _Job(
            env_kwargs,
            view,
            shares[w],
            seed,
            w,
            workers,
            top_k,
            horizon,
            explore,
            behaviour,
            progress and w == 0,
        )
        for w in range(workers)
    ]
    if workers == 1:
        return _collect(jobs[0])
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return RankingData.concatenate(list(pool.map(_collect, jobs)))


@dataclass
class _LandmarkJob:
    env_kwargs: dict[str, Any]
    n_states: int
    seed: int
    worker: int
    workers: int
    top_k: int
    horizon: int
    explore: float
    behaviour: str | None
    progress: bool


def _collect_landmarks(job: _LandmarkJob) -> RankingData:
    from selenv.agents.rollout import LandmarkRolloutAgent

    th.set_num_threads(1)
    env = gym.make(LANDMARK_ID, **job.env_kwargs)
    view = view_for(LANDMARK_ID, env)
    labeller = LandmarkRolloutAgent(top_k=job.top_k, horizon=job.horizon)
    agent = None
    if job.behaviour is not None:
        from learned.rl.agent import SB3PolicyAgent

        agent = SB3PolicyAgent(job.behaviour, env_id=LANDMARK_ID)
    rng = np.random.default_rng([job.seed, job.worker])
    rows: list[dict[str, np.ndarray]] = []
    deltas: list[np.ndarray] = []
    episode = 0

    def reset() -> tuple[Any, dict[str, Any]]:
        nonlocal episode
        s = train_seed(job.seed, job.worker, job.workers, episode)
        episode += 1
        out = env.reset(seed=s)
        labeller.reset(env, seed=s)
        if agent is not None:
            agent.reset(env, seed=s)
        return out

    obs, info = reset()
    n = int(np.shape(obs["action_mask"])[0])
    bar = tqdm(total=job.n_states, desc="rollout labels", unit="state", disable=not job.progress)
    while len(rows) < job.n_states:
        best, scores = labeller.scores()
        d = np.full(n, np.inf)
        for subset, value in scores.items():  # a landmark's label: its best subset's score
            for lm in subset:
                d[lm] = min(d[lm], -value)
        if np.isfinite(d).sum() > 1 and np.ptp(d[np.isfinite(d)]) > 0:
            rows.append(view(obs))
            deltas.append(d)
            bar.update(1)
        action = best[0] if agent is None else int(agent.act(obs, info))
        if rng.random() < job.explore:
            action = int(rng.choice(np.flatnonzero(obs["action_mask"])))
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            obs, info = reset()
    bar.close()
    env.close()
    stacked = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    return RankingData(stacked, np.stack(deltas))


def collect_landmark_rollout_labels(
    env_kwargs: dict[str, Any],
    n_states: int,
    seed: int,
    *,
    top_k: int = 4,
    horizon: int = 10,
    explore: float = 0.05,
    behaviour: str | None = None,
    workers: int = 1,
    progress: bool = True,
) -> RankingData:
    """Label ``LandmarkSelection-v0`` picks with the landmark ``rollout`` reference's scores.

    At every pick the labeller scores its candidate subsets of the picks left in the filter
    step (``top_k`` by one-step gain plus brute force's own); a landmark's ``dJ`` is minus the
    best score of a candidate subset containing it, ``+inf`` if none does. The behaviour
    plays the first landmark of rollout's best subset (or ``behaviour``'s pick: DAgger).
    Picks where all labelled landmarks tie are skipped. Same seeds and options as
    :func:`collect_cl_rollout_labels`.

    Raises:
        ValueError: as :func:`collect_cl_rollout_labels`.
    """
    from selenv.agents.rollout import LandmarkRolloutAgent

    for name, value, low in (("n_states", n_states, 1), ("workers", workers, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if not 0.0 <= explore <= 1.0:
        raise ValueError(f"explore must be in [0, 1], got {explore!r}")
    LandmarkRolloutAgent(top_k=top_k, horizon=horizon)  # validates top_k / horizon
    workers = min(workers, n_states)
    shares = [n_states // workers + (w < n_states % workers) for w in range(workers)]
    jobs = [
        _LandmarkJob(
            env_kwargs,
            shares[w],
            seed,
            w,
            workers,
            top_k,
            horizon,
            explore,
            behaviour,
            progress and w == 0,
        )
        for w in range(workers)
    ]
    if workers == 1:
        return _collect_landmarks(jobs[0])
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return RankingData.concatenate(list(pool.map(_collect_landmarks, jobs)))
