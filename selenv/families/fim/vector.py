"""``gymnasium.make_vec("selenv/FIMSelection-v1", num_envs=B)``: ``B`` episodes in batch arrays.

:class:`FIMSelectionVectorEnv` keeps the ``B`` sub-envs' gain states in one
:class:`~selenv.families.fim.batched.FIMBatchState` (``G``, ``Z`` ``(B, N, m, d)``, ``L^-1``
``(B, d, d)``, gains and selections ``(B, N)``) and steps them with the same batched functions
the single env :class:`~selenv.families.fim.env.FIMSelectionEnv` calls (its ``B = 1`` case).
Resets draw each sub-env's problem from its own generator exactly as the single env does
(:func:`~selenv.families.fim.scenario.make_problems`: the seed-independent part cached per
config; times and whitened pools ``G`` by closed-form geometry and Jacobians over all the
sub-envs reset together, the rest of each problem's geometry only when asked for, e.g. by
:meth:`FIMSelectionVectorEnv.problem`; the initial gains batched). Seeding, ``NEXT_STEP``
autoreset, ``reset_mask`` and batched infos are those of
:class:`~selenv.envs.vector.BatchedVectorEnv`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from selenv.envs.actions import InvalidActionRule
from selenv.envs.conventions import check_render_mode
from selenv.envs.rendering import Renderer
from selenv.envs.vector import BatchedVectorEnv, check_discrete_actions, check_num_envs
from selenv.families.fim.batched import FIMBatchState, SubEnvGainState, batched_features
from selenv.families.fim.env import (
    FIMSelectionEnv,
    fim_observation_space,
    fim_observations,
    fim_settings,
)
from selenv.families.fim.scenario import (
    FIMProblem,
    FIMProblemBatch,
    make_problems,
    problem_constants,
)
from selenv.scenarios.validation import ArgumentTypeError, describe

__all__ = ["FIMSelectionVectorEnv"]


class FIMSelectionVectorEnv(BatchedVectorEnv):
    """``B`` ``FIMSelection-v1`` episodes stepped together (Gymnasium ``VectorEnv``).

    Sub-env ``b`` after ``reset(seed=s)`` replays ``gymnasium.make("selenv/FIMSelection-v1",
    **kwargs).reset(seed=s + b)`` driven by the same actions (values within rtol 1e-9,
    decisions identical; :func:`~selenv.envs.vector_check.check_vector_equivalence`).

    Args:
        num_envs: ``B``, an int in ``[1, 65536]``.
        render_mode: ``None`` or ``"rgb_array"`` (``render()``: one frame per sub-env).

    The other keywords (``preset``, ``n_candidates``, ``budget``, ``sensors``, ``n_agents``,
    ``camera_sigma_px``, ``toa_sigma_m``, ``doppler_sigma_mps``, ``randomize``,
    ``invalid_action``, ``invalid_action_penalty``, ``objective``) are exactly the single
    env's, validated by the same code (:func:`~selenv.families.fim.env.fim_settings`).

    Spaces: ``single_observation_space`` is the single env's ``Dict`` (``gain (N,)``,
    ``whitened (N, m d)``, ``features (N, 4)``, ``selected (N,)``, ``budget_left (1,)``,
    ``action_mask (N,)``); observations carry a leading ``(B,)`` axis. Actions: ``(B,)``
    integers (``MultiDiscrete``), one candidate index per sub-env; a wrong shape or dtype is a
    ``ValueError`` / ``TypeError``, an index outside ``[0, N)`` a ``ValueError`` naming the
    sub-env (for every sub-env, also one that autoresets this step). :meth:`action_masks`
    returns ``(B, N)`` bool.

    Steps: the log-det objective (the default) is batched throughout: closed-form inverse
    factors of the picks' rank-``m`` updates, then a few stacked products and elementwise
    passes for all sub-envs that pick (block update, eq. 9; the batch state is a
    :class:`~selenv.families.fim.batched.FIMBatchState`). Other objectives (``"trace"``
    eq. 6, ``"max_eig"`` eq. 7, ``"det"``, user-registered): the state update and ``f`` are
    batched; the candidate gains fall back to the core function that ``CriterionGainState``
    calls, :func:`~selenv.core.objectives.criterion_gains`, per sub-env that picked.

    Invalid actions (a masked candidate), per sub-env as the single env: ``"noop"`` spends the
    slot (reward ``invalid_action_penalty``, ``info["invalid_action"]``, ``info["invalid_code"]``
    where it happened); ``"terminate"`` ends that sub-env's episode;
    ``"raise"``: ``ValueError`` naming the sub-env, before any sub-env is stepped.

    Infos: the single env's keys batched (``objective (B,)``, ``action_mask (B, N)``,
    ``n_selected``, ``invalid_action``, ``invalid_code``) with Gymnasium's ``_key`` masks.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        **BatchedVectorEnv.metadata,
        "render_modes": ["rgb_array"],
        "render_fps": 4,
    }
    sub_env_metadata = FIMSelectionEnv.metadata
    sub_env_attributes = {"budget_left": "budget_left"}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
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
        num_envs = check_num_envs(num_envs)
        render_mode = check_render_mode(render_mode, self.metadata)
        settings = fim_settings(
            preset=preset, n_candidates=n_candidates, budget=budget, sensors=sensors,
            n_agents=n_agents, camera_sigma_px=camera_sigma_px, toa_sigma_m=toa_sigma_m,
            doppler_sigma_mps=doppler_sigma_mps, randomize=randomize,
            invalid_action=invalid_action, invalid_action_penalty=invalid_action_penalty,
            objective=objective,
        )  # fmt: skip
        self.settings = settings
        self.config, self.objective = settings.config, settings.objective
        self.invalid_rule, self.budget = settings.invalid_rule, settings.budget
        self.n, self.m, self.d = settings.n, settings.m, settings.d
        self.interest = settings.interest
        self._setup(
            num_envs, fim_observation_space(self.n, self.m, self.d), spaces.Discrete(self.n),
            render_mode,
        )  # fmt: skip
        B = self.num_envs
        self._constants = problem_constants(self.config)
        #: the batched gain states of the ``B`` sub-envs
        self.core = FIMBatchState(B, self._constants.Q0, (self.n, self.m, self.d),
                                  self.objective, self.interest)  # fmt: skip
        self._steps = np.zeros(B, dtype=np.intp)
        self._features = np.zeros((B, self.n, 4), np.float32)
        self._sources: list[tuple[FIMProblemBatch, int] | None] = [None] * B
        self._renderer: Renderer | None = None

    # -- per sub-env views -------------------------------------------------------------------
    def problem(self, i: int) -> FIMProblem:
        """Sub-env ``i``'s current problem (as the single env's ``env.problem``)."""
        src = self._sources[self._sub_env(i)]
        if src is None:
            raise RuntimeError("call reset() before using the env")
        return src[0].problem(src[1])

    def state(self, i: int) -> SubEnvGainState:
        """Sub-env ``i``'s live gain state (as the single env's ``env.state``)."""
        i = self._sub_env(i)
        if self._sources[i] is None:
            raise RuntimeError("call reset() before using the env")
        return self.core.view(i)

    @property
    def budget_left(self) -> np.ndarray:
        """``(B,)`` picks still to make per sub-env (an invalid no-op pick spends one too)."""
        out: np.ndarray = self.budget - self._steps
        return out

    def action_masks(self) -> np.ndarray:
        """``(B, N)`` bool masks of the allowed actions (MaskablePPO protocol)."""
        return np.logical_not(self.core.selected)

    def render_env(self, i: int) -> np.ndarray | None:
        """A frame of sub-env ``i`` (``(H, W, 3)`` uint8), drawn as the single env draws."""
        from selenv.families.fim.rendering import draw_fim_selection  # matplotlib: first frame

        problem, state = self.problem(i), self.core.view(i)
        if self._renderer is None:
            self._renderer = Renderer("rgb_array", self.metadata["render_fps"])
        return self._renderer.render(
            lambda fig: draw_fim_selection(
                fig, problem, state.selected, state.information, "FIMSelection-v1"
            )
        )

    def close(self, **kwargs: Any) -> None:
        """Close the renderer, if any."""
        renderer = getattr(self, "_renderer", None)  # None if __init__ failed
        if renderer is not None:
            renderer.close()
        super().close(**kwargs)

    # -- BatchedVectorEnv hooks --------------------------------------------------------------
    def _reset_envs(self, idx: np.ndarray, options: dict[str, Any]) -> dict[str, Any]:
        rngs = [self.np_randoms[i] for i in idx]
        batch = make_problems(self.config, rngs)  # type: ignore[arg-type, unused-ignore]
        self.core.start(idx, batch.G)
        self._features[idx] = batched_features(batch.times, self._constants.sensor)
        self._steps[idx] = 0
        for j, i in enumerate(idx.tolist()):
            self._sources[i] = (batch, j)
        return self._infos(idx, None)

    def _step_envs(
        self, actions: np.ndarray, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        core, rule = self.core, self.invalid_rule
        invalid = core.selected[idx, actions]
        if invalid.any() and rule.mode == "raise":
            j = int(np.flatnonzero(invalid)[0])
            i, k = int(idx[j]), int(actions[j])
            rule.check(f"sub-env {i}: action {k}", f"masked: candidate {k} is already selected")
        rewards = np.full(idx.size, rule.penalty)
        valid = ~invalid
        if valid.all():
            rewards = core.add(idx, actions)
        elif valid.any():
            rewards[valid] = core.add(idx[valid], actions[valid])
        ended = invalid & rule.terminates  # "terminate": the slot is not spent
        self._steps[idx[~ended]] += 1
        terminated = ended | (self._steps[idx] == self.budget)
        return (
            rewards,
            terminated,
            np.zeros(idx.size, dtype=np.bool_),
            self._infos(idx, invalid),
        )

    def _observe(self) -> dict[str, np.ndarray]:
        core = self.core
        frac = (self.budget - self._steps) / self.budget
        return fim_observations(core.gains, core.Z, core.selected, self._features, frac)

    # -- helpers -------------------------------------------------------------------------------
    def _infos(self, idx: np.ndarray, invalid: np.ndarray | None) -> dict[str, Any]:
        """The single env's info keys for sub-envs ``idx`` batched (``invalid``: ``(k,)``)."""
        core = self.core
        bad = np.zeros(idx.size, np.bool_) if invalid is None else invalid
        return {
            "objective": core.objective[idx],
            "action_mask": np.logical_not(core.selected[idx]),
            "n_selected": core.count[idx],
            **InvalidActionRule.masked_info(bad),
        }

    def _check_actions(self, actions: Any) -> np.ndarray:
        """``(B,)`` candidate indices: shape, dtype and range checked for every sub-env."""
        arr = check_discrete_actions(actions, self.num_envs, self.n, "candidate index")
        return arr.astype(np.intp, copy=False)

    def _sub_env(self, i: Any) -> int:
        if isinstance(i, bool) or not isinstance(i, int | np.integer):
            raise ArgumentTypeError(f"i must be an int sub-env index, got {describe(i)}")
        if not 0 <= i < self.num_envs:
            raise ValueError(f"i must lie in [0, {self.num_envs}), got {i}")
        return int(i)
