"""``selenv/ReceiverClustering-v1``: dynamic clustering of GNSS receivers with a shared bias."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from selenv.envs.actions import INVALID_CODES, InvalidActionRule, check_discrete
from selenv.envs.conventions import EpisodeLengthSpec, check_render_mode
from selenv.envs.rendering import Renderer
from selenv.families.clustering.batched import assignment_masks, edit_masks, swap_pairs
from selenv.families.clustering.filters import ClusterFilterBank
from selenv.families.clustering.labels import canonicalize, random_feasible_clustering
from selenv.families.clustering.scenario import (
    ClusteringConfig,
    ClusteringProblem,
    MultipathRegimes,
    make_clustering_problem,
)
from selenv.scenarios.validation import (
    ArgumentTypeError,
    check_bool,
    check_choice,
    check_integer,
    describe,
)

__all__ = [
    "ACTION_MODES",
    "INITIALS",
    "PRESETS",
    "ClusteringEnvSettings",
    "ReceiverClusteringEnv",
    "apply_edit",
    "clustering_config",
    "clustering_env_settings",
    "clustering_observation",
    "clustering_observation_space",
    "describe_action",
    "describe_edit",
    "edit_action_count",
    "edit_cost_changes",
    "edit_mask",
    "initial_clustering",
    "render_clustering",
]

ACTION_MODES = ("assignment", "edit")
#: longest episode (the regime path of every step is drawn at reset)
MAX_STEPS = 100_000


INITIALS = ("random", "singletons")
#: noise presets: ``"multipath"`` (default) time-varying regimes, ``"paper"`` fixed ``sigma``
PRESETS = ("multipath", "paper")


def _regimes(
    preset: str, p_enter: float | None, p_leave: float | None, degraded_factor: float | None
) -> MultipathRegimes | None:
    """The noise model of ``preset`` with the given overrides (``ValueError`` naming them)."""
    check_choice(preset, "preset", PRESETS)
    given = {"p_enter": p_enter, "p_leave": p_leave, "degraded_factor": degraded_factor}
    overrides = {name: v for name, v in given.items() if v is not None}
    if preset == "paper":
        if overrides:
            raise ValueError(
                f"{sorted(overrides)} set the multipath noise model; preset='paper' keeps "
                "sigma fixed (use preset='multipath')"
            )
        return None
    return MultipathRegimes(**overrides)


def clustering_config(
    *,
    n_agents: int,
    n_max_states: int | None,
    sigma: Any,
    noise_correlation: float,
    dt: float,
    tau: int,
    weights: tuple[float, float, float],
    prior_std: tuple[float, float, float],
    horizon: int,
    initial: str,
    preset: str = "paper",
    p_enter: float | None = None,
    p_leave: float | None = None,
    degraded_factor: float | None = None,
) -> ClusteringConfig:
    """Validated scenario config from the env keywords (shared by both clustering envs).

    ``preset="multipath"``: :class:`~selenv.families.clustering.scenario.MultipathRegimes` with its
    defaults, overridden by ``p_enter``, ``p_leave``, ``degraded_factor`` when given;
    ``preset="paper"``: fixed ``sigma`` (those three must then be ``None``).

    Raises:
        TypeError, ValueError: any bad keyword (via :class:`ClusteringConfig` or
            :class:`~selenv.families.clustering.scenario.MultipathRegimes`, naming it and its
            range),
            ``horizon`` not an int in ``[1, MAX_STEPS]`` (100 000), an unknown ``initial`` or
            ``preset``.
    """
    check_integer(horizon, "horizon", 1, MAX_STEPS)
    check_choice(initial, "initial", INITIALS)
    regimes = _regimes(preset, p_enter, p_leave, degraded_factor)
    if not isinstance(weights, tuple | list | np.ndarray):
        raise ArgumentTypeError(f"weights must be 3 numbers, got {describe(weights)}")
    if not isinstance(prior_std, tuple | list | np.ndarray):
        raise ArgumentTypeError(f"prior_std must be 3 numbers, got {describe(prior_std)}")
    return ClusteringConfig(
        n_agents=n_agents,
        n_max_states=n_max_states,
        sigma=sigma,
        noise_correlation=noise_correlation,
        dt=dt,
        tau=tau,
        weights=tuple(weights),  # type: ignore[arg-type]
        prior_std=tuple(prior_std),  # type: ignore[arg-type]
        regimes=regimes,
    )


def initial_clustering(
    problem: ClusteringProblem,
    initial: str,
    options: dict[str, Any],
    rng: np.random.Generator,
) -> np.ndarray:
    """Start clustering: ``options["clustering"]`` (validated), singletons, or random feasible."""
    if "clustering" in options:
        return problem.check_clustering(options["clustering"], "options['clustering']")
    if initial == "singletons":
        return np.arange(problem.n)
    return random_feasible_clustering(problem.n, problem.max_cluster_size, rng)


def check_int_labels(action: Any, n: int, name: str = "action") -> np.ndarray:
    """An assignment action as an integer array (any int dtype); floats are never rounded.

    Raises:
        TypeError: not an array of integers (floats, even integral, bools, strings, ...); the
            shape and range are checked by :meth:`ClusteringProblem.check_labels`.
    """
    try:
        arr = np.asarray(action)
    except ValueError as exc:  # ragged
        raise ValueError(
            f"{name} must be an int array of shape ({n},), got {describe(action)}"
        ) from exc
    if arr.dtype.kind not in "iu":
        raise ArgumentTypeError(
            f"{name} must hold integer labels (an int array of shape ({n},) with values in "
            f"[0, {n})), got {describe(action)}"
        )
    return arr


# -- the "edit" action encoding -----------------------------------------------------------------
def edit_action_count(n: int) -> int:
    """``1 + n^2 + n(n-1)/2``: no-op, moves ``(i, j)`` and swaps ``i < j``."""
    return 1 + n * n + n * (n - 1) // 2


def _swap_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    return swap_pairs(n)


def edit_mask(labels: np.ndarray, max_size: int) -> np.ndarray:
    """Allowed edits of a canonical clustering, ``(1 + n^2 + n(n-1)/2,)`` bool.

    * ``0``: keep the clustering (always allowed, so the mask is never all zeros);
    * ``1 + i n + j``, ``j != i``: receiver ``i`` joins receiver ``j``'s cluster (allowed if they
      differ and that cluster has room); ``j == i``: ``i`` leaves to a new singleton cluster
      (allowed if its cluster has other members);
    * ``1 + n^2 + p``: swap the clusters of the ``p``-th pair ``i < j`` (allowed if they differ
      and are not both singletons).

    Every allowed edit yields a feasible clustering with a different partition.
    """
    return edit_masks(np.asarray(labels, dtype=np.int64)[None], max_size)[0]


def apply_edit(labels: np.ndarray, action: int) -> np.ndarray:
    """The clustering after edit ``action`` (see :func:`edit_mask`); does not check the mask."""
    n = labels.size
    out = labels.copy()
    if action == 0:
        return out
    a = action - 1
    if a < n * n:
        i, j = divmod(a, n)
        out[i] = labels.max() + 1 if i == j else labels[j]
        return out
    iu, ju = _swap_pairs(n)
    i, j = int(iu[a - n * n]), int(ju[a - n * n])
    out[i], out[j] = labels[j], labels[i]
    return out


def describe_edit(n: int, action: int) -> str:
    """Human-readable meaning of edit ``action`` of ``n`` receivers (see :func:`edit_mask`)."""
    if action == 0:
        return "no-op"
    a = action - 1
    if a < n * n:
        i, j = divmod(a, n)
        return f"receiver {i} -> new singleton" if i == j else f"receiver {i} -> cluster of {j}"
    iu, ju = _swap_pairs(n)
    return f"swap receivers {int(iu[a - n * n])} and {int(ju[a - n * n])}"


def describe_action(action_mode: str, action: Any) -> str:
    """An action as an invalid action's message names it (labels, or the edit index)."""
    if action_mode == "assignment":
        return np.array2string(np.asarray(action), separator=",", max_line_width=10**6)
    return str(int(np.asarray(action).reshape(())))


