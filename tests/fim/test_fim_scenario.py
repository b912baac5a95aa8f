"""Tests of the Kirchner et al. (2020) models and the FIM-selection scenario."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from selenv.core.information import logdet_objective
from selenv.families.fim import models as km
from selenv.families.fim.scenario import (
    PRESETS,
    SENSOR_NAMES,
    FIMProblem,
    FIMScenarioConfig,
    config_from,
    make_problem,
)

ALL_SENSORS = ("camera", "toa", "doppler")


def central_fd(f, x: np.ndarray, rel: float = 1e-6) -> np.ndarray:
    """Central differences of ``f: (d,) -> (...)``; returns ``(..., d)``."""
    cols = []
    for j in range(x.size):
        h = rel * max(1.0, abs(x[j]))
        e = np.zeros_like(x)
        e[j] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def assert_jac_close(J: np.ndarray, J_fd: np.ndarray, rtol: float = 1e-5) -> None:
    assert J.shape == J_fd.shape
    np.testing.assert_allclose(J, J_fd, rtol=rtol, atol=rtol * 1e-3 * np.max(np.abs(J_fd)))


def random_geometry(rng: np.random.Generator, T: int = 40):
    """Random times, agent positions (above ground) and velocities, and a motion theta."""
    s = rng.uniform(0.0, 60.0, T)
    p = np.column_stack([rng.uniform(-300, 300, (T, 2)), rng.uniform(20, 120, T)])
    pdot = rng.normal(0.0, 10.0, (T, 3))
    theta = np.concatenate([rng.normal(0, 20, 2), rng.normal(0, 2, 2), rng.normal(0, 0.05, 2)])
    return s, p, pdot, theta


# -- kirchner_models: Jacobians against finite differences --------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_toa_jacobian_matches_fd(seed: int) -> None:
    rng = np.random.default_rng(seed)
    s, p, _, theta = random_geometry(rng)
    k = np.arange(s.size)
    x = np.concatenate([theta, [rng.normal(0, 1), rng.normal(0, 100)]])  # + theta_T, theta_T0

    def f(x: np.ndarray) -> np.ndarray:
        return km.toa_mean(x[:6], s, p, k, x[6], x[7])

    J = km.toa_jacobian(theta, s, p, k)
    assert J.shape == (s.size, 8)
    assert_jac_close(J, central_fd(f, x))
    np.testing.assert_array_equal(J[:, 6], k)  # d / d theta_T = k
    np.testing.assert_array_equal(J[:, 7], 1.0)  # d / d theta_T0 = 1


def test_toa_mean_is_eq20() -> None:
    s = np.array([0.0, 10.0])
    p = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 12.0]])
    theta = np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0])  # q(10) = (5, 0)
    mu = km.toa_mean(theta, s, p, np.array([0, 7]), 2.0, 100.0)
    np.testing.assert_allclose(mu, [5.0 + 100.0, 13.0 + 14.0 + 100.0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_doppler_jacobian_matches_fd(seed: int) -> None:
    rng = np.random.default_rng(seed)
    s, p, pdot, theta = random_geometry(rng)
    x = np.concatenate([theta, [rng.normal(0, 300)]])

    def f(x: np.ndarray) -> np.ndarray:
        return km.doppler_mean(x[:6], s, p, pdot, x[6])

    J = km.doppler_jacobian(theta, s, p, pdot)
    assert J.shape == (s.size, 7)
    assert_jac_close(J, central_fd(f, x))
    np.testing.assert_array_equal(J[:, 6], 1.0)


def test_doppler_sign_is_minus_range_rate() -> None:
    # receiver flying straight away from a stationary target: rhodot = +|v|, mean = -|v|
    s = np.array([5.0])
    p = np.array([[100.0, 0.0, 0.0]])
    pdot = np.array([[7.0, 0.0, 0.0]])
    np.testing.assert_allclose(km.doppler_mean(np.zeros(6), s, p, pdot, 0.0), [-7.0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_jacobian_matches_fd(seed: int) -> None:
    rng = np.random.default_rng(seed)
    s, p, _, theta = random_geometry(rng)
    q, _ = km.target_state(theta, s)
    aim = np.column_stack([q + rng.normal(0, 5, q.shape), np.zeros(s.size)])
    Rc = km.look_at_rotation(p, aim)
    A = km.intrinsics(50.0, 3.0, -2.0)
    assert np.all(km.camera_depth(theta, s, p, Rc, A) > 0)
    J = km.camera_jacobian(theta, s, p, Rc, A)
    assert J.shape == (s.size, 2, 6)
    assert_jac_close(J, central_fd(lambda x: km.camera_mean(x, s, p, Rc, A), theta))


def test_motion_model_eq18() -> None:
    theta = np.array([1.0, 2.0, 3.0, 4.0, 0.5, -1.0])
    q, qdot = km.target_state(theta, np.array([0.0, 2.0]))
    np.testing.assert_allclose(q, [[1.0, 2.0], [1 + 6 + 1, 2 + 8 - 2]])
    np.testing.assert_allclose(qdot, [[3.0, 4.0], [4.0, 2.0]])


def test_look_at_rotation_convention() -> None:
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.normal(0, 100, (20, 2)), rng.uniform(10, 80, 20)])
    target = np.array([3.0, -4.0, 0.0])
    Rc = km.look_at_rotation(p, target)
    np.testing.assert_allclose(
        Rc @ np.swapaxes(Rc, 1, 2), np.broadcast_to(np.eye(3), Rc.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(Rc), 1.0)
    u = (target - p) / np.linalg.norm(target - p, axis=1, keepdims=True)
    np.testing.assert_allclose(Rc[:, 2], u, atol=1e-12)  # optical axis towards the target
    np.testing.assert_allclose(Rc[:, 0, 2], 0.0, atol=1e-12)  # image x is horizontal
    assert np.all(Rc[:, 1, 2] < 0)  # image y points down in the world
    # the aimed-at point projects onto the principal point
    theta = np.array([3.0, -4.0, 0, 0, 0, 0])
    A = km.intrinsics(50.0, 10.0, 20.0)
    np.testing.assert_allclose(
        km.camera_mean(theta, np.zeros(20), p, Rc, A), np.tile([10.0, 20.0], (20, 1)), atol=1e-9
    )
    with pytest.raises(ValueError, match="target"):
        km.look_at_rotation(np.array([[3.0, -4.0, 0.0]]), target)
    down = km.look_at_rotation(np.array([[0.0, 0.0, 10.0]]), np.zeros(3))  # vertical fallback
    np.testing.assert_allclose(down[0] @ down[0].T, np.eye(3), atol=1e-12)


def test_spiral_path_velocity_is_derivative() -> None:
    s = np.linspace(1.0, 59.0, 30)
    theta = np.array([0.0, 0.0, 3.0, 1.0, 0.05, -0.02])

    def pos(s_: np.ndarray) -> np.ndarray:
        q, qd = km.target_state(theta, s_)
        kw = dict(window_s=60.0, start_radius=400.0, end_radius=60.0, sweep_rad=np.pi,
                  end_bearing=0.3, altitude=50.0)  # fmt: skip
        return km.spiral_path(s_, q, qd, **kw)

    p, v = pos(s)
    h = 1e-4
    np.testing.assert_allclose(v, (pos(s + h)[0] - pos(s - h)[0]) / (2 * h), rtol=1e-6, atol=1e-6)
    q, _ = km.target_state(theta, s)
    rng_ = np.linalg.norm(p[:, :2] - q, axis=1)
    np.testing.assert_allclose(rng_[[0, -1]], [400 - 340 / 60, 60 + 340 / 60], rtol=1e-12)
    assert np.all(np.diff(rng_) < 0)  # closest at the end
    np.testing.assert_allclose(p[:, 2], 50.0)


# -- the scenario -------------------------------------------------------------------------------
def small(preset: str = "example2_moving", **kw) -> FIMProblem:
    kw.setdefault("n_candidates", 25)
    seed = kw.pop("seed", 0)
    return make_problem(config_from(preset, **kw), np.random.default_rng(seed))


@pytest.mark.parametrize("randomize", [False, True])
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_problem_jacobian_matches_fd_with_nuisance(preset: str, randomize: bool) -> None:
    P = small(preset, sensors=ALL_SENSORS, n_candidates=15, randomize=randomize)
    rng = np.random.default_rng(11)
    idx = rng.permutation(P.N)[:30]
    for _ in range(2):
        theta = P.theta_prior_mean + np.sqrt(np.diag(P.P0)) * rng.normal(size=P.d)
        J = P.measurement_jacobian(theta, idx)
        assert J.shape == (idx.size, P.m, P.d)
        assert_jac_close(J, central_fd(lambda x: P.measurement_mean(x, idx), theta))
    # H is the Jacobian at the prior mean, not at the truth
    np.testing.assert_array_equal(P.H, P.measurement_jacobian(P.theta_prior_mean))
    # nuisance columns: toa has k and 1 on its agent's columns, doppler 1
    for a in range(P.config.n_agents):
        toa = np.flatnonzero((P.agent == a) & (P.sensor == 1))
        cT, cT0 = P.param_names.index(f"cT[{a}]"), P.param_names.index(f"cT0[{a}]")
        lam = P.param_names.index(f"lambdaDf[{a}]")
        np.testing.assert_array_equal(P.H[toa, 0, cT], np.arange(toa.size))
        np.testing.assert_array_equal(P.H[toa, 0, cT0], 1.0)
        dop = np.flatnonzero((P.agent == a) & (P.sensor == 2))
        np.testing.assert_array_equal(P.H[dop, 0, lam], 1.0)
        others = np.flatnonzero(P.agent != a)
        assert not np.any(P.H[others][:, :, [cT, cT0, lam]])


def test_Qk_from_G_equals_inverse_formula() -> None:
    P = small("example3_moving", sensors=ALL_SENSORS, randomize=True)
    Q_white = np.einsum("kmi,kmj->kij", P.G, P.G)
    Q_inv = np.stack([P.H[k].T @ np.linalg.inv(P.R[k]) @ P.H[k] for k in range(P.N)])
    np.testing.assert_allclose(Q_white, Q_inv, rtol=1e-9, atol=1e-12 * np.abs(Q_inv).max())
    np.testing.assert_allclose(P.Q0 @ P.P0, np.eye(P.d), atol=1e-12)


def test_padding_and_noise() -> None:
    cfg = config_from("example2_moving", sensors=ALL_SENSORS, n_candidates=10)
    P = make_problem(cfg, np.random.default_rng(0))
    cam, toa, dop = (P.sensor == c for c in range(3))
    assert P.m == 2
    np.testing.assert_array_equal(P.rows, np.where(cam, 2, 1))
    assert not np.any(P.H[~cam, 1, :])  # scalar candidates zero-padded
    np.testing.assert_array_equal(P.R[~cam, 1, 1], 1.0)
    np.testing.assert_array_equal(P.R[:, 0, 1], 0.0)
    np.testing.assert_allclose(P.R[cam], np.broadcast_to(0.8**2 * np.eye(2), (10, 2, 2)))
    np.testing.assert_allclose(P.R[toa, 0, 0], 3.0**2)
    np.testing.assert_allclose(P.R[dop, 0, 0], (33e-9 * 299_792_458) ** 2)
    scalar = make_problem(
        config_from("example2_moving", sensors=("toa",), n_candidates=5), np.random.default_rng(0)
    )
    assert scalar.H.shape == (5, 1, 8) and scalar.m == 1


def test_same_seed_same_problem_and_seeds_differ() -> None:
    cfg = config_from("example3_moving", sensors=ALL_SENSORS, n_candidates=40, randomize=True)
    a, b = (make_problem(cfg, np.random.default_rng(7)) for _ in range(2))
    for name in ("H", "G", "R", "theta_true", "times", "positions", "Q0"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    c = make_problem(cfg, np.random.default_rng(8))
    assert not np.array_equal(a.H, c.H)
    assert not np.array_equal(a.theta_true, c.theta_true)
    assert not np.array_equal(a.times, c.times)
    # without randomize the geometry is fixed and only the truth changes
    fixed = dataclasses.replace(cfg, randomize=False)
    d, e = (make_problem(fixed, np.random.default_rng(s)) for s in (1, 2))
    np.testing.assert_array_equal(d.H, e.H)
    assert not np.array_equal(d.theta_true, e.theta_true)


def test_presets() -> None:
    moving = ("example1_moving", "example2_moving", "example3_moving")
    assert set(PRESETS) == {"example1", "example2", "example3", *moving}
    cd = ("camera", "doppler")
    # name: (agents, sensors, stationary, d); d = motion parameters + one lambdaDf per Doppler
    expect = {"example1": (1, ("camera",), True, 2), "example2": (1, cd, True, 3),
              "example3": (2, cd, True, 4), "example1_moving": (1, ("camera",), False, 6),
              "example2_moving": (1, cd, False, 7),
              "example3_moving": (2, cd, False, 8)}  # fmt: skip
    for name, (n_agents, sensors, stationary, d) in expect.items():
        cfg = PRESETS[name]
        assert cfg.n_candidates == 1000 and cfg.preset == name
        assert cfg.n_agents == n_agents and cfg.sensors == sensors
        assert cfg.stationary is stationary
        P = make_problem(cfg, np.random.default_rng(0))
        assert P.d == d and len(P.param_names) == d
        assert P.N == 1000 * len(sensors) * n_agents
        assert set(P.sensor.tolist()) == {SENSOR_NAMES.index(s) for s in sensors}
        assert P.G.shape == P.H.shape == (P.N, 2, d) and P.R.shape == (P.N, 2, 2)
        for arr in (P.agent, P.sensor, P.rows, P.times):
            assert arr.shape == (P.N,)
        assert P.positions.shape == (P.N, 3)
    P1 = make_problem(PRESETS["example1"], np.random.default_rng(3))
    assert P1.param_names == ("x", "y")  # stationary: theta_2 = theta_3 = 0, not estimated
    np.testing.assert_array_equal(P1.full_theta(P1.theta_true)[2:6], 0.0)
    assert small("example3_moving").param_names == (
        "x", "y", "vx", "vy", "ax", "ay", "lambdaDf[0]", "lambdaDf[1]"
    )  # fmt: skip
    assert small("example3_moving", sensors=ALL_SENSORS).param_names[6:] == (
        "cT[0]", "cT0[0]", "lambdaDf[0]", "cT[1]", "cT0[1]", "lambdaDf[1]"
    )  # fmt: skip


@pytest.mark.parametrize("preset", ["example1", "example2", "example3"])
def test_paper_presets_estimate_a_stationary_position(preset: str) -> None:
    """Examples 1-3 as in the paper: one stationary vehicle, theta_2 = theta_3 = 0 known."""
    n = PRESETS[preset].n_agents
    P = small(preset, seed=4)
    nuisance = ("lambdaDf[0]", "lambdaDf[1]")[: n if preset != "example1" else 0]
    assert P.param_names == ("x", "y", *nuisance)  # d = 2 position-only motion parameters
    np.testing.assert_array_equal(P.free[:2], [0, 1])
    assert not set(P.free.tolist()) & {2, 3, 4, 5}  # velocity, curvature not estimated
    full = P.full_theta(P.theta_true)
    np.testing.assert_array_equal(full[2:6], 0.0)
    # the target does not move: its trajectory (eq. 18) is the start position at every time
    q, qdot = km.target_state(full, P.times)
    np.testing.assert_array_equal(q, np.broadcast_to(P.theta_true[:2], q.shape))
    np.testing.assert_array_equal(qdot, 0.0)
    # the moving variant of the same pool estimates velocity and curvature as well
    M = small(f"{preset}_moving", seed=4)
    assert M.param_names[:6] == ("x", "y", "vx", "vy", "ax", "ay")
    assert M.param_names[6:] == P.param_names[2:]
    assert np.any(M.full_theta(M.theta_true)[2:6] != 0.0)


@pytest.mark.parametrize(("preset", "n_agents"), [("example2_moving", 1), ("example3_moving", 2)])
def test_moving_presets_are_the_v0_presets(preset: str, n_agents: int) -> None:
    """``example2/3_moving`` = the earlier moving ``example2/3`` (written out field by field)."""
    old = FIMScenarioConfig(preset=preset, n_agents=n_agents, sensors=("camera", "doppler"),
                            n_candidates=40, randomize=True)  # fmt: skip
    assert not old.stationary
    a = make_problem(config_from(preset, n_candidates=40, randomize=True), np.random.default_rng(5))
    b = make_problem(old, np.random.default_rng(5))
    assert a.config == old and a.param_names == b.param_names
    for f in dataclasses.fields(FIMProblem):
        if f.name not in ("config", "param_names"):
            np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), err_msg=f.name)


def _rollout(env, seed: int, steps: int) -> list:
    """Observations and rewards of ``steps`` picks drawn from a seeded generator (masked)."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        action = int(rng.choice(np.flatnonzero(info["action_mask"])))
        obs, reward, *_, info = env.step(action)
        out += [obs, reward, info["objective"]]
    return out


