"""The faster GA / labels / cost cache against recordings and the previous implementations.

GA traces and operator draws of the ``"literal"`` variant (integers: exact; the ``"improved"``
ones are in ``tests/test_clustering_ga.py``) were recorded with the code before the speed-ups.
GA runs on a :class:`ClusterFilterBank`, 300-step ``ga`` episodes and 120-step episodes of seven
agents in ``ReceiverClustering-v0`` are recorded with the current code as decisions (hashes of
int64 populations / assignments / discrete observations, counters, lengths: exact) and float
values (J, rewards, float observations: ``rtol = 1e-9``), so they hold on any machine and BLAS
kernel (checked under OpenBLAS Haswell and Prescott: identical decisions, values within 7e-16).
The final J of the episodes equals the pre-speed-up recordings (made on another machine) to
1e-15. The label helpers are compared with the previous implementations, kept here as small
reference functions.
"""

from __future__ import annotations

import hashlib

import gymnasium as gym
import numpy as np
import pytest
from test_clustering_ga import _trace

import selenv  # noqa: F401  (registers the env and agents)
from selenv.agents import make as make_agent
from selenv.agents.clustering_ga import (
    GAConfig,
    GeneticClustering,
    o1c_literal,
    o1m_literal,
    o2c_literal,
    o2m_literal,
    o3m,
)
from selenv.scenarios.clustering import ClusteringConfig, make_clustering_problem
from selenv.scenarios.clustering_filters import ClusterFilterBank, cluster_keys
from selenv.scenarios.clustering_labels import canonical_labels, random_feasible_clustering


# ----------------------------------------------------------------------------- references
def canonical_reference(x: np.ndarray) -> np.ndarray:
    """The pre-issue-19 ``canonical_labels``: ``np.unique`` with first indices, ranked."""
    _, first, inverse = np.unique(x, return_index=True, return_inverse=True)
    rank = np.empty(first.size, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(first.size)
    return rank[inverse.reshape(-1)]


def cluster_keys_reference(canon: np.ndarray) -> list[tuple[int, ...]]:
    """The pre-issue-19 ``cluster_keys``: stable argsort split at label changes."""
    order = np.argsort(canon, kind="stable")
    bounds = np.flatnonzero(np.diff(canon[order])) + 1
    return [tuple(int(i) for i in part) for part in np.split(order, bounds)]


@pytest.mark.parametrize("seed", range(40))
def test_canonical_labels_and_cluster_keys_match_the_references(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 40))
    for high in (2, n + 1, 10**12):
        x = rng.integers(0, high, size=n)
        small = high < 2**15
        for arr in (
            x,
            x.astype(np.int32) if small else x,
            x.astype(np.uint16) if small else x,
            list(x),
        ):
            got = canonical_labels(arr)
            ref = canonical_reference(np.asarray(arr).astype(np.int64))
            assert got.dtype == np.int64 and got.shape == (n,)
            np.testing.assert_array_equal(got, ref)
        canon = canonical_reference(x)
        assert cluster_keys(canon) == cluster_keys_reference(canon)
    xf = rng.integers(0, n + 1, size=n).astype(np.float64)
    np.testing.assert_array_equal(canonical_labels(xf), canonical_reference(xf.astype(np.int64)))


# ----------------------------------------------------------------------------- literal GA
LITERAL_CFG: dict[str, dict] = {
    "default": {},
    "ops10101": {"operators": (1, 0, 1, 0, 1), "population_size": 9},
    "ops01110": {"operators": (0, 1, 1, 1, 0), "redraw_partner": True, "max_size": 4},
}
LITERAL_RECORDED = {
    ("default", 0): ("0585af973373f0f5", [0, 1, 0, 2, 3, 1, 3, 3, 2, 1, 2, 0], -1.5175383866),
    ("default", 1): ("b5edf9665a6a04e8", [0, 0, 1, 2, 1, 0, 1, 2, 3, 3, 2, 3], -1.5479511654),
    ("default", 2): ("58bc68c9742b47b1", [0, 1, 2, 3, 3, 2, 2, 0, 1, 3, 0, 1], -1.9558762535),
    ("ops10101", 3): ("75f48ecf2f7f4b17", [0, 1, 2, 3, 3, 0, 3, 2, 1, 0, 1, 2], -1.354173008),
    ("ops01110", 4): ("4e47edea61c41e24", [0, 1, 1, 0, 2, 2, 1, 1, 2, 0, 0, 2], -1.3636830721),
}
LITERAL_OPS_RECORDED = "979f6d271102a572"


