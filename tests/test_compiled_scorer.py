"""``compile_scorer``: the compiled candidate scorer gives the eager one's outputs and gradients.

Checked on real FIMSelection-v1 observations (masks with selected candidates included): the
compiled forward against the eager forward of the same module to 1e-6, and the parameter
gradients of a loss through both to 1e-5 (float32 sums over the batch, reordered). The
fallback: a compile that fails warns once and the module runs eagerly with the same outputs;
copies of a compiled module run eagerly; the weights are untouched.
"""

from __future__ import annotations

import copy
import warnings

import gymnasium as gym
import numpy as np
import pytest

torch = pytest.importorskip("torch")

import selenv  # noqa: E402, F401
from selenv.learned.rl import compiled as compiled_module  # noqa: E402
from selenv.learned.rl.candidate_policy import CandidateScorer  # noqa: E402
from selenv.learned.rl.compiled import (  # noqa: E402
    CompileFallbackWarning,
    compile_scorer,
    compiled_forward,
)


def _batch(n: int = 6) -> tuple[gym.spaces.Dict, dict[str, torch.Tensor]]:
    env = gym.make("selenv/FIMSelection-v1", n_candidates=40, budget=5)
    rows = []
    obs, info = env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(n):
        rows.append(obs)
        allowed = np.flatnonzero(info["action_mask"])
        obs, _, done, _, info = env.step(int(rng.choice(allowed)))
        if done:
            obs, info = env.reset(seed=len(rows))
    batch = {k: torch.as_tensor(np.stack([r[k] for r in rows]), dtype=torch.float32) for k in obs}
    return env.observation_space, batch


def _scorer(space: gym.spaces.Dict) -> CandidateScorer:
    torch.manual_seed(0)
    return CandidateScorer(space, hidden=(32, 32), gain_skip_init=0.5)


def _grads(module: torch.nn.Module, out: torch.Tensor) -> list[torch.Tensor]:
    module.zero_grad()
    scores = out[:, :40].clamp(min=-50.0)  # the masked logits are constants
    (scores.square().mean() + out[:, 40:].sum()).backward()
    return [p.grad.clone() for p in module.parameters() if p.grad is not None]


def test_compiled_outputs_and_gradients_equal_the_eager_ones() -> None:
    torch.set_num_threads(1)
    space, batch = _batch()
    assert (batch["action_mask"] < 0.5).any()  # some candidates are masked
    module = _scorer(space)
    eager_out = module.scores(batch)
    eager_grads = _grads(module, module.scores(batch))
    fast = compile_scorer(module)
    assert compile_scorer(module) is fast and compiled_forward(module) is fast
    out = module(batch)
    if fast.error is not None:
        pytest.skip(f"torch.compile cannot run here: {fast.error}")
    torch.testing.assert_close(out, eager_out, rtol=1e-6, atol=1e-6)
    # float32 gradients summed over the batch in another order by the fused kernels: 1e-5
    for got, want in zip(_grads(module, module(batch)), eager_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


def test_a_failing_compile_warns_once_and_runs_eagerly(monkeypatch) -> None:
    def broken(fn):
        def run(*args):
            raise RuntimeError("no C compiler\nsecond line")

        return run

    monkeypatch.setattr(compiled_module.th, "compile", broken)
    space, batch = _batch(3)
    module = _scorer(space)
    want = module.scores(batch)
    state = {k: v.clone() for k, v in module.state_dict().items()}
    fast = compile_scorer(module)
    with pytest.warns(CompileFallbackWarning, match="no C compiler"):
        got = module(batch)
    assert fast.error == "RuntimeError: no C compiler"
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no second warning
        torch.testing.assert_close(module(batch), want, rtol=0, atol=0)
    assert module.state_dict().keys() == state.keys()
    for key, value in module.state_dict().items():
        assert torch.equal(value, state[key])


def test_copies_run_eagerly_and_non_scorers_are_refused() -> None:
    space, _ = _batch(1)
    module = _scorer(space)
    compile_scorer(module)
    assert compiled_forward(copy.deepcopy(module)) is None
    with pytest.raises(TypeError, match="candidate scorer"):
        compile_scorer(torch.nn.Linear(2, 2))