def _assert_same(a: list, b: list) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        if isinstance(x, dict):
            assert x.keys() == y.keys()
            for key in x:
                np.testing.assert_array_equal(x[key], y[key], err_msg=key)
        else:
            assert x == y  # bit-identical floats


def test_env_defaults_keep_the_v0_moving_presets() -> None:
    """FIMSelection-v1 defaults to example2_moving, fim_selection_v0 to example3_moving."""
    import gymnasium as gym

    import selenv  # noqa: F401  (registers the ids)
    from selenv.multiagent import fim_selection_v0

    env_id = "selenv/FIMSelection-v1"
    default, moving = gym.make(env_id), gym.make(env_id, preset="example2_moving")
    assert default.unwrapped.config == moving.unwrapped.config  # type: ignore[attr-defined]
    for seed in (0, 1):
        _assert_same(_rollout(default, seed, 6), _rollout(moving, seed, 6))
    paper = gym.make(env_id, preset="example2")
    assert paper.unwrapped.config.stationary  # type: ignore[attr-defined]
    obs, _ = paper.reset(seed=0)
    assert paper.unwrapped.problem.param_names == ("x", "y", "lambdaDf[0]")  # type: ignore[attr-defined]
    assert obs["whitened"].shape[-1] != default.reset(seed=0)[0]["whitened"].shape[-1]

    ma_default = fim_selection_v0.parallel_env()
    ma_moving = fim_selection_v0.parallel_env(preset="example3_moving")
    assert ma_default.config == ma_moving.config and not ma_default.config.stationary
    for seed in (0, 1):
        runs = []
        for env in (ma_default, ma_moving):
            rng = np.random.default_rng(seed)
            obs, _ = env.reset(seed=seed)
            trace = [obs]
            while env.agents:
                acts = {
                    ag: int(rng.choice(np.flatnonzero(obs[ag]["action_mask"]))) for ag in env.agents
                }
                obs, rew, *_ = env.step(acts)
                trace += [obs, rew]
            runs.append(trace)
        assert len(runs[0]) == len(runs[1]) > 2
        for x, y in zip(*runs, strict=True):
            assert x.keys() == y.keys()
            for ag in x:
                if isinstance(x[ag], dict):
                    for key in x[ag]:
                        np.testing.assert_array_equal(x[ag][key], y[ag][key], err_msg=key)
                else:
                    assert x[ag] == y[ag]


