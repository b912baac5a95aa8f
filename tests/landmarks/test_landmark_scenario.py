"""Landmark-selection scenario (Soubaras & Chahbazian 2023): models, CRLB, EKF consistency."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.stats import chi2

from selenv.core.crlb import pcrlb_step_covariance, pcrlb_step_information
from selenv.core.kalman import kf_update
from selenv.core.riccati import riccati_step
from selenv.families.landmarks.flight import body_vectors_along, draw_layout
from selenv.families.landmarks.models import (
    C_NED_TO_ENU,
    aoa_angles,
    body_rates_from_euler_rates,
    euler_rate_matrix,
    euler_to_dcm,
    euler_to_dcm_derivatives,
    measure,
    measurement_jacobian,
    paper_error_to_state,
    paper_jacobian,
    process_noise,
    propagate,
    propagate_steps,
    propagation_jacobians,
    skew,
    state_difference,
    wrap_angle,
)
from selenv.families.landmarks.scenario import (
    LandmarkConfig,
    LandmarkEKF,
    check_selection,
    crlb_reference,
    make_landmark_problem,
    scenario_static,
    selection_logdet_gain,
)


def _rot(axis: int, a: float) -> np.ndarray:
    """Independent elementary rotation: expm(a [e_axis]_x)."""
    return expm(a * skew(np.eye(3)[axis]))


def _random_state(rng: np.random.Generator) -> np.ndarray:
    x = np.empty(9)
    x[0:3] = rng.uniform(-2000, 2000, 3) + np.array([0, 0, 1000])
    x[3:6] = rng.normal(0, 30, 3)
    x[6:9] = [rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-np.pi, np.pi)]
    return x


def _landmarks_around(rng: np.random.Generator, x: np.ndarray, n: int = 8) -> np.ndarray:
    """Landmarks in every direction (ahead, behind, above, below), away from the body z axis."""
    C = euler_to_dcm(x[6:9])
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(-1.3, 1.3, n)  # |elevation| <= 75 deg: rho > 0
    r = rng.uniform(200, 5000, n)
    delta = r[:, None] * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)], 1
    )
    return x[0:3] + delta @ C.T  # p_n = p + C_b^e Delta


def _central_diff(f, x0: np.ndarray, eps: np.ndarray | float) -> np.ndarray:
    """Jacobian of f at x0 by central differences: (*f.shape, len(x0))."""
    eps = np.broadcast_to(eps, x0.shape)
    cols = []
    for i in range(x0.size):
        e = np.zeros_like(x0)
        e[i] = eps[i]
        cols.append((f(x0 + e) - f(x0 - e)) / (2 * eps[i]))
    return np.stack(cols, -1)


# -- attitude and propagation -------------------------------------------------------------------
def test_dcm_convention_and_derivatives(rng):
    for _ in range(5):
        th = rng.uniform(-1.2, 1.2, 3) * [1, 1, 2.5]
        C = euler_to_dcm(th)
        ref = C_NED_TO_ENU @ _rot(2, th[2]) @ _rot(1, th[1]) @ _rot(0, th[0])
        np.testing.assert_allclose(C, ref, atol=1e-14)
        np.testing.assert_allclose(C @ C.T, np.eye(3), atol=1e-14)
        dC = _central_diff(euler_to_dcm, th, 1e-6)  # (3, 3, angle)
        np.testing.assert_allclose(np.moveaxis(dC, -1, 0), euler_to_dcm_derivatives(th), atol=1e-9)
    ths = rng.normal(size=(4, 3))
    np.testing.assert_allclose(euler_to_dcm(ths), np.stack([euler_to_dcm(t) for t in ths]))
    # level, heading North: forward = North, right = East, down = -Up
    # heading 90 deg: forward = East
    np.testing.assert_allclose(euler_to_dcm([0, 0, 0]), [[0, 1, 0], [1, 0, 0], [0, 0, -1]])
    np.testing.assert_allclose(euler_to_dcm([0, 0, np.pi / 2])[:, 0], [1, 0, 0], atol=1e-15)
    # Euler kinematics: w_b = E^-1 theta_dot
    th, td = rng.normal(size=3) * 0.5, rng.normal(size=3)
    np.testing.assert_allclose(euler_rate_matrix(th) @ body_rates_from_euler_rates(th, td), td)


def test_propagate_equations():
    x = np.array([10.0, 20.0, 1000.0, 0.0, 50.0, 0.0, 0.0, 0.0, 0.0])
    u = np.array([0.0, 0.0, -9.80665, 0.0, 0.0, 0.01])  # level flight, yaw rate 0.01 rad/s
    xp = propagate(x, u, 0.1)
    np.testing.assert_allclose(xp[0:6], [10.0, 25.0, 1000.0, 0.0, 50.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(xp[6:9], [0.0, 0.0, 0.001], atol=1e-15)


def test_propagation_jacobians_vs_finite_differences(rng):
    for _ in range(5):
        x = _random_state(rng)
        u = np.r_[rng.normal(0, 3, 3), rng.normal(0, 0.3, 3)]
        u[2] -= 9.8
        F, G = propagation_jacobians(x, u, 0.1)
        eps = np.r_[np.full(3, 1e-3), np.full(3, 1e-4), np.full(3, 1e-5)]
        F_fd = _central_diff(lambda z, u=u: propagate(z, u, 0.1), x, eps)
        G_fd = _central_diff(lambda w, x=x: propagate(x, w, 0.1), u, 1e-2)  # x+ is linear in u
        np.testing.assert_allclose(F, F_fd, atol=1e-7)
        np.testing.assert_allclose(G, G_fd, atol=1e-8)
        Q = process_noise(G, 1e-3, 1e-5)
        np.testing.assert_allclose(Q, G @ np.diag([1e-6] * 3 + [1e-10] * 3) @ G.T, atol=1e-22)
        ev = np.linalg.eigvalsh(Q)
        assert ev.min() > -1e-20 and np.sum(ev > 1e-6 * ev.max()) == 6  # PSD, rank 6


# -- angles of arrival --------------------------------------------------------------------------
def test_measurement_sign_conventions():
    x = np.array([0.0, 0.0, 1000.0, 0, 0, 0, 0.0, 0.0, 0.0])  # level, heading North
    lm = np.array(
        [[0.0, 1000.0, 0.0], [1000.0, 0.0, 1000.0], [0.0, -1000.0, 2000.0], [-1000.0, 0.0, 1000.0]]
    )
    az, el = measure(x, lm).T
    np.testing.assert_allclose(np.degrees(az), [0.0, 90.0, 180.0, -90.0], atol=1e-12)
    np.testing.assert_allclose(np.degrees(el), [-45.0, 0.0, 45.0, 0.0], atol=1e-12)  # up > 0


def test_measurement_jacobian_vs_finite_differences(rng):
    for _ in range(6):
        x = _random_state(rng)
        lm = _landmarks_around(rng, x)
        H = measurement_jacobian(x, lm)
        eps = np.r_[np.full(6, 1e-3), np.full(3, 1e-7)]
        H_fd = _central_diff(lambda z, lm=lm: measure(z, lm), x, eps)  # (N, 2, 9)
        np.testing.assert_allclose(H, H_fd, atol=1e-8, rtol=1e-5)
        assert np.all(H[:, :, 3:6] == 0.0)


def test_paper_jacobian_vs_finite_differences_in_error_state(rng):
    """Eq. (20) is dh/de for C_b^e = C_hat expm([phi]_x), p = p_hat + C_hat dp^b."""
    for _ in range(6):
        x = _random_state(rng)
        lm = _landmarks_around(rng, x)
        C_hat, p_hat = euler_to_dcm(x[6:9]), x[0:3]

        def h_err(e, lm=lm, C_hat=C_hat, p_hat=p_hat):
            C = C_hat @ expm(skew(e[0:3]))
            p = p_hat + C_hat @ e[6:9]
            return aoa_angles((lm - p) @ C)  # Delta = C_e^b (p_n - p)

        eps = np.r_[np.full(3, 1e-7), np.full(3, 1e-3), np.full(3, 1e-3)]
        H_fd = _central_diff(h_err, np.zeros(9), eps)
        Hp = paper_jacobian(x, lm)
        np.testing.assert_allclose(Hp, H_fd, atol=1e-8, rtol=1e-5)
        H_state = measurement_jacobian(x, lm) @ paper_error_to_state(x)
        np.testing.assert_allclose(H_state, Hp, atol=1e-14)


# -- posterior CRLB -----------------------------------------------------------------------------
def _random_model(rng, n=6, m=4):
    F = np.eye(n) + 0.3 * rng.normal(size=(n, n))
    A = rng.normal(size=(n, n))
    Q = A @ A.T / n + 0.2 * np.eye(n)
    H = rng.normal(size=(m, n))
    B = rng.normal(size=(m, m))
    R = B @ B.T / m + 0.5 * np.eye(m)
    A = rng.normal(size=(n, n))
    J = A @ A.T / n + 0.5 * np.eye(n)
    return J, F, Q, H, R


def test_pcrlb_information_equals_covariance_form(rng):
    for m in (4, 0):
        J, F, Q, H, R = _random_model(rng, m=m)
        J_next = pcrlb_step_information(J, F, Q, H, R)
        Pc_next = pcrlb_step_covariance(np.linalg.inv(J), F, Q, H, R)
        np.testing.assert_allclose(np.linalg.inv(J_next), Pc_next, rtol=1e-9, atol=1e-12)
    # independent check: the Riccati step of core.riccati; batched input broadcasts
    J, F, Q, H, R = _random_model(rng)
    Ps = np.stack([np.linalg.inv(J), np.linalg.inv(2 * J)])
    np.testing.assert_allclose(
        pcrlb_step_covariance(Ps, F, Q, H, R), riccati_step(Ps, F, Q, H, R), atol=1e-12
    )
    Js = np.stack([J, 2 * J])
    np.testing.assert_allclose(
        pcrlb_step_information(Js, F, Q, H, R)[1], pcrlb_step_information(2 * J, F, Q, H, R)
    )


def test_pcrlb_covariance_singular_q_and_bad_input(rng):
    J, F, Q, H, R = _random_model(rng)
    Q_sing = np.diag([1.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    Pc = pcrlb_step_covariance(np.linalg.inv(J), F, Q_sing, H, R)
    assert np.linalg.eigvalsh(Pc).min() > 0
    with pytest.raises(ValueError, match="Q"):
        pcrlb_step_information(J, F, Q_sing, H, R)
    with pytest.raises(ValueError, match="H"):
        pcrlb_step_covariance(J, F, Q, H[:, :3], R)
    bad = Q.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="Q"):
        pcrlb_step_covariance(J, F, bad, H, R)


# -- problem generation -------------------------------------------------------------------------
def test_problem_is_seeded_and_the_truth_is_the_model():
    cfg = LandmarkConfig(horizon=60, n_landmarks=12)
    a = make_landmark_problem(cfg, np.random.default_rng(7))
    b = make_landmark_problem(cfg, np.random.default_rng(7))
    c = make_landmark_problem(cfg, np.random.default_rng(8))
    for name in ("landmarks", "states", "imu_measured", "measurement_noise", "x0_hat", "Q"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.measurement_noise, c.measurement_noise)
    assert not np.array_equal(a.landmarks, c.landmarks)
    np.testing.assert_array_equal(a.states, c.states)  # the flight is deterministic
    for k in (0, 17, 59):
        np.testing.assert_allclose(a.states[k + 1], propagate(a.states[k], a.imu_true[k], a.dt))
        z = wrap_angle(measure(a.states[k + 1], a.landmarks) + a.measurement_noise[k])
        np.testing.assert_allclose(a.measurements[k], z, atol=1e-12)
    assert a.measurements.shape == (60, 12, 2) and a.states.shape == (61, 9)
    assert not a.states.flags.writeable


def test_default_trajectory_and_layout():
    p = make_landmark_problem(None, np.random.default_rng(0))
    s = p.states
    assert s.shape == (301, 9) and p.landmarks.shape == (30, 3)
    np.testing.assert_allclose(s[:, 2], 1000.0, atol=1.0)  # altitude hold
    np.testing.assert_allclose(np.hypot(s[:, 3], s[:, 4]), 50.0, atol=0.5)
    assert 25 < np.degrees(np.abs(s[:, 6]).max()) < 30  # coordinated turns at 6 deg/s
    assert np.ptp(np.degrees(s[:, 8])) > 45  # the heading changes
    delta = (p.landmarks[None] - s[:, None, 0:3]) @ euler_to_dcm(s[:, 6:9])
    off = np.degrees(np.arccos(np.clip(delta[..., 2] / np.linalg.norm(delta, axis=-1), -1, 1)))
    assert off.min() >= 5.0  # never near the body z axis
    assert np.all(p.landmarks[:, 2] <= 100) and np.ptp(p.landmarks[:, 0]) > 5000


def _layout_by_body_vectors(cfg, states, rng, dcm):
    """``draw_layout``'s acceptance test written on the body vectors (eq. 17) themselves."""
    n, m = cfg.n_landmarks, cfg.landmark_margin
    low = [*(states[:, 0:2].min(axis=0) - m), cfg.landmark_height[0]]
    high = [*(states[:, 0:2].max(axis=0) + m), cfg.landmark_height[1]]
    sin_min = np.sin(np.deg2rad(cfg.min_off_nadir_deg))
    kept, rejected = [], 0
    while sum(len(k) for k in kept) < n:
        cand = rng.uniform(low, high, size=(2 * n, 3))
        delta = body_vectors_along(states, cand, dcm)
        rho = np.hypot(delta[..., 0], delta[..., 1])
        ok = np.all(rho > sin_min * np.linalg.norm(delta, axis=-1), axis=0)
        kept.append(cand[ok])
        rejected += int((~ok).sum())
    return np.concatenate(kept)[:n], rejected