def _edit_changes(
    labels: np.ndarray, keys: list[tuple[int, ...]], actions: np.ndarray
) -> tuple[np.ndarray, list[tuple[tuple[int, ...], ...]]]:
    """Clusters each edit removes (indices into ``keys``, -1: none) and adds (member tuples)."""
    n = labels.size
    iu, ju = _swap_pairs(n)
    removed = np.full((actions.size, 2), -1, dtype=np.int64)
    added: list[tuple[tuple[int, ...], ...]] = []
    for e, action in enumerate(actions.tolist()):
        a = action - 1
        if a < 0:
            added.append(())
            continue
        if a < n * n:
            i, j = divmod(a, n)
            A = int(labels[i])
            rest = tuple(x for x in keys[A] if x != i)
            if i == j:  # i leaves to a new singleton
                removed[e, 0] = A
                added.append((rest, (i,)) if rest else ((i,),))
                continue
            B = int(labels[j])
            removed[e] = (A, B)
            joined = tuple(sorted((*keys[B], i)))
            added.append((rest, joined) if rest else (joined,))
            continue
        i, j = int(iu[a - n * n]), int(ju[a - n * n])
        A, B = int(labels[i]), int(labels[j])
        removed[e] = (A, B)
        added.append(
            (
                tuple(sorted((*(x for x in keys[A] if x != i), j))),
                tuple(sorted((*(x for x in keys[B] if x != j), i))),
            )
        )
    return removed, added


