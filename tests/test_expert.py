"""Expert iteration on CLScheduling-v1: rollout labels, DAgger rounds, the training entry point."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from selenv.families.cooperative.rollout import CLRolloutAgent
from selenv.learned.families.cooperative import CL_ID, collect_cl_rollout_labels
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent
from selenv.learned.rl.expert import TRAIN_SEED_BASE, train_seed
from selenv.train import train_cl_expert

#: a small CL team: 4 labels take a few dozen rollout decisions (ties among them); with 3 agents
#: nearly every pair is a no-op (an exact tie, not labelled) and 4 labels took ~1300 decisions
SMALL = {"n_agents": 4, "horizon": 12}


def test_labels_are_rollout_scores_on_its_candidates() -> None:
    data = collect_cl_rollout_labels(SMALL, 4, seed=0, horizon=2, explore=0.0, progress=False)
    assert len(data) == 4
    n = data.deltas.shape[1]
    # replay: the same seeds and the labeller's own choices give the same scores
    env = gym.make(CL_ID, **SMALL)
    ref = CLRolloutAgent(top_k=3, horizon=2)
    episode, k = 0, 0
    obs, info = env.reset(seed=train_seed(0, 0, 1, episode))
    ref.reset(env)
    while k < len(data):
        mask = np.asarray(obs["action_mask"], dtype=bool)
        choice = n - 1
        if mask[:-1].any():
            choice, scores = ref.scores()
            if len(set(scores.values())) > 1:  # ties are skipped by the collector
                row = data.deltas[k]
                assert set(np.flatnonzero(np.isfinite(row))) == set(scores)
                for a, s in scores.items():
                    assert row[a] == -s
                assert row[choice] == row[np.isfinite(row)].min()  # the choice is the best
                allowed = data.obs["action_mask"][k].astype(bool)  # the top-3 view
                assert set(np.flatnonzero(allowed)) == set(scores)
                assert not (allowed & ~mask).any()
                k += 1
        obs, _, term, trunc, info = env.step(choice)
        if term or trunc:
            episode += 1
            obs, info = env.reset(seed=train_seed(0, 0, 1, episode))
            ref.reset(env)


def test_train_seeds_are_disjoint_from_held_out_seeds() -> None:
    seeds = {train_seed(s, w, 2, e) for s in range(3) for w in range(2) for e in range(50)}
    assert min(seeds) >= TRAIN_SEED_BASE
    assert len(seeds) == 3 * 2 * 50


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_states": 0}, "n_states"),
        ({"workers": 0}, "workers"),
        ({"explore": 1.5}, "explore"),
        ({"top_k": 0}, "top_k"),
        ({"horizon": -1}, "horizon"),
    ],
)
def test_collect_rejects_bad_options(kwargs: dict, match: str) -> None:
    args = {"n_states": 2, "seed": 0, **kwargs}
    n_states, seed = args.pop("n_states"), args.pop("seed")
    with pytest.raises(ValueError, match=match):
        collect_cl_rollout_labels(SMALL, n_states, seed, progress=False, **args)


def test_train_cl_expert_tiny_budget_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "clx.zip"
    argv = [
        "--out",
        str(out),
        "--env-kwargs",
        json.dumps(SMALL),
        "--rounds",
        "2",
        "--states-per-round",
        "5",
        "--horizon",
        "1",
        "--workers",
        "1",
        "--epochs",
        "1",
        "--eval-episodes",
        "0",
        "--no-progress",
    ]
    meta = train_cl_expert.main(argv)
    assert out.is_file() and (tmp_path / "clx_round0.zip").is_file()
    log = meta["expert_iteration"]["rounds_log"]
    assert [r["states"] for r in log] == [5, 10]  # DAgger aggregates the rounds
    assert meta["expert_iteration"]["command"].startswith("python -m selenv.train.train_cl_expert")
    env = gym.make(CL_ID, **SMALL)
    assert meta["obs_layout"]["n_candidates_trained"] == env.unwrapped.n_pairs + 1
    agent = SB3PolicyAgent(out, env_id=CL_ID)  # the saved file loads safely and plays
    obs, info = env.reset(seed=3)
    agent.reset(env, seed=3)
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(agent.act(obs, info))
        done = term or trunc
    with pytest.raises(SystemExit):  # the outputs exist: exit 2 unless --force
        train_cl_expert.main(argv)
    bad = [*argv, "--force", "--checkpoint", str(DEFAULT_CHECKPOINTS["selenv/FIMSelection-v1"])]
    with pytest.raises(ValueError, match="trained on"):
        train_cl_expert.main(bad)


def test_landmark_labels_and_training_entry_point(tmp_path: Path) -> None:
    from selenv.learned.families.landmarks import LANDMARK_ID, collect_landmark_rollout_labels
    from selenv.train import train_landmark_expert

    data = collect_landmark_rollout_labels({}, 8, seed=0, horizon=2, progress=False)
    finite = np.isfinite(data.deltas)
    assert (finite.sum(axis=1) >= 2).all()  # at least two labelled landmarks, not all tied
    assert all(np.ptp(row[f]) > 0 for row, f in zip(data.deltas, finite, strict=True))
    assert not (finite & ~data.obs["action_mask"].astype(bool)).any()  # only open landmarks
    out = tmp_path / "lm.zip"
    meta = train_landmark_expert.main(
        [
            "--out",
            str(out),
            "--rounds",
            "1",
            "--states-per-round",
            "6",
            "--horizon",
            "1",
            "--workers",
            "1",
            "--epochs",
            "1",
            "--eval-episodes",
            "0",
            "--no-progress",
        ]
    )
    assert meta["env_id"] == LANDMARK_ID and out.is_file()
    assert meta["expert_iteration"]["command"].startswith(
        "python -m selenv.train.train_landmark_expert"
    )
    # the starting checkpoint's results describe it, not the new weights
    start = json.loads(DEFAULT_CHECKPOINTS[LANDMARK_ID].with_suffix(".json").read_text())
    assert "held_out_bench" in start
    assert "held_out_bench" not in meta and meta["metrics"] is None
    assert meta["initialised_from"]["checkpoint"] == str(DEFAULT_CHECKPOINTS[LANDMARK_ID])
    assert meta["initialised_from"]["held_out_bench"] == start["held_out_bench"]
    assert meta["initialised_from"]["expert_iteration"] == start["expert_iteration"]
    saved = json.loads(out.with_suffix(".json").read_text())
    assert saved["initialised_from"] == meta["initialised_from"]


def test_fast_rollout_labels_are_its_scores_on_its_candidates() -> None:
    from selenv.families.landmarks.fast_rollout import LandmarkFastRolloutAgent
    from selenv.learned.families.landmarks import LANDMARK_ID, collect_landmark_rollout_labels

    data = collect_landmark_rollout_labels(
        {}, 5, seed=0, horizon=2, explore=0.0, labeller="fast_rollout", progress=False
    )
    assert len(data) == 5
    # replay: the same seeds and the labeller's own picks give the same rows
    env = gym.make(LANDMARK_ID)
    ref = LandmarkFastRolloutAgent(top_k=4, horizon=2)
    obs, info = env.reset(seed=train_seed(0, 0, 1, 0))
    ref.reset(env)
    k = 0
    while k < len(data):
        best, scores = ref.scores()
        row = np.full(data.deltas.shape[1], np.inf)
        for subset, value in scores.items():
            for lm in subset:
                row[lm] = min(row[lm], -value)
        finite = np.isfinite(row)
        if finite.sum() > 1 and np.ptp(row[finite]) > 0:  # ties are skipped by the collector
            np.testing.assert_array_equal(data.deltas[k], row)
            assert len(set(np.flatnonzero(finite))) <= 6  # the labeller's shortlist
            k += 1
        obs, _, term, trunc, info = env.step(best[0])
        assert not (term or trunc)


def test_an_unknown_labeller_is_refused_before_any_work(capsys: pytest.CaptureFixture) -> None:
    from selenv.learned.families.landmarks import collect_landmark_rollout_labels
    from selenv.train import train_landmark_expert

    with pytest.raises(ValueError, match="labeller"):
        collect_landmark_rollout_labels({}, 2, seed=0, labeller="greedy", progress=False)
    with pytest.raises(SystemExit) as exc:
        train_landmark_expert.main(["--labeller", "greedy"])
    assert exc.value.code == 2
    assert "--labeller" in capsys.readouterr().err