@pytest.mark.parametrize(("cfg", "seed"), list(LITERAL_RECORDED))
def test_literal_variant_is_bit_identical_to_the_recorded_runs(cfg: str, seed: int) -> None:
    got = _trace(seed, variant="literal", **LITERAL_CFG[cfg])
    want = LITERAL_RECORDED[(cfg, seed)]
    assert (got[0], got[1]) == want[:2]  # populations (int64 hash) and best labels: exact
    assert got[2] == pytest.approx(want[2], rel=1e-9, abs=1e-10)  # cost, rounded to 1e-10


def test_literal_operators_are_bit_identical_to_the_recorded_draws() -> None:
    rng = np.random.default_rng(7)
    a = np.array([0, 0, 1, 1, 2, 2, 3, 3, 4, 4])
    b = np.array([4, 3, 3, 2, 2, 1, 1, 0, 0, 4])
    h = hashlib.sha256()
    for _ in range(50):
        for c in (o1c_literal(a, b, rng, 3), o2c_literal(a, b, rng, 3), o1m_literal(a, rng, 3),
                  o2m_literal(a, rng, 2), o3m(a, rng, 3)):  # fmt: skip
            h.update(np.asarray(c, np.int64).tobytes())
    assert h.hexdigest()[:16] == LITERAL_OPS_RECORDED


# ----------------------------------------------------------------------------- on the filter bank
def _bank_trace(
    seed: int, variant: str, gens: int = 60
) -> tuple[str, tuple[int, ...], list[float]]:
    """(hash of the int64 populations, counters, J every 10 generations) of a bank GA run."""
    rng = np.random.default_rng(seed)
    problem = make_clustering_problem(ClusteringConfig(), rng)
    bank = ClusterFilterBank(problem, random_feasible_clustering(30, 3, rng))
    for _ in range(25):
        bank.step()
    ga = GeneticClustering(bank.evaluate, bank.labels, 3, GAConfig(variant=variant), rng=rng)
    h = hashlib.sha256()
    J: list[float] = []
    for g in range(gens):
        best, _ = ga.generation()
        h.update(ga.population.astype(np.int64).tobytes())  # decisions: exact
        bank.recluster(best)
        bank.step()
        if g % 10 == 9:
            J.append(float(bank.cost().J))
    counters = (ga.n_evaluations, bank.n_cost_evaluations, bank.n_cluster_passes)
    return h.hexdigest()[:16], counters, J


#: recorded with the current code (2026-12-02); populations and counters are decisions
#: (compared exactly), J values are compared to rtol 1e-9 (they hold on any BLAS kernel)
BANK_RECORDED = {
    ("improved", 0): (
        "4baed312354a003c",
        (1220, 1220, 1234),
        [
            0.22338722273052125,
            0.2015145645939339,
            0.18757406569166524,
            0.1856069819272569,
            0.18354016569189663,
            0.18351570109259246,
        ],
    ),
    ("improved", 1): (
        "94816d29602910bc",
        (1220, 1220, 1231),
        [
            0.18821203846480145,
            0.17576516005371898,
            0.17288504181807285,
            0.16996971195273936,
            0.167535486855133,
            0.1648429459749575,
        ],
    ),
    ("literal", 0): (
        "0e39429161516a6a",
        (1220, 1220, 878),
        [
            0.20406953375293152,
            0.18623918334536077,
            0.18567931557615,
            0.18556012675248992,
            0.18556014644073973,
            0.1839879138745542,
        ],
    ),
    ("literal", 1): (
        "e3066419dcef141d",
        (1220, 1220, 923),
        [
            0.18453695498847436,
            0.17945867128039766,
            0.1713374161064522,
            0.16795987403440127,
            0.16573949288943426,
            0.1630442545881258,
        ],
    ),
}


