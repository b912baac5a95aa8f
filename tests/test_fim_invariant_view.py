"""The d-independent candidate view of FIMSelection and the configuration mixture it trains on.

The statistics are checked against a second formulation (explicit d x d information matrices
and log-determinant differences), for invariance under rotations and zero padding of the
whitened rows, and on every preset of the env.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from numpy.testing import assert_allclose

import selenv  # noqa: F401
from selenv.exits import UsageError
from selenv.families.fim.view import WIDTH, FIMInvariantView, invariant_features
from selenv.learned.rl.mixture import MIXTURES, EnvMixture, parse_mixture
from selenv.learned.rl.views import view_for

ENV_ID = "selenv/FIMSelection-v1"
PRESETS = ("example1", "example2", "example3", "example1_moving", "example2_moving",
           "example3_moving")  # fmt: skip


def _pool(seed: int, n: int = 25, m: int = 2, d: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    Z = rng.normal(size=(n, m, d)) * rng.uniform(0.1, 1.5, size=(n, 1, 1))
    Z[3, 1] = 0.0  # a one-row (Doppler-like) candidate
    unselected = np.ones(n, dtype=bool)
    unselected[[2, 7, 11]] = False
    return Z, unselected


def _logdet(A: np.ndarray) -> float:
    sign, value = np.linalg.slogdet(A)
    assert sign > 0
    return float(value)


def _gain(Z: np.ndarray, k: int, F: np.ndarray) -> float:
    """``log det(F + Z_k^T Z_k) - log det F``: the information form, no Woodbury."""
    return _logdet(F + Z[k].T @ Z[k]) - _logdet(F)


@pytest.mark.parametrize("closed_form", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("steps_left", [0, 1, 6])
def test_statistics_match_explicit_information_matrices(
    seed: int, steps_left: int, closed_form: bool
) -> None:
    Z, unselected = _pool(seed)
    d = Z.shape[2]
    got = invariant_features(Z, unselected, steps_left, closed_form=closed_form)
    idx = np.flatnonzero(unselected)
    eye = np.eye(d)
    gains = {k: _gain(Z, k, eye) for k in idx}
    ranked = sorted(idx, key=lambda k: -gains[k])
    t, s = ranked[0], ranked[1]
    S = sum(Z[j].T @ Z[j] for j in idx)
    beta = steps_left / idx.size
    for k in idx:
        lam = np.sort(np.linalg.eigvalsh(Z[k] @ Z[k].T))[::-1]
        after = _gain(Z, k, eye + Z[s].T @ Z[s] if k == t else eye + Z[t].T @ Z[t])
        C = Z[k] @ Z[t].T
        want = [
            np.log1p(lam[0]),
            np.log1p(lam[1]),
            after,
            after / gains[k],
            _gain(Z, k, eye + beta * S),
            np.sum(C * C) / (np.trace(Z[k] @ Z[k].T) * np.trace(Z[t] @ Z[t].T)),
            np.log1p(steps_left),
        ]
        assert_allclose(got[k], want, rtol=1e-9, atol=1e-12)
    assert not got[~unselected].any()  # selected candidates: zero rows
    assert got[t, 2] < gains[t] and got[t, 3] < 1.0  # t's gain survives s only in part


def test_closed_form_and_stacked_paths_agree_on_random_pools() -> None:
    rng = np.random.default_rng(1)
    for _ in range(40):
        n, d = int(rng.integers(2, 60)), int(rng.integers(2, 9))
        Z = rng.normal(size=(n, 2, d)) * rng.uniform(0.01, 3.0, size=(n, 1, 1))
        Z[rng.random(n) < 0.3, 1] = 0.0  # one-row candidates: a zero eigenvalue
        unselected = rng.random(n) < 0.8
        unselected[0] = True
        r = int(rng.integers(0, 20))
        assert_allclose(
            invariant_features(Z, unselected, r),
            invariant_features(Z, unselected, r, closed_form=False),
            rtol=1e-9,
            atol=1e-12,
        )


def test_statistics_are_invariant_to_rotations_and_zero_padding() -> None:
    Z, unselected = _pool(5, d=6)
    base = invariant_features(Z, unselected, 3)
    Q, _ = np.linalg.qr(np.random.default_rng(9).normal(size=(6, 6)))
    assert_allclose(invariant_features(Z @ Q, unselected, 3), base, rtol=1e-9, atol=1e-12)
    padded = np.concatenate([Z, np.zeros((*Z.shape[:2], 2))], axis=2)
    assert_allclose(invariant_features(padded, unselected, 3), base, rtol=1e-9, atol=1e-12)
    # but not to a change of the pool: the statistics see the other candidates
    other = unselected.copy()
    other[int(np.argmax(base[:, 0] + base[:, 1]))] = False
    assert not np.allclose(invariant_features(Z, other, 3)[other], base[other])


def test_edge_cases_one_candidate_left_and_none() -> None:
    Z, _ = _pool(3)
    one = np.zeros(len(Z), dtype=bool)
    one[4] = True
    row = invariant_features(Z, one, 1)[4]
    gain = _gain(Z, 4, np.eye(Z.shape[2]))
    assert_allclose(row[2], gain, rtol=1e-9)  # nothing else to pick first
    assert_allclose(row[3], 1.0, rtol=1e-9)
    assert not invariant_features(Z, np.zeros(len(Z), dtype=bool), 0).any()


@pytest.mark.parametrize("preset", PRESETS)
def test_view_on_every_preset_has_one_width_and_tracks_the_episode(preset: str) -> None:
    env = gym.make(ENV_ID, preset=preset, budget=4)
    view = view_for(ENV_ID, env, "invariant")
    assert isinstance(view, FIMInvariantView)
    space = view.space(env.observation_space)
    n = env.unwrapped.n  # type: ignore[attr-defined]
    assert space["whitened"].shape == (n, WIDTH)
    obs, _ = env.reset(seed=11)
    for step in range(4):
        cand = view(obs)
        assert space.contains(cand)
        assert_allclose(cand["whitened"][obs["action_mask"] > 0, 6], np.log1p(4 - step), rtol=1e-6)
        assert not cand["whitened"][obs["selected"] > 0].any()
        # the first two statistics are the observed log-det gain, split by eigenvalue
        logdet = cand["whitened"][:, 0] + cand["whitened"][:, 1]
        open_ = obs["action_mask"] > 0
        assert_allclose(logdet[open_], obs["gain"][open_], rtol=1e-4, atol=1e-5)
        obs, *_ = env.step(int(np.argmax(np.where(open_, obs["gain"], -1.0))))
    last = view(obs)["whitened"]  # budget spent: no pick left, so nothing to share it with
    assert not last[:, 6].any()
    assert_allclose(last[:, 4], last[:, 0] + last[:, 1], rtol=1e-5, atol=1e-6)


def test_view_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="m must be a positive integer"):
        FIMInvariantView(0, 5)
    with pytest.raises(ValueError, match="budget must be a positive integer"):
        FIMInvariantView(2, True)
    with pytest.raises(ValueError, match="not a multiple of m = 3"):
        FIMInvariantView(3, 5).space(gym.make(ENV_ID).observation_space)


def test_mixture_is_deterministic_and_plays_every_configuration() -> None:
    configs = [{"preset": "example1", "n_candidates": 40, "budget": 2},
               {"preset": "example2_moving", "n_candidates": 20, "budget": 3}]  # fmt: skip
    runs = []
    for _ in range(2):
        env = EnvMixture(ENV_ID, configs, "invariant")
        env.reset(seed=4)
        seen, trace = set(), []
        for _episode in range(8):
            obs, info = env.reset()
            seen.add(info["mixture_index"])
            done = False
            length = 0
            while not done:
                mask = env.action_masks()
                assert np.array_equal(mask, obs["action_mask"] > 0)
                obs, reward, term, trunc, _ = env.step(int(np.flatnonzero(mask)[0]))
                trace.append(reward)
                done = term or trunc
                length += 1
            assert length == configs[info["mixture_index"]]["budget"]
        runs.append(trace)
        assert seen == {0, 1}
    assert runs[0] == runs[1]


def test_mixture_refuses_configurations_of_another_pool_size() -> None:
    configs = [
        {"preset": "example1", "n_candidates": 40},
        {"preset": "example2", "n_candidates": 40},
    ]
    with pytest.raises(ValueError, match="same pool size"):
        EnvMixture(ENV_ID, configs, "invariant")
    with pytest.raises(ValueError, match="at least one"):
        EnvMixture(ENV_ID, [], "invariant")


def test_parse_mixture() -> None:
    assert parse_mixture("kirchner_presets") == MIXTURES["kirchner_presets"]
    assert len(MIXTURES["kirchner_presets"]) == 24
    assert parse_mixture('[{"budget": 3}]') == [{"budget": 3}]
    for bad in ("nope", "[]", "[1]", "{}"):
        with pytest.raises(ValueError, match="--mixture must be one of"):
            parse_mixture(bad)


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--view", "raw"], "--view must be one of"),
        (["--mixture", "kirchner_presets"], "--mixture needs --view invariant"),
        (["--view", "invariant", "--mixture", "kirchner_presets"], "add --vec-env dummy"),
        (["--view", "invariant", "--mixture", "x"], "--mixture must be one of"),
    ],
)
def test_training_script_refuses_bad_view_and_mixture_options(tmp_path, argv, match) -> None:
    from selenv.train import train_fim_ppo

    with pytest.raises(UsageError, match=match):
        train_fim_ppo.main([*argv, "--out", str(tmp_path / "p.zip"), "--no-progress"])
    assert not list(tmp_path.iterdir())  # refused before any work


def test_shipped_argument_takes_a_plain_file_name_only() -> None:
    from selenv.learned.rl.agent import make_ppo_agent

    for bad in ("../fim_selection_ppo.zip", "/tmp/x.zip", ""):
        with pytest.raises(ValueError, match="shipped must be a file name"):
            make_ppo_agent(shipped=bad)
    with pytest.raises(ValueError, match="not both"):
        make_ppo_agent(shipped="fim_selection_ppo.zip", checkpoint="x.zip")


@pytest.mark.parametrize(("preset", "budget"), [("example1", 5), ("example3_moving", 20)])
def test_shipped_general_policy_plays_other_presets_and_budgets(preset: str, budget: int) -> None:
    from selenv.agents import make

    agent = make("ppo_general", ENV_ID)
    env = gym.make(ENV_ID, preset=preset, budget=budget)
    obs, info = env.reset(seed=3)
    agent.reset(env, seed=3)
    picks = []
    done = False
    while not done:
        action = int(agent.act(obs, info))
        assert obs["action_mask"][action]  # a valid pick, never a refusal
        picks.append(action)
        obs, _, term, trunc, info = env.step(action)
        done = term or trunc
    assert len(set(picks)) == budget