@pytest.mark.parametrize(
    "kwargs", [{}, {"n_landmarks": 200}, {"n_landmarks": 12, "min_off_nadir_deg": 40.0}]
)
def test_layout_acceptance_equals_the_body_vector_test(kwargs):
    """The layout's products-of-columns acceptance keeps exactly the candidates the per-state
    body vectors keep (same layouts, seed for seed), rejections included."""
    cfg = LandmarkConfig(**kwargs)
    st = scenario_static(cfg)
    rejected = 0
    for seed in range(40):
        want, r = _layout_by_body_vectors(cfg, st.states, np.random.default_rng(seed), st.dcm)
        rejected += r
        got = draw_layout(cfg, st.states, np.random.default_rng(seed), st.dcm)
        np.testing.assert_array_equal(got, want)
    if kwargs.get("min_off_nadir_deg", 0.0) >= 40.0:
        assert rejected > 100  # the comparison exercised the rejection side


def test_user_layout_and_bad_config():
    lm = np.array([[1000.0, 2000.0, 0.0], [-3000.0, 500.0, 10.0], [0.0, -2500.0, 0.0]])
    p = make_landmark_problem(
        LandmarkConfig(horizon=5, n_landmarks=3, landmarks=lm), np.random.default_rng(0)
    )
    np.testing.assert_array_equal(p.landmarks, lm)
    bad = lm.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"landmarks\[1\]"):
        LandmarkConfig(n_landmarks=3, landmarks=bad)
    with pytest.raises(ValueError, match="landmarks"):
        LandmarkConfig(n_landmarks=4, landmarks=lm)
    with pytest.raises(ValueError, match="n_landmarks"):
        LandmarkConfig(n_landmarks=0)
    with pytest.raises(ValueError, match="horizon"):
        LandmarkConfig(horizon=0)
    with pytest.raises(ValueError, match="dt"):
        LandmarkConfig(dt=float("nan"))
    with pytest.raises(ValueError, match=r"aoa_sigma_deg\[1\]"):
        LandmarkConfig(aoa_sigma_deg=(0.6, -1.0))
    with pytest.raises(ValueError, match="accel_sigma"):
        LandmarkConfig(accel_sigma=0.0)
    with pytest.raises(ValueError, match="legs"):
        LandmarkConfig(legs=((5.0, 40.0),))
    with pytest.raises(ValueError, match="rng"):
        make_landmark_problem(None, 0)  # type: ignore[arg-type]


