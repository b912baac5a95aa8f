"""A permutation-equivariant candidate-scoring policy for MaskablePPO / PPO on every env.

The policy is SB3 extended by composition: a features extractor (:class:`CandidateScorer`)
runs one shared MLP over every candidate of the pool and returns one score per candidate
(the action logits) followed by a pooled embedding of the pool (the value function's input).
:class:`CandidateScoringPolicy` wires the two halves into MaskablePPO's actor and critic
without any layer whose size depends on the pool size ``N``::

    obs ──► x_k = [log1p g_k, r_k, symlog z_k, features_k, selected_k, budget]
        ──► h_k = act(W_1 x_k)                     (shared weights, (N, hidden))
        ──► h_k = act(W_i h_k + U_i mean_j h_j)    (DeepSets layers i >= 2, mean over unselected)
        ──► pooled = [mean_k h_k, max_k h_k]       (over unselected k, (2 hidden,))
        ──► score_k = v . h_k + w r_k
    features = [score_1 .. score_N, pooled]
        actor : logits = features[:N]              (ScoreSlice, no weights)
        critic: value  = Linear(MLP(features[N:]))

with ``g_k`` the marginal gain, ``r_k = log(g_k / max_j g_j)`` the gain relative to the best
unselected candidate (0 for greedy's pick, clipped at -10), ``z_k`` the whitened row and ``w``
a learnable scalar (the "gain skip": with the head at zero the policy is a softened greedy).
So a permutation of the candidates permutes the logits and leaves the value unchanged, and a
model trained on one pool size runs on any other with the same ``m d`` (whitened width).
"""

from __future__ import annotations

from functools import partial
from itertools import pairwise
from typing import Any, cast

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.policies import MaskableMultiInputActorCriticPolicy
from stable_baselines3 import PPO
from stable_baselines3.common.policies import MultiInputActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from selenv.learned.rl.compiled import compiled_forward

__all__ = [
    "ALGORITHMS",
    "MASKED_LOGIT",
    "OBS_KEYS",
    "CandidatePolicyHeads",
    "CandidateScorer",
    "CandidateScoringPPOPolicy",
    "CandidateScoringPolicy",
    "ScoreSlice",
    "make_maskable_ppo",
    "make_ppo",
    "obs_layout",
]

#: observation keys the scorer reads (the ``FIMSelection-v1`` layout)
OBS_KEYS = ("gain", "whitened", "features", "selected", "budget_left", "action_mask")
#: static per-candidate features per candidate (one-hot sensor x3, time in window)
N_STATIC_FEATURES = 4

_ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "relu": nn.ReLU}
#: logit of a masked candidate (the value MaskablePPO's masked categorical uses)
MASKED_LOGIT = -1e8


def obs_layout(observation_space: spaces.Space) -> dict[str, int]:
    """Pool size and per-candidate widths of a ``FIMSelection-v1`` observation space.

    Returns:
        ``{"n": N, "whitened_dim": m d, "n_features": 4}``.

    Raises:
        ValueError: not a ``Dict`` with the ``FIMSelection-v1`` keys and consistent shapes.
    """
    if not isinstance(observation_space, spaces.Dict):
        raise ValueError(f"expected a Dict observation space, got {observation_space}")
    missing = [k for k in OBS_KEYS if k not in observation_space.spaces]
    if missing:
        have = list(observation_space.spaces)
        raise ValueError(f"observation space lacks the keys {missing} (has {have})")
    shapes = {k: tuple(observation_space[k].shape or ()) for k in OBS_KEYS}
    n = shapes["gain"][0] if len(shapes["gain"]) == 1 else -1
    ok = (
        n > 0
        and len(shapes["whitened"]) == 2
        and shapes["whitened"][0] == n
        and shapes["features"] == (n, N_STATIC_FEATURES)
        and shapes["selected"] == (n,)
        and shapes["action_mask"] == (n,)
        and shapes["budget_left"] == (1,)
    )
    if not ok:
        raise ValueError(f"inconsistent FIMSelection observation shapes: {shapes}")
    return {"n": n, "whitened_dim": shapes["whitened"][1], "n_features": N_STATIC_FEATURES}


def _symlog(x: th.Tensor) -> th.Tensor:
    """``sign(x) log(1 + |x|)``: squashes the whitened rows (|z| up to ~30) to a tame range."""
    return th.sign(x) * th.log1p(th.abs(x))


def _mlp(sizes: list[int], activation: type[nn.Module]) -> nn.Sequential:
    """``Linear, act`` pairs through ``sizes``."""
    layers: list[nn.Module] = []
    for a, b in pairwise(sizes):
        layers += [nn.Linear(a, b), activation()]
    return nn.Sequential(*layers)


