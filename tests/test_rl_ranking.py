"""Ranking pre-training (selenv.learned.rl.ranking) and the verified top-k policy agent."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from selenv.agents import make
from selenv.families.clustering.env import apply_edit, edit_mask
from selenv.learned.families.clustering import clustering_edit_deltas, collect_clustering_ranking
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent
from selenv.learned.rl.candidate_policy import make_maskable_ppo
from selenv.learned.rl.ranking import RankingData, fit_ranking, listnet_targets
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.train import train_clustering_dagger, train_clustering_ppo

CLU_ID = "selenv/ReceiverClustering-v1"
FIM_ID = "selenv/FIMSelection-v1"


def _play_final(agent: SB3PolicyAgent) -> float:
    env = gym.make(CLU_ID, n_agents=9, horizon=4)
    obs, info = env.reset(seed=2)
    agent.reset(env, seed=2)
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(agent.act(obs, info))
        done = terminated or truncated
    return float(info["objective"])


def test_listnet_targets_closed_form() -> None:
    d = np.array([[0.0, 1.0, np.inf, -1.0], [2.0, 2.0, 2.0, np.inf]])
    q = listnet_targets(d, temperature=0.5)
    allowed = np.array([0.0, 1.0, -1.0])
    z = -(allowed - allowed.min()) / (0.5 * allowed.std())
    expect = np.exp(z) / np.exp(z).sum()
    np.testing.assert_allclose(q[0, [0, 1, 3]], expect, rtol=1e-12)
    assert q[0, 2] == 0.0 and q[1, 3] == 0.0
    np.testing.assert_allclose(q[1, :3], 1.0 / 3.0)  # ties: uniform
    with pytest.raises(ValueError, match="temperature must be > 0"):
        listnet_targets(d, 0.0)
    with pytest.raises(ValueError, match="at least one allowed action"):
        listnet_targets(np.full((1, 3), np.inf), 1.0)


def test_edit_deltas_match_single_evaluations_and_greedy() -> None:
    env = gym.make(CLU_ID, n_agents=9, horizon=20, action_mode="edit")
    env.reset(seed=4)
    for _ in range(3):
        env.step(0)
    bank = env.unwrapped.bank
    d = clustering_edit_deltas(env)
    mask = edit_mask(bank.labels, env.unwrapped.max_size)
    assert np.array_equal(np.isfinite(d), mask) and d[0] == 0.0
    keep = bank.cost().J
    for a in np.flatnonzero(mask)[1:12]:
        single = float(bank.evaluate(apply_edit(bank.labels, int(a)))[0])
        np.testing.assert_allclose(d[a], single - keep, rtol=1e-10, atol=1e-14)
    greedy = make("greedy", CLU_ID, every=1)
    greedy.reset(env, seed=0)
    expected = int(np.argmin(d)) if d.min() < 0 else 0
    assert greedy.act(None, {}) == expected


def test_ranking_fit_learns_the_oracle_order() -> None:
    """On labelled states the fitted policy's top edit is much closer to the oracle's best."""
    kwargs = {"n_agents": 6, "horizon": 60, "preset": "paper"}
    data = collect_clustering_ranking(kwargs, 120, seed=0, label_every=1, workers=1,
                                      explore=0.3, progress=False)  # fmt: skip
    assert len(data) == 120 and data.deltas.shape[1] == 1 + 36 + 15
    env = gym.make(CLU_ID, **kwargs, action_mode="edit")
    env = CandidateViewWrapper(env, view_for(CLU_ID, env))
    model = make_maskable_ppo(env, seed=0)
    before = fit_ranking(model.policy, data, epochs=1, learning_rate=1e-9, val_fraction=0.0,
                         progress=False)  # fmt: skip
    after = fit_ranking(model.policy, data, epochs=40, learning_rate=3e-3, val_fraction=0.0,
                        progress=False)  # fmt: skip
    assert after["cross_entropy"] < before["cross_entropy"] - 0.5
    assert after["regret"] < 0.6 * before["regret"]
    assert after["top1"] > before["top1"]
    with pytest.raises(ValueError, match="every obs entry"):
        RankingData({"gain": data.obs["gain"][:3]}, data.deltas)


def test_clustering_script_ranks_then_verifies(tmp_path: Path) -> None:
    out = tmp_path / "clu_rank.zip"
    meta = train_clustering_ppo.main(
        [
            "--n-envs=1",
            "--vec-env=dummy",
            "--no-progress",
            "--total-timesteps=0",
            '--env-kwargs={"n_agents": 9, "horizon": 10}',
            "--rank-states=30",
            "--rank-epochs=2",
            "--rank-workers=2",  # spawned worker processes
            "--rank-horizon=20",
            "--eval-episodes=1",
            "--eval-horizon=10",
            "--baselines=ga",
            "--verify-top-k=2",
            f"--out={out}",
            "--tensorboard-dir=",
        ]
    )
    assert meta["pretraining"]["states_train"] == 27 and meta["training"]["timesteps_done"] == 0
    agents = meta["metrics"]["agents"]
    assert set(agents) == {"ppo", "ppo_top2", "ga"}
    assert agents["ppo"]["cost_evaluations_per_decision"] == 0.0
    assert 0.0 < agents["ppo_top2"]["cost_evaluations_per_decision"] <= 2.0
    assert agents["ga"]["cost_evaluations_per_decision"] >= 19.0
    top2 = SB3PolicyAgent(out, env_id=CLU_ID, verify_top_k=2)
    env = gym.make(CLU_ID, n_agents=9, horizon=5)
    obs, info = env.reset(seed=1)
    top2.reset(env, seed=1)
    labels = top2.act(obs, info)
    j_new = float(env.unwrapped.bank.evaluate(labels)[0])
    assert j_new <= env.unwrapped.bank.cost().J  # never plays a worsening edit
    # DAgger: the trained policy drives the labelling trajectories, the exact costs label them
    dagger = collect_clustering_ranking({"n_agents": 9, "horizon": 12}, 6, seed=3, workers=1,
                                        label_every=2, explore=0.0, progress=False,
                                        behaviour=str(out), behaviour_top_k=2)  # fmt: skip
    assert len(dagger) == 6 and np.all(dagger.deltas[:, 0] == 0.0)
    assert np.array_equal(np.isfinite(dagger.deltas), dagger.obs["action_mask"].astype(bool))
    # the DAgger script: the checkpoint drives, the exact costs label, the logits are refitted
    dag = train_clustering_dagger.main(
        [
            f"--checkpoint={out}",
            f"--out={tmp_path / 'dagger.zip'}",
            '--env-kwargs={"n_agents": 9, "horizon": 10}',
            "--states=8",
            "--epochs=1",
            "--workers=1",
            "--no-progress",
            "--eval-episodes=1",
            "--verify-top-k=2",
            "--baselines=",
        ]
    )
    assert dag["dagger"]["states_train"] == 7 and set(dag["metrics"]["agents"]) == {
        "ppo",
        "ppo_top2",
    }
    assert np.isfinite(_play_final(SB3PolicyAgent(tmp_path / "dagger.zip", env_id=CLU_ID)))
    with pytest.raises(ValueError, match="was trained on 'selenv/FIMSelection-v1'"):
        train_clustering_dagger.main(
            [
                f"--checkpoint={DEFAULT_CHECKPOINTS[FIM_ID]}",
                f"--out={tmp_path / 'x.zip'}",
                "--no-progress",
            ]
        )
    with pytest.raises(ValueError, match="no exact verification"):
        fim = SB3PolicyAgent(env_id="selenv/FIMSelection-v1", verify_top_k=3)
        fim.reset(gym.make("selenv/FIMSelection-v1"), seed=0)
    with pytest.raises(ValueError, match="verify_top_k must be an int >= 0"):
        SB3PolicyAgent(out, env_id=CLU_ID, verify_top_k=-1)


def test_fit_metrics_with_unlabelled_actions_are_finite_json() -> None:
    """Labellers that score only their candidates (dJ = +inf elsewhere): no infinite regret."""
    import json

    import torch as th

    from selenv.learned.families.landmarks import LANDMARK_ID, collect_landmark_rollout_labels

    data = collect_landmark_rollout_labels(
        {}, 16, seed=0, horizon=1, labeller="fast_rollout", progress=False
    )
    assert (~np.isfinite(data.deltas)).any()
    env = gym.make(LANDMARK_ID)
    model = make_maskable_ppo(CandidateViewWrapper(env, view_for(LANDMARK_ID, env)), seed=0)
    metrics = fit_ranking(model.policy, data, epochs=1, val_fraction=0.0, progress=False)
    json.dumps(metrics, allow_nan=False)  # strict JSON: no Infinity
    obs = {k: th.as_tensor(v, dtype=th.float32) for k, v in data.obs.items()}
    with th.no_grad():
        top = model.policy.pi_features_extractor(obs)[:, : data.deltas.shape[1]].argmax(1)
    picked = data.deltas[np.arange(len(data)), top.numpy()]
    labelled = np.isfinite(picked)
    assert metrics["top_unlabelled"] == round(float(np.mean(~labelled)), 4)
    if labelled.any():
        best = data.deltas.min(axis=1)
        assert metrics["regret"] == pytest.approx(float(np.mean((picked - best)[labelled])))
    else:
        assert metrics["regret"] is None
