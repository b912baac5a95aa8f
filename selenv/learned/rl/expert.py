"""Expert iteration: a non-myopic lookahead reference as the labeller of a policy's states.

A labeller is an agent that scores the candidate actions of a decision by simulating ahead on
the forecast (no truth, no future noise), such as a family's ``rollout`` reference. Its scores
are a dense label of a state: each evaluated action gets ``dJ`` (lower is better, the
convention of :class:`selenv.learned.rl.ranking.RankingData`); the actions it did not evaluate
get ``+inf`` -- ListNet's target is then 0 on them, so the policy learns to rank them last. A
policy fitted to these labels (:func:`selenv.learned.rl.ranking.fit_ranking`) plays the
labeller's choice for the price of one network evaluation.

DAgger (Ross et al. 2011): round 0 follows the labeller's own choices; later rounds follow
the current learner (``behaviour``), so the labels cover the states the learner visits.

This module is the collection loop that every family's labeller shares
(:func:`collect_rollout_labels`); a family's learned module supplies the labeller (a
:data:`Labeller`: the agent and how it labels one decision) and its ``collect_*`` entry
point: :func:`selenv.learned.families.cooperative.collect_cl_rollout_labels`,
:func:`selenv.learned.families.landmarks.collect_landmark_rollout_labels`.

The workers are a :class:`selenv.parallel.ProcessExecutor` pool: they die with this process
(even after ``kill -9``), and a SIGINT / SIGTERM of the caller during a collection abandons
it (the workers stop at once, nothing is left running).

Seeds: training episodes are seeded ``10**6 * (seed + 1) + k`` (``k = 0, 1, ...`` per
worker stride), disjoint from the held-out evaluation seeds ``< 10**6`` of the docs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from tqdm.auto import tqdm

import selenv  # noqa: F401  (registers the envs, also in worker processes)
from selenv.learned.rl._moved import moved_attr
from selenv.learned.rl.ranking import RankingData
from selenv.learned.rl.views import view_for
from selenv.parallel import ProcessExecutor, TaskStopped, stoppable

__all__ = [
    "TRAIN_SEED_BASE",
    "Label",
    "LabelFn",
    "Labeller",
    "collect_rollout_labels",
    "collect_shares",
    "train_seed",
]

#: training episode seeds start at ``TRAIN_SEED_BASE * (seed + 1)``
TRAIN_SEED_BASE = 10**6

#: a labelled decision: (view row or None if not labelled, deltas, the labeller's action,
#: whether the action is forced -- the only allowed one, no behaviour or exploration asked)
Label = tuple[dict[str, np.ndarray] | None, np.ndarray | None, int, bool]
#: how a decision is labelled: ``label(agent, view, obs, n_actions)``
LabelFn = Callable[[Any, Any, dict[str, Any], int], Label]
#: a family's labeller: ``labeller(top_k, horizon) -> (agent, label)``; a module-level function
#: (or a ``functools.partial`` of one) so that it reaches the worker processes; it raises
#: ``ValueError`` on a bad ``top_k`` / ``horizon``
Labeller = Callable[[int, int], tuple[Any, LabelFn]]


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
    labeller: Labeller


def _stoppable_share(share: Callable[[Any], RankingData], job: Any) -> RankingData | None:
    """One worker's share of the labels (``None``: abandoned on the pool's stop request)."""
    try:
        with stoppable():
            return share(job)
    except TaskStopped:
        return None


def collect_shares(share: Callable[[Any], RankingData], jobs: Sequence[Any]) -> RankingData:
    """``share(job)`` for every job, stacked: in this process for one job, else one worker each.

    ``share`` is a module-level function (it reaches spawned workers by reference; a script
    that collects with more than one job needs the ``if __name__ == "__main__":`` guard). The
    workers are a :class:`selenv.parallel.ProcessExecutor` pool: they die with this process,
    and a SIGINT / SIGTERM of the caller abandons the collection (``KeyboardInterrupt``).
    """
    if len(jobs) == 1:
        return share(jobs[0])
    with ProcessExecutor(len(jobs)) as pool:
        parts = pool.map(partial(_stoppable_share, share), jobs, progress=False)
    done = [p for p in parts if p is not None]
    if len(done) < len(parts):  # a worker stopped by a Ctrl-C to the process group
        raise KeyboardInterrupt
    return RankingData.concatenate(done)


def _collect_share(job: _Job) -> RankingData:
    th.set_num_threads(1)  # one worker per core
    env = gym.make(job.env_id, **job.env_kwargs)
    view = view_for(job.env_id, env, job.view)
    labeller, label = job.labeller(job.top_k, job.horizon)
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


def collect_rollout_labels(
    env_id: str,
    env_kwargs: dict[str, Any],
    n_states: int,
    seed: int,
    *,
    labeller: Labeller,
    view: str | None,
    top_k: int,
    horizon: int,
    explore: float = 0.05,
    behaviour: str | None = None,
    workers: int = 1,
    progress: bool = True,
) -> RankingData:
    """Label ``n_states`` decisions of ``env_id`` with ``labeller``'s scores.

    Args:
        env_id: the env's id.
        env_kwargs: its keyword arguments.
        n_states: labelled decisions to collect.
        seed: training seed (episode seeds: :func:`train_seed`).
        labeller: the family's labeller (:data:`Labeller`), built with ``top_k`` and
            ``horizon`` in each worker.
        view: candidate view of the policy (``None``: the env's first,
            :func:`~selenv.learned.rl.views.view_for`).
        top_k: the labeller's ``top_k``.
        horizon: the labeller's ``horizon``.
        explore: probability of a random allowed action instead of the behaviour's.
        behaviour: checkpoint whose (deterministic) actions drive the trajectories (DAgger);
            ``None``: the labeller's own choices.
        workers: processes (spawned; the caller needs the ``__main__`` guard if > 1); they
            die with the caller and are stopped when it is interrupted.
        progress: tqdm bar (first worker).

    Raises:
        ValueError: ``n_states`` or ``workers`` < 1, ``explore`` outside [0, 1], or the
            labeller's refusal of ``top_k`` / ``horizon`` (before any process starts).
    """
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
    labeller(top_k, horizon)  # validates top_k / horizon before any process starts
    return collect_shares(_collect_share, jobs)


#: names that moved to the families' learned modules (deprecated here, for one release)
_MOVED = {
    **dict.fromkeys(("CL_ID", "collect_cl_rollout_labels"), "selenv.learned.families.cooperative"),
    **dict.fromkeys(
        ("LANDMARK_ID", "LANDMARK_LABELLERS", "collect_landmark_rollout_labels"),
        "selenv.learned.families.landmarks",
    ),
}


def __getattr__(name: str) -> Any:
    """A moved name (``_MOVED``), with a ``DeprecationWarning`` naming its new module."""
    return moved_attr(__name__, name, _MOVED)