@pytest.mark.parametrize(("variant", "seed"), list(BANK_RECORDED))
def test_ga_on_the_filter_bank_matches_the_recording(variant: str, seed: int) -> None:
    pop_hash, counters, J = _bank_trace(seed, variant)
    want_hash, want_counters, want_J = BANK_RECORDED[(variant, seed)]
    assert (pop_hash, counters) == (want_hash, want_counters)
    np.testing.assert_allclose(J, want_J, rtol=1e-9, atol=0)


# ----------------------------------------------------------------------------- episodes
def _episode(seed: int, variant: str, steps: int = 300) -> tuple[str, int, list[float]]:
    """(hash of the int64 assignments, length, J every 50 steps and at the end) of an episode."""
    env = gym.make("selenv/ReceiverClustering-v0", preset="paper", horizon=steps)
    obs, info = env.reset(seed=seed)
    kw = {} if variant == "improved" else {"variant": "literal"}
    agent = make_agent("ga", "selenv/ReceiverClustering-v0", **kw)
    agent.reset(env, seed=seed)
    J = [float(info["objective"])]
    h = hashlib.sha256(obs["assignment"].astype(np.int64).tobytes())
    done = False
    while not done:
        obs, _r, term, trunc, info = env.step(agent.act(obs, info))
        J.append(float(info["objective"]))
        h.update(obs["assignment"].astype(np.int64).tobytes())
        done = term or trunc
    return h.hexdigest()[:16], len(J), [*J[::50], J[-1]]


#: recorded with the current code (2026-12-02): assignments exact, J to rtol 1e-9
EPISODE_RECORDED = {
    ("improved", 0): (
        "d1bf76fdaf098b85",
        301,
        [
            3.0,
            0.18598140788057765,
            0.17890323189788532,
            0.17745248896475624,
            0.17745260117217565,
            0.17745260117217568,
            0.17745260117217565,
            0.17745260117217565,
        ],
    ),
    ("improved", 1): (
        "5d7f38ffc5cac240",
        301,
        [
            3.0,
            0.16727985528326195,
            0.16520765832412032,
            0.16228216582709512,
            0.16184814321116422,
            0.16179675088230092,
            0.1610223511028624,
            0.1610223511028624,
        ],
    ),
    ("improved", 2): (
        "413beddc2202bb8d",
        301,
        [
            3.0,
            0.18710342071077785,
            0.18226949835858336,
            0.18183959774758038,
            0.1801522749349203,
            0.18015227493574823,
            0.18015227493574826,
            0.18015227493574826,
        ],
    ),
    ("literal", 0): (
        "d2b1210c59dcfd9a",
        301,
        [
            3.0,
            0.17984880788236293,
            0.177508359495555,
            0.176983315238264,
            0.17671960845838847,
            0.17666435265619868,
            0.17618767941354838,
            0.17618767941354838,
        ],
    ),
    ("literal", 1): (
        "bdbc5b1ca9b00c3e",
        301,
        [
            3.0,
            0.17030592010001955,
            0.16515033009936075,
            0.16424558148388058,
            0.1618950898692424,
            0.16168773245030754,
            0.1616209112466668,
            0.1616209112466668,
        ],
    ),
    ("literal", 2): (
        "244e9d995c4acb81",
        301,
        [
            3.0,
            0.1911283711403267,
            0.18719864763699068,
            0.18299674864843965,
            0.18106824075679176,
            0.1798755530203457,
            0.17987574547663818,
            0.17987574547663818,
        ],
    ),
}


