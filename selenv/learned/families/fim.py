"""A learned selector for ``FIMSelection-v1`` that reaches ``swap``: policy picks, then swaps.

``swap`` (greedy, then best-improvement 1-swap local search,
:func:`selenv.agents.fim_solvers.swap_whitened`) is the strongest heuristic on
``FIMSelection-v1``; a candidate-scoring policy played alone stops short of it. This agent
uses the policy as a second starting point of the same local search:

1. **policy start**: the policy (by default the shipped ``ppo_general`` checkpoint) makes the
   first ``policy_steps`` picks (default 2) on a scratch copy of the env's gain state -- the
   observation it would see after each of its own picks, its logits in numpy
   (:meth:`~selenv.learned.rl.agent.SB3PolicyAgent.logits` with ``backend="numpy"``) -- and
   greedy completes the budget;
2. **greedy start**: greedy's picks (Kirchner et al. 2020, Algorithm 1);
3. each start is polished by best-improvement swaps (the move rule of ``swap``: every
   (selected, unselected) pair, the best applied while it gains more than ``tol`` nats), and
   the better of the two local optima is played (``starts="both"``, the default).

The greedy start polished is ``swap``'s result, so the agent is never below ``swap``; the
policy start leads to another local optimum on some problems, and the agent plays it where it
is the better one. Where the policy start's search reaches a selection on greedy's search
path, it stops (from there it would end where greedy's did).

``starts="greedy"`` is exactly ``swap`` (the same moves in the same order), ``starts="policy"``
the policy's start alone.

The swap deltas are ``swap``'s own, :func:`~selenv.agents.fim_solvers.swap_deltas` (the
Schur complement of the determinant-lemma matrix, in closed form for ``m <= 2`` rows per
candidate).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import PlanAgent
from selenv.agents.fim_solvers import greedy_whitened, swap_deltas, whiten_in
from selenv.core.information import information_matrix
from selenv.core.linalg import FloatArray
from selenv.families.fim.batched import FIMBatchState
from selenv.families.fim.env import fim_observations
from selenv.learned.rl.agent import CHECKPOINT_DIR, SB3PolicyAgent

__all__ = [
    "DEFAULT_CHECKPOINT",
    "STARTS",
    "FIMPolicySwapAgent",
    "make_fim_learned",
    "polish",
]

FIM_ENV_ID = "selenv/FIMSelection-v1"
#: shipped checkpoint of the policy start (file name in ``checkpoints/``)
DEFAULT_CHECKPOINT = "fim_selection_ppo_general.zip"
#: the ``starts`` option: which starting selections the swap search polishes
STARTS = ("both", "policy", "greedy")
_ONE = np.zeros(1, dtype=np.intp)


def polish(
    Q0: FloatArray,
    G: FloatArray,
    start: Any,
    *,
    max_rounds: int = 200,
    tol: float = 1e-9,
    visited: set[frozenset[int]] | None = None,
    stop_at: set[frozenset[int]] | None = None,
) -> tuple[np.ndarray, int]:
    """Best-improvement 1-swap search from ``start``: ``swap``'s moves, ``(indices, rounds)``.

    Each round scores every (selected, unselected) pair
    (:func:`~selenv.agents.fim_solvers.swap_deltas`) and applies the
    best (row-major first on ties, the selected slot replaced in place) if it gains more than
    ``tol`` nats; the objective never decreases. ``rounds`` counts the passes made (the last
    one finds no improving swap unless ``max_rounds`` or ``stop_at`` stopped the search).

    Args:
        Q0: ``(d, d)`` SPD prior information (validated by the caller).
        G: ``(N, m, d)`` whitened candidates.
        start: ``B`` distinct candidate indices.
        max_rounds: passes at most (>= 0).
        tol: smallest gain (nats) a swap must make to be applied.
        visited: if given, every selection the search passes through is added to it.
        stop_at: selections at which the search stops (e.g. another search's ``visited``:
            from there it would follow that search's moves to the same local optimum).
    """
    sel = np.array(start, dtype=np.intp)
    N = G.shape[0]
    rounds = 0
    chosen = np.zeros(N, dtype=bool)
    while rounds < max_rounds and 0 < sel.size < N:
        key = frozenset(sel.tolist())
        if stop_at is not None and key in stop_at:
            break
        if visited is not None:
            visited.add(key)
        rounds += 1
        chosen[:] = False
        chosen[sel] = True
        uns = np.flatnonzero(~chosen)  # ascending, as swap's
        delta = swap_deltas(whiten_in(Q0, G, sel), sel, uns)
        i, j = np.unravel_index(int(np.argmax(delta)), delta.shape)
        if delta[i, j] <= tol:
            break
        sel[i] = uns[j]
    return sel, rounds


def _check_count(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise ValueError(f"{name} must be an int >= 0, got {value!r}")
    return int(value)


class FIMPolicySwapAgent(PlanAgent):
    """The policy's picks and greedy's, each polished by swaps; plays the better (module doc).

    Args:
        checkpoint: candidate-scoring checkpoint trained on ``FIMSelection-v1`` (default: the
            shipped ``ppo_general``, :data:`DEFAULT_CHECKPOINT`).
        starts: ``"both"`` (default), ``"policy"`` or ``"greedy"`` (exactly ``swap``).
        max_rounds: swap passes per start at most (>= 0; 0 plays the start itself).
        tol: smallest gain in nats a swap must make (finite, >= 0).
        policy_steps: picks the policy makes before greedy completes the policy start
            (default 2; 0: the policy makes every pick).
        policy_pool: ``M > 0`` lets the policy start pick from the ``M`` open candidates the
            policy scores highest at the decision (its features then describe that sub-pool);
            0 (default): from every open candidate.

    Raises:
        ValueError: a bad option (named), or the checkpoint is missing, unreadable or was
            trained on another env.
    """

    name = "ppo_swap"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        starts: str = "both",
        max_rounds: int = 200,
        tol: float = 1e-9,
        policy_pool: int = 0,
        policy_steps: int = 2,
    ) -> None:
        if starts not in STARTS:
            raise ValueError(f"starts must be one of {', '.join(STARTS)}; got {starts!r}")
        self.starts = starts
        self.max_rounds = _check_count(max_rounds, "max_rounds")
        if isinstance(tol, bool) or not isinstance(tol, int | float) or not 0 <= tol < math.inf:
            raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
        self.tol = float(tol)
        self.policy_pool = _check_count(policy_pool, "policy_pool")
        self.policy_steps = _check_count(policy_steps, "policy_steps")
        self.policy: SB3PolicyAgent | None = None
        if starts != "greedy":
            path = CHECKPOINT_DIR / DEFAULT_CHECKPOINT if checkpoint is None else checkpoint
            self.policy = SB3PolicyAgent(path, env_id=FIM_ENV_ID)
        elif checkpoint is not None:
            raise ValueError("checkpoint is not used with starts='greedy' (no policy start)")

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Bind to a ``FIMSelection`` env with the log-det objective.

        Raises:
            ValueError: another env, or another objective (the swap deltas are log det's).
        """
        base = env.unwrapped
        if not hasattr(base, "core") or not hasattr(base, "budget_left"):
            raise ValueError(f"agent {self.name!r} plays FIMSelection envs, got {base!r}")
        objective = getattr(base, "solver_objective", "logdet")
        if objective != "logdet":
            raise ValueError(
                f"agent {self.name!r} supports objective='logdet' only, got {objective!r}; "
                "use swap for the others"
            )
        super().reset(env, seed)
        if self.policy is not None:
            self.policy.reset(env, seed)

    def plan(self, obs: Any, info: dict[str, Any]) -> list[int]:
        """The better polished start on the candidates not yet selected (prior: the FIM now)."""
        base = self.env.unwrapped
        state = base.state  # type: ignore[attr-defined]
        left = int(base.budget_left)  # type: ignore[attr-defined]
        remaining = np.flatnonzero(~state.selected)
        prior = state.information  # Q0 + FIM of the picks so far
        G = np.asarray(state.G)[remaining]
        starts = []
        if self.starts != "policy":
            starts.append(np.array(greedy_whitened(prior, G, left).indices, dtype=np.intp))
        if self.starts != "greedy":
            picks = self.policy_picks(obs, left)
            starts.append(np.searchsorted(remaining, picks))
        best, best_value = None, -math.inf
        path: set[frozenset[int]] = set()  # greedy's search path: a policy start that joins it
        for start in starts:  # ends where greedy's does, so its search stops there
            first = best is None
            sel, _ = polish(
                prior, G, start, max_rounds=self.max_rounds, tol=self.tol,
                visited=path if first else None, stop_at=None if first else path,
            )  # fmt: skip
            value = float(np.linalg.slogdet(information_matrix(prior, G, sel))[1])
            if value > best_value:  # ties: the first start (greedy's)
                best, best_value = sel, value
        assert best is not None  # at least one start by construction
        return [int(remaining[k]) for k in best]

    def policy_picks(self, obs: Any, left: int) -> list[int]:
        """The policy start: ``left`` picks (env indices), the policy's first, then greedy's.

        The policy makes the first ``policy_steps`` picks (all with 0), each on the observation
        it would see after its own picks so far, and greedy the rest. They play on a scratch
        :class:`~selenv.families.fim.batched.FIMBatchState` (the env is not stepped) whose
        prior is the information now and whose pool is every candidate not yet selected, or
        with ``policy_pool = M > 0`` the ``M`` of them the policy scores highest now (one
        forward pass over the pool).
        """
        base = self.env.unwrapped
        state = base.state  # type: ignore[attr-defined]
        budget = int(base.budget)  # type: ignore[attr-defined]
        assert self.policy is not None  # built unless starts == "greedy"
        pool = np.flatnonzero(~state.selected)
        if 0 < self.policy_pool < pool.size:
            mask = ~state.selected
            logits = self.policy.logits(obs, {"action_mask": mask}, backend="numpy")
            top = np.argsort(-logits[pool], kind="stable")[: max(self.policy_pool, left)]
            pool = np.sort(pool[top])
        G = np.asarray(state.G)[pool]
        scratch = FIMBatchState(1, state.information, G.shape)
        scratch.start(_ONE, G[None])
        features = np.asarray(obs["features"])[pool][None]
        picks: list[int] = []
        steps = left if self.policy_steps == 0 else min(self.policy_steps, left)
        for step in range(left):
            mask = ~scratch.selected[0]
            if step < steps:
                frac = np.array([(left - step) / budget])
                batch = fim_observations(scratch.gains, scratch.Z, scratch.selected, features, frac)
                view = {key: val[0] for key, val in batch.items()}
                logits = self.policy.logits(view, {"action_mask": mask}, backend="numpy")
                j = int(np.argmax(logits))
            else:  # greedy completes the start: the largest gain (Algorithm 1, line 4)
                j = int(np.argmax(np.where(mask, scratch.gains[0], -np.inf)))
            picks.append(int(pool[j]))
            scratch.add(_ONE, np.array([j]))
        return picks


def make_fim_learned(**options: Any) -> FIMPolicySwapAgent:
    """Factory of the learned ``FIMSelection-v1`` selector (:class:`FIMPolicySwapAgent`).

    Options: ``checkpoint`` (default: the shipped ``ppo_general``), ``starts="both"``,
    ``max_rounds=200``, ``tol=1e-9``, ``policy_steps=2``, ``policy_pool=0``.

    Raises:
        ValueError: an unknown option (named, with the known ones) or a bad value.
    """
    known = ("checkpoint", "starts", "max_rounds", "tol", "policy_pool", "policy_steps")
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(f"unknown option(s) {unknown}; the options are {', '.join(known)}")
    return FIMPolicySwapAgent(**options)