class CandidateScorer(BaseFeaturesExtractor):
    """Shared per-candidate network: one score per candidate plus a pooled embedding of the pool.

    The first layer sees one candidate; every later layer also sees the masked mean of the
    previous layer over the unselected candidates (a DeepSets layer), so a score can depend on
    the rest of the pool. Output ``(B, N + 2 hidden)``: ``scores (N)`` then
    ``[masked mean, masked max] (2 hidden)`` of the last layer over the unselected candidates.
    No weight depends on ``N``.

    Args:
        observation_space: a ``FIMSelection-v1`` ``Dict`` space.
        hidden: widths of the shared per-candidate MLP.
        activation: ``"tanh"`` or ``"relu"``.
        gain_skip_init: initial weight ``w`` of the skip ``w r_k`` (relative log gain) added to
            every score, a learnable scalar: 0 starts from a near-uniform policy; ``w > 0``
            starts from a softened greedy (``pi_k ∝ (g_k / max g)^w``).
        shortlist: ``m > 0``: the network runs on the ``m`` unselected candidates of largest
            ``gain`` only (its context and pooled embedding over them); the other candidates
            get the masked logit, so the policy chooses among that shortlist. The update then
            costs about ``m / N`` of the full pool's. The inference agent's ``top_m=m`` is the
            same rule. 0 (default): every candidate.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        hidden: tuple[int, ...] | list[int] = (64, 64),
        activation: str = "tanh",
        gain_skip_init: float = 0.0,
        shortlist: int = 0,
    ) -> None:
        if isinstance(shortlist, bool) or not isinstance(shortlist, int) or shortlist < 0:
            raise ValueError(f"shortlist must be an int >= 0, got {shortlist!r}")
        layout = obs_layout(observation_space)
        hidden = [int(h) for h in hidden]
        if not hidden or min(hidden) < 1:
            raise ValueError(f"hidden must be a non-empty list of positive widths, got {hidden}")
        if activation not in _ACTIVATIONS:
            known = sorted(_ACTIVATIONS)
            raise ValueError(f"activation must be one of {known}, got {activation!r}")
        self.n_candidates = layout["n"]
        self.whitened_dim = layout["whitened_dim"]
        self.pooled_dim = 2 * hidden[-1]
        super().__init__(observation_space, features_dim=self.n_candidates + self.pooled_dim)
        in_dim = 2 + self.whitened_dim + N_STATIC_FEATURES + 1 + 1
        act = _ACTIVATIONS[activation]
        self.act = act()
        self.input_layer = nn.Linear(in_dim, hidden[0])
        self.set_layers = nn.ModuleList(nn.Linear(a, b) for a, b in pairwise(hidden))
        self.ctx_layers = nn.ModuleList(nn.Linear(a, b, bias=False) for a, b in pairwise(hidden))
        self.score_head = nn.Linear(hidden[-1], 1)
        self.gain_skip = nn.Parameter(th.tensor(float(gain_skip_init)))
        self.shortlist = shortlist

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """:meth:`scores`, compiled once :func:`~selenv.learned.rl.compiled.compile_scorer` ran."""
        fast = compiled_forward(self)
        return self.scores(observations) if fast is None else fast(observations)

    def scores(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """``[scores (B, N), pooled (B, 2 hidden)]`` concatenated (the class docstring)."""
        raw = th.clamp(observations["gain"], min=0.0)  # (B, N)
        mask = observations["action_mask"] > 0.5  # (B, N) unselected candidates
        n = raw.shape[1]
        gain = th.log1p(raw)
        # relative gain log((g_k + eps) / (max_j g_j + eps)) over the unselected j: 0 at the top
        log_g = th.log(raw + 1e-6)
        top = log_g.masked_fill(~mask, -th.inf).amax(dim=1, keepdim=True)
        rel = th.where(mask, log_g - th.where(th.isfinite(top), top, 0.0), 0.0).clamp(min=-10.0)
        x = th.cat(
            [
                gain.unsqueeze(-1),
                rel.unsqueeze(-1),
                _symlog(observations["whitened"]),
                observations["features"],
                observations["selected"].unsqueeze(-1),
                observations["budget_left"].unsqueeze(1).expand(-1, n, -1),
            ],
            dim=-1,
        )
        m = self.shortlist
        if 0 < m < n:  # the m unselected candidates of largest gain (masked ones last)
            idx = raw.masked_fill(~mask, -1.0).topk(m, dim=1).indices  # (B, m)
            x = x.gather(1, idx.unsqueeze(-1).expand(-1, -1, x.shape[-1]))
            short, pooled = self._network(x, mask.gather(1, idx), rel.gather(1, idx))
            scores = th.full_like(raw, MASKED_LOGIT).scatter(1, idx, short)
        else:
            scores, pooled = self._network(x, mask, rel)
        return th.cat([scores, pooled], dim=-1)

    def _network(
        self, x: th.Tensor, mask: th.Tensor, rel: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        """Scores ``(B, K)`` and pooled embedding ``(B, 2 hidden)`` of ``K`` candidates.

        ``x`` ``(B, K, in)`` their inputs, ``mask`` ``(B, K)`` the unselected ones, ``rel``
        ``(B, K)`` their relative log gains.
        """
        m = mask.unsqueeze(-1).to(x.dtype)
        count = m.sum(dim=1).clamp(min=1.0)  # (B, 1)
        h = self.act(self.input_layer(x))  # (B, K, hidden)
        for layer, ctx_layer in zip(self.set_layers, self.ctx_layers, strict=True):
            ctx = (h * m).sum(dim=1) / count  # masked mean over unselected candidates
            h = self.act(layer(h) + ctx_layer(ctx).unsqueeze(1))
        mean = (h * m).sum(dim=1) / count
        big = th.finfo(h.dtype).max
        mx = h.masked_fill(~mask.unsqueeze(-1), -big).amax(dim=1)
        mx = th.where(mask.any(dim=1, keepdim=True), mx, th.zeros_like(mx))
        pooled = th.cat([mean, mx], dim=-1)  # (B, 2 hidden)
        scores = self.score_head(h).squeeze(-1) + self.gain_skip * rel
        # masked candidates get MaskablePPO's own masked logit, so plain PPO (which has no
        # action_masks argument) never samples them and MaskablePPO is unchanged
        return scores.masked_fill(~mask, MASKED_LOGIT), pooled


class ScoreSlice(nn.Module):
    """The actor's ``action_net``: the first ``N`` entries of the features are the logits."""

    def __init__(self, pooled_dim: int) -> None:
        super().__init__()
        self.pooled_dim = pooled_dim

    def forward(self, latent: th.Tensor) -> th.Tensor:  # noqa: D102
        return latent[..., : latent.shape[-1] - self.pooled_dim]


