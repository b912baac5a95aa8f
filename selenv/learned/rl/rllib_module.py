"""The candidate-scoring policy as an RLlib ``RLModule`` (new API stack), shared by all agents.

:class:`CandidateScoringRLModule` is the RLlib twin of
:class:`~selenv.learned.rl.candidate_policy.CandidateScoringPolicy`: it holds the same torch modules
(:class:`~selenv.learned.rl.candidate_policy.CandidateScorer` and
:class:`~selenv.learned.rl.candidate_policy.CandidatePolicyHeads`, imported, not copied) behind
RLlib's ``TorchRLModule`` + ``ValueFunctionAPI``, so RLlib's PPO trains it with parameter
sharing (every agent of a PettingZoo env maps to the one module id :data:`SHARED_MODULE_ID`).

Input: one agent's **candidate view** (:mod:`selenv.learned.rl.rllib_env`), a ``Dict`` with one row
per action, the ``FIMSelection-v1`` layout (:data:`~selenv.learned.rl.candidate_policy.OBS_KEYS`)::

    gain (B, N)  whitened (B, N, W)  features (B, N, 4)  selected (B, N)
    budget_left (B, 1)  action_mask (B, N)

Forward (all shapes batched over ``B``; ``N`` the pool, ``H`` the last hidden width)::

    x_k      = [log1p g_k, r_k, symlog z_k, features_k, selected_k, budget]   (B, N, W + 8)
    h_k      = act(W_1 x_k)                            shared weights, (B, N, H_1)
    h_k      = act(W_i h_k + U_i mean_{j in A} h_j)    DeepSets layers i >= 2
    pooled   = [mean_{k in A} h_k, max_{k in A} h_k]   (B, 2 H)
    logit_k  = v . h_k + w r_k  if k in A  else  MASKED_LOGIT (-1e8)          (B, N)
    value    = u . MLP_vf(pooled) + c                   (B,)

with ``A`` the allowed candidates (``action_mask``), ``r_k = log(g_k / max_{j in A} g_j)``
(clipped at -10) and ``w`` the learnable gain skip. RLlib's ``TorchCategorical`` over the
logits is the policy: a masked candidate has probability ``exp(-1e8) = 0`` (it is never
sampled, contributes ``0 log 0 = 0`` to the entropy and nothing to the KL).

Properties (tested in ``tests/test_rllib.py``):

* **permutation-equivariant**: permuting the candidates (rows of every per-candidate key and
  of the mask) permutes the logits the same way and leaves the value unchanged (sums, means
  and maxima over candidates are order-free);
* **pool-size independent**: no weight depends on ``N``; a module built for one pool size runs
  on any other with the same per-candidate width ``W`` (the module is built from a space only
  to read ``W``).

``model_config`` keys (:data:`DEFAULT_MODEL_CONFIG`): ``hidden`` (widths of the shared
per-candidate MLP), ``activation`` (``"tanh"``/``"relu"``), ``gain_skip_init`` (``w`` at
initialisation) and ``vf`` (widths of the value MLP on the pooled embedding); other keys,
which RLlib merges into every spec (PPO's ``vf_share_layers``), are ignored. Weights start as
in SB3 (orthogonal, gain ``sqrt 2``; score head 0.01; value output 1), so an untrained module
is close to uniform over the allowed candidates.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Iterator
from functools import partial
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis.value_function_api import ValueFunctionAPI
from ray.rllib.core.rl_module.torch.torch_rl_module import TorchRLModule
from stable_baselines3.common.policies import BasePolicy
from torch import nn

from selenv.learned.resources import bounded_widths
from selenv.learned.rl.candidate_policy import (
    MASKED_LOGIT,
    OBS_KEYS,
    CandidatePolicyHeads,
    CandidateScorer,
    obs_layout,
)
from selenv.learned.rl.views import candidate_space

__all__ = [
    "DEFAULT_MODEL_CONFIG",
    "MASKED_LOGIT",
    "MODULE_CLASS",
    "SHARED_MODULE_ID",
    "CandidateScoringRLModule",
    "build_module",
    "check_model_config",
]

#: the one module id every agent maps to (parameter sharing)
SHARED_MODULE_ID = "shared"
#: architecture defaults (those of the SB3 candidate policy, ``make_ppo``)
DEFAULT_MODEL_CONFIG: dict[str, Any] = {
    "hidden": [64, 64],
    "activation": "tanh",
    "gain_skip_init": 0.0,
    "vf": [64],
}
_ACTIVATIONS = ("tanh", "relu")


def check_model_config(config: dict[str, Any] | None) -> dict[str, Any]:
    """``config`` over :data:`DEFAULT_MODEL_CONFIG`, as plain JSON types.

    Raises:
        ValueError: not a mapping, an unknown key, a non-positive or non-integer width, an
            empty ``hidden``, a width or a number of layers above its ceiling (``max_width``,
            ``max_layers`` of :data:`selenv.learned.resources.CHECKPOINT_LIMITS`), an unknown
            activation or a non-finite ``gain_skip_init``.
    """
    if config is not None and not isinstance(config, dict):
        raise ValueError(f"model_config must be a mapping, got {config!r:.80}")
    config = dict(config or {})
    unknown = sorted(set(config) - set(DEFAULT_MODEL_CONFIG))
    if unknown:
        raise ValueError(
            f"unknown model_config keys {unknown}; known: {sorted(DEFAULT_MODEL_CONFIG)}"
        )
    out = {**DEFAULT_MODEL_CONFIG, **config}
    for key in ("hidden", "vf"):
        widths = out[key]
        if not isinstance(widths, list | tuple) or not all(
            isinstance(w, int | np.integer) and not isinstance(w, bool) and w >= 1 for w in widths
        ):
            raise ValueError(f"model_config {key} must be a list of positive ints, got {widths!r}")
        out[key] = bounded_widths(
            [int(w) for w in widths], f"model_config {key}", "module", allow_empty=True
        )
    if not out["hidden"]:
        raise ValueError("model_config hidden must hold at least one width")
    if out["activation"] not in _ACTIVATIONS:
        raise ValueError(
            f"model_config activation must be one of {list(_ACTIVATIONS)}, "
            f"got {out['activation']!r}"
        )
    skip = out["gain_skip_init"]
    if isinstance(skip, bool) or not isinstance(skip, int | float) or not np.isfinite(skip):
        raise ValueError(f"model_config gain_skip_init must be a finite number, got {skip!r}")
    out["gain_skip_init"] = float(skip)
    return out


class CandidateScoringRLModule(TorchRLModule, ValueFunctionAPI):
    """Candidate scores as logits, value from the pooled embedding (module docstring).

    Built by RLlib from an ``RLModuleSpec`` (``observation_space`` a candidate-view ``Dict``,
    ``action_space`` ``Discrete(N)``, ``model_config`` see :data:`DEFAULT_MODEL_CONFIG`) or
    by :func:`build_module`.

    Raises:
        ValueError: the observation space is not a candidate view, the action space is not
            ``Discrete(N)`` of the pool size, or a bad ``model_config``.
    """

    def setup(self) -> None:
        """Build the scorer, the value MLP and its output; SB3's initialisation."""
        # RLlib merges its own keys (PPO: ``vf_share_layers``) into every spec's model_config
        raw = self.model_config or {}
        given = dict(raw) if isinstance(raw, dict) else dataclasses.asdict(raw)
        cfg = check_model_config({k: v for k, v in given.items() if k in DEFAULT_MODEL_CONFIG})
        self.module_config = cfg
        space = self.observation_space
        if not isinstance(space, spaces.Dict):
            raise ValueError(f"observation space must be a candidate-view Dict, got {space}")
        n = obs_layout(space)["n"]
        if not isinstance(self.action_space, spaces.Discrete) or self.action_space.n != n:
            raise ValueError(
                f"action space must be Discrete({n}) (the pool), got {self.action_space}"
            )
        self.scorer = CandidateScorer(
            space,
            hidden=cfg["hidden"],
            activation=cfg["activation"],
            gain_skip_init=cfg["gain_skip_init"],
        )
        activation = type(self.scorer.act)
        self.heads = CandidatePolicyHeads(
            self.scorer.features_dim, self.scorer.pooled_dim, cfg["vf"], activation
        )
        self.value_out = nn.Linear(self.heads.latent_dim_vf, 1)
        # as CandidateScoringPolicy._build (ortho_init): sqrt(2) everywhere, small score head
        for module, gain in ((self.scorer, np.sqrt(2)), (self.heads, np.sqrt(2))):
            module.apply(partial(BasePolicy.init_weights, gain=gain))
        BasePolicy.init_weights(self.value_out, gain=1.0)
        BasePolicy.init_weights(self.scorer.score_head, gain=0.01)

    # -- the network ---------------------------------------------------------------------------
    def features(self, obs: dict[str, th.Tensor]) -> th.Tensor:
        """``(B, N + 2H)``: the scores (masked at :data:`MASKED_LOGIT`) then the pooled part."""
        missing = [k for k in OBS_KEYS if k not in obs]
        if missing:
            raise ValueError(f"candidate observation lacks the keys {missing}")
        return self.scorer({k: th.as_tensor(obs[k]).float() for k in OBS_KEYS})

    def _split(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        n = features.shape[-1] - self.scorer.pooled_dim
        return features[..., :n], features[..., n:]

    def _forward(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        logits, _ = self._split(self.features(batch[Columns.OBS]))
        return {Columns.ACTION_DIST_INPUTS: logits}

    def _forward_train(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        features = self.features(batch[Columns.OBS])
        logits, _ = self._split(features)
        return {Columns.ACTION_DIST_INPUTS: logits, Columns.EMBEDDINGS: features}

    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> th.Tensor:
        """``(B,)`` value of each observation (from ``embeddings`` = features when given)."""
        features = self.features(batch[Columns.OBS]) if embeddings is None else embeddings
        return self.value_out(self.heads.forward_critic(features)).squeeze(-1)


#: dotted name of the module class (recorded in the exported JSON and checked on load)
MODULE_CLASS = f"{CandidateScoringRLModule.__module__}.{CandidateScoringRLModule.__name__}"


def build_module(
    n_candidates: int, whitened_dim: int, model_config: dict[str, Any] | None = None
) -> CandidateScoringRLModule:
    """A fresh module for ``n_candidates`` candidates of width ``whitened_dim`` (CPU, eval mode).

    The weights do not depend on ``n_candidates``: the result runs on any pool size.

    Raises:
        ValueError: non-positive sizes or a bad ``model_config``.
    """
    for name, value in (("n_candidates", n_candidates), ("whitened_dim", whitened_dim)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    with _quiet_rlmodule_config_warning():
        module = CandidateScoringRLModule(
            observation_space=candidate_space(int(n_candidates), int(whitened_dim)),
            action_space=spaces.Discrete(int(n_candidates)),
            inference_only=False,
            model_config=check_model_config(model_config),
        )
    module.eval()
    return module


@contextlib.contextmanager
def _quiet_rlmodule_config_warning() -> Iterator[None]:
    """Mute RLlib 2.60's own ``RLModule(config=[RLModuleConfig object])`` deprecation notice.

    ``RLModule.__init__`` builds a deprecated ``RLModuleConfig`` internally whatever the caller
    passes, which logs that warning (on ``ray._common.deprecation``) once per process; it says
    nothing about this module, so it is hidden while :func:`build_module` runs.
    """
    log = logging.getLogger("ray._common.deprecation")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)
