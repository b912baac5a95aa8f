"""The learned FIM-selection policy: training entry point, equivariance, checkpoint loading."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

import selenv  # noqa: F401  (registers the env ids and baseline agents)
from selenv.agents import agents_for, make
from selenv.families.fim.env import fim_observation_space
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent, make_ppo_agent
from selenv.learned.rl.candidate_policy import CandidateScoringPolicy, make_maskable_ppo
from selenv.train import train_fim_ppo

DEFAULT_CHECKPOINT = DEFAULT_CHECKPOINTS["selenv/FIMSelection-v1"]
ENV_ID = "selenv/FIMSelection-v1"
META_KEYS = {
    "env_id",
    "env_kwargs",
    "architecture",
    "obs_layout",
    "training",
    "metrics",
    "selenv_version",
    "torch_version",
    "sb3_version",
}

torch.set_num_threads(1)


def _policy(env: gym.Env, seed: int = 0) -> CandidateScoringPolicy:
    torch.manual_seed(seed)
    policy = CandidateScoringPolicy(env.observation_space, env.action_space, lambda _: 3e-4)
    with torch.no_grad():  # move away from the near-uniform init so the logits differ
        for p in policy.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return policy.eval()


def _obs_after_picks(env: gym.Env, seed: int, picks: int) -> dict[str, np.ndarray]:
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(picks):
        obs, *_, info = env.step(int(rng.choice(np.flatnonzero(info["action_mask"]))))
    return obs


def _logits_and_value(policy: CandidateScoringPolicy, obs: dict[str, np.ndarray]):
    tensor, _ = policy.obs_to_tensor(obs)
    with torch.no_grad():
        dist = policy.get_distribution(tensor, action_masks=obs["action_mask"].astype(bool))
        return dist.distribution.logits[0].numpy(), policy.predict_values(tensor)[0, 0].item()


def _play(agent, env: gym.Env, seed: int) -> float:
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    done = False
    while not done:
        action = agent.act(obs, info)
        assert info["action_mask"][action], f"{agent.name} took masked action {action}"
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    return info["objective"]


# -- training entry point ---------------------------------------------------------------------
def test_short_training_writes_zip_and_metadata(tmp_path: Path) -> None:
    out = tmp_path / "ckpt" / "tiny.zip"
    meta = train_fim_ppo.main(
        [
            '--env-kwargs={"preset": "example2_moving", "n_candidates": 10, "budget": 3}',
            "--total-timesteps=256",
            "--n-envs=2",
            "--n-steps=64",
            "--batch-size=64",
            "--n-epochs=2",
            "--eval-episodes=2",
            f"--out={out}",
            f"--tensorboard-dir={tmp_path / 'runs'}",
            "--no-progress",
        ]
    )
    assert out.is_file()
    on_disk = json.loads(out.with_suffix(".json").read_text())
    assert on_disk == meta
    assert META_KEYS <= set(meta)
    assert meta["env_id"] == ENV_ID
    assert meta["env_kwargs"] == {"preset": "example2_moving", "n_candidates": 10, "budget": 3}
    assert meta["obs_layout"] == {
        "m": 2,
        "d": 7,
        "whitened_dim": 14,
        "n_features": 4,
        "n_candidates_trained": 20,
    }
    assert meta["training"]["total_timesteps"] >= 256 and meta["training"]["seed"] == 0
    assert meta["training"]["wall_seconds"] > 0
    metrics = meta["metrics"]
    assert set(metrics["agents"]) == {"ppo", "greedy", "random"}
    for res in metrics["agents"].values():
        assert np.isfinite(res["mean_final_objective"]) and len(res["returns"]) == 2
    assert metrics["episodes"] == 2
    assert any((tmp_path / "runs").rglob("events.out.tfevents.*"))
    # the written checkpoint plays its env through the agent
    env = gym.make(ENV_ID, n_candidates=10, budget=3)
    assert np.isfinite(_play(SB3PolicyAgent(out), env, seed=1))


def test_bad_config_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"must end in \.zip"):
        train_fim_ppo.main([f"--out={tmp_path / 'x.pt'}", "--no-progress"])


# -- the policy -------------------------------------------------------------------------------
def test_logits_are_permutation_equivariant() -> None:
    env = gym.make(ENV_ID, n_candidates=8, budget=5)
    policy = _policy(env)
    obs = _obs_after_picks(env, seed=3, picks=2)
    perm = np.random.default_rng(0).permutation(env.action_space.n)
    permuted = {k: (v if k == "budget_left" else v[perm]) for k, v in obs.items()}
    logits, value = _logits_and_value(policy, obs)
    logits_p, value_p = _logits_and_value(policy, permuted)
    allowed = obs["action_mask"].astype(bool)
    assert np.isfinite(logits[allowed]).all() and np.ptp(logits[allowed]) > 1e-3
    np.testing.assert_allclose(logits_p, logits[perm], rtol=1e-5, atol=1e-5)
    assert value_p == pytest.approx(value, rel=1e-5, abs=1e-5)


def test_weights_do_not_depend_on_pool_size() -> None:
    small = gym.make(ENV_ID, n_candidates=5, budget=3)  # N = 10
    large = gym.make(ENV_ID, n_candidates=40, budget=3)  # N = 80
    p_small, p_large = _policy(small), _policy(large, seed=1)
    shapes = {k: tuple(v.shape) for k, v in p_small.state_dict().items()}
    assert shapes == {k: tuple(v.shape) for k, v in p_large.state_dict().items()}
    p_large.load_state_dict(p_small.state_dict())  # strict: same parameters
    for env, policy in ((small, p_small), (large, p_large)):
        obs = _obs_after_picks(env, seed=0, picks=1)
        action, _ = policy.predict(obs, action_masks=obs["action_mask"].astype(bool))
        assert obs["action_mask"][int(action)]
    # one candidate's score sees the pool only through the pooled context: a pool that
    # repeats every candidate twice has the same mean/max, hence the same scores
    obs = _obs_after_picks(small, seed=0, picks=1)
    doubled = {k: (v if k == "budget_left" else np.concatenate([v, v])) for k, v in obs.items()}
    p20 = CandidateScoringPolicy(
        **{
            **p_small._get_constructor_parameters(),
            "observation_space": fim_observation_space(20, 2, 7),
            "action_space": spaces.Discrete(20),
        }
    ).eval()
    p20.load_state_dict(p_small.state_dict())
    logits, value = _logits_and_value(p_small, obs)
    logits2, value2 = _logits_and_value(p20, doubled)
    # (the distribution normalises its logits: doubling the pool shifts them all by log 2)
    np.testing.assert_allclose(
        logits2 - logits2.max(), np.concatenate([logits, logits]) - logits.max(), atol=1e-5
    )
    assert value2 == pytest.approx(value, rel=1e-5, abs=1e-5)


def test_make_maskable_ppo_defaults() -> None:
    env = gym.make(ENV_ID, n_candidates=5, budget=2)
    model = make_maskable_ppo(env, n_steps=16, batch_size=16)
    assert model.gamma == 1.0
    assert isinstance(model.policy, CandidateScoringPolicy)
    with pytest.raises(ValueError, match="net_arch"):
        make_maskable_ppo(env, policy_kwargs={"net_arch": {"pi": [64], "vf": [64]}})


# -- the shipped checkpoint -------------------------------------------------------------------
def test_shipped_checkpoint_is_competitive_with_greedy() -> None:
    env = gym.make(ENV_ID)
    meta = json.loads(DEFAULT_CHECKPOINT.with_suffix(".json").read_text())
    assert META_KEYS <= set(meta)
    assert DEFAULT_CHECKPOINT.stat().st_size < 1_000_000
    seeds = range(20_000, 20_005)
    scores = {}
    for name, agent in (
        ("ppo", make_ppo_agent()),
        ("greedy", make("greedy", ENV_ID)),
        ("random", make("random", ENV_ID)),
    ):
        scores[name] = np.mean([_play(agent, env, seed) for seed in seeds])
    assert scores["ppo"] >= scores["random"]
    assert scores["ppo"] >= 0.95 * scores["greedy"], scores


def test_shipped_checkpoint_runs_on_another_pool_size() -> None:
    agent = SB3PolicyAgent()
    for n_candidates, budget in ((10, 4), (150, 12)):
        env = gym.make(ENV_ID, n_candidates=n_candidates, budget=budget)
        assert np.isfinite(_play(agent, env, seed=7))


def test_registered_as_ppo() -> None:
    # selenv registers the lazy factory; building it imports selenv.learned.rl.agent and loads
    # the file
    assert "ppo" in agents_for(ENV_ID)
    agent = make("ppo", ENV_ID)  # the record's agent, wrapping the loader's
    assert isinstance(agent.inner, SB3PolicyAgent) and agent.name == "ppo"
    assert agent.checkpoint.name == "fim_selection_ppo_general.zip"  # the shipped record
    own = make(f"ppo:{DEFAULT_CHECKPOINT}", ENV_ID)  # the family's default weights, as a file
    assert own.checkpoint == DEFAULT_CHECKPOINT


# -- mismatches are ValueErrors ---------------------------------------------------------------
def test_env_with_another_whitened_width_is_rejected() -> None:
    env = gym.make(ENV_ID, preset="example3_moving", n_candidates=10, budget=3)  # d = 8
    agent = SB3PolicyAgent()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"fim_selection_ppo\.zip.*d=7.*this env has m=2, d=8"):
        agent.reset(env, seed=0)
    obs, info = env.reset(seed=0)
    with pytest.raises(ValueError, match="whitened width 16"):
        agent.act(obs, info)


def _copy_checkpoint(tmp_path: Path) -> Path:
    zip_path = tmp_path / "copy.zip"
    shutil.copy(DEFAULT_CHECKPOINT, zip_path)
    shutil.copy(DEFAULT_CHECKPOINT.with_suffix(".json"), zip_path.with_suffix(".json"))
    return zip_path


def test_metadata_disagreeing_with_model_is_rejected(tmp_path: Path) -> None:
    zip_path = _copy_checkpoint(tmp_path)
    meta = json.loads(zip_path.with_suffix(".json").read_text())
    meta["obs_layout"].update(d=8, whitened_dim=16)
    zip_path.with_suffix(".json").write_text(json.dumps(meta))
    # the policy is rebuilt from the metadata (safe_load): a wrong width cannot take the weights
    with pytest.raises(
        ValueError, match=r"(?s)copy\.zip: weights do not fit its metadata.*size mismatch"
    ):
        SB3PolicyAgent(zip_path)
    meta["obs_layout"] = {"m": 2, "d": 7, "whitened_dim": 15}
    zip_path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="whitened_dim=15 != m\\*d"):
        SB3PolicyAgent(zip_path)
    meta["obs_layout"] = {"m": 2, "d": 7, "whitened_dim": 14, "n_candidates_trained": 50}
    zip_path.with_suffix(".json").write_text(json.dumps(meta))
    SB3PolicyAgent(zip_path)  # pool-size independent weights: any build size takes them
    meta["obs_layout"]["n_candidates_trained"] = 200
    meta["env_id"] = "selenv/LandmarkSelection-v1"
    zip_path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="trained on 'selenv/LandmarkSelection-v1'"):
        SB3PolicyAgent(zip_path)
    del meta["obs_layout"]
    zip_path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="lacks an obs_layout object"):
        SB3PolicyAgent(zip_path)


def test_missing_or_broken_files_are_value_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not found"):
        SB3PolicyAgent(tmp_path / "nope.zip")
    zip_path = _copy_checkpoint(tmp_path)
    zip_path.with_suffix(".json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        SB3PolicyAgent(zip_path)
    zip_path.with_suffix(".json").unlink()
    with pytest.raises(ValueError, match=r"copy\.json not found"):
        SB3PolicyAgent(zip_path)
    shutil.copy(DEFAULT_CHECKPOINT.with_suffix(".json"), zip_path.with_suffix(".json"))
    zip_path.write_bytes(b"this is not a zip file")
    with pytest.raises(ValueError, match=r"copy\.zip is not a readable zip"):
        SB3PolicyAgent(zip_path)
