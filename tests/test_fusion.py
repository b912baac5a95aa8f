"""Fusion with unknown correlation: CI family, DMV and PECMV against definitions and references.

Independent references here use plain ``np.linalg.inv`` / ``slogdet`` on the full matrices
(the definitions as printed), never the module's own helpers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import eigh
from scipy.optimize import minimize_scalar

import selenv.fusion as public
from selenv.core.fusion import (
    PECMVResult,
    covariance_intersection,
    dmv_cost,
    dmv_omega_batch,
    dmv_update,
    joint_covariance_is_admissible,
    pecmv_batch,
    pecmv_objective,
    pecmv_update,
)

inv = np.linalg.inv


def spd(rng: np.random.Generator, n: int, scale: float = 1.0, spread: float = 1.0) -> np.ndarray:
    """Random SPD matrix with eigenvalues ``scale * 10^U(-spread, spread)``."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    A = scale * (Q * 10.0 ** rng.uniform(-spread, spread, n)) @ Q.T
    return 0.5 * (A + A.T)


Problem = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def problem(
    rng: np.random.Generator, m: int | None = None, n: int | None = None, nj: int | None = None
) -> Problem:
    m = int(rng.integers(1, 3)) if m is None else m
    n = int(rng.integers(max(m, 2), 6)) if n is None else n
    nj = int(rng.integers(max(m, 2), 6)) if nj is None else nj
    P_i = spd(rng, n, 10 ** rng.uniform(-1, 1))
    P_j = spd(rng, nj, 10 ** rng.uniform(-2, 1))
    H_i, H_j = rng.normal(size=(m, n)), rng.normal(size=(m, nj))
    R = spd(rng, m, 10 ** rng.uniform(-2, 0), 0.5)
    return P_i, P_j, H_i, H_j, R


def random_contractions(
    rng: np.random.Generator, n_i: int, n_j: int, k: int = 6
) -> list[np.ndarray]:
    """Random ``C`` with ||C||_2 in {0.3, 0.9, 1} plus rank-one and isometric extremes."""
    out = []
    for norm in (0.3, 0.9, 1.0):
        C = rng.normal(size=(n_i, n_j))
        out.append(norm * C / np.linalg.norm(C, 2))
    for _ in range(k - 3):
        u, v = rng.normal(size=n_i), rng.normal(size=n_j)
        out.append(np.sign(rng.normal()) * np.outer(u / np.linalg.norm(u), v / np.linalg.norm(v)))
    U, _, Vt = np.linalg.svd(rng.normal(size=(n_i, n_j)), full_matrices=False)
    out.append(U @ Vt)  # all singular values 1
    return out


def true_cov(
    K: np.ndarray,
    P_i: np.ndarray,
    P_j: np.ndarray,
    H_i: np.ndarray,
    H_j: np.ndarray,
    R: np.ndarray,
    X: np.ndarray,
) -> np.ndarray:
    """Covariance of ``e_i - K (H_i e_i + H_j e_j + v)`` when ``Cov(e_i, e_j) = X``."""
    M = np.hstack([np.eye(P_i.shape[0]) - K @ H_i, -K @ H_j])
    P_J = np.block([[P_i, X], [X.T, P_j]])
    return M @ P_J @ M.T + K @ R @ K.T


def min_eig(A: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(0.5 * (A + A.T))[0])


def pbar_information(w: float, *pr: np.ndarray) -> np.ndarray:
    """Eq. (5), information form, with explicit inverses (the reference)."""
    P_i, P_j, H_i, H_j, R = pr
    B = H_j @ P_j @ H_j.T
    return inv(w * inv(P_i) + (1 - w) * H_i.T @ inv(B + (1 - w) * R) @ H_i)