class CandidatePolicyHeads(nn.Module):
    """Replaces SB3's ``MlpExtractor``: actor passes the features through, critic sees the pool.

    ``net_arch["pi"]`` must be empty (the logits are the scores); ``net_arch["vf"]`` are the
    widths of the value MLP on the pooled embedding.
    """

    def __init__(
        self, features_dim: int, pooled_dim: int, vf: list[int], activation: type[nn.Module]
    ) -> None:
        super().__init__()
        self.pooled_dim = pooled_dim
        self.value_net = _mlp([pooled_dim, *vf], activation)
        self.latent_dim_pi = features_dim
        self.latent_dim_vf = vf[-1] if vf else pooled_dim

    def forward(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:  # noqa: D102
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: th.Tensor) -> th.Tensor:  # noqa: D102
        return features

    def forward_critic(self, features: th.Tensor) -> th.Tensor:  # noqa: D102
        return self.value_net(features[..., features.shape[-1] - self.pooled_dim :])


class _CandidateScoringMixin:
    """Shared by the MaskablePPO and PPO policies: logits = per-candidate scores.

    Defaults: ``features_extractor_class=CandidateScorer``, ``net_arch=dict(pi=[], vf=[64])``.
    The value net is an MLP on the pooled embedding only, so no weight depends on ``N``.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.Tanh,
        ortho_init: bool = True,
        features_extractor_class: type[BaseFeaturesExtractor] = CandidateScorer,
        features_extractor_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        net_arch = dict(pi=[], vf=[64]) if net_arch is None else net_arch
        if not isinstance(net_arch, dict) or net_arch.get("pi"):
            raise ValueError(f"net_arch must be dict(pi=[], vf=[...]), got {net_arch!r}")
        if not issubclass(features_extractor_class, CandidateScorer):
            raise ValueError("features_extractor_class must be CandidateScorer (or a subclass)")
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"action space must be Discrete(N), got {action_space}")
        n = obs_layout(observation_space)["n"]
        if action_space.n != n:
            raise ValueError(f"action space Discrete({action_space.n}) != pool size {n}")
        super().__init__(  # type: ignore[call-arg]  # the SB3 policy base (see the subclasses)
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch,
            activation_fn=activation_fn,
            ortho_init=ortho_init,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            **kwargs,
        )

    def _build_mlp_extractor(self) -> None:
        _build_heads(self)

    def _build(self, lr_schedule: Schedule) -> None:
        """Build the heads and optimiser; ``action_net`` slices the scores (no weights)."""
        _build_policy(self, lr_schedule)


def _build_heads(policy: Any) -> None:
    """``policy.mlp_extractor`` = :class:`CandidatePolicyHeads` (an SB3 actor-critic policy)."""
    extractor = policy.pi_features_extractor
    if not isinstance(extractor, CandidateScorer):
        raise TypeError(f"expected a CandidateScorer, got {type(extractor).__name__}")
    vf = list(policy.net_arch.get("vf", [])) if isinstance(policy.net_arch, dict) else []
    policy.mlp_extractor = CandidatePolicyHeads(
        policy.features_dim, extractor.pooled_dim, vf, policy.activation_fn
    )


def _build_policy(policy: Any, lr_schedule: Schedule) -> None:
    """SB3's ``_build`` for the candidate policies: heads, score slice, value net, optimiser."""
    _build_heads(policy)
    heads = policy.mlp_extractor
    policy.action_net = ScoreSlice(heads.pooled_dim)
    policy.value_net = nn.Linear(heads.latent_dim_vf, 1)
    if policy.ortho_init:
        extractors = {policy.pi_features_extractor, policy.vf_features_extractor}
        for module, gain in [
            *[(e, np.sqrt(2)) for e in extractors],
            (heads, np.sqrt(2)),
            (policy.value_net, 1.0),
        ]:
            module.apply(partial(policy.init_weights, gain=gain))
        # small score head: the untrained policy is close to uniform (plus the gain skip)
        for e in extractors:
            policy.init_weights(e.score_head, gain=0.01)
    policy.optimizer = policy.optimizer_class(
        policy.parameters(), lr=lr_schedule(1), **policy.optimizer_kwargs
    )