@pytest.mark.parametrize(("variant", "seed"), list(EPISODE_RECORDED))
def test_ga_episode_matches_the_recorded_curve(variant: str, seed: int) -> None:
    got_hash, length, J = _episode(seed, variant)
    want_hash, want_length, want_J = EPISODE_RECORDED[(variant, seed)]
    assert (got_hash, length) == (want_hash, want_length)
    np.testing.assert_allclose(J, want_J, rtol=1e-9, atol=0)


# ----------------------------------------------------------------------------- internals
def test_canonicalize_rows_equals_the_row_loop() -> None:
    from selenv.scenarios.clustering_labels import canonicalize_rows

    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 30):
        for high in (1, 3, n + 5, 10**12):
            x = rng.integers(0, high, size=(20, n))
            got = canonicalize_rows(x)
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, np.stack([canonical_reference(r) for r in x]))


@pytest.mark.parametrize("per_step", [False, True])
@pytest.mark.parametrize("s", [1, 2, 3])
def test_window_pass_is_bit_identical_to_riccati_pass(per_step: bool, s: int) -> None:
    from selenv.core.riccati import riccati_pass
    from selenv.scenarios.clustering_filters import window_pass

    rng = np.random.default_rng(s)
    problem = make_clustering_problem(ClusteringConfig(), rng)
    F, Q, H = problem.axis_model(tuple(range(s)))
    B, steps, d = 5, 20, 2 * s + 1
    A = rng.normal(size=(B, d, d))
    P0 = A @ np.swapaxes(A, 1, 2) + np.eye(d)
    shape = (B, steps, 2 * s, 2 * s) if per_step else (B, 2 * s, 2 * s)
    R = np.zeros(shape) + np.eye(2 * s) * rng.uniform(0.1, 1.0, size=(*shape[:-1], 1))
    got, ref = window_pass(P0, F, Q, H, R, steps), riccati_pass(P0, F, Q, H, R, steps)
    assert got.tobytes() == ref.tobytes()
    zero = (np.zeros_like(P0), F, np.zeros_like(Q), H, np.zeros_like(R), steps)
    with pytest.raises(ValueError, match="singular at step 1") as exc:
        window_pass(*zero)
    with pytest.raises(ValueError, match="singular at step 1") as exc_ref:
        riccati_pass(*zero)
    assert str(exc.value) == str(exc_ref.value)


def test_evaluate_validates_the_batch_and_names_the_first_bad_row() -> None:
    rng = np.random.default_rng(0)
    problem = make_clustering_problem(ClusteringConfig(), rng)
    bank = ClusterFilterBank(problem, random_feasible_clustering(30, 3, rng))
    good = np.stack([random_feasible_clustering(30, 3, rng) for _ in range(4)])
    J = bank.evaluate(good)
    np.testing.assert_array_equal(bank.evaluate(good[::-1]), J[::-1])  # cached: same bits
    for bad, pattern in (
        (lambda c: c.__setitem__((2, 0), 30), r"candidates\[2\]: labels must lie in"),
        (lambda c: c.__setitem__((1, slice(0, 4)), 0), r"candidates\[1\]: cluster"),
    ):
        c = good.copy()
        bad(c)
        with pytest.raises(ValueError, match=pattern):
            bank.evaluate(c)
    with pytest.raises(ValueError, match=r"candidates\[3\] must hold integer labels"):
        bank.evaluate(np.vstack([good[:3], good[3:] + 0.5]))
    with pytest.raises(ValueError, match=r"candidates\[0\] must be an integer array"):
        bank.evaluate(good.astype(bool))
    np.testing.assert_array_equal(bank.evaluate(good.astype(np.float64)), J)


