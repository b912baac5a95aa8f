"""Stable-Baselines3 ``VecEnv`` over a native selenv vector env (and its candidate view).

SB3 trains on a ``VecEnv``; its :class:`~stable_baselines3.common.vec_env.DummyVecEnv` steps
``B`` Python envs one after the other. :class:`NativeVecEnv` instead drives one
:class:`~selenv.envs.vector.BatchedVectorEnv` (``gymnasium.make_vec(id, num_envs=B)``), whose
step is one batched numpy computation over the ``B`` sub-envs, and converts between the two
conventions:

* **Autoreset**: SB3 expects the reset to happen in the step that ended the episode (the
  returned observation is the next episode's first, the last one is in
  ``infos[b]["terminal_observation"]``); Gymnasium's native vector envs reset in the next step
  (``NEXT_STEP``). The adapter resets the finished sub-envs at once with
  ``reset(options={"reset_mask": done})`` -- without a seed, so each continues its own
  generator exactly as the ``NEXT_STEP`` autoreset (and ``DummyVecEnv``'s ``env.reset()``)
  would: the episodes are the same as with ``DummyVecEnv`` over ``gymnasium.make`` envs seeded
  alike (tested).
* **Truncation**: ``infos[b]["TimeLimit.truncated"]`` is ``truncated and not terminated``.
* **Masks**: ``env_method("action_masks")`` returns the ``B`` masks, so
  :func:`sb3_contrib.common.maskable.utils.get_action_masks` and MaskablePPO work.
* **Candidate views**: a pure :class:`~selenv.envs.views.CandidateView` (a function of the
  observation alone) is applied to each sub-env's observation and ``view.env_action`` maps the
  policy's candidate back to the env's action. A view that reads the live env (the previewed
  fused gains of ``cl_pairs_fused``) is built once per sub-env on the vector env's
  ``sub_env(b)`` proxy, which serves those reads from one batched computation (the CL vector
  env's ``preview_gains``); a vector env without ``sub_env`` refuses such views.
* **Copies**: observations are copied out of the vector env, so SB3's rollout buffer, which
  stores the previous observation after the step, never sees a buffer the step overwrote.

:func:`make_native_vec_env` builds it (wrapped in SB3's ``VecMonitor`` for episode statistics).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

from selenv.envs.views import CandidateView, IdentityView

__all__ = ["NativeVecEnv", "make_native_vec_env"]


def _index(tree: Any, b: int) -> Any:
    if isinstance(tree, dict):
        return {k: _index(v, b) for k, v in tree.items()}
    return np.array(tree[b], copy=True)


def _stack(rows: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]}


def _copy(tree: Any) -> Any:
    if isinstance(tree, dict):
        return {k: np.array(v, copy=True) for k, v in tree.items()}
    return np.array(tree, copy=True)


class NativeVecEnv(VecEnv):
    """SB3 ``VecEnv`` over a Gymnasium vector env with ``NEXT_STEP`` autoreset (see module doc).

    Args:
        venv: the vector env (``gymnasium.make_vec(id, num_envs=B)``); it must offer
            ``action_masks()`` returning ``(B, ...)`` masks.
        view: a pure candidate view applied per sub-env (``None``: the env's own observation),
            or a list of ``B`` views, one per sub-env (views that read the live env, built on
            ``venv.sub_env(b)``).

    Raises:
        ValueError: ``venv`` does not autoreset in ``NEXT_STEP`` mode, has no
            ``action_masks``, ``view`` is a single view that reads the live env, or a list of
            the wrong length.
    """

    def __init__(
        self,
        venv: gym.vector.VectorEnv,
        view: CandidateView | Sequence[CandidateView] | None = None,
    ) -> None:
        mode = venv.metadata.get("autoreset_mode")
        if mode is not None and mode != gym.vector.AutoresetMode.NEXT_STEP:
            raise ValueError(f"venv must autoreset in NEXT_STEP mode, got {mode}")
        if not callable(getattr(venv, "action_masks", None)):
            raise ValueError(f"venv {type(venv).__name__} has no action_masks() method")
        if isinstance(view, CandidateView) and view.live:
            raise ValueError(
                f"the candidate view {view.name!r} reads the live env (previewed updates): "
                "pass one view per sub-env, built on venv.sub_env(b)"
            )
        if isinstance(view, Sequence) and len(view) != venv.num_envs:
            raise ValueError(f"view: expected {venv.num_envs} views (one per sub-env)")
        self.venv = venv
        views: list[CandidateView] | None
        if view is None or isinstance(view, IdentityView):
            views = None
        elif isinstance(view, CandidateView):
            views = [view] * venv.num_envs
        else:
            views = list(view)
        self.views = views
        self.view = None if views is None else views[0]
        single = venv.single_observation_space
        obs_space = single if self.view is None else self.view.space(single)
        self._last_raw: Any = None
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, obs_space, venv.single_action_space)

    # -- SB3 VecEnv API --------------------------------------------------------------------------
    def reset(self) -> Any:  # noqa: D102
        seeds = list(self._seeds)
        opts = self._options[0] if all(o == self._options[0] for o in self._options) else None
        if opts is None:
            raise ValueError("per-sub-env reset options differ; the native vector env takes one")
        seed_arg = None if all(s is None for s in seeds) else seeds
        obs, infos = self.venv.reset(seed=seed_arg, options=dict(opts) or None)  # type: ignore[arg-type]
        self.reset_infos = self._split_infos(infos)
        self._reset_seeds()
        self._reset_options()
        return self._out(obs)

    def step_async(self, actions: np.ndarray) -> None:  # noqa: D102
        self._actions = np.asarray(actions)

    def step_wait(self) -> tuple[Any, np.ndarray, np.ndarray, list[dict[str, Any]]]:  # noqa: D102
        if self._actions is None:
            raise RuntimeError("step_async() must come before step_wait()")
        acts = self._env_actions(self._actions)
        self._actions = None
        obs, rewards, terminated, truncated, infos = self.venv.step(acts)
        done = np.logical_or(terminated, truncated)
        out_infos = self._split_infos(infos)
        if done.any():
            for b in map(int, np.flatnonzero(done)):
                terminal = _index(obs, b)
                out_infos[b]["terminal_observation"] = (
                    terminal if self.views is None else self.views[b](terminal)
                )
                out_infos[b]["TimeLimit.truncated"] = bool(truncated[b] and not terminated[b])
            obs, reset_infos = self.venv.reset(options={"reset_mask": done})
            for b, info in enumerate(self._split_infos(reset_infos)):
                if done[b]:
                    self.reset_infos[b] = info
        return self._out(obs), np.asarray(rewards, np.float32), done, out_infos

    def close(self) -> None:  # noqa: D102
        self.venv.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:  # noqa: D102
        return [getattr(self.venv, attr_name) for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:  # noqa: D102
        setattr(self.venv, attr_name, value)

    def env_method(  # noqa: D102
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        idx = list(self._indices(indices))
        if method_name == "action_masks":
            masks = np.asarray(self.venv.action_masks(), dtype=np.bool_)  # type: ignore[attr-defined]
            return [masks[i].reshape(-1) for i in idx]
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in idx]

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:  # noqa: D102
        return [False for _ in self._indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:  # noqa: D102
        frames: Any = self.venv.render()
        return [None] * self.num_envs if frames is None else list(frames)

    def action_masks(self) -> np.ndarray:
        """``(B, n)`` boolean masks (flattened per sub-env, MaskablePPO's layout)."""
        masks = np.asarray(self.venv.action_masks(), dtype=np.bool_)  # type: ignore[attr-defined]
        return masks.reshape(self.num_envs, -1)

    # -- helpers ---------------------------------------------------------------------------------
    def _indices(self, indices: Any) -> Iterable[int]:
        if indices is None:
            return range(self.num_envs)
        if isinstance(indices, int | np.integer):
            return [int(indices)]
        return [int(i) for i in indices]

    def _out(self, obs: Any) -> Any:
        self._last_raw = obs
        if self.views is None:
            return _copy(obs)
        return _stack([self.views[b](_index(obs, b)) for b in range(self.num_envs)])

    def _env_actions(self, actions: np.ndarray) -> np.ndarray:
        if self.views is None:
            return actions
        rows = [
            self.views[b].env_action(_index(self._last_raw, b), int(actions[b]))
            for b in range(self.num_envs)
        ]
        return np.asarray(rows)

    def _split_infos(self, infos: dict[str, Any]) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for key, values in infos.items():
            if key.startswith("_"):
                continue
            have = infos.get("_" + key)
            for b in range(self.num_envs):
                if have is None or have[b]:
                    out[b][key] = values[b]
        return out


def make_native_vec_env(
    env_id: str,
    n_envs: int,
    *,
    seed: int | None = None,
    view: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    monitor: bool = True,
) -> VecEnv:
    """``VecMonitor(NativeVecEnv(gymnasium.make_vec(env_id, n_envs, **env_kwargs), view))``.

    Args:
        env_id: a selenv id with a native vector env.
        n_envs: ``B``.
        seed: seeds sub-env ``b`` with ``seed + b`` at the first reset (SB3's ``VecEnv.seed``).
        view: name of the candidate view (:func:`selenv.learned.rl.views.view_for`; built
            from one single env of the same keywords); ``None``: the env's observation.
        env_kwargs: the env's keywords.
        monitor: wrap in SB3's ``VecMonitor`` (episode returns and lengths for the logs).

    Raises:
        ValueError: ``env_id`` has no native vector env, or the view reads the live env and
            the vector env cannot serve it (no ``sub_env``).
    """
    from selenv.envs.vector import BatchedVectorEnv

    kwargs = dict(env_kwargs or {})
    venv = gym.make_vec(env_id, num_envs=n_envs, **kwargs)
    if not isinstance(venv, BatchedVectorEnv):
        venv.close()
        raise ValueError(f"{env_id} has no native vector env (gymnasium.make_vec looped)")
    cand: CandidateView | list[CandidateView] | None = None
    if view is not None:
        from selenv.learned.rl.views import view_for

        template = gym.make(env_id, **kwargs)
        cand = view_for(env_id, template, view)
        template.close()
        if cand.live:
            sub_env = getattr(venv, "sub_env", None)
            if not callable(sub_env):
                venv.close()
                raise ValueError(
                    f"the candidate view {view!r} reads the live env (previewed updates), "
                    f"which {type(venv).__name__} does not serve (no sub_env); train it "
                    "with vec_env='dummy'"
                )
            cand = [view_for(env_id, sub_env(b), view) for b in range(n_envs)]
    out: VecEnv = NativeVecEnv(venv, cand)
    if seed is not None:
        out.seed(seed)
    return VecMonitor(out) if monitor else out
