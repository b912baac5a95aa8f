"""A factorised edit scorer for ``ReceiverClustering-v1``: per-receiver work, not per-edit work.

:class:`~selenv.learned.rl.candidate_policy.CandidateScorer` runs its MLP on every one of the
``N = 1 + n^2 + n(n-1)/2`` edit rows of :class:`~selenv.families.clustering.view.ClusteringEditView`
(1,336 rows for ``n = 30`` receivers). But an edit row only describes its two receivers ``i``,
``j`` (:data:`~selenv.families.clustering.view.SOURCE_COLUMNS`,
:data:`~selenv.families.clustering.view.TARGET_COLUMNS`) plus the time, so
:class:`FactorisedEditScorer` embeds each *receiver* once and scores an edit by a weight-free
combination of its receivers' embeddings::

    u_r  = the receiver table: SOURCE_COLUMNS of the "r leaves" row 1 + r (n + 1)    (B, n, 8)
    x_r  = [symlog u_r, budget_left]                                               (B, n, 9)
    h_r  = act(W_1 x_r);  h_r = act(W_l h_r + U_l mean_s h_s)  (DeepSets layers)    (B, n, H)
    [q_r, s_r, a_r, b_r, c_r, d_r] = score_head(h_r)   (small init; q_r, s_r in R^k)
    kappa_r = key_head(h_r)                                                        (B, n, k)
    phi_ij  = log1p |[ls_i - cm_j, ls_i - ls_j, cm_i - cm_j]|                       (B, n, n, 6)

    score(no-op)       = beta_noop
    score(leave i)     = a_i + beta_leave
    score(move i -> j) = q_i . kappa_j / sqrt(k) + b_i + c_j + alpha_move . phi_ij + beta_move
    score(swap i < j)  = (s_i . kappa_j + s_j . kappa_i) / sqrt(k) + d_i + d_j
                         + alpha_swap . (phi_ij + phi_ji) + beta_swap
    logit_e = score(e) + w r_e,  masked edits at MASKED_LOGIT

with ``ls`` the receiver's log noise levels, ``cm`` its cluster's mean log noise level, ``r_e``
the relative log gain and ``w`` the gain skip exactly as in ``CandidateScorer`` (the view's gain
is 1 for the no-op and 0 for the edits, so ``w = 1`` starts at ~94 % "keep the clustering").
The value function sees ``[mean_r h_r, max_r h_r]`` (``(B, 2 H)``), so the features layout
``[scores (N), pooled (2 H)]`` is that of ``CandidateScorer`` and everything built on it (the
candidate-scoring policies, :class:`~selenv.learned.rl.lean.LeanScorer`, the ranking fit) works
unchanged.

Why bilinear + additive rather than a two-stage receiver-then-target head: MaskablePPO needs one
logit per action of ``Discrete(N)`` under the env's mask, which this gives directly (a two-stage
head would need its own masked, factorised distribution and changes to the algorithm), and the
per-edit work is a rank-``k`` dot product plus a few products with ``phi`` -- the
``(n, H) x (H, k)`` heads and two ``(n, k) x (k, n)`` products replace an ``N x H x H`` MLP
(``n = 30``, ``H = 128``, ``k = 16``: ~0.8 M multiply-adds per state instead of ~26 M). The
low-rank term carries "which target suits which source", the additive terms "which receivers
are worth moving" and "which clusters are worth joining", ``phi`` the one non-linear pairwise
relation that matters for the cost (how far ``i``'s noise is from ``j``'s cluster).

Symmetries: relabelling the receivers permutes the edits accordingly and the logits with them
(the no-op's and the value are unchanged); swap scores are symmetric in ``(i, j)``. No weight
depends on ``n``: a model trained on 30 receivers plays 12 or 50.

The architecture is recorded in the checkpoint JSON as ``"features_extractor":``
:data:`EDIT_EXTRACTOR` with ``hidden``, ``activation``, ``gain_skip_init`` and ``rank`` (the
class's earlier path, ``selenv.learned.rl.edit_policy.FactorisedEditScorer``, is read as this
one: :func:`selenv.learned.resources.current_class_name`); :func:`load_edit_policy` rebuilds it
from that JSON and reads only the weights (``torch.load(weights_only=True)``,
:func:`selenv.learned.rl.safe_load.read_weights`), never executing anything from the file.
"""