def test_candidate_order_and_pools() -> None:
    P = small("example3_moving", sensors=("doppler", "camera", "toa"), randomize=True)
    assert P.config.sensors == ALL_SENSORS  # canonical order
    key = np.lexsort((P.times, P.sensor, P.agent))
    np.testing.assert_array_equal(key, np.arange(P.N))  # agent-major, sensor, time
    assert np.all(np.diff(P.agent) >= 0)
    for a in range(2):
        np.testing.assert_array_equal(P.pool(a), np.flatnonzero(P.agent == a))
        assert P.pool(a).size == 3 * 25
    with pytest.raises(ValueError, match="agent_index"):
        P.pool(2)
    assert np.all((P.times >= 0) & (P.times <= P.config.window_s))


def test_agents_approach_target_from_different_sides() -> None:
    P = small("example3_moving")
    q, _ = km.target_state(P.theta_prior_mean, P.times)
    dist = np.linalg.norm(P.positions[:, :2] - q, axis=1)
    ends = []
    for a in range(2):
        cam = np.flatnonzero((P.agent == a) & (P.sensor == 0))
        assert np.argmin(dist[cam]) == cam.size - 1  # closest at the end of the path
        ends.append(P.positions[cam[-1], :2] - q[cam[-1]])
    assert ends[0] @ ends[1] < 0  # opposite sides


