r"""Record short seeded episodes of the registered env ids, to pin what an env version does.

Run against a checkout of the release that defines a version, e.g. for ``-v0`` (release 0.1,
commit ``c70af56``)::

    git worktree add /tmp/selenv-0.1 c70af56
    PYTHONPATH=/tmp/selenv-0.1 python scripts/record_version_episodes.py --version v0 \
        --out tests/data/episodes_v0.json --source "release 0.1, commit c70af56"

The episodes use only the public API that every release has (``reset(seed=...)``,
``action_masks()``, ``step``) and a seeded policy over the *valid* actions, so the record is
what the version does with valid actions; ``tests/test_env_versions.py`` replays the same
actions on today's ids and compares decisions (the valid action sets, as digests of their int
indices) exactly and rewards to ``rtol = 1e-9``.
The output is written atomically (temporary file, then rename).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import selenv
from selenv.atomic import write_text

#: (family id without version, gymnasium.make keywords) of every recorded case
CASES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("selenv/CLScheduling", {}),
    ("selenv/FIMSelection", {}),
    ("selenv/FIMSelection", {"preset": "example1", "n_candidates": 30}),
    ("selenv/FIMSelection", {"preset": "example3"}),
    ("selenv/LandmarkSelection", {}),
    ("selenv/ReceiverClustering", {}),
    ("selenv/ReceiverClustering", {"n_agents": 12, "horizon": 40}),
)
#: (PettingZoo module name without version, parallel_env keywords) of every recorded case
MULTIAGENT_CASES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("selenv.multiagent.receiver_clustering", {"n_agents": 8, "horizon": 30}),
    ("selenv.multiagent.receiver_clustering", {}),
    ("selenv.multiagent.fim_selection", {}),
)
SEEDS = (0, 1, 2)
STEPS = 12


def policy_action(env: gym.Env[Any, Any], rng: np.random.Generator) -> Any:
    """A seeded valid action: a uniform valid index, or for an assignment action one move."""
    base = env.unwrapped
    mask = np.asarray(base.action_masks(), dtype=bool)
    if isinstance(env.action_space, gym.spaces.Discrete):
        return int(rng.choice(np.flatnonzero(mask)))
    labels = np.array(base.bank.labels, dtype=np.int64)  # assignment mode: move one receiver
    n = labels.size
    i = int(rng.integers(n))
    labels[i] = int(rng.choice(np.flatnonzero(mask.reshape(n, n)[i])))
    return labels


def mask_digest(mask: Any) -> str:
    """The valid action indices of a mask as a short SHA-256 of int64 (a decision, no floats)."""
    idx = np.flatnonzero(np.asarray(mask, dtype=bool)).astype(np.int64)
    return hashlib.sha256(idx.tobytes()).hexdigest()[:16]


def record_episode(env_id: str, kwargs: dict[str, Any], seed: int) -> dict[str, Any]:
    """Actions, masks and rewards of one episode of at most :data:`STEPS` steps."""
    env = gym.make(env_id, **kwargs)
    rng = np.random.default_rng(1000 + seed)
    env.reset(seed=seed)
    actions, masks, rewards, ends = [], [], [], []
    for _ in range(STEPS):
        masks.append(mask_digest(env.unwrapped.action_masks()))
        action = policy_action(env, rng)
        _, reward, terminated, truncated, _ = env.step(action)
        actions.append(np.asarray(action).tolist())
        rewards.append(float(reward))
        ends.append([bool(terminated), bool(truncated)])
        if terminated or truncated:
            break
    env.close()
    return {"seed": seed, "actions": actions, "masks": masks, "rewards": rewards, "ends": ends}


def record_multiagent_episode(module: str, kwargs: dict[str, Any], seed: int) -> dict[str, Any]:
    """Per-agent actions, the masks and the per-agent rewards of one PettingZoo episode.

    Actions are seeded and valid by each agent's ``obs["action_mask"]``; a step's masks are
    digested together in the order of ``env.agents``.
    """
    env = importlib.import_module(module).parallel_env(**kwargs)
    rng = np.random.default_rng(1000 + seed)
    obs, _ = env.reset(seed=seed)
    actions, masks, rewards = [], [], []
    for _ in range(STEPS):
        if not env.agents:
            break
        agent_masks = [np.asarray(obs[a]["action_mask"], dtype=bool) for a in env.agents]
        masks.append(mask_digest(np.concatenate(agent_masks)))
        act = {
            a: int(rng.choice(np.flatnonzero(m)))
            for a, m in zip(env.agents, agent_masks, strict=True)
        }
        obs, rew, _, _, _ = env.step(act)
        actions.append(act)
        rewards.append({a: float(r) for a, r in sorted(rew.items())})
    env.close()
    return {"seed": seed, "actions": actions, "masks": masks, "rewards": rewards}


def write_atomic(path: Path, payload: dict[str, Any]) -> None:
    """Write compact JSON to ``path`` atomically (:func:`selenv.atomic.write_text`)."""
    write_text(path, json.dumps(payload, indent=None, separators=(",", ":")) + "\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--version", required=True, help="the id suffix to record, e.g. v0")
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--source", default="", help="what was checked out (release, commit)")
    args = parser.parse_args(argv)
    cases = []
    for family, kwargs in CASES:
        env_id = f"{family}-{args.version}"
        episodes = [record_episode(env_id, kwargs, s) for s in SEEDS]
        cases.append({"env_id": env_id, "kwargs": kwargs, "episodes": episodes})
    multiagent = []
    for family, kwargs in MULTIAGENT_CASES:
        module = f"{family}_{args.version}"
        episodes = [record_multiagent_episode(module, kwargs, s) for s in SEEDS]
        multiagent.append({"module": module, "kwargs": kwargs, "episodes": episodes})
    meta = {"selenv_version": selenv.__version__, "source": args.source}
    payload = {"recorded_with": meta, "steps": STEPS, "cases": cases, "multiagent": multiagent}
    write_atomic(args.out, payload)


if __name__ == "__main__":
    main()