from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib import MaskablePPO
from stable_baselines3 import PPO
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from selenv.families.clustering.view import (
    SOURCE_COLUMNS,
    ClusteringEditView,
    edit_endpoints,
    leave_rows,
    receivers_for_count,
)
from selenv.learned.resources import (
    bounded_int,
    check_parameter_count,
    current_class_name,
    mlp_parameters,
)
from selenv.learned.rl.candidate_policy import (
    _ACTIVATIONS,
    MASKED_LOGIT,
    CandidateScorer,
    CandidateScoringPolicy,
    CandidateScoringPPOPolicy,
    obs_layout,
)
from selenv.learned.rl.safe_load import (
    POLICY_CLASSES,
    _common_architecture,
    _training_algorithm,
    build_on_training_pool,
    load_policy,
    model_from_checkpoint,
)

__all__ = [
    "EDIT_EXTRACTOR",
    "SCORERS",
    "FactorisedEditScorer",
    "build_edit_policy",
    "edit_model_from_checkpoint",
    "edit_policy_spec",
    "edit_scorer_parameters",
    "is_edit_architecture",
    "load_edit_policy",
    "scorer_policy_kwargs",
]

#: the ``architecture.features_extractor`` string of a factorised checkpoint (exact match, after
#: :func:`~selenv.learned.resources.current_class_name`)
EDIT_EXTRACTOR = "selenv.learned.families.clustering_edits.FactorisedEditScorer"
#: the ``--scorer`` choices of the clustering training scripts
SCORERS = ("factorised", "mlp")
#: pairwise edit features per (i, j): ``|ls_i - cm_j|`` (2), ``|ls_i - ls_j|`` (2),
#: ``|cm_i - cm_j|`` (2)
N_PAIR_FEATURES = 6


def _symlog(x: th.Tensor) -> th.Tensor:
    """``sign(x) log(1 + |x|)``, elementwise (any shape)."""
    return th.sign(x) * th.log1p(th.abs(x))


def _check_rank(rank: object) -> None:
    """``TypeError`` / ``ValueError`` naming ``rank`` unless it is an int >= 1."""
    if isinstance(rank, bool) or not isinstance(rank, int):
        raise TypeError(f"rank must be an int, got {type(rank).__name__}")
    if rank < 1:
        raise ValueError(f"rank must be >= 1, got {rank}")


