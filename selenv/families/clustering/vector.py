"""Native vector env of ``selenv/ReceiverClustering-v1``: ``B`` clusterings stepped together.

``gymnasium.make_vec("selenv/ReceiverClustering-v1", num_envs=B, **kwargs)`` returns
:class:`ReceiverClusteringVectorEnv`. Each sub-env keeps its own
:class:`~selenv.families.clustering.filters.ClusterFilterBank` (``venv.banks[b]``, the oracle
view a heuristic reads, as ``env.unwrapped.bank`` of the single env), but the work of a step
runs over all sub-envs at once, through the same functions the single env calls with one bank:

* the filter step: every cluster of every sub-env, stacked by cluster size, in one
  :func:`~selenv.families.clustering.batched.filter_step` per size
  (:func:`~selenv.families.clustering.filters.step_banks`);
* the cost eq. (10) of every sub-env from the new posteriors' statistics in one
  :func:`~selenv.families.clustering.batched.clustering_costs`;
* re-clustering: the Algorithm 1 forward passes of the new clusters of every changed sub-env,
  by size, in one :func:`~selenv.families.clustering.batched.window_pass` each
  (:func:`~selenv.families.clustering.filters.recluster_banks`);
* action parsing (canonical labels, feasibility) and the masks of every sub-env
  (:func:`~selenv.families.clustering.batched.edit_masks`,
  :func:`~selenv.families.clustering.batched.assignment_masks`);
* observations written into preallocated ``(B, ...)`` arrays;
* at reset, the regime chains of all reset sub-envs
  (:func:`~selenv.families.clustering.scenario.make_clustering_problems`; each sub-env's
  generator draws exactly what the single env's draws) and the seed-independent tables
  (per-size models, correlations, priors) from module-level caches.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from selenv.envs.actions import invalid_code
from selenv.envs.conventions import check_render_mode
from selenv.envs.rendering import Renderer
from selenv.envs.vector import BatchedVectorEnv, check_num_envs
from selenv.families.clustering.batched import assignment_masks, edit_masks, label_counts
from selenv.families.clustering.env import (
    ClusteringEnvSettings,
    ReceiverClusteringEnv,
    apply_edit,
    check_int_labels,
    clustering_env_settings,
    describe_action,
    describe_edit,
    initial_clustering,
    render_clustering,
)
from selenv.families.clustering.filters import (
    ClusterFilterBank,
    bank_costs,
    recluster_banks,
    step_banks,
)
from selenv.families.clustering.labels import canonicalize, canonicalize_rows
from selenv.families.clustering.scenario import make_clustering_problems
from selenv.scenarios.validation import ArgumentTypeError, describe

__all__ = ["ReceiverClusteringVectorEnv"]


class ReceiverClusteringVectorEnv(BatchedVectorEnv):
    """``num_envs`` copies of :class:`~selenv.families.clustering.env.ReceiverClusteringEnv`.

    Args:
        num_envs: ``B``, an int in ``[1, 65536]``.
        **keywords: exactly the single env's (validated by the same code,
            :func:`~selenv.families.clustering.env.clustering_env_settings`), shared by every
            sub-env.
        render_mode: ``None`` or ``"rgb_array"`` (:meth:`render_env` draws one sub-env).

    Spaces: the single env's, batched: observations ``assignment (B, n)``, ``cluster_size
    (B, n)``, ``sigma (B, n, 2)``, ``position_var (B, n)``, ``cost (B, 4)``, ``time (B, 1)``
    and ``action_mask (B, mask)`` (int8) when the single env observes it; actions ``(B, n)``
    labels (assignment mode) or ``(B,)`` edit indices (edit mode). :meth:`action_masks` is
    ``(B, n * n)`` or ``(B, 1 + n^2 + n(n-1)/2)`` bool. Infos hold the single env's keys as
    ``(B, ...)`` arrays with Gymnasium's ``"_key"`` masks (``invalid_code`` ``(B,)`` int64).

    Invalid actions, per sub-env, by ``invalid_action``: ``"noop"`` keeps that sub-env's
    clustering and steps it; ``"terminate"`` ends its episode (reset at the next step);
    ``"raise"`` raises ``ValueError`` naming the sub-env before any sub-env changes. Actions
    outside the space (wrong shape, non-integers, out of range) are a ``TypeError`` /
    ``ValueError`` naming ``actions`` and the sub-env.

    ``reset(options={"clustering": labels})``: ``labels`` ``(n,)`` starts every reset sub-env
    from that clustering; ``(B, n)`` gives row ``b`` to sub-env ``b`` (rows of sub-envs not
    reset, with ``reset_mask``, are ignored). Each is validated as the single env validates it.

    ``cost_evaluations`` counts the Algorithm 1 evaluations run on ``banks[b]`` (by an agent
    searching on the vector env's banks), as the single env counts those on its bank.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        **BatchedVectorEnv.metadata,
        "render_modes": ["rgb_array"],
        "render_fps": 10,
    }
    sub_env_metadata = ReceiverClusteringEnv.metadata

    def __init__(
        self,
        num_envs: int = 1,
        *,
        n_agents: int = 30,
        n_max_states: int | None = 14,
        sigma: Any = None,
        noise_correlation: float = 0.9,
        dt: float = 0.1,
        tau: int = 20,
        weights: tuple[float, float, float] = (1.0, 1.0, 1.0),
        horizon: int = 500,
        prior_std: tuple[float, float, float] = (1.0, 1.0, 1.0),
        action_mode: str = "assignment",
        initial: str = "random",
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        preset: str = "multipath",
        p_enter: float | None = None,
        p_leave: float | None = None,
        degraded_factor: float | None = None,
        obs_mask: bool = True,
    ) -> None:
        B = check_num_envs(num_envs)
        render_mode = check_render_mode(render_mode, self.metadata)
        st = clustering_env_settings(
            n_agents=n_agents,
            n_max_states=n_max_states,
            sigma=sigma,
            noise_correlation=noise_correlation,
            dt=dt,
            tau=tau,
            weights=weights,
            horizon=horizon,
            prior_std=prior_std,
            action_mode=action_mode,
            initial=initial,
            invalid_action=invalid_action,
            invalid_action_penalty=invalid_action_penalty,
            preset=preset,
            p_enter=p_enter,
            p_leave=p_leave,
            degraded_factor=degraded_factor,
            obs_mask=obs_mask,
        )
        self.settings: ClusteringEnvSettings = st
        self.config = st.config
        self.n, self.horizon, self.max_size = st.n, st.horizon, st.max_size
        self.action_mode, self.invalid_rule = st.action_mode, st.invalid_rule
        self._setup(B, st.observation_space, st.action_space, render_mode)
        n = st.n
        #: the filter bank of each sub-env (``None`` before the first reset)
        self.banks: list[ClusterFilterBank | None] = [None] * B
        self._buf: dict[str, np.ndarray] = {
            "assignment": np.zeros((B, n), np.int64),
            "cluster_size": np.ones((B, n), np.int64),
            "sigma": np.zeros((B, n, 2), np.float32),
            "position_var": np.zeros((B, n), np.float32),
            "cost": np.zeros((B, 4), np.float32),
            "time": np.zeros((B, 1), np.float32),
        }
        if st.observes_mask:
            self._buf["action_mask"] = np.zeros((B, st.mask_size), np.int8)
        self._masks = np.zeros((B, st.mask_size), np.bool_)
        self._renderer = Renderer(render_mode, self.metadata["render_fps"])

    # -- vector API -----------------------------------------------------------------------------
    def action_masks(self) -> np.ndarray:
        """``(B, mask)`` bool: each sub-env's ``action_masks()`` (edit or per-receiver masks)."""
        return self._masks.copy()

    def render_env(self, i: int) -> np.ndarray | None:
        """A frame of sub-env ``i`` (``render_mode="rgb_array"``: ``(H, W, 3)`` uint8)."""
        return render_clustering(
            self._renderer, self._bank(i), self.max_size, "ReceiverClustering-v1"
        )

    def close(self, **kwargs: Any) -> None:
        """Close the renderer."""
        renderer = getattr(self, "_renderer", None)  # absent if __init__ failed
        if renderer is not None:
            renderer.close()
        super().close(**kwargs)

    # -- BatchedVectorEnv hooks -----------------------------------------------------------------
    def _bank(self, i: int) -> ClusterFilterBank:
        bank = self.banks[int(i)]
        if bank is None:
            raise RuntimeError("call reset() before using the environment")
        return bank

    def _reset_envs(self, idx: np.ndarray, options: dict[str, Any]) -> dict[str, Any]:
        unknown = set(options) - {"clustering"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: ['clustering']")
        starts = self._start_clusterings(idx, options)
        rngs = [self.np_randoms[i] for i in idx.tolist()]
        problems = make_clustering_problems(self.config, rngs, self.horizon)
        banks = []
        for i, rng, problem, start in zip(idx.tolist(), rngs, problems, starts, strict=True):
            if start is None:  # random or singletons, drawn as the single env draws it
                labels = initial_clustering(problem, self.settings.initial, {}, rng)
            else:
                labels = problem.check_clustering(*start)
            bank = ClusterFilterBank(problem, labels)
            self.banks[i] = bank
            banks.append(bank)
        costs = bank_costs(banks)
        position_var = np.stack([bank.receiver_position_variance() for bank in banks])
        self._write(idx, banks, costs, position_var)
        return self._infos(idx, banks, costs, np.zeros(idx.size, np.bool_))

    def _start_clusterings(
        self, idx: np.ndarray, options: dict[str, Any]
    ) -> list[tuple[Any, str] | None]:
        """``options["clustering"]`` per reset sub-env: ``(labels, name)`` or ``None``."""
        if "clustering" not in options:
            return [None] * idx.size
        given = options["clustering"]
        try:
            arr = np.asarray(given)
        except ValueError as exc:  # ragged
            raise ValueError(
                f"options['clustering'] must be labels of shape ({self.n},) or "
                f"({self.num_envs}, {self.n}), got {describe(given)}"
            ) from exc
        if arr.ndim == 2:
            if arr.shape[0] != self.num_envs:
                raise ValueError(
                    f"options['clustering'] must have shape ({self.n},) (every sub-env) or "
                    f"({self.num_envs}, {self.n}) (one row per sub-env), got {arr.shape}"
                )
            return [(arr[i], f"options['clustering'][{i}]") for i in idx.tolist()]
        return [(arr, "options['clustering']")] * idx.size

    def _step_envs(
        self, actions: np.ndarray, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        banks = [self._bank(i) for i in idx.tolist()]
        current = self._buf["assignment"][idx]
        if self.action_mode == "assignment":
            new, reasons = self._parse_assignments(actions, idx, banks)
        else:
            new, reasons = self._parse_edits(actions, idx, current)
        rule = self.invalid_rule
        bad = [j for j, reason in enumerate(reasons) if reason is not None]
        if bad and rule.mode == "raise":  # raises here, before any sub-env changes
            j = bad[0]
            what = f"sub-env {int(idx[j])}: action {describe_action(self.action_mode, actions[j])}"
            rule.check(what, reasons[j])
        invalid = np.zeros(idx.size, np.bool_)
        invalid[bad] = True
        ends = invalid & rule.terminates
        changed = ~invalid & np.any(new != current, axis=1)
        moved = np.flatnonzero(changed)
        if moved.size:
            recluster_banks([banks[j] for j in moved.tolist()], list(new[moved]))
        run = np.flatnonzero(~ends)
        costs = np.empty((idx.size, 4))
        rewards = np.full(idx.size, rule.penalty)
        terminated = ends.copy()
        if run.size:
            stepped = [banks[j] for j in run.tolist()]
            result = step_banks(stepped)
            costs[run] = result.costs
            rewards[run] = -result.costs[:, 0] + np.where(invalid[run], rule.penalty, 0.0)
            ks = np.array([bank.k for bank in stepped])
            terminated[run] = ks >= self.horizon
            self._write(idx[run], stepped, result.costs, result.position_var)
        if run.size < idx.size:
            stay = np.flatnonzero(ends)
            costs[stay] = bank_costs([banks[j] for j in stay.tolist()])
        infos = self._infos(idx, banks, costs, changed)
        infos["invalid_action"] = invalid
        infos["invalid_code"] = np.array([invalid_code(r) for r in reasons], dtype=np.int64)
        return rewards, terminated, np.zeros(idx.size, np.bool_), infos

    def _observe(self) -> dict[str, np.ndarray]:
        return {key: value.copy() for key, value in self._buf.items()}

    # -- helpers --------------------------------------------------------------------------------
    def _parse_assignments(
        self, actions: np.ndarray, idx: np.ndarray, banks: list[ClusterFilterBank]
    ) -> tuple[np.ndarray, list[str | None]]:
        """Canonical labels ``(k, n)`` of each sub-env's action and why each is invalid."""
        n, k = self.n, idx.size
        if actions.dtype.kind not in "iu":
            check_int_labels(actions[0], n, f"actions[{int(idx[0])}]")  # raises, naming it
        if actions.shape != (k, n):
            raise ValueError(
                f"actions must have shape ({self.num_envs}, {n}) (labels per sub-env), "
                f"got {(self.num_envs, *actions.shape[1:])}"
            )
        arr = actions.astype(np.int64, copy=False)
        if k and (arr.min() < 0 or arr.max() >= n):
            j = int(np.flatnonzero((arr < 0).any(1) | (arr >= n).any(1))[0])
            banks[j].problem.check_labels(arr[j], f"actions[{int(idx[j])}]")  # raises
        canon = canonicalize_rows(arr)
        too_big = label_counts(canon).max(1) > self.max_size
        reasons: list[str | None] = [None] * k
        for j in np.flatnonzero(too_big).tolist():
            reasons[j] = f"infeasible: {banks[j].problem.violation(arr[j])}"
        return canon, reasons

    def _parse_edits(
        self, actions: np.ndarray, idx: np.ndarray, current: np.ndarray
    ) -> tuple[np.ndarray, list[str | None]]:
        """Labels ``(k, n)`` after each sub-env's edit and why each is invalid."""
        k, n_edit = idx.size, self.settings.mask_size
        if actions.dtype == np.bool_ or actions.dtype.kind not in "iu":
            raise ArgumentTypeError(
                f"actions must be integers in [0, {n_edit}) (one edit per sub-env), got "
                f"dtype {actions.dtype}"
            )
        if actions.shape != (k,):
            raise ValueError(
                f"actions must have shape ({self.num_envs},) (one edit per sub-env), "
                f"got {(self.num_envs, *actions.shape[1:])}"
            )
        arr = actions.astype(np.int64, copy=False)
        out_of_range = (arr < 0) | (arr >= n_edit)
        if out_of_range.any():
            j = int(np.flatnonzero(out_of_range)[0])
            raise ValueError(
                f"actions[{int(idx[j])}] {int(arr[j])} is out of range: expected an integer in "
                f"[0, {n_edit})"
            )
        allowed = self._masks[idx, arr]
        new = current.copy()
        reasons: list[str | None] = [None] * k
        for j in range(k):
            a = int(arr[j])
            if not allowed[j]:
                reasons[j] = f"masked: {describe_edit(self.n, a)} is not allowed now"
            elif a:
                new[j] = canonicalize(apply_edit(current[j], a))
        return new, reasons

    def _write(
        self,
        idx: np.ndarray,
        banks: list[ClusterFilterBank],
        costs: np.ndarray,
        position_var: np.ndarray,
    ) -> None:
        """Observation rows and masks of sub-envs ``idx`` from their banks (after a change)."""
        buf = self._buf
        labels = np.stack([bank.labels for bank in banks])
        buf["assignment"][idx] = labels
        buf["cluster_size"][idx] = np.take_along_axis(label_counts(labels), labels, axis=1)
        buf["sigma"][idx] = np.stack([bank.current_sigma() for bank in banks])
        buf["position_var"][idx] = position_var
        buf["cost"][idx] = costs
        ks = np.array([bank.k for bank in banks], dtype=np.float64)
        buf["time"][idx, 0] = np.minimum(ks / self.horizon, 1.0)
        if self.action_mode == "edit":
            masks = edit_masks(labels, self.max_size)
        else:
            masks = assignment_masks(labels, self.max_size)
        self._masks[idx] = masks
        if "action_mask" in buf:
            buf["action_mask"][idx] = masks

    def _infos(
        self,
        idx: np.ndarray,
        banks: list[ClusterFilterBank],
        costs: np.ndarray,
        changed: np.ndarray,
    ) -> dict[str, Any]:
        """The single env's info keys for sub-envs ``idx``, as ``(len(idx), ...)`` arrays."""
        return {
            "objective": costs[:, 0].copy(),
            "J_G": costs[:, 1].copy(),
            "J_C": costs[:, 2].copy(),
            "J_L": costs[:, 3].copy(),
            "n_clusters": self._buf["assignment"][idx].max(1) + 1,
            "changed": changed,
            "k": np.array([bank.k for bank in banks], dtype=np.int64),
            "action_mask": self._masks[idx],
            "cost_evaluations": np.array(
                [bank.n_cost_evaluations for bank in banks], dtype=np.int64
            ),
            "invalid_action": np.zeros(idx.size, np.bool_),
            "invalid_code": np.zeros(idx.size, np.int64),
        }