def test_check_selection():
    np.testing.assert_array_equal(check_selection([4, 1], 5), [4, 1])
    np.testing.assert_array_equal(check_selection(np.array([2.0]), 5), [2])
    np.testing.assert_array_equal(check_selection([False, True, False, True, False], 5), [1, 3])
    assert check_selection([], 5).size == 0
    for bad in ([5], [-1], [1, 1], [np.nan, 1], [[1, 2]], [1.5], ["a"]):
        with pytest.raises(ValueError, match="selection"):
            check_selection(bad, 5)


# -- EKF ------------------------------------------------------------------------------------------
def test_ekf_nees_all_landmarks_is_consistent():
    """30 Monte Carlo runs x 100 steps: the run-averaged NEES sits in the 95 % chi2 band."""
    M, T, N = 30, 100, 20
    cfg = LandmarkConfig(horizon=T, n_landmarks=N)
    nees = np.empty((M, T))
    for r in range(M):
        p = make_landmark_problem(cfg, np.random.default_rng(100 + r))
        ekf = LandmarkEKF(p)
        for k in range(T):
            ekf.predict(k)
            ekf.update(np.arange(N))
            e = state_difference(ekf.x, p.states[k + 1])
            nees[r, k] = e @ np.linalg.solve(ekf.P, e)
    lo, hi = chi2.ppf([0.025, 0.975], 9 * M) / M
    per_step = nees.mean(axis=0)
    assert lo < nees.mean() < hi, (lo, nees.mean(), hi)
    assert np.mean((per_step > lo) & (per_step < hi)) >= 0.8