@pytest.mark.parametrize("randomize", [False, True])
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_camera_points_in_front(preset: str, randomize: bool) -> None:
    for seed in range(5):
        P = make_problem(config_from(preset, randomize=randomize), np.random.default_rng(seed))
        cam = np.flatnonzero(P.sensor == 0)
        assert cam.size == 1000 * P.config.n_agents
        args = (P.times[cam], P.positions[cam], P.camera_rotation[cam], P.intrinsics)
        assert np.all(km.camera_depth(P.full_theta(P.theta_prior_mean), *args) > 0)
        assert np.all(km.camera_depth(P.full_theta(P.theta_true), *args) > 0)


def test_truth_redrawn_until_in_front_of_cameras() -> None:
    cfg = config_from("example2_moving", n_candidates=50, prior_position_m=150.0)
    behind = 0
    for seed in range(20):
        P = make_problem(cfg, np.random.default_rng(seed))
        cam = np.flatnonzero(P.sensor == 0)
        args = (P.times[cam], P.positions[cam], P.camera_rotation[cam], P.intrinsics)
        assert np.all(km.camera_depth(P.theta_true, *args) > 0)
        # a raw prior draw at this width often lands behind a camera: the check is not vacuous
        raw = P.theta_prior_mean + np.sqrt(np.diag(P.P0)) * np.random.default_rng(seed).normal(
            size=P.d
        )
        behind += bool(np.any(km.camera_depth(raw, *args) <= 0))
    assert behind > 0
    with pytest.raises(ValueError, match="prior"):
        make_problem(
            # cameras all round the target and a huge prior: no draw is in front of all of them
            config_from("example1", n_candidates=20, sweep_deg=300.0, prior_position_m=1e5),
            np.random.default_rng(0),
        )


