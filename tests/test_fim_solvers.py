"""Selection solvers against brute force, the (1 - 1/e) bound and each other."""

from __future__ import annotations

import math

import mpmath
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
    swap_deltas,
    swap_whitened,
    whiten_in,
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


# -- swap deltas: the closed-form Schur complement against the determinant lemma and mpmath -----

_SEL = np.array([0, 3, 6, 8])
_UNS = np.setdiff1d(np.arange(10), _SEL)


def _delta_pool(kind: str, m: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A ``(Q0, G)`` pool of 10 candidates in ``d = 4``; ``kind`` makes it near-degenerate."""
    r = np.random.default_rng(seed)
    d, N = 4, 10
    Q0 = random_spd(r, d)
    G = r.normal(size=(N, m, d))
    if kind == "tiny_prior":  # the selection holds (nearly) all the information
        Q0 = 1e-6 * Q0
    elif kind == "duplicates":  # exact ties between pairs
        G[5:] = G[:5]
    elif kind == "collinear":  # each candidate's rows (nearly) parallel
        G[:, -1] = G[:, 0] * (1 + 1e-9) + (1e-7 * r.normal(size=(N, d)) if m > 1 else 0.0)
    elif kind == "spread":  # candidates from 1e-3 to 1e3 in scale
        G = G * 10.0 ** r.uniform(-3, 3, (N, 1, 1))
    return Q0, G


def _mp_deltas(Q0: np.ndarray, G: np.ndarray, sel: np.ndarray, uns: np.ndarray) -> np.ndarray:
    """``log det(A - Q_i + Q_j) - log det A`` in 50-digit arithmetic on the float64 inputs."""
    with mpmath.workdps(50):
        Qk = [mpmath.matrix(g.T.tolist()) * mpmath.matrix(g.tolist()) for g in G]
        A = mpmath.matrix(Q0.tolist())
        for k in sel:
            A += Qk[k]
        base = mpmath.log(mpmath.det(A))
        return np.array(
            [[float(mpmath.log(mpmath.det(A - Qk[i] + Qk[j])) - base) for j in uns] for i in sel]
        )


def _lemma_deltas(Q0: np.ndarray, G: np.ndarray, sel: np.ndarray, uns: np.ndarray) -> np.ndarray:
    """The same deltas pair by pair: ``slogdet`` of ``[[I - S_ii, -C_ij], [C_ij^T, I + S_jj]]``."""
    A = Q0 + sum(G[k].T @ G[k] for k in sel)
    P = np.linalg.solve(A, np.eye(A.shape[0]))
    eye = np.eye(G.shape[1])
    out = np.empty((sel.size, uns.size))
    for a, i in enumerate(sel):
        for b, j in enumerate(uns):
            M = np.block(
                [
                    [eye - G[i] @ P @ G[i].T, -G[i] @ P @ G[j].T],
                    [G[j] @ P @ G[i].T, eye + G[j] @ P @ G[j].T],
                ]
            )
            sign, value = np.linalg.slogdet(M)
            out[a, b] = value if sign > 0 else -np.inf
    return out


@pytest.mark.parametrize("kind", ["random", "tiny_prior", "duplicates", "collinear", "spread"])
@pytest.mark.parametrize("m", [1, 2, 3])
def test_swap_deltas_match_the_lemma_and_an_mpmath_reference(kind: str, m: int) -> None:
    """Closed forms (m = 1, 2) and the batched Schur complement (m = 3) to 1e-9 of mpmath.

    Tolerance: ``|delta - ref| <= 1e-9 (1 + |ref|)`` (rtol = atol = 1e-9; measured worst
    ~1e-11, on the ``spread`` pools). The pair-by-pair ``slogdet`` of the lemma matrix agrees
    with mpmath to 1e-5 only on ``spread`` pools (~1e-6 measured: it goes through ``A^-1``),
    1e-9 elsewhere.
    """
    for seed in range(2):
        Q0, G = _delta_pool(kind, m, seed)
        ref = _mp_deltas(Q0, G, _SEL, _UNS)
        fast = swap_deltas(whiten_in(Q0, G, _SEL), _SEL, _UNS)
        np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-9)
        lemma_tol = 1e-5 if kind == "spread" else 1e-9
        lemma = _lemma_deltas(Q0, G, _SEL, _UNS)
        np.testing.assert_allclose(lemma, ref, rtol=lemma_tol, atol=lemma_tol)
        if kind == "duplicates":  # candidate k + 5 repeats k: equal columns, exactly
            assert np.array_equal(fast[:, 1:3], fast[:, 4:6])  # uns 2, 4 vs 7, 9


@pytest.mark.parametrize("scale", [1e3, 1e4])
@pytest.mark.parametrize("m", [1, 2, 3])
def test_swap_deltas_when_one_candidate_holds_a_direction(m: int, scale: float) -> None:
    """Removing the only candidate that sees ``e_0``: ``1 - S_ii`` of 1e-9 / 1e-11.

    Both formulations lose ``eps / (1 - S_ii)`` to the cancellation in ``I - S_ii``; the
    closed form stays within ``atol = 10 eps / gap`` of mpmath (``gap``: the smallest
    eigenvalue of any ``I - S_ii``; measured up to 1.6 eps / gap), and nothing is NaN even
    when ``1 - S_ii`` rounds to ~eps.
    """
    r = np.random.default_rng(5)
    Q0 = 1e-3 * np.eye(4)
    G = r.normal(size=(10, m, 4))
    G[:, :, 0] *= 1e-3
    G[0] = 0.0
    G[0, 0, 0] = scale  # candidate 0 (selected) alone measures e_0
    Z = whiten_in(Q0, G, _SEL)
    Zs = Z[_SEL]
    gap = float(np.linalg.eigvalsh(np.eye(m) - Zs @ Zs.transpose(0, 2, 1)).min())  # of I - S_ii
    assert gap < 1e-8  # the instance really is near-degenerate
    ref = _mp_deltas(Q0, G, _SEL, _UNS)
    fast = swap_deltas(Z, _SEL, _UNS)
    np.testing.assert_allclose(fast, ref, rtol=0, atol=10 * np.finfo(float).eps / gap)
    assert ref[0].max() < -15  # dropping candidate 0 loses the direction: the worst swaps
    G[0, 0, 0] = 1e6  # 1 - S_ii ~ eps: rounding, but never NaN (-inf for a non-PD pair)
    assert not np.isnan(swap_deltas(whiten_in(Q0, G, _SEL), _SEL, _UNS)).any()


def _reference_swap(Q0: np.ndarray, G: np.ndarray, start: np.ndarray) -> list[int]:
    """Best-improvement swaps from ``start`` with the pair-by-pair lemma deltas (the old pass)."""
    sel = start.copy()
    for _ in range(200):
        uns = np.setdiff1d(np.arange(G.shape[0]), sel)
        delta = _lemma_deltas(Q0, G, sel, uns)
        i, j = np.unravel_index(int(np.argmax(delta)), delta.shape)
        if delta[i, j] <= 1e-9:
            break
        sel[i] = uns[j]
    return sel.tolist()


@pytest.mark.parametrize("m", [1, 2, 3])
def test_swap_makes_the_moves_of_the_lemma_search(m: int) -> None:
    """swap_whitened's moves (slot by slot) are those of the pair-by-pair slogdet search.

    From random starts (many swaps per search) and from greedy's (swap's default).
    """
    passes = 0
    for seed in range(8):
        r = np.random.default_rng(200 + seed)
        Q0 = random_spd(r, 5, 0.1)
        G = r.normal(size=(16, m, 5)) * r.uniform(0.2, 2.0, (16, 1, 1))
        start = r.choice(16, size=4, replace=False)
        got = swap_whitened(Q0, G, 4, initial=start)
        assert list(got.indices) == _reference_swap(Q0, G, start)
        passes += got.evaluations // (4 * 12)
        greedy_start = np.array(greedy_whitened(Q0, G, 4).indices)
        assert list(swap_whitened(Q0, G, 4).indices) == _reference_swap(Q0, G, greedy_start)
    assert passes >= 8 * 3  # the searches did swap: at least 2 moves each on average