# ----------------------------------------------------------------------------- env steps
def _env_run(agent_spec: str, preset: str, seed: int = 0, steps: int = 120) -> tuple[str, list]:
    """(hash of every integer / bool / str entry, float summary) of a 120-step episode.

    Decisions and discrete observations (assignments, masks, counters, flags) are hashed
    exactly; every float (observation arrays, rewards, info values) goes into a summary
    ``[count, sum |x|, sum |x| * position]`` compared to rtol 1e-9 (no cancellation: a sum of
    absolute values; the position weight catches a reordering).
    """
    env = gym.make("selenv/ReceiverClustering-v0", preset=preset, horizon=steps)
    obs, info = env.reset(seed=seed)
    agent = make_agent(agent_spec, "selenv/ReceiverClustering-v0")
    agent.reset(env, seed=seed)
    h = hashlib.sha256()
    floats: list[np.ndarray] = []

    def feed(name: str, v: object) -> None:
        h.update(name.encode())
        a = np.asarray(v)
        if a.dtype.kind == "f":
            floats.append(a.astype(np.float64).ravel())
        elif a.dtype.kind in "iub":
            h.update(f"{a.shape}".encode())
            h.update(np.ascontiguousarray(a.astype(np.int64)).tobytes())
        else:
            h.update(repr(v).encode())

    def update(obs: dict, r: float, info: dict) -> None:
        for k in sorted(obs):
            feed(k, obs[k])
        feed("reward", r)
        for k in sorted(info):
            feed(k, info[k])

    update(obs, 0.0, info)
    done = False
    while not done:
        obs, r, term, trunc, info = env.step(agent.act(obs, info))
        update(obs, float(r), info)
        done = term or trunc
    x = np.abs(np.concatenate(floats))
    summary = [float(x.size), float(x.sum()), float((x * np.arange(1, x.size + 1)).sum())]
    return h.hexdigest()[:16], summary


#: recorded with the current code (2026-12-02): discrete data exact, floats to rtol 1e-9
ENV_RECORDED = {
    ("paper", "ga"): ("94ed5c36c38d89d7", [12100.0, 3875.193540738922, 23283365.94532694]),
    ("paper", "ga:variant=literal"): (
        "947acdfa935ad1ad",
        [12100.0, 3870.247763541694, 23268739.874504067],
    ),
    ("paper", "greedy"): ("382dfa3d023f1d3b", [12100.0, 3874.2174693921957, 23263028.944082607]),
    ("paper", "offline_static"): (
        "49cd41db9678909b",
        [12100.0, 3859.0366639381064, 23243683.647884466],
    ),
    ("paper", "fixed_random"): (
        "c8d8b669a51e6d18",
        [12100.0, 3922.8804005081683, 23621642.59324367],
    ),
    ("paper", "singletons"): ("c9501482fffcc610", [12100.0, 4147.092385451186, 24950568.13345376]),
    ("paper", "rollout"): ("709ec1ee4d6d2ec4", [12100.0, 3874.0406310680537, 23263278.141697228]),
    ("multipath", "ga"): ("930271daafd241a3", [12100.0, 6937.859628067323, 43560108.10750407]),
    ("multipath", "ga:variant=literal"): (
        "284f0135f294fd74",
        [12100.0, 6928.527399295278, 43468602.514235005],
    ),
    ("multipath", "greedy"): ("07a5573cb8c229b2", [12100.0, 6882.215143833831, 43074273.300283015]),
    ("multipath", "offline_static"): (
        "15d40422b839956a",
        [12100.0, 6956.19589447245, 43713457.19780667],
    ),
    ("multipath", "fixed_random"): (
        "a92a6cf690afb4ac",
        [12100.0, 7042.678018808044, 44402833.35434342],
    ),
    ("multipath", "singletons"): (
        "ed2ef6e559af1b41",
        [12100.0, 7997.145295909144, 50718158.878960855],
    ),
    ("multipath", "rollout"): (
        "9f64ee49fa6fd6de",
        [12100.0, 6881.977274052231, 43073102.510944396],
    ),
}


@pytest.mark.parametrize(("preset", "agent"), list(ENV_RECORDED))
def test_env_episode_matches_the_recording(preset: str, agent: str) -> None:
    got_hash, summary = _env_run(agent, preset)
    want_hash, want_summary = ENV_RECORDED[(preset, agent)]
    assert got_hash == want_hash
    np.testing.assert_allclose(summary, want_summary, rtol=1e-9, atol=0)