def test_sample_measurements_statistics() -> None:
    P = small("example2_moving", sensors=ALL_SENSORS, randomize=True)
    rng = np.random.default_rng(99)
    n = 20000
    for code in range(3):
        k = int(np.flatnonzero(P.sensor == code)[3])
        y = P.sample_measurements(rng, np.full(n, k))
        assert y.shape == (n, 2)
        mu = P.measurement_mean(P.theta_true, [k])[0]
        sd = np.sqrt(np.diag(P.R[k]))
        assert np.all(np.abs(y.mean(axis=0) - mu) < 5 * sd / np.sqrt(n))
        np.testing.assert_allclose(np.cov(y.T), P.R[k], rtol=0.05, atol=0.03 * sd.max() ** 2)
    # one call over every candidate: mean at the truth, not at the prior mean
    ys = np.stack([P.sample_measurements(rng) for _ in range(400)])
    z = (ys.mean(axis=0) - P.measurement_mean(P.theta_true)) / np.sqrt(
        np.diagonal(P.R, axis1=1, axis2=2) / 400
    )
    assert np.abs(z).max() < 6


def test_sample_measurements_reproducible() -> None:
    P = small()
    a = P.sample_measurements(np.random.default_rng(1), [0, 5, 30])
    b = P.sample_measurements(np.random.default_rng(1), [0, 5, 30])
    np.testing.assert_array_equal(a, b)


