"""Pre-training a candidate-scoring policy to rank actions by their exact one-step value.

Where an env has a cheap exact oracle of the objective after each candidate action (the
Algorithm 1 cost of every local edit in ``ReceiverClustering-v1``), the oracle's values are
a far denser training signal than PPO's return: one labelled state scores *every* candidate.
This module collects such labels along an expert's trajectories and fits the policy's logits
to them with a listwise (ListNet, Cao et al. 2007) cross-entropy

    q_k = softmax_k(-dJ_k / (tau * std_allowed(dJ)))      over the allowed candidates k
    loss = - sum_k q_k log pi_k                            (pi = the policy's masked softmax)

where ``dJ_k = J(after k) - J(keep)`` (the no-op has ``dJ = 0``). The result is an ordinary
(Maskable)PPO checkpoint: it plays on its own (zero oracle calls per decision, the ranking's
top action) or as the proposal of a verified top-``k`` search
(:class:`selenv.learned.rl.agent.SB3PolicyAgent` with ``verify_top_k``), and PPO may fine-tune it.

    data = collect_clustering_ranking({"n_agents": 30}, n_states=3000, seed=0, workers=2)
    stats = fit_ranking(model.policy, data, epochs=15)
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from tqdm.auto import tqdm

import selenv  # noqa: F401  (registers the envs, also in worker processes)
from selenv.learned.rl.views import view_for

__all__ = [
    "RankingData",
    "clustering_edit_deltas",
    "collect_clustering_ranking",
    "fit_ranking",
    "listnet_targets",
]

CLUSTERING_ID = "selenv/ReceiverClustering-v1"


@dataclass
class RankingData:
    """Labelled states: candidate-view observations and the oracle's value of every action.

    Attributes:
        obs: candidate-view observations stacked over the ``S`` states (``key -> (S, ...)``).
        deltas: ``(S, N)`` objective change of each action (lower is better), ``+inf`` where
            the action is masked; the no-op (if any) has 0.
    """

    obs: dict[str, np.ndarray]
    deltas: np.ndarray

    def __post_init__(self) -> None:
        s = self.deltas.shape[0]
        bad = [k for k, v in self.obs.items() if v.shape[0] != s]
        if self.deltas.ndim != 2 or bad:
            raise ValueError(
                f"RankingData: deltas must be (S, N) and every obs entry have S={s} rows; "
                f"deltas {self.deltas.shape}, mismatched keys {bad}"
            )

    def __len__(self) -> int:
        return int(self.deltas.shape[0])

    @staticmethod
    def concatenate(parts: list[RankingData]) -> RankingData:
        """Stack several collections (same pool size)."""
        keys = parts[0].obs.keys()
        obs = {k: np.concatenate([p.obs[k] for p in parts]) for k in keys}
        return RankingData(obs, np.concatenate([p.deltas for p in parts]))


def clustering_edit_deltas(env: gym.Env[Any, Any]) -> np.ndarray:
    """``(1 + n^2 + n(n-1)/2,)`` change of the Algorithm 1 cost ``J`` by each edit, now.

    ``dJ_a = J(apply_edit(labels, a)) - J(labels)`` at the env's current time (what the
    greedy search compares); 0 for the no-op, ``+inf`` for masked edits. Costs one
    evaluation per allowed edit (counted by the env's filter bank).
    """
    from selenv.families.clustering.env import edit_cost_changes, edit_mask

    base = env.unwrapped
    bank = base.bank  # type: ignore[attr-defined]
    mask = edit_mask(bank.labels, base.max_size)  # type: ignore[attr-defined]
    out = np.full(mask.size, np.inf)
    allowed = np.flatnonzero(mask)
    out[allowed] = edit_cost_changes(bank, allowed)
    return out


@dataclass(frozen=True)
class _Job:
    env_kwargs: dict[str, Any]
    n_states: int
    seed: int
    label_every: int
    explore: float
    progress: bool
    behaviour: str | None
    behaviour_top_k: int


def _collect_worker(job: _Job) -> RankingData:
    env = gym.make(CLUSTERING_ID, **{**job.env_kwargs, "action_mode": "edit"})
    view = view_for(CLUSTERING_ID, env)
    rng = np.random.default_rng(job.seed)
    agent = None
    if job.behaviour is not None:
        from selenv.learned.rl.agent import SB3PolicyAgent

        th.set_num_threads(1)  # one worker per core

        agent = SB3PolicyAgent(
            job.behaviour, env_id=CLUSTERING_ID, verify_top_k=job.behaviour_top_k
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
    this with ``workers > 1`` needs the ``if __name__ == "__main__":`` guard) share the work.

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
        _Job(
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
    if workers == 1:
        return _collect_worker(jobs[0])
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return RankingData.concatenate(list(pool.map(_collect_worker, jobs)))


def listnet_targets(deltas: np.ndarray, temperature: float) -> np.ndarray:
    """ListNet target distribution ``q`` ``(S, N)`` from the oracle's ``dJ`` (lower is better).

    ``q = softmax(-dJ / (temperature * s))`` over the allowed actions of each state, with ``s``
    the spread (std) of that state's allowed ``dJ`` (so ``temperature`` is scale-free); masked
    actions get 0. A state whose allowed actions all tie gets the uniform distribution.

    Raises:
        ValueError: ``temperature <= 0`` or a state without any allowed action.
    """
    if not temperature > 0.0:
        raise ValueError(f"temperature must be > 0, got {temperature!r}")
    d = np.asarray(deltas, dtype=np.float64)
    allowed = np.isfinite(d)
    if not np.all(allowed.any(axis=1)):
        raise ValueError("every state needs at least one allowed action (a finite delta)")
    dz = np.where(allowed, d, 0.0)
    count = allowed.sum(axis=1, keepdims=True)
    mean = dz.sum(axis=1, keepdims=True) / count
    spread = np.sqrt((np.where(allowed, d - mean, 0.0) ** 2).sum(axis=1, keepdims=True) / count)
    z = -(dz - dz.min(axis=1, keepdims=True, initial=np.inf, where=allowed))
    z = z / (temperature * np.where(spread > 0.0, spread, 1.0))
    w = np.where(allowed, np.exp(z), 0.0)
    return w / w.sum(axis=1, keepdims=True)


def fit_ranking(
    policy: Any,
    data: RankingData,
    *,
    epochs: int = 15,
    batch_size: int = 32,
    learning_rate: float = 1e-3,
    temperature: float = 0.1,
    val_fraction: float = 0.1,
    seed: int = 0,
    progress: bool = True,
) -> dict[str, float]:
    """Fit the policy's action logits to the ListNet targets of ``data`` (Adam, in place).

    Only the actor's path (the features extractor's scores) is trained; the value head is
    left for PPO. Returns metrics on the held-out ``val_fraction`` of the states: the
    cross-entropy, ``top1`` (the policy's top action is the oracle's best) and ``regret``
    (mean ``dJ`` of the policy's top action minus the oracle's best, >= 0).

    Raises:
        ValueError: ``epochs < 1``, ``batch_size < 1`` or ``val_fraction`` outside [0, 1).
    """
    if epochs < 1 or batch_size < 1 or not 0.0 <= val_fraction < 1.0:
        raise ValueError(
            f"need epochs >= 1, batch_size >= 1, 0 <= val_fraction < 1; got {epochs}, "
            f"{batch_size}, {val_fraction}"
        )
    q_all = listnet_targets(data.deltas, temperature)
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(data))
    n_val = round(val_fraction * len(data))
    val, train = order[:n_val], order[n_val:]
    if train.size == 0:
        raise ValueError(
            f"no training states left: {len(data)} states, val_fraction {val_fraction}"
        )
    extractor = policy.pi_features_extractor
    optim = th.optim.Adam(extractor.parameters(), lr=learning_rate)
    n = data.deltas.shape[1]

    def logits(idx: np.ndarray) -> th.Tensor:
        obs = {k: th.as_tensor(v[idx], dtype=th.float32) for k, v in data.obs.items()}
        return th.log_softmax(extractor(obs)[:, :n], dim=1)

    policy.set_training_mode(True)
    bar = tqdm(total=epochs * train.size, desc="ranking fit", unit="state", disable=not progress)
    for _ in range(epochs):
        rng.shuffle(train)
        for start in range(0, train.size, batch_size):
            idx = train[start : start + batch_size]
            q = th.as_tensor(q_all[idx], dtype=th.float32)
            loss = -(q * logits(idx)).sum(dim=1).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
            bar.update(idx.size)
            bar.set_postfix(loss=f"{loss.item():.4f}")
    bar.close()
    policy.set_training_mode(False)
    eval_idx = val if val.size else train
    with th.no_grad():
        logp = th.cat([logits(eval_idx[s : s + 256]) for s in range(0, eval_idx.size, 256)])
    q = th.as_tensor(q_all[eval_idx], dtype=th.float32)
    ce = float(-(q * logp).sum(dim=1).mean())
    top = logp.argmax(dim=1).numpy()
    d = data.deltas[eval_idx]
    best = np.min(d, axis=1)
    return {
        "states_train": int(train.size),
        "states_eval": int(eval_idx.size),
        "cross_entropy": round(ce, 5),
        "top1": round(float(np.mean(top == np.argmin(d, axis=1))), 4),
        "regret": float(np.mean(d[np.arange(top.size), top] - best)),
    }
