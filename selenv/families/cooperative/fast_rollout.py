"""``fast_rollout`` for ``CLScheduling``: the ``rollout`` lookahead with all candidates batched.

The cooperative-localization ``rollout`` (:mod:`selenv.families.cooperative.rollout`) scores
stop and the ``top_k`` open pairs by simulating the greedy schedule ``horizon`` filter steps
ahead, one candidate and one previewed pair at a time (about 120 single-pair fusions per
decision on the benchmark preset, each a Python-level call). This agent runs **the same
lookahead** (same candidates, base policy, forecast and tie rules) with the candidates'
covariances stacked, so every simulated filter step is a handful of batched calls of
:mod:`selenv.families.cooperative.batched`, the functions the env itself steps with:

* the forecast estimate is the same for every candidate (a forecast update has zero
  innovation, so only the covariances differ): one ``(C, A, n)`` trajectory;
* each simulated step previews every open pair of every candidate in **one** fusion call
  (``C x P`` rows, eqs. 4-6 of Chen & Kia 2022 for ``dmv``), the greedy pick is an ``argmax``
  per candidate, and prediction, ZUPT and beacon updates are one call each for the whole stack.

What the forecast may use is :class:`~selenv.families.cooperative.forecast.CLForecast`'s
contract: the current estimate and covariance, the models, the noise statistics, the
measurement schedule and the held last input; never the true state or noise realisations
(residuals are zero, so estimates stay on the held-input trajectory). The scores equal
``rollout``'s to rounding (tested, rtol 1e-9) and the choices are ``rollout``'s.

:class:`CLFastRolloutAgent` also exposes the two pieces a learned lookahead builds on:
:meth:`~CLFastRolloutAgent.candidates` (the root previews) and
:meth:`~CLFastRolloutAgent.simulate` (the batched simulation returning the forecast stack at
the horizon).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import Agent, AgentSpec, register_agent
from selenv.agents.rollout import best_index
from selenv.core.linalg import FloatArray
from selenv.families.cooperative import batched
from selenv.families.cooperative.env import CLSchedulingEnv, agent_objective
from selenv.families.cooperative.forecast import CLForecast
from selenv.families.cooperative.rollout import CL_ENV_ID, rollout_options
from selenv.families.cooperative.scenario import input_sigmas

__all__ = ["CLFastRolloutAgent", "Decision", "ForecastStack"]


@dataclass
class ForecastStack:
    """``C`` forecasts of a team that share one estimate trajectory (module docstring).

    Attributes:
        x: (C, A, n) estimates (equal rows: forecast updates have zero innovation).
        P: (C, A, n, n) covariances.
        k: filter steps done (the same for every row).
    """

    x: FloatArray
    P: FloatArray
    k: int


@dataclass
class Decision:
    """The root of a decision: its forecast, candidates and their previewed gains.

    Attributes:
        root: the forecast from the env's state now.
        actions: ``[P (stop), pairs...]`` (C,) candidates.
        gains: (C,) their one-step gains (0 for stop).
        pair_gains: (P,) every pair's previewed gain now (``-inf`` where not open).
        open_pairs: (K,) the open pairs; posteriors: (K, n, n) agent ``i``'s previewed
            posterior of each (what the gains were computed from).
    """

    root: CLForecast
    actions: list[int]
    gains: FloatArray
    pair_gains: FloatArray
    open_pairs: np.ndarray
    posteriors: FloatArray


class CLFastRolloutAgent(Agent):
    """``rollout`` of the greedy schedule with its candidates batched (module docstring).

    Args:
        top_k: pairs evaluated per decision (>= 1), besides stop.
        horizon: filter steps simulated after the current one (>= 0; 0: myopic, greedy's pick).
        base: base policy of the simulation: ``"greedy"`` or ``"all"``.
        allow_large: lift the ceilings on ``top_k`` and ``horizon``
            (:data:`~selenv.agents.rollout.ROLLOUT_CEILINGS`).

    Attributes:
        last_scores: ``{action: score}`` of the last decision (stop is ``P``).
    """

    name = "fast_rollout"

    def __init__(
        self, top_k: int = 3, horizon: int = 5, base: str = "greedy", allow_large: bool = False
    ) -> None:
        self.top_k, self.horizon, self.base_policy = rollout_options(
            top_k, horizon, base, allow_large
        )
        self.last_scores: dict[int, float] = {}

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        base = env.unwrapped
        if not isinstance(base, CLSchedulingEnv):
            raise ValueError(
                f"agent {self.name!r} needs {CL_ENV_ID} here, got {type(base).__name__}"
            )
        self.cl = base
        cfg = base.config
        self._pairs = np.asarray(cfg.relative_pairs, dtype=np.intp).reshape(-1, 2)
        self._sigma = input_sigmas(cfg)
        self._beacons = np.asarray(cfg.beacons, dtype=np.float64).reshape(-1, 3)
        self.last_scores = {}

    def act(self, obs: Any, info: dict[str, Any]) -> int:
        """The first action of the best simulated trajectory (a pair index, or stop ``P``)."""
        choice, self.last_scores = self.scores()
        return choice

    # -- the pieces --------------------------------------------------------------------------
    def candidates(self) -> Decision:
        """The root forecast, the candidates ``[P (stop), pairs...]`` and their one-step gains.

        Candidates: stop and the ``top_k`` open pairs of largest previewed objective drop
        (ties: lower index), as ``rollout``.
        """
        env = self.cl
        root = CLForecast.from_env(env)
        open_ = np.flatnonzero(env.action_masks()[:-1])
        stack = ForecastStack(root.x[None].copy(), root.P[None].copy(), root.k)
        H_i, H_j = self._jacobians(stack.x[0])
        gains, posteriors = self._previews(stack, np.zeros(open_.size, np.intp), open_, H_i, H_j)
        order = np.argsort(-gains, kind="stable")[: self.top_k]
        ranked = [int(p) for p in open_[order]]
        pair_gains = np.full(env.n_pairs, -np.inf)
        pair_gains[open_] = gains
        return Decision(
            root,
            [env.n_pairs, *ranked],
            np.concatenate([[0.0], gains[order]]),
            pair_gains,
            open_,
            posteriors,
        )

    def simulate(self, decision: Decision, steps: int) -> ForecastStack:
        """Play each candidate, finish its filter step and ``steps`` more with the base policy.

        Returns the stack of the ``C`` forecasts after the last simulated step's picks (not yet
        advanced past it); stops early when the episode's last step is reached. ``rollout``'s
        ``_simulate`` is this plus a final :meth:`advance` (see :meth:`scores`).
        """
        env, root, candidates = self.cl, decision.root, decision.actions
        C, stop = len(candidates), env.n_pairs
        stack = ForecastStack(
            np.repeat(root.x[None], C, axis=0), np.repeat(root.P[None], C, axis=0), root.k
        )
        H_i, H_j = self._jacobians(stack.x[0])
        pending = np.repeat(env.action_masks()[None, :-1], C, axis=0)
        first = np.array([c for c in candidates if c != stop], dtype=np.intp)
        rows = np.array([r for r, c in enumerate(candidates) if c != stop], dtype=np.intp)
        if rows.size:
            self._fuse(stack, rows, first, H_i, H_j)
            pending[rows, first] = False
            live = np.zeros(C, dtype=bool)
            live[rows] = True
            pending &= live[:, None]  # stop ends the filter step
            # rollout's cache: the root gains, refreshed for the pairs involving the fused agent
            gains = np.repeat(decision.pair_gains[None], C, axis=0)
            if self.base_policy == "greedy":
                rr, pp = np.nonzero(pending[rows] & self._involves(self._pairs[first, 0]))
                gains[rows[rr], pp] = self._previews(stack, rows[rr], pp, H_i, H_j)[0]
            self._base_step(stack, pending, gains, env.budget_left - 1, H_i, H_j)
        for _ in range(steps):
            if stack.k >= env.horizon:  # the episode ends when this step closes
                return stack
            self.advance(stack, root.u_hold)
            H_i, H_j = self._jacobians(stack.x[0])
            avail = stack.k % root.config.relative_every == 0
            pending = np.full((C, env.n_pairs), avail)
            gains = np.full(pending.shape, -np.inf)
            if avail and self.base_policy == "greedy":
                r, p = np.nonzero(pending)
                gains[r, p] = self._previews(stack, r, p, H_i, H_j)[0]
            self._base_step(stack, pending, gains, env.budget, H_i, H_j)
        return stack

    def objective(self, stack: ForecastStack) -> FloatArray:
        """(C,) the env's objective (sum over agents) of every forecast of the stack."""
        return np.sum(agent_objective(stack.P, self.cl.objective), axis=-1)

    def advance(self, stack: ForecastStack, u_hold: FloatArray) -> None:
        """The env's transition to the next filter step, on every row (in place).

        Prediction with the held input ``x+ = f(x, u)``, ``P+ = F P F^T + Q``, then the ZUPT
        and beacon Kalman updates on their schedule with zero innovation (the forecast's
        measurements equal their predictions: only the covariances change).
        """
        cfg, model = self.cl.config, self.cl.config.agent_model
        C = stack.x.shape[0]
        u = np.broadcast_to(u_hold, (C, *u_hold.shape))
        batched.predict(model, stack.x, stack.P, u, cfg.dt, self._sigma)
        stack.k += 1
        k = stack.k
        if cfg.model == "ins" and cfg.zupt_every is not None and k % cfg.zupt_every == 0:
            zero = np.zeros((*stack.x.shape[:2], 3))
            batched.zupt_updates(stack.x, stack.P, stack.x[..., 3:6].copy(), zero, cfg.zupt_sigma)
        if self.cl.fusion != "dead_reckoning" and k % cfg.beacon_every == 0 and cfg.beacon_agents:
            zero = np.zeros((*stack.x.shape[:2], self._beacons.shape[0]))
            batched.beacon_updates(
                model,
                stack.x,
                stack.P,
                stack.x.copy(),
                cfg.beacon_agents,
                self._beacons,
                zero,
                cfg.range_sigma,
            )

    # -- the decision ------------------------------------------------------------------------
    def scores(self) -> tuple[int, dict[int, float]]:
        """The choice and every candidate's score (stop is ``P``), from the env's state now.

        Score: the drop of the env's objective from now to the end of the simulated trajectory
        (``rollout``'s); ``horizon = 0`` or no open pair: the one-step gains (greedy's choice).
        """
        decision = self.candidates()
        root, cands = decision.root, decision.actions
        if self.horizon == 0 or len(cands) == 1:
            scores = [float(g) for g in decision.gains]
        else:
            stack = self.simulate(decision, self.horizon)
            if stack.k < self.cl.horizon:
                self.advance(stack, root.u_hold)
            start = root.objective_value()
            scores = [float(start - v) for v in self.objective(stack)]
        return cands[best_index(scores)], dict(zip(cands, scores, strict=True))

    # -- batched helpers -----------------------------------------------------------------------
    def _jacobians(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(H_i, H_j)`` (P, m, n) of every pair at the estimates ``x`` (A, n)."""
        bearing = self.cl.config.bearing_sigma_deg is not None
        model = self.cl.config.agent_model
        return batched.relative_jacobians(
            model, x[self._pairs[:, 0]], x[self._pairs[:, 1]], bearing
        )

    def _previews(
        self,
        stack: ForecastStack,
        r: np.ndarray,
        p: np.ndarray,
        H_i: FloatArray,
        H_j: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """``(gains (K,), P_i+ (K, n, n))`` of fusing pair ``p[k]`` into row ``r[k]`` now.

        Agent ``i``'s posterior by the env's fusion with zero residual;
        gain = ``agent_objective(P_i) - agent_objective(P_i+)`` (``CLForecast.gain``).
        """
        if r.size == 0:
            return np.zeros(0), np.zeros((0, *stack.P.shape[2:]))
        i, j = self._pairs[p, 0], self._pairs[p, 1]
        P_i = stack.P[r, i]
        residual = np.zeros((r.size, H_i.shape[1]))
        _, P_new = batched.fuse(
            self.cl.fusion,
            stack.x[r, i],
            P_i,
            stack.P[r, j],
            H_i[p],
            H_j[p],
            self.cl.sim.R_rel,
            residual,
        )
        objective = self.cl.objective
        return agent_objective(P_i, objective) - agent_objective(P_new, objective), P_new

    def _involves(self, agents: np.ndarray) -> np.ndarray:
        """(K, P) whether pair ``p`` involves agent ``agents[k]`` (as ``i`` or ``j``)."""
        return np.any(self._pairs[None, :, :] == agents[:, None, None], axis=-1)

    def _fuse(
        self, stack: ForecastStack, r: np.ndarray, p: np.ndarray, H_i: FloatArray, H_j: FloatArray
    ) -> None:
        """Fuse pair ``p[k]`` into row ``r[k]`` (distinct rows), in place."""
        stack.P[r, self._pairs[p, 0]] = self._previews(stack, r, p, H_i, H_j)[1]

    def _base_step(
        self,
        stack: ForecastStack,
        pending: np.ndarray,
        gains: FloatArray,
        slots: int,
        H_i: FloatArray,
        H_j: FloatArray,
    ) -> None:
        """The base policy's picks for the rest of a filter step, every row (``rollout``'s).

        ``pending`` (C, P) open pairs per row (rows without any take no pick); ``gains``
        (C, P) their cached previewed gains (greedy; refreshed for the pairs that involve the
        agent just updated, as ``rollout`` does). Greedy stops a row when no gain is positive.
        """
        pending = pending.copy()
        live = np.asarray(pending.any(axis=1), dtype=bool)
        for _ in range(max(slots, 0)):
            rows = np.flatnonzero(live)
            if rows.size == 0:
                return
            if self.base_policy == "all":
                picks = np.argmax(pending[rows], axis=1)  # first open pair in index order
            else:
                masked = np.where(pending[rows], gains[rows], -np.inf)
                picks = np.argmax(masked, axis=1)  # first index on ties
                ok = masked[np.arange(rows.size), picks] > 0.0
                live[rows[~ok]] = False
                rows, picks = rows[ok], picks[ok]
                if rows.size == 0:
                    return
            self._fuse(stack, rows, picks, H_i, H_j)
            pending[rows, picks] = False
            if self.base_policy == "greedy":
                rr, pp = np.nonzero(pending[rows] & self._involves(self._pairs[picks, 0]))
                if rr.size:
                    gains[rows[rr], pp] = self._previews(stack, rows[rr], pp, H_i, H_j)[0]
            live &= pending.any(axis=1)


register_agent(
    AgentSpec(
        "fast_rollout",
        (CL_ENV_ID,),
        CLFastRolloutAgent,
        "rollout's lookahead (top-3 pairs + stop, 5 filter steps of greedy) with the "
        "candidates batched: rollout's scores at a fraction of its time (no future noise)",
    )
)