class CandidateScoringPolicy(_CandidateScoringMixin, MaskableMultiInputActorCriticPolicy):
    """MaskablePPO policy whose logits are :class:`CandidateScorer`'s per-candidate scores."""


class CandidateScoringPPOPolicy(_CandidateScoringMixin, MultiInputActorCriticPolicy):
    """Plain-PPO twin of :class:`CandidateScoringPolicy` (same weights, same ``state_dict``).

    PPO passes no ``action_masks``; the scorer masks the logits itself from the observation's
    ``action_mask`` (:data:`MASKED_LOGIT`), so a masked candidate is never sampled.
    """


#: ``algo`` name -> (SB3 algorithm, policy class)
ALGORITHMS: dict[str, tuple[type[Any], type[Any]]] = {
    "maskable_ppo": (MaskablePPO, CandidateScoringPolicy),
    "ppo": (PPO, CandidateScoringPPOPolicy),
}


def make_ppo(
    env: gym.Env[Any, Any] | VecEnv, algo: str = "maskable_ppo", **ppo_kwargs: Any
) -> MaskablePPO | PPO:
    """MaskablePPO (``algo="maskable_ppo"``) or PPO (``"ppo"``) with the candidate-scoring policy.

    Defaults are those of the FIM selection task; ``gamma=1`` because the undiscounted return
    is the objective. Any keyword of the algorithm overrides a default; ``policy_kwargs`` are
    merged. Plain PPO never samples a masked action either (the policy masks its logits from
    the observation's ``action_mask``), but only MaskablePPO also uses the env's
    ``action_masks()`` and drops masked actions from the entropy.

    Raises:
        ValueError: unknown ``algo``.
    """
    if algo not in ALGORITHMS:
        raise ValueError(f"algo must be one of {sorted(ALGORITHMS)}, got {algo!r}")
    algorithm, policy = ALGORITHMS[algo]
    policy_kwargs = {
        "net_arch": dict(pi=[], vf=[64]),
        "features_extractor_kwargs": {"hidden": [64, 64], "activation": "tanh"},
        **ppo_kwargs.pop("policy_kwargs", {}),
    }
    kwargs: dict[str, Any] = {
        "learning_rate": 1e-3,
        "n_steps": 128,
        "batch_size": 512,
        "n_epochs": 4,
        "gamma": 1.0,
        "gae_lambda": 0.95,
        "clip_range": 0.2,
        "ent_coef": 1e-3,
        "vf_coef": 0.5,
        "max_grad_norm": 0.5,
        "device": "cpu",
        "verbose": 0,
        **ppo_kwargs,
    }
    model: MaskablePPO | PPO = algorithm(policy, env, policy_kwargs=policy_kwargs, **kwargs)
    return model


def make_maskable_ppo(env: gym.Env[Any, Any] | VecEnv, **ppo_kwargs: Any) -> MaskablePPO:
    """:func:`make_ppo` with ``algo="maskable_ppo"`` (the default of every training script)."""
    return cast(MaskablePPO, make_ppo(env, "maskable_ppo", **ppo_kwargs))