class FactorisedEditScorer(CandidateScorer):
    """Edit scores from per-receiver embeddings (module docstring), for MaskablePPO / PPO.

    A :class:`~selenv.learned.rl.candidate_policy.CandidateScorer` in interface (the candidate
    policies accept it as ``features_extractor_class``): ``forward`` maps the candidate
    observation (``whitened (B, N, 17)``, ``gain (B, N)``, ``action_mask (B, N)``,
    ``budget_left (B, 1)``) to ``(B, N + 2 H)`` = ``[scores (N), pooled (2 H)]``; but its
    per-candidate work is a weight-free combination of ``(B, n, .)`` receiver tensors.

    ``scores_every_candidate`` (class attribute): every edit is scored cheaply already, so a
    ``top_m`` pre-selection does not apply.

    Args:
        observation_space: the ``ClusteringEditView`` candidate space of ``n`` receivers
            (``N = 1 + n^2 + n(n-1)/2`` candidates of ``whitened`` width 17).
        hidden: widths ``H_1 .. H_L`` of the per-receiver DeepSets MLP (``H = H_L``).
        activation: ``"tanh"`` or ``"relu"``.
        gain_skip_init: initial weight ``w`` of the gain skip ``w r_e``.
        rank: ``k``, the width of the bilinear source/target factors.

    Raises:
        TypeError: ``observation_space`` is not a ``gymnasium.spaces.Dict``; ``rank`` not an
            int.
        ValueError: the space is not an edit-view space, ``hidden`` has a non-positive width,
            an unknown ``activation``, ``rank < 1``.
    """

    #: every edit is scored cheaply: a ``top_m`` pre-selection does not apply
    scores_every_candidate = True
    leave_rows: th.Tensor  # (n,) rows of the "r leaves" edits
    swap_i: th.Tensor  # (P,) first receiver of each swap row
    swap_j: th.Tensor  # (P,) second receiver of each swap row
    source_columns: th.Tensor  # (8,) SOURCE_COLUMNS
    diagonal: th.Tensor  # (n, n) bool identity

    def __init__(
        self,
        observation_space: spaces.Dict,
        hidden: tuple[int, ...] | list[int] = (64, 64),
        activation: str = "tanh",
        gain_skip_init: float = 0.0,
        rank: int = 16,
    ) -> None:
        if not isinstance(observation_space, spaces.Dict):
            raise TypeError(
                f"observation_space must be a gymnasium Dict space, got "
                f"{type(observation_space).__name__}"
            )
        layout = obs_layout(observation_space)
        if layout["whitened_dim"] != ClusteringEditView.WIDTH:
            raise ValueError(
                f"observation_space: whitened width {layout['whitened_dim']}, the clustering "
                f"edit view's is {ClusteringEditView.WIDTH}"
            )
        try:
            n = receivers_for_count(layout["n"])
        except ValueError as exc:
            raise ValueError(f"observation_space: {exc} (not a clustering edit view)") from exc
        widths = [int(h) for h in hidden]
        if not widths or min(widths) < 1:
            raise ValueError(f"hidden must be a non-empty list of positive widths, got {widths}")
        if activation not in _ACTIVATIONS:
            known = sorted(_ACTIVATIONS)
            raise ValueError(f"activation must be one of {known}, got {activation!r}")
        _check_rank(rank)
        self.n_candidates = layout["n"]
        self.whitened_dim = layout["whitened_dim"]
        self.n_receivers = n
        self.rank = rank
        self.pooled_dim = 2 * widths[-1]
        # CandidateScorer's constructor builds the per-candidate MLP: skip it, keep its interface
        BaseFeaturesExtractor.__init__(
            self, observation_space, features_dim=self.n_candidates + self.pooled_dim
        )
        self.act = _ACTIVATIONS[activation]()
        self.input_layer = nn.Linear(len(SOURCE_COLUMNS) + 1, widths[0])
        self.set_layers = nn.ModuleList(nn.Linear(a, b) for a, b in pairwise(widths))
        self.ctx_layers = nn.ModuleList(nn.Linear(a, b, bias=False) for a, b in pairwise(widths))
        # [q (k), s (k), leave a, move-source b, move-target c, swap d]; the policy initialises
        # it at gain 0.01 (every score starts near 0), key_head at the usual gain
        self.score_head = nn.Linear(widths[-1], 2 * rank + 4)
        self.key_head = nn.Linear(widths[-1], rank)
        self.pair_weights = nn.Parameter(th.zeros(2, N_PAIR_FEATURES))  # move, swap
        self.type_bias = nn.Parameter(th.zeros(4))  # no-op, leave, move, swap
        self.gain_skip = nn.Parameter(th.tensor(float(gain_skip_init)))
        i, j = edit_endpoints(n)
        n_move = n * n
        self.register_buffer("leave_rows", th.as_tensor(leave_rows(n)), persistent=False)
        self.register_buffer("swap_i", th.as_tensor(i[1 + n_move :]), persistent=False)
        self.register_buffer("swap_j", th.as_tensor(j[1 + n_move :]), persistent=False)
        self.register_buffer(
            "source_columns", th.as_tensor(np.asarray(SOURCE_COLUMNS)), persistent=False
        )
        self.register_buffer("diagonal", th.eye(n, dtype=th.bool), persistent=False)

    def receiver_table(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """The receivers' features ``u`` from the leave rows, ``(B, n, 8)`` (unsquashed)."""
        rows = observations["whitened"].index_select(1, self.leave_rows)  # (B, n, 17)
        return rows.index_select(2, self.source_columns)

    def scores(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """``[scores (B, N), pooled (B, 2 H)]`` concatenated, ``(B, N + 2 H)``."""
        raw = th.clamp(observations["gain"], min=0.0)  # (B, N)
        mask = observations["action_mask"] > 0.5  # (B, N)
        log_g = th.log(raw + 1e-6)
        top = log_g.masked_fill(~mask, -th.inf).amax(dim=1, keepdim=True)
        rel = th.where(mask, log_g - th.where(th.isfinite(top), top, 0.0), 0.0).clamp(min=-10.0)

        u = self.receiver_table(observations)  # (B, n, 8)
        b, n = u.shape[0], self.n_receivers
        budget = observations["budget_left"].reshape(b, 1, 1).expand(b, n, 1)
        h = self.act(self.input_layer(th.cat([_symlog(u), budget], dim=-1)))  # (B, n, H_1)
        for layer, ctx_layer in zip(self.set_layers, self.ctx_layers, strict=True):
            h = self.act(layer(h) + ctx_layer(h.mean(dim=1)).unsqueeze(1))
        pooled = th.cat([h.mean(dim=1), h.amax(dim=1)], dim=-1)  # (B, 2 H)

        k = self.rank
        heads = self.score_head(h)  # (B, n, 2k + 4)
        q, s = heads[..., :k], heads[..., k : 2 * k]
        leave, src, tgt, swp = heads[..., 2 * k :].unbind(dim=-1)  # each (B, n)
        key = self.key_head(h)  # (B, n, k)
        scale = 1.0 / math.sqrt(k)
        ls, cm = u[..., 0:2], u[..., 2:4]  # log sigma, cluster mean log sigma (B, n, 2)
        phi = th.log1p(
            th.cat(
                [
                    (ls.unsqueeze(2) - cm.unsqueeze(1)).abs(),
                    (ls.unsqueeze(2) - ls.unsqueeze(1)).abs(),
                    (cm.unsqueeze(2) - cm.unsqueeze(1)).abs(),
                ],
                dim=-1,
            )
        )  # (B, n, n, 6)
        pair = phi @ self.pair_weights.T  # (B, n, n, 2): move, swap
        bias = self.type_bias
        move = (
            th.bmm(q, key.transpose(1, 2)) * scale
            + src.unsqueeze(2)
            + tgt.unsqueeze(1)
            + pair[..., 0]
            + bias[2]
        )  # (B, n, n)
        move = th.where(self.diagonal, th.diag_embed(leave + bias[1]), move)
        sk = th.bmm(s, key.transpose(1, 2)) * scale + pair[..., 1] + swp.unsqueeze(2)  # (B, n, n)
        swap = (sk + sk.transpose(1, 2))[:, self.swap_i, self.swap_j] + bias[3]  # (B, P)
        noop = bias[0].expand(b, 1)
        scores = th.cat([noop, move.reshape(b, n * n), swap], dim=1) + self.gain_skip * rel
        scores = scores.masked_fill(~mask, MASKED_LOGIT)
        return th.cat([scores, pooled], dim=-1)


def scorer_policy_kwargs(
    scorer: str, rank: int = 16
) -> tuple[type[CandidateScorer], dict[str, Any]]:
    """``(features_extractor_class, extra extractor kwargs)`` of a ``--scorer`` choice.

    Raises:
        TypeError: ``rank`` is not an int.
        ValueError: ``scorer`` is not one of :data:`SCORERS`, or ``rank < 1``.
    """
    if scorer not in SCORERS:
        raise ValueError(f"scorer must be one of {list(SCORERS)}, got {scorer!r}")
    if scorer == "mlp":
        return CandidateScorer, {}
    _check_rank(rank)
    return FactorisedEditScorer, {"rank": rank}


# -- checkpoints ---------------------------------------------------------------------------------
def is_edit_architecture(metadata: dict[str, Any]) -> bool:
    """Whether a checkpoint's metadata names :class:`FactorisedEditScorer` (exact string).

    The string is compared under its current name
    (:func:`~selenv.learned.resources.current_class_name`), so checkpoints that recorded the
    class's earlier module path load too.
    """
    arch = metadata.get("architecture") if isinstance(metadata, dict) else None
    return (
        isinstance(arch, dict)
        and current_class_name(arch.get("features_extractor")) == EDIT_EXTRACTOR
    )


def edit_policy_spec(metadata: dict[str, Any], name: str = "") -> tuple[str, dict[str, Any]]:
    """``(algorithm, policy_kwargs)`` of a factorised checkpoint, from its JSON metadata only.

    The classes come from fixed tables (:data:`EDIT_EXTRACTOR`, the two candidate-scoring
    policies of :data:`~selenv.learned.rl.safe_load.POLICY_CLASSES`); the JSON only selects
    among them and gives numbers.

    Raises:
        ValueError: not a factorised architecture, an unknown algorithm or policy, or
            missing / malformed fields.
    """
    algo = _training_algorithm(metadata, name)
    cls = POLICY_CLASSES[algo]
    policy_name = f"{cls.__module__}.{cls.__name__}"
    arch = metadata.get("architecture")
    if not isinstance(arch, dict) or not is_edit_architecture(metadata):
        raise ValueError(
            f"checkpoint {name}: architecture features_extractor must be {EDIT_EXTRACTOR!r}"
        )
    if arch.get("policy", policy_name) != policy_name:
        raise ValueError(
            f"checkpoint {name}: architecture policy={arch.get('policy')!r:.120}; expected "
            f"{policy_name!r} for {algo}"
        )
    source = f"checkpoint {name}" if name else "checkpoint"
    extractor, net_arch = _common_architecture(arch, source)
    if "rank" not in arch:
        raise ValueError(f"{source}: incomplete architecture metadata: no 'rank'")
    rank = bounded_int(arch["rank"], "architecture.rank", "max_width", source)
    check_parameter_count(edit_scorer_parameters(extractor["hidden"], net_arch["vf"], rank), source)
    return algo, {
        "net_arch": net_arch,
        "features_extractor_class": FactorisedEditScorer,
        "features_extractor_kwargs": {**extractor, "rank": rank},
    }


def edit_scorer_parameters(hidden: list[int], vf: list[int], rank: int) -> int:
    """Parameters of a factorised edit policy (an upper estimate, before building it).

    The per-receiver DeepSets chain from ``len(SOURCE_COLUMNS) + 1`` inputs, the score and
    key heads (``3 rank + 4`` outputs), the pair weights and biases, the value MLP ``vf`` on
    the pooled ``2 H`` and its output; the scorer doubled for the critic's own copy.
    """
    chain = mlp_parameters([len(SOURCE_COLUMNS) + 1, *hidden])
    chain += sum(a * b for a, b in pairwise(hidden))
    scorer = chain + (hidden[-1] + 1) * (3 * rank + 4) + 2 * N_PAIR_FEATURES + 4 + 1
    value = mlp_parameters([2 * hidden[-1], *vf]) + (vf[-1] if vf else 2 * hidden[-1]) + 1
    return 2 * scorer + value


def build_edit_policy(
    metadata: dict[str, Any], name: str = ""
) -> CandidateScoringPolicy | CandidateScoringPPOPolicy:
    """A fresh factorised policy of the metadata's architecture on its training pool.

    Raises:
        ValueError: see :func:`edit_policy_spec`; a missing or malformed ``obs_layout``.
    """
    algo, policy_kwargs = edit_policy_spec(metadata, name)
    return build_on_training_pool(POLICY_CLASSES[algo], policy_kwargs, metadata, name)


def load_edit_policy(
    checkpoint: str | Path, metadata: dict[str, Any]
) -> CandidateScoringPolicy | CandidateScoringPPOPolicy:
    """The trained factorised policy of ``checkpoint``, in evaluation mode on the CPU.

    Rebuilt from the JSON (:func:`build_edit_policy`); the zip contributes only its
    ``policy.pth`` tensors (:func:`selenv.learned.rl.safe_load.read_weights`), loaded strictly.

    Raises:
        ValueError: see :func:`build_edit_policy` and ``read_weights``; weights that do not fit
            the architecture.
    """
    return load_policy(checkpoint, metadata, build=build_edit_policy)


def edit_model_from_checkpoint(
    checkpoint: str | Path, metadata: dict[str, Any], env: Any, **ppo_kwargs: Any
) -> MaskablePPO | PPO:
    """A new SB3 model on ``env`` (the edit view) holding a factorised checkpoint's weights.

    The counterpart of :func:`selenv.learned.rl.safe_load.model_from_checkpoint` (same safety:
    JSON for the architecture, ``weights_only`` tensors for the weights); the optimizer
    starts afresh.

    Raises:
        ValueError: as :func:`load_edit_policy`.
    """
    return model_from_checkpoint(checkpoint, metadata, env, spec=edit_policy_spec, **ppo_kwargs)