def edit_cost_changes(bank: ClusterFilterBank, actions: Any) -> np.ndarray:
    """``dJ_a = J(apply_edit(labels, a)) - J(labels)`` of each edit ``a`` of ``actions``, now.

    Algorithm 1 cost eq. (10) at the bank's current time (``labels = bank.labels``): what a
    local search compares. The no-op (0) gets 0 without an evaluation; every other edit costs
    one evaluation (counted by the bank), done by
    :meth:`~selenv.families.clustering.filters.ClusterFilterBank.evaluate_changes` on the
    two clusters the edit changes. ``actions`` must be allowed edits (:func:`edit_mask`);
    returns ``(len(actions),)``.
    """
    acts = np.asarray(actions, dtype=np.int64).reshape(-1)
    out = np.zeros(acts.size)
    edits = np.flatnonzero(acts != 0)
    if edits.size:
        removed, added = _edit_changes(bank.labels, bank.clusters, acts[edits])
        J, J_now = bank.evaluate_changes(removed, added)
        out[edits] = J - J_now
    return out


def render_clustering(
    renderer: Renderer, bank: ClusterFilterBank, max_size: int, title: str
) -> np.ndarray | None:
    """Draw ``bank``'s clustering and cost terms with ``renderer`` (both clustering envs)."""
    c = bank.cost()
    labels, sigma, k = bank.labels.copy(), bank.current_sigma(), bank.k
    from selenv.families.clustering.rendering import (
        draw_receiver_clustering,  # matplotlib: first frame
    )

    return renderer.render(
        lambda fig: draw_receiver_clustering(
            fig, labels, sigma, c.J, c.J_G, c.J_C, c.J_L, k, max_size, title
        )
    )


# -- observations -------------------------------------------------------------------------------
def clustering_observation_space(n: int, mask_size: int | None = None) -> spaces.Dict:
    """Observation space over ``n`` receivers; ``mask_size`` adds ``action_mask``."""
    space: dict[str, spaces.Space[Any]] = {
        "assignment": spaces.Box(0, n - 1, (n,), np.int64),
        # sizes are >= 1; the bound is 0 because vector learners fill the slots of sub-envs
        # that did not end with zeros (TorchRL's batched GymEnv, info["final_obs"])
        "cluster_size": spaces.Box(0, n, (n,), np.int64),
        "sigma": spaces.Box(0.0, np.inf, (n, 2), np.float32),
        "position_var": spaces.Box(0.0, np.inf, (n,), np.float32),
        "cost": spaces.Box(0.0, np.inf, (4,), np.float32),
        "time": spaces.Box(0.0, 1.0, (1,), np.float32),
    }
    if mask_size is not None:
        space["action_mask"] = spaces.MultiBinary(mask_size)
    return spaces.Dict(space)


def clustering_observation(bank: ClusterFilterBank, horizon: int) -> dict[str, np.ndarray]:
    """Observation of the current state of ``bank`` (no ``action_mask``)."""
    labels = bank.labels
    c = bank.cost()
    return {
        "assignment": labels.copy(),
        "cluster_size": np.bincount(labels)[labels].astype(np.int64),
        "sigma": bank.current_sigma().astype(np.float32),
        "position_var": bank.receiver_position_variance().astype(np.float32),
        "cost": np.array([c.J, c.J_G, c.J_C, c.J_L], np.float32),
        "time": np.array([min(bank.k / horizon, 1.0)], np.float32),
    }


