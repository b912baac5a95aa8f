"""Selection solvers against brute force, the (1 - 1/e) bound and each other."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import random_pool, random_spd

from selenv.agents.fim_solvers import (
    brute_force,
    cooperative_greedy,
    greedy,
    greedy_whitened,
    lazy_greedy,
    random_selection,
    swap,
)
from selenv.core.information import logdet_objective, whiten

BOUND = 1 - 1 / math.e


def _small(seed: int, m: int = 1):
    r = np.random.default_rng(seed)
    d = int(r.integers(2, 6))
    Q0 = random_spd(r, d, float(r.choice([0.05, 1.0])))
    H, R = random_pool(r, 12, d, m=m, pad=(m == 2))
    return Q0, H, R


@pytest.mark.parametrize("m", [1, 2])
def test_greedy_within_bound_and_close_to_optimum(m):
    gaps = []
    for seed in range(40):
        Q0, H, R = _small(seed, m)
        B = 1 + seed % 5
        opt = brute_force(Q0, H, R, B)
        g = greedy(Q0, H, R, B)
        assert g.objective >= BOUND * opt.objective - 1e-12
        assert g.objective <= opt.objective + 1e-9
        gaps.append((opt.objective - g.objective) / opt.objective)
        # brute force is really optimal: no random subset beats it
        r = np.random.default_rng(seed)
        G = whiten(H, R)
        Q0v = Q0
        for _ in range(30):
            S = r.choice(12, B, replace=False)
            assert logdet_objective(Q0v, G, S) <= opt.objective + 1e-9
    assert np.mean(gaps) < 0.01  # greedy is close to optimal on small instances


def test_lazy_greedy_picks_exactly_greedy_with_fewer_evaluations():
    r = np.random.default_rng(3)
    Q0 = random_spd(r, 8)
    H, R = random_pool(r, 400, 8, m=2, pad=True)
    g, lz = greedy(Q0, H, R, 20), lazy_greedy(Q0, H, R, 20)
    assert lz.indices == g.indices
    assert lz.objective == pytest.approx(g.objective, rel=1e-12)
    assert lz.evaluations < g.evaluations


def test_swap_never_worse_than_greedy_and_usually_optimal():
    hits = 0
    for seed in range(30):
        Q0, H, R = _small(seed + 100, m=1 + seed % 2)
        B = 2 + seed % 4
        g, s, o = greedy(Q0, H, R, B), swap(Q0, H, R, B), brute_force(Q0, H, R, B)
        assert s.objective >= g.objective - 1e-12
        assert s.objective <= o.objective + 1e-9
        hits += s.objective >= o.objective - 1e-9
    assert hits >= 27


def test_brute_force_size_guard():
    r = np.random.default_rng(0)
    H, R = random_pool(r, 60, 3)
    with pytest.raises(ValueError, match="refuses C\\(60, 10\\)"):
        brute_force(np.eye(3), H, R, 10)


def test_budget_validation():
    r = np.random.default_rng(0)
    H, R = random_pool(r, 5, 3)
    with pytest.raises(ValueError, match="larger than the pool"):
        greedy(np.eye(3), H, R, 6)
    with pytest.raises(ValueError, match="budget"):
        greedy(np.eye(3), H, R, -1)
    with pytest.raises(TypeError, match="budget"):
        greedy(np.eye(3), H, R, 2.0)


def test_scalar_form_equals_block_form():
    r = np.random.default_rng(5)
    Q0 = random_spd(r, 4)
    H = r.normal(size=(30, 4))
    var = r.uniform(0.1, 2.0, size=30)
    a = greedy(Q0, H, var, 6)
    b = greedy(Q0, H[:, None, :], var[:, None, None], 6)
    assert a.indices == b.indices


def test_random_selection_is_seeded():
    r = np.random.default_rng(0)
    H, R = random_pool(r, 30, 3)
    a = random_selection(np.eye(3), H, R, 5, rng=np.random.default_rng(7))
    b = random_selection(np.eye(3), H, R, 5, rng=np.random.default_rng(7))
    assert a == b and len(set(a.indices)) == 5


def test_cooperative_greedy_matches_its_definition():
    r = np.random.default_rng(11)
    d = 5
    Q0 = random_spd(r, d, 0.1)
    pools = [random_pool(r, 50, d, m=2, pad=True) for _ in range(3)]
    budgets = [4, 3, 5]
    ind = cooperative_greedy(Q0, pools, budgets, mode="independent")
    coop = cooperative_greedy(Q0, pools, budgets, mode="cooperative")
    prior = Q0.copy()
    for i, ((H, R), B) in enumerate(zip(pools, budgets, strict=True)):
        G = whiten(H, R)
        assert ind.selections[i].indices == greedy_whitened(Q0, G, B).indices
        assert coop.selections[i].indices == greedy_whitened(prior, G, B).indices
        sel = G[list(coop.selections[i].indices)].reshape(-1, d)
        prior = prior + sel.T @ sel
    assert coop.objective == pytest.approx(
        np.linalg.slogdet(prior)[1] - np.linalg.slogdet(Q0)[1], rel=1e-10
    )
    with pytest.raises(ValueError, match="mode"):
        cooperative_greedy(Q0, pools, budgets, mode="joint")


def test_solver_options_are_validated() -> None:
    import numpy as np

    from selenv.agents.fim_solvers import brute_force, swap

    rng = np.random.default_rng(0)
    Q0, H, R = np.eye(3), rng.normal(size=(8, 3)), np.ones(8)
    with pytest.raises(ValueError, match="max_subsets must be an int"):
        brute_force(Q0, H, R, 2, max_subsets=float("nan"))  # NaN used to skip the size guard
    with pytest.raises(ValueError, match="max_rounds must be >= 0"):
        swap(Q0, H, R, 2, max_rounds=-1)


def test_multiagent_budgets_type() -> None:
    from selenv.multiagent import fim_selection_v0

    with pytest.raises(TypeError, match="budgets must be an int or a sequence"):
        fim_selection_v0.parallel_env(budgets=2.0)


def test_vns_options_and_exhausted_neighbourhoods() -> None:
    import numpy as np

    from selenv.agents.fim_solvers import brute_force
    from selenv.agents.vns import vns

    rng = np.random.default_rng(1)
    Q0, H, R = np.eye(3), rng.normal(size=(8, 3)), np.ones(8)
    with pytest.raises(ValueError, match="initial must hold integer indices"):
        vns(Q0, H, R, 2, initial=[0.9, 3.2])  # used to be truncated to [0, 3]
    with pytest.raises(ValueError, match=r"l_max must be an int <= min\(K, N - K\) = 2"):
        vns(Q0, H, R, 2, l_max=5)  # used to fail with "not enough values to unpack"
    sel = vns(Q0, H, R, 2, m_l=(10**6,), rng=0)  # every neighbourhood is enumerated once
    # C(2,1) C(6,1) + C(2,2) C(6,2) = 27 candidates per pass, a few passes; before the fix it
    # re-enumerated each exhausted neighbourhood until 10**6 draws (minutes)
    assert sel.evaluations < 200
    assert sel.objective == pytest.approx(brute_force(Q0, H, R, 2).objective)
