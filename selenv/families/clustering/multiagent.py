"""Multi-agent receiver clustering (PettingZoo ``ParallelEnv``).

Greiff, Di Cairano & Berntorp (2022): ``n`` GNSS receivers share one bias and are split into
clusters, each running one Kalman filter on its members, with at most ``N_max`` states per
cluster, i.e. ``max_size = (N_max - 2) // 4`` receivers (Problem 1). Here every receiver is an
agent that chooses its own cluster each step; the filters, the cost eq. (10) and the
re-initialisation of new clusters (Algorithm 2, lines 17-19) are those of
``selenv/ReceiverClustering-v1`` (:class:`~selenv.families.clustering.filters.ClusterFilterBank`).
The receivers choose together, one action each per filter step, so a joint choice can overfill
a cluster; the module resolves it by the rule below (the single-agent
``selenv/ReceiverClustering-v2`` instead builds the clustering one receiver per step under an
exact mask).

| | |
|---|---|
| Import | ``from selenv.multiagent import receiver_clustering_v1`` |
| API | ``parallel_env(...)`` (native ``ParallelEnv``), ``env(...)`` (AEC with the standard |
| | wrappers), ``raw_env(...)`` (unwrapped AEC), as in PettingZoo's own parallel modules |
| Agents | ``receiver_0 ... receiver_{n-1}`` (``n = n_agents``), all live until the horizon |
| Action | ``Discrete(n)``: a cluster label of the current canonical labelling (masked) |
| Observation | ``Dict``: as in ``selenv/ReceiverClustering-v1`` + ``self``, ``action_mask`` |
| Reward | shared: ``-J`` after the filter step (eq. 10) |
| State | ``Box(2n)``: canonical assignment and per-receiver position variance |

## Action
The current clustering is observed as canonical labels ``assignment`` (``0 .. m-1`` in order
of first appearance, ``m`` clusters). Receiver ``i`` answers a label ``t`` in ``[0, n)``:

* ``t == assignment[i]``: stay;
* ``t < m``, another cluster: join that cluster;
* ``t >= m`` (a label not in use): move to a new cluster labelled ``t``; receivers choosing the
  same unused label form that new cluster together.

``obs["action_mask"]`` (``int8``; not repeated in ``infos``, see Version History) holds the
labels receiver ``i`` could take if every other receiver stayed: its own label, every used
label whose cluster has room (``size < max_size``) and every unused label. Its own label is
always allowed, so the mask is never all zeros. With ``n_max_states=None`` every action is
allowed. A masked label (a full cluster) is handled by ``invalid_action``
(:mod:`selenv.envs.actions`): ``"noop"`` (default) keeps the receiver where it is
(``infos[agent]["invalid_action"]``, ``["invalid_code"]``; ``invalid_action_penalty`` is
added to its reward), ``"raise"`` raises ``ValueError``, ``"terminate"`` ends the episode for
every agent (the offenders' reward is the penalty, the others' 0). An out-of-range or
non-integer action is a ``ValueError``/``TypeError`` naming the agent and the action in every
mode; a step must give an action for exactly the live agents.

## Resolution of joint moves (part of the contract)
The joint choice may overfill a cluster (two receivers joining a cluster with room for one).
The env resolves it sequentially (:func:`resolve_moves`):

1. start from the current clustering and its cluster sizes;
2. draw a visiting order, a random permutation of the receivers, from the env's generator
   (seeded by ``reset(seed=...)``; a new order every step);
3. visit the receivers in that order: a receiver that stays is accepted; a receiver that moves
   is accepted iff its target cluster *in the partially built assignment* still has room
   (``size < max_size``); then it leaves its cluster (size - 1) and joins the target (size + 1).
   Otherwise it stays in its current cluster.

**The result is always feasible.** The current clustering is feasible (every cluster holds at
most ``max_size`` receivers) and each visit keeps it so: staying or a rejected move changes
nothing, and an accepted move only decreases the size of the cluster it leaves and raises the
size of its target from ``< max_size`` to ``<= max_size``. By induction over the visits the
final assignment is feasible, whatever the actions and the order. An unmasked move can still
be rejected (the mask assumes everyone else stays); a receiver that leaves its cluster frees a
place there for receivers visited after it, so the order matters: which of several receivers
competing for the free places wins is decided by the seeded order.
``infos[agent]["accepted"]`` says whether the agent's choice was carried out and
``env.last_order`` holds the visiting order of the last step.

## Step
Resolve the joint action as above, then ``bank.recluster(new_labels)`` (new clusters start from
their Algorithm 1 moments) and ``bank.step()`` (one prediction and update of every cluster
filter, ``k -> k + 1``). Every agent gets the reward ``-J`` of the new posterior;
``infos[agent]`` holds ``objective`` (``J``), ``accepted``, ``changed``,
``n_clusters`` and ``k`` (``reset`` gives the same keys, ``accepted`` true).

## Observation
Per agent, ``assignment (n,)``, ``cluster_size (n,)``, ``sigma (n, 2)``, ``position_var (n,)``,
``cost (4,)`` ``(J, J_G, J_C, J_L)``, ``time (1,)`` ``k / horizon`` (shared; as in the
single-agent env), ``self (n,)`` the one-hot index of the agent and ``action_mask (n,)``.

## Noise model
As ``selenv/ReceiverClustering-v1`` (its docstring has the table): ``preset="multipath"``
(default) switches each receiver between open sky and multipath / urban-canyon conditions (a
two-state Markov chain: ``p_enter = 0.01``, ``p_leave = 0.05`` per step, noise std x
``degraded_factor = 5`` while degraded), the path drawn at reset; ``preset="paper"`` keeps
``sigma`` fixed. ``obs["sigma"]`` holds the current levels, never the future ones.

## Starting State and Episode End
As ``selenv/ReceiverClustering-v1``: ``sigma ~ U(0, 1]`` unless given (then the regime path),
filters at the prior, a random feasible clustering (``initial="singletons"``: all singletons)
or ``reset(options={"clustering": labels})``; other option keys are ignored. The same seed
draws the same ``sigma``, regime path and initial clustering as the single-agent env. All
agents terminate together after ``horizon`` filter steps and leave ``env.agents``.

## Rendering
``render_mode="rgb_array"`` / ``"human"``: the frame of ``selenv/ReceiverClustering-v1``.

## Arguments
``parallel_env(n_agents=30, n_max_states=14, sigma=None, noise_correlation=0.9, dt=0.1, tau=20,
weights=(1, 1, 1), horizon=500, prior_std=(1, 1, 1), initial="random", invalid_action="noop",
invalid_action_penalty=0.0, render_mode=None, preset="multipath", p_enter=None, p_leave=None,
degraded_factor=None)``.

## Version History
* v1 (``receiver_clustering_v1``): time-varying noise (``preset="multipath"``) is the
  default; ``invalid_action`` modes and rendering.
* v0 (``receiver_clustering_v0``): release 0.1, fixed receiver noise: this module with
  ``preset="paper"`` by default, replaying 0.1's episodes (tested against recordings);
  deprecated in favour of v1.
* Both, since release 0.2: the mask is observed only (``obs[agent]["action_mask"]``), no
  longer repeated in ``infos`` (TorchRL's ``PettingZooWrapper`` reads a mask from the
  observation or the info, not both); observations, rewards and resolutions are unchanged.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils import wrappers
from pettingzoo.utils.conversions import parallel_to_aec

from selenv.envs.actions import INVALID_CODES, InvalidActionRule, check_discrete
from selenv.envs.conventions import KnownKeywords, check_render_mode
from selenv.envs.cycles import MaxCycles
from selenv.envs.rendering import Renderer
from selenv.families.clustering.env import (
    clustering_config,
    clustering_observation,
    clustering_observation_space,
    initial_clustering,
    render_clustering,
)
from selenv.families.clustering.filters import ClusterFilterBank
from selenv.families.clustering.scenario import (
    ClusteringProblem,
    make_clustering_problem,
)

__all__ = [
    "ReceiverClusteringParallelEnv",
    "env",
    "label_masks",
    "parallel_env",
    "raw_env",
    "resolve_moves",
]


def label_masks(labels: np.ndarray, max_size: int) -> np.ndarray:
    """(n, n) bool: row ``i`` holds the labels receiver ``i`` may choose if all others stay.

    Its own label, every used label whose cluster has room and every unused label.
    """
    n = labels.size
    room = np.bincount(labels, minlength=n) < max_size  # unused labels have size 0
    mask = np.broadcast_to(room, (n, n)).copy()
    mask[np.arange(n), labels] = True  # staying is always allowed
    return mask


def resolve_moves(
    labels: np.ndarray, targets: np.ndarray, max_size: int, order: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Carry out the receivers' cluster choices in ``order`` while the targets have room.

    Args:
        labels: (n,) current feasible clustering (labels in ``[0, n)``).
        targets: (n,) chosen label of each receiver (in ``[0, n)``).
        max_size: largest feasible cluster.
        order: a permutation of ``range(n)``, the visiting order.

    Returns:
        ``(new_labels, accepted)``: the resulting clustering (same labelling as ``labels``,
        not canonical; feasible whenever ``labels`` is) and whether each choice was carried out.
    """
    n = labels.size
    if targets.shape != (n,) or not np.array_equal(np.sort(order), np.arange(n)):
        raise ValueError(f"targets must have shape ({n},) and order be a permutation of range(n)")
    new = labels.copy()
    sizes = np.bincount(labels, minlength=n)
    accepted = np.ones(n, bool)
    for i in order:
        t = targets[i]
        if t == new[i]:
            continue  # stay
        if sizes[t] < max_size:
            sizes[new[i]] -= 1  # leaving only frees room
            sizes[t] += 1  # joining was checked: size <= max_size
            new[i] = t
        else:
            accepted[i] = False
    return new, accepted