def test_ekf_tracks_the_crlb_and_selection_gain(rng):
    p = make_landmark_problem(LandmarkConfig(horizon=100, n_landmarks=30), np.random.default_rng(3))
    crlb_all = crlb_reference(p)
    pair = [np.sort(rng.choice(30, 2, replace=False)) for _ in range(100)]
    crlb_pair = crlb_reference(p, pair)
    assert crlb_all.shape == (101, 9, 9)
    ekf_all, ekf_pair = LandmarkEKF(p), LandmarkEKF(p)
    gaps_all, gaps_pair = [], []
    for k in range(100):
        ekf_all.predict()
        ekf_all.update(np.arange(30))
        ekf_pair.predict()
        H, _ = ekf_pair.candidates()
        P_pred, logdet_pred = ekf_pair.P.copy(), ekf_pair.logdet_P
        gain = selection_logdet_gain(P_pred, H[pair[k]], p.R_landmark)
        ekf_pair.update(pair[k])
        assert gain == pytest.approx(logdet_pred - ekf_pair.logdet_P, abs=1e-8)
        gaps_all.append(ekf_all.logdet_P - np.linalg.slogdet(crlb_all[k + 1])[1])
        gaps_pair.append(ekf_pair.logdet_P - np.linalg.slogdet(crlb_pair[k + 1])[1])
    assert np.max(np.abs(gaps_all[50:])) < 0.1, gaps_all[50:]
    assert np.max(np.abs(gaps_pair[50:])) < 0.3, gaps_pair[50:]
    # more landmarks, more information: the all-landmark bound is below the pair bound
    assert np.linalg.slogdet(crlb_all[-1])[1] < np.linalg.slogdet(crlb_pair[-1])[1] - 1.0
    # batched gains over candidate pairs, K = 0, and a prediction-only bound
    H, _ = ekf_pair.candidates()
    pairs = np.array([[0, 1], [2, 3], [4, 5]])
    g = selection_logdet_gain(ekf_pair.P, H[pairs], p.R_landmark)
    assert g.shape == (3,)
    assert g[1] == pytest.approx(selection_logdet_gain(ekf_pair.P, H[[2, 3]], p.R_landmark))
    assert selection_logdet_gain(ekf_pair.P, H[[]], p.R_landmark) == 0.0
    none = crlb_reference(p, [[]] * 10)
    M = p.F_true[0] @ p.P0 @ p.F_true[0].T + p.Q[0]
    np.testing.assert_allclose(none[1], M, rtol=1e-12, atol=1e-18)


