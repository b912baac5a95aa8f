"""ReceiverClustering-v1's factorised edit scorer (selenv.learned.families.clustering_edits)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from selenv.families.clustering.env import apply_edit, edit_action_count
from selenv.families.clustering.view import (
    SOURCE_COLUMNS,
    TARGET_COLUMNS,
    edit_endpoints,
    leave_rows,
    receivers_for_count,
)
from selenv.learned.families.clustering_edits import (
    EDIT_EXTRACTOR,
    FactorisedEditScorer,
    edit_model_from_checkpoint,
    edit_policy_spec,
    load_edit_policy,
    scorer_policy_kwargs,
)
from selenv.learned.rl import training
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent, load_metadata
from selenv.learned.rl.candidate_policy import (
    MASKED_LOGIT,
    CandidateScorer,
    CandidateScoringPolicy,
    make_ppo,
)
from selenv.learned.rl.safe_load import load_policy
from selenv.learned.rl.views import CandidateViewWrapper, candidate_space, view_for
from selenv.train import train_clustering_dagger, train_clustering_ppo

CLU_ID = "selenv/ReceiverClustering-v1"
SHIPPED = DEFAULT_CHECKPOINTS[CLU_ID]
TINY = ["--n-envs=2", "--n-steps=64", "--batch-size=64", "--n-epochs=1", "--no-progress"]


def _edit_env(n: int = 9, horizon: int = 12) -> gym.Env[Any, Any]:
    return gym.make(CLU_ID, n_agents=n, horizon=horizon, action_mode="edit")


def _states(n: int = 9, steps: int = 6, seed: int = 3) -> list[dict[str, np.ndarray]]:
    """Candidate-view observations along an episode of random allowed edits."""
    env = _edit_env(n, horizon=steps + 2)
    view = view_for(CLU_ID, env)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = []
    for _ in range(steps):
        cand = view(obs)
        out.append(cand)
        obs, *_ = env.step(int(rng.choice(np.flatnonzero(cand["action_mask"]))))
    return out


def _batch(states: list[dict[str, np.ndarray]]) -> dict[str, th.Tensor]:
    return {k: th.as_tensor(np.stack([s[k] for s in states]), dtype=th.float32) for k in states[0]}


def _scorer(n: int = 9, seed: int = 0, **kwargs: Any) -> FactorisedEditScorer:
    """A scorer with every weight random at a visible scale (not the policy's small init)."""
    th.manual_seed(seed)
    scorer = FactorisedEditScorer(candidate_space(edit_action_count(n), 17), **kwargs)
    with th.no_grad():
        for p in scorer.parameters():
            p.normal_(0.0, 0.5)
    return scorer


# -- the view's edit layout ----------------------------------------------------------------------
def test_edit_layout_helpers_match_the_view_and_the_env() -> None:
    for n in range(1, 40):
        assert receivers_for_count(edit_action_count(n)) == n
    for bad in (3, 1335, 1337):
        with pytest.raises(ValueError, match="count="):
            receivers_for_count(bad)
    with pytest.raises(TypeError, match="count must be an int"):
        receivers_for_count(2.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="n must be an int"):
        edit_endpoints("9")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n must be >= 1"):
        leave_rows(0)
    n = 9
    env = _edit_env(n)
    obs, _ = env.reset(seed=1)
    view: Any = view_for(CLU_ID, env)
    i, j = edit_endpoints(n)
    # the view's own endpoints (as it computed them before the helpers existed)
    iu, ju = np.triu_indices(n, k=1)
    mi, mj = np.divmod(np.arange(n * n), n)
    assert np.array_equal(view.i, np.concatenate([[0], mi, iu]))
    assert np.array_equal(view.j, np.concatenate([[0], mj, ju]))
    assert np.array_equal(view.i, i) and np.array_equal(view.j, j)
    labels = np.asarray(obs["assignment"])
    for a in range(1, edit_action_count(n)):  # each row's (i, j) is the edit the env applies
        after = apply_edit(labels, a)
        if a <= n * n:
            assert all(after[r] == labels[r] for r in range(n) if r != i[a])
        else:
            assert after[i[a]] == labels[j[a]] and after[j[a]] == labels[i[a]]
    cand = view(obs)
    rows = leave_rows(n)
    w = cand["whitened"]
    np.testing.assert_allclose(w[rows][:, [0, 1]], np.log(obs["sigma"]), rtol=1e-6)
    # a move row's source / target columns are its receivers' leave-row source columns
    a = 1 + 2 * n + 5
    np.testing.assert_array_equal(w[a, list(SOURCE_COLUMNS)], w[rows[2], list(SOURCE_COLUMNS)])
    np.testing.assert_array_equal(w[a, list(TARGET_COLUMNS)], w[rows[5], list(SOURCE_COLUMNS)])


# -- the scorer ----------------------------------------------------------------------------------
def test_shapes_and_pool_size_independence() -> None:
    states = _states(9, steps=3)
    scorer = _scorer(9, hidden=[32, 16], rank=4)
    out = scorer(_batch(states))
    n_edits = edit_action_count(9)
    assert out.shape == (3, n_edits + 2 * 16) and scorer.features_dim == n_edits + 32
    assert scorer.n_receivers == 9 and scorer.pooled_dim == 32
    space12 = candidate_space(edit_action_count(12), 17)
    other = FactorisedEditScorer(space12, hidden=[32, 16], rank=4)
    other.load_state_dict(scorer.state_dict())  # same weights, another pool size
    out12 = other(_batch(_states(12, steps=2)))
    assert out12.shape == (2, edit_action_count(12) + 32)
    assert th.isfinite(out12).all()


def test_scores_follow_the_documented_equation() -> None:
    n, k = 9, 4
    scorer = _scorer(n, hidden=[16, 8], rank=k, gain_skip_init=0.7)
    cand = _states(n, steps=4)[-1]
    cand["action_mask"][:] = 1  # compare every edit unmasked
    obs = _batch([cand])
    with th.no_grad():
        scores = scorer(obs)[0, : edit_action_count(n)].numpy().astype(np.float64)
        u = scorer.receiver_table(obs)
        budget = obs["budget_left"].reshape(1, 1, 1).expand(1, n, 1)
        x = th.cat([th.sign(u) * th.log1p(u.abs()), budget], dim=-1)
        h = th.tanh(scorer.input_layer(x))
        for layer, ctx in zip(scorer.set_layers, scorer.ctx_layers, strict=True):
            h = th.tanh(layer(h) + ctx(h.mean(dim=1)).unsqueeze(1))
        heads, key = scorer.score_head(h)[0].numpy(), scorer.key_head(h)[0].numpy()
    u0 = u[0].numpy()
    q, s = heads[:, :k], heads[:, k : 2 * k]
    leave, src, tgt, swp = heads[:, 2 * k :].T
    alpha = scorer.pair_weights.detach().numpy()
    beta = scorer.type_bias.detach().numpy()
    w = float(scorer.gain_skip.detach())

    def phi(a: int, b: int) -> np.ndarray:
        ls_a, cm_a, ls_b, cm_b = u0[a, :2], u0[a, 2:4], u0[b, :2], u0[b, 2:4]
        return np.log1p(np.abs(np.concatenate([ls_a - cm_b, ls_a - ls_b, cm_a - cm_b])))

    i_all, j_all = edit_endpoints(n)
    for e in range(edit_action_count(n)):
        i, j = int(i_all[e]), int(j_all[e])
        if e == 0:
            expect = beta[0]  # the no-op: gain 1, relative gain 0
        elif e <= n * n and i == j:
            expect = leave[i] + beta[1] - 10.0 * w
        elif e <= n * n:
            expect = q[i] @ key[j] / math.sqrt(k) + src[i] + tgt[j] + alpha[0] @ phi(i, j)
            expect += beta[2] - 10.0 * w
        else:
            expect = (s[i] @ key[j] + s[j] @ key[i]) / math.sqrt(k) + swp[i] + swp[j]
            expect += alpha[1] @ (phi(i, j) + phi(j, i)) + beta[3] - 10.0 * w
        assert scores[e] == pytest.approx(expect, abs=1e-4), (e, i, j)


def test_permuting_the_receivers_permutes_the_edit_scores() -> None:
    n = 9
    env = _edit_env(n)
    obs, _ = env.reset(seed=5)
    for a in (1 + 0 * n + 4, 1 + 3 * n + 3):  # a move and a leave: uneven clusters
        if view_for(CLU_ID, env)(obs)["action_mask"][a]:
            obs, *_ = env.step(a)
    view = view_for(CLU_ID, env)
    perm = np.random.default_rng(0).permutation(n)  # new receiver r is old receiver perm[r]
    permuted = {
        **obs,
        "sigma": obs["sigma"][perm],
        "position_var": obs["position_var"][perm],
        "assignment": obs["assignment"][perm],
    }
    scorer = _scorer(n, hidden=[16, 16], rank=4)
    with th.no_grad():
        old, new = scorer(_batch([view(obs)]))[0], scorer(_batch([view(permuted)]))[0]
    count = edit_action_count(n)

    def index(a: int, b: int, swap: bool) -> int:
        if swap:
            lo, hi = min(a, b), max(a, b)
            return 1 + n * n + int(np.flatnonzero((iu == lo) & (ju == hi))[0])
        return 1 + a * n + b

    iu, ju = np.triu_indices(n, k=1)
    i_all, j_all = edit_endpoints(n)
    mapped = np.empty(count, dtype=np.intp)  # new edit e is old edit mapped[e]
    mapped[0] = 0
    for e in range(1, count):
        a, b = perm[i_all[e]], perm[j_all[e]]
        mapped[e] = index(int(a), int(b), swap=e > n * n)
    th.testing.assert_close(new[:count], old[:count][th.as_tensor(mapped)], rtol=1e-5, atol=1e-5)
    th.testing.assert_close(new[count:], old[count:], rtol=1e-5, atol=1e-5)  # pooled: invariant
    assert not th.allclose(new[1:count], old[1:count])  # the permutation did move scores


def test_a_masked_edit_is_never_sampled() -> None:
    env = CandidateViewWrapper(_edit_env(9), view_for(CLU_ID, _edit_env(9)))
    extractor, extra = scorer_policy_kwargs("factorised", 4)
    kw = {"hidden": [16], "activation": "tanh", "gain_skip_init": 0.0, **extra}
    for algo in ("maskable_ppo", "ppo"):
        model = make_ppo(
            env,
            algo,
            n_steps=16,
            batch_size=16,
            policy_kwargs={"features_extractor_class": extractor, "features_extractor_kwargs": kw},
        )
        policy: Any = model.policy
        scorer = policy.pi_features_extractor
        assert isinstance(scorer, FactorisedEditScorer)
        with th.no_grad():  # the moves score far above everything else: only the mask stops them
            scorer.type_bias.copy_(th.tensor([0.0, 0.0, 50.0, 0.0]))
        cand = _states(9, steps=2)[-1]
        allowed = np.zeros(edit_action_count(9), dtype=bool)
        allowed[[0, 1 + 9 * 9 + 3, 1 + 4 * 9 + 4]] = True  # no-op, one swap, one leave
        cand["action_mask"] = allowed.astype(np.int8)
        obs_t, _ = policy.obs_to_tensor(cand)
        obs_t = {key: v.repeat(4000, *([1] * (v.ndim - 1))) for key, v in obs_t.items()}
        with th.no_grad():
            if algo == "maskable_ppo":
                masks = np.tile(allowed, (4000, 1))
                dist = policy.get_distribution(obs_t, action_masks=masks)
            else:
                dist = policy.get_distribution(obs_t)
            sampled = dist.sample().numpy()
            logits = scorer(obs_t)[0, : allowed.size].numpy()
        assert allowed[sampled].all(), algo
        assert set(np.unique(sampled)) == set(np.flatnonzero(allowed)), algo  # uniform-ish
        assert (logits[~allowed] == MASKED_LOGIT).all()


def test_gradients_reach_every_parameter() -> None:
    env = CandidateViewWrapper(_edit_env(9), view_for(CLU_ID, _edit_env(9)))
    extractor, extra = scorer_policy_kwargs("factorised", 4)
    model = make_ppo(
        env,
        n_steps=16,
        batch_size=16,
        policy_kwargs={
            "features_extractor_class": extractor,
            "features_extractor_kwargs": {"hidden": [16, 16], "gain_skip_init": 1.0, **extra},
        },
    )
    policy: Any = model.policy
    obs_t = _batch(_states(9, steps=4))
    mask = obs_t["action_mask"].numpy().astype(bool)
    values, log_prob, entropy = policy.evaluate_actions(
        obs_t, th.zeros(4, dtype=th.long), action_masks=mask
    )
    logits = policy.pi_features_extractor(obs_t)[:, : mask.shape[1]]
    allowed_logits = th.where(th.as_tensor(mask), logits, th.zeros_like(logits))
    loss = values.sum() + log_prob.sum() + entropy.sum() + allowed_logits.sum()
    policy.optimizer.zero_grad()
    loss.backward()
    for name, p in policy.named_parameters():
        assert p.grad is not None, name
        assert float(p.grad.abs().sum()) > 0.0, name
    # every kind of edit's logit depends on its receivers' observed features
    n = 9
    scorer = _scorer(n, hidden=[16], rank=4)
    obs = _batch(_states(n, steps=2)[-1:])
    obs["action_mask"][:] = 1.0
    rows = leave_rows(n)
    for edit, receivers in [
        (1 + 2 * n + 2, [2]),  # 2 leaves
        (1 + 2 * n + 5, [2, 5]),  # 2 joins 5's cluster
        (1 + n * n + 3, [0, 4]),  # swap pair 3: (0, 4)
    ]:
        white = obs["whitened"].clone().requires_grad_(True)
        (grad,) = th.autograd.grad(scorer({**obs, "whitened": white})[0, edit], white)
        for r in receivers:
            assert float(grad[0, rows[r]].abs().sum()) > 0.0, (edit, r)


# -- bad input -----------------------------------------------------------------------------------
def test_bad_input_is_refused_naming_the_argument() -> None:
    space = candidate_space(edit_action_count(5), 17)
    with pytest.raises(TypeError, match="observation_space"):
        FactorisedEditScorer({"gain": None})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="observation_space: count=100"):
        FactorisedEditScorer(candidate_space(100, 17))
    with pytest.raises(ValueError, match="whitened width 16"):
        FactorisedEditScorer(candidate_space(edit_action_count(5), 16))
    with pytest.raises(ValueError, match="rank must be >= 1"):
        FactorisedEditScorer(space, rank=0)
    with pytest.raises(TypeError, match="rank must be an int"):
        FactorisedEditScorer(space, rank=2.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="hidden"):
        FactorisedEditScorer(space, hidden=[8, 0])
    with pytest.raises(ValueError, match="activation"):
        FactorisedEditScorer(space, activation="gelu")
    with pytest.raises(ValueError, match="scorer must be one of"):
        scorer_policy_kwargs("transformer")
    assert scorer_policy_kwargs("mlp") == (CandidateScorer, {})
    assert train_clustering_ppo.parse_args([]).scorer == "factorised"
    with pytest.raises(ValueError, match="--scorer must be one of"):
        train_clustering_ppo.main(["--scorer=deep", "--out=/nonexistent/x.zip", "--force"])


