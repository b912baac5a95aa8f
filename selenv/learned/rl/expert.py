"""Expert iteration: the non-myopic ``rollout`` references (CL scheduling, landmarks) as labellers.

The ``rollout`` agent (:class:`selenv.families.cooperative.rollout.CLRolloutAgent`) scores stop and
the
``top_k`` open pairs of a decision by simulating ``horizon`` filter steps of greedy on the
forecast covariance recursion (no truth, no future noise). Its scores are a dense label of a
state: each evaluated action gets ``dJ = -score`` (the objective drop, negated, so lower is
better, the convention of :class:`selenv.learned.rl.ranking.RankingData`); the actions it did not
evaluate (one-step gain below its ``top_k``) get ``+inf`` -- ListNet's target is then 0 on
them, so the policy learns to rank them last. A policy fitted to these labels
(:func:`selenv.learned.rl.ranking.fit_ranking`) plays rollout's choice for the price of one network
evaluation.

DAgger (Ross et al. 2011): round 0 follows the labeller's own choices; later rounds follow
the current learner (``behaviour``), so the labels cover the states the learner visits.
Only decisions whose evaluated actions differ are labelled: stop-only steps carry no choice,
and early in an episode every pair's fused update is a no-op (DMV's ``w* = 1``), so stop and
the pairs tie exactly (about the first ten steps of the benchmark preset).

``LandmarkSelection-v1`` (:func:`collect_landmark_rollout_labels`) works the same way with
the landmark ``rollout``; both share one collection loop (``_collect``).

The workers are a :class:`selenv.parallel.ProcessExecutor` pool: they die with this process
(even after ``kill -9``), and a SIGINT / SIGTERM of the caller during a collection abandons
it (the workers stop at once, nothing is left running).

Seeds: training episodes are seeded ``10**6 * (seed + 1) + k`` (``k = 0, 1, ...`` per
worker stride), disjoint from the held-out evaluation seeds ``< 10**6`` of the docs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from tqdm.auto import tqdm

import selenv  # noqa: F401  (registers the envs, also in worker processes)
from selenv.learned.rl.ranking import RankingData
from selenv.learned.rl.views import view_for
from selenv.parallel import ProcessExecutor, TaskStopped, stoppable

__all__ = [
    "CL_ID",
    "LANDMARK_ID",
    "LANDMARK_LABELLERS",
    "TRAIN_SEED_BASE",
    "collect_cl_rollout_labels",
    "collect_landmark_rollout_labels",
    "train_seed",
]

CL_ID = "selenv/CLScheduling-v1"
LANDMARK_ID = "selenv/LandmarkSelection-v1"
#: the landmark labellers: the ``rollout`` reference and its shortlist version
LANDMARK_LABELLERS = ("rollout", "fast_rollout")
#: training episode seeds start at ``TRAIN_SEED_BASE * (seed + 1)``
TRAIN_SEED_BASE = 10**6


def train_seed(seed: int, worker: int, workers: int, episode: int) -> int:
    """Seed of a worker's ``episode``-th training episode (disjoint from ``[0, 10**6)``)."""
    return TRAIN_SEED_BASE * (seed + 1) + episode * workers + worker


@dataclass
class _Job:
    env_id: str
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
    labeller: str = "rollout"


#: a labelled decision: (view row or None if not labelled, deltas, the labeller's action,
#: whether the action is forced -- the only allowed one, no behaviour or exploration asked)
_Label = tuple[dict[str, np.ndarray] | None, np.ndarray | None, int, bool]


def _cl_label(labeller: Any, view: Any, obs: dict[str, Any], n: int) -> _Label:
    """Rollout's scores of stop and its ``top_k`` pairs (exact ties are not labelled)."""
    mask = np.asarray(obs["action_mask"], dtype=bool)
    if not mask[:-1].any():
        return None, None, n - 1, True  # stop is the only allowed action
    choice, scores = labeller.scores()
    values = list(scores.values())
    if not max(values) > min(values):  # every pair a no-op (DMV w* = 1): no label
        return None, None, choice, False
    row = view(obs)
    allowed = np.asarray(row["action_mask"], dtype=bool)
    d = np.full(n, np.inf)
    for a, value in scores.items():
        if allowed[a]:  # a restricted view (top-k) may differ on exact gain ties
            d[a] = -value
    return (row, d, choice, False) if np.isfinite(d).sum() > 1 else (None, None, choice, False)


def _landmark_label(labeller: Any, view: Any, obs: dict[str, Any], n: int) -> _Label:
    """A landmark's label: minus the best score of rollout's candidate subsets containing it."""
    best, scores = labeller.scores()
    d = np.full(n, np.inf)
    for subset, value in scores.items():
        for lm in subset:
            d[lm] = min(d[lm], -value)
    finite = np.isfinite(d)
    if finite.sum() > 1 and np.ptp(d[finite]) > 0:
        return view(obs), d, best[0], False
    return None, None, best[0], False


def _labeller(job: _Job) -> tuple[Any, Any]:
    from selenv.families.cooperative.rollout import CLRolloutAgent
    from selenv.families.landmarks.fast_rollout import LandmarkFastRolloutAgent
    from selenv.families.landmarks.rollout import LandmarkRolloutAgent

    if job.env_id == CL_ID:
        return CLRolloutAgent(top_k=job.top_k, horizon=job.horizon), _cl_label
    if job.labeller == "fast_rollout":
        return LandmarkFastRolloutAgent(top_k=job.top_k, horizon=job.horizon), _landmark_label
    return LandmarkRolloutAgent(top_k=job.top_k, horizon=job.horizon), _landmark_label


