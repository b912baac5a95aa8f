"""``gymnasium.make_vec("selenv/CLScheduling-v1", num_envs=B)``: all sub-envs in one state.

:class:`CLSchedulingVectorEnv` keeps the filters of its ``B`` sub-envs in arrays with a leading
batch axis and steps them with :mod:`selenv.families.cooperative.batched`, the functions the
single :class:`~selenv.families.cooperative.env.CLSchedulingEnv` calls with ``B = 1``.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from selenv.envs.actions import InvalidActionRule
from selenv.envs.conventions import check_render_mode
from selenv.envs.rendering import Renderer
from selenv.envs.vector import BatchedVectorEnv
from selenv.families.cooperative import batched
from selenv.families.cooperative.env import CLSchedulingEnv, agent_objective
from selenv.families.cooperative.scenario import (
    CLProblem,
    input_sigmas,
    make_cl_problem,
    relative_noise_cov,
)
from selenv.scenarios.validation import ArgumentTypeError, check_integer, describe
from selenv.threads import small_blas

__all__ = ["CLSchedulingVectorEnv", "CLSubEnv"]


class CLSchedulingVectorEnv(BatchedVectorEnv):
    """``B`` :class:`~selenv.families.cooperative.env.CLSchedulingEnv` sub-envs stepped at once.

    Sub-env ``b`` reproduces ``gymnasium.make("selenv/CLScheduling-v1", **kwargs)`` reset with
    the same seed and driven by the same actions (decisions identical, values within rtol
    1e-9; see :mod:`selenv.envs.vector` for seeding and autoreset).

    State (leading axis ``B``): estimates ``x (B, A, n)``, covariances ``P (B, A, n, n)``,
    steps done ``k (B,)``, pairs processed in the current filter step ``(B, P)``, budget slots
    spent ``(B,)``, and each sub-env's draws (inputs ``(B, T, A, n_input)``, ZUPT, beacon and
    relative noise); the truth ``(T + 1, A, n)`` is seed-independent and shared.

    Batched over the sub-envs (and their agents / pairs): the reset's filter start, the
    prediction, ZUPT and beacon updates, the relative update of the chosen pair of every
    sub-env (``fusion="dmv"`` and ``"naive"``), the pair gains of the observation, the
    objective and the masks. ``fusion="ci"``, ``"pecmv"`` and the learned rules fuse the chosen
    pairs one sub-env at a time (a scalar search, an SDP, a network per update) with the same
    core function. A reset draws each sub-env's realisation from its own generator
    (:func:`~selenv.families.cooperative.scenario.make_cl_problem`, a handful of draws; the
    truth is cached).

    Args:
        num_envs: ``B``, an int in ``[1, 65536]``.
        **config: the single env's keywords (``preset``, ``n_agents``, ``budget``,
            ``fusion``, ``horizon``, ``objective``, ``topology``, ``invalid_action``,
            ``invalid_action_penalty``, ...), validated by it.
        render_mode: ``None`` or ``"rgb_array"`` (:meth:`render_env`).

    Spaces: the single env's, batched: observations ``Dict`` of ``(B, ...)`` arrays, actions
    ``MultiDiscrete([P + 1] * B)``; :meth:`action_masks` is ``(B, P + 1)`` bool; infos carry the
    single env's keys batched (``processed`` ``(B, P)`` bool, ``invalid_code`` ``(B,)`` int64).
    ``invalid_action="raise"`` raises a ``ValueError`` naming the sub-env before any sub-env
    steps.

    Previews: :meth:`preview_gains` is the ``(B, P)`` single env's ``preview_gain`` of every
    open pair of every sub-env, one batched fusion per state (cached until the next step or
    reset); :meth:`sub_env` hands out a read-only :class:`CLSubEnv` with the single env's
    ``pairs``, ``preview_gain`` and ``action_masks``, so the candidate views that preview
    (``cl_pairs_fused``, ``cl_pairs_fused_top3``) run on sub-env ``b`` unchanged.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        **BatchedVectorEnv.metadata,
        "render_modes": ["rgb_array"],
        "render_fps": CLSchedulingEnv.metadata["render_fps"],
    }
    sub_env_metadata = CLSchedulingEnv.metadata
    sub_env_attributes = {"budget_left": "budget_left"}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        *,
        preset: str = "benchmark",
        n_agents: int | None = None,
        budget: int | None = None,
        fusion: str = "dmv",
        horizon: int | None = None,
        objective: str | None = None,
        topology: str | None = None,
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        **config: Any,
    ) -> None:
        render_mode = check_render_mode(render_mode, self.metadata)
        #: a single env: it validates the keywords and holds the configuration and spaces
        self.proto = CLSchedulingEnv(
            preset=preset,
            n_agents=n_agents,
            budget=budget,
            fusion=fusion,
            horizon=horizon,
            objective=objective,
            topology=topology,
            invalid_action=invalid_action,
            invalid_action_penalty=invalid_action_penalty,
            **config,
        )
        proto = self.proto
        self._setup(num_envs, proto.observation_space, proto.action_space, render_mode)
        cfg = self.config = proto.config
        self.pairs, self.n_pairs = proto.pairs, proto.n_pairs
        self.budget, self.horizon = proto.budget, proto.horizon
        self.fusion, self.objective = proto.fusion, proto.objective
        self.invalid_rule = proto.invalid_rule
        self.model = cfg.agent_model
        B, A, n, T = self.num_envs, cfg.n_agents, self.model.n, self.horizon
        nb, m = len(cfg.beacons), relative_noise_cov(cfg).shape[0]
        self._pair_index = np.asarray(self.pairs, dtype=np.intp).reshape(-1, 2)
        self._R = relative_noise_cov(cfg)
        self._sigma = input_sigmas(cfg)
        self._bearing = cfg.bearing_sigma_deg is not None
        self.x = np.zeros((B, A, n))
        self.P = np.zeros((B, A, n, n))
        self.k = np.zeros(B, dtype=np.int64)
        self._inputs = np.zeros((B, T, A, self.model.n_input))
        self._zupt_noise = np.zeros((B, T, A, 3))
        self._beacon_noise = np.zeros((B, T, A, nb))
        self._relative_noise = np.zeros((B, T, self.n_pairs, m))
        self._states: np.ndarray | None = None
        self._problems: list[CLProblem | None] = [None] * B
        self._done_pairs = np.zeros((B, self.n_pairs), dtype=np.bool_)
        self._slots = np.zeros(B, dtype=np.int64)
        self._available = np.zeros(B, dtype=np.bool_)
        self._logdets = np.zeros((B, A))
        self._objective = np.zeros(B)
        self._masks = np.zeros((B, self.n_pairs + 1), dtype=np.bool_)
        self._masks[:, -1] = True
        self._reasons: dict[int, str] = {}
        #: (B, P) previewed gains of the current state (None: not computed since it changed)
        self._previews: np.ndarray | None = None
        self._renderer = Renderer(render_mode, self.metadata["render_fps"])

    # -- state helpers -------------------------------------------------------------------------
    @property
    def states(self) -> np.ndarray:
        """(T + 1, A, n) true states (the same for every sub-env; needs ``reset``)."""
        if self._states is None:
            raise RuntimeError("call reset() before using the environment")
        return self._states

    def _refresh(self, rows: np.ndarray, agents: np.ndarray | None = None) -> None:
        """Log dets, objective and masks of the sub-envs ``rows`` after their ``P`` changed.

        ``agents``: the one agent of each row whose ``P`` changed (``None``: all of them).
        """
        if agents is None:
            self._logdets[rows] = batched.logdets(self.P[rows])
        else:
            self._logdets[rows, agents] = batched.logdets(self.P[rows, agents])
        if self.objective == "logdet":
            self._objective[rows] = np.sum(self._logdets[rows], axis=-1)
        else:
            P = self.P[rows]
            self._objective[rows] = np.sum(agent_objective(P, self.objective), axis=-1)
        self._update_masks(rows)

    def _update_masks(self, rows: np.ndarray) -> None:
        """``(P + 1,)`` masks of ``rows``: available, unprocessed pairs with budget left; stop."""
        open_ = self._available[rows, None] & ~self._done_pairs[rows]
        open_ &= (self._slots[rows] < self.budget)[:, None]
        self._masks[rows, :-1] = open_

    def _advance(self, rows: np.ndarray) -> None:
        """One filter step of the sub-envs ``rows``: prediction, ZUPT and beacon updates.

        ``x+ = f(x, u)``, ``P+ = F P F^T + Q`` for every agent, then the velocity and beacon
        range Kalman updates of the sub-envs on their schedule; opens the step's pairs.
        """
        cfg, states = self.config, self.states
        k = self.k[rows]
        full = rows.size == self.num_envs  # every sub-env (rows sorted, unique): views
        x, P = (self.x, self.P) if full else (self.x[rows], self.P[rows])
        batched.predict(self.model, x, P, self._inputs[rows, k], cfg.dt, self._sigma)
        k = k + 1
        self.k[rows] = k
        if cfg.model == "ins" and cfg.zupt_every is not None:
            z = np.flatnonzero(k % cfg.zupt_every == 0)
            if z.size:
                xz, Pz, kz = x[z], P[z], k[z]
                v_true = states[kz, :, 3:6]
                batched.zupt_updates(
                    xz, Pz, v_true, self._zupt_noise[rows[z], kz - 1], cfg.zupt_sigma
                )
                x[z], P[z] = xz, Pz
        b = np.flatnonzero(k % cfg.beacon_every == 0)
        if b.size and cfg.beacon_agents:
            xb, Pb, kb = x[b], P[b], k[b]
            batched.beacon_updates(
                self.model,
                xb,
                Pb,
                states[kb],
                cfg.beacon_agents,
                np.asarray(cfg.beacons, dtype=np.float64).reshape(-1, 3),
                self._beacon_noise[rows[b], kb - 1],
                cfg.range_sigma,
            )
            x[b], P[b] = xb, Pb
        if not full:
            self.x[rows], self.P[rows] = x, P
        self._available[rows] = k % cfg.relative_every == 0
        self._done_pairs[rows] = False
        self._slots[rows] = 0

    # -- BatchedVectorEnv hooks ----------------------------------------------------------------
    def _reset_envs(self, idx: np.ndarray, options: dict[str, Any]) -> dict[str, Any]:
        """New realisations for ``idx`` (each from its own generator); propagate to step 1."""
        self._previews = None
        cfg = self.config
        for i in idx.tolist():
            rng = self.np_randoms[i]
            problem = make_cl_problem(cfg, rng)
            self._problems[i] = problem
            self._states = problem.states
            self._inputs[i] = problem.inputs
            self._zupt_noise[i] = problem.zupt_noise
            self._beacon_noise[i] = problem.beacon_noise
            self._relative_noise[i] = problem.relative_noise
            self.x[i] = problem.x0_hat
        self.P[idx] = cfg.P0()
        self.k[idx] = 0
        self._advance(idx)
        self._refresh(idx)
        return self._infos(idx)

    def _check_actions(self, actions: Any) -> np.ndarray:
        """``(B,)`` integer actions (``(B, 1)`` accepted); a wrong shape is a ``ValueError``."""
        arr = super()._check_actions(actions)
        if arr.ndim == 2 and arr.shape[1] == 1:
            arr = arr[:, 0]
        if arr.ndim != 1:
            raise ValueError(
                f"actions must have shape ({self.num_envs},) (one pair index per sub-env), got "
                f"shape {arr.shape}"
            )
        if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
            raise ArgumentTypeError(
                f"actions must be integers in [0, {self.n_pairs + 1}), got {describe(actions)} "
                f"of dtype {arr.dtype}"
            )
        return arr.astype(np.int64, copy=False)

    def reset(
        self, *, seed: Any = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-env (or ``options["reset_mask"]``'s); see :mod:`selenv.envs.vector`."""
        self._reasons = {}
        self._previews = None
        return super().reset(seed=seed, options=options)

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every sub-env (see :class:`~selenv.envs.vector.BatchedVectorEnv`)."""
        self._reasons = {}
        self._previews = None
        return super().step(actions)

    def _step_envs(
        self, actions: np.ndarray, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One env step of the sub-envs ``idx``: a pair of each (or stop), batched.

        The chosen pair's relative update (eqs. 4-6 for ``dmv``), then, where the filter step
        ends (stop, budget spent or no pair left), the next prediction and its ZUPT and beacon
        updates; reward = the decrease of the objective.
        """
        self._previews = None
        P1 = self.n_pairs
        bad = np.flatnonzero((actions < 0) | (actions > P1))
        if bad.size:
            sub = int(idx[bad[0]])
            raise ValueError(
                f"sub-env {sub}: action {int(actions[bad[0]])} is out of range: expected an "
                f"integer in [0, {P1 + 1})"
            )
        rows = np.arange(idx.size)
        valid = self._masks[idx, actions]
        rule = self.invalid_rule
        invalid = np.flatnonzero(~valid)
        for r in invalid.tolist():  # rare: the reasons, and raise mode before any change
            sub, act = int(idx[r]), int(actions[r])
            if self._done_pairs[sub, act]:
                why = f"masked: pair {self.pairs[act]} was already processed in this step"
            else:
                why = f"masked: pair {self.pairs[act]} has no relative measurement in this step"
            try:
                rule.check(f"action {act}", why)
            except ValueError as exc:
                raise ValueError(f"sub-env {sub}: {exc}") from None
            self._reasons[sub] = why
        rewards = np.where(valid, 0.0, rule.penalty)
        terminated = np.zeros(idx.size, dtype=np.bool_)
        live = valid | (not rule.terminates)
        terminated[~live] = True
        pick = live & (actions < P1)
        proc = np.flatnonzero(pick & valid)
        if proc.size:
            b, p = idx[proc], actions[proc]
            before = self._objective[b]
            self._relative_updates(b, p)
            self._done_pairs[b, p] = True
            self._refresh(b, self._pair_index[p, 0])
            rewards[proc] = before - self._objective[b]
        self._slots[idx[pick]] += 1
        self._update_masks(idx[live])
        ends = live & (
            (actions == P1) | (self._slots[idx] >= self.budget) | ~self._masks[idx, :-1].any(axis=1)
        )
        last = ends & (self.k[idx] >= self.horizon)
        terminated |= last
        adv = rows[ends & ~last]
        if adv.size:
            b = idx[adv]
            before = self._objective[b]
            self._advance(b)
            self._refresh(b)
            rewards[adv] += before - self._objective[b]
        return rewards, terminated, np.zeros(idx.size, dtype=np.bool_), self._infos(idx)

    def _relative_terms(
        self, b: np.ndarray, p: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(H_i, H_j (K, m, n), residual (K, m))`` of pair ``p[r]`` of sub-env ``b[r]`` now.

        The measurement of the current step ``k``: ``z = h(t_i, t_j) + noise[k - 1, p]`` from
        the true states at ``k``, ``residual = z - h(x_i, x_j)``, Jacobians at the estimates.
        """
        ij = self._pair_index[p]
        i, j = ij[:, 0], ij[:, 1]
        k = self.k[b]
        truth = self.states[k]  # (K, A, n)
        rows = np.arange(b.size)
        return batched.relative_terms(
            self.model,
            self.x[b, i],
            self.x[b, j],
            truth[rows, i],
            truth[rows, j],
            self._relative_noise[b, k - 1, p],
            self._bearing,
        )

    def _relative_updates(self, b: np.ndarray, p: np.ndarray) -> None:
        """Fuse pair ``p[r]`` into agent ``i`` of sub-env ``b[r]`` for every row (batched)."""
        ij = self._pair_index[p]
        i, j = ij[:, 0], ij[:, 1]
        H_i, H_j, res = self._relative_terms(b, p)
        x, P = batched.fuse(
            self.fusion, self.x[b, i], self.P[b, i], self.P[b, j], H_i, H_j, self._R, res
        )
        self.x[b, i], self.P[b, i] = x, P

    def _preview_rows(self, b: np.ndarray, p: np.ndarray) -> np.ndarray:
        """(K,) objective decrease of fusing pair ``p[r]`` into sub-env ``b[r]`` now (no change).

        Agent ``i``'s posterior ``P_i+`` of the env's ``fusion`` (``dmv``: eqs. 4-6, batched
        over the rows; ``ci``, ``pecmv`` and the learned rules one row at a time, as
        :func:`~selenv.families.cooperative.batched.fuse` runs them), then
        ``agent_objective(P_i) - agent_objective(P_i+)``: ``log det P_i - log det P_i+`` or the
        drop of ``tr P_i[:2, :2]`` (negative when the update would raise it).
        """
        if b.size == 0:
            return np.zeros(0)
        ij = self._pair_index[p]
        i, j = ij[:, 0], ij[:, 1]
        H_i, H_j, res = self._relative_terms(b, p)
        P_i = self.P[b, i]
        _, P_new = batched.fuse(
            self.fusion, self.x[b, i], P_i, self.P[b, j], H_i, H_j, self._R, res
        )
        before = agent_objective(P_i, self.objective)
        return np.asarray(before - agent_objective(P_new, self.objective), dtype=np.float64)

    def _observe(self) -> dict[str, np.ndarray]:
        """The batched observation (the single env's ``Dict``, every entry ``(B, ...)``)."""
        mask = self._masks
        return {
            "logdet": self._logdets.astype(np.float32),
            "pos_std": np.sqrt(np.trace(self.P[:, :, :2, :2], axis1=2, axis2=3)).astype(np.float32),
            "pair_gain": self._pair_gains().astype(np.float32),
            "budget_left": ((self.budget - self._slots) / self.budget)
            .astype(np.float32)
            .reshape(-1, 1),
            "time": (self.k / self.horizon).astype(np.float32).reshape(-1, 1),
            "action_mask": mask.astype(np.int8),
        }

    def _pair_gains(self) -> np.ndarray:
        """(B, P) ``log det(I + N^-1 A)`` of every open pair of every sub-env (0 when masked)."""
        out = np.zeros((self.num_envs, self.n_pairs))
        b, p = np.nonzero(self._masks[:, :-1])
        if b.size:
            ij = self._pair_index[p]
            i, j = ij[:, 0], ij[:, 1]
            H_i, H_j = batched.relative_jacobians(
                self.model, self.x[b, i], self.x[b, j], self._bearing
            )
            d = self.model.dim
            Pd = self.P[:, :, :d, :d]  # the position blocks: H is zero elsewhere
            out[b, p] = batched.pair_gains(Pd[b, i], Pd[b, j], H_i, H_j, self._R, d)
        return out

    def _infos(self, idx: np.ndarray) -> dict[str, Any]:
        """The single env's info keys for the sub-envs ``idx``, batched."""
        truth = self.states[self.k[idx]]
        err = self.x[idx, :, :2] - truth[:, :, :2]
        invalid = np.array([int(i) in self._reasons for i in idx], dtype=np.bool_)
        return {
            "objective": self._objective[idx].copy(),
            "k": self.k[idx].copy(),
            "position_errors": np.sqrt(np.sum(err * err, axis=-1)),
            "processed": self._done_pairs[idx].copy(),
            "action_mask": self._masks[idx].copy(),
            **InvalidActionRule.masked_info(invalid),
        }

    # -- public ------------------------------------------------------------------------------
    @property
    def budget_left(self) -> np.ndarray:
        """``(B,)``: the single env's ``budget_left`` per sub-env (pairs left in its step)."""
        out: np.ndarray = self.budget - self._slots
        return out

    def action_masks(self) -> np.ndarray:
        """(B, P + 1) bool: available, unprocessed pairs of every sub-env; stop always allowed."""
        return self._masks.copy()

    def preview_gains(self) -> np.ndarray:
        """(B, P) previewed objective decrease of every open pair of every sub-env; 0 if masked.

        Entry ``[b, p]`` is the single env's ``preview_gain(p)`` of sub-env ``b`` (rtol 1e-9):
        one previewed ``fusion`` update of agent ``i``'s belief with pair ``p = (i, j)``'s
        measurement, undone, ``agent_objective(P_i) - agent_objective(P_i+)``, with ``P_i+``
        of eqs. (4)-(6) for ``dmv`` (the weight ``w*`` of eq. (6), then eq. (5)). All open
        ``(sub-env, pair)`` rows (:meth:`action_masks`, stop excluded) go through one call of
        :func:`~selenv.families.cooperative.batched.fuse` (``dmv``, ``naive``: batched; the
        other rules: one row at a time). The array is computed once per state and returned
        again (the same read-only object) until the next :meth:`step` or :meth:`reset`.

        Raises:
            RuntimeError: before ``reset``.
        """
        if self._previews is None:
            self.states  # noqa: B018 -- RuntimeError before reset
            with small_blas():
                out = np.zeros((self.num_envs, self.n_pairs))
                b, p = np.nonzero(self._masks[:, :-1])
                out[b, p] = self._preview_rows(b, p)
            out.flags.writeable = False
            self._previews = out
        return self._previews

    def sub_env(self, b: int) -> CLSubEnv:
        """A read-only :class:`CLSubEnv` of sub-env ``b`` (what a candidate view reads).

        Raises:
            TypeError: ``b`` not an int.
            ValueError: ``b`` outside ``[0, B - 1]``.
        """
        return CLSubEnv(self, check_integer(b, "b (the sub-env index)", 0, self.num_envs - 1))

    def render_env(self, i: int) -> Any:
        """Sub-env ``i``'s frame (``render_mode="rgb_array"``: ``(H, W, 3)`` uint8), or ``None``."""
        if self.render_mode is None:
            return None
        from selenv.families.cooperative.rendering import draw_cl_scheduling

        problem = self._problems[i]
        if problem is None:
            raise RuntimeError("call reset() before rendering")
        k = int(self.k[i])
        sim = SimpleNamespace(truth=self.states[k], x=self.x[i], P=self.P[i], k=k, problem=problem)
        done = np.flatnonzero(self._done_pairs[i]).tolist()
        title = f"CLScheduling-v1 ({self.fusion})"
        return self._renderer.render(
            lambda fig: draw_cl_scheduling(fig, sim, self.pairs, done, title)
        )

    def close(self, **kwargs: Any) -> None:
        """Close the render figure, if any."""
        renderer = getattr(self, "_renderer", None)  # None: the constructor raised
        if renderer is not None:
            renderer.close()
        super().close(**kwargs)


class CLSubEnv:
    """Read-only proxy of sub-env ``b`` of a :class:`CLSchedulingVectorEnv` (live, no copy).

    What the candidate views read from a single env: ``unwrapped`` (the proxy itself),
    ``pairs`` and ``n_pairs``, ``preview_gain(p)`` and ``action_masks()``; so
    ``VIEWS["cl_pairs_fused"](venv.sub_env(b))`` builds the view of sub-env ``b``. Every read
    sees the vector env's current state. Attributes cannot be set.
    """

    __slots__ = ("b", "venv")
    venv: CLSchedulingVectorEnv  #: the vector env
    b: int  #: the sub-env index

    def __init__(self, venv: CLSchedulingVectorEnv, b: int) -> None:
        object.__setattr__(self, "venv", venv)
        object.__setattr__(self, "b", b)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"CLSubEnv is read-only: cannot set {name!r}")

    def __repr__(self) -> str:
        return f"CLSubEnv(b={self.b}, num_envs={self.venv.num_envs})"

    @property
    def unwrapped(self) -> CLSubEnv:
        """The proxy itself (as ``env.unwrapped`` of an unwrapped single env)."""
        return self

    @property
    def pairs(self) -> tuple[tuple[int, int], ...]:
        """The directed pairs ``(i, j)`` (the env's ``pairs``)."""
        return self.venv.pairs

    @property
    def n_pairs(self) -> int:
        """``P``, the number of directed pairs."""
        return self.venv.n_pairs

    def preview_gain(self, p: int) -> float:
        """The single env's ``preview_gain(p)`` of sub-env ``b`` (see ``preview_gains``).

        An open pair reads ``venv.preview_gains()[b, p]``. A masked pair (processed in this
        step, or not measured now) is previewed like the single env previews it (one row:
        the same measurement, fused into the current belief), not read as the array's 0.

        Raises:
            TypeError: ``p`` not an int.
            ValueError: ``p`` outside ``[0, P - 1]`` (stop is not a pair).
        """
        venv = self.venv
        p = check_integer(p, "p (the pair index)", 0, venv.n_pairs - 1)
        if venv._masks[self.b, p]:
            return float(venv.preview_gains()[self.b, p])
        rows = venv._preview_rows(np.array([self.b]), np.array([p]))
        return float(rows[0])

    def preview_gains_of(self, ps: np.ndarray) -> np.ndarray:
        """``preview_gain(p)`` for every pair of ``ps`` (int array), in one read when open.

        What :class:`~selenv.families.cooperative.view.CLView` calls for the open pairs of an
        observation: one indexed read of ``venv.preview_gains()`` instead of ``len(ps)`` calls.
        """
        ps = np.asarray(ps, dtype=np.intp)
        venv = self.venv
        if ps.size and (ps.min() < 0 or ps.max() >= venv.n_pairs):
            raise ValueError(f"ps: pair indices must lie in [0, {venv.n_pairs - 1}]")
        if venv._masks[self.b, ps].all():
            return np.array(venv.preview_gains()[self.b, ps], dtype=float)
        return np.array([self.preview_gain(int(p)) for p in ps], dtype=float)

    def action_masks(self) -> np.ndarray:
        """(P + 1,) bool: sub-env ``b``'s mask (a copy)."""
        return self.venv._masks[self.b].copy()
