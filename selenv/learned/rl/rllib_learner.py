"""RLlib's PPO learner with advantages standardised over the steps that enter the loss.

RLlib's new-API PPO (``GeneralAdvantageEstimation`` learner connector) standardises the
advantages over the whole train batch **including** the one artificial timestep that
``AddOneTsToEpisodesAndTruncate`` appends to every (single-agent) episode chunk for value
bootstrapping. Those rows are excluded from the loss by ``Columns.LOSS_MASK``, but their
"advantages" (``-V(s_T)`` of an observation the value function is never trained on) still
enter the mean and the standard deviation. With long episodes the bias is negligible; in
selenv's multi-agent envs an agent's episode is a handful of decisions (``fim_selection_v0``:
5 per agent, so 1 row in 6 is artificial), and the junk rows shift every real advantage by a
constant and inflate the scale that divides them: the policy gradient of the real decisions is
shrunk and swamped by noise (measured on ``fim_selection_v0``: the real rows' mean advantage
at -0.11 to -0.16 standard deviations after the first iterations, a positive policy loss of
0.2-0.4 per minibatch later on, where a PPO update drives it to or below 0). Reported upstream
at https://github.com/ray-project/ray/issues/57989 (open in Ray 2.60).

:class:`MaskedAdvantagePPOTorchLearner` re-standardises the advantages over the loss-masked
rows of every minibatch before RLlib's loss::

    A_k <- (A_k - mean_{j in M} A_j) / (std_{j in M} A_j + 1e-8)      k in M (the mask)

which is what Stable-Baselines3's PPO does (``normalize_advantage=True``: per minibatch, over
real steps only). Rows outside the mask are set to 0 (they contribute nothing either way).
Everything else is RLlib's ``PPOTorchLearner``. Selected with ``--advantage-norm masked`` of
:mod:`selenv.train.train_rllib_marl` (``PPOConfig.training(learner_class=...)``).
"""

from __future__ import annotations

from typing import Any

import torch as th
from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing

__all__ = ["MaskedAdvantagePPOTorchLearner", "masked_standardize"]


def masked_standardize(advantages: th.Tensor, mask: th.Tensor | None) -> th.Tensor:
    """Standardise ``advantages`` (shape ``(B,)``) over the rows where ``mask`` is true.

    ``mask`` (bool, ``(B,)``) ``None`` means every row. Rows outside the mask become 0. As
    SB3's PPO: ``(A - mean) / (std + 1e-8)`` with the unbiased standard deviation; a single
    masked row (no spread) becomes its centred value 0.
    """
    if mask is None:
        mask = th.ones_like(advantages, dtype=th.bool)
    mask = mask.to(th.bool)
    n = int(mask.sum())
    if n == 0:
        return th.zeros_like(advantages)
    real = advantages[mask]
    mean = real.mean()
    std = real.std() if n > 1 else real.new_tensor(0.0)
    out = th.zeros_like(advantages)
    out[mask] = (real - mean) / (std + 1e-8)
    return out


class MaskedAdvantagePPOTorchLearner(PPOTorchLearner):
    """``PPOTorchLearner`` whose minibatch advantages are standardised over the loss mask."""

    def compute_loss_for_module(
        self, *, module_id: Any, config: Any, batch: dict[str, Any], fwd_out: dict[str, Any]
    ) -> Any:
        """RLlib's PPO loss on ``batch`` with :func:`masked_standardize`-d advantages."""
        key = Postprocessing.ADVANTAGES
        if key in batch:
            batch = dict(batch)  # the epochs reuse the batch: leave it unchanged
            batch[key] = masked_standardize(batch[key], batch.get(Columns.LOSS_MASK))
        return super().compute_loss_for_module(
            module_id=module_id, config=config, batch=batch, fwd_out=fwd_out
        )
