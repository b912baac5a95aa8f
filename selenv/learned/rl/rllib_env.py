"""selenv's PettingZoo ``ParallelEnv`` modules as RLlib ``MultiAgentEnv`` s (new API stack).

:class:`SelenvMultiAgentEnv` wraps ``selenv.multiagent.fim_selection_v0`` or
``selenv.multiagent.receiver_clustering_v1`` for RLlib's ``MultiAgentEnvRunner``; every agent
sees its own observation through a **candidate view** (one row per action, the layout of
:func:`selenv.learned.rl.views.candidate_space`) so that one
:class:`~selenv.learned.rl.rllib_module.CandidateScoringRLModule` acts for all agents::

    config.environment(SelenvMultiAgentEnv, env_config={"env": "fim_selection_v0",
                                                         "env_kwargs": {"mode": "cooperative"}})

Turns, observations, rewards (the RLlib contract, checked by
``ray.rllib.utils.pre_checks.env.check_multiagent_environments``):

* **only agents that must act get an observation**: agent ``a`` acts when
  ``infos[a]["on_turn"]`` (``fim_selection_v0``; cooperative mode: one agent at a time,
  independent mode: every agent with budget left), every live agent otherwise
  (``receiver_clustering_v1``). A waiting agent is not asked: it passes with action 0 (the
  only action its mask allows; the env ignores it), exactly as
  :class:`selenv.learned.rl.marl.SharedPolicyEnv` plays the turns for SB3;
* **rewards are the env's** (shared: every live agent gets the team reward of the step, plus
  its own invalid-action penalty, if any). RLlib adds the rewards an agent receives while it
  waits to its last action ("hanging" rewards), so with ``gamma = 1`` the return of each
  decision is the team return from that decision to the end of the episode, as in
  ``SharedPolicyEnv``; the team return of an episode is the sum over steps of the mean over
  agents of the step's rewards (what ``selenv bench`` reports);
* ``terminateds`` / ``truncateds`` hold the env's flags of the agents that were live and
  ``"__all__"``; the step that ends the episode returns the final observation of **every**
  agent, so each agent's last (hanging) decision is closed with its reward.

``reset(seed=s)`` passes ``s`` to the PettingZoo env, whose generator then draws the scenario
and every later random choice (receiver clustering's visiting order): the same seed and
actions give the same episode. Observations are pure functions of the env's observation
(:data:`VIEWS`), so the bench agent (:mod:`selenv.learned.rl.rllib_agent`) applies the same view.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces
from ray.rllib.env.multi_agent_env import MultiAgentEnv
from ray.rllib.utils.typing import MultiAgentDict

from selenv.learned.rl.candidate_policy import obs_layout
from selenv.learned.rl.views import N_FEATURES, candidate_space

__all__ = [
    "CLUSTERING_MODULE",
    "FIM_MODULE",
    "VIEWS",
    "ClusterLabelView",
    "SelenvMultiAgentEnv",
    "TurnView",
    "acting_agents",
    "make_parallel_env",
    "resolve_env",
    "view_for",
]

FIM_MODULE = "selenv.multiagent.fim_selection_v0"
CLUSTERING_MODULE = "selenv.multiagent.receiver_clustering_v1"


class TurnView:
    """``fim_selection_v0``: the agent's observation without ``on_turn`` (already candidates).

    The ``Dict`` is ``FIMSelection-v1``'s over the agent's own pool (``N_i`` candidates,
    ``W = m d``); only acting agents are shown, so ``on_turn`` would always be 1.
    """

    name = "fim_turns"

    def space(self, env_space: spaces.Space[Any]) -> spaces.Dict:
        """The env's ``Dict`` space without ``on_turn`` (checked to be a candidate layout)."""
        if not isinstance(env_space, spaces.Dict):
            raise ValueError(f"expected a Dict observation space, got {env_space}")
        space = spaces.Dict({k: v for k, v in env_space.spaces.items() if k != "on_turn"})
        obs_layout(space)  # raises ValueError unless it is the candidate layout
        return space

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        return {k: v for k, v in obs.items() if k != "on_turn"}


