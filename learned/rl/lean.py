"""Lean deterministic inference for the candidate-scoring policies (no SB3 ``predict``).

SB3's ``policy.predict`` costs far more than the network on the small candidate pools of the
selenv envs: it copies the observation dict, checks and preprocesses every key against the
space, builds a batch, constructs a (masked) ``Categorical`` distribution and takes its mode.
For a deterministic action that reduces to ``argmax`` of the per-candidate scores of
:class:`~learned.rl.candidate_policy.CandidateScorer` over the allowed candidates, which this
module evaluates directly: the scorer's own ``forward`` on tensors that share memory with the
numpy observation (``torch.from_numpy``, float32 as SB3 feeds it), under
``torch.inference_mode``. Same module, same float32 arithmetic, same mode (``argmax`` of
the masked categorical's probabilities, as SB3 takes it, so even float32 ties break alike),
so the action equals ``predict(..., deterministic=True)``; ``tests/test_lean_inference.py``
checks that on every step of episodes of every env with a shipped checkpoint.

Measured speed-ups are in ``docs/BENCHMARKS.md`` (``benchmarks/bench_policy_inference.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th

from learned.rl.candidate_policy import MASKED_LOGIT, OBS_KEYS, CandidateScorer

__all__ = ["LeanScorer"]


class LeanScorer:
    """Deterministic action of a candidate-scoring policy straight from its features extractor.

    Args:
        policy: a :class:`~learned.rl.candidate_policy.CandidateScoringPolicy` or
            ``CandidateScoringPPOPolicy`` (its ``pi_features_extractor`` is used, in eval mode).

    Raises:
        TypeError: the policy's actor features extractor is not a ``CandidateScorer``.
    """

    def __init__(self, policy: Any) -> None:
        extractor = getattr(policy, "pi_features_extractor", None)
        if not isinstance(extractor, CandidateScorer):
            raise TypeError(
                "policy must be a candidate-scoring policy (pi_features_extractor a "
                f"CandidateScorer), got {type(policy).__name__}"
            )
        self.scorer = extractor
        self.n = extractor.n_candidates

    def scores(self, cand: dict[str, np.ndarray], mask: np.ndarray) -> np.ndarray:
        """Per-candidate logits ``(N,)`` of one observation (masked entries at the masked logit).

        Args:
            cand: candidate-view observation (keys of ``OBS_KEYS``, unbatched).
            mask: ``(N,)`` bool, the allowed candidates (replaces ``cand["action_mask"]``, as
                the ``ppo`` agent does with the env's mask).
        """
        obs = {
            k: th.from_numpy(np.ascontiguousarray(cand[k], dtype=np.float32)[None])
            for k in OBS_KEYS
            if k != "action_mask"
        }
        obs["action_mask"] = th.from_numpy(mask.astype(np.float32)[None])
        with th.inference_mode():
            out = self.scorer(obs)
        return out[0, : mask.shape[0]].numpy()

    def _mode(self, cand: dict[str, np.ndarray], mask: np.ndarray) -> int:
        """The mode exactly as SB3 takes it: ``argmax`` of the (masked) categorical's probs."""
        obs = {
            k: th.from_numpy(np.ascontiguousarray(cand[k], dtype=np.float32)[None])
            for k in OBS_KEYS
            if k != "action_mask"
        }
        mask_t = th.from_numpy(mask[None])
        obs["action_mask"] = mask_t.to(th.float32)
        with th.inference_mode():
            logits = self.scorer(obs)[:, : mask.shape[0]]
            logits = th.where(mask_t, logits, th.tensor(MASKED_LOGIT, dtype=logits.dtype))
            probs = th.distributions.Categorical(logits=logits, validate_args=False).probs
            return int(th.argmax(probs, dim=1)[0])

    def action(self, cand: dict[str, np.ndarray], mask: np.ndarray) -> int:
        """``argmax`` of the scores over the allowed candidates (the first one on ties).

        Raises:
            ValueError: no candidate is allowed.
        """
        allowed = np.asarray(mask, dtype=bool)
        if not allowed.any():
            raise ValueError("no allowed action (empty action mask)")
        return self._mode(cand, allowed)