def test_problem_arrays_read_only() -> None:
    P = small()
    with pytest.raises(ValueError):
        P.H[0, 0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        P.H = P.G  # type: ignore[misc]


def test_information_grows_with_measurements() -> None:
    P = small("example2_moving", n_candidates=200)
    f_all = logdet_objective(P.Q0, P.G, np.arange(P.N))
    f_half = logdet_objective(P.Q0, P.G, np.arange(0, P.N, 2))
    assert f_all > f_half > 0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"sensors": ("camera", "lidar")}, "sensors"),
        ({"sensors": ()}, "sensors"),
        ({"sensors": "camera"}, "sensors"),
        ({"sensors": ("camera", "camera")}, "sensors"),
        ({"n_candidates": 0}, "n_candidates"),
        ({"n_candidates": 2.5}, "n_candidates"),
        ({"n_agents": 0}, "n_agents"),
        ({"n_agents": True}, "n_agents"),
        ({"camera_sigma_px": -1.0}, "camera_sigma_px"),
        ({"toa_sigma_m": 0.0}, "toa_sigma_m"),
        ({"doppler_sigma_mps": float("nan")}, "doppler_sigma_mps"),
        ({"focal_px": -50.0}, "focal_px"),
        ({"window_s": 0.0}, "window_s"),
        ({"prior_position_m": -1.0}, "prior_position_m"),
        ({"prior_lambda_mps": float("inf")}, "prior_lambda_mps"),
        ({"altitude_m": 0.0}, "altitude_m"),
        ({"stationary": 1}, "stationary"),
        ({"randomize": "yes"}, "randomize"),
    ],
)
def test_bad_config_raises_naming_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        FIMScenarioConfig(**kwargs)
    with pytest.raises(ValueError, match=field):
        config_from("example1", **kwargs)


