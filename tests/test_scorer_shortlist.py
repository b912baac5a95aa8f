"""The candidate scorer's ``shortlist``: the network on the ``m`` best-gain unselected candidates.

Independent truth: the same weights without a shortlist, run on the observation cut down to
those ``m`` candidates (its context and pooled embedding are then over exactly them), must give
the shortlisted scorer's scores on them and its pooled embedding; every other candidate gets
the masked logit. A shortlist as large as the pool is the full scorer; checkpoints record it.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

torch = pytest.importorskip("torch")

import selenv  # noqa: E402, F401
from selenv.learned.rl.candidate_policy import MASKED_LOGIT, CandidateScorer  # noqa: E402
from selenv.learned.rl.safe_load import policy_spec  # noqa: E402

N = 80  # the pool at n_candidates=40 (its default preset: two sensors' candidates)


def _batch() -> tuple[gym.spaces.Dict, dict[str, torch.Tensor]]:
    env = gym.make("selenv/FIMSelection-v1", n_candidates=40, budget=6)
    rows, rng = [], np.random.default_rng(1)
    obs, info = env.reset(seed=3)
    for _ in range(5):  # 0 to 4 candidates already selected
        rows.append(obs)
        obs, _, _, _, info = env.step(int(rng.choice(np.flatnonzero(info["action_mask"]))))
    batch = {k: torch.as_tensor(np.stack([r[k] for r in rows]), dtype=torch.float32) for k in obs}
    assert batch["gain"].shape[1] == N
    return env.observation_space, batch


def _pair(space: gym.spaces.Dict, m: int) -> tuple[CandidateScorer, CandidateScorer]:
    torch.manual_seed(0)
    short = CandidateScorer(space, hidden=(16, 16), gain_skip_init=0.7, shortlist=m)
    full = CandidateScorer(space, hidden=(16, 16), gain_skip_init=0.7)
    full.load_state_dict(short.state_dict())
    return short, full


@pytest.mark.parametrize("m", [1, 8, 25])
def test_shortlist_scores_equal_the_full_scorer_on_the_cut_pool(m: int) -> None:
    space, batch = _batch()
    short, full = _pair(space, m)
    out = short(batch)
    scores, pooled = out[:, :N], out[:, N:]
    gain, allowed = batch["gain"].numpy(), batch["action_mask"].numpy() > 0.5
    for b in range(gain.shape[0]):
        # the m allowed candidates of largest gain (no ties in these draws)
        order = np.argsort(-np.where(allowed[b], gain[b], -1.0), kind="stable")[:m]
        keep = np.sort(order)
        cut = {k: v[b : b + 1] for k, v in batch.items()}
        cut = {k: (v[:, keep] if v.ndim >= 2 and v.shape[1] == N else v) for k, v in cut.items()}
        want = full(cut)
        torch.testing.assert_close(scores[b, keep], want[0, :m], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(pooled[b], want[0, m:], rtol=1e-6, atol=1e-6)
        rest = np.setdiff1d(np.arange(N), keep)
        assert torch.all(scores[b, rest] == MASKED_LOGIT)


def test_a_shortlist_as_large_as_the_pool_is_the_full_scorer() -> None:
    space, batch = _batch()
    short, full = _pair(space, N)
    torch.testing.assert_close(short(batch), full(batch), rtol=0, atol=0)


def test_bad_shortlists_are_refused_and_checkpoints_record_it() -> None:
    space, _ = _batch()
    for bad in (-1, 2.0, True):
        with pytest.raises(ValueError, match="shortlist"):
            CandidateScorer(space, shortlist=bad)
    arch = {
        "policy": "selenv.learned.rl.candidate_policy.CandidateScoringPolicy",
        "features_extractor": "selenv.learned.rl.candidate_policy.CandidateScorer",
        "hidden": [16, 16],
        "activation": "tanh",
        "net_arch": {"pi": [], "vf": [64]},
    }
    meta = {"architecture": arch, "obs_layout": {"whitened_dim": 14}}
    assert "shortlist" not in policy_spec(meta)[1]["features_extractor_kwargs"]
    meta["architecture"] = {**arch, "shortlist": 32}
    assert policy_spec(meta)[1]["features_extractor_kwargs"]["shortlist"] == 32
    meta["architecture"] = {**arch, "shortlist": -3}
    with pytest.raises(ValueError, match=r"architecture\.shortlist"):
        policy_spec(meta)
