"""The candidate view of ``CLScheduling``: directed pairs and stop as candidates."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces

from selenv.envs.views import N_FEATURES, CandidateView, candidate_space

__all__ = ["VIEWS", "CLView"]


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
        self.live = previewer is not None  # reads the env's previews, not only the observation
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
            many = getattr(getattr(self.previewer, "__self__", None), "preview_gains_of", None)
            if callable(many):  # a vector env's sub-env: every open pair in one read
                raw = np.asarray(many(open_), dtype=float)
            else:
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


#: the family's candidate views (the first is the default): pairs alone, with the previewed
#: fused gain of each pair, or with it for the 3 best pairs only
VIEWS: dict[str, Callable[[Any], CandidateView]] = {
    "cl_pairs": lambda env: CLView(env.unwrapped.pairs),
    "cl_pairs_fused": lambda env: CLView(env.unwrapped.pairs, env.unwrapped.preview_gain),
    "cl_pairs_fused_top3": lambda env: CLView(
        env.unwrapped.pairs, env.unwrapped.preview_gain, top_k=3
    ),
}
