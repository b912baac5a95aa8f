"""The shared MARL policy as the PettingZoo ``ppo`` agent of ``selenv bench``."""

from __future__ import annotations

import numpy as np
import pytest

from selenv.agents import make
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.marl import SharedPPOPolicy
from selenv.learned.rl.safe_load import load_policy
from selenv.multiagent import fim_selection_v0

MODULE = "selenv.multiagent.fim_selection_v0"


@pytest.mark.parametrize("name", ["ppo", "ppo_independent"])
@pytest.mark.parametrize("mode", ["cooperative", "independent"])
def test_shared_ppo_acts_like_predict_for_acting_agents_and_passes_otherwise(
    mode: str, name: str
) -> None:
    env = fim_selection_v0.parallel_env(mode=mode)
    agent = make(name, MODULE)
    assert isinstance(agent.inner, SharedPPOPolicy)  # the record's agent wraps the loader's
    policy = load_policy(agent.checkpoint, agent.metadata)
    observations, infos = env.reset(seed=4)
    agent.reset(env, seed=4)
    acted = waited = 0
    while env.agents:
        actions = agent.act(observations, infos)
        assert set(actions) == set(env.agents)
        for a, action in actions.items():
            if not infos[a].get("on_turn", True):
                assert action == 0
                waited += 1
                continue
            obs = {k: v for k, v in observations[a].items() if k != "on_turn"}
            mask = np.asarray(infos[a].get("action_mask", obs["action_mask"]), dtype=bool)
            expected, _ = policy.predict(obs, action_masks=mask, deterministic=True)
            assert action == int(expected) and mask[action]
            acted += 1
        observations, _, _, _, infos = env.step(actions)
    assert acted > 0 and (waited > 0) == (mode == "cooperative")


def test_shared_ppo_rejects_a_checkpoint_of_another_env() -> None:
    with pytest.raises(ValueError, match="trained on"):
        SharedPPOPolicy(str(DEFAULT_CHECKPOINTS["selenv/FIMSelection-v1"]))


def test_shared_ppo_rejects_an_env_of_another_width() -> None:
    agent = SharedPPOPolicy()
    env = fim_selection_v0.parallel_env(preset="example1")
    env.reset(seed=0)
    if env.observation_space(env.possible_agents[0])["whitened"].shape[1] == agent.width:
        pytest.skip("example1 has the trained width")
    with pytest.raises(ValueError, match="whitened width"):
        agent.reset(env, seed=0)


def test_shipped_marl_checkpoints_are_distinct_and_named_by_file_only() -> None:
    from selenv.learned.rl.marl import make_shared_ppo

    assert make("ppo_independent", MODULE).checkpoint.endswith("fim_marl_ppo_independent.zip")
    assert make("ppo", MODULE).checkpoint.endswith("fim_marl_ppo.zip")
    for bad in ("../fim_marl_ppo.zip", "", 3):
        with pytest.raises(ValueError, match="shipped must be a file name"):
            make_shared_ppo(shipped=bad)
    with pytest.raises(ValueError, match="not both"):
        make_shared_ppo(shipped="fim_marl_ppo.zip", checkpoint="x.zip")
