"""The candidate view of ``ReceiverClustering``: the local edits of the clustering as candidates."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from selenv.envs.views import N_FEATURES, CandidateView, candidate_space
from selenv.families.clustering.env import (
    apply_edit,
    edit_action_count,
    edit_cost_changes,
    edit_mask,
)

__all__ = [
    "RECEIVER_FEATURES",
    "SOURCE_COLUMNS",
    "TARGET_COLUMNS",
    "TIME_COLUMN",
    "VIEWS",
    "ClusteringEditView",
    "edit_endpoints",
    "leave_rows",
    "receivers_for_count",
]

#: the per-receiver quantities an edit row describes, for its receiver ``i`` and its ``j``
RECEIVER_FEATURES = (
    "log_sigma_0",
    "log_sigma_1",
    "cluster_mean_log_sigma_0",
    "cluster_mean_log_sigma_1",
    "cluster_size",
    "log_position_var",
    "rel_log_position_var",
    "rel_log_cluster_var",
)
#: columns of an edit row's ``whitened`` holding :data:`RECEIVER_FEATURES` of receiver ``i``
SOURCE_COLUMNS = (0, 1, 4, 5, 8, 10, 13, 15)
#: columns of an edit row's ``whitened`` holding :data:`RECEIVER_FEATURES` of receiver ``j``
TARGET_COLUMNS = (2, 3, 6, 7, 9, 11, 14, 16)
#: column of an edit row's ``whitened`` holding the time in the episode
TIME_COLUMN = 12


def _check_receivers(n: object) -> None:
    """``TypeError`` / ``ValueError`` naming ``n`` unless it is an int >= 1."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"n must be an int, got {type(n).__name__}")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n!r}")