@dataclass(frozen=True, eq=False)
class ClusteringEnvSettings:
    """The validated keywords of a clustering env (single or vector) and its spaces.

    Attributes:
        config: the scenario config (:func:`clustering_config`).
        preset, action_mode, initial: as given (validated).
        n: receivers; horizon: filter steps per episode; max_size: receivers per cluster.
        invalid_rule: the ``invalid_action`` handling.
        obs_mask: whether the assignment mode observes its ``action_mask``.
        action_space, observation_space: the single env's spaces.
    """

    config: ClusteringConfig
    preset: str
    action_mode: str
    initial: str
    n: int
    horizon: int
    max_size: int
    invalid_rule: InvalidActionRule
    obs_mask: bool
    action_space: spaces.Space[Any]
    observation_space: spaces.Dict

    @property
    def mask_size(self) -> int:
        """Length of the flat action mask (``n * n`` or the edit count)."""
        return self.n * self.n if self.action_mode == "assignment" else edit_action_count(self.n)

    @property
    def observes_mask(self) -> bool:
        """Whether the observation holds ``action_mask``."""
        return self.action_mode == "edit" or self.obs_mask


def clustering_env_settings(
    *,
    n_agents: int,
    n_max_states: int | None,
    sigma: Any,
    noise_correlation: float,
    dt: float,
    tau: int,
    weights: tuple[float, float, float],
    horizon: int,
    prior_std: tuple[float, float, float],
    action_mode: str,
    initial: str,
    invalid_action: str,
    invalid_action_penalty: float,
    preset: str,
    p_enter: float | None,
    p_leave: float | None,
    degraded_factor: float | None,
    obs_mask: bool,
) -> ClusteringEnvSettings:
    """Validate the keywords of :class:`ReceiverClusteringEnv` (shared with its vector env).

    Raises:
        TypeError, ValueError: naming the bad keyword (see the env's ``## Arguments``).
    """
    obs_mask = check_bool(obs_mask, "obs_mask")
    rule = InvalidActionRule(invalid_action, invalid_action_penalty)
    config = clustering_config(
        n_agents=n_agents,
        n_max_states=n_max_states,
        sigma=sigma,
        noise_correlation=noise_correlation,
        dt=dt,
        tau=tau,
        weights=weights,
        prior_std=prior_std,
        horizon=horizon,
        initial=initial,
        preset=preset,
        p_enter=p_enter,
        p_leave=p_leave,
        degraded_factor=degraded_factor,
    )
    check_choice(action_mode, "action_mode", ACTION_MODES)
    n = int(n_agents)
    action_space: spaces.Space[Any]
    if action_mode == "assignment":
        action_space = spaces.MultiDiscrete([n] * n)
        observation_space = clustering_observation_space(n, n * n if obs_mask else None)
    else:
        n_edit = edit_action_count(n)
        action_space = spaces.Discrete(n_edit)
        observation_space = clustering_observation_space(n, n_edit)
    return ClusteringEnvSettings(
        config=config,
        preset=preset,
        action_mode=action_mode,
        initial=initial,
        n=n,
        horizon=int(horizon),
        max_size=config.max_cluster_size,
        invalid_rule=rule,
        obs_mask=obs_mask,
        action_space=action_space,
        observation_space=observation_space,
    )


