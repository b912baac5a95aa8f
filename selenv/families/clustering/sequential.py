"""ReceiverClustering with one ``Discrete`` action and an exact mask: one receiver placed per step.

Each filter step of :class:`~selenv.families.clustering.env.ReceiverClusteringEnv` becomes
``n`` env steps. At the ``i``-th, the action ``j`` places receiver ``i`` in the new clustering:
``j < i`` joins the cluster receiver ``j`` is in, ``j == i`` opens a new cluster, ``j > i`` is
not allowed (receiver ``j`` is not placed yet). The mask is exact: ``j < i`` is allowed iff
``j``'s new cluster holds fewer than ``max_size`` receivers, ``j == i`` always, so every
sequence of allowed actions builds a clustering that meets the state limit, and every such
clustering is built by at least one (its canonical sequence: each receiver joins the lowest
receiver of its cluster). After receiver ``n - 1`` the assignment env re-clusters and runs its
filter step; that env step's reward is the assignment env's (``-J``), the others' 0, so the
return equals the assignment env's return for the same clusterings.

Built on the assignment env (composition, same seeds, same filters): an agent that plays the
assignment env plays this one through :class:`SequentialAgent`, with the same trajectory.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from selenv.agents.base import Agent
from selenv.envs.actions import InvalidActionRule, check_discrete
from selenv.envs.conventions import EpisodeLengthSpec
from selenv.families.clustering.env import ReceiverClusteringEnv

__all__ = [
    "ReceiverClusteringSequentialEnv",
    "SequentialAgent",
    "assignment_keywords",
    "placement_actions",
    "placement_masks",
    "placement_reason",
]

#: keywords the sequential env fixes on its assignment env
FIXED = ("action_mode", "obs_mask")


def placement_masks(
    receivers: np.ndarray, new: np.ndarray, sizes: np.ndarray, max_size: int
) -> np.ndarray:
    """``(k, n)`` bool: the allowed placements of ``k`` partial clusterings (the exact mask).

    ``receivers`` ``(k,)`` the receiver each places next, ``new`` ``(k, n)`` each placed
    receiver's cluster by its lowest receiver (``-1``: not placed), ``sizes`` ``(k, n)`` the
    cluster sizes by lowest receiver. ``j < i`` is allowed iff ``j``'s cluster holds fewer than
    ``max_size`` receivers, ``j == i`` (open a cluster) always, ``j > i`` never. The single env
    is the ``k = 1`` case of the vector env's call.
    """
    cols = np.arange(new.shape[1])
    i = np.asarray(receivers)[:, None]
    room = np.take_along_axis(sizes, np.maximum(new, 0), axis=1) < max_size
    return ((cols < i) & room) | (cols == i)


def placement_reason(i: int, j: int, max_size: int) -> str:
    """Why placing receiver ``i`` with action ``j`` is masked (the ``"masked: ..."`` reason)."""
    if j > i:
        return f"masked: receiver {j} is not placed yet (placing receiver {i})"
    return f"masked: receiver {j}'s cluster already holds max_size={max_size} receivers"


def assignment_keywords(render_mode: str | None, config: dict[str, Any]) -> dict[str, Any]:
    """The keywords of the assignment env (or vector env) a sequential env runs underneath.

    Raises:
        TypeError: ``config`` sets one of :data:`FIXED`.
    """
    fixed = sorted(set(config) & set(FIXED))
    if fixed:
        raise TypeError(
            f"{fixed} cannot be set: the sequential env always places one receiver per step "
            "(use ReceiverClustering's assignment or edit action_mode on -v1)"
        )
    return {
        "action_mode": "assignment",
        "obs_mask": False,
        "invalid_action": "raise",  # the placements only ever build feasible clusterings
        "render_mode": render_mode,
        **config,
    }


class ReceiverClusteringSequentialEnv(EpisodeLengthSpec, gym.Env[dict[str, np.ndarray], np.int64]):
    """``selenv/ReceiverClustering-v2``: GNSS receivers clustered one receiver per step.

    ## Description
    The dynamic clustering problem of Greiff, Di Cairano & Berntorp (2022) with one
    ``Discrete`` action and an exact mask. The receivers, their shared bias, the cluster
    Kalman filters, the noise model (``preset``), the information and the cost eq. (10)
    ``J = a_G J_G + a_C J_C + a_L J_L`` are those of ``selenv/ReceiverClustering-v1``
    (:class:`~selenv.families.clustering.env.ReceiverClusteringEnv`, whose docstring has them;
    this env runs one underneath, :attr:`inner`). Only the way a clustering is chosen differs:
    each filter step's new clustering is built receiver by receiver, ``n_agents`` env steps
    per filter step, so generic masked ``Discrete`` code (CleanRL's PPO, DQN, TorchRL's
    ``ActionMask``, MaskablePPO) runs on it unchanged.

    ## Action Space
    ``Discrete(n)``. At the ``i``-th step of a filter step, action ``j`` places receiver ``i``:
    ``j < i`` joins the new cluster of receiver ``j``, ``j == i`` opens a new cluster,
    ``j > i`` is masked (receiver ``j`` is not placed yet). The mask is exact: ``j < i`` is
    allowed iff ``j``'s new cluster holds fewer than ``max_size = (n_max_states - 2) // 4``
    receivers, so every sequence of allowed actions builds a clustering within the state
    limit, and every such clustering is built by one (:func:`placement_actions`: each receiver
    joins the lowest receiver of its cluster). :meth:`action_masks` is the ``(n,)`` bool mask.
    Keeping the current clustering is the placement sequence of its labels.

    A masked action is handled by ``invalid_action`` (:mod:`selenv.envs.actions`):
    ``"noop"`` (default) places the receiver alone, voids this filter step's new clustering
    (the filter step keeps the current one, as ``-v1``'s no-op) and adds
    ``invalid_action_penalty`` (``info["invalid_code"]`` 1, ``"masked"``); ``"raise"``
    raises ``ValueError``; ``"terminate"`` ends the episode. Out-of-range, bool or float
    actions are a ``ValueError`` / ``TypeError``.

    ## Observation Space
    ``Dict``: the ``-v1`` keys ``assignment (n,)`` (current clustering), ``cluster_size (n,)``,
    ``sigma (n, 2)``, ``position_var (n,)``, ``cost (4,)`` ``(J, J_G, J_C, J_L)``,
    ``time (1,)``, and ``receiver (n,)`` one-hot of the receiver the next action places,
    ``new_assignment (n,)`` each placed receiver's new cluster by its lowest receiver (``-1``:
    not placed yet) and ``action_mask (n,)`` (int8).

    ## Rewards
    ``-J`` after each filter step; ``info["objective"]`` is ``J``. The reward is paid at the
    step that places the last receiver, 0 at the other steps (plus the invalid-action
    penalty): the return equals ``-v1``'s for the same clusterings. ``info`` has ``-v1``'s
    keys (``objective``, ``J_G``, ``J_C``, ``J_L``, ``n_clusters``, ``changed``, ``k``,
    ``cost_evaluations``, as after the latest filter step), ``action_mask`` ``(n,)``,
    ``placing`` (the index of the receiver the next action places) and ``invalid_action`` /
    ``invalid_code``, the same keys at every step.

    ## Starting State
    As ``-v1`` (its ``reset`` options included: ``options={"clustering": labels}``); receiver
    0 is the first placed.

    ## Episode End
    Terminates after ``horizon`` filter steps, ``horizon * n_agents`` env steps
    (``env.spec.max_episode_steps``), or at a masked action with
    ``invalid_action="terminate"``.

    ## Arguments
    ``gymnasium.make("selenv/ReceiverClustering-v2", invalid_action="noop",
    invalid_action_penalty=0.0, render_mode=None, **config)``: ``config`` is every other
    keyword of ``-v1`` (``n_agents=30``, ``n_max_states=14``, ``horizon=500``,
    ``preset="multipath"``, ...; the same defaults and ranges, validated by it);
    ``action_mode`` and ``obs_mask`` are refused (``TypeError``). ``render_mode``: ``None``,
    ``"rgb_array"`` or ``"human"`` (``-v1``'s frame of the current clustering).

    ## Agents
    Every agent of ``-v1`` plays this env through :class:`SequentialAgent`
    (``selenv.agents.make(name, "selenv/ReceiverClustering-v2")`` wraps it): it asks for the
    clustering at a filter step's first placement and plays its placements, the same episode
    and return as on ``-v1`` with the same seed.

    ## Vector Env
    ``gymnasium.make_vec("selenv/ReceiverClustering-v2", num_envs=B, **kwargs)`` returns the
    native
    :class:`~selenv.families.clustering.sequential_vector.ReceiverClusteringSequentialVectorEnv`:
    placements in ``(B, n)`` arrays, the filter steps of the sub-envs that placed their last
    receiver batched by ``-v1``'s vector env. Sub-env ``b`` reproduces this env reset with
    seed ``s + b`` and driven by the same actions; Gymnasium's three autoreset modes.

    ## PettingZoo
    ``selenv.multiagent.receiver_clustering_v1`` keeps per-receiver actions (each receiver
    picks a label at every filter step; the joint state limit is applied to the joint
    action by the module's rule, documented there).

    ## Version History
    * v2: one ``Discrete`` placement per step with an exact mask (``-v1``'s
      ``MultiDiscrete`` labels could be infeasible under a per-receiver mask; its edit mode
      reaches only local edits per filter step). Same dynamics, costs and seeds as v1.
    * v1: time-varying noise (``preset="multipath"``), the assignment mode's mask observed;
      frozen (``selenv/ReceiverClustering-v1`` still builds
      :class:`~selenv.families.clustering.env.ReceiverClusteringEnv`).
    * v0: release 0.1 (fixed receiver noise); deprecated.
    """

    metadata: dict[str, Any] = ReceiverClusteringEnv.metadata  # its frames and codes

    def __init__(
        self,
        *,
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        **config: Any,
    ) -> None:
        inner_keywords = assignment_keywords(render_mode, config)
        self.invalid_rule = InvalidActionRule(invalid_action, invalid_action_penalty)
        self.inner = ReceiverClusteringEnv(**inner_keywords)
        self.render_mode = self.inner.render_mode
        self.n, self.max_size, self.horizon = self.inner.n, self.inner.max_size, self.inner.horizon
        self.max_episode_steps = self.horizon * self.n
        n = self.n
        inner_space = self.inner.observation_space
        assert isinstance(inner_space, spaces.Dict)
        self.observation_space = spaces.Dict(
            {
                **inner_space.spaces,
                "receiver": spaces.MultiBinary(n),
                "new_assignment": spaces.Box(-1, n - 1, (n,), np.int64),
                "action_mask": spaces.MultiBinary(n),
            }
        )
        self.action_space = spaces.Discrete(n)
        self._inner_obs: dict[str, np.ndarray] = {}
        self._inner_info: dict[str, Any] = {}
        self._receiver = 0
        self._new = np.full(n, -1, dtype=np.int64)
        self._sizes = np.zeros(n, dtype=np.int64)  # by the cluster's lowest receiver
        self._void = False
        self._done = False

    # -- the assignment env underneath -----------------------------------------------------------
    @property
    def bank(self) -> Any:
        """The assignment env's cluster filters (its current clustering)."""
        return self.inner.bank

    @property
    def receiver(self) -> int:
        """The receiver the next action places (0 at the start of every filter step)."""
        return self._receiver

    @property
    def inner_observation(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The assignment env's latest ``(obs, info)`` (what an assignment agent acts on)."""
        return self._inner_obs, self._inner_info

    def action_masks(self) -> np.ndarray:
        """``(n,)`` bool: the clusters receiver :attr:`receiver` may join, or open its own."""
        receiver = np.array([self._receiver])
        return placement_masks(receiver, self._new[None], self._sizes[None], self.max_size)[0]

    # -- Gymnasium API -------------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Reset the assignment env (same seed, same episode) and open a filter step."""
        self._inner_obs, self._inner_info = self.inner.reset(seed=seed, options=options)
        # one generator: the assignment env's, which draws every random number
        self._np_random, self._np_random_seed = self.inner.np_random, self.inner.np_random_seed
        self._open()
        self._done = False
        return self._obs(), self._info(None)

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Place receiver :attr:`receiver`; after the last one, re-cluster and filter."""
        if self._done:
            raise RuntimeError("episode is over: call reset()")
        i = self._receiver
        j = check_discrete(action, self.n)
        reason = None if self.action_masks()[j] else placement_reason(i, j, self.max_size)
        rule = self.invalid_rule
        if rule.check(f"action {j} (placing receiver {i})", reason) and rule.terminates:
            self._done = True
            return self._obs(), rule.penalty, True, False, self._info(reason)
        reward = rule.penalty if reason else 0.0
        lead = i if reason is not None or j == i else int(self._new[j])
        self._void |= reason is not None
        self._new[i] = lead
        self._sizes[lead] += 1
        terminated = False
        if i + 1 < self.n:
            self._receiver = i + 1
        else:
            labels = self.bank.labels.copy() if self._void else self._new.copy()
            obs, r, terminated, truncated, info = self.inner.step(labels)
            self._inner_obs, self._inner_info = obs, info
            reward += float(r)
            self._done = bool(terminated or truncated)
            self._open()
        return self._obs(), reward, terminated, False, self._info(reason)

    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        """The assignment env's frame of the current clustering."""
        return self.inner.render()

    def close(self) -> None:
        """Close the assignment env's render window, if any."""
        self.inner.close()

    # -- helpers -------------------------------------------------------------------------------
    def _open(self) -> None:
        self._receiver, self._void = 0, False
        self._new[:] = -1
        self._sizes[:] = 0

    def _obs(self) -> dict[str, np.ndarray]:
        receiver = np.zeros(self.n, dtype=np.int8)
        receiver[self._receiver] = 1
        return {
            **self._inner_obs,
            "receiver": receiver,
            "new_assignment": self._new.copy(),
            "action_mask": self.action_masks().astype(np.int8),
        }

    def _info(self, reason: str | None) -> dict[str, Any]:
        return {
            **self._inner_info,
            "action_mask": self.action_masks(),
            "placing": self._receiver,
            **InvalidActionRule.info(reason),
        }


def placement_actions(labels: np.ndarray) -> np.ndarray:
    """``(n,)`` int64: the canonical actions that build the clustering ``labels``.

    Receiver ``i`` joins the lowest receiver of its cluster (``i`` itself if it is the lowest,
    which opens the cluster). Allowed at every step when ``labels`` meets the state limit.
    """
    labels = np.asarray(labels)
    out = np.empty(labels.size, dtype=np.int64)
    first: dict[int, int] = {}
    for i, lab in enumerate(labels.tolist()):
        out[i] = first.setdefault(lab, i)
    return out


class SequentialAgent(Agent):
    """An agent of the assignment env playing :class:`ReceiverClusteringSequentialEnv`.

    At the first step of each filter step it asks ``agent`` for the clustering (on the
    assignment env's own observation, info and state), then plays its
    :func:`placement_actions` one receiver at a time: the same clusterings, filters and
    return as ``agent`` on the assignment env with the same seed. ``agent`` is the wrapped
    agent (its ``name`` names it).
    """

    name = "sequential"

    def __init__(self, agent: Any) -> None:
        self.agent = agent
        self._env: ReceiverClusteringSequentialEnv | None = None
        self._plan = np.zeros(0, dtype=np.int64)

    def reset(self, env: Any, seed: int | None = None) -> None:
        """Bind to the sequential env (wrapped or not) and reset ``agent`` on its assignment env."""
        base = env.unwrapped
        if not isinstance(base, ReceiverClusteringSequentialEnv):
            raise TypeError(
                f"SequentialAgent plays ReceiverClusteringSequentialEnv, got {type(base).__name__}"
            )
        self._env = base
        self.agent.reset(base.inner, seed=seed)

    def act(self, obs: Any, info: Any) -> int:
        """The next receiver's placement (the plan is made at the filter step's first)."""
        env = self._env
        if env is None:
            raise RuntimeError("call reset(env) before act()")
        if env.receiver == 0:
            inner_obs, inner_info = env.inner_observation
            labels = np.asarray(self.agent.act(inner_obs, inner_info))
            self._plan = placement_actions(labels)
        return int(self._plan[env.receiver])
