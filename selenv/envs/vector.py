"""The base of the native batched vector envs: one state with a leading batch axis.

Each Gymnasium family registers a :class:`BatchedVectorEnv` subclass as its
``vector_entry_point``, so ``gymnasium.make_vec("selenv/<Family>-v1", num_envs=B)`` returns it
(Gymnasium's ``vectorization_mode="sync"`` / ``"async"`` still give the Python loop over
``gymnasium.make`` envs). The subclass keeps the state of all ``B`` sub-envs in arrays with a
leading batch axis and steps them with the family's batched core functions, the same functions
its single env calls (the single env is the ``B = 1`` case), so the math exists once.

What this base does, the same way for every family:

* **Seeding** as :class:`gymnasium.vector.SyncVectorEnv` does: ``reset(seed=s)`` seeds sub-env
  ``b`` with ``s + b``, a list gives one seed per sub-env, ``None`` keeps (or, on the first
  reset, draws) each sub-env's generator. Sub-env ``b`` owns a generator made exactly as
  :meth:`gymnasium.Env.reset` makes one (:func:`gymnasium.utils.seeding.np_random`), so sub-env
  ``b`` reproduces ``gymnasium.make(id).reset(seed=s + b)`` driven by the same actions.
* **Autoreset** in Gymnasium's default ``NEXT_STEP`` mode: the step after a sub-env terminated
  or truncated resets it (with its own generator, as ``env.reset()`` without a seed would),
  returning its first observation with reward 0 and both flags false; its action is ignored.
  ``gymnasium.make_vec(id, num_envs=B, autoreset_mode=...)`` (or :meth:`set_autoreset_mode`)
  selects Gymnasium's other modes: ``SAME_STEP`` resets a finished sub-env within the step
  that ended it (its last observation and info in ``infos["final_obs"]`` /
  ``infos["final_info"]``, Gymnasium's keys), ``DISABLED`` never resets (stepping a finished
  sub-env is a ``RuntimeError``; reset it with ``options={"reset_mask": mask}``); TorchRL
  asks for one of these two. Every mode draws the same episodes for the same seeds.
* **Partial resets** with ``options={"reset_mask": mask}`` (``(B,)`` bool), as Gymnasium 1.1+.
* **Infos** batched the Gymnasium way: every key holds a ``(B,)`` (or ``(B, ...)``) array and
  ``"_key"`` a ``(B,)`` bool mask of the sub-envs that reported it.
* **Masks**: :meth:`action_masks` returns the ``(B, ...)`` masks (MaskablePPO's protocol).
* **Rendering**: ``render()`` returns the frames of every sub-env (a tuple, like
  ``SyncVectorEnv``); :meth:`render_env` draws one.
* **Sub-env attributes**: ``call``, ``get_attr`` and ``set_attr`` as ``SyncVectorEnv`` has them
  (:mod:`selenv.envs.vector_attrs`): generators, spec, metadata, spaces, masks, frames, the
  family's declared attributes and the user's own.
* **Memory**: above 256 sub-envs the memory ``num_envs`` needs is estimated before anything
  is allocated (:mod:`selenv.envs.vector_memory`); a ``ValueError`` naming ``num_envs``, the
  estimate and the available memory refuses a batch that would not fit.
* **Threads**: ``reset`` and ``step`` run with one BLAS thread (:func:`selenv.threads.small_blas`:
  the batched calls are many small matrices, which BLAS threads only slow down).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from selenv.envs.actions import INVALID_CODES
from selenv.envs.conventions import KnownKeywords
from selenv.envs.vector_attrs import SubEnvAttributes
from selenv.envs.vector_memory import PROBE_ABOVE, check_vector_memory
from selenv.scenarios.validation import ArgumentTypeError, describe
from selenv.threads import small_blas

__all__ = ["BatchedVectorEnv", "check_discrete_actions", "check_num_envs", "merge_infos"]

#: largest ``num_envs`` accepted (a guard against a typo allocating the machine's memory)
MAX_NUM_ENVS = 1 << 16


def check_num_envs(num_envs: Any) -> int:
    """``num_envs``: an int in ``[1, 65536]`` (bools and floats are refused)."""
    if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer):
        raise ArgumentTypeError(f"num_envs must be an int, got {describe(num_envs)}")
    if not 1 <= num_envs <= MAX_NUM_ENVS:
        raise ValueError(f"num_envs must lie in [1, {MAX_NUM_ENVS}], got {num_envs}")
    return int(num_envs)


def check_discrete_actions(actions: Any, num_envs: int, n: int, what: str) -> np.ndarray:
    """``(B,)`` int64 actions of ``Discrete(n)`` sub-envs: shape, dtype and range checked.

    ``(B, 1)`` is accepted. ``what`` names one sub-env's action in the messages
    (``"candidate index"``).

    Raises:
        ValueError: another shape, or an action outside ``[0, n)`` (naming the sub-env).
        TypeError: not integers (bools and floats are refused, never rounded).
    """
    arr = np.asarray(actions)
    if arr.shape not in ((num_envs,), (num_envs, 1)):
        raise ValueError(
            f"actions must have shape ({num_envs},) (one {what} per sub-env), got shape {arr.shape}"
        )
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
        raise ArgumentTypeError(
            f"actions must be integers in [0, {n}), got {describe(actions)} of dtype {arr.dtype}"
        )
    arr = arr.reshape(num_envs).astype(np.int64, copy=False)
    bad = (arr < 0) | (arr >= n)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"actions[{i}] (sub-env {i}) = {arr[i]} is out of range: expected an integer in "
            f"[0, {n})"
        )
    return arr


def merge_infos(infos: dict[str, Any], new: dict[str, Any], idx: np.ndarray, n: int) -> None:
    """Write the batched info ``new`` (values ``(len(idx), ...)``) into ``infos`` at ``idx``.

    Keys are created on first use as arrays over all ``n`` sub-envs (numeric values keep their
    dtype; anything else becomes an object array), with the ``"_key"`` mask Gymnasium's vector
    envs use; ``infos`` is updated in place.
    """
    for key, values in new.items():
        if key not in infos:
            arr = np.asarray(values) if not isinstance(values, list) else None
            if arr is not None and arr.dtype != object and arr.shape[:1] == (len(idx),):
                infos[key] = np.zeros((n, *arr.shape[1:]), arr.dtype)
            else:
                infos[key] = np.full(n, None, dtype=object)
            infos["_" + key] = np.zeros(n, dtype=np.bool_)
        target = infos[key]
        if target.dtype == object:
            for j, i in enumerate(idx):
                target[i] = values[j]
        else:
            target[idx] = values
        infos["_" + key][idx] = True


class BatchedVectorEnv(SubEnvAttributes, KnownKeywords, VectorEnv):
    """Base of the families' native vector envs (see the module docstring).

    Subclasses call :meth:`_setup` from ``__init__`` and implement:

    * :meth:`_reset_envs` ``(idx, options)``: draw new episodes for the sub-envs ``idx`` (a
      sorted ``(k,)`` int array) from ``self.np_randoms[i]``; return their batched infos;
    * :meth:`_step_envs` ``(actions, idx)``: step the sub-envs ``idx`` with ``actions`` (the
      rows of the batched action for them); return ``(rewards (k,), terminated (k,),
      truncated (k,), infos)``;
    * :meth:`_observe` ``()``: the batched observation of all sub-envs;
    * :meth:`action_masks` ``()``: the ``(B, ...)`` boolean masks;
    * :meth:`render_env` ``(i)`` if the family renders.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": ["rgb_array"],
        "invalid_codes": INVALID_CODES,
    }

    def __new__(cls, *args: Any, **kwargs: Any) -> BatchedVectorEnv:
        """Check the memory a large ``num_envs`` needs before ``__init__`` allocates it.

        Above :data:`selenv.envs.vector_memory.PROBE_ABOVE` sub-envs the memory is estimated
        (:func:`~selenv.envs.vector_memory.check_vector_memory`) and a ``ValueError`` naming
        ``num_envs``, the estimate and the available memory is raised when it does not fit.
        """
        num_envs = kwargs.get("num_envs", args[0] if args else 1)
        valid = isinstance(num_envs, int | np.integer) and not isinstance(num_envs, bool)
        if valid and PROBE_ABOVE < num_envs <= MAX_NUM_ENVS:
            rest = {k: v for k, v in kwargs.items() if k != "num_envs"}
            check_vector_memory(cls, int(num_envs), tuple(args[1:]), rest)
        return super().__new__(cls, *args, **kwargs)  # KnownKeywords: unknown keywords

    def _setup(
        self,
        num_envs: int,
        single_observation_space: spaces.Space[Any],
        single_action_space: spaces.Space[Any],
        render_mode: str | None,
    ) -> None:
        self.num_envs = check_num_envs(num_envs)
        self.single_observation_space = single_observation_space
        self.single_action_space = single_action_space
        self.observation_space = batch_space(single_observation_space, self.num_envs)
        self.action_space = batch_space(single_action_space, self.num_envs)
        self.render_mode = render_mode
        self.autoreset_mode = AutoresetMode.NEXT_STEP  # Gymnasium 1.1+ vector envs expose it
        self.metadata = {**type(self).metadata, "autoreset_mode": self.autoreset_mode}
        #: one generator per sub-env, made as :meth:`gymnasium.Env.reset` makes one
        self.np_randoms: list[np.random.Generator | None] = [None] * self.num_envs
        #: the seed each generator was made from (``-1`` once one is assigned by the user)
        self.np_random_seeds: list[int | None] = [None] * self.num_envs
        self._autoreset = np.zeros(self.num_envs, dtype=np.bool_)
        self._has_reset = False

    # -- gymnasium.vector API ----------------------------------------------------------------
    @small_blas
    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-env (or those of ``options["reset_mask"]``); see the module doc."""
        seeds = self._seeds(seed)
        opts = dict(options or {})
        mask = opts.pop("reset_mask", None)
        if mask is None:
            idx = np.arange(self.num_envs)
        else:
            if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
                raise ArgumentTypeError(
                    f"options['reset_mask'] must be a bool numpy array, got {describe(mask)}"
                )
            if mask.shape != (self.num_envs,) or not mask.any():
                raise ValueError(
                    f"options['reset_mask'] must have shape ({self.num_envs},) and a True "
                    f"entry, got shape {mask.shape} with {int(mask.sum())} True"
                )
            if not self._has_reset and not mask.all():
                raise RuntimeError("the first reset must reset every sub-env (no reset_mask)")
            idx = np.flatnonzero(mask)
        for i in idx:
            if seeds[i] is not None or self.np_randoms[i] is None:
                self.np_randoms[i], self.np_random_seeds[i] = seeding.np_random(seeds[i])
        infos = self._reset_envs(idx, opts)
        self._autoreset[idx] = False
        self._has_reset = True
        out: dict[str, Any] = {}
        merge_infos(out, infos, idx, self.num_envs)
        return self._observe(), out

    def set_autoreset_mode(self, mode: Any) -> None:
        """Select the autoreset mode: an :class:`~gymnasium.vector.AutoresetMode` or its value.

        Raises:
            ValueError: not one of ``"NextStep"``, ``"SameStep"``, ``"Disabled"``.
        """
        try:
            self.autoreset_mode = AutoresetMode(mode)
        except ValueError:
            choices = [m.value for m in AutoresetMode]
            raise ValueError(f"autoreset_mode must be one of {choices}, got {mode!r}") from None
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}

    @small_blas
    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every sub-env; what happens to finished ones depends on :attr:`autoreset_mode`."""
        if not self._has_reset:
            raise RuntimeError("call reset() before step()")
        mode = self.autoreset_mode
        if mode == AutoresetMode.DISABLED and self._autoreset.any():
            raise RuntimeError(
                f"sub-envs {np.flatnonzero(self._autoreset).tolist()} have ended: reset them "
                "with reset(options={'reset_mask': mask}) first (autoreset_mode is DISABLED)"
            )
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminated = np.zeros(self.num_envs, dtype=np.bool_)
        truncated = np.zeros(self.num_envs, dtype=np.bool_)
        out: dict[str, Any] = {}
        acts = self._check_actions(actions)
        step_idx = np.flatnonzero(~self._autoreset)
        reset_idx = np.flatnonzero(self._autoreset)
        if step_idx.size:
            r, te, tr, infos = self._step_envs(acts[step_idx], step_idx)
            rewards[step_idx], terminated[step_idx], truncated[step_idx] = r, te, tr
            done = np.asarray(te, dtype=bool) | np.asarray(tr, dtype=bool)
            if mode == AutoresetMode.SAME_STEP and done.any():
                self._finish_same_step(out, infos, step_idx, done)
            else:
                merge_infos(out, infos, step_idx, self.num_envs)
        if reset_idx.size:
            infos = self._reset_envs(reset_idx, {})
            merge_infos(out, infos, reset_idx, self.num_envs)
        self._autoreset = terminated | truncated
        if mode == AutoresetMode.SAME_STEP:
            self._autoreset[:] = False
        return self._observe(), rewards, terminated, truncated, out

    def _finish_same_step(
        self, out: dict[str, Any], infos: dict[str, Any], step_idx: np.ndarray, done: np.ndarray
    ) -> None:
        """``SAME_STEP``: keep the final observations and infos, reset the finished sub-envs."""
        ended = step_idx[done]
        final = self._observe()
        final_obs = np.full(self.num_envs, None, dtype=object)
        for b in ended:
            final_obs[b] = _row(final, int(b))
        rows = {key: _take(values, done) for key, values in infos.items()}
        final_info: dict[str, Any] = {}
        merge_infos(final_info, rows, ended, self.num_envs)
        kept = {key: _take(values, ~done) for key, values in infos.items()}
        if (~done).any():
            merge_infos(out, kept, step_idx[~done], self.num_envs)
        merge_infos(out, self._reset_envs(ended, {}), ended, self.num_envs)
        out["final_obs"], out["_final_obs"] = final_obs, np.isin(np.arange(self.num_envs), ended)
        out["final_info"], out["_final_info"] = final_info, out["_final_obs"].copy()

    def render(self) -> tuple[Any, ...] | None:
        """The frames of every sub-env (``render_mode="rgb_array"``), or ``None``."""
        if self.render_mode is None:
            return None
        return tuple(self.render_env(i) for i in range(self.num_envs))

    # -- to implement --------------------------------------------------------------------------
    def action_masks(self) -> np.ndarray:
        """``(B, ...)`` boolean masks of the allowed actions of every sub-env."""
        raise NotImplementedError

    def render_env(self, i: int) -> Any:
        """The frame of sub-env ``i``."""
        raise NotImplementedError(f"{type(self).__name__} does not render")

    def _reset_envs(self, idx: np.ndarray, options: dict[str, Any]) -> dict[str, Any]:
        raise NotImplementedError

    def _step_envs(
        self, actions: np.ndarray, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        raise NotImplementedError

    def _observe(self) -> Any:
        raise NotImplementedError

    # -- helpers -------------------------------------------------------------------------------
    def _seeds(self, seed: Any) -> list[int | None]:
        n = self.num_envs
        if seed is None:
            return [None] * n
        if isinstance(seed, int | np.integer) and not isinstance(seed, bool):
            return [int(seed) + i for i in range(n)]
        if isinstance(seed, list | tuple | np.ndarray):
            if len(seed) != n:
                raise ValueError(f"seed: expected {n} seeds (one per sub-env), got {len(seed)}")
            return [None if s is None else int(s) for s in seed]
        raise ArgumentTypeError(
            f"seed must be None, an int or a list of {n} ints, got {describe(seed)}"
        )

    def _check_actions(self, actions: Any) -> np.ndarray:
        """The batched action as an array with a leading ``(B,)`` axis (shape checked)."""
        arr = np.asarray(actions)
        if arr.shape[:1] != (self.num_envs,):
            raise ValueError(
                f"actions: expected a leading axis of {self.num_envs} (one per sub-env), "
                f"got shape {arr.shape}"
            )
        return arr


def _row(tree: Any, b: int) -> Any:
    """Sub-env ``b``'s part of a batched observation (a copy)."""
    if isinstance(tree, dict):
        return {k: _row(v, b) for k, v in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_row(v, b) for v in tree)
    return np.array(np.asarray(tree)[b], copy=True)


def _take(values: Any, keep: np.ndarray) -> Any:
    """The rows ``keep`` (a bool mask) of one batched info value (array or list)."""
    if isinstance(values, list):
        return [v for v, k in zip(values, keep, strict=True) if k]
    return np.asarray(values)[keep]
