"""A CleanRL-style PPO (the single-file ``ppo.py`` loop) trains on every env, unmodified.

The loop is CleanRL's: ``gym.vector.SyncVectorEnv`` of ``gym.make(id)`` +
``FlattenObservation``, an MLP actor-critic with orthogonal init, ``num_steps`` rollouts, GAE,
clipped PPO epochs over shuffled minibatches. No action masks (CleanRL's ``ppo.py`` has none):
invalid picks are the envs' documented no-ops. The same loop also runs on the native vector env
(``gym.make_vec`` with Gymnasium's vector ``FlattenObservation``). Each run is two iterations of
4 envs x 64 steps; the test asserts that the loop ran and every stored number is finite.
"""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pytest

torch = pytest.importorskip("torch")
nn = torch.nn

import selenv  # noqa: E402, F401  (registers the ids)
from selenv.families import FAMILIES  # noqa: E402

#: every current id at its default keywords (ReceiverClustering-v2 included: one Discrete)
IDS = [f.current_id for f in FAMILIES]


def make_env(env_id: str) -> Callable[[], gym.Env]:
    def thunk() -> gym.Env:
        env = gym.make(env_id)
        env = gym.wrappers.FlattenObservation(env)
        return gym.wrappers.RecordEpisodeStatistics(env)

    return thunk


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, obs_dim: int, n_actions: int) -> None:
        super().__init__()
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, 1), std=1.0),
        )  # fmt: skip
        self.actor = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, n_actions), std=0.01),
        )  # fmt: skip

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x)

    def get_action_and_value(self, x: torch.Tensor, action: torch.Tensor | None = None) -> tuple:
        logits = self.actor(x)
        probs = torch.distributions.Categorical(logits=logits)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs.entropy(), self.critic(x)


def ppo(
    envs: gym.vector.VectorEnv, seed: int = 1, num_steps: int = 64, iterations: int = 2
) -> dict:
    """CleanRL ``ppo.py``'s training loop (its defaults, shortened); returns the last buffers."""
    gamma, gae_lambda, clip_coef, ent_coef, vf_coef, max_grad_norm = 0.99, 0.95, 0.2, 0.01, 0.5, 0.5
    update_epochs, num_minibatches, lr = 4, 4, 2.5e-4
    torch.manual_seed(seed)
    n = envs.num_envs
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    agent = Agent(obs_dim, int(envs.single_action_space.n))
    optimizer = torch.optim.Adam(agent.parameters(), lr=lr, eps=1e-5)
    obs = torch.zeros((num_steps, n, obs_dim))
    actions = torch.zeros((num_steps, n))
    logprobs, rewards, dones, values = (torch.zeros((num_steps, n)) for _ in range(4))
    batch_size = n * num_steps
    minibatch_size = batch_size // num_minibatches
    next_obs_np, _ = envs.reset(seed=seed)
    next_obs, next_done = torch.Tensor(next_obs_np), torch.zeros(n)
    episodes, losses = 0, []
    for iteration in range(1, iterations + 1):
        optimizer.param_groups[0]["lr"] = (1.0 - (iteration - 1.0) / iterations) * lr
        for step in range(num_steps):
            obs[step], dones[step] = next_obs, next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
                values[step] = value.flatten()
            actions[step], logprobs[step] = action, logprob
            next_obs_np, reward, terminations, truncations, _ = envs.step(action.numpy())
            next_done_np = np.logical_or(terminations, truncations)
            episodes += int(next_done_np.sum())
            rewards[step] = torch.tensor(reward, dtype=torch.float32).view(-1)
            next_obs, next_done = torch.Tensor(next_obs_np), torch.Tensor(next_done_np)
        with torch.no_grad():  # GAE
            next_value = agent.get_value(next_obs).reshape(1, -1)
            advantages = torch.zeros_like(rewards)
            lastgaelam = 0
            for t in reversed(range(num_steps)):
                if t == num_steps - 1:
                    nextnonterminal, nextvalues = 1.0 - next_done, next_value
                else:
                    nextnonterminal, nextvalues = 1.0 - dones[t + 1], values[t + 1]
                delta = rewards[t] + gamma * nextvalues * nextnonterminal - values[t]
                advantages[t] = lastgaelam = (
                    delta + gamma * gae_lambda * nextnonterminal * lastgaelam
                )
            returns = advantages + values
        b_obs, b_logprobs = obs.reshape((-1, obs_dim)), logprobs.reshape(-1)
        b_actions, b_advantages = actions.reshape(-1), advantages.reshape(-1)
        b_returns, b_values = returns.reshape(-1), values.reshape(-1)
        b_inds = np.arange(batch_size)
        for _epoch in range(update_epochs):
            np.random.default_rng(seed + iteration).shuffle(b_inds)
            for start in range(0, batch_size, minibatch_size):
                mb = b_inds[start : start + minibatch_size]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(
                    b_obs[mb], b_actions.long()[mb]
                )
                ratio = (newlogprob - b_logprobs[mb]).exp()
                mb_adv = b_advantages[mb]
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                pg_loss = torch.max(
                    -mb_adv * ratio, -mb_adv * torch.clamp(ratio, 1 - clip_coef, 1 + clip_coef)
                ).mean()
                v_loss = 0.5 * ((newvalue.view(-1) - b_returns[mb]) ** 2).mean()
                loss = pg_loss - ent_coef * entropy.mean() + v_loss * vf_coef
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), max_grad_norm)
                optimizer.step()
                losses.append(float(loss))
        _ = b_values
    return {"obs": obs, "rewards": rewards, "values": values, "advantages": advantages,
            "losses": np.array(losses), "episodes": episodes}  # fmt: skip


def _check(out: dict) -> None:
    for key in ("obs", "rewards", "values", "advantages"):
        assert torch.isfinite(out[key]).all(), key
    assert out["losses"].size == 2 * 4 * 4 and np.isfinite(out["losses"]).all()
    assert out["rewards"].abs().sum() > 0  # the env's rewards reached the buffer


@pytest.mark.parametrize("env_id", IDS)
def test_cleanrl_ppo_on_sync_vector_env(env_id: str) -> None:
    torch.set_num_threads(1)
    envs = gym.vector.SyncVectorEnv([make_env(env_id) for _ in range(4)])
    _check(ppo(envs))
    envs.close()


@pytest.mark.parametrize("env_id", IDS)
def test_cleanrl_ppo_on_the_native_vector_env(env_id: str) -> None:
    torch.set_num_threads(1)
    venv = gym.make_vec(env_id, num_envs=4)
    assert type(venv).__module__.startswith("selenv.families.")  # the native one
    envs = gym.wrappers.vector.FlattenObservation(venv)
    _check(ppo(envs))
    envs.close()