def test_ekf_update_paths_agree_and_protect_state():
    p = make_landmark_problem(LandmarkConfig(horizon=5, n_landmarks=10), np.random.default_rng(1))
    a, b = LandmarkEKF(p), LandmarkEKF(p)
    a.predict(0)
    b.predict(0)
    a.candidates()  # cached path
    ra = a.update([7, 2])
    rb = b.update(np.array([7, 2]))  # selected-only path
    assert ra is not None and rb is not None
    np.testing.assert_allclose(a.x, b.x, rtol=1e-12)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-12)
    # direct Joseph update with the wrapped innovation
    b2 = LandmarkEKF(p)
    x_pred, P_pred = b2.predict()
    H = measurement_jacobian(x_pred, p.landmarks[[7, 2]]).reshape(4, 9)
    y = wrap_angle(p.measurements[0, [7, 2]] - measure(x_pred, p.landmarks[[7, 2]])).ravel()
    ref = kf_update(x_pred, P_pred, H @ x_pred + y, H, np.diag(np.tile(np.diag(p.R_landmark), 2)))
    np.testing.assert_allclose(a.x, ref.x, rtol=1e-12)
    # empty selection keeps the prediction; bad selections leave the filter untouched
    x1, P1 = a.predict(1)
    x1, P1 = x1.copy(), P1.copy()
    for bad in ([10], [1, 1], [np.nan], [[0, 1]]):
        with pytest.raises(ValueError, match="selection"):
            a.update(bad)
    np.testing.assert_array_equal(a.x, x1)
    assert a.update([]) is None
    np.testing.assert_array_equal(a.P, P1)
    with pytest.raises(RuntimeError):
        a.update([0])  # one update per step
    with pytest.raises(ValueError, match="k"):
        a.predict(5)


def test_propagate_steps_repeats_propagate():
    rng = np.random.default_rng(0)
    x = np.r_[rng.normal(size=6) * 10.0, rng.normal(size=3) * 0.3]
    u = np.r_[rng.normal(size=2), -9.8, rng.normal(size=3) * 0.05]
    xs = propagate_steps(x, u, 0.1, 7)
    assert xs.shape == (8, 9)
    y = x
    for t in range(7):
        y = propagate(y, u, 0.1)
        np.testing.assert_array_equal(xs[t + 1], y)  # the same arithmetic, same machine
    with pytest.raises(ValueError, match="x"):
        propagate_steps(np.zeros(3), u, 0.1, 2)
