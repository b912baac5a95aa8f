"""Candidate views: every selection env's observation as a set of candidates, one per action.

:class:`~selenv.learned.rl.candidate_policy.CandidateScoringPolicy` reads a ``Dict`` observation
with
one row per action (the ``FIMSelection-v1`` layout)::

    gain        (N,)      a non-negative marginal gain of taking the action now (0: unknown)
    whitened    (N, W)    per-candidate numeric features (symlog-squashed by the policy)
    features    (N, 4)    per-candidate flags / static features in [-1, 1]
    selected    (N,)      1 if the candidate was already used
    budget_left (1,)      fraction of the decision budget left
    action_mask (N,)      allowed actions

``FIMSelection-v1`` and ``LandmarkSelection-v1`` already observe this layout (identity view).
``CLScheduling-v1`` is rewritten by :class:`CLView`: the ``P`` directed pairs plus the stop
action are the candidates; ``ReceiverClustering-v1`` by :class:`ClusteringEditView`: the local
edits (move, leave, swap, no-op) of the current clustering. A view is a pure function of the
observation, so the same view is applied in training (:class:`CandidateViewWrapper`) and when
a checkpoint acts (:mod:`selenv.learned.rl.agent`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

__all__ = [
    "VIEWS",
    "CLView",
    "CandidateView",
    "CandidateViewWrapper",
    "ClusteringEditView",
    "IdentityView",
    "view_for",
]

N_FEATURES = 4


def candidate_space(n: int, width: int) -> spaces.Dict:
    """The candidate ``Dict`` space for ``n`` candidates with ``width`` numeric features each."""
    return spaces.Dict(
        {
            "action_mask": spaces.MultiBinary(n),
            "budget_left": spaces.Box(0.0, 1.0, (1,), np.float32),
            "features": spaces.Box(-1.0, 1.0, (n, N_FEATURES), np.float32),
            "gain": spaces.Box(0.0, np.inf, (n,), np.float32),
            "selected": spaces.MultiBinary(n),
            "whitened": spaces.Box(-np.inf, np.inf, (n, width), np.float32),
        }
    )


class CandidateView:
    """Base class: ``space(env_space)`` and ``__call__(obs)`` rewrite an env's observations.

    ``env_action(obs, a)`` maps a candidate index back to the env's action (identity unless the
    env's action encoding differs from the candidates, as in receiver clustering's assignment
    mode).
    """

    name = "base"

    def env_action(self, obs: dict[str, np.ndarray], action: int) -> Any:  # noqa: D102
        return action

    def space(self, env_space: spaces.Space) -> spaces.Dict:  # noqa: D102
        raise NotImplementedError

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        raise NotImplementedError

    def verify(self, env: gym.Env[Any, Any], obs: dict[str, np.ndarray], actions: Any) -> int:
        """Cost the candidate ``actions`` exactly in ``env`` and return the best one.

        Only views of envs with a cheap exact objective oracle implement it (the policy then
        acts as a learned proposal for a small local search).

        Raises:
            ValueError: the view has no verification.
        """
        raise ValueError(f"the {self.name!r} candidate view has no exact verification")


class IdentityView(CandidateView):
    """The env already observes candidates (``FIMSelection-v1``, ``LandmarkSelection-v1``)."""

    name = "identity"

    def space(self, env_space: spaces.Space) -> spaces.Dict:  # noqa: D102
        if not isinstance(env_space, spaces.Dict):
            raise ValueError(f"expected a Dict observation space, got {env_space}")
        return env_space

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        return obs


class CLView(CandidateView):
    """``CLScheduling-v1``: candidates = the ``P`` directed pairs ``(i, j)`` + stop (last).

    Pair ``p = (i, j)``: ``gain`` = the env's ``pair_gain`` (naive-EKF information gain, a
    proxy of the fused one) or, with ``previewer`` (view ``"cl_pairs_fused"``), the exact
    objective decrease of the pair's fused update, ``max(previewer(p), 0)`` with
    ``previewer = env.unwrapped.preview_gain`` (what the ``greedy`` agent maximises; one
    previewed update per available pair and decision); ``whitened`` = ``[log det P_i,
    log det P_j, log std_i, log std_j]`` (agent ``i`` measures, ``j`` is measured: the fused
    gain depends on how the two compare); ``features`` = ``[0, time, 0, 0]``. Stop: gain 0,
    whitened 0, features ``[1, time, 0, 0]``.

    ``top_k`` (view ``"cl_pairs_fused_top3"``, needs ``previewer``): only stop and the
    ``top_k`` open pairs by previewed gain (ties by index) stay allowed in ``action_mask`` --
    the candidate set of the ``rollout`` reference, which a policy distilled from it ranks.
    """

    name = "cl_pairs"
    WIDTH = 4

    def __init__(
        self,
        pairs: tuple[tuple[int, int], ...],
        previewer: Callable[[int], float] | None = None,
        top_k: int | None = None,
    ) -> None:
        self.pairs = tuple(pairs)
        self.previewer = previewer
        if top_k is not None and (previewer is None or top_k < 1):
            raise ValueError(f"top_k needs a previewer and must be >= 1, got {top_k!r}")
        self.top_k = top_k
        if previewer is not None:
            self.name = "cl_pairs_fused" if top_k is None else f"cl_pairs_fused_top{top_k}"
        self.i = np.array([p[0] for p in self.pairs], dtype=np.intp)
        self.j = np.array([p[1] for p in self.pairs], dtype=np.intp)

    def space(self, env_space: spaces.Space) -> spaces.Dict:  # noqa: D102
        n_pairs = len(self.pairs)
        if not isinstance(env_space, spaces.Dict) or env_space["pair_gain"].shape != (n_pairs,):
            raise ValueError(f"expected a CLScheduling observation with {n_pairs} pairs")
        return candidate_space(n_pairs + 1, self.WIDTH)

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        P = len(self.pairs)
        logdet = np.asarray(obs["logdet"], dtype=np.float32)
        log_std = np.log(np.maximum(np.asarray(obs["pos_std"], dtype=np.float32), 1e-12))
        whitened = np.zeros((P + 1, self.WIDTH), np.float32)
        whitened[:P] = np.stack(
            [logdet[self.i], logdet[self.j], log_std[self.i], log_std[self.j]], axis=1
        )
        features = np.zeros((P + 1, N_FEATURES), np.float32)
        features[P, 0] = 1.0
        features[:, 1] = float(np.asarray(obs["time"]).reshape(-1)[0])
        gain = np.zeros(P + 1, np.float32)
        mask = np.asarray(obs["action_mask"], dtype=np.int8)
        if self.previewer is None:
            gain[:P] = obs["pair_gain"]
        else:
            open_ = np.flatnonzero(mask[:P])
            raw = np.array([self.previewer(int(p)) for p in open_])
            gain[open_] = np.maximum(raw, 0.0)
            if self.top_k is not None and open_.size > self.top_k:
                keep = open_[np.lexsort((open_, -raw))[: self.top_k]]  # rollout's ranking
                mask = np.zeros_like(mask)
                mask[keep] = 1
                mask[P] = obs["action_mask"][P]
        selected = np.zeros(P + 1, np.int8)
        selected[:P] = 1 - mask[:P]
        return {
            "action_mask": mask,
            "budget_left": np.asarray(obs["budget_left"], dtype=np.float32),
            "features": features,
            "gain": gain,
            "selected": selected,
            "whitened": whitened,
        }


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
    :func:`selenv.envs.receiver_clustering.edit_mask` of the observed labels, so the view also
    serves the default ``action_mode="assignment"``: :meth:`env_action` then returns the
    edited labels.
    """

    name = "clustering_edits"
    WIDTH = 17

    def __init__(self, n: int, max_size: int, action_mode: str) -> None:
        from selenv.envs.receiver_clustering import edit_action_count

        self.n, self.max_size, self.action_mode = int(n), int(max_size), action_mode
        self.count = edit_action_count(self.n)
        iu, ju = np.triu_indices(self.n, k=1)
        mi, mj = np.divmod(np.arange(self.n * self.n), self.n)
        self.i = np.concatenate([[0], mi, iu]).astype(np.intp)
        self.j = np.concatenate([[0], mj, ju]).astype(np.intp)
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
        from selenv.envs.receiver_clustering import edit_mask

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
        i, j = self.i, self.j
        w = np.concatenate(
            [ls[i], ls[j], cl_mean[i], cl_mean[j], size[i, None], size[j, None],
             lpv[i, None], lpv[j, None], np.full((self.count, 1), t),
             rel_pv[i, None], rel_pv[j, None], rel_cv[i, None], rel_cv[j, None]],
            axis=1,
        ).astype(np.float32)  # fmt: skip
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
        from selenv.envs.receiver_clustering import apply_edit

        return apply_edit(np.asarray(obs["assignment"], dtype=np.int64), int(action))

    def verify(self, env: gym.Env[Any, Any], obs: dict[str, np.ndarray], actions: Any) -> int:
        """The lowest-``J`` edit among ``actions`` if it beats keeping the clustering, else 0.

        ``J`` of each edited clustering is Algorithm 1's cost (the no-op keeps the current one).

        Costs ``len(actions)`` evaluations (minus a no-op) through the env's filter bank, which
        counts them (``info["cost_evaluations"]``), exactly as the greedy search does.
        """
        from selenv.envs.receiver_clustering import edit_cost_changes

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


