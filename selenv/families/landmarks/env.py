"""``selenv/LandmarkSelection-v1``: pick K of N angle-of-arrival landmarks for each EKF update."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.core.information import information_matrix
from selenv.core.linalg import FloatArray
from selenv.core.objectives import get_objective, objective_names
from selenv.envs.actions import INVALID_CODES, InvalidActionRule, check_discrete
from selenv.envs.conventions import (
    EpisodeLengthSpec,
    check_known_keywords,
    check_render_mode,
    named_parameters,
)
from selenv.envs.rendering import Renderer
from selenv.families.fim.env import fim_observation_space
from selenv.families.landmarks.batched import (
    POSITION,
    GainSpec,
    SelectionBatch,
    add_picks,
    landmark_costs,
    landmark_features,
    landmark_interest,
    open_selection,
    whiten_landmarks,
    write_observation,
)
from selenv.families.landmarks.scenario import (
    LandmarkConfig,
    LandmarkEKF,
    LandmarkProblem,
    make_landmark_problem,
)
from selenv.scenarios.validation import ArgumentTypeError, check_choice, describe

__all__ = [
    "OBJECTIVES",
    "POSITION",
    "LandmarkGainView",
    "LandmarkSelectionEnv",
    "LandmarkSettings",
    "landmark_cost",
    "landmark_features",
    "landmark_interest",
    "landmark_settings",
    "padded_picks",
]

#: the built-in objectives (every registered one is accepted: :func:`objective_names`)
OBJECTIVES = ("logdet", "det", "trace", "max_eig")

_ROW0 = np.zeros(1, dtype=np.intp)  # the single env is row 0 of a batch of one


def padded_picks(picks: Sequence[int], k: int) -> np.ndarray:
    """``(k,)`` int64: ``picks`` in order, padded with ``-1``.

    The fixed-shape form of ``info["picks"]`` and ``info["last_selection"]``.
    """
    out = np.full(k, -1, dtype=np.int64)
    out[: len(picks)] = picks
    return out


def landmark_cost(P: FloatArray, objective: str) -> float:
    """The cost of a posterior covariance ``P`` (9, 9) under a registered objective.

    ``"logdet"`` / ``"det"``: ``log det P`` or ``det P`` (eq. 11); ``"trace"``: the position
    MSE ``tr(P[:3, :3])`` (m^2), the A-optimal criterion (Kirchner et al. 2020, eq. 6) on the
    position block; ``"max_eig"``: ``lambda_max(P[:3, :3])`` (m^2), the variance along the
    worst-determined direction of the position, the E-optimal criterion (eq. 7). Any other
    registered objective scores the block :func:`landmark_interest` gives. The ``B = 1`` case
    of :func:`~selenv.families.landmarks.batched.landmark_costs`.

    Raises:
        TypeError, ValueError: ``objective`` not a registered name.
    """
    return float(landmark_costs(np.asarray(P, dtype=np.float64)[None], objective)[0])


@dataclass(frozen=True)
class LandmarkSettings:
    """The validated keywords of ``LandmarkSelection-v1`` (single and vector env alike).

    Attributes:
        config: the scenario.
        n: ``N``, the number of landmarks.
        k: picks per filter step.
        horizon: filter steps.
        objective: the cost's name.
        invalid_rule: the ``invalid_action`` handling.
        render_mode: the checked mode.
        spec: what the gain state scores (``solver_objective``, ``interest``).
    """

    config: LandmarkConfig
    n: int
    k: int
    horizon: int
    objective: str
    invalid_rule: InvalidActionRule
    render_mode: str | None
    spec: GainSpec


def landmark_settings(
    owner: type,
    metadata: dict[str, Any],
    *,
    n_landmarks: Any,
    k: Any,
    horizon: Any,
    objective: Any,
    landmarks: Any,
    invalid_action: Any,
    invalid_action_penalty: Any,
    render_mode: Any,
    config: dict[str, Any],
) -> LandmarkSettings:
    """Validate the keywords of ``owner`` (the single or the vector env) as the env does.

    Raises:
        TypeError: an unknown keyword or a value of the wrong type, naming it.
        ValueError: a value out of range, naming it.
    """
    fields = {f.name for f in dataclasses.fields(LandmarkConfig)}
    check_known_keywords(
        config,
        fields - {"n_landmarks", "horizon", "landmarks"},
        "LandmarkSelection-v1",
        named_parameters(owner),
    )
    mode = check_render_mode(render_mode, metadata)
    rule = InvalidActionRule(invalid_action, invalid_action_penalty)
    check_choice(objective, "objective", objective_names())
    if isinstance(k, bool | np.bool_) or not isinstance(k, int | np.integer):
        raise ArgumentTypeError(f"k must be an int in [1, n_landmarks], got {describe(k)}")
    cfg = LandmarkConfig(n_landmarks=n_landmarks, horizon=horizon, landmarks=landmarks, **config)
    if not 1 <= k <= cfg.n_landmarks:
        raise ValueError(f"k must lie in [1, n_landmarks={cfg.n_landmarks}], got {k}")
    spec = GainSpec(get_objective(objective).solver_name, landmark_interest(objective))
    return LandmarkSettings(
        config=cfg,
        n=int(cfg.n_landmarks),
        k=int(k),
        horizon=int(cfg.horizon),
        objective=objective,
        invalid_rule=rule,
        render_mode=mode,
        spec=spec,
    )


def landmark_observation_space(n: int) -> gym.spaces.Dict:
    """The observation space over ``n`` landmarks (the ``FIMSelection-v1`` layout)."""
    space = fim_observation_space(n, 2, 9)
    space.spaces["features"] = gym.spaces.Box(-1.0, 1.0, (n, 4), np.float32)
    return space


class LandmarkGainView:
    """The gain state of the single env's open filter step (row ``0`` of its batch).

    The attributes of :class:`~selenv.core.information.LogDetGainState` the agents read:
    ``selected`` (N,), ``order``, ``G`` (N, 2, 9), ``Q0`` (9, 9), ``P`` (9, 9), ``Z``
    (N, 2, 9), ``gains`` (N,), ``information`` (9, 9), ``objective``, :meth:`masked_gains`.
    Views of the env's arrays for this filter step (a new step has new arrays); a pick updates
    ``selected``, ``Z``, ``gains``, ``P`` and ``objective`` in place.
    """

    def __init__(self, sel: SelectionBatch, order: list[int]) -> None:
        self._sel = sel
        self.order = order
        self.N, self.m, self.d = sel.G.shape[1:]

    @property
    def selected(self) -> np.ndarray:
        """(N,) bool: the landmarks picked in this filter step."""
        return self._sel.selected[0]

    @property
    def G(self) -> FloatArray:
        """(N, 2, 9) whitened Jacobians ``R^-1/2 H``."""
        return self._sel.G[0]

    @property
    def Q0(self) -> FloatArray:
        """(9, 9) prior information ``P_pred^-1``."""
        return self._sel.Q0[0]

    @property
    def Z(self) -> FloatArray:
        """(N, 2, 9) the landmarks whitened in the current information."""
        return self._sel.Z[0]

    @property
    def gains(self) -> FloatArray:
        """(N,) marginal gains of every landmark (also the picked ones)."""
        return self._sel.gains[0]

    @property
    def P(self) -> FloatArray:
        """(9, 9) ``A^-1``: the posterior covariance of the picks so far."""
        return self._sel.P(_ROW0)[0]

    @property
    def information(self) -> FloatArray:
        """(9, 9) ``A = Q0 + sum_{k in S} G_k^T G_k``, recomputed from the picks (eq. 2)."""
        return information_matrix(self.Q0, self.G, self.order)

    @property
    def objective(self) -> float:
        """``f(S)`` of the picks (the log-det gain eq. 9, or ``c(P_pred) - c(P_S)``)."""
        return float(self._sel.objective[0])

    def masked_gains(self) -> FloatArray:
        """Gains with the picked landmarks at ``-inf`` (for argmax)."""
        return np.where(self.selected, -np.inf, self.gains)


class LandmarkSelectionEnv(EpisodeLengthSpec, gym.Env[dict[str, np.ndarray], np.int64]):
    r"""Choose which K of N landmarks the EKF processes at each step of an angles-only UAV flight.

    ## Description
    The data-selection problem of Soubaras & Chahbazian (2023). A UAV navigates with an EKF on
    position, velocity and Euler attitude (9 states), propagated with a noisy IMU at 10 Hz; it
    can observe the azimuth and elevation of ``n_landmarks`` known landmarks (eqs. 16-18) but
    processes only ``k`` of them per step (Algorithm 3: propagation, selection, update). The
    paper's cost is eq. (11) on the approximate CRLB, i.e. the filter's posterior covariance:
    ``det P`` (``objective="det"``) or ``log det P`` (``"logdet"``, default). For one step both
    are minimised by the same selection, which maximises ``log det(I + W_S)`` with ``W`` the
    selected rows whitened in the predicted covariance; the sequence matters through the
    future (the Bellman eq. 13 the paper truncates to its first term). ``objective="trace"``
    scores the position MSE ``tr(P[:3, :3])`` (m^2) instead (A-optimal, Kirchner et al. 2020
    eq. 6, on the position block; not submodular), ``objective="max_eig"`` the largest
    eigenvalue of that block (E-optimal, eq. 7; not submodular either).

    ## Action Space
    ``Discrete(N)``: one landmark per env step; the filter updates after the ``k``-th pick of
    a filter step. Landmarks already picked in this filter step are masked
    (:meth:`action_masks`, ``info["action_mask"]``, ``obs["action_mask"]``). A masked pick is
    handled by ``invalid_action`` (:mod:`selenv.envs.actions`): ``"noop"`` (default) spends
    the pick slot without adding a landmark (the filter still updates after ``k`` slots, with
    the landmarks picked), ``"raise"`` raises ``ValueError``, ``"terminate"`` ends the
    episode. A non-integer or out-of-range action is a ``TypeError`` / ``ValueError``.

    ## Observation Space
    The ``FIMSelection-v1`` layout over the landmarks of the current filter step:

    | key | shape | meaning |
    |---|---|---|
    | ``gain`` | ``(N,)`` | marginal gain given this step's picks (see below) |
    | ``whitened`` | ``(N, 18)`` | ``R^-1/2 H_n`` whitened in the current information |
    | ``features`` | ``(N, 4)`` | sin, cos of the predicted azimuth, elevation / (pi/2), time |
    | ``selected`` | ``(N,)`` | 1 if picked in this filter step |
    | ``budget_left`` | ``(1,)`` | fraction of the ``k`` picks still to make |
    | ``action_mask`` | ``(N,)`` | 1 where the action is allowed |

    ``gain``: the marginal ``log det`` information gain (``"logdet"``, ``"det"``), or with
    ``"trace"`` / ``"max_eig"`` the decrease of ``tr(P[:3, :3])`` / ``lambda_max(P[:3, :3])``
    (m^2) of this step's posterior if the landmark were added.

    ## Rewards
    0 for the first ``k - 1`` picks of a filter step; at the ``k``-th the filter updates and the
    reward is minus the cost eq. (11) of the posterior (``-log det P``, ``-det P`` or, with
    ``"trace"`` / ``"max_eig"``, ``-tr(P[:3, :3])`` / ``-lambda_max(P[:3, :3])``), so the
    return is minus the paper's objective eq. (12).
    ``info["objective"]`` is that cost after the latest update (its name:
    ``env.unwrapped.objective``) and ``info["position_error"]`` the true position error (m) of
    that posterior estimate (``k`` is the index of the step whose picks are open).
    ``info["picks"]`` (the landmarks picked so far in the open step) and
    ``info["last_selection"]`` (those the latest update used) are ``(k,)`` int64 arrays in pick
    order, padded with ``-1`` (``last_selection`` is all ``-1`` before the first update), so
    every step's ``info`` has the same keys, shapes and dtypes.

    ## Starting State
    A new seeded flight per ``reset``: landmark layout, IMU noise, initial error (Table I),
    measurement noise; the first propagation is done, so the first pick is for step 1.

    ## Episode End
    Terminates after ``horizon`` filter updates, i.e. ``k * horizon`` steps
    (``env.spec.max_episode_steps``), or at an invalid action with
    ``invalid_action="terminate"``. Never truncates.

    ## Rendering
    ``render_mode="rgb_array"`` or ``"human"``: the UAV's true track and estimate, the
    landmarks with the ones picked now and in the last update, the 2-sigma position ellipse.

    ## Vector Env
    ``gymnasium.make_vec("selenv/LandmarkSelection-v1", num_envs=B, **kwargs)`` returns the
    native :class:`~selenv.families.landmarks.vector.LandmarkSelectionVectorEnv`: the ``B``
    filters and gain states in arrays with a leading batch axis, stepped by the batched core
    (:mod:`selenv.families.landmarks.batched`) this env runs with ``B = 1``. Autoreset is
    Gymnasium's ``NEXT_STEP``; seeding is ``SyncVectorEnv``'s (``reset(seed=s)`` seeds sub-env
    ``b`` with ``s + b``), so sub-env ``b`` replays ``gymnasium.make(id)`` reset with
    ``seed=s + b`` under the same actions. ``vectorization_mode="sync"`` still gives the loop.

    ## Arguments
    ``gymnasium.make("selenv/LandmarkSelection-v1", n_landmarks=30, k=2, horizon=300,
    objective="logdet", landmarks=None, invalid_action="noop", invalid_action_penalty=0.0,
    render_mode=None)``; ``landmarks`` is an optional (N, 3) ENU layout; ``objective`` is
    ``"logdet"``, ``"det"``, ``"trace"``, ``"max_eig"`` or any objective registered with
    :func:`~selenv.core.objective_registry.register_objective` (scored on the whole state if
    it is unit-invariant, else on the position block). Any other
    :class:`~selenv.families.landmarks.scenario.LandmarkConfig` field can be passed too (its
    docstring
    gives every range: ``n_landmarks`` an int in ``[1, 200]``, ``horizon`` in ``[1, 100000]``,
    ``dt`` in ``[1e-3, 1]`` s, ...); ``k`` is an int in ``[1, n_landmarks]``. An unknown
    keyword raises ``TypeError``; a bad value a ``TypeError`` / ``ValueError`` naming it.

    ## Version History
    * v1: the current id; valid trajectories as v0's. ``invalid_action`` modes, rendering and
      every registered ``objective`` (``"trace"``, ``"max_eig"``, ...) added, the default
      unchanged.
    * v0: release 0.1 (the same episodes for valid actions, tested against recordings);
      deprecated in favour of v1.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "invalid_codes": INVALID_CODES,
    }

    def __init__(
        self,
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
        settings = landmark_settings(
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
        self.render_mode = settings.render_mode
        self.invalid_rule = settings.invalid_rule
        self.config = settings.config
        self.n, self.k, self.horizon = settings.n, settings.k, settings.horizon
        self.objective = settings.objective
        self._gain_spec = settings.spec
        self.max_episode_steps = self.k * self.horizon
        self.action_space = gym.spaces.Discrete(self.n)
        self.observation_space = landmark_observation_space(self.n)  # type: ignore[assignment, unused-ignore]
        self.problem: LandmarkProblem | None = None
        self._ekf: LandmarkEKF | None = None
        self._sel = SelectionBatch.empty(1, self.n)  # the gain state: a batch of one
        self._open = False
        self._features = np.zeros((self.n, 4), np.float32)
        self.picks: list[int] = []
        self.last_selection: tuple[int, ...] | None = None
        self._cost = float("nan")
        self._error = float("nan")
        self._done = False
        self._slots = 0
        self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])

    # -- oracle view for heuristics (same names as FIMSelectionEnv) --------------------------
    @property
    def ekf(self) -> LandmarkEKF:
        """The filter (needs ``reset``)."""
        if self._ekf is None:
            raise RuntimeError("call reset() before using the environment")
        return self._ekf

    @property
    def state(self) -> LandmarkGainView:
        """Gain state of the current filter step: prior ``P_pred^-1`` plus this step's picks."""
        if not self._open:
            raise RuntimeError("call reset() before using the environment")
        return LandmarkGainView(self._sel, self.picks)

    @property
    def solver_objective(self) -> str:
        """What the one-step oracle agents maximise: the objective or its ``solver_proxy``.

        ``det`` and ``log det`` of the posterior have the same minimiser, the maximiser of the
        log-det gain, so ``"det"`` maps to ``"logdet"``; ``"trace"`` and ``"max_eig"`` are
        scored on :data:`POSITION` (:attr:`interest`).
        """
        return self._gain_spec.objective

    @property
    def interest(self) -> tuple[int, ...] | None:
        """State indices the objective scores (:func:`landmark_interest`).

        The position for ``"trace"`` / ``"max_eig"``; ``None`` (the whole state) for
        ``"logdet"`` / ``"det"``.
        """
        return self._gain_spec.interest

    @property
    def budget_left(self) -> int:
        """Picks left in the current filter step (an invalid no-op pick spends one too)."""
        return self.k - self._slots

    def action_masks(self) -> np.ndarray:
        """(N,) bool: landmarks not yet picked in this filter step."""
        return ~self.state.selected

    # -- Gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """New seeded flight; propagate to step 1 and open its selection."""
        super().reset(seed=seed)
        self.problem = make_landmark_problem(self.config, self.np_random)
        self._ekf = LandmarkEKF(self.problem)
        self.last_selection = None
        self._done = False
        self._cost = self._cost_of(self._ekf.P)
        self._error = self._position_error()
        self._ekf.predict()
        self._open_step()
        return self._obs(), self._info()

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Pick one landmark; after the ``k``-th pick, update the filter and propagate."""
        ekf = self.ekf
        if not self._open or self._done:
            raise RuntimeError("episode is over: call reset()")
        a = check_discrete(action, self.n)
        reason = (
            f"masked: landmark {a} is already picked in this step"
            if self._sel.selected[0, a]
            else None
        )
        rule = self.invalid_rule
        if rule.check(f"action {a}", reason) and rule.terminates:
            self._done = True
            return self._obs(), rule.penalty, True, False, self._info(reason)
        penalty = rule.penalty if reason else 0.0
        if reason is None:
            add_picks(self._sel, _ROW0, np.array([a]), self._gain_spec)
            self.picks.append(a)
        self._slots += 1
        if self._slots < self.k:
            return self._obs(), penalty, False, False, self._info(reason)
        ekf.update(self.picks)
        self.last_selection = tuple(self.picks)
        self._cost = self._cost_of(ekf.P)
        self._error = self._position_error()  # of the posterior, before the next prediction
        reward = penalty - self._cost
        if ekf.k >= self.horizon:
            self._done = True
            return self._obs(), reward, True, False, self._info(reason)
        ekf.predict()
        self._open_step()
        return self._obs(), reward, False, False, self._info(reason)

    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        """A frame of the flight (``render_mode`` ``"rgb_array"``: ``(H, W, 3)`` uint8)."""
        ekf, problem = self.ekf, self.problem
        title = "LandmarkSelection-v1"
        picks, last = tuple(self.picks), self.last_selection
        from selenv.families.landmarks.rendering import (
            draw_landmark_selection,  # matplotlib: first frame
        )

        return self._renderer.render(
            lambda fig: draw_landmark_selection(
                fig, problem, ekf.x, ekf.P, ekf.k, picks, last, title
            )
        )

    def close(self) -> None:
        """Close the render window, if any."""
        self._renderer.close()

    # -- helpers -----------------------------------------------------------------------------
    def _cost_of(self, P: FloatArray) -> float:
        return landmark_cost(P, self.objective)

    def _open_step(self) -> None:
        """Gain state over the landmarks at the new prediction: ``Q0 = P_pred^-1``."""
        ekf = self.ekf
        H, h_pred = ekf.candidates()
        G = whiten_landmarks(H[None], ekf.problem.R_landmark)
        self._sel = SelectionBatch.empty(1, self.n)  # new arrays: older views stay as they were
        open_selection(self._sel, _ROW0, ekf.P[None], G, self._gain_spec)
        self._features = landmark_features(h_pred, ekf.k, self.horizon)
        self._open = True
        self.picks = []
        self._slots = 0

    def _obs(self) -> dict[str, np.ndarray]:
        n = self.n
        out: dict[str, np.ndarray] = {
            "gain": np.empty((1, n), np.float32),
            "whitened": np.empty((1, n, 18), np.float32),
            "selected": np.empty((1, n), np.int8),
            "budget_left": np.empty((1, 1), np.float32),
            "action_mask": np.empty((1, n), np.int8),
        }
        write_observation(out, _ROW0, self._sel, np.array([self.budget_left / self.k]))
        obs = {key: value[0] for key, value in out.items()}
        obs["features"] = self._features.copy()
        return obs

    def _position_error(self) -> float:
        ekf = self.ekf
        truth = self.problem.states[ekf.k]  # type: ignore[union-attr]
        return float(np.linalg.norm(ekf.x[:3] - truth[:3]))

    def _info(self, reason: str | None = None) -> dict[str, Any]:
        ekf = self.ekf
        mask = self.action_masks() if not self._done else np.ones(self.n, bool)
        return {
            "objective": self._cost,
            "position_error": self._error,
            "k": ekf.k,
            "picks": padded_picks(self.picks, self.k),
            "last_selection": padded_picks(self.last_selection or (), self.k),
            "action_mask": mask,
            **self.invalid_rule.info(reason),
        }
