"""``rollout`` for ``LandmarkSelection``: a myopic selector simulated ahead.

The method and what its forecast may use: :mod:`selenv.agents.rollout`.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import AgentSpec, PlanAgent, register_agent
from selenv.agents.fim_solvers import greedy_whitened
from selenv.agents.rollout import best_index, ceiling_option, choice_option
from selenv.core.information import block_logdet_gains
from selenv.core.linalg import FloatArray, cholesky_spd
from selenv.core.objectives import make_gain_state, subset_criteria
from selenv.families.landmarks.env import LandmarkSelectionEnv
from selenv.families.landmarks.forecast import LandmarkForecast

__all__ = ["LandmarkRolloutAgent", "landmark_env"]

LANDMARK_ENV_ID = "selenv/LandmarkSelection-v1"
LANDMARK_BASES = ("brute_force", "greedy")


def landmark_env(env: gym.Env[Any, Any], name: str) -> LandmarkSelectionEnv:
    """``env.unwrapped`` if it is ``LandmarkSelection``, else ``ValueError`` naming ``name``."""
    base = env.unwrapped
    if not isinstance(base, LandmarkSelectionEnv):
        raise ValueError(f"agent {name!r} needs {LANDMARK_ENV_ID} here, got {type(base).__name__}")
    return base


def _combinations(n: int, k: int) -> np.ndarray:
    """All ``k``-subsets of ``range(n)`` in lexicographic order, ``(C(n, k), k)``."""
    return np.array(list(itertools.combinations(range(n), k)), dtype=np.intp).reshape(-1, k)


def _subset_gains(
    P: FloatArray,
    G: FloatArray,
    combos: np.ndarray,
    objective: str = "logdet",
    interest: tuple[int, ...] | None = None,
) -> FloatArray:
    """One-step gain of each subset, ``(C,)``, higher is better.

    ``"logdet"``: ``log det(I + G_S P G_S^T)`` (the dual identity), ``G_S P G_S^T`` gathered from
    ``S = G P G^T`` over all rows (one ``Nm x Nm`` product). ``"trace"`` / ``"max_eig"``: minus
    the trace / largest eigenvalue of the ``interest`` block of the posterior
    ``(P^-1 + G_S^T G_S)^-1``
    (:func:`~selenv.core.objectives.subset_criteria`, batched Cholesky).
    """
    if objective != "logdet":
        Linv = np.linalg.inv(cholesky_spd(P, "P"))
        Qk = np.einsum("kmi,kmj->kij", G, G)
        idx = None if interest is None else np.asarray(interest, dtype=np.intp)
        return -subset_criteria(Linv.T @ Linv, Qk, combos, objective, idx)
    N, m, d = G.shape
    Gf = G.reshape(N * m, d)
    S = Gf @ P @ Gf.T  # S = G P G^T, every pair of rows
    rows = (combos[:, :, None] * m + np.arange(m)).reshape(combos.shape[0], -1)  # (C, K m)
    return block_logdet_gains(S[rows[:, :, None], rows[:, None, :]])  # log det(I + W_S)


class LandmarkRolloutAgent(PlanAgent):
    """Rollout of a myopic selector in ``LandmarkSelection-v1``, one plan per filter step.

    At the first pick of a filter step, candidates are the ``top_k`` K-subsets of the open
    landmarks by one-step gain in the env's objective (``log det(I + W_S)``, or the decrease of
    the position trace / largest position variance with ``objective="trace"`` / ``"max_eig"``)
    (all ``C(N, K)`` subsets ranked when there
    are at most ``max_subsets``; otherwise each of the ``top_k`` best single landmarks completed
    greedily), plus the base policy's own subset. For each, a forecast applies the update, then
    ``horizon`` future filter steps (prediction with the held IMU sample, the base policy's
    subset at the predicted covariance, update); the score is minus the env's cost eq. (11)
    summed over those updates. The best subset is played over the next K env steps.
    ``horizon = 0`` scores only the current update: ``brute_force``'s optimal subset. A lone
    candidate is played without simulation (score 0).

    Args:
        top_k: K-subsets evaluated per filter step (>= 1).
        horizon: future filter steps simulated (>= 0; 0: myopic).
        base: base policy of the simulation, ``"brute_force"`` or ``"greedy"``.
        max_subsets: largest ``C(N, K)`` ranked exhaustively.
        allow_large: lift the ceilings on ``top_k``, ``horizon`` and ``max_subsets``
            (:data:`~selenv.agents.rollout.ROLLOUT_CEILINGS`).
    """

    name = "rollout"

    def __init__(
        self,
        top_k: int = 4,
        horizon: int = 10,
        base: str = "brute_force",
        max_subsets: int = 20_000,
        allow_large: bool = False,
    ) -> None:
        self.top_k = ceiling_option(top_k, "top_k", 1, allow_large)
        self.horizon = ceiling_option(horizon, "horizon", 0, allow_large)
        self.base_policy = choice_option(base, "base", LANDMARK_BASES)
        self.max_subsets = ceiling_option(max_subsets, "max_subsets", 1, allow_large)
        self._combos: dict[tuple[int, int], np.ndarray] = {}

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Bind to the env; refuse (``ValueError``) a brute-force base over too many subsets."""
        super().reset(env, seed)
        base = landmark_env(env, self.name)
        n_sub = math.comb(base.n, base.k)
        if self.base_policy == "brute_force" and n_sub > self.max_subsets:
            raise ValueError(
                f"rollout with base='brute_force' refuses C({base.n}, {base.k}) = {n_sub:,} "
                f"subsets per simulated step (max_subsets={self.max_subsets:,}); use base='greedy'"
            )
        self.lm = base

    def _subsets(self, n: int, k: int) -> np.ndarray:
        key = (n, k)
        combos = self._combos.get(key)
        if combos is None:
            combos = self._combos[key] = _combinations(n, k)
        return combos

    def _base_choice(self, P: FloatArray, G: FloatArray, budget: int) -> tuple[int, ...]:
        """The base policy's subset (indices into ``G``, ascending) for the covariance ``P``.

        ``brute_force``: the best subset by the dual identity ``log det(I + G_S P G_S^T)`` (the
        optimum of :func:`~selenv.agents.fim_solvers.brute_force_whitened`, on ``2K x 2K``
        determinants);
        ``greedy``: :func:`greedy_whitened` with the prior ``P^-1``. Both on the env's
        one-step objective (``solver_objective``: log det, or the position trace / max eig).
        """
        objective, interest = self.lm.solver_objective, self.lm.interest
        if self.base_policy == "brute_force":
            combos = self._subsets(G.shape[0], budget)
            gains = _subset_gains(P, G, combos, objective, interest)
            return tuple(int(i) for i in combos[int(np.argmax(gains))])
        Linv = np.linalg.inv(cholesky_spd(P, "P"))
        Q0 = Linv.T @ Linv  # P^-1 from its Cholesky factor
        sel = greedy_whitened(0.5 * (Q0 + Q0.T), G, budget, objective=objective, interest=interest)
        return tuple(sorted(sel.indices))

    def plan(self, obs: Any, info: dict[str, Any]) -> list[int]:
        """The best candidate subset for the picks left in this filter step."""
        best, _ = self.scores()
        return list(best)

    def candidates(self) -> list[tuple[int, ...]]:
        """Candidate subsets (landmark indices, ascending), best one-step gain first."""
        env = self.lm
        state, budget = env.state, env.budget_left
        remaining = np.flatnonzero(~state.selected)
        G = state.G[remaining]
        prior = state.information  # P_pred^-1 plus this step's picks so far
        out: list[tuple[int, ...]] = []
        if math.comb(remaining.size, budget) <= self.max_subsets:
            combos = self._subsets(remaining.size, budget)
            gains = _subset_gains(state.P, G, combos, env.solver_objective, env.interest)
            for c in np.argsort(-gains, kind="stable")[: self.top_k]:
                out.append(tuple(int(remaining[i]) for i in combos[c]))
            if self.base_policy == "brute_force":  # the top subset is the base's own choice
                return out
        else:
            assert state.gains is not None  # the env tracks them
            singles = np.argsort(-state.gains[remaining], kind="stable")[: self.top_k]
            for j in singles:  # greedy completion of each of the best single landmarks
                st = make_gain_state(
                    prior, G, env.solver_objective, interest=env.interest, track_gains=True
                )
                st.add(int(j))
                for _ in range(budget - 1):
                    st.add(int(np.argmax(st.masked_gains())))
                out.append(tuple(sorted(int(remaining[i]) for i in st.order)))
            out = list(dict.fromkeys(out))  # two singles may complete to the same subset
        own = tuple(int(remaining[i]) for i in self._base_choice(state.P, G, budget))
        return out if own in out else [*out, own]

    def scores(self) -> tuple[tuple[int, ...], dict[tuple[int, ...], float]]:
        """The chosen subset and every candidate's score (minus the summed cost)."""
        env = self.lm
        cands = self.candidates()
        root = LandmarkForecast.from_env(env)
        H0 = root.jacobians()
        picked = list(env.picks)
        steps = min(self.horizon, env.horizon - root.k)  # future filter updates in the episode
        scores = []
        for sel in cands if len(cands) > 1 else ():  # a lone candidate needs no score
            f = root.copy()
            f.update([*picked, *sel], H0)
            total = -f.cost()
            for _ in range(steps):
                f.predict()
                H = f.jacobians()
                f.update(self._base_choice(f.P, f.whitened(H), env.k), H)
                total -= f.cost()
            scores.append(total)
        if not scores:
            return cands[0], {cands[0]: 0.0}
        return cands[best_index(scores)], dict(zip(cands, scores, strict=True))


register_agent(
    AgentSpec(
        "rollout",
        (LANDMARK_ENV_ID,),
        LandmarkRolloutAgent,
        "rollout: top-4 K-subsets, 10 filter steps of brute force ahead (no future noise)",
    )
)