class ReceiverClusteringParallelEnv(MaxCycles, KnownKeywords, ParallelEnv):
    """Parallel multi-agent receiver clustering; see the module docstring for the manual.

    Args:
        n_agents: number of receivers ``n`` (one agent each).
        n_max_states: ``N_max`` of Problem 1; ``None`` lifts the constraint.
        sigma: optional (n_agents, 2) measurement std devs (sampled ``U(0, 1]`` when absent);
            the base levels with ``preset="multipath"``.
        noise_correlation: inter-receiver noise correlation ``r`` in [0, 1).
        dt: step ``h``.
        tau: window of Algorithm 1.
        weights: ``(alpha_G, alpha_C, alpha_L)`` of eq. (10).
        horizon: filter steps per episode.
        prior_std: initial 1-sigma ``(position, velocity, bias)`` per axis.
        initial: ``"random"`` or ``"singletons"`` initial clustering.
        invalid_action: ``"noop"``, ``"raise"`` or ``"terminate"`` (module docstring).
        invalid_action_penalty: reward added for a masked label (float, default 0).
        render_mode: ``None``, ``"rgb_array"`` or ``"human"``.
        max_cycles: ``None`` (default: the episode ends as the env says) or an int ``N >= 1``:
            PettingZoo's cap, every live agent truncated after ``N`` parallel steps.
        preset: ``"multipath"`` (time-varying noise, default) or ``"paper"`` (fixed ``sigma``).
        p_enter: per-step probability of entering the degraded state (``None``: 0.01).
        p_leave: per-step probability of leaving it (``None``: 0.05).
        degraded_factor: noise std multiplier while degraded (``None``: 5).
    """

    metadata: dict[str, Any] = {  # noqa: RUF012
        "name": "receiver_clustering_v1",
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "is_parallelizable": True,
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
        initial: str = "random",
        invalid_action: str = "noop",
        invalid_action_penalty: float = 0.0,
        render_mode: str | None = None,
        preset: str = "multipath",
        p_enter: float | None = None,
        p_leave: float | None = None,
        degraded_factor: float | None = None,
        max_cycles: int | None = None,
    ) -> None:
        self.render_mode = check_render_mode(render_mode, self.metadata)
        self._set_max_cycles(max_cycles)
        self.invalid_rule = InvalidActionRule(invalid_action, invalid_action_penalty)
        self.config = clustering_config(
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
        self.preset = preset
        self.n = n = int(n_agents)
        self.horizon = int(horizon)
        self.initial = initial
        self.max_size = self.config.max_cluster_size
        self.possible_agents = [f"receiver_{i}" for i in range(n)]
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        base = clustering_observation_space(n, mask_size=n).spaces
        self._action_spaces: dict[str, spaces.Discrete] = {
            a: spaces.Discrete(n) for a in self.possible_agents
        }
        self._observation_spaces = {
            a: spaces.Dict({**base, "self": spaces.MultiBinary(n)}) for a in self.possible_agents
        }
        high = np.concatenate([np.full(n, n - 1.0), np.full(n, np.inf)]).astype(np.float32)
        self.state_space = spaces.Box(0.0, high, (2 * n,), np.float32)
        self.agents: list[str] = []
        self.problem: ClusteringProblem | None = None
        self.last_order: np.ndarray | None = None
        self._bank: ClusterFilterBank | None = None
        self._np_random: np.random.Generator | None = None
        self._renderer = Renderer(self.render_mode, self.metadata["render_fps"])

    # -- spaces and oracle view ------------------------------------------------------------------
    def observation_space(self, agent: str) -> spaces.Space[Any]:
        """The (fixed) observation space of ``agent``."""
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space[Any]:
        """The (fixed) action space of ``agent``."""
        return self._action_spaces[agent]

    @property
    def bank(self) -> ClusterFilterBank:
        """The cluster filters (Algorithm 1 costs via ``bank.evaluate``); needs ``reset``."""
        if self._bank is None:
            raise RuntimeError("call reset() before using the environment")
        return self._bank

    def action_mask(self, agent: str) -> np.ndarray:
        """(n,) bool: the labels ``agent`` may choose (see :func:`label_masks`)."""
        return label_masks(self.bank.labels, self.max_size)[self._index[agent]]

    def state(self) -> np.ndarray:
        """Global state ``(assignment, position_var)`` as one (2n,) float32 array."""
        bank = self.bank
        return np.concatenate([bank.labels, bank.receiver_position_variance()]).astype(np.float32)

    # -- PettingZoo API ------------------------------------------------------------------------
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """New noise realisation (unless ``sigma`` was given) and initial clustering.

        ``options={"clustering": labels}`` sets the initial clustering (validated).
        """
        if seed is not None or self._np_random is None:
            self._np_random, _ = seeding.np_random(seed)
        self.problem = make_clustering_problem(self.config, self._np_random, self.horizon)
        opts = options or {}
        labels = initial_clustering(self.problem, self.initial, opts, self._np_random)
        self._bank = ClusterFilterBank(self.problem, labels)
        self.last_order = None
        self.agents = list(self.possible_agents)
        self._start_cycles()
        masks = label_masks(self.bank.labels, self.max_size)
        infos = self._infos(masks, None, changed=False)
        return self._observations(masks), infos

    def _step_once(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        """Resolve the joint cluster choice, re-cluster, filter; shared reward ``-J``."""
        if not self.agents:
            raise RuntimeError("episode is over: call reset()")
        bank = self.bank
        missing = set(self.agents) - set(actions)
        extra = set(actions) - set(self.agents)
        if missing or extra:
            raise ValueError(
                f"actions must hold exactly the live agents; "
                f"missing {sorted(missing)}, unexpected {sorted(extra)}"
            )
        masks = label_masks(bank.labels, self.max_size)
        targets = np.array([self._parse(a, actions[a]) for a in self.possible_agents])
        reasons: dict[str, str] = {}
        for a, i in self._index.items():
            t = int(targets[i])
            if not masks[i, t]:
                reasons[a] = (
                    f"masked: label {t} is a cluster that already holds "
                    f"max_size={self.max_size} receivers"
                )
                self.invalid_rule.check(f"action {t} of {a}", reasons[a])
                targets[i] = bank.labels[i]  # noop: the receiver stays
        live = list(self.agents)
        if reasons and self.invalid_rule.terminates:
            self.agents = []
            masks = label_masks(bank.labels, self.max_size)
            obs = self._observations(masks, live)
            infos = self._infos(masks, None, False, reasons, live)
            rewards = {a: self.invalid_rule.penalty if a in reasons else 0.0 for a in live}
            ended = dict.fromkeys(live, True)
            return obs, rewards, ended, dict.fromkeys(live, False), infos
        assert self._np_random is not None
        self.last_order = self._np_random.permutation(self.n)
        new_labels, accepted = resolve_moves(bank.labels, targets, self.max_size, self.last_order)
        changed = bank.recluster(new_labels)
        bank.step()
        J = bank.cost().J
        done = bank.k >= self.horizon
        masks = label_masks(bank.labels, self.max_size)
        obs = self._observations(masks, live)
        infos = self._infos(masks, accepted, changed, reasons, live)
        penalty = self.invalid_rule.penalty
        rewards = {a: -J + (penalty if a in reasons else 0.0) for a in live}
        terms = dict.fromkeys(live, done)
        truncs = dict.fromkeys(live, False)
        if done:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    # -- helpers -------------------------------------------------------------------------------
    def _parse(self, agent: str, action: Any) -> int:
        return check_discrete(action, self.n, f"action of {agent}: label")

    def render(self) -> np.ndarray | None:
        """The clustering frame (``render_mode`` ``"rgb_array"``: ``(H, W, 3)`` uint8)."""
        return render_clustering(self._renderer, self.bank, self.max_size, "receiver_clustering_v1")

    def close(self) -> None:
        """Close the render window, if any."""
        self._renderer.close()

    def _observations(
        self, masks: np.ndarray, agents: list[str] | None = None
    ) -> dict[str, dict[str, np.ndarray]]:
        shared = clustering_observation(self.bank, self.horizon)
        eye = np.eye(self.n, dtype=np.int8)
        return {
            a: {
                **{key: value.copy() for key, value in shared.items()},
                "self": eye[i],
                "action_mask": masks[i].astype(np.int8),
            }
            for a, i in self._index.items()
            if a in (self.agents if agents is None else agents)
        }

    def _infos(
        self,
        masks: np.ndarray,
        accepted: np.ndarray | None,
        changed: bool,
        reasons: dict[str, str] | None = None,
        agents: list[str] | None = None,
    ) -> dict[str, dict[str, Any]]:
        bank = self.bank
        common = {
            "objective": bank.cost().J,
            "changed": changed,
            "n_clusters": int(bank.labels.max()) + 1,
            "k": bank.k,
        }
        infos: dict[str, dict[str, Any]] = {}
        reasons = reasons or {}
        for a, i in self._index.items():
            if a in (self.agents if agents is None else agents):
                infos[a] = dict(common)
                # reset: True (nothing was refused); the same keys at every step (TorchRL's
                # PettingZooWrapper builds its info spec from the reset's infos)
                infos[a]["accepted"] = accepted is None or (bool(accepted[i]) and a not in reasons)
                infos[a].update(InvalidActionRule.info(reasons.get(a)))
        return infos


def parallel_env(**kwargs: Any) -> ReceiverClusteringParallelEnv:
    """The native ``ParallelEnv`` (keywords: :class:`ReceiverClusteringParallelEnv`)."""
    return ReceiverClusteringParallelEnv(**kwargs)


def raw_env(**kwargs: Any) -> AECEnv:
    """The unwrapped AEC version (agents act in turn), via ``parallel_to_aec``."""
    return parallel_to_aec(parallel_env(**kwargs))


def env(**kwargs: Any) -> AECEnv:
    """The AEC version with PettingZoo's standard wrappers (bounds check, call order)."""
    return _standard_wrappers(raw_env(**kwargs))


def _standard_wrappers(aec: AECEnv) -> AECEnv:
    return wrappers.OrderEnforcingWrapper(wrappers.AssertOutOfBoundsWrapper(aec))


def _v0_kwargs(kwargs: dict[str, Any]) -> dict[str, Any]:
    """Release 0.1's defaults (fixed receiver noise), with a ``DeprecationWarning``."""
    warnings.warn(
        "selenv.multiagent.receiver_clustering_v0 reproduces selenv 0.1 (preset='paper'); "
        "selenv.multiagent.receiver_clustering_v1 is the current version",
        DeprecationWarning,
        stacklevel=3,
    )
    return {"preset": "paper", **kwargs}


def _named_v0(env: ReceiverClusteringParallelEnv) -> ReceiverClusteringParallelEnv:
    env.metadata = {**env.metadata, "name": "receiver_clustering_v0"}
    return env


def parallel_env_v0(**kwargs: Any) -> ReceiverClusteringParallelEnv:
    """``receiver_clustering_v0.parallel_env``: :func:`parallel_env` with 0.1's defaults."""
    return _named_v0(parallel_env(**_v0_kwargs(kwargs)))


def raw_env_v0(**kwargs: Any) -> AECEnv:
    """``receiver_clustering_v0.raw_env``: :func:`raw_env` with 0.1's defaults."""
    return parallel_to_aec(_named_v0(parallel_env(**_v0_kwargs(kwargs))))


def env_v0(**kwargs: Any) -> AECEnv:
    """``receiver_clustering_v0.env``: :func:`env` with 0.1's defaults."""
    return _standard_wrappers(parallel_to_aec(_named_v0(parallel_env(**_v0_kwargs(kwargs)))))
