"""Kalman/EKF/information updates against independent textbook formulas and closed forms."""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import random_spd
from scipy.stats import multivariate_normal

from selenv.core.kalman import (
    KalmanFilter,
    KalmanUpdate,
    ekf_update,
    information_update,
    kf_predict,
    kf_update,
)

inv = np.linalg.inv  # reference formulas only; the module under test never inverts


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(b))


def random_problem(seed: int, n: int, m: int):
    r = np.random.default_rng(seed)
    x = r.normal(size=n)
    P = random_spd(r, n, 2.0)
    H = r.normal(size=(m, n))
    R = random_spd(r, m, 0.3)
    z = H @ x + r.normal(size=m)
    return x, P, z, H, R


def cv_model(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """2-D constant velocity, state (px, py, vx, vy), continuous white-noise acceleration."""
    F1 = np.array([[1.0, dt], [0.0, 1.0]])
    Q1 = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return np.kron(F1, np.eye(2)), np.kron(Q1, np.eye(2))  # kron(., I2) orders (px, py, vx, vy)


# ----------------------------------------------------------------------------- update math


@pytest.mark.parametrize(
    ("seed", "n", "m"), [(0, 1, 1), (1, 2, 1), (2, 4, 2), (3, 5, 3), (4, 3, 3)]
)
def test_update_matches_textbook_and_information_form(seed, n, m):
    x, P, z, H, R = random_problem(seed, n, m)
    res = kf_update(x, P, z, H, R)
    assert isinstance(res, KalmanUpdate)

    S = H @ P @ H.T + R
    K = P @ H.T @ inv(S)
    np.testing.assert_allclose(res.y, z - H @ x, rtol=1e-12, atol=1e-12)
    assert rel_err(res.S, S) < 1e-12
    assert rel_err(res.K, K) < 1e-10
    assert rel_err(res.P, P - K @ S @ K.T) < 1e-10  # textbook covariance form
    assert rel_err(res.x, x + K @ (z - H @ x)) < 1e-10

    P_info = inv(inv(P) + H.T @ inv(R) @ H)  # covariance via the information form
    x_info = P_info @ (inv(P) @ x + H.T @ inv(R) @ z)
    assert rel_err(res.P, P_info) < 1e-10
    assert rel_err(res.x, x_info) < 1e-10

    Y, yv = information_update(inv(P), inv(P) @ x, z, H, R)
    assert rel_err(Y, inv(P_info)) < 1e-10
    assert rel_err(inv(Y), res.P) < 1e-10
    assert rel_err(np.linalg.solve(Y, yv), res.x) < 1e-10

    assert isinstance(res.log_likelihood, float)
    ref_ll = multivariate_normal(mean=H @ x, cov=S).logpdf(z)
    assert res.log_likelihood == pytest.approx(ref_ll, rel=1e-10, abs=1e-10)
    np.testing.assert_array_equal(res.P, res.P.T)


def test_information_update_from_zero_prior_information():
    _, _, z, H, R = random_problem(7, 3, 3)  # m = n with H invertible: fully observed
    Y, yv = information_update(np.zeros((3, 3)), np.zeros(3), z, H, R)
    assert rel_err(Y, H.T @ inv(R) @ H) < 1e-10
    assert rel_err(np.linalg.solve(Y, yv), np.linalg.solve(H, z)) < 1e-10


def test_inputs_are_not_modified():
    x, P, z, H, R = random_problem(8, 3, 2)
    copies = [a.copy() for a in (x, P, z, H, R)]
    kf_update(x, P, z, H, R)
    kf_predict(x, P, P, P)
    for a, c in zip((x, P, z, H, R), copies, strict=True):
        np.testing.assert_array_equal(a, c)


# ------------------------------------------------------------------------------- batching


@pytest.mark.parametrize("shared_model", [True, False])
def test_batched_equals_loop(shared_model):
    r = np.random.default_rng(11)
    B, n, m = 6, 4, 2
    x = r.normal(size=(B, n))
    P = np.stack([random_spd(r, n) for _ in range(B)])
    z = r.normal(size=(B, m))
    if shared_model:
        F, Q = r.normal(size=(n, n)), random_spd(r, n, 0.1)
        H, R = r.normal(size=(m, n)), random_spd(r, m, 0.5)

        def pick(A, b):
            return A
    else:
        F = r.normal(size=(B, n, n))
        Q = np.stack([random_spd(r, n, 0.1) for _ in range(B)])
        H = r.normal(size=(B, m, n))
        R = np.stack([random_spd(r, m, 0.5) for _ in range(B)])

        def pick(A, b):
            return A[b]

    xp, Pp = kf_predict(x, P, F, Q)
    res = kf_update(xp, Pp, z, H, R)
    Yb, yb = information_update(inv(P), x, z, H, R)
    assert xp.shape == (B, n) and Pp.shape == (B, n, n)
    assert res.K.shape == (B, n, m) and res.S.shape == (B, m, m)
    assert np.shape(res.log_likelihood) == (B,)
    for b in range(B):
        xp1, Pp1 = kf_predict(x[b], P[b], pick(F, b), pick(Q, b))
        np.testing.assert_allclose(xp[b], xp1, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(Pp[b], Pp1, rtol=1e-12, atol=1e-12)
        one = kf_update(xp1, Pp1, z[b], pick(H, b), pick(R, b))
        for field in ("x", "P", "y", "S", "K"):
            np.testing.assert_allclose(
                getattr(res, field)[b], getattr(one, field), rtol=1e-10, atol=1e-12
            )
        assert res.log_likelihood[b] == pytest.approx(one.log_likelihood, rel=1e-10)
        Y1, y1 = information_update(inv(P[b]), x[b], z[b], pick(H, b), pick(R, b))
        np.testing.assert_allclose(Yb[b], Y1, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(yb[b], y1, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------ prediction


def test_predict_constant_velocity_by_hand():
    dt, q = 0.5, 1.0
    x = np.array([1.0, 2.0])  # position, velocity
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    xp, Pp = kf_predict(x, P, F, Q)
    # x' = (1 + 0.5 * 2, 2);  F P F^T = [[2.75, 1], [1, 1]];  Q = [[1/24, 1/8], [1/8, 1/2]]
    np.testing.assert_allclose(xp, [2.0, 2.0], rtol=1e-15)
    np.testing.assert_allclose(Pp, [[2.75 + 1 / 24, 1.125], [1.125, 1.5]], rtol=1e-14)


# ------------------------------------------------------------------------------------- EKF


def test_ekf_with_linear_h_equals_kf():
    x, P, z, H, R = random_problem(21, 4, 2)
    lin = kf_update(x, P, z, H, R)
    ext = ekf_update(x, P, z, lambda s: H @ s, lambda s: H, R)
    for field in ("x", "P", "y", "S", "K"):
        np.testing.assert_allclose(getattr(ext, field), getattr(lin, field), rtol=1e-13, atol=0)
    assert ext.log_likelihood == pytest.approx(lin.log_likelihood, rel=1e-13)


def _range(s: np.ndarray) -> np.ndarray:
    return np.array([np.hypot(s[0], s[1])])


def _range_jac(s: np.ndarray) -> np.ndarray:
    rng_ = np.hypot(s[0], s[1])
    return np.array([[s[0] / rng_, s[1] / rng_, 0.0, 0.0]])


def test_ekf_range_uses_jacobian_at_prior_mean():
    x = np.array([3.0, 4.0, 1.0, -1.0])
    P = np.diag([1.0, 2.0, 0.5, 0.5])
    P[0, 1] = P[1, 0] = 0.3
    R = np.array([[0.05]])
    z = np.array([5.7])
    calls = []

    def jac(s):
        calls.append(s.copy())
        return _range_jac(s)

    res = ekf_update(x, P, z, _range, jac, R)
    assert len(calls) == 1
    np.testing.assert_array_equal(calls[0], x)

    eps = 1e-6  # central finite differences, independent of the analytic Jacobian
    H_fd = np.stack(
        [(_range(x + eps * e) - _range(x - eps * e)) / (2 * eps) for e in np.eye(4)], axis=1
    )
    y = z - _range(x)
    S = H_fd @ P @ H_fd.T + R
    K = P @ H_fd.T @ inv(S)
    np.testing.assert_allclose(res.y, y, rtol=1e-14)
    np.testing.assert_allclose(res.K, K, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(res.x, x + K @ y, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(res.P, P - K @ S @ K.T, rtol=1e-7, atol=1e-9)

    # linearising anywhere else gives a visibly different answer
    H_off = _range_jac(x + np.array([1.0, -1.0, 0.0, 0.0]))
    K_off = P @ H_off.T @ inv(H_off @ P @ H_off.T + R)
    assert not np.allclose(res.x, x + K_off @ y, rtol=1e-4)


# ------------------------------------------------------------------------------- class API


def test_class_agrees_with_procedural_api_over_trajectory():
    r = np.random.default_rng(20240607)
    F, Q = cv_model(dt=0.1, q=0.5)
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    R = 0.2 * np.eye(2)
    truth = np.array([0.0, 0.0, 1.0, 0.5])
    x0, P0 = np.zeros(4), 10.0 * np.eye(4)

    kf = KalmanFilter(x0, P0, F, Q)
    x, P = x0, P0
    for _ in range(20):
        truth = F @ truth + r.multivariate_normal(np.zeros(4), Q)
        z = H @ truth + r.multivariate_normal(np.zeros(2), R)
        xc, Pc = kf.predict()
        x, P = kf_predict(x, P, F, Q)
        np.testing.assert_array_equal(xc, x)
        np.testing.assert_array_equal(Pc, P)
        out = kf.update(z, H, R)
        ref = kf_update(x, P, z, H, R)
        x, P = ref.x, ref.P
        np.testing.assert_array_equal(kf.x, x)
        np.testing.assert_array_equal(kf.P, P)
        np.testing.assert_array_equal(out.K, ref.K)
        assert out.log_likelihood == ref.log_likelihood
    assert np.linalg.norm(kf.x[:2] - truth[:2]) < 3.0  # the filter actually tracks
    assert np.all(np.diag(kf.P) < 10.0)


# ------------------------------------------------------------------------ numerical safety


def test_joseph_form_stays_pd_where_textbook_form_does_not():
    P = np.array([[1.0, 0.5], [0.5, 1.0]])
    H = np.array([[1.0, 0.0]])
    R = np.array([[1e-18]])  # S = 1 + 1e-18 rounds to 1, so K = (1, 0.5) exactly
    res = kf_update(np.zeros(2), P, np.array([0.3]), H, R)
    textbook = P - res.K @ res.S @ res.K.T
    assert np.linalg.eigvalsh(textbook).min() <= 0.0  # the simple form loses definiteness
    np.testing.assert_array_equal(res.P, res.P.T)
    np.linalg.cholesky(res.P)  # raises LinAlgError if not PD
    assert np.linalg.eigvalsh(res.P).min() > 0.0
    assert res.P[0, 0] == pytest.approx(1e-18, rel=1e-6)  # true posterior variance ~ R


def test_joseph_form_symmetric_pd_with_tiny_R_over_many_steps():
    r = np.random.default_rng(5)
    F, Q = cv_model(dt=1.0, q=1.0)
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    R = 1e-10 * np.eye(2)
    x, P = np.zeros(4), random_spd(r, 4, 100.0)
    for _ in range(50):
        x, P = kf_predict(x, P, F, Q)
        res = kf_update(x, P, r.normal(size=2), H, R)
        x, P = res.x, res.P
        np.testing.assert_array_equal(P, P.T)
        np.linalg.cholesky(P)
        assert np.linalg.eigvalsh(P).min() > 0.0
        assert np.all(np.diag(P)[:2] <= 1e-10 * (1 + 1e-6))  # measured states: var <= R


@pytest.mark.parametrize(("q", "r"), [(0.1, 2.0), (1.0, 1.0), (3.0, 0.01)])
def test_scalar_random_walk_reaches_riccati_steady_state(q, r):
    P_pred_ss = (q + np.sqrt(q * q + 4 * q * r)) / 2
    P_post_ss = P_pred_ss * r / (P_pred_ss + r)
    F, Q, H, R = np.eye(1), q * np.eye(1), np.eye(1), r * np.eye(1)
    x, P = np.zeros(1), np.array([[100.0]])
    prev = np.inf
    for _ in range(10_000):
        x, P_pred = kf_predict(x, P, F, Q)
        res = kf_update(x, P_pred, np.array([0.0]), H, R)
        x, P = res.x, res.P
        if abs(P[0, 0] - prev) <= 1e-15 * P[0, 0]:
            break
        prev = P[0, 0]
    else:
        pytest.fail("Riccati iteration did not converge")
    assert P_pred[0, 0] == pytest.approx(P_pred_ss, rel=1e-12)
    assert P[0, 0] == pytest.approx(P_post_ss, rel=1e-12)
    assert res.K[0, 0] == pytest.approx(P_pred_ss / (P_pred_ss + r), rel=1e-12)


# ------------------------------------------------------------------------------ bad inputs

_x, _P, _z, _H, _R = random_problem(99, 4, 2)
_F, _Q = cv_model(0.1, 1.0)


def _nan_z():
    return np.array([np.nan, 0.0])


BAD_CALLS = {
    "R not symmetric": (
        lambda: kf_update(_x, _P, _z, _H, np.array([[1.0, 0.2], [0.0, 1.0]])),
        r"^R must be symmetric",
    ),
    "P not PD": (
        lambda: kf_update(_x, np.diag([1.0, 1.0, -1.0, 1.0]), _z, _H, _R),
        r"^P must be positive definite",
    ),
    "NaN in z": (lambda: kf_update(_x, _P, _nan_z(), _H, _R), r"^z must be finite"),
    "H wrong shape": (
        lambda: kf_update(_x, _P, _z, np.ones((3, 4)), _R),
        re.escape("H must have shape (2, 4), got (3, 4)"),
    ),
    "R wrong size": (
        lambda: kf_update(_x, _P, _z, _H, np.eye(3)),
        re.escape("R must have shape (2, 2)"),
    ),
    "inf in x": (lambda: kf_predict(np.full(4, np.inf), _P, _F, _Q), r"^x must be finite"),
    "x matrix-shaped": (lambda: kf_predict(np.ones((2, 2, 4)), _P, _F, _Q), r"^x must have"),
    "Q not PSD": (lambda: kf_predict(_x, _P, _F, -_Q), r"^Q must be positive semi-definite"),
    "F wrong shape": (lambda: kf_predict(_x, _P, _F[:3], _Q), r"^F must have shape \(4, 4\)"),
    "F NaN": (lambda: kf_predict(_x, _P, _F * np.nan, _Q), r"^F must be finite"),
    "batched P mismatch": (
        lambda: kf_predict(np.zeros((3, 4)), np.stack([_P] * 2), _F, _Q),
        re.escape("P must have shape (3, 4, 4)"),
    ),
    "unbatched P with batched x": (
        lambda: kf_predict(np.zeros((3, 4)), _P, _F, _Q),
        re.escape("P must have shape (*, 4, 4)"),
    ),
    "batched H wrong batch": (
        lambda: kf_update(
            np.zeros((3, 4)), np.stack([_P] * 3), np.zeros((3, 2)), np.ones((2, 2, 4)), _R
        ),
        re.escape("H must have shape (3, 2, 4)"),
    ),
    "unbatched z with batched x": (
        lambda: kf_update(np.zeros((3, 4)), np.stack([_P] * 3), _z, _H, _R),
        re.escape("z must have shape (3, *)"),
    ),
    "ekf h wrong shape": (
        lambda: ekf_update(_x, _P, _z, lambda s: s[:3], lambda s: _H, _R),
        r"^h\(x\) must have shape .*got \(3,\)",
    ),
    "ekf Jacobian NaN": (
        lambda: ekf_update(_x, _P, _z, lambda s: _H @ s, lambda s: _H * np.nan, _R),
        re.escape("H_jac(x) must be finite"),
    ),
    "ekf batched": (
        lambda: ekf_update(np.zeros((3, 4)), np.stack([_P] * 3), _z, lambda s: s, lambda s: s, _R),
        r"^ekf_update is unbatched",
    ),
    "information R not PD": (
        lambda: information_update(np.eye(4), _x, _z, _H, -_R),
        r"^R must be positive definite",
    ),
    "information Y wrong shape": (
        lambda: information_update(np.eye(3), _x, _z, _H, _R),
        re.escape("Y must have shape (4, 4), got (3, 3)"),
    ),
    "class Q not symmetric": (
        lambda: KalmanFilter(_x, _P, _F, _Q + np.triu(np.ones((4, 4)), 1)),
        r"^Q must be symmetric",
    ),
}


@pytest.mark.parametrize("case", list(BAD_CALLS))
def test_bad_inputs_raise_value_error_naming_argument(case):
    call, pattern = BAD_CALLS[case]
    with pytest.raises(ValueError, match=pattern):
        call()


def test_rank_deficient_process_noise_is_accepted_and_negative_rejected():
    # discrete white-noise acceleration Q for a (position, velocity) state is rank one
    dt, q = 0.1, 2.0
    G = np.array([[0.5 * dt**2], [dt]])
    Q = q * G @ G.T
    x, P = kf_predict(np.zeros(2), np.eye(2), np.array([[1.0, dt], [0.0, 1.0]]), Q)
    np.testing.assert_allclose(
        P, np.array([[1.0, dt], [0.0, 1.0]]) @ np.array([[1.0, 0.0], [dt, 1.0]]) + Q
    )
    with pytest.raises(ValueError, match="Q must be positive semi-definite"):
        kf_predict(np.zeros(2), np.eye(2), np.eye(2), -Q)


def test_unvalidated_fast_path_matches_validated_update() -> None:
    rng = np.random.default_rng(11)
    n, m = 6, 3
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    H = rng.normal(size=(m, n))
    B = rng.normal(size=(m, m))
    R = B @ B.T + 0.5 * np.eye(m)
    x, z = rng.normal(size=n), rng.normal(size=m)
    ref = kf_update(x, P, z, H, R)
    fast = kf_update(x, P, z, H, R, validate=False)
    for name in ("x", "P", "y", "S", "K"):
        np.testing.assert_allclose(getattr(fast, name), getattr(ref, name), rtol=1e-12, atol=1e-12)
    assert fast.log_likelihood == pytest.approx(ref.log_likelihood, rel=1e-12)
    # the batched path (a different code path) agrees with the single path
    batched = kf_update(x[None], P[None], z[None], H, R)
    np.testing.assert_allclose(batched.P[0], ref.P, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(batched.log_likelihood[0], ref.log_likelihood, rtol=1e-10)
    with pytest.raises(ValueError, match="not positive definite"):
        kf_update(x, P, z, H, -10 * np.eye(m) - H @ P @ H.T, validate=False)