class ClusterLabelView:
    """``receiver_clustering_v1``: candidates = the cluster labels receiver ``i`` may answer.

    The action is a label ``t`` in ``[0, n)`` of the canonical labelling (``m`` labels in use),
    so the candidates are the ``n`` labels and the module scores clusters, not receivers:
    relabelling the clusters permutes the rows and the logits alike, and nothing depends on
    ``n``. Row ``t`` describes the cluster ``C_t`` that ``i`` would be in (for an unused label,
    the new singleton ``{i}``), with ``ls = log sigma`` (2 channels), ``pv`` the position
    variance and ``cv_t`` the mean ``pv`` of ``C_t``::

        whitened_t = [ls_i (2), mean_{j in C_t} ls_j (2), |C_t| / max_size, log pv_i,
                      log pv_i - max_j log pv_j, log cv_t, log cv_t - max_s log cv_s, k / T]
        features_t = [t is i's label (stay), t is another used label (join),
                      t is unused (new cluster), i's own cluster is a singleton]
        gain_t     = 1 for i's own label, 0 for every other (no cost is evaluated: a module
                     with a positive gain skip starts near "stay", as the SB3 edit view)
        selected = 0, budget_left = 1 - k / T

    Mask: the env's mask (own label, used labels with room, unused labels) restricted to the
    used labels and the **first** unused label ``m``: the ``n - m`` unused labels are the same
    action (a new cluster), so one row stands for them; receivers that move to a new cluster
    in the same step therefore form one new cluster together (the env's rule for a shared
    unused label). The own label is always allowed, so the mask is never all zeros.
    """

    name = "cluster_labels"
    WIDTH = 10

    def __init__(self, max_size: int) -> None:
        if isinstance(max_size, bool) or not isinstance(max_size, int | np.integer) or max_size < 1:
            raise ValueError(f"max_size must be a positive int, got {max_size!r}")
        self.max_size = int(max_size)

    def space(self, env_space: spaces.Space[Any]) -> spaces.Dict:
        """``candidate_space(n, WIDTH)`` for ``n`` receivers."""
        if not isinstance(env_space, spaces.Dict) or "assignment" not in env_space.spaces:
            raise ValueError(
                f"expected a receiver_clustering_v1 observation space, got {env_space}"
            )
        shape = env_space["assignment"].shape or (0,)
        return candidate_space(int(shape[0]), self.WIDTH)

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        labels = np.asarray(obs["assignment"], dtype=np.intp)
        n = labels.size
        me = int(np.argmax(obs["self"]))
        own = int(labels[me])
        m = int(labels.max()) + 1
        used = np.arange(n) < m
        sizes = np.bincount(labels, minlength=n).astype(np.float64)  # (n,) 0 for unused
        ls = np.log(np.maximum(np.asarray(obs["sigma"], dtype=np.float64), 1e-6))  # (n, 2)
        pv = np.maximum(np.asarray(obs["position_var"], dtype=np.float64), 1e-12)  # (n,)
        sum_ls = np.zeros((n, 2))
        np.add.at(sum_ls, labels, ls)
        sum_pv = np.zeros(n)
        np.add.at(sum_pv, labels, pv)
        safe = np.maximum(sizes, 1.0)
        cl_ls = np.where(used[:, None], sum_ls / safe[:, None], ls[me])  # (n, 2)
        lcv = np.log(np.where(used, sum_pv / safe, pv[me]))  # (n,)
        lpv = np.log(pv)
        t = float(np.asarray(obs["time"]).reshape(-1)[0])
        col = np.ones((n, 1))
        whitened = np.concatenate(
            [
                np.broadcast_to(ls[me], (n, 2)),
                cl_ls,
                (sizes / self.max_size)[:, None],
                col * lpv[me],
                col * (lpv[me] - lpv.max()),
                lcv[:, None],
                (lcv - lcv[used].max())[:, None],
                col * t,
            ],
            axis=1,
        ).astype(np.float32)
        is_own = np.arange(n) == own
        features = np.zeros((n, N_FEATURES), np.float32)
        features[:, 0] = is_own
        features[:, 1] = used & ~is_own
        features[:, 2] = ~used
        features[:, 3] = float(sizes[own] == 1)
        allowed = np.asarray(obs["action_mask"], dtype=bool) & (np.arange(n) <= m)
        allowed[own] = True
        return {
            "action_mask": allowed.astype(np.int8),
            "budget_left": np.array([1.0 - t], np.float32),
            "features": features,
            "gain": is_own.astype(np.float32),
            "selected": np.zeros(n, np.int8),
            "whitened": whitened,
        }


View = TurnView | ClusterLabelView
#: PettingZoo module -> factory of its candidate view from the ``ParallelEnv``
VIEWS: dict[str, Callable[[Any], View]] = {
    FIM_MODULE: lambda penv: TurnView(),
    CLUSTERING_MODULE: lambda penv: ClusterLabelView(penv.max_size),
}


def resolve_env(name: str) -> str:
    """Full module name of a supported env (``"fim_selection_v0"`` or the dotted name).

    Raises:
        ValueError: not one of :data:`VIEWS`.
    """
    full = name if "." in str(name) else f"selenv.multiagent.{name}"
    if full not in VIEWS:
        known = [m.rsplit(".", 1)[1] for m in VIEWS]
        raise ValueError(f"no RLlib support for env {name!r}; supported: {known}")
    return full


def make_parallel_env(name: str, env_kwargs: dict[str, Any] | None = None) -> Any:
    """``module.parallel_env(**env_kwargs)`` of a supported env.

    Raises:
        ValueError: unsupported env, or the env rejects ``env_kwargs`` (``TypeError`` from
            the constructor is reported as ``ValueError`` too, naming the keywords).
    """
    module = importlib.import_module(resolve_env(name))
    kwargs = dict(env_kwargs or {})
    try:
        return module.parallel_env(**kwargs)
    except TypeError as exc:
        raise ValueError(f"cannot build {module.__name__} with env_kwargs {kwargs}: {exc}") from exc


