"""Every fused / updated covariance is certified SPD before it is returned, on every BLAS kernel.

The certificate (``selenv.core.spd``) is a Cholesky factorisation of the shifted correlation
matrix ``D^-1/2 P D^-1/2 - tau I``. The cases here sit at least a factor 1e3 away from the
threshold (``tau = 1e-12`` on the correlation matrix's smallest eigenvalue), so that any correct
BLAS reaches the same verdict; the suite runs them under two OpenBLAS kernels in CI.
"""

from __future__ import annotations

import mpmath
import numpy as np
import pytest
from test_validation import _sweep_case

from selenv.core.kalman import kf_update
from selenv.core.spd import SPD_MARGIN, is_certified_spd, require_spd, spd_margin
from selenv.fusion import covariance_intersection, dmv_update, pecmv_update


def _with_correlation_eigenvalue(lam: float, n: int, seed: int, scales: np.ndarray) -> np.ndarray:
    """``D C D`` with a correlation-like ``C`` whose smallest eigenvalue is ``lam`` (mpmath)."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    ev = np.concatenate([[lam], rng.uniform(0.5, 2.0, size=n - 1)])
    C = (Q * ev) @ Q.T
    return scales[:, None] * C * scales[None, :]


def _mp_min_correlation_eig(A: np.ndarray) -> float:
    """Smallest eigenvalue of the correlation matrix of the float64 matrix ``A``, in 50 digits."""
    with mpmath.workdps(50):
        M = mpmath.matrix(A.tolist())
        n = A.shape[0]
        if any(M[i, i] <= 0 for i in range(n)):
            return -np.inf
        s = [1 / mpmath.sqrt(M[i, i]) for i in range(n)]
        C = mpmath.matrix(n, n)
        for i in range(n):
            for j in range(n):
                C[i, j] = s[i] * M[i, j] * s[j]
        return float(min(mpmath.eigsy(C)[0]))


@pytest.mark.parametrize("n", [1, 2, 3, 6, 15])
@pytest.mark.parametrize("seed", range(4))
def test_certificate_verdicts_a_factor_1e3_from_the_threshold(n: int, seed: int) -> None:
    scales = 10.0 ** np.random.default_rng(seed + 50).uniform(-60, 60, size=n)
    for lam in (1e-8, 1e-3, 1.0):
        A = _with_correlation_eigenvalue(lam, n, seed, scales)
        assert _mp_min_correlation_eig(A) > 1e3 * SPD_MARGIN  # the case really is far inside
        assert is_certified_spd(A)
        assert require_spd(A, "f") is A
    if n == 1:
        bad = [np.array([[0.0]]), np.array([[-1.0]]), np.array([[np.nan]])]
    else:
        bad = [_with_correlation_eigenvalue(lam, n, seed, scales) for lam in (-1e-9, -1e-6, -0.5)]
    for A in bad:
        if n > 1:
            assert _mp_min_correlation_eig(A) < 1e-3 * SPD_MARGIN  # far outside
        assert not is_certified_spd(A)
        with pytest.raises(ValueError, match=r"f: the m .* not numerically positive definite"):
            require_spd(A, "f", "the m")


def test_certificate_batches_name_the_first_bad_item() -> None:
    scales = np.ones(4)
    good = [_with_correlation_eigenvalue(1e-6, 4, s, scales) for s in range(5)]
    stack = np.stack(good)
    np.testing.assert_array_equal(is_certified_spd(stack), np.ones(5, bool))
    stack[3] = _with_correlation_eigenvalue(-1e-3, 4, 9, scales)
    np.testing.assert_array_equal(is_certified_spd(stack), [True, True, True, False, True])
    with pytest.raises(ValueError, match=r"\(batch item 3\) is not numerically positive"):
        require_spd(stack, "g")
    stack[1, 0, 0] = -1.0  # a non-positive diagonal takes the item-by-item path
    np.testing.assert_array_equal(is_certified_spd(stack), [True, False, True, False, True])


def test_margin_grows_with_n_beyond_the_fixed_threshold() -> None:
    assert spd_margin(3) == SPD_MARGIN
    assert spd_margin(45) == SPD_MARGIN
    assert spd_margin(200) > SPD_MARGIN  # rounding of a 200 x 200 factorisation is larger


# ------------------------------------------------------------------ the fusion functions
@pytest.mark.parametrize("s_P", [1.0, 1e4, 1e8])
def test_pecmv_inside_the_limit_returns_a_certified_posterior(s_P: float) -> None:
    res = pecmv_update(*_sweep_case(s_P=s_P))
    assert is_certified_spd(res.P)
    assert np.linalg.eigvalsh(res.P)[0] > 0.0
    assert _mp_min_correlation_eig(res.P) > 1e3 * SPD_MARGIN


@pytest.mark.parametrize("s_P", [1e16, 1e20, 1e60])
def test_pecmv_beyond_the_limit_is_refused_on_every_kernel(s_P: float) -> None:
    """P_i ~ s_P R: P_i - U S^-1 U^T cancels; the exact posterior's correlation eigenvalue is
    ~1/s_P <= 1e-16, far below the margin, so no rounding can certify it."""
    with pytest.raises(ValueError, match="not numerically positive definite"):
        pecmv_update(*_sweep_case(s_P=s_P))


def _near_singular_kf(s_P: float) -> tuple[np.ndarray, ...]:
    """A 3-state prior ``s_P`` times larger than the noise of a full-rank 3-row measurement
    along rotated axes: the exact posterior's correlation eigenvalue is ~1/s_P."""
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    P = s_P * (Q * np.array([1.0, 2.0, 3.0])) @ Q.T
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) @ Q.T
    return np.zeros(3), P, np.zeros(2), H, np.eye(2)


@pytest.mark.parametrize("s_P", [1.0, 1e4, 1e7])
def test_kalman_posteriors_inside_the_limit_are_certified(s_P: float) -> None:
    x, P, z, H, R = _near_singular_kf(s_P)
    for upd in (kf_update(x, P, z, H, R), kf_update(x, P, z, H, R, validate=False)):
        assert is_certified_spd(upd.P)
        assert _mp_min_correlation_eig(upd.P) > 1e3 * SPD_MARGIN


@pytest.mark.parametrize("s_P", [1e17, 1e30])
def test_kalman_posteriors_beyond_the_limit_are_refused(s_P: float) -> None:
    x, P, z, H, R = _near_singular_kf(s_P)
    with pytest.raises(ValueError, match="not numerically positive definite"):
        kf_update(x, P, z, H, R)
    with pytest.raises(ValueError, match="not numerically positive definite"):
        kf_update(x, P, z, H, R, validate=False)


@pytest.mark.parametrize("s", [1.0, 1e6])
def test_dmv_and_ci_results_are_certified(s: float) -> None:
    P_i, P_j, H_i, H_j, R = _sweep_case(s_P=s)
    res = dmv_update(P_i, P_j, H_i, H_j, R)
    assert is_certified_spd(res.P)
    ci = covariance_intersection(np.zeros(3), P_i, np.zeros(3), P_j[:3, :3] * s)
    assert is_certified_spd(ci.P)
    assert _mp_min_correlation_eig(ci.P) > 1e3 * SPD_MARGIN
