"""Native vector env of ``selenv/ReceiverClustering-v2``: ``B`` sequential clusterings together.

``gymnasium.make_vec("selenv/ReceiverClustering-v2", num_envs=B, **kwargs)`` returns
:class:`ReceiverClusteringSequentialVectorEnv`: sub-env ``b`` is
:class:`~selenv.families.clustering.sequential.ReceiverClusteringSequentialEnv` (one receiver
placed per step), seeded and stepped as ``gymnasium.make`` would. The placements (the exact
mask, the cluster sizes) are ``(B, n)`` arrays updated in numpy; the filter steps are those of
the assignment vector env :class:`~selenv.families.clustering.vector.ReceiverClusteringVectorEnv`
underneath (:attr:`inner`, sharing the sub-envs' generators), run at once for every sub-env
that placed its last receiver in this step. Sub-envs need not be in step with one another
(an autoreset or a ``terminate`` ends one early): each keeps its own receiver index.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from selenv.envs.actions import InvalidActionRule, invalid_code
from selenv.envs.vector import BatchedVectorEnv, check_discrete_actions, check_num_envs
from selenv.families.clustering.sequential import (
    ReceiverClusteringSequentialEnv,
    assignment_keywords,
    placement_masks,
    placement_reason,
)
from selenv.families.clustering.vector import ReceiverClusteringVectorEnv

__all__ = ["ReceiverClusteringSequentialVectorEnv"]

#: the assignment env's info keys the sequential env reports as they were after its last
#: filter step (``action_mask`` and the invalid-action keys are the placement step's own)
_CARRIED = ("objective", "J_G", "J_C", "J_L", "n_clusters", "changed", "k", "cost_evaluations")


class ReceiverClusteringSequentialVectorEnv(BatchedVectorEnv):
    """``num_envs`` copies of :class:`ReceiverClusteringSequentialEnv`.

    Args:
        num_envs: ``B``, an int in ``[1, 65536]``.
        invalid_action: ``"noop"``, ``"raise"`` or ``"terminate"`` (as the single env).
        invalid_action_penalty: float in ``[-1e6, 1e6]``.
        render_mode: ``None`` or ``"rgb_array"`` (:meth:`render_env` draws one sub-env).
        **config: every other keyword of the single env (``n_agents``, ``n_max_states``,
            ``horizon``, ``preset``, ...), validated by the assignment vector env;
            ``action_mode`` and ``obs_mask`` are fixed.

    Spaces: the single env's, batched: observations as the assignment vector env's plus
    ``receiver (B, n)``, ``new_assignment (B, n)`` and ``action_mask (B, n)`` (int8); actions
    ``(B,)`` placements. :meth:`action_masks` is ``(B, n)`` bool. Infos hold the single env's
    keys as ``(B, ...)`` arrays with Gymnasium's ``"_key"`` masks.

    Invalid actions, per sub-env: ``"noop"`` places the receiver alone and voids that
    sub-env's new clustering (its filter step keeps the current one); ``"terminate"`` ends its
    episode; ``"raise"`` raises ``ValueError`` naming the sub-env before any sub-env changes.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        **BatchedVectorEnv.metadata,
        "render_modes": ["rgb_array"],
        "render_fps": 10,
    }
    sub_env_metadata = ReceiverClusteringSequentialEnv.metadata
    sub_env_attributes = {"receiver": "receivers"}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        *,
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        **config: Any,
    ) -> None:
        B = check_num_envs(num_envs)
        inner_keywords = assignment_keywords(render_mode, config)
        self.invalid_rule = InvalidActionRule(invalid_action, invalid_action_penalty)
        self.inner = ReceiverClusteringVectorEnv(B, **inner_keywords)
        self.n, self.max_size, self.horizon = self.inner.n, self.inner.max_size, self.inner.horizon
        n = self.n
        inner_space = self.inner.single_observation_space
        assert isinstance(inner_space, spaces.Dict)
        single_obs = spaces.Dict(
            {
                **inner_space.spaces,
                "receiver": spaces.MultiBinary(n),
                "new_assignment": spaces.Box(-1, n - 1, (n,), np.int64),
                "action_mask": spaces.MultiBinary(n),
            }
        )
        self._setup(B, single_obs, spaces.Discrete(n), self.inner.render_mode)
        # one generator per sub-env, shared: the filter steps draw from the same ones
        self.inner.np_randoms, self.inner.np_random_seeds = self.np_randoms, self.np_random_seeds
        #: the receiver each sub-env's next action places
        self.receivers = np.zeros(B, np.int64)
        self._new = np.full((B, n), -1, np.int64)
        self._sizes = np.zeros((B, n), np.int64)  # by the cluster's lowest receiver
        self._void = np.zeros(B, np.bool_)
        self._carried: dict[str, np.ndarray] = {}

    # -- vector API -----------------------------------------------------------------------------
    def action_masks(self) -> np.ndarray:
        """``(B, n)`` bool: each sub-env's ``action_masks()`` (join a placed cluster, or open)."""
        return self._masks(np.arange(self.num_envs))

    def render_env(self, i: int) -> np.ndarray | None:
        """A frame of sub-env ``i``'s current clustering (``(H, W, 3)`` uint8)."""
        return self.inner.render_env(i)

    def close(self, **kwargs: Any) -> None:
        """Close the renderer."""
        inner = getattr(self, "inner", None)  # absent if __init__ failed
        if inner is not None:
            inner.close()
        super().close(**kwargs)

    @property
    def banks(self) -> list[Any]:
        """Each sub-env's cluster filters (its current clustering), as the inner env's."""
        return self.inner.banks

    # -- BatchedVectorEnv hooks -----------------------------------------------------------------
    def _reset_envs(self, idx: np.ndarray, options: dict[str, Any]) -> dict[str, Any]:
        infos = self.inner._reset_envs(idx, options)
        self._open(idx)
        self._carry(idx, infos)
        return self._infos(idx, np.zeros(idx.size, np.bool_), [None] * idx.size)

    def _step_envs(
        self, actions: np.ndarray, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        rule, k = self.invalid_rule, idx.size
        i = self.receivers[idx]
        allowed = self._masks(idx)[np.arange(k), actions]
        reasons = [
            None if ok else placement_reason(int(r), int(j), self.max_size)
            for ok, r, j in zip(allowed.tolist(), i.tolist(), actions.tolist(), strict=True)
        ]
        invalid = ~allowed
        if invalid.any() and rule.mode == "raise":  # before any sub-env changes
            bad = int(np.flatnonzero(invalid)[0])
            what = f"sub-env {int(idx[bad])}: action {int(actions[bad])}"
            rule.check(what, reasons[bad])
        rewards = np.where(invalid, rule.penalty, 0.0)
        terminated = invalid & rule.terminates
        truncated = np.zeros(k, np.bool_)
        go = ~terminated
        b, r, j = idx[go], i[go], actions[go]
        lead = np.where(invalid[go] | (j == r), r, self._new[b, np.minimum(j, r)])
        self._new[b, r] = lead
        self._sizes[b, lead] += 1
        self._void[b] |= invalid[go]
        self.receivers[b] = r + 1
        last = go & (i == self.n - 1)
        if last.any():
            rows = idx[last]
            labels = np.where(
                self._void[rows, None], self.inner._buf["assignment"][rows], self._new[rows]
            )
            rew, term, _, infos = self.inner._step_envs(labels, rows)
            rewards[last] += rew
            terminated[last] = term
            self._carry(rows, infos)
            self._open(rows)
        return rewards, terminated, truncated, self._infos(idx, invalid, reasons)

    def _observe(self) -> dict[str, np.ndarray]:
        B = self.num_envs
        receiver = np.zeros((B, self.n), np.int8)
        receiver[np.arange(B), np.minimum(self.receivers, self.n - 1)] = 1
        return {
            **self.inner._observe(),
            "receiver": receiver,
            "new_assignment": self._new.copy(),
            "action_mask": self.action_masks().astype(np.int8),
        }

    def _check_actions(self, actions: Any) -> np.ndarray:
        """``(B,)`` placements: shape, dtype and range checked for every sub-env."""
        return check_discrete_actions(actions, self.num_envs, self.n, "placement")

    # -- helpers --------------------------------------------------------------------------------
    def _open(self, idx: np.ndarray) -> None:
        """Start a filter step's placements for sub-envs ``idx``."""
        self.receivers[idx] = 0
        self._new[idx] = -1
        self._sizes[idx] = 0
        self._void[idx] = False

    def _masks(self, idx: np.ndarray) -> np.ndarray:
        """``(k, n)`` bool masks of sub-envs ``idx`` (as the single env's ``action_masks``)."""
        return placement_masks(self.receivers[idx], self._new[idx], self._sizes[idx], self.max_size)

    def _carry(self, idx: np.ndarray, infos: dict[str, Any]) -> None:
        """Keep the assignment env's info of sub-envs ``idx`` after a reset or filter step."""
        for key in _CARRIED:
            values = np.asarray(infos[key])
            if key not in self._carried:
                self._carried[key] = np.zeros((self.num_envs, *values.shape[1:]), values.dtype)
            self._carried[key][idx] = values

    def _infos(
        self, idx: np.ndarray, invalid: np.ndarray, reasons: list[str | None]
    ) -> dict[str, Any]:
        """The single env's info keys for sub-envs ``idx``, as ``(len(idx), ...)`` arrays."""
        return {
            **{key: self._carried[key][idx].copy() for key in _CARRIED},
            "action_mask": self._masks(idx),
            "placing": self.receivers[idx].copy(),
            "invalid_action": invalid.copy(),
            "invalid_code": np.array([invalid_code(r) for r in reasons], dtype=np.int64),
        }