def _collect(job: _Job) -> RankingData | None:
    """One worker's share of the labels (``None``: abandoned on the pool's stop request)."""
    try:
        with stoppable():
            return _collect_share(job)
    except TaskStopped:
        return None


def _collect_share(job: _Job) -> RankingData:
    th.set_num_threads(1)  # one worker per core
    env = gym.make(job.env_id, **job.env_kwargs)
    view = view_for(job.env_id, env, job.view)
    labeller, label = _labeller(job)
    agent = None
    if job.behaviour is not None:
        from selenv.learned.rl.agent import SB3PolicyAgent

        agent = SB3PolicyAgent(job.behaviour, env_id=job.env_id)
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
        row, d, action, forced = label(labeller, view, obs, n)
        if row is not None and d is not None:
            rows.append(row)
            deltas.append(d)
            bar.update(1)
        if not forced:
            if agent is not None:  # DAgger: the learner's own states, the labeller's labels
                action = int(agent.act(obs, info))
            if rng.random() < job.explore:
                action = int(rng.choice(np.flatnonzero(obs["action_mask"])))
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            obs, info = reset()
    bar.close()
    env.close()
    stacked = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    return RankingData(stacked, np.stack(deltas))


def _collect_all(
    env_id: str,
    env_kwargs: dict[str, Any],
    n_states: int,
    seed: int,
    view: str | None,
    top_k: int,
    horizon: int,
    explore: float,
    behaviour: str | None,
    workers: int,
    progress: bool,
    labeller: str = "rollout",
) -> RankingData:
    """Validate the options, split the work over ``workers`` processes, stack the labels."""
    for name, value, low in (("n_states", n_states, 1), ("workers", workers, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if not 0.0 <= explore <= 1.0:
        raise ValueError(f"explore must be in [0, 1], got {explore!r}")
    workers = min(workers, n_states)
    shares = [n_states // workers + (w < n_states % workers) for w in range(workers)]
    jobs = [
        _Job(
            env_id,
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
            labeller,
        )
        for w in range(workers)
    ]
    _labeller(jobs[0])  # validates top_k / horizon before any process starts
    if workers == 1:
        return _collect_share(jobs[0])
    with ProcessExecutor(workers) as pool:
        parts = pool.map(_collect, jobs, progress=False)
    done = [p for p in parts if p is not None]
    if len(done) < len(parts):  # a worker stopped by a Ctrl-C to the process group
        raise KeyboardInterrupt
    return RankingData.concatenate(done)


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
        env_kwargs: ``CLScheduling-v1`` keyword arguments (``{}``: the benchmark preset).
        n_states: labelled decisions to collect (each with actions of different scores).
        seed: training seed (episode seeds: :func:`train_seed`).
        view: candidate view of the policy; ``cl_pairs_fused_top3`` allows exactly the
            labeller's candidates (stop and the ``top_k`` pairs by previewed gain).
        top_k: pairs the labeller scores per decision (besides stop).
        horizon: filter steps the labeller simulates after the current one.
        explore: probability of a random allowed action instead of the behaviour's.
        behaviour: checkpoint whose (deterministic) actions drive the trajectories (DAgger);
            ``None``: the labeller's own choices.
        workers: processes (spawned; the caller needs the ``__main__`` guard if > 1); they
            die with the caller and are stopped when it is interrupted.
        progress: tqdm bar (first worker).

    Raises:
        ValueError: ``n_states``, ``workers``, ``top_k`` < 1, ``horizon`` < 0, or ``explore``
            outside [0, 1].
    """
    return _collect_all(
        CL_ID,
        env_kwargs,
        n_states,
        seed,
        view,
        top_k,
        horizon,
        explore,
        behaviour,
        workers,
        progress,
    )


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
    labeller: str = "rollout",
) -> RankingData:
    """Label ``LandmarkSelection-v1`` picks with the landmark ``rollout`` reference's scores.

    At every pick the labeller scores its candidate subsets of the picks left in the filter
    step (``top_k`` by one-step gain plus brute force's own); a landmark's ``dJ`` is minus the
    best score of a candidate subset containing it, ``+inf`` if none does. The behaviour
    plays the first landmark of rollout's best subset (or ``behaviour``'s pick: DAgger).
    Picks where all labelled landmarks tie are skipped. Same seeds and options as
    :func:`collect_cl_rollout_labels`, plus ``labeller``: ``"rollout"``
    (:class:`~selenv.families.landmarks.rollout.LandmarkRolloutAgent`) or ``"fast_rollout"``
    (:class:`~selenv.families.landmarks.fast_rollout.LandmarkFastRolloutAgent`: the same
    forecast on a shortlist of the 6 landmarks with the largest single gain, 11-15x cheaper
    per label).

    Raises:
        ValueError: as :func:`collect_cl_rollout_labels`; ``labeller`` not one of the two.
    """
    if labeller not in LANDMARK_LABELLERS:
        raise ValueError(f"labeller must be one of {LANDMARK_LABELLERS}, got {labeller!r}")
    return _collect_all(
        LANDMARK_ID,
        env_kwargs,
        n_states,
        seed,
        None,
        top_k,
        horizon,
        explore,
        behaviour,
        workers,
        progress,
        labeller,
    )