# -- checkpoints ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    """A factorised checkpoint trained for 256 steps by the script, and its in-memory model."""
    out = tmp_path_factory.mktemp("edit") / "clu.zip"
    models: list[Any] = []

    def capturing(*args: Any, **kwargs: Any) -> Any:
        models.append(make_ppo(*args, **kwargs))
        return models[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(training, "make_ppo", capturing)
        meta = train_clustering_ppo.main(
            [
                *TINY,
                "--total-timesteps=256",
                "--vec-env=dummy",
                '--env-kwargs={"n_agents": 9, "horizon": 10}',
                "--rank-states=0",
                "--verify-top-k=",
                "--eval-episodes=0",
                "--hidden=32,32",
                "--edit-rank=8",
                f"--out={out}",
                "--tensorboard-dir=",
            ]
        )
    assert meta["training"]["timesteps_done"] == 256 and len(models) == 1
    return out, models[0]


def test_checkpoint_records_the_architecture(trained: tuple[Path, Any]) -> None:
    out, model = trained
    meta = json.loads(out.with_suffix(".json").read_text())
    arch = meta["architecture"]
    assert arch["features_extractor"] == EDIT_EXTRACTOR and arch["rank"] == 8
    assert arch["hidden"] == [32, 32] and meta["training"]["scorer"] == "factorised"
    assert arch["n_parameters"] == sum(p.numel() for p in model.policy.parameters())
    algo, kwargs = edit_policy_spec(meta, "x")
    assert algo == "MaskablePPO" and kwargs["features_extractor_class"] is FactorisedEditScorer


@pytest.mark.parametrize("lean", [True, False])
def test_checkpoint_round_trip_acts_like_the_trained_model(
    trained: tuple[Path, Any], lean: bool
) -> None:
    out, model = trained
    agent = SB3PolicyAgent(out, env_id=CLU_ID, lean=lean)
    loaded = agent._policies[edit_action_count(9)]
    assert isinstance(loaded.pi_features_extractor, FactorisedEditScorer)
    for name, p in loaded.state_dict().items():
        th.testing.assert_close(p, model.policy.state_dict()[name], rtol=0, atol=0)
    model.policy.set_training_mode(False)
    env = _edit_env(9, horizon=10)
    view = view_for(CLU_ID, env)
    obs, info = env.reset(seed=11)
    agent.reset(env, seed=11)
    done, steps, moved = False, 0, 0
    while not done:
        cand = view(obs)
        mask = cand["action_mask"].astype(bool)
        expect, _ = model.predict(cand, action_masks=mask, deterministic=True)
        action = agent.act(obs, info)
        assert action == int(expect)
        scores = agent.scores(cand)
        with th.no_grad():
            obs_t, _ = model.policy.obs_to_tensor(cand)
            mine = model.policy.pi_features_extractor(obs_t)[0, : mask.size].numpy()
        np.testing.assert_array_equal(scores, mine)
        moved += int(action != 0)
        obs, _, terminated, truncated, info = env.step(action)
        done, steps = terminated or truncated, steps + 1
    assert steps == 10
    # the default (assignment) encoding and another receiver count rebuild the same weights
    play = gym.make(CLU_ID, n_agents=12, horizon=3)
    obs, info = play.reset(seed=2)
    agent.reset(play, seed=2)
    labels = agent.act(obs, info)
    assert np.shape(labels) == (12,)


def test_edit_model_from_checkpoint_continues_from_the_weights(trained: tuple[Path, Any]) -> None:
    out, model = trained
    meta = load_metadata(out)
    env = CandidateViewWrapper(_edit_env(9), view_for(CLU_ID, _edit_env(9)))
    again = edit_model_from_checkpoint(out, meta, env)
    for name, p in again.policy.state_dict().items():
        th.testing.assert_close(p, model.policy.state_dict()[name], rtol=0, atol=0)
    policy = load_edit_policy(out, meta)
    assert isinstance(policy, CandidateScoringPolicy) and not policy.training


def test_tampered_factorised_metadata_is_refused(trained: tuple[Path, Any]) -> None:
    out, _ = trained
    meta = load_metadata(out)
    arch = meta["architecture"]
    with pytest.raises(ValueError, match="weights do not fit"):
        load_edit_policy(out, {**meta, "architecture": {**arch, "rank": 4}})
    with pytest.raises(ValueError, match=r"architecture\.rank must be a positive integer"):
        load_edit_policy(out, {**meta, "architecture": {**arch, "rank": "8"}})
    with pytest.raises(ValueError, match="architecture policy"):
        load_edit_policy(out, {**meta, "architecture": {**arch, "policy": "os.system"}})
    with pytest.raises(ValueError, match=r"training\.algorithm"):
        load_edit_policy(out, {**meta, "training": {"algorithm": "DQN"}})
    # a near miss of the exact extractor string goes to the MLP loader, which refuses it
    near = {**meta, "architecture": {**arch, "features_extractor": EDIT_EXTRACTOR + " "}}
    with pytest.raises(ValueError, match="features_extractor"):
        load_policy(out, near)
    with pytest.raises(ValueError, match="top_m=2"):
        SB3PolicyAgent(out, env_id=CLU_ID, top_m=2)


def test_dagger_fresh_factorised_policy_from_the_shipped_mlp() -> None:
    meta = load_metadata(SHIPPED)
    env = CandidateViewWrapper(_edit_env(9), view_for(CLU_ID, _edit_env(9)))
    model, arch = train_clustering_dagger.fresh_model(meta, env, "factorised", 8, seed=0)
    assert isinstance(model.policy.pi_features_extractor, FactorisedEditScorer)
    assert arch["features_extractor"] == EDIT_EXTRACTOR and arch["hidden"] == [128, 128]
    _, kwargs = edit_policy_spec({**meta, "architecture": arch})
    assert kwargs["features_extractor_kwargs"]["rank"] == 8
    assert train_clustering_dagger.parse_args([]).scorer == "checkpoint"


# -- the shipped (MLP) checkpoint ----------------------------------------------------------------
def test_the_shipped_mlp_checkpoint_loads_and_acts_as_before() -> None:
    meta = load_metadata(SHIPPED)
    assert meta["architecture"]["features_extractor"].endswith("candidate_policy.CandidateScorer")
    reference = load_policy(SHIPPED, meta)  # the loader the agent used before this scorer
    agent = SB3PolicyAgent(env_id=CLU_ID)
    policy = agent._policies[meta["obs_layout"]["n_candidates_trained"]]
    extractor = policy.pi_features_extractor
    assert type(extractor) is CandidateScorer
    assert type(policy) is type(reference)
    for name, p in policy.state_dict().items():
        th.testing.assert_close(p, reference.state_dict()[name], rtol=0, atol=0)
    env = gym.make(CLU_ID, n_agents=30, horizon=4, action_mode="edit")
    view = view_for(CLU_ID, env)
    obs, info = env.reset(seed=7)
    agent.reset(env, seed=7)
    for _ in range(4):
        cand = view(obs)
        mask = cand["action_mask"].astype(bool)
        expect, _ = reference.predict(cand, action_masks=mask, deterministic=True)  # type: ignore[call-arg]
        action = agent.act(obs, info)
        assert action == int(expect)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