def test_config_from_errors_list_valid_names() -> None:
    with pytest.raises(ValueError, match=r"example1.*example2.*example3"):
        config_from("example9")
    with pytest.raises(ValueError, match="n_candidates"):
        config_from("example2_moving", n_candidate=5)
    cfg = config_from("example1", n_candidates=7, sensors=["doppler", "camera"])
    assert cfg.sensors == ("camera", "doppler") and cfg.n_candidates == 7
    assert cfg.preset == "example1" and PRESETS["example1"].n_candidates == 1000


def test_bad_indices_and_theta() -> None:
    P = small()
    with pytest.raises(ValueError, match="idx"):
        P.measurement_mean(P.theta_true, [P.N])
    with pytest.raises(ValueError, match="idx"):
        P.measurement_jacobian(P.theta_true, [0.5])
    with pytest.raises(ValueError, match="theta"):
        P.measurement_mean(np.zeros(3), [0])


def test_build_with_every_sensor_has_the_full_pool() -> None:
    """Timing of this build lives in benchmarks/, not here (no timed tests)."""
    cfg = config_from("example2_moving", sensors=ALL_SENSORS, randomize=True)
    P = make_problem(cfg, np.random.default_rng(0))
    assert P.N == 3000 and P.G.shape[0] == 3000
