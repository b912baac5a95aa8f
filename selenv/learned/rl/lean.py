"""Lean deterministic inference for the candidate-scoring policies (no SB3 ``predict``).

SB3's ``policy.predict`` costs far more than the network on the small candidate pools of the
selenv envs: it copies the observation dict, checks and preprocesses every key against the
space, builds a batch, constructs a (masked) ``Categorical`` distribution and takes its mode.
For a deterministic action that reduces to ``argmax`` of the per-candidate scores of
:class:`~selenv.learned.rl.candidate_policy.CandidateScorer` over the allowed candidates, which this
module evaluates directly: the scorer's own ``forward`` on tensors that share memory with the
numpy observation (``torch.from_numpy``, float32 as SB3 feeds it), under
``torch.inference_mode``. Same module, same float32 arithmetic, same mode (``argmax`` of
the masked categorical's probabilities, as SB3 takes it, so even float32 ties break alike),
so the action equals ``predict(..., deterministic=True)``; ``tests/test_lean_inference.py``
checks that on every step of episodes of every env with a shipped checkpoint.

Measured speed-ups are in ``docs/benchmarks/learned_selectors.md``
(``benchmarks/bench_policy_inference.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th

from selenv.learned.rl.candidate_policy import MASKED_LOGIT, OBS_KEYS, CandidateScorer

__all__ = ["LeanScorer"]


class LeanScorer:
    """Deterministic action of a candidate-scoring policy straight from its features extractor.

    Args:
        policy: a :class:`~selenv.learned.rl.candidate_policy.CandidateScoringPolicy` or
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


class TopMScorer:
    """Approximate deterministic action: the network scores only the ``m`` best-gain candidates.

    The policy's scores are dominated by the gain skip (``w r_k``) and the network refines
    the order among near-greedy candidates, so on large pools (``FIMSelection-v1`` at
    N = 1000) evaluating it on the ``m`` allowed candidates of largest ``gain`` -- in numpy,
    float32, the DeepSets context taken over those ``m`` -- gives nearly the full policy's
    choice at a fraction of its cost. Unlike :class:`LeanScorer` this is *not* the trained
    policy's exact action (the context differs); its quality is measured by ``selenv bench``
    (``ppo:top_m=32``, docs/benchmarks/learned_selectors.md).

    Args:
        policy: a candidate-scoring policy (see :class:`LeanScorer`).
        m: candidates scored per decision (>= 1).

    Raises:
        TypeError: not a candidate-scoring policy.
        ValueError: ``m < 1``.
    """

    def __init__(self, policy: Any, m: int) -> None:
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ValueError(f"top_m must be an int >= 1, got {m!r}")
        scorer = LeanScorer(policy).scorer
        self.m = m

        def w(layer: Any) -> tuple[np.ndarray, np.ndarray | None]:
            b = None if layer.bias is None else layer.bias.detach().numpy().astype(np.float32)
            return layer.weight.detach().numpy().astype(np.float32).T, b

        self.W1, self.b1 = w(scorer.input_layer)
        self.sets = [w(layer) for layer in scorer.set_layers]
        self.ctxs = [w(layer)[0] for layer in scorer.ctx_layers]
        self.head_w, head_b = w(scorer.score_head)
        self.head_b = np.zeros(1, np.float32) if head_b is None else head_b
        self.skip = np.float32(scorer.gain_skip.detach().item())
        self.act = np.tanh if isinstance(scorer.act, th.nn.Tanh) else (lambda x: np.maximum(x, 0))

    def action(self, cand: dict[str, np.ndarray], mask: np.ndarray) -> int:
        """The best of the ``m`` allowed candidates of largest gain, by the policy's scores.

        Raises:
            ValueError: no candidate is allowed.
        """
        allowed = np.flatnonzero(np.asarray(mask, dtype=bool))
        if allowed.size == 0:
            raise ValueError("no allowed action (empty action mask)")
        raw = np.maximum(np.asarray(cand["gain"], dtype=np.float32), 0.0)
        if allowed.size > self.m:
            part = np.argpartition(-raw[allowed], self.m - 1)[: self.m]
            idx = np.sort(allowed[part])
        else:
            idx = allowed
        return int(idx[int(np.argmax(self.scores(cand, idx)))])

    def scores(self, cand: dict[str, np.ndarray], idx: np.ndarray) -> np.ndarray:
        """The policy's scores ``(len(idx),)`` of the candidates ``idx`` (context over them)."""
        raw = np.maximum(np.asarray(cand["gain"], dtype=np.float32), 0.0)
        g = raw[idx]
        log_g = np.log(g + np.float32(1e-6))
        rel = np.maximum(log_g - log_g.max(), np.float32(-10.0))
        white = np.asarray(cand["whitened"], dtype=np.float32)[idx]
        x = np.concatenate(
            [
                np.log1p(g)[:, None],
                rel[:, None],
                np.sign(white) * np.log1p(np.abs(white)),
                np.asarray(cand["features"], dtype=np.float32)[idx],
                np.asarray(cand["selected"], dtype=np.float32)[idx, None],
                np.broadcast_to(
                    np.asarray(cand["budget_left"], dtype=np.float32).reshape(1, -1),
                    (idx.size, 1),
                ),
            ],
            axis=1,
        )
        h = self.act(x @ self.W1 + self.b1)
        for (W, b), U in zip(self.sets, self.ctxs, strict=True):
            h = self.act(h @ W + b + h.mean(axis=0) @ U)
        return np.asarray((h @ self.head_w)[:, 0] + self.head_b[0] + self.skip * rel)
