"""``gymnasium.make_vec("selenv/LandmarkSelection-v1", num_envs=B)``: B landmark envs in arrays.

:class:`LandmarkSelectionVectorEnv` keeps the filters, layouts, noises and gain states of ``B``
sub-envs with a leading batch axis and steps them with the batched core
(:mod:`selenv.families.landmarks.batched`) that the single env calls with ``B = 1``; resets draw
each sub-env's episode from its own generator
(:func:`~selenv.families.landmarks.scenario.draw_episodes`) on top of the per-config cache
(:func:`~selenv.families.landmarks.scenario.scenario_static`).
Sub-env ``b`` reproduces ``gymnasium.make(id).reset(seed=s + b)`` driven by the same actions
(:func:`~selenv.envs.vector_check.check_vector_equivalence`).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.envs.actions import InvalidActionRule
from selenv.envs.rendering import Renderer
from selenv.envs.vector import BatchedVectorEnv, check_num_envs
from selenv.families.landmarks.batched import (
    SelectionBatch,
    add_picks,
    aoa_candidates,
    ekf_predict,
    ekf_update,
    landmark_costs,
    landmark_features,
    open_selection,
    whiten_landmarks,
    write_observation,
)
from selenv.families.landmarks.env import (
    LandmarkSelectionEnv,
    landmark_observation_space,
    landmark_settings,
)
from selenv.families.landmarks.models import STATE_DIM
from selenv.families.landmarks.scenario import draw_episodes, scenario_static
from selenv.scenarios.validation import ArgumentTypeError, describe

__all__ = ["LandmarkSelectionVectorEnv"]


class LandmarkSelectionVectorEnv(BatchedVectorEnv):
    """``B`` ``LandmarkSelection-v1`` envs stepped together (native batched vector env).

    Args:
        num_envs: ``B``, an int in ``[1, 65536]``.
        **config: the keywords of
            :class:`~selenv.families.landmarks.env.LandmarkSelectionEnv` (``n_landmarks``,
            ``k``, ``horizon``, ``objective``, ``landmarks``, ``invalid_action``,
            ``invalid_action_penalty``, ...), validated by the same code.
        render_mode: ``None`` or ``"rgb_array"`` (:meth:`render_env` draws one sub-env).

    Spaces: the single env's, batched: actions ``(B,)`` ints, observations a ``Dict`` of
    ``gain`` (B, N), ``whitened`` (B, N, 18), ``features`` (B, N, 4), ``selected`` (B, N),
    ``budget_left`` (B, 1), ``action_mask`` (B, N). Infos: the single env's keys as ``(B,)``
    arrays with ``"_key"`` masks. An invalid (masked) pick is handled per sub-env as the single
    env does (``"noop"``, ``"terminate"``, or ``"raise"``: a ``ValueError`` naming the sub-env,
    raised before any sub-env changes). Autoreset: Gymnasium's ``NEXT_STEP``.

    Raises:
        TypeError, ValueError: a bad keyword, naming it.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        **BatchedVectorEnv.metadata,
        "render_modes": ["rgb_array"],
        "render_fps": 10,
    }
    sub_env_metadata = LandmarkSelectionEnv.metadata
    sub_env_attributes = {"budget_left": "budget_left"}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        *,
        n_landmarks: int = 30,
        k: int = 2,
        horizon: int = 300,
        objective: str = "logdet",
        landmarks: Any = None,
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        **config: Any,
    ) -> None:
        B = check_num_envs(num_envs)
        s = landmark_settings(
            type(self),
            self.metadata,
            n_landmarks=n_landmarks,
            k=k,
            horizon=horizon,
            objective=objective,
            landmarks=landmarks,
            invalid_action=invalid_action,
            invalid_action_penalty=invalid_action_penalty,
            render_mode=render_mode,
            config=config,
        )
        self.config, self.invalid_rule, self.objective = s.config, s.invalid_rule, s.objective
        self.n, self.k, self.horizon = s.n, s.k, s.horizon
        self._gain_spec = s.spec
        self._setup(B, landmark_observation_space(s.n), gym.spaces.Discrete(s.n), s.render_mode)
        self._static = scenario_static(s.config)
        N, T, K = s.n, s.horizon, s.k
        cfg = s.config
        self._dt, self._sigmas = float(cfg.dt), (float(cfg.accel_sigma), cfg.gyro_sigma)
        # episodes (drawn at reset), filters, the candidates at the current predictions
        self._landmarks = np.zeros((B, N, 3))
        self._imu = np.zeros((B, T, 6))
        self._z = np.zeros((B, T, N, 2))
        self._x = np.zeros((B, STATE_DIM))
        self._P = np.zeros((B, STATE_DIM, STATE_DIM))
        self._k = np.zeros(B, dtype=np.int64)  # predictions done (the time index of x)
        self._H = np.zeros((B, N, 2, STATE_DIM))
        self._h = np.zeros((B, N, 2))
        # the selection of the open filter step
        self._sel = SelectionBatch.empty(B, N)
        self._picks = np.zeros((B, K), dtype=np.int64)
        self._n_picks = np.zeros(B, dtype=np.int64)
        self._slots = np.zeros(B, dtype=np.int64)
        self._last = np.zeros((B, K), dtype=np.int64)
        self._n_last = np.full(B, -1, dtype=np.int64)  # -1: no update yet
        self._cost = np.full(B, np.nan)
        self._error = np.full(B, np.nan)
        self._done = np.zeros(B, dtype=np.bool_)
        self._obs: dict[str, np.ndarray] = {
            "gain": np.zeros((B, N), np.float32),
            "whitened": np.zeros((B, N, 2 * STATE_DIM), np.float32),
            "features": np.zeros((B, N, 4), np.float32),
            "selected": np.zeros((B, N), np.int8),
            "budget_left": np.zeros((B, 1), np.float32),
            "action_mask": np.zeros((B, N), np.int8),
        }
        self._renderer: Renderer | None = None

    # -- gymnasium.vector API ----------------------------------------------------------------
    @property
    def budget_left(self) -> np.ndarray:
        """``(B,)``: the single env's ``budget_left`` per sub-env (picks left in its step)."""
        out: np.ndarray = self.k - self._slots
        return out

    def action_masks(self) -> np.ndarray:
        """(B, N) bool: the landmarks not yet picked in each sub-env's filter step."""
        return ~self._sel.selected

    def render_env(self, i: int) -> np.ndarray | None:
        """The frame of sub-env ``i`` (``render_mode="rgb_array"``: ``(H, W, 3)`` uint8)."""
        if isinstance(i, bool) or not isinstance(i, int | np.integer):
            raise ArgumentTypeError(f"i must be an int sub-env index, got {describe(i)}")
        if not 0 <= i < self.num_envs:
            raise ValueError(f"i must lie in [0, {self.num_envs}), got {i}")
        if self.render_mode is None:
            return None
        if self._renderer is None:
            self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])
        from selenv.families.landmarks.rendering import draw_landmark_selection

        problem = SimpleNamespace(landmarks=self._landmarks[i], states=self._static.states)
        x, P, k = self._x[i].copy(), self._P[i].copy(), int(self._k[i])
        picks = tuple(int(j) for j in self._picks[i, : self._n_picks[i]])
        n_last = int(self._n_last[i])
        last = None if n_last < 0 else tuple(int(j) for j in self._last[i, :n_last])
        title = f"LandmarkSelection-v1 [{i}]"
        frame: np.ndarray | None = self._renderer.render(
            lambda fig: draw_landmark_selection(fig, problem, x, P, k, picks, last, title)
        )
        return frame

    def close_extras(self, **kwargs: Any) -> None:
        """Close the renderer's figure, if any."""
        renderer = getattr(self, "_renderer", None)  # None if __init__ raised
        if renderer is not None:
            renderer.close()

    # -- BatchedVectorEnv hooks ----------------------------------------------------------------
    def _check_actions(self, actions: Any) -> np.ndarray:
        """``(B,)`` integer actions (shape and type; ranges are checked per stepped sub-env)."""
        arr = super()._check_actions(actions)
        if arr.shape != (self.num_envs,):
            raise ValueError(
                f"actions must have shape ({self.num_envs},) (one landmark per sub-env), got "
                f"shape {arr.shape}"
            )
        if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
            raise ArgumentTypeError(
                f"actions must be integers in [0, {self.n}), got dtype {arr.dtype}"
            )
        return arr

    def _reset_envs(self, idx: np.ndarray, options: dict[str, Any]) -> dict[str, Any]:
        """New episodes for ``idx`` from their generators; propagate to step 1 and open it."""
        st = self._static
        rngs = [self.np_randoms[i] for i in idx]  # made by reset() before this call
        draws = draw_episodes(self.config, [r for r in rngs if r is not None])
        self._landmarks[idx] = draws.landmarks
        self._imu[idx] = draws.imu_measured
        self._z[idx] = draws.measurements
        g = idx.size
        P0 = np.broadcast_to(st.P0, (g, STATE_DIM, STATE_DIM))
        self._cost[idx] = landmark_costs(P0, self.objective)
        self._error[idx] = np.linalg.norm(draws.x0_hat[:, :3] - st.states[0, :3], axis=1)
        self._x[idx], self._P[idx] = ekf_predict(
            draws.x0_hat, P0, draws.imu_measured[:, 0], self._dt, *self._sigmas
        )
        self._k[idx] = 1
        self._n_last[idx] = -1
        self._done[idx] = False
        self._open(idx)
        return self._infos(idx, np.zeros(g, dtype=np.bool_))

    def _step_envs(
        self, actions: np.ndarray, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One pick per sub-env of ``idx``; the ``k``-th pick updates, then predicts."""
        bad = (actions < 0) | (actions >= self.n)
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"action {int(actions[j])} of sub-env {int(idx[j])} is out of range: expected "
                f"an integer in [0, {self.n})"
            )
        if self._done[idx].any():
            raise RuntimeError("episode is over: call reset()")
        a = actions.astype(np.intp)
        masked = self._sel.selected[idx, a]
        rule = self.invalid_rule
        g = idx.size
        rewards = np.zeros(g)
        terminated = np.zeros(g, dtype=np.bool_)
        if masked.any():
            j = int(np.flatnonzero(masked)[0])
            rule.check(
                f"sub-env {int(idx[j])}: action {int(a[j])}",
                f"masked: landmark {int(a[j])} is already picked in this step",
            )
            rewards[masked] = rule.penalty  # noop: added to the reward; terminate: the reward
            if rule.terminates:
                terminated[masked] = True
                self._done[idx[masked]] = True
        live = ~terminated
        ok = live & ~masked
        if ok.any():  # valid picks join the gain states
            rows, picks = idx[ok], a[ok]
            add_picks(self._sel, rows, picks, self._gain_spec)
            self._picks[rows, self._n_picks[rows]] = picks
            self._n_picks[rows] += 1
        rows = idx[live]
        self._slots[rows] += 1
        full = live & (self._slots[idx] >= self.k)
        if full.any():
            rewards[full] -= self._update(idx[full])
            ending = full & (self._k[idx] >= self.horizon)
            terminated |= ending
            self._done[idx[ending]] = True
            going = full & ~ending
            if going.any():
                rows = idx[going]
                self._x[rows], self._P[rows] = ekf_predict(
                    self._x[rows], self._P[rows], self._imu[rows, self._k[rows]], self._dt,
                    *self._sigmas,
                )  # fmt: skip
                self._k[rows] += 1
                self._open(rows)
            rest = live & ~going
        else:
            rest = live
        if rest.any():  # picks without a new filter step: gains, masks, budget
            rows = idx[rest]
            write_observation(self._obs, rows, self._sel, (self.k - self._slots[rows]) / self.k)
        infos = self._infos(idx, masked)
        return rewards, terminated, np.zeros(g, dtype=np.bool_), infos

    def _observe(self) -> dict[str, np.ndarray]:
        """The batched observation (copies of the env's buffers)."""
        return {key: value.copy() for key, value in self._obs.items()}

    # -- helpers -------------------------------------------------------------------------------
    def _open(self, rows: np.ndarray) -> None:
        """Gain states at the new predictions of ``rows``: ``Q0 = P_pred^-1``, no pick."""
        H, h = aoa_candidates(self._x[rows], self._landmarks[rows])
        self._H[rows], self._h[rows] = H, h
        G = whiten_landmarks(H, self._static.R_landmark)
        open_selection(self._sel, rows, self._P[rows], G, self._gain_spec)
        self._n_picks[rows] = 0
        self._slots[rows] = 0
        self._obs["features"][rows] = landmark_features(h, self._k[rows], self.horizon)
        write_observation(self._obs, rows, self._sel, np.ones(rows.size))

    def _update(self, rows: np.ndarray) -> np.ndarray:
        """Update the filters of ``rows`` with their picks (grouped by count); their costs."""
        counts = self._n_picks[rows]
        for c in np.unique(counts):
            if c == 0:
                continue  # no valid pick: the prediction stands
            r = rows[counts == c]
            p = self._picks[r, :c]
            rr = r[:, None]
            z = self._z[rr, (self._k[r] - 1)[:, None], p]  # measurements[k - 1] of the picks
            res = ekf_update(
                self._x[r], self._P[r], self._H[rr, p], self._h[rr, p], z, self._static.R_landmark
            )
            self._x[r], self._P[r] = res.x, res.P
        self._last[rows] = self._picks[rows]
        self._n_last[rows] = counts
        cost = landmark_costs(self._P[rows], self.objective)
        self._cost[rows] = cost
        truth = self._static.states[self._k[rows], :3]
        self._error[rows] = np.linalg.norm(self._x[rows, :3] - truth, axis=1)
        return cost

    def _infos(self, idx: np.ndarray, invalid: np.ndarray) -> dict[str, Any]:
        """The single env's info keys for ``idx``, batched."""
        slot = np.arange(self.k)
        picks = np.where(slot < self._n_picks[idx, None], self._picks[idx], -1)
        last = np.where(slot < self._n_last[idx, None], self._last[idx], -1)
        mask = ~self._sel.selected[idx]
        mask[self._done[idx]] = True
        return {
            "objective": self._cost[idx],
            "position_error": self._error[idx],
            "k": self._k[idx],
            "picks": picks,
            "last_selection": last,
            "action_mask": mask,
            **InvalidActionRule.masked_info(invalid),
        }