def pbar_kalman(w: float, *pr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    P_i, P_j, H_i, H_j, R = pr
    S = H_i @ P_i @ H_i.T / w + H_j @ P_j @ H_j.T / (1 - w) + R
    K = P_i / w @ H_i.T @ inv(S)
    return (np.eye(len(P_i)) - K @ H_i) @ P_i / w, K


# ------------------------------------------------------------------------------------- DMV


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_dmv_bound_is_conservative_for_every_admissible_X(seed: int) -> None:
    rng = np.random.default_rng(seed)
    P_i, P_j, H_i, H_j, R = problem(rng)
    res = dmv_update(P_i, P_j, H_i, H_j, R)
    L_i, L_j = np.linalg.cholesky(P_i), np.linalg.cholesky(P_j)
    for w in {res.omega, 0.2, 0.7} - {1.0}:
        out = dmv_update(P_i, P_j, H_i, H_j, R, omega=w)
        for C in random_contractions(rng, len(P_i), len(P_j)):
            X = L_i @ C @ L_j.T
            P_true = true_cov(out.K, P_i, P_j, H_i, H_j, R, X)
            assert min_eig(out.P - P_true) >= -1e-9 * np.abs(out.P).max()


@pytest.mark.parametrize("m", [1, 2, 3])
def test_dmv_kalman_and_information_forms_agree(rng: np.random.Generator, m: int) -> None:
    for _ in range(5):
        P_i, P_j, H_i, H_j, R = problem(rng, m=m, n=m + 2)
        for w in (1e-4, 0.05, 0.5, 0.95):  # 1e-4 uses the module's information form
            out = dmv_update(P_i, P_j, H_i, H_j, R, omega=w)
            P_info = pbar_information(w, P_i, P_j, H_i, H_j, R)
            P_kal, K_kal = pbar_kalman(w, P_i, P_j, H_i, H_j, R)
            np.testing.assert_allclose(P_info, P_kal, rtol=1e-8, atol=1e-10 * np.abs(P_kal).max())
            np.testing.assert_allclose(out.P, P_info, rtol=1e-7, atol=1e-9 * np.abs(P_info).max())
            np.testing.assert_allclose(out.K, K_kal, rtol=1e-7, atol=1e-9 * np.abs(K_kal).max())


@pytest.mark.parametrize("m", [1, 2])
def test_dmv_cheap_cost_equals_log_det_of_full_matrix(rng: np.random.Generator, m: int) -> None:
    for _ in range(5):
        P_i, P_j, H_i, H_j, R = problem(rng, m=m)
        ws = np.array([0.01, 0.3, 0.6, 0.99])
        direct = [np.linalg.slogdet(pbar_information(w, P_i, P_j, H_i, H_j, R))[1] for w in ws]
        np.testing.assert_allclose(dmv_cost(ws, P_i, P_j, H_i, H_j, R), direct, atol=1e-9)
        assert dmv_cost(1.0, P_i, P_j, H_i, H_j, R) == pytest.approx(np.linalg.slogdet(P_i)[1])


def _reference_omega(*pr: np.ndarray) -> tuple[float, float]:
    """Bounded minimisation of log det Pbar (full matrices) refined on a dense grid."""
    P_i = pr[0]

    def f(w: float) -> float:
        return float(np.linalg.slogdet(pbar_information(w, *pr))[1])

    grid = np.linspace(1e-3, 1 - 1e-6, 400)
    vals = [f(w) for w in grid]
    k = int(np.argmin(vals))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    best = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
    cands = [(float(best.fun), float(best.x)), (float(np.linalg.slogdet(P_i)[1]), 1.0)]
    return min(cands)


@pytest.mark.parametrize("m", [1, 2, 3])
def test_dmv_optimal_omega_matches_bounded_minimisation(rng: np.random.Generator, m: int) -> None:
    interior = 0
    for _ in range(12):
        P_i, P_j, H_i, H_j, R = problem(rng, m=m, n=int(rng.integers(m + 1, 10)))
        P_j *= 10 ** rng.uniform(-2, 0)  # agent j better localised: updates are common
        res = dmv_update(P_i, P_j, H_i, H_j, R)
        f_ref, w_ref = _reference_omega(P_i, P_j, H_i, H_j, R)
        assert res.log_det <= f_ref + 1e-10
        assert res.log_det == pytest.approx(np.linalg.slogdet(res.P)[1], abs=1e-9)
        if 0 < w_ref < 1:
            interior += 1
            assert res.omega == pytest.approx(w_ref, abs=1e-5)
    assert interior >= 6


def test_dmv_no_update_rule_both_ways(rng: np.random.Generator) -> None:
    for m in (1, 2):
        for _ in range(5):
            P_i, P_j, H_i, H_j, R = problem(rng, m=m)
            n = len(P_i)
            A, B = H_i @ P_i @ H_i.T, H_j @ P_j @ H_j.T
            t0 = np.trace(inv(B) @ A)  # tr(B^-1 A) scales as 1/t when P_j -> t P_j
            for factor, expect_update in (
                (1.001, False),
                (0.999, True),
                (1e3, False),
                (1e-3, True),
            ):
                t = t0 / n * factor
                res = dmv_update(P_i, t * P_j, H_i, H_j, R)
                assert res.updated is expect_update
                if expect_update:
                    assert res.omega < 1 and res.log_det < np.linalg.slogdet(P_i)[1]
                else:
                    assert res.omega == 1.0
                    assert np.all(res.K == 0) and np.array_equal(res.P, P_i)


def test_dmv_omega_zero_when_n_equals_m() -> None:
    # n = m = 1, a = 100, b = 1, r = 1: f'(0) >= 0, so agent i takes the measurement only
    P_i, P_j, H, R = np.array([[100.0]]), np.array([[1.0]]), np.array([[1.0]]), np.array([[1.0]])
    res = dmv_update(P_i, P_j, H, -H, R, x_i=[3.0], residual=[0.5])
    assert res.omega == 0.0
    np.testing.assert_allclose(res.P, [[2.0]])  # (H^T (B + R)^-1 H)^-1
    np.testing.assert_allclose(res.K, [[1.0]])
    assert res.x is not None
    np.testing.assert_allclose(res.x, [3.5])
    grid = dmv_cost(np.linspace(0, 1, 101), P_i, P_j, H, -H, R)
    assert res.log_det <= grid.min() + 1e-12


@pytest.mark.parametrize("m", [1, 2, 3])
def test_dmv_cost_is_convex_on_a_grid(rng: np.random.Generator, m: int) -> None:
    for _ in range(6):
        P_i, P_j, H_i, H_j, R = problem(rng, m=m, n=m + 2)
        ws = np.linspace(0.02, 0.98, 97)
        c = dmv_cost(ws, P_i, P_j, H_i, H_j, R)
        second = c[2:] - 2 * c[1:-1] + c[:-2]
        assert second.min() >= -1e-9 * max(1.0, np.abs(c).max())


def test_dmv_state_correction() -> None:
    rng = np.random.default_rng(7)
    P_i, P_j, H_i, H_j, R = problem(rng, m=2, n=4)
    res = dmv_update(P_i, 0.01 * P_j, H_i, H_j, R, x_i=np.ones(4), residual=[0.3, -0.2])
    assert res.dx is not None and res.x is not None
    np.testing.assert_allclose(res.dx, res.K @ [0.3, -0.2])
    np.testing.assert_allclose(res.x, 1 + res.dx)
    assert dmv_update(P_i, P_j, H_i, H_j, R).dx is None


# ------------------------------------------------------------------------------------ PECMV


def _compare(fast: PECMVResult, ref: PECMVResult, P_i: np.ndarray) -> None:
    assert fast.log_det == pytest.approx(ref.log_det, abs=2e-6)
    scale = np.abs(P_i).max()
    np.testing.assert_allclose(fast.P, ref.P, atol=1e-3 * scale)


def test_pecmv_closed_form_equals_sdp_for_scalar_measurements(rng: np.random.Generator) -> None:
    """Cases: no update (beta >= alpha), interior (alpha beta >= beta^2 + r), boundary."""
    n = 3
    P_i = spd(rng, n, 2.0)
    h = rng.normal(size=(1, n))
    a = (h @ P_i @ h.T).item()
    for b_over_a, r in ((1.5, 0.1 * a), (0.04, 0.01 * a), (0.3, 0.05 * a)):
        P_j = spd(rng, n)
        h_j = rng.normal(size=(1, n))
        h_j *= np.sqrt(b_over_a * a / (h_j @ P_j @ h_j.T).item())
        R = np.array([[r]])
        cf = pecmv_update(P_i, P_j, h, h_j, R, method="closed_form")
        ref = pecmv_update(P_i, P_j, h, h_j, R, method="sdp")
        _compare(cf, ref, P_i)
        assert cf.updated is (b_over_a < 1)
        assert ref.updated is cf.updated


@pytest.mark.parametrize("m", [2, 3])
def test_pecmv_fast_path_equals_sdp(rng: np.random.Generator, m: int) -> None:
    paths = set()
    for k in range(5):
        n = 9 if k == 4 else m + 1  # one case of the paper's size
        P_i, P_j, H_i, H_j, R = problem(rng, m=m, n=n, nj=n)
        if k == 0:  # R = H_j P_j H_j^T (whitened Bhat = I) and Ahat >= 8 I: interior case
            R = H_j @ P_j @ H_j.T
            P_i *= 8.0 / eigh(H_i @ P_i @ H_i.T, R, eigvals_only=True).min()
        fast = pecmv_update(P_i, P_j, H_i, H_j, R, method="fast")
        ref = pecmv_update(P_i, P_j, H_i, H_j, R, method="sdp")
        paths.add(fast.path)
        _compare(fast, ref, P_i)
        assert fast.log_det >= ref.log_det - 1e-9  # never worse than the reference optimum
    assert {"interior", "reduced_sdp"} <= paths


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_pecmv_optimality_admissibility_and_nees_bound(seed: int) -> None:
    rng = np.random.default_rng(seed)
    P_i, P_j, H_i, H_j, R = problem(rng, m=int(rng.integers(1, 4)))
    res = pecmv_update(P_i, P_j, H_i, H_j, R)
    n = len(P_i)
    assert joint_covariance_is_admissible(P_i, P_j, res.X)
    assert np.linalg.norm(res.C, 2) <= 1 + 1e-9
    L_i, L_j = np.linalg.cholesky(P_i), np.linalg.cholesky(P_j)
    np.testing.assert_allclose(L_i @ res.C @ L_j.T, res.X, atol=1e-10 * np.abs(res.X).max())
    assert pecmv_objective(res.X, P_i, P_j, H_i, H_j, R) == pytest.approx(res.log_det, abs=1e-9)
    assert np.linalg.slogdet(res.P)[1] == pytest.approx(res.log_det, abs=1e-9)
    P_inv = inv(res.P)
    for C in random_contractions(rng, n, len(P_j)):
        X = L_i @ C @ L_j.T
        assert pecmv_objective(X, P_i, P_j, H_i, H_j, R) <= res.log_det + 1e-8  # X* maximises
        nees = np.trace(P_inv @ true_cov(res.K, P_i, P_j, H_i, H_j, R, X))
        assert nees <= n * (1 + 1e-8)  # the bound is attained by some X


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_loewner_order_pecmv_below_dmv(seed: int) -> None:
    """P_PECMV <= P_DMV and P_PECMV <= P_i (Loewner); DMV is only better in log det.

    ``P_DMV <= P_i`` does *not* hold in general: Pbar(w) = (w P_i^-1 + ...)^-1 inflates the
    directions of agent i that the measurement does not see by 1/w.
    """
    rng = np.random.default_rng(seed)
    P_i, P_j, H_i, H_j, R = problem(rng)
    pe, dm = pecmv_update(P_i, P_j, H_i, H_j, R), dmv_update(P_i, P_j, H_i, H_j, R)
    tol = 1e-9 * np.abs(P_i).max()
    assert min_eig(dm.P - pe.P) >= -tol
    assert min_eig(P_i - pe.P) >= -tol
    assert dm.log_det <= np.linalg.slogdet(P_i)[1] + 1e-12
    assert pe.log_det <= dm.log_det + 1e-9


def test_pecmv_no_update_rule(rng: np.random.Generator) -> None:
    for m in (1, 2, 3):
        P_i, P_j, H_i, H_j, R = problem(rng, m=m)
        A, B = H_i @ P_i @ H_i.T, H_j @ P_j @ H_j.T
        lam = eigh(A, B, eigvals_only=True).max()  # A <= t B  <=>  t >= lam
        t = 1.01 * lam
        res = pecmv_update(P_i, t * P_j, H_i, H_j, R)
        assert not res.updated and np.all(res.K == 0) and np.array_equal(res.P, P_i)
        U = P_i @ H_i.T + res.X @ H_j.T  # the returned X makes the measurement uninformative
        assert np.abs(U).max() <= 1e-9 * np.abs(P_i @ H_i.T).max()
        assert joint_covariance_is_admissible(P_i, t * P_j, res.X)
        # just outside the rule: an update happens
        s = 0.99 * lam
        res2 = pecmv_update(P_i, s * P_j, H_i, H_j, R)
        assert res2.updated and res2.log_det < np.linalg.slogdet(P_i)[1]
    ref = pecmv_update(P_i, t * P_j, H_i, H_j, R, method="sdp")
    assert not ref.updated
    assert ref.log_det == pytest.approx(np.linalg.slogdet(P_i)[1], abs=1e-6)


def test_pecmv_reduced_problem_barrier_fallback_matches(
    rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """When Clarabel stalls, the barrier path alone must reach the same optimum."""
    import selenv.core.fusion.sdp as fusion_sdp

    cases: list[Problem] = []
    while len(cases) < 3:
        pr = problem(rng, m=2, n=4, nj=4)
        if pecmv_update(*pr).path == "reduced_sdp":
            cases.append(pr)
    normal = [pecmv_update(*pr) for pr in cases]
    monkeypatch.setattr(fusion_sdp, "_OK", ())  # every Clarabel status counts as a failure
    for pr, ref in zip(cases, normal, strict=True):
        out = pecmv_update(*pr)
        assert out.log_det == pytest.approx(ref.log_det, abs=1e-9)
        np.testing.assert_allclose(out.P, ref.P, atol=1e-7 * np.abs(pr[0]).max())


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_pecmv_badly_scaled_inputs(seed: int) -> None:
    """Scales over 8 decades: still admissible, optimal against random X, NEES-bounded."""
    rng = np.random.default_rng(seed)
    m = int(rng.integers(2, 4))
    n, nj = int(rng.integers(m, 7)), int(rng.integers(1, 7))
    P_i = spd(rng, n, 10 ** rng.uniform(-3, 3), 2)
    P_j = spd(rng, nj, 10 ** rng.uniform(-4, 3), 2)
    H_i, H_j = rng.normal(size=(m, n)), rng.normal(size=(m, nj))
    R = spd(rng, m, 10 ** rng.uniform(-4, 1), 1)
    res = pecmv_update(P_i, P_j, H_i, H_j, R)
    assert joint_covariance_is_admissible(P_i, P_j, res.X, tol=1e-7)
    L_i, L_j = np.linalg.cholesky(P_i), np.linalg.cholesky(P_j)
    for C in random_contractions(rng, n, nj):
        X = L_i @ C @ L_j.T
        assert pecmv_objective(X, P_i, P_j, H_i, H_j, R) <= res.log_det + 1e-7
        P_true = true_cov(res.K, P_i, P_j, H_i, H_j, R, X)
        assert np.trace(np.linalg.solve(res.P, P_true)) <= n * (1 + 1e-5)


def test_pecmv_given_C_and_correction(rng: np.random.Generator) -> None:
    P_i, P_j, H_i, H_j, R = problem(rng, m=2)
    res = pecmv_update(P_i, P_j, H_i, H_j, R)
    again = pecmv_update(P_i, P_j, H_i, H_j, R, C=res.C, x_i=np.zeros(len(P_i)), residual=[1, 2])
    assert again.path == "given"
    np.testing.assert_allclose(again.P, res.P, atol=1e-10 * np.abs(P_i).max())
    assert again.x is not None
    np.testing.assert_allclose(again.x, again.K @ [1.0, 2.0])
    diag = np.diag(np.tanh(rng.normal(size=min(len(P_i), len(P_j)))))  # an LPECMV-style C
    C = np.zeros((len(P_i), len(P_j)))
    C[: len(diag), : len(diag)] = diag
    lp = pecmv_update(P_i, P_j, H_i, H_j, R, C=C)
    assert lp.log_det <= res.log_det + 1e-9


# --------------------------------------------------------------------------------------- CI


def test_ci_variants_against_their_definitions(rng: np.random.Generator) -> None:
    for _ in range(5):
        n = int(rng.integers(1, 6))
        A, B = spd(rng, n, 10 ** rng.uniform(-1, 1)), spd(rng, n, 10 ** rng.uniform(-1, 1))
        a, b = rng.normal(size=n), rng.normal(size=n)
        Ai, Bi = inv(A), inv(B)
        ws = np.linspace(0, 1, 2001)
        for method in ("optimal", "fast", "improved_fast"):
            res = covariance_intersection(a, A, b, B, method=method)
            w = res.omega
            P = inv(w * Ai + (1 - w) * Bi)  # P^-1 = w A^-1 + (1-w) B^-1
            np.testing.assert_allclose(res.P, P, rtol=1e-8, atol=1e-12)
            np.testing.assert_allclose(res.x, P @ (w * Ai @ a + (1 - w) * Bi @ b), atol=1e-8)
            assert res.log_det == pytest.approx(np.linalg.slogdet(P)[1], abs=1e-9)
        grid = [np.linalg.slogdet(inv(w * Ai + (1 - w) * Bi))[1] for w in ws]
        opt = covariance_intersection(a, A, b, B)
        assert opt.log_det <= min(grid) + 1e-12
        fast = covariance_intersection(a, A, b, B, method="fast")
        assert fast.omega == pytest.approx(np.trace(B) / (np.trace(A) + np.trace(B)))
        imp = covariance_intersection(a, A, b, B, method="improved_fast")
        dS = np.linalg.det(Ai + Bi)
        w_if = (dS - np.linalg.det(Bi) + np.linalg.det(Ai)) / (2 * dS)
        assert imp.omega == pytest.approx(w_if, rel=1e-9)
        ici = covariance_intersection(a, A, b, B, method="inverse")
        w = ici.omega
        G = inv(w * A + (1 - w) * B)
        P = inv(Ai + Bi - G)  # C^-1 = A^-1 + B^-1 - (w A + (1-w) B)^-1
        np.testing.assert_allclose(ici.P, P, rtol=1e-8, atol=1e-12)
        x = P @ ((Ai - w * G) @ a + (Bi - (1 - w) * G) @ b)
        np.testing.assert_allclose(ici.x, x, atol=1e-8)
        grid_ici = [np.linalg.slogdet(inv(Ai + Bi - inv(v * A + (1 - v) * B)))[1] for v in ws]
        assert ici.log_det <= min(grid_ici) + 1e-12


@pytest.mark.parametrize("method", ["optimal", "fast", "improved_fast"])
def test_ci_is_consistent_for_every_admissible_cross_covariance(
    rng: np.random.Generator, method: str
) -> None:
    for _ in range(5):
        n = int(rng.integers(1, 5))
        A, B = spd(rng, n, 10 ** rng.uniform(-1, 1)), spd(rng, n, 10 ** rng.uniform(-1, 1))
        res = covariance_intersection(np.zeros(n), A, np.zeros(n), B, method=method)
        w = res.omega
        K = np.hstack([w * res.P @ inv(A), (1 - w) * res.P @ inv(B)])  # x = K [a; b]
        L_A, L_B = np.linalg.cholesky(A), np.linalg.cholesky(B)
        for C in random_contractions(rng, n, n):
            X = L_A @ C @ L_B.T
            P_true = K @ np.block([[A, X], [X.T, B]]) @ K.T
            assert min_eig(res.P - P_true) >= -1e-9 * np.abs(res.P).max()


# ----------------------------------------------------------------------------------- batched


@pytest.mark.parametrize(("m", "n"), [(1, 1), (1, 3), (1, 9), (2, 2), (2, 4), (3, 5)])
def test_dmv_omega_batch_equals_single(rng: np.random.Generator, m: int, n: int) -> None:
    probs = [problem(rng, m=m, n=n, nj=max(m, 3)) for _ in range(12)]
    for k, pr in enumerate(probs):
        pr[1][...] *= 10.0 ** (2 * (k % 4) - 4)  # spread: no-update rows and strong updates
    if n == m == 1:
        probs[0] = (np.array([[100.0]]), probs[0][1], np.array([[1.0]]), probs[0][3], probs[0][4])
    stack = [np.stack([pr[i] for pr in probs]) for i in range(5)]
    w = dmv_omega_batch(stack[0], stack[1], stack[2], stack[3], stack[4])
    single = np.array([dmv_update(*pr).omega for pr in probs])
    np.testing.assert_allclose(w, single, atol=1e-10)
    assert (w == 1).any() and (w < 1).any()
    w_shared = dmv_omega_batch(stack[0], stack[1], stack[2], stack[3], probs[0][4])  # one R
    single_shared = [dmv_update(*pr[:4], probs[0][4]).omega for pr in probs]
    np.testing.assert_allclose(w_shared, single_shared, atol=1e-10)


@pytest.mark.parametrize("m", [1, 2])
def test_pecmv_batch_equals_single(rng: np.random.Generator, m: int) -> None:
    probs = [problem(rng, m=m, n=4, nj=3) for _ in range(8 if m == 1 else 4)]
    for k, pr in enumerate(probs):
        pr[1][...] *= 10.0 ** (2 * (k % 4) - 4)  # from strong updates to no update
    stack = [np.stack([pr[i] for pr in probs]) for i in range(5)]
    out = pecmv_batch(*stack)
    for k, pr in enumerate(probs):
        res = pecmv_update(*pr)
        for field in ("P", "K", "X", "C"):
            ref = getattr(res, field)
            np.testing.assert_allclose(
                getattr(out, field)[k], ref, atol=1e-9 * max(1, np.abs(ref).max())
            )
        assert out.updated[k] == res.updated
        assert out.log_det[k] == pytest.approx(res.log_det, abs=1e-9)
    if m == 1:
        assert out.updated.any() and not out.updated.all()


# -------------------------------------------------------------------------------- bad inputs


def _good(m: int = 2) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return list(problem(rng, m=m, n=3, nj=3))


@pytest.mark.parametrize("fn", [dmv_update, pecmv_update])
def test_bad_inputs_name_the_argument(fn: Callable[..., Any]) -> None:
    args = _good()
    bad = [a.copy() for a in args]
    bad[0][0, 1] += 1.0  # non-symmetric P_i
    with pytest.raises(ValueError, match="P_i"):
        fn(*bad)
    bad = [a.copy() for a in args]
    bad[4] = -bad[4]  # R not positive definite
    with pytest.raises(ValueError, match="R"):
        fn(*bad)
    bad = [a.copy() for a in args]
    bad[3][0, 0] = np.nan  # NaN in H_j
    with pytest.raises(ValueError, match="H_j"):
        fn(*bad)
    bad = [a.copy() for a in args]
    bad[3] = bad[3][:1]  # H_j with m = 1 rows while H_i has 2
    with pytest.raises(ValueError, match="H_j"):
        fn(*bad)
    with pytest.raises(ValueError, match="R"):
        fn(*args[:4], np.eye(3))  # R of the wrong size
    with pytest.raises(ValueError, match="P_j"):
        fn(args[0], np.ones((3, 3)), *args[2:])  # singular P_j
    with pytest.raises(ValueError, match="residual"):
        fn(*args, x_i=np.zeros(3))
    with pytest.raises(ValueError, match="residual"):
        fn(*args, residual=np.zeros(5))


def test_bad_inputs_of_the_other_entry_points() -> None:
    P_i, P_j, H_i, H_j, R = _good()
    with pytest.raises(ValueError, match="H_j"):  # agent j perfectly known: DMV undefined
        dmv_update(P_i, P_j, H_i, 0 * H_j, R)
    with pytest.raises(ValueError, match="omega"):
        dmv_update(P_i, P_j, H_i, H_j, R, omega=1.5)
    with pytest.raises(ValueError, match="H_i"):  # n_i = 1 < m = 2
        dmv_update(np.eye(1), P_j, np.ones((2, 1)), H_j, R)
    with pytest.raises(ValueError, match="method"):
        pecmv_update(P_i, P_j, H_i, H_j, R, method="magic")
    with pytest.raises(ValueError, match="closed_form"):
        pecmv_update(P_i, P_j, H_i, H_j, R, method="closed_form")
    with pytest.raises(ValueError, match="C must be a contraction"):
        pecmv_update(P_i, P_j, H_i, H_j, R, C=2 * np.eye(3))
    A = P_i.copy()
    A[0, 2] += 0.5
    with pytest.raises(ValueError, match="A"):
        covariance_intersection(np.zeros(3), A, np.zeros(3), P_j)
    with pytest.raises(ValueError, match="b"):
        covariance_intersection(np.zeros(3), P_i, np.zeros(2), P_j)
    with pytest.raises(ValueError, match="method"):
        covariance_intersection(np.zeros(3), P_i, np.zeros(3), P_j, method="x")
    stack = [np.stack([a, a]) for a in (P_i, P_j, H_i, H_j, R)]
    bad = [s.copy() for s in stack]
    bad[0][1, 0, 1] += 1.0
    with pytest.raises(ValueError, match="P_i"):
        dmv_omega_batch(*bad)
    with pytest.raises(ValueError, match="P_i"):
        pecmv_batch(*bad)
    bad = [s.copy() for s in stack]
    bad[3][0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="H_j"):
        dmv_omega_batch(*bad)
    with pytest.raises(ValueError, match="H_j"):
        pecmv_batch(*bad)
    with pytest.raises(ValueError, match="R"):
        pecmv_batch(stack[0], stack[1], stack[2], stack[3], -np.eye(2))
    with pytest.raises(ValueError, match="X"):
        joint_covariance_is_admissible(P_i, P_j, np.ones((3, 2)))


@pytest.mark.parametrize("m", [1, 2])
def test_validate_false_gives_the_same_results(rng: np.random.Generator, m: int) -> None:
    for _ in range(4):
        pr = problem(rng, m=m)
        for fn in (dmv_update, pecmv_update):
            a, b = fn(*pr), fn(*pr, validate=False)
            np.testing.assert_allclose(a.P, b.P, rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(a.K, b.K, rtol=1e-12, atol=1e-14)
    bad = list(problem(rng, m=m))
    bad[4] = -bad[4]
    with pytest.raises(ValueError, match="R"):  # definiteness is still checked
        dmv_update(*bad, validate=False)


def test_public_reexport() -> None:
    for name in public.__all__:
        assert getattr(public, name) is getattr(__import__("selenv.core.fusion").core.fusion, name)
