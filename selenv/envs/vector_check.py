"""Check that a native vector env replays the single env, sub-env by sub-env.

:func:`check_vector_equivalence` drives ``gymnasium.make_vec(env_id, num_envs=B)`` and ``B``
single envs ``gymnasium.make(env_id)`` (reset with the same seeds) with the same actions, and
compares everything they return: observations, rewards, the termination and truncation flags,
the action masks and the infos the single env reports, across autoresets (``NEXT_STEP``: the
step after an episode ended, the single env is reset without a seed, as the vector env resets
that sub-env with its own generator, and the action is ignored).

Tolerances (the portability contract: decisions identical, values within rtol 1e-9): integer
and boolean arrays (masks, selections, flags) must be equal; float64 values agree to
``rtol=1e-9, atol=1e-12``; float32 observations to ``rtol=3e-7`` (two float32 ulps: a float64
difference in the last bits can move a float32 rounding by one ulp) and ``atol=1e-6``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

__all__ = ["ActionPicker", "check_vector_equivalence", "random_masked_action"]

#: ``picker(b, env, mask, rng) -> action`` for sub-env ``b`` given its single env and mask
ActionPicker = Callable[[int, gym.Env[Any, Any], np.ndarray, np.random.Generator], Any]


def random_masked_action(
    b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator
) -> Any:
    """A uniformly random allowed action of a ``Discrete`` or ``MultiDiscrete`` mask."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim == 1:
        return int(rng.choice(np.flatnonzero(m)))
    return np.array([int(rng.choice(np.flatnonzero(row))) for row in m], dtype=np.int64)


def _compare(a: Any, b: Any, where: str) -> None:
    if isinstance(a, dict):
        if not isinstance(b, dict) or set(a) != set(b):
            raise AssertionError(f"{where}: keys differ: {sorted(a)} vs {sorted(b)}")
        for key in a:
            _compare(a[key], b[key], f"{where}[{key!r}]")
        return
    x, y = np.asarray(a), np.asarray(b)
    if x.shape != y.shape:
        raise AssertionError(f"{where}: shape {x.shape} vs {y.shape}")
    if x.dtype.kind in "fc" or y.dtype.kind in "fc":
        single = x.dtype == np.float32 or y.dtype == np.float32
        rtol, atol = (3e-7, 1e-6) if single else (1e-9, 1e-12)
        np.testing.assert_allclose(x, y, rtol=rtol, atol=atol, err_msg=where)
    elif x.dtype == object or y.dtype == object:
        if x.tolist() != y.tolist():
            raise AssertionError(f"{where}: {x!r} != {y!r}")
    else:
        np.testing.assert_array_equal(x, y, err_msg=where)


def _masks(env: gym.Env[Any, Any]) -> np.ndarray:
    return np.asarray(env.unwrapped.action_masks())  # type: ignore[attr-defined]


def check_vector_equivalence(
    env_id: str,
    *,
    num_envs: int = 4,
    seeds: Sequence[int] | None = None,
    steps: int = 60,
    picker: ActionPicker = random_masked_action,
    info_keys: Sequence[str] | None = None,
    rng: np.random.Generator | None = None,
    **kwargs: Any,
) -> dict[str, int]:
    """Drive the vector env and ``num_envs`` single envs in lock-step; raise on any difference.

    Args:
        env_id: a registered id with a native vector env.
        num_envs: ``B``.
        seeds: one seed per sub-env (default ``0, 1, ..., B-1``).
        steps: vector steps to take (autoresets included).
        picker: chooses each sub-env's action from its single env (random masked by default;
            a heuristic agent's ``act`` wrapped as a picker checks the heuristics' episodes).
        info_keys: the info keys to compare (default: every key the single env reports that
            the vector env reports too).
        rng: generator of the picker (default ``np.random.default_rng(0)``).
        **kwargs: the env keywords, given to both ``make_vec`` and ``make``.

    Returns:
        counts: ``{"steps": ..., "episodes": ..., "autoresets": ...}``.

    Raises:
        AssertionError: naming the step, sub-env and field that differ.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    seeds = list(range(num_envs)) if seeds is None else list(seeds)
    venv = gym.make_vec(env_id, num_envs=num_envs, **kwargs)
    envs = [gym.make(env_id, **kwargs) for _ in range(num_envs)]
    counts = {"steps": 0, "episodes": 0, "autoresets": 0}
    try:
        vobs, vinfo = venv.reset(seed=seeds)  # type: ignore[arg-type]  # a list: Gymnasium's too
        singles = [env.reset(seed=s) for env, s in zip(envs, seeds, strict=True)]
        _check_batch(
            venv,
            envs,
            vobs,
            vinfo,
            [o for o, _ in singles],
            [i for _, i in singles],
            info_keys,
            "reset",
        )
        ended = np.zeros(num_envs, dtype=bool)
        for t in range(steps):
            masks = [_masks(env) for env in envs]
            actions = [picker(b, envs[b], masks[b], rng) for b in range(num_envs)]
            vobs, vrew, vterm, vtrunc, vinfo = venv.step(np.asarray(actions))
            obs, infos = [], []
            for b, env in enumerate(envs):
                where = f"step {t}, sub-env {b}"
                if ended[b]:
                    o, info = env.reset()
                    r: SupportsFloat = 0.0
                    te, tr = False, False
                    counts["autoresets"] += 1
                else:
                    o, r, te, tr, info = env.step(actions[b])
                    counts["episodes"] += bool(te or tr)
                _compare(vrew[b], r, f"{where}: reward")
                if bool(vterm[b]) != bool(te) or bool(vtrunc[b]) != bool(tr):
                    raise AssertionError(
                        f"{where}: flags (terminated, truncated) {(vterm[b], vtrunc[b])} vs "
                        f"{(te, tr)}"
                    )
                ended[b] = bool(te or tr)
                obs.append(o)
                infos.append(info)
            _check_batch(venv, envs, vobs, vinfo, obs, infos, info_keys, f"step {t}")
            counts["steps"] += 1
    finally:
        venv.close()
        for env in envs:
            env.close()
    return counts


def _check_batch(
    venv: Any,
    envs: list[gym.Env[Any, Any]],
    vobs: Any,
    vinfo: dict[str, Any],
    obs: list[Any],
    infos: list[dict[str, Any]],
    info_keys: Sequence[str] | None,
    when: str,
) -> None:
    vmask = np.asarray(venv.action_masks())
    for b, env in enumerate(envs):
        where = f"{when}, sub-env {b}"
        sub = _index(vobs, b)
        _compare(sub, obs[b], f"{where}: observation")
        _compare(vmask[b], _masks(env), f"{where}: action mask")
        keys = info_keys if info_keys is not None else [k for k in infos[b] if k in vinfo]
        for key in keys:
            if key not in vinfo or not vinfo["_" + key][b]:
                raise AssertionError(f"{where}: info {key!r} missing from the vector env")
            _compare(vinfo[key][b], infos[b][key], f"{where}: info[{key!r}]")


def _index(tree: Any, b: int) -> Any:
    if isinstance(tree, dict):
        return {k: _index(v, b) for k, v in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_index(v, b) for v in tree)
    return np.asarray(tree)[b]
