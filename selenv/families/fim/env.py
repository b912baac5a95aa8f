"""``selenv/FIMSelection-v1``: heterogeneous measurement selection by Fisher information."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from selenv.core.objectives import get_objective, objective_names
from selenv.envs.actions import INVALID_CODES, InvalidActionRule, check_discrete
from selenv.envs.conventions import EpisodeLengthSpec, check_render_mode
from selenv.envs.rendering import Renderer
from selenv.families.fim.batched import FIMBatchState, SubEnvGainState, batched_features
from selenv.families.fim.scenario import (
    SENSOR_NAMES,
    FIMProblem,
    FIMProblemBatch,
    FIMScenarioConfig,
    config_from,
    make_problems,
    problem_constants,
)
from selenv.scenarios.validation import ArgumentTypeError, check_choice, check_integer, describe

__all__ = [
    "FIMSelectionEnv",
    "FIMSettings",
    "candidate_features",
    "check_sensors",
    "fim_observation",
    "fim_observation_space",
    "fim_observations",
    "fim_settings",
    "parse_action",
]


def check_sensors(sensors: Any) -> tuple[Any, ...] | None:
    """``sensors`` keyword: ``None`` (the preset's) or a tuple / list, returned as a tuple."""
    if sensors is not None and not isinstance(sensors, tuple | list):
        raise ArgumentTypeError(
            f"sensors must be None or a sequence of names from {SENSOR_NAMES}, "
            f"got {describe(sensors)}"
        )
    return None if sensors is None else tuple(sensors)


def parse_action(action: Any, n: int, mask: np.ndarray, name: str = "action") -> int:
    """Validate a ``Discrete(n)`` action against ``mask``; return it as ``int`` (strict).

    Raises:
        TypeError: not an integer (bools and floats are rejected, never rounded).
        ValueError: out of ``[0, n)`` or masked, with the reason.
    """
    k = check_discrete(action, n, name)
    if not mask[k]:
        raise ValueError(f"{name} {k} is masked: candidate {k} is already selected")
    return k


def fim_observation_space(n: int, m: int, d: int) -> spaces.Dict:
    """The ``Dict`` observation space over a pool of ``n`` candidates (``m`` rows, ``d`` params)."""
    return spaces.Dict(
        {
            "gain": spaces.Box(0.0, np.inf, (n,), np.float32),
            "whitened": spaces.Box(-np.inf, np.inf, (n, m * d), np.float32),
            "features": spaces.Box(0.0, 1.0, (n, 4), np.float32),
            "selected": spaces.MultiBinary(n),
            "budget_left": spaces.Box(0.0, 1.0, (1,), np.float32),
            "action_mask": spaces.MultiBinary(n),
        }
    )


def candidate_features(problem: FIMProblem) -> np.ndarray:
    """Static per-candidate features ``(N, 4)``: one-hot sensor, time in the window in [0, 1]."""
    return batched_features(problem.times[None], problem.sensor)[0]


def fim_observations(
    gains: np.ndarray,
    Z: np.ndarray,
    selected: np.ndarray,
    features: np.ndarray,
    budget_fraction: np.ndarray,
) -> dict[str, np.ndarray]:
    """Assemble ``B`` observations (new arrays) with a leading batch axis.

    Args:
        gains: ``(B, N)`` current marginal gains (0 in the observation once selected).
        Z: ``(B, N, m, d)`` candidates whitened in the current information.
        selected: ``(B, N)`` bool.
        features: ``(B, N, 4)`` float32 (:func:`candidate_features`).
        budget_fraction: ``(B,)`` fraction of the budget still to spend.
    """
    B, N = gains.shape
    selected = np.asarray(selected, dtype=bool)
    gain = gains.astype(np.float32)
    gain[selected] = 0.0
    mask = np.logical_not(selected).view(np.int8)
    return {
        "gain": gain,
        "whitened": Z.reshape(B, N, -1).astype(np.float32),
        "features": features.copy(),
        "selected": selected.astype(np.int8),
        "budget_left": budget_fraction.astype(np.float32).reshape(B, 1),
        "action_mask": mask,
    }


def fim_observation(
    gains: np.ndarray,
    Z: np.ndarray,
    selected: np.ndarray,
    features: np.ndarray,
    budget_fraction: float,
) -> dict[str, np.ndarray]:
    """Assemble one observation from a gain state's ``gains (n,)`` and ``Z (n, m, d)``."""
    obs = fim_observations(
        gains[None], Z[None], selected[None], features[None], np.array([budget_fraction])
    )
    return {key: val[0] for key, val in obs.items()}


@dataclass(frozen=True)
class FIMSettings:
    """The validated keywords of ``FIMSelection`` (shared by the single and the vector env).

    Attributes:
        config: the scenario config; ``objective``: a registered name; ``invalid_rule``:
            what a masked pick does; ``budget``: picks per episode, in ``[1, N]``;
        n, m, d: pool size, rows per candidate, parameters; ``interest``: ``(x, y)`` indices
            scored by objectives that are not unit-invariant (``None``: all parameters).
    """

    config: FIMScenarioConfig
    objective: str
    invalid_rule: InvalidActionRule
    budget: int
    n: int
    m: int
    d: int
    interest: tuple[int, ...] | None


def fim_settings(
    *,
    preset: str = "example2_moving",
    n_candidates: int = 100,
    budget: int = 10,
    sensors: tuple[str, ...] | list[str] | None = None,
    n_agents: int | None = None,
    camera_sigma_px: float | None = None,
    toa_sigma_m: float | None = None,
    doppler_sigma_mps: float | None = None,
    randomize: bool = True,
    invalid_action: str = "noop",
    invalid_action_penalty: float = 0.0,
    objective: str = "logdet",
) -> FIMSettings:
    """Validate the env keywords (see :class:`FIMSelectionEnv`, Arguments).

    Raises:
        TypeError, ValueError: a bad keyword, named, with its range.
    """
    objective = check_choice(objective, "objective", objective_names())
    invalid_rule = InvalidActionRule(invalid_action, invalid_action_penalty)
    overrides: dict[str, Any] = {"n_candidates": n_candidates, "randomize": randomize}
    check_integer(budget, "budget", 1)  # the type first; the pool size bounds it below
    for key, val in (
        ("sensors", check_sensors(sensors)),
        ("n_agents", n_agents),
        ("camera_sigma_px", camera_sigma_px),
        ("toa_sigma_m", toa_sigma_m),
        ("doppler_sigma_mps", doppler_sigma_mps),
    ):
        if val is not None:
            overrides[key] = val
    config = config_from(preset, **overrides)
    const = problem_constants(config)
    n, m, d = const.shape
    interest = (
        None
        if get_objective(objective).unit_invariant
        else tuple(const.param_names.index(name) for name in ("x", "y"))
    )
    budget = check_integer(budget, f"budget (at most the pool size {n})", 1, n)
    return FIMSettings(config, objective, invalid_rule, budget, n, m, d, interest)


class FIMSelectionEnv(EpisodeLengthSpec, gym.Env[dict[str, np.ndarray], np.int64]):
    r"""Pick measurements one at a time to maximise the log det of the Fisher information.

    ## Description
    The heterogeneous measurement-selection problem of Kirchner, Hespanha & Garagić (2020).
    Sensing agents move along paths and collect a pool of candidate measurements of a vehicle
    (camera image coordinates eq. 23, time of arrival eq. 20, Doppler shift eq. 22). Only
    ``budget`` of them can be sent to the fusion centre. Each step the agent picks one more
    candidate; the objective is eq. (9),
    ``f(F) = log det(Q0 + sum_{k in F} Q_k) - log det Q0`` with ``Q_k = J_k^T Sigma_k^-1 J_k``.
    ``f`` is monotone submodular, so greedy (always taking the largest current gain) is within
    ``1 - 1/e`` of the optimum; swap search and brute force do better on small pools.

    ## Action Space
    ``Discrete(N)``: the index of the candidate to select, ``N = n_candidates x sensors x
    agents``. Already-selected candidates are masked (:meth:`action_masks`,
    ``info["action_mask"]``, ``obs["action_mask"]``). Picking a masked candidate is handled by
    ``invalid_action`` (:mod:`selenv.envs.actions`): ``"noop"`` (default) spends the budget
    slot without selecting anything (``info["invalid_action"]``, ``info["invalid_code"]``),
    ``"raise"`` raises ``ValueError``, ``"terminate"`` ends the episode. A non-integer or
    out-of-range action is a ``TypeError`` / ``ValueError`` in every mode.

    ## Observation Space
    ``Dict`` (``m`` = rows per candidate, 2 with cameras else 1; ``d`` = parameters):

    | key | shape | meaning |
    |---|---|---|
    | ``gain`` | ``(N,)`` | current marginal gain in ``objective`` (0 once selected) |
    | ``whitened`` | ``(N, m d)`` | ``G_k L^-T``: candidate whitened in the current FIM ``L L^T`` |
    | ``features`` | ``(N, 4)`` | one-hot sensor (camera, toa, doppler), time in window [0, 1] |
    | ``selected`` | ``(N,)`` | 1 if selected |
    | ``budget_left`` | ``(1,)`` | fraction of the budget still to spend |
    | ``action_mask`` | ``(N,)`` | 1 where the action is allowed |

    ``gain`` alone lets a policy reproduce greedy (its argmax); ``whitened`` holds every
    cross term (``Z_k Z_l^T``), so a policy can also anticipate redundancy between candidates.
    ``gain`` by ``objective``: ``"logdet"`` ``log det(I + S_k)`` (nats); ``"trace"`` the
    decrease of the target-position MSE bound ``tr(E P E^T)`` (m^2) if ``k`` were added;
    ``"max_eig"`` the decrease of ``lambda_max(E P E^T)`` (m^2). ``whitened`` does not depend on
    ``objective``.

    ## Rewards
    The gain of the pick in ``log det FIM`` (nats), so the undiscounted return is ``f(F)``.
    ``info["objective"]`` is ``f`` after the step (its name: ``env.unwrapped.objective``).
    ``objective="trace"`` (A-optimal, eq. 6) or ``"max_eig"`` (E-optimal, eq. 7) score the
    target position ``(x, y)`` instead (``E`` selects them; :mod:`selenv.core.objectives`):
    ``f(F) = tr(E P0 E^T) - tr(E P_F E^T)`` (the decrease of the position MSE bound, m^2) or
    ``lambda_max(E P0 E^T) - lambda_max(E P_F E^T)``, ``P_F`` the CRLB; the reward is the
    step's increase of ``f``, so the return is again ``f(F)``. Neither is submodular: greedy has
    no guarantee there and the ``lazy_greedy`` agent refuses them.

    ## Starting State
    A new scenario per ``reset``: the truth is drawn from the prior ``p(theta)`` and, when
    ``randomize`` is true, the geometry (path rotation, range, candidate times) is drawn too.
    Nothing is selected.

    ## Episode End
    Terminates after ``budget`` steps (``env.spec.max_episode_steps``), i.e. when the budget
    is spent, or at an invalid action with ``invalid_action="terminate"``. Never truncates.

    ## Rendering
    ``render_mode="rgb_array"`` or ``"human"``: the sensing agents' paths, the target, every
    candidate by sensor type with the picked ones bold, and the 2-sigma ellipse of the target
    position under the current information.

    ## Arguments
    ``gymnasium.make("selenv/FIMSelection-v1", preset="example2_moving", n_candidates=100,
    budget=10, sensors=None, n_agents=None, camera_sigma_px=None, toa_sigma_m=None,
    doppler_sigma_mps=None, randomize=True, invalid_action="noop", invalid_action_penalty=0.0,
    render_mode=None)``; ``None`` keeps the preset's value. Presets: ``example1`` (one
    camera), ``example2`` (camera + Doppler), ``example3`` (two agents), each with the paper's
    stationary target, and ``example1_moving``, ``example2_moving``, ``example3_moving`` (same
    pools, moving target: velocity and curvature estimated too). The default
    ``example2_moving`` is the v0 benchmark (what ``example2`` was before the paper's
    stationary reading; kept so v0 trajectories do not change). Ranges (an error
    naming the keyword and its range outside them): ``n_candidates`` an int in ``[1, 5000]``,
    ``n_agents`` in ``[1, 8]``, ``budget`` in ``[1, N]``, ``camera_sigma_px`` in
    ``[1e-3, 1e3]`` px, ``toa_sigma_m`` in ``[1e-3, 1e5]`` m, ``doppler_sigma_mps`` in
    ``[1e-3, 1e5]`` m/s, ``invalid_action_penalty`` in ``[-1e6, 1e6]``
    (:class:`~selenv.families.fim.scenario.FIMScenarioConfig` lists all fields).
    ``objective="logdet"`` (default), ``"trace"``, ``"max_eig"``, ``"det"`` or any objective
    registered with :func:`~selenv.core.objective_registry.register_objective` chooses ``f``
    (see Rewards; an unknown name is a ``ValueError`` listing the known ones).

    ## Vector Env
    ``gymnasium.make_vec("selenv/FIMSelection-v1", num_envs=B, **kwargs)`` returns the native
    :class:`~selenv.families.fim.vector.FIMSelectionVectorEnv`: the ``B`` episodes in batch
    arrays, stepped by the same batched core as this env
    (:class:`~selenv.families.fim.batched.FIMBatchState`, of which this env is the ``B = 1``
    case), observations and infos with a leading ``(B,)`` axis, ``action_masks()`` ``(B, N)``.
    Autoreset is Gymnasium's ``NEXT_STEP`` (the step after an episode ends resets that sub-env,
    reward 0, its action ignored). Seeding as ``SyncVectorEnv``: ``reset(seed=s)`` seeds
    sub-env ``b`` with ``s + b``, so it replays ``gymnasium.make(...).reset(seed=s + b)``;
    ``options={"reset_mask": mask}`` resets some sub-envs. ``vectorization_mode="sync"`` still
    gives the Python loop over single envs.

    ## Version History
    * v1: ``preset="example1" / "example2" / "example3"`` are Kirchner et al.'s stationary
      examples (the moving-target ones are ``example*_moving``; the default,
      ``example2_moving``, is v0's default scenario); ``invalid_action`` modes, rendering and
      every registered ``objective``.
    * v0: release 0.1: ``preset="example2"`` (the default) and ``"example3"`` meant the
      moving-target scenarios; ``FIMSelection-v0`` maps them so (tested against recordings of
      0.1's episodes); deprecated in favour of v1.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        "render_modes": ["rgb_array", "human"],
        "render_fps": 4,
        "invalid_codes": INVALID_CODES,
    }

    def __init__(
        self,
        *,
        preset: str = "example2_moving",
        n_candidates: int = 100,
        budget: int = 10,
        sensors: tuple[str, ...] | list[str] | None = None,
        n_agents: int | None = None,
        camera_sigma_px: float | None = None,
        toa_sigma_m: float | None = None,
        doppler_sigma_mps: float | None = None,
        randomize: bool = True,
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        objective: str = "logdet",
        render_mode: str | None = None,
    ) -> None:
        self.render_mode = check_render_mode(render_mode, self.metadata)
        settings = fim_settings(
            preset=preset, n_candidates=n_candidates, budget=budget, sensors=sensors,
            n_agents=n_agents, camera_sigma_px=camera_sigma_px, toa_sigma_m=toa_sigma_m,
            doppler_sigma_mps=doppler_sigma_mps, randomize=randomize,
            invalid_action=invalid_action, invalid_action_penalty=invalid_action_penalty,
            objective=objective,
        )  # fmt: skip
        self.settings = settings
        self.objective = settings.objective
        self.invalid_rule = settings.invalid_rule
        self.config = settings.config
        self.n, self.m, self.d = settings.n, settings.m, settings.d
        #: ``(x, y)`` indices scored by objectives that are not unit-invariant (trace, max_eig);
        #: ``None`` (all parameters) for unit-invariant ones (log det, det)
        self.interest: tuple[int, ...] | None = settings.interest
        self.budget = settings.budget
        self.max_episode_steps = self.budget
        self.action_space = spaces.Discrete(self.n)
        self.observation_space = fim_observation_space(self.n, self.m, self.d)  # type: ignore[assignment, unused-ignore]
        self._batch: FIMProblemBatch | None = None
        self._problem: FIMProblem | None = None
        #: the batched core holding this env's one episode (the ``B = 1`` case)
        self.core = FIMBatchState(
            1, problem_constants(self.config).Q0, (self.n, self.m, self.d), self.objective,
            self.interest,
        )  # fmt: skip
        self._state: SubEnvGainState | None = None
        self._steps = 0
        self._done = False
        self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])

    # -- oracle view used by heuristic agents ---------------------------------------------
    @property
    def problem(self) -> FIMProblem | None:
        """The current problem (``None`` before :meth:`reset`).

        Built on first access after a reset (its geometry beyond ``G`` and ``times`` is not
        needed to step the episode; :class:`~selenv.families.fim.scenario.FIMProblemBatch`).
        """
        if self._problem is None and self._batch is not None:
            self._problem = self._batch.problem(0)
        return self._problem

    @property
    def state(self) -> SubEnvGainState:
        """The live gain state (information, gains, selection); requires :meth:`reset`.

        The ``GainState`` interface (:class:`~selenv.core.information.LogDetGainState`'s
        attributes and methods) over the env's batched core (:attr:`core`).
        """
        if self._state is None:
            raise RuntimeError("call reset() before using the env")
        return self._state

    @property
    def solver_objective(self) -> str:
        """The objective the oracle agents optimise: ``objective`` or its ``solver_proxy``.

        ``"det"`` -> ``"logdet"``: the same picks without under- / overflow of ``det``;
        :attr:`interest` holds its indices.
        """
        return get_objective(self.objective).solver_name

    @property
    def budget_left(self) -> int:
        """Number of picks still to make (an invalid no-op pick spends one too)."""
        return self.budget - self._steps

    def action_masks(self) -> np.ndarray:
        """Boolean ``(N,)`` mask of allowed actions (MaskablePPO protocol)."""
        return ~self.state.selected

    # -- gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Draw a new scenario from ``np_random`` and clear the selection."""
        super().reset(seed=seed)
        batch = make_problems(self.config, [self.np_random])
        self._batch, self._problem = batch, None
        self.core.start(_ONE, batch.G)
        self._state = self.core.view(0)
        self._features = batched_features(batch.times, batch.constants.sensor)
        self._steps, self._done = 0, False
        return self._obs(), self._info()

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Select candidate ``action``; reward is its gain in ``objective`` (log det: nats)."""
        state = self.state
        if self._done:
            raise RuntimeError("episode is over: call reset()")
        k = check_discrete(action, self.n)
        reason = f"masked: candidate {k} is already selected" if state.selected[k] else None
        rule = self.invalid_rule
        if rule.check(f"action {k}", reason) and rule.terminates:
            self._done = True
            return self._obs(), rule.penalty, True, False, self._info(reason)
        reward = rule.penalty if reason else float(self.core.add(_ONE, np.array([k]))[0])
        self._steps += 1
        self._done = self.budget_left == 0
        return self._obs(), reward, self._done, False, self._info(reason)

    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        """A frame of the scene (``render_mode`` ``"rgb_array"``: ``(H, W, 3)`` uint8)."""
        state, problem = self.state, self.problem
        title = "FIMSelection-v1"
        from selenv.families.fim.rendering import draw_fim_selection  # matplotlib: first frame

        return self._renderer.render(
            lambda fig: draw_fim_selection(fig, problem, state.selected, state.information, title)
        )

    def close(self) -> None:
        """Close the render window, if any."""
        self._renderer.close()

    def _obs(self) -> dict[str, np.ndarray]:
        core = self.core
        frac = np.array([self.budget_left / self.budget])
        obs = fim_observations(core.gains, core.Z, core.selected, self._features, frac)
        return {key: val[0] for key, val in obs.items()}

    def _info(self, reason: str | None = None) -> dict[str, Any]:
        s = self.state
        return {
            "objective": s.objective,
            "action_mask": ~s.selected,
            "n_selected": int(self.core.count[0]),
            **self.invalid_rule.info(reason),
        }


#: the sub-env index of the single env in its batched core
_ONE = np.zeros(1, dtype=np.intp)
