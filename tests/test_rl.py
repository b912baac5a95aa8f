"""RL glue (selenv.learned.rl): candidate views, PettingZoo -> SB3 parameter sharing, training
scripts,
the policy-as-agent adapter on every env it serves."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.test import parallel_api_test  # noqa: F401  (the wrapped env passes it)

from selenv.agents import make
from selenv.families.cooperative.view import CLView
from selenv.families.fim.agents import CooperativeGreedyPolicy
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent
from selenv.learned.rl.candidate_policy import (
    MASKED_LOGIT,
    CandidateScoringPPOPolicy,
    make_maskable_ppo,
    make_ppo,
    obs_layout,
)
from selenv.learned.rl.marl import SharedPolicyEnv
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.multiagent import fim_selection_v0
from selenv.train import (
    train_cl_ppo,
    train_clustering_ppo,
    train_fim_marl,
    train_fim_ppo,
    train_landmark_ppo,
)

CL_ID = "selenv/CLScheduling-v1"
LM_ID = "selenv/LandmarkSelection-v1"
CLU_ID = "selenv/ReceiverClustering-v1"
FIM_ID = "selenv/FIMSelection-v1"
TINY = ["--n-envs=2", "--n-steps=64", "--batch-size=64", "--n-epochs=1", "--no-progress"]


def _play(agent, env, seed: int) -> tuple[float, float]:
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    total, done = 0.0, False
    while not done:
        obs, r, terminated, truncated, info = env.step(agent.act(obs, info))
        total += float(r)
        done = terminated or truncated
    return total, float(info["objective"])


# -- candidate views --------------------------------------------------------------------------
def test_cl_view_rows_are_the_pairs() -> None:
    env = gym.make(CL_ID, n_agents=3, horizon=5)
    obs, _ = env.reset(seed=0)
    view = view_for(CL_ID, env)
    assert isinstance(view, CLView)
    cand = view(obs)
    space = view.space(env.observation_space)
    assert space.contains(cand)
    P = len(env.unwrapped.pairs)
    assert cand["whitened"].shape == (P + 1, 4) and obs_layout(space)["n"] == P + 1
    for p, (i, j) in enumerate(env.unwrapped.pairs):
        assert cand["whitened"][p, 0] == pytest.approx(obs["logdet"][i])
        assert cand["whitened"][p, 1] == pytest.approx(obs["logdet"][j])
        assert cand["gain"][p] == pytest.approx(obs["pair_gain"][p])
    assert cand["features"][P, 0] == 1.0 and np.all(cand["features"][:P, 0] == 0.0)
    assert np.array_equal(cand["action_mask"], obs["action_mask"])
    with pytest.raises(ValueError, match="no candidate view"):
        view_for("selenv/Unknown-v0", env)


def test_cl_fused_view_carries_greedys_previewed_gains() -> None:
    env = gym.make(CL_ID, n_agents=3, budget=2, horizon=5)
    obs, info = env.reset(seed=3)
    view = view_for(CL_ID, env, "cl_pairs_fused")
    assert view.name == "cl_pairs_fused"
    cand = view(obs)
    allowed = np.flatnonzero(obs["action_mask"][:-1])
    assert allowed.size > 0
    expect = [max(env.unwrapped.preview_gain(int(p)), 0.0) for p in allowed]
    np.testing.assert_allclose(cand["gain"][allowed], expect, rtol=1e-6)
    assert cand["gain"][-1] == 0.0  # stop
    greedy = make("greedy", CL_ID)
    greedy.reset(env, seed=3)
    g = cand["gain"][:-1]
    assert greedy.act(obs, info) == (int(np.argmax(g)) if g.max() > 0 else len(g))
    with pytest.raises(ValueError, match="no candidate view 'nope'"):
        view_for(CL_ID, env, "nope")


def test_clustering_view_matches_the_edit_encoding() -> None:
    """The view's mask is the env's edit mask; in assignment mode its actions are the edits."""
    from selenv.families.clustering.env import apply_edit

    edit = gym.make(CLU_ID, n_agents=9, horizon=5, action_mode="edit")
    obs, _ = edit.reset(seed=2)
    view = view_for(CLU_ID, edit)
    cand = view(obs)
    assert view.space(edit.observation_space).contains(cand)
    assert np.array_equal(cand["action_mask"].astype(bool), edit.unwrapped.action_masks())
    n = 9
    a_move, a_swap = 1 + 2 * n + 5, 1 + n * n + 3  # receiver 2 -> 5's cluster; swap pair 3
    assert cand["features"][a_move, 1] == 1.0 and cand["features"][a_swap, 2] == 1.0
    np.testing.assert_allclose(cand["whitened"][a_move, 0:2], np.log(obs["sigma"][2]), rtol=1e-6)
    np.testing.assert_allclose(cand["whitened"][a_move, 2:4], np.log(obs["sigma"][5]), rtol=1e-6)
    assign = gym.make(CLU_ID, n_agents=9, horizon=5)
    obs_a, _ = assign.reset(seed=2)
    view_a = view_for(CLU_ID, assign)
    allowed = np.flatnonzero(view_a(obs_a)["action_mask"])
    labels = view_a.env_action(obs_a, int(allowed[-1]))
    assert np.array_equal(labels, apply_edit(obs_a["assignment"], int(allowed[-1])))
    assign.step(labels)  # a feasible clustering the env accepts


def test_view_wrapper_passes_gym_and_sb3_checks() -> None:
    from stable_baselines3.common.env_checker import check_env

    # budget 1: each step opens with every action allowed (the checkers act unmasked)
    env = gym.make(CL_ID, n_agents=2, budget=1, fusion="naive", horizon=5)
    wrapped = CandidateViewWrapper(env, view_for(CL_ID, env))
    with pytest.warns(UserWarning, match="unconventional shape"):  # (N, F) candidate rows
        check_env(wrapped, skip_render_check=True)
    obs, _ = wrapped.reset(seed=1)
    assert np.array_equal(wrapped.action_masks(), obs["action_mask"].astype(bool))


# -- multi-agent parameter sharing ------------------------------------------------------------
@pytest.mark.parametrize("mode", ["cooperative", "independent"])
def test_shared_policy_env_reproduces_greedy(mode: str) -> None:
    """Greedy played turn by turn through the wrapper == greedy on the parallel env."""
    kwargs = {"n_candidates": 10, "budgets": 3, "mode": mode}
    penv = fim_selection_v0.parallel_env(**kwargs)
    greedy = CooperativeGreedyPolicy()
    obs, infos = penv.reset(seed=4)
    while penv.agents:
        obs, _, _, _, infos = penv.step(greedy.act(obs, penv.agents))
    expected = next(iter(infos.values()))["objective"]
    env = SharedPolicyEnv(fim_selection_v0.parallel_env(**kwargs))
    o, info = env.reset(seed=4)
    total, done, agents_seen = 0.0, False, set()
    start = info["objective"]
    while not done:
        agents_seen.add(info["agent"])
        gain = np.where(env.action_masks(), o["gain"], -np.inf)
        o, r, terminated, truncated, info = env.step(int(np.argmax(gain)))
        total += r
        done = terminated or truncated
    assert info["objective"] == pytest.approx(expected)
    assert total == pytest.approx(expected - start)  # the return is the team's gain
    assert agents_seen == {"agent_0", "agent_1"}  # one policy decided for both agents


def test_shared_policy_env_rejects_heterogeneous_agents() -> None:
    penv = fim_selection_v0.parallel_env(n_candidates=10, budgets=3)
    spaces_ = {"agent_0": spaces.Discrete(3), "agent_1": spaces.Discrete(4)}
    penv.action_space = lambda a: spaces_[a]  # type: ignore[method-assign]
    with pytest.raises(ValueError, match="one observation and action space"):
        SharedPolicyEnv(penv)


# -- training scripts end to end (tiny budgets) -----------------------------------------------
def test_landmark_training_script(tmp_path: Path) -> None:
    out = tmp_path / "lm.zip"
    meta = train_landmark_ppo.main(
        [
            *TINY,
            "--total-timesteps=128",
            "--vec-env=dummy",
            '--env-kwargs={"n_landmarks": 8, "k": 2, "horizon": 5}',
            "--eval-episodes=1",
            "--baselines=greedy",
            f"--out={out}",
            f"--tensorboard-dir={tmp_path / 'runs'}",
        ]
    )
    assert json.loads(out.with_suffix(".json").read_text()) == meta
    assert meta["env_id"] == LM_ID and meta["view"] == "identity"
    assert set(meta["metrics"]["agents"]) == {"ppo", "greedy"}
    assert any((tmp_path / "runs").rglob("events.out.tfevents.*"))


def test_cl_training_script_with_subprocess_envs(tmp_path: Path) -> None:
    out = tmp_path / "cl.zip"
    meta = train_cl_ppo.main(
        [
            *TINY,
            "--total-timesteps=128",
            "--vec-env=subproc",
            '--env-kwargs={"n_agents": 3, "budget": 1, "horizon": 6}',
            "--eval-episodes=1",
            "--baselines=greedy,random",
            f"--out={out}",
            "--tensorboard-dir=",
        ]
    )
    assert meta["view"] == "cl_pairs_fused" and meta["obs_layout"]["n_candidates_trained"] == 7
    agent = SB3PolicyAgent(out, env_id=CL_ID)
    for n_agents in (3, 4):  # the policy does not depend on the number of pairs
        env = gym.make(CL_ID, n_agents=n_agents, budget=1, horizon=4)
        assert np.isfinite(_play(agent, env, seed=3)[1])
    with pytest.raises(ValueError, match=r"cl\.zip was trained on 'selenv/CLScheduling-v1'"):
        SB3PolicyAgent(out, env_id=LM_ID)


def test_clustering_training_script(tmp_path: Path) -> None:
    out = tmp_path / "clu.zip"
    meta = train_clustering_ppo.main(
        [
            *TINY,
            "--total-timesteps=128",
            "--vec-env=dummy",
            '--env-kwargs={"n_agents": 9, "horizon": 10}',
            "--rank-states=0",  # PPO from scratch (the ranking stage: test_rl_ranking.py)
            "--verify-top-k=",
            "--eval-episodes=1",
            "--eval-horizon=8",
            "--baselines=fixed_random",
            f"--out={out}",
            "--tensorboard-dir=",
        ]
    )
    assert meta["view"] == "clustering_edits" and meta["eval_env_kwargs"]["horizon"] == 8
    assert meta["pretraining"] == {"method": None}
    assert set(meta["metrics"]["agents"]) == {"ppo", "fixed_random"}
    agent = SB3PolicyAgent(out, env_id=CLU_ID)  # plays the default (assignment) encoding
    assert np.isfinite(_play(agent, gym.make(CLU_ID, n_agents=12, horizon=4), seed=5)[1])


def test_marl_training_script(tmp_path: Path) -> None:
    out = tmp_path / "marl.zip"
    meta = train_fim_marl.main(
        [
            *TINY,
            "--total-timesteps=128",
            '--env-kwargs={"preset": "example3_moving", "n_candidates": 8, "budgets": 2}',
            "--eval-episodes=2",
            f"--out={out}",
            "--tensorboard-dir=",
        ]
    )
    finals = meta["metrics"]["mean_final_objective"]
    assert set(finals) == {
        "shared_ppo_cooperative",
        "shared_ppo_independent",
        "cooperative_greedy",
        "independent_greedy",
    }
    assert all(np.isfinite(v) for v in finals.values())
    assert meta["marl"]["path"] == "selenv.learned.rl.marl.SharedPolicyEnv"
    # --eval-only re-evaluates the saved checkpoint on its own env kwargs: same numbers
    again = train_fim_marl.main(["--eval-only", "--eval-episodes=2", f"--out={out}", "--force"])
    assert again["metrics"] == meta["metrics"]


def test_plain_ppo_never_samples_a_masked_candidate() -> None:
    """PPO has no action_masks argument: the policy masks its logits from the observation."""
    env = gym.make(FIM_ID, n_candidates=6, budget=3)
    model = make_ppo(env, "ppo", seed=0, n_steps=32, batch_size=32)
    assert isinstance(model.policy, CandidateScoringPPOPolicy)
    obs, _ = env.reset(seed=1)
    for a in (0, 4):
        obs, *_ = env.step(a)
    obs_t, _ = model.policy.obs_to_tensor(obs)
    dist = model.policy.get_distribution(obs_t)
    probs = dist.distribution.probs.detach().numpy()[0]
    masked = obs["action_mask"] == 0
    assert masked.sum() >= 2 and probs[masked].max() < 1e-12  # at least the two picks
    np.testing.assert_allclose(probs.sum(), 1.0, rtol=1e-6)
    assert float(dist.distribution.logits.detach()[0, masked].max()) <= MASKED_LOGIT / 2
    with pytest.raises(ValueError, match="algo must be one of"):
        make_ppo(env, "a2c")


def test_fim_training_script_with_plain_ppo(tmp_path: Path) -> None:
    out = tmp_path / "fim_plain.zip"
    meta = train_fim_ppo.main(
        [
            *TINY,
            "--algo=ppo",
            "--total-timesteps=128",
            '--env-kwargs={"n_candidates": 8, "budget": 3}',
            "--eval-episodes=1",
            "--baselines=random",
            f"--out={out}",
            "--tensorboard-dir=",
        ]
    )
    assert meta["training"]["algorithm"] == "PPO"
    assert meta["architecture"]["policy"].endswith("CandidateScoringPPOPolicy")
    agent = SB3PolicyAgent(out, env_id=FIM_ID)
    assert not agent.masked
    assert np.isfinite(_play(agent, gym.make(FIM_ID, n_candidates=12, budget=4), seed=2)[1])
    with pytest.raises(ValueError, match="--algo must be one of"):
        train_fim_ppo.main([*TINY, "--algo=dqn", f"--out={out}", "--force"])


def test_training_learns_a_toy_problem_with_known_optimum() -> None:
    """On a 6-candidate, budget-2 FIM pool PPO must beat random and approach brute force.

    (6 candidates: 15 feasible subsets. With 2 candidates and budget 2 every policy picked the
    same set, and "PPO beats random" compared two sums of the same terms one ulp apart.)
    """
    kwargs = {"n_candidates": 6, "budget": 2, "sensors": ["camera"]}
    env = gym.make(FIM_ID, **kwargs)
    model = make_maskable_ppo(env, seed=0, n_steps=256, batch_size=128, learning_rate=3e-3)
    model.learn(6_000)
    seeds = range(100, 130)

    def final(policy) -> float:
        out = []
        for s in seeds:
            obs, info = env.reset(seed=s)
            done = False
            while not done:
                a = policy(obs)
                obs, _, terminated, truncated, info = env.step(a)
                done = terminated or truncated
            out.append(info["objective"])
        return float(np.mean(out))

    ppo = final(lambda o: int(model.predict(o, action_masks=o["action_mask"].astype(bool),
                                            deterministic=True)[0]))  # fmt: skip
    rng = np.random.default_rng(0)
    rand = final(lambda o: int(rng.choice(np.flatnonzero(o["action_mask"]))))
    bf = make("brute_force", FIM_ID)

    def best() -> float:
        out = []
        for s in seeds:
            out.append(_play(bf, env, s)[1])
        return float(np.mean(out))

    opt = best()
    assert opt - rand > 0.05 * abs(opt), (rand, opt)  # the choice matters on this pool
    assert ppo > rand + 0.5 * (opt - rand), (ppo, rand, opt)
    assert ppo >= opt - 0.25 * (opt - rand), (ppo, rand, opt)


# -- shipped checkpoints ----------------------------------------------------------------------
@pytest.mark.parametrize("env_id", sorted(DEFAULT_CHECKPOINTS))
def test_shipped_checkpoint_loads_and_acts(env_id: str) -> None:
    if not DEFAULT_CHECKPOINTS[env_id].is_file():
        pytest.fail(f"shipped checkpoint {DEFAULT_CHECKPOINTS[env_id]} is missing")
    agent = make("ppo", env_id)
    kwargs = {"horizon": 5} if env_id != FIM_ID else {}
    env = gym.make(env_id, **kwargs)
    ret, obj = _play(agent, env, seed=11)
    assert np.isfinite(ret) and np.isfinite(obj)
    meta = json.loads(DEFAULT_CHECKPOINTS[env_id].with_suffix(".json").read_text())
    assert meta["env_id"] == env_id and meta["metrics"]


def test_shipped_proxy_cl_checkpoint_uses_its_own_view() -> None:
    """The metadata's view is re-applied: the proxy policy reads the naive gains, no previews."""
    ckpt = DEFAULT_CHECKPOINTS[CL_ID].with_name("cl_scheduling_ppo_proxy.zip")
    agent = SB3PolicyAgent(ckpt, env_id=CL_ID)
    env = gym.make(CL_ID, n_agents=3, budget=1, horizon=3)
    ret, obj = _play(agent, env, seed=4)
    assert agent.view.name == "cl_pairs" and np.isfinite(ret) and np.isfinite(obj)
    shipped = SB3PolicyAgent(env_id=CL_ID)
    shipped.reset(env, seed=0)
    assert shipped.view.name == "cl_pairs_fused"


def test_bench_runs_a_checkpoint_path(tmp_path: Path) -> None:
    """`selenv bench --agents ppo:PATH` plays that file next to the heuristics."""
    from selenv.cli import main as cli_main

    ckpt = DEFAULT_CHECKPOINTS[FIM_ID]
    out = tmp_path / "bench.json"
    code = cli_main(
        [
            "bench",
            FIM_ID,
            "--agents",
            f"greedy,ppo:{ckpt}",
            "--episodes",
            "1",
            "--env-kwargs",
            '{"n_candidates": 10, "budget": 3}',
            "--json",
            str(out),
            "--no-progress",
        ]
    )
    assert code == 0
    res = json.loads(out.read_text())["results"][0]
    assert set(res["agents"]) == {"greedy", f"ppo:{ckpt}"}
    assert len(res["agents"][f"ppo:{ckpt}"]["returns"]) == 1
    # a named checkpoint that cannot be loaded is a usage error (exit 2), not a skipped agent
    assert cli_main(["bench", FIM_ID, "--agents", f"ppo:{tmp_path / 'no.zip'}",
                     "--episodes", "1", "--no-progress"]) == 2  # fmt: skip