#: env id -> {view name -> factory of the view from the env}; the first name is the default
VIEWS: dict[str, dict[str, Callable[[Any], CandidateView]]] = {
    "selenv/FIMSelection-v1": {"identity": lambda env: IdentityView()},
    "selenv/LandmarkSelection-v1": {"identity": lambda env: IdentityView()},
    "selenv/CLScheduling-v1": {
        "cl_pairs": lambda env: CLView(env.unwrapped.pairs),
        "cl_pairs_fused": lambda env: CLView(env.unwrapped.pairs, env.unwrapped.preview_gain),
        "cl_pairs_fused_top3": lambda env: CLView(
            env.unwrapped.pairs, env.unwrapped.preview_gain, top_k=3
        ),
    },
    "selenv/ReceiverClustering-v1": {
        "clustering_edits": lambda env: ClusteringEditView(
            env.unwrapped.n, env.unwrapped.max_size, env.unwrapped.action_mode
        )
    },
}


def view_for(env_id: str, env: gym.Env[Any, Any], name: str | None = None) -> CandidateView:
    """Candidate view ``name`` (default: the env's first) of ``env`` (``gymnasium.make(env_id)``).

    Raises:
        ValueError: no view for ``env_id``, or no view ``name`` for it (the message lists the
            supported ones).
    """
    if env_id not in VIEWS:
        raise ValueError(f"no candidate view for {env_id!r}; supported: {sorted(VIEWS)}")
    views = VIEWS[env_id]
    if name is None:
        name = next(iter(views))
    if name not in views:
        raise ValueError(f"no candidate view {name!r} for {env_id}; supported: {sorted(views)}")
    return views[name](env)


class CandidateViewWrapper(gym.ObservationWrapper[Any, Any, Any]):
    """Apply a :class:`CandidateView` to a Gymnasium env; forwards ``action_masks()``."""

    def __init__(self, env: gym.Env[Any, Any], view: CandidateView) -> None:
        super().__init__(env)
        self.view = view
        self.observation_space = view.space(env.observation_space)

    def observation(self, observation: Any) -> dict[str, np.ndarray]:  # noqa: D102
        return self.view(observation)

    def action_masks(self) -> np.ndarray:
        """The wrapped env's mask (MaskablePPO reads it through the VecEnv)."""
        return np.asarray(self.env.unwrapped.action_masks(), dtype=bool)  # type: ignore[attr-defined]