class ReceiverClusteringEnv(EpisodeLengthSpec, gym.Env[dict[str, np.ndarray], Any]):
    r"""Re-cluster GNSS receivers with a shared bias to minimise the posterior MSE cost.

    ## Description
    The dynamic clustering problem of Greiff, Di Cairano & Berntorp (2022). ``n_agents``
    receivers, each with position and velocity in R^2 and a shared bias in R^2 (eqs. 2-3),
    are split into clusters; each cluster runs one Kalman filter on its members' states, one
    copy of the bias and their (correlated, eq. 4) measurements. A cluster may hold at most
    ``N_max`` states and measurements (Problem 1), i.e. ``(N_max - 2) // 4`` receivers. The
    cost eq. (10) ``J = a_G J_G + a_C J_C + a_L J_L`` is computed from the filters' posteriors;
    one big cluster would be best (Remark 2) but is infeasible.

    ## Noise model (presets)
    ``preset="multipath"`` (default): the receivers enter and leave multipath / urban-canyon
    conditions. Each receiver has base (open-sky) noise levels ``sigma ~ U(0, 1]`` per channel
    and a two-state Markov chain (open sky / degraded; a Gilbert-Elliott channel, the
    "good/bad" land-mobile-satellite model of Lutz et al. 1991), independent across receivers:

    | parameter | default | meaning (at ``dt = 0.1`` s) |
    |---|---|---|
    | ``p_enter`` | 0.01 | per-step P(open sky -> degraded): open-sky spells of 100 steps (10 s) |
    | ``p_leave`` | 0.05 | per-step P(degraded -> open sky): degraded spells of 20 steps (2 s) |
    | ``degraded_factor`` | 5 | both noise std devs times 5 while degraded (25x the variance) |

    About ``p_enter / (p_enter + p_leave) = 1/6`` of the receivers are degraded at any time
    (the chain starts from that stationary distribution). Step ``k``'s measurement noise is
    eq. (3b)-(4) with the levels of step ``k``: the filters, Algorithm 1's window passes and
    the cost all use the ``R_k`` of each step. The whole regime path (steps ``0 .. horizon``) is
    drawn at ``reset`` from the env's generator, after ``sigma`` and before the initial
    clustering, like any noise realisation: a seed fixes the trajectory on every executor.
    With these defaults a partition solved once at ``k = 0`` (``offline_static``) loses to
    online re-clustering (``greedy``, ``ga``): the best clustering moves with the regimes.

    ``preset="paper"``: Greiff et al.'s setting, ``sigma`` fixed for the episode (the
    trajectories of v0 before the presets existed, bit for bit).

    ## Information
    At step ``k`` the decision-maker knows the current levels of every receiver
    (``obs["sigma"]``: a receiver estimates its noise level from its signal quality) and the
    past, never the future regime path. The heuristics use Algorithm 1 costs
    (``bank.evaluate``), which filter over the past window ``k - tau .. k`` with the past and
    current ``R``; the ``rollout`` agent forecasts the future from the Markov statistics only.

    ## Action Space
    ``action_mode="assignment"`` (default): ``MultiDiscrete([n] * n)``, the clustering to use
    from now on as a label per receiver (labels are arbitrary: only the partition matters).
    This is the GA's encoding. :meth:`action_masks` gives, per receiver, the labels it could
    take if every other receiver stayed; the joint state limit cannot be expressed per
    receiver, so an element of the space can still be infeasible (a cluster over ``N_max``).

    ``action_mode="edit"``: ``Discrete(1 + n^2 + n(n-1)/2)``, one local edit of the current
    clustering (no-op, receiver ``i`` joins ``j``'s cluster or leaves to a singleton, swap two
    receivers), exactly masked (:func:`edit_mask`). Meant for RL (MaskablePPO).

    An infeasible clustering or a masked edit is handled by ``invalid_action``
    (:mod:`selenv.envs.actions`): ``"noop"`` (default) keeps the current clustering and runs
    the filter step (``info["invalid_action"]``; ``info["invalid_code"]`` 2, ``"infeasible"``,
    or 1, ``"masked"``), ``"raise"`` raises ``ValueError`` naming the violated cluster,
    ``"terminate"`` ends the episode. Labels
    outside ``[0, n)``, a wrong shape or non-integers are a ``ValueError`` / ``TypeError``.

    ## Observation Space
    ``Dict``: ``assignment (n,)`` canonical labels, ``cluster_size (n,)`` size of each
    receiver's cluster, ``sigma (n, 2)`` the current noise levels (step ``k``; constant with
    ``preset="paper"``), ``position_var (n,)`` each receiver's per-axis position
    variance, ``cost (4,)`` ``(J, J_G, J_C, J_L)`` now, ``time (1,)`` ``k / horizon``, and
    ``action_mask``: in edit mode the exact mask of the edits; in assignment mode the
    per-receiver masks ``(n * n,)`` of :meth:`action_masks` (row ``i``: the labels receiver
    ``i`` may take if every other receiver stays; ``obs_mask=False`` leaves it out, as
    release 0.1 did).

    ## Rewards
    ``-J`` after the filter step; ``info["objective"]`` is ``J`` (with ``J_G``, ``J_C``,
    ``J_L``, ``n_clusters``, ``changed``, ``k``, and ``cost_evaluations``: candidate
    clusterings costed by Algorithm 1 in this episode so far, by the agent's searches).

    ## Starting State
    ``sigma ~ U(0, 1]`` per receiver and channel (new draw per reset unless ``sigma`` is
    given; with ``preset="multipath"`` these are the base levels and the regime path is drawn
    next); filters at the prior ``diag(prior_std^2)``; a random feasible clustering with
    ``ceil(n / max_size)`` near-equal clusters (``initial="singletons"`` for the worst one), or
    ``reset(options={"clustering": labels})``.

    ## Episode End
    Terminates after ``horizon`` filter steps (``env.spec.max_episode_steps``; a
    finite-horizon problem, ``time`` is observed), or at an invalid action with
    ``invalid_action="terminate"``.

    ## Rendering
    ``render_mode="rgb_array"`` or ``"human"``: the receivers placed at their current two noise
    levels and coloured by cluster, and ``J`` with its terms ``J_G, J_C, J_L``.

    ## Step
    ``step(action)`` (1) re-clusters at time ``k`` if the partition changes, re-initialising the
    new clusters' filters with the moments of their Algorithm 1 evaluation (Alg. 2, lines
    17-19), then (2) runs one prediction and update of every cluster filter, ``k -> k + 1``.

    ## Arguments
    ``gymnasium.make("selenv/ReceiverClustering-v1", n_agents=30, n_max_states=14, sigma=None,
    noise_correlation=0.9, dt=0.1, tau=20, weights=(1, 1, 1), horizon=500,
    prior_std=(1, 1, 1), action_mode="assignment", initial="random", invalid_action="noop",
    invalid_action_penalty=0.0, render_mode=None, preset="multipath", p_enter=None,
    p_leave=None, degraded_factor=None, obs_mask=True)``. ``n_max_states=None`` lifts the
    constraint.
    Ranges (:class:`~selenv.families.clustering.scenario.ClusteringConfig` has them all; outside, a
    ``TypeError`` / ``ValueError`` naming the keyword and its range): ``n_agents`` an int in
    ``[1, 200]``, ``n_max_states`` an int >= 6, ``sigma`` entries in ``[1e-4, 1e3]``,
    ``noise_correlation`` in ``[0, 0.99]``, ``dt`` in ``[1e-3, 10]`` s, ``tau`` in
    ``[1, 10000]``, ``weights`` in ``[0, 1e6]``, ``prior_std`` in ``[1e-3, 1e2]``, ``horizon``
    in ``[1, 100000]``, ``degraded_factor`` in ``[1, 100]``, probabilities in ``[0, 1]``.
    ``sigma`` given explicitly sets the base levels (the regime path is still drawn);
    ``p_enter``, ``p_leave``, ``degraded_factor`` (``None``: the preset's value) override the
    multipath model and are a ``ValueError`` with ``preset="paper"``.

    ## Vector Env
    ``gymnasium.make_vec("selenv/ReceiverClustering-v1", num_envs=B, **kwargs)`` (the same
    keywords) returns the native
    :class:`~selenv.families.clustering.vector.ReceiverClusteringVectorEnv`: ``B`` sub-envs
    whose filters, costs, re-clusterings and masks run as batched numpy calls over all of them
    (:mod:`selenv.families.clustering.batched`, the code this env runs with ``B = 1``).
    Sub-env ``b`` reproduces this env reset with seed ``s + b`` and driven by the same actions
    (values within ``rtol 1e-9``); autoreset is Gymnasium's ``NEXT_STEP``.
    ``vectorization_mode="sync"`` still gives ``SyncVectorEnv``.

    ## Version History
    * v1: time-varying noise (``preset="multipath"``) is the default; the assignment mode
      observes its per-receiver ``action_mask``; ``invalid_action`` modes and rendering.
    * v0: release 0.1: fixed receiver noise; ``ReceiverClustering-v0`` is this class with
      ``preset="paper"`` and ``obs_mask=False`` by default, replaying 0.1's episodes (tested
      against recordings);
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
        self.render_mode = check_render_mode(render_mode, self.metadata)
        settings = clustering_env_settings(
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
        self.settings = settings
        self.obs_mask = settings.obs_mask
        self.invalid_rule = settings.invalid_rule
        self.config = settings.config
        self.preset = settings.preset
        self.n = settings.n
        self.horizon = settings.horizon
        self.max_episode_steps = self.horizon
        self.action_mode = settings.action_mode
        self.initial = settings.initial
        self.max_size = settings.max_size
        self.action_space: spaces.Space[Any] = settings.action_space
        self.observation_space = settings.observation_space  # type: ignore[assignment, unused-ignore]
        self.problem: ClusteringProblem | None = None
        self._bank: ClusterFilterBank | None = None
        self._done = False
        self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])

    # -- oracle view for heuristics ----------------------------------------------------------
    @property
    def bank(self) -> ClusterFilterBank:
        """The cluster filters (Algorithm 1 costs via ``bank.evaluate``); needs ``reset``."""
        if self._bank is None:
            raise RuntimeError("call reset() before using the environment")
        return self._bank

    def action_masks(self) -> np.ndarray:
        """Edit mode: :func:`edit_mask`. Assignment mode: (n * n,) per-receiver label masks."""
        bank = self.bank
        if self.action_mode == "edit":
            return edit_mask(bank.labels, self.max_size)
        return assignment_masks(bank.labels[None], self.max_size)[0]

    # -- Gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """New noise realisation (unless ``sigma`` was given) and initial clustering.

        ``options={"clustering": labels}`` sets the initial clustering (validated).
        """
        super().reset(seed=seed)
        self.problem = make_clustering_problem(self.config, self.np_random, self.horizon)
        opts = options or {}
        unknown = set(opts) - {"clustering"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: ['clustering']")
        labels = initial_clustering(self.problem, self.initial, opts, self.np_random)
        self._bank = ClusterFilterBank(self.problem, labels)
        self._done = False
        return self._obs(), self._info(changed=False)

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Re-cluster (if the action changes the partition), then one filter step."""
        bank = self.bank
        if self._done:
            raise RuntimeError("episode is over: call reset()")
        labels, reason = self._parse(action)
        rule = self.invalid_rule
        # the action is described (an array2string) only for an invalid action's message
        invalid = reason is not None and rule.check(f"action {self._describe(action)}", reason)
        if invalid and rule.terminates:
            self._done = True
            return self._obs(), rule.penalty, True, False, self._info(False, reason)
        changed = False if labels is None else bank.recluster(labels)
        bank.step()
        J = bank.cost().J
        self._done = bank.k >= self.horizon
        reward = -J + (rule.penalty if reason else 0.0)
        return self._obs(), reward, self._done, False, self._info(changed, reason)

    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        """A frame of the clustering (``render_mode`` ``"rgb_array"``: ``(H, W, 3)`` uint8)."""
        return render_clustering(self._renderer, self.bank, self.max_size, "ReceiverClustering-v1")

    def close(self) -> None:
        """Close the render window, if any."""
        self._renderer.close()

    # -- helpers -----------------------------------------------------------------------------
    def _parse(self, action: Any) -> tuple[np.ndarray | None, str | None]:
        """``(labels, None)`` for a valid action, ``(None, reason)`` for an invalid one.

        Raises:
            TypeError, ValueError: the action is not in the action space.
        """
        bank = self.bank
        if self.action_mode == "assignment":
            problem = self.problem
            assert problem is not None  # reset() ran: the bank exists
            arr = problem.check_labels(check_int_labels(action, self.n), "action")
            canon = canonicalize(arr)  # what check_clustering returns for a feasible arr
            if np.bincount(canon).max() > problem.max_cluster_size:
                return None, f"infeasible: {problem.violation(arr)}"
            return canon, None
        k = check_discrete(action, edit_action_count(self.n))
        if not edit_mask(bank.labels, self.max_size)[k]:
            return None, f"masked: {self.describe_edit(k)} is not allowed now"
        return apply_edit(bank.labels, k), None

    def _describe(self, action: Any) -> str:
        return describe_action(self.action_mode, action)

    def describe_edit(self, action: int) -> str:
        """Human-readable meaning of an edit action."""
        return describe_edit(self.n, action)

    def _obs(self) -> dict[str, np.ndarray]:
        obs = clustering_observation(self.bank, self.horizon)
        if self.action_mode == "edit" or self.obs_mask:
            obs["action_mask"] = self.action_masks().astype(np.int8)
        return obs

    def _info(self, changed: bool, reason: str | None = None) -> dict[str, Any]:
        bank = self.bank
        c = bank.cost()
        return {
            "objective": c.J,
            "J_G": c.J_G,
            "J_C": c.J_C,
            "J_L": c.J_L,
            "n_clusters": int(bank.labels.max()) + 1,
            "changed": changed,
            "k": bank.k,
            "action_mask": self.action_masks(),
            "cost_evaluations": bank.n_cost_evaluations,
            **self.invalid_rule.info(reason),
        }