def view_for(name: str, penv: Any) -> View:
    """The candidate view of a supported env for the built ``penv``."""
    return VIEWS[resolve_env(name)](penv)


def acting_agents(penv: Any, infos: dict[str, Any]) -> list[str]:
    """The live agents that must decide now (``on_turn``, true when the env has no turns)."""
    return [a for a in penv.agents if infos.get(a, {}).get("on_turn", True)]


class SelenvMultiAgentEnv(MultiAgentEnv):
    """A selenv PettingZoo module as an RLlib ``MultiAgentEnv`` (module docstring).

    Args:
        config: ``{"env": module name (short or dotted), "env_kwargs": {...}}``; RLlib passes
            its ``env_config`` here (an ``EnvContext``, a dict).

    Raises:
        ValueError: unknown config keys, an unsupported env, env kwargs it rejects, or agents
            with different spaces (parameter sharing needs one space).
    """

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__()
        config = dict(config or {})
        unknown = sorted(set(config) - {"env", "env_kwargs"})
        if unknown:
            raise ValueError(f"unknown env_config keys {unknown}; expected 'env', 'env_kwargs'")
        self.env_name = resolve_env(config.get("env", FIM_MODULE))
        self.env_kwargs = dict(config.get("env_kwargs") or {})
        self.penv = make_parallel_env(self.env_name, self.env_kwargs)
        self.view = view_for(self.env_name, self.penv)
        agents = list(self.penv.possible_agents)
        obs_spaces = [self.penv.observation_space(a) for a in agents]
        act_spaces = [self.penv.action_space(a) for a in agents]
        if any(s != obs_spaces[0] for s in obs_spaces) or any(
            s != act_spaces[0] for s in act_spaces
        ):
            raise ValueError(
                f"{self.env_name}: parameter sharing needs one observation and action space "
                f"for every agent; got {dict(zip(agents, act_spaces, strict=True))}"
            )
        #: every agent's (candidate-view) observation space and action space
        self.agent_observation_space: spaces.Dict = self.view.space(obs_spaces[0])
        self.agent_action_space: spaces.Space[Any] = act_spaces[0]
        self.possible_agents = agents
        self.agents = []
        self.observation_spaces = dict.fromkeys(agents, self.agent_observation_space)
        self.action_spaces = dict.fromkeys(agents, self.agent_action_space)
        self._infos: dict[str, Any] = {}

    def reset(  # type: ignore[override]  # RLlib's multi-agent reset, not gymnasium's
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[MultiAgentDict, MultiAgentDict]:
        """Reset the PettingZoo env with ``seed``; observations of the agents that act first."""
        super().reset(seed=seed, options=options)
        obs, self._infos = self.penv.reset(seed=seed, options=options)
        self.agents = list(self.penv.agents)
        acting = acting_agents(self.penv, self._infos)
        return {a: self.view(obs[a]) for a in acting}, {a: self._infos[a] for a in acting}

    def step(  # type: ignore[override]  # RLlib's multi-agent step, not gymnasium's
        self, action_dict: MultiAgentDict
    ) -> tuple[MultiAgentDict, MultiAgentDict, MultiAgentDict, MultiAgentDict, MultiAgentDict]:
        """One joint step: the acting agents' actions, 0 for the waiting ones."""
        if not self.penv.agents:
            raise RuntimeError("step() called after the episode ended; call reset()")
        live = list(self.penv.agents)
        extra = sorted(map(str, set(action_dict) - set(live)))
        missing = sorted(set(acting_agents(self.penv, self._infos)) - set(action_dict))
        if extra or missing:
            raise ValueError(
                f"actions must cover the acting agents; missing {missing}, not live {extra}"
            )
        actions = {a: int(action_dict.get(a, 0)) for a in live}
        obs, rewards, terms, truncs, self._infos = self.penv.step(actions)
        self.agents = list(self.penv.agents)
        done = not self.penv.agents
        shown = list(obs) if done else acting_agents(self.penv, self._infos)
        rewards = {a: float(r) for a, r in rewards.items()}
        terminateds = {a: bool(v) for a, v in terms.items()}
        truncateds = {a: bool(v) for a, v in truncs.items()}
        terminateds["__all__"] = done and any(terms.values())
        truncateds["__all__"] = done and not terminateds["__all__"]
        return (
            {a: self.view(obs[a]) for a in shown},
            rewards,
            terminateds,
            truncateds,
            {a: self._infos[a] for a in shown},
        )

    def render(self) -> Any:
        """The PettingZoo env's frame (its ``render_mode``)."""
        return self.penv.render()

    def close(self) -> None:
        """Close the PettingZoo env."""
        self.penv.close()