def edit_endpoints(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Receivers ``(i, j)`` of every edit row, each ``(1 + n^2 + n(n-1)/2,)`` ``intp``.

    Row 0 is the no-op (``(0, 0)``, its ``whitened`` is zero); row ``1 + i n + j`` moves ``i`` to
    ``j``'s cluster (leaves to a singleton when ``i = j``); row ``1 + n^2 + p`` swaps the
    ``p``-th pair ``i < j`` (``numpy.triu_indices(n, 1)`` order). This is the env's
    ``action_mode="edit"`` encoding (:func:`selenv.families.clustering.env.edit_mask`).

    Raises:
        TypeError: ``n`` is not an int.
        ValueError: ``n < 1``.
    """
    _check_receivers(n)
    n = int(n)
    iu, ju = np.triu_indices(n, k=1)
    mi, mj = np.divmod(np.arange(n * n), n)
    i = np.concatenate([[0], mi, iu]).astype(np.intp)
    j = np.concatenate([[0], mj, ju]).astype(np.intp)
    return i, j


def leave_rows(n: int) -> np.ndarray:
    """Rows ``1 + r (n + 1)`` of the "receiver ``r`` leaves" edits, ``(n,)`` ``intp``.

    Such a row's :data:`SOURCE_COLUMNS` hold receiver ``r``'s :data:`RECEIVER_FEATURES` (every
    row is filled, masked or not), so the ``n`` rows are the observation's receiver table.

    Raises:
        TypeError: ``n`` is not an int.
        ValueError: ``n < 1``.
    """
    _check_receivers(n)
    return (1 + np.arange(int(n)) * (int(n) + 1)).astype(np.intp)


def receivers_for_count(count: int) -> int:
    """The number of receivers ``n`` with ``1 + n^2 + n(n-1)/2 = count`` edits.

    Raises:
        TypeError: ``count`` is not an int.
        ValueError: ``count`` is not such a number (not an edit-view pool size).
    """
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)):
        raise TypeError(f"count must be an int, got {type(count).__name__}")
    if count < 2:
        raise ValueError(f"count must be >= 2 (an edit count), got {count!r}")
    # 3 n^2 - n + 2 - 2 count = 0
    n = round((1.0 + np.sqrt(1.0 + 24.0 * (int(count) - 1))) / 6.0)
    if n < 1 or edit_action_count(n) != int(count):
        raise ValueError(f"count={count} is not 1 + n^2 + n(n-1)/2 for any receiver count n")
    return int(n)


class ClusteringEditView(CandidateView):
    """``ReceiverClustering-v1``: candidates = the local edits of the current clustering.

    The ``1 + n^2 + n(n-1)/2`` edits of the env's ``action_mode="edit"`` (no-op; receiver
    ``i`` joins ``j``'s cluster, or leaves to a singleton when ``i = j``; swap ``i < j``), each
    described without evaluating the cost: ``whitened`` = ``[log sigma_i (2), log sigma_j (2),
    mean log sigma of i's cluster (2), of j's cluster (2), |C_i| / max, |C_j| / max,
    log position var_i, log position var_j, time, log(pv_i / max pv), log(pv_j / max pv),
    log(cv_i / max cv), log(cv_j / max cv)]`` (``pv`` a receiver's position variance, ``cv``
    the mean ``pv`` of its cluster: ``J_L`` and ``J_C`` are maxima over receivers and
    clusters, so the edits that matter touch the worst ones) and ``features`` =
    ``[no-op, move, swap, leave]``; ``gain`` is 1 for the no-op and 0 for every edit
    (unknown: no cost is evaluated), so a policy with a positive gain skip starts close to
    "keep the clustering" and learns which edits pay for their filter re-initialisation. The
    mask is
    :func:`selenv.families.clustering.env.edit_mask` of the observed labels, so the view also
    serves the default ``action_mode="assignment"``: :meth:`env_action` then returns the
    edited labels.
    """

    name = "clustering_edits"
    WIDTH = 17

    def __init__(self, n: int, max_size: int, action_mode: str) -> None:

        self.n, self.max_size, self.action_mode = int(n), int(max_size), action_mode
        self.count = edit_action_count(self.n)
        mi, mj = np.divmod(np.arange(self.n * self.n), self.n)
        self.i, self.j = edit_endpoints(self.n)
        kind = np.zeros((self.count, N_FEATURES), np.float32)
        kind[0, 0] = 1.0
        kind[1 : 1 + self.n * self.n, 1] = 1.0
        kind[1 + self.n * self.n :, 2] = 1.0
        kind[1 : 1 + self.n * self.n, 3] = (mi == mj).astype(np.float32)
        self.kind = kind
        self.gain = np.zeros(self.count, np.float32)
        self.gain[0] = 1.0  # the no-op: see the class docstring

    def space(self, env_space: spaces.Space) -> spaces.Dict:  # noqa: D102
        if not isinstance(env_space, spaces.Dict) or env_space["sigma"].shape != (self.n, 2):
            raise ValueError(f"expected a ReceiverClustering observation with {self.n} receivers")
        return candidate_space(self.count, self.WIDTH)

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102

        labels = np.asarray(obs["assignment"], dtype=np.intp)
        ls = np.log(np.maximum(np.asarray(obs["sigma"], dtype=np.float32), 1e-6))  # (n, 2)
        sizes = np.bincount(labels, minlength=labels.max() + 1).astype(np.float32)
        sums = np.zeros((sizes.size, 2), np.float32)
        np.add.at(sums, labels, ls)
        cl_mean = (sums / sizes[:, None])[labels]  # (n, 2) mean log sigma of own cluster
        size = sizes[labels] / self.max_size
        pv = np.maximum(np.asarray(obs["position_var"], dtype=np.float64), 1e-12)
        lpv = np.log(pv)
        cv = np.zeros(sizes.size)
        np.add.at(cv, labels, pv)
        lcv = np.log(cv / sizes)[labels]  # (n,) log mean position var of own cluster
        rel_pv, rel_cv = lpv - lpv.max(), lcv - lcv.max()
        t = float(np.asarray(obs["time"]).reshape(-1)[0])
        # per-receiver table, gathered once for each end of every edit (the columns of
        # [ls_i, ls_j, cl_mean_i, cl_mean_j, size_i, size_j, lpv_i, lpv_j, t, rel_pv_i,
        # rel_pv_j, rel_cv_i, rel_cv_j]); float64 then one cast, as the concatenation did
        table = np.empty((self.n, 8))
        table[:, 0:2], table[:, 2:4], table[:, 4] = ls, cl_mean, size
        table[:, 5], table[:, 6], table[:, 7] = lpv, rel_pv, rel_cv
        w = np.empty((self.count, self.WIDTH), np.float32)
        w[:, SOURCE_COLUMNS] = table[self.i]
        w[:, TARGET_COLUMNS] = table[self.j]
        w[:, TIME_COLUMN] = t
        w[0] = 0.0
        mask = edit_mask(labels, self.max_size).astype(np.int8)
        features = self.kind.copy()
        return {
            "action_mask": mask,
            "budget_left": np.array([1.0 - t], np.float32),
            "features": features,
            "gain": self.gain.copy(),
            "selected": np.zeros(self.count, np.int8),
            "whitened": w,
        }

    def env_action(self, obs: dict[str, np.ndarray], action: int) -> Any:  # noqa: D102
        if self.action_mode == "edit":
            return action

        return apply_edit(np.asarray(obs["assignment"], dtype=np.int64), int(action))

    def verify(self, env: gym.Env[Any, Any], obs: dict[str, np.ndarray], actions: Any) -> int:
        """The lowest-``J`` edit among ``actions`` if it beats keeping the clustering, else 0.

        ``J`` of each edited clustering is Algorithm 1's cost (the no-op keeps the current one).

        Costs ``len(actions)`` evaluations (minus a no-op) through the env's filter bank, which
        counts them (``info["cost_evaluations"]``), exactly as the greedy search does.
        """
        bank = env.unwrapped.bank  # type: ignore[attr-defined]
        if not np.array_equal(bank.labels, np.asarray(obs["assignment"])):
            raise ValueError("verify: obs is not the env's current observation")
        edits = np.asarray(actions, dtype=np.int64).reshape(-1)
        edits = edits[edits != 0]
        if edits.size == 0:
            return 0
        d = edit_cost_changes(bank, edits)
        j = int(np.argmin(d))
        return int(edits[j]) if d[j] < 0.0 else 0


#: the family's candidate view: the local edits of the clustering
VIEWS: dict[str, Callable[[Any], CandidateView]] = {
    "clustering_edits": lambda env: ClusteringEditView(
        env.unwrapped.n, env.unwrapped.max_size, env.unwrapped.action_mode
    )
}
