"""Speed work: the faster CLScheduling step and LandmarkSelection reset give the previous results.

The references below are the previous implementations, kept verbatim: the per-pair loop of
``CLSchedulingEnv._pair_gains``, the uncached objective, ``relative_update`` for the env's
pair update, the separate ``jacobians`` / ``propagate`` calls of ``CLSimulation.predict`` (with
the previous strapdown formulas), and the landmark flight flown anew at every reset. The new
internals are compared with them on many states, and seeded episodes played by several agents
are recorded (every action, observation array, reward, terminated / truncated and info entry)
with the new code and with the references patched in.

Contract: the references and the new code run in the same process, so a comparison is exact
where both do the same operations (the strapdown formulas, the prediction, the cached objective
and log dets, the flight cache, ``process_noise``). Where the new code batches what the
reference did one pair at a time (``_pair_gains``, ``relative_jacobians``) the BLAS kernel may
take another path per matrix and round differently (it does under ``OPENBLAS_CORETYPE=Prescott``),
so those floats are compared with ``assert_allclose(rtol=1e-9)``. Episodes: the decisions and
integer / bool data (actions, masks, flags, ``k``, lengths) are exact, the floats within
``rtol=1e-9`` (float32 observations within one float32 ulp, see ``assert_same_episode``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

import selenv.families.cooperative.scenario as coop
import selenv.families.landmarks.scenario as landmarks_mod
from selenv.core.linalg import FloatArray, logdet_spd
from selenv.families.cooperative.env import CLSchedulingEnv, agent_objective
from selenv.families.landmarks import models as lm
from selenv.families.landmarks.env import LandmarkSelectionEnv
from selenv.families.landmarks.flight import fly
from selenv.families.landmarks.scenario import LandmarkConfig, make_landmark_problem

# ------------------------------------------------------------------ previous implementation


def _ref_trig(theta: Any) -> tuple[float, float, float, float, float, float]:
    r, p, y = float(theta[0]), float(theta[1]), float(theta[2])
    return math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(y), math.cos(y)


def _ref_dcm(th: FloatArray) -> FloatArray:
    sr, cr, sp, cp, sy, cy = _ref_trig(th)
    return np.array(
        [
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [sp, -sr * cp, -cr * cp],
        ]
    )


def _ref_dcm_derivatives(th: FloatArray) -> FloatArray:
    sr, cr, sp, cp, sy, cy = _ref_trig(th)
    return np.array(
        [
            [
                [0.0, cr * sp * sy - sr * cy, -sr * sp * sy - cr * cy],
                [0.0, cr * sp * cy + sr * sy, -sr * sp * cy + cr * sy],
                [0.0, -cr * cp, sr * cp],
            ],
            [
                [-sp * sy, sr * cp * sy, cr * cp * sy],
                [-sp * cy, sr * cp * cy, cr * cp * cy],
                [cp, sr * sp, cr * sp],
            ],
            [
                [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                [-cp * sy, -sr * sp * sy - cr * cy, -cr * sp * sy + sr * cy],
                [0.0, 0.0, 0.0],
            ],
        ]
    )


def _ref_rate_matrix(th: FloatArray) -> FloatArray:
    sr, cr, sp, cp, _, _ = _ref_trig(th)
    tp = sp / cp
    return np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr / cp, cr / cp]])


def _ref_rate_derivatives(th: FloatArray) -> tuple[FloatArray, FloatArray]:
    sr, cr, sp, cp, _, _ = _ref_trig(th)
    tp, c2 = sp / cp, cp * cp
    dEr = np.array([[0.0, cr * tp, -sr * tp], [0.0, -sr, -cr], [0.0, cr / cp, -sr / cp]])
    dEp = np.array([[0.0, sr / c2, cr / c2], [0.0, 0.0, 0.0], [0.0, sr * sp / c2, cr * sp / c2]])
    return dEr, dEp


def ref_propagate(x: FloatArray, u: FloatArray, h: float) -> FloatArray:
    """The previous ``landmark_models.propagate`` (checked inputs)."""
    p, v, th = x[0:3], x[3:6], x[6:9]
    a = _ref_dcm(th) @ u[0:3] + np.array([0.0, 0.0, -lm.GRAVITY])
    out = np.empty(lm.STATE_DIM)
    out[0:3] = p + v * h + 0.5 * a * h * h
    out[3:6] = v + a * h
    out[6:9] = th + _ref_rate_matrix(th) @ u[3:6] * h
    return out


def ref_propagation_jacobians(x: FloatArray, u: FloatArray, h: float) -> tuple[Any, Any]:
    """The previous ``landmark_models.propagation_jacobians`` (checked inputs)."""
    th, f, w = x[6:9], u[0:3], u[3:6]
    C = _ref_dcm(th)
    A = _ref_dcm_derivatives(th) @ f
    dEr, dEp = _ref_rate_derivatives(th)
    F = np.eye(lm.STATE_DIM)
    F[0:3, 3:6] = h * np.eye(3)
    F[0:3, 6:9] = 0.5 * h * h * A.T
    F[3:6, 6:9] = h * A.T
    F[6:9, 6] += h * (dEr @ w)
    F[6:9, 7] += h * (dEp @ w)
    G = np.zeros((lm.STATE_DIM, 6))
    G[0:3, 0:3] = 0.5 * h * h * C
    G[3:6, 0:3] = h * C
    G[6:9, 3:6] = h * _ref_rate_matrix(th)
    return F, G


def ref_predict(sim: coop.CLSimulation) -> None:
    """The previous ``CLSimulation.predict``: ``jacobians`` then ``propagate`` per agent."""
    cfg = sim.problem.config
    for i in range(cfg.n_agents):
        u = sim.problem.inputs[sim.k, i]
        if sim.model.name == "ins":
            F, G = ref_propagation_jacobians(sim.x[i], u, cfg.dt)
            Q = lm.process_noise(G, *cfg.input_sigma_of(i))
            sim.x[i] = ref_propagate(sim.x[i], u, cfg.dt)
        else:
            F, Q = sim.model.jacobians(sim.x[i], u, cfg.dt, cfg.input_sigma_of(i))
            sim.x[i] = sim.model.propagate(sim.x[i], u, cfg.dt)
        P = F @ sim.P[i] @ F.T + Q
        sim.P[i] = 0.5 * (P + P.T)
    sim.k += 1


def ref_relative_update(sim: coop.CLSimulation, p: int, method: str | None = None) -> float:
    """The previous ``CLSimulation.relative_update`` (the env's pair update)."""
    i = sim.problem.config.relative_pairs[p][0]
    before = float(logdet_spd(sim.P[i], "P_i"))
    sim.x[i], sim.P[i] = sim.preview(p, method)
    return before - float(logdet_spd(sim.P[i], "P_i"))


def ref_pair_gains(env: CLSchedulingEnv) -> np.ndarray:
    """The previous ``CLSchedulingEnv._pair_gains``: one update per open pair."""
    sim = env.sim
    out = np.zeros(env.n_pairs)
    mask = env.action_masks()
    for p in np.flatnonzero(mask[:-1]):
        i, j = env.pairs[p]
        H_i, H_j, _ = sim.relative_terms(int(p))
        A = H_i @ sim.P[i] @ H_i.T
        N = H_j @ sim.P[j] @ H_j.T + sim.R_rel
        out[p] = np.linalg.slogdet(np.eye(A.shape[0]) + np.linalg.solve(N, A))[1]
    return out


class RefCLEnv(CLSchedulingEnv):
    """``CLSchedulingEnv`` with the previous pair gains, objective, update and prediction."""

    def objective_value(self) -> float:
        return float(np.sum(agent_objective(self.sim.P, self.objective)))

    def _pair_gains(self, mask: np.ndarray | None = None) -> np.ndarray:
        return ref_pair_gains(self)

    def _advance(self) -> None:
        sim = self.sim
        sim.predict = lambda: ref_predict(sim)  # type: ignore[method-assign]

        def apply_relative(p: int, method: str | None = None) -> None:
            ref_relative_update(sim, p, method)

        sim.apply_relative = apply_relative  # type: ignore[method-assign]
        super()._advance()


def ref_flight(cfg: LandmarkConfig) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The previous reset: fly the trajectory and form ``F_true``, ``Q`` anew every time."""
    states, imu_true = fly(cfg)
    T, dt = int(cfg.horizon), float(cfg.dt)
    F_true, Q = np.empty((T, 9, 9)), np.empty((T, 9, 9))
    for k in range(T):
        F_true[k], G = ref_propagation_jacobians(states[k], imu_true[k], dt)
        Q[k] = lm.process_noise(G, float(cfg.accel_sigma), cfg.gyro_sigma)
    return states, imu_true, F_true, Q


# ------------------------------------------------------------------ recording episodes

#: float32 observations are roundings of float64 values that may differ in the last bits (the
#: batched pair gains), and such a rounding can land one float32 ulp apart: allow that much
F32_RTOL = float(np.finfo(np.float32).eps)
F64_RTOL = 1e-9


def _flatten(x: Any, path: str, out: list[tuple[str, Any]]) -> None:
    """Append ``(path, leaf)`` for every leaf of nested dicts / lists / tuples."""
    if isinstance(x, dict):
        out.append((f"{path}{{}}", tuple(sorted(x))))  # the keys, exactly
        for k in sorted(x):
            _flatten(x[k], f"{path}.{k}", out)
    elif isinstance(x, list | tuple):
        out.append((f"{path}[]", len(x)))
        for i, v in enumerate(x):
            _flatten(v, f"{path}[{i}]", out)
    else:
        out.append((path, np.array(x, copy=True) if isinstance(x, np.ndarray) else x))


def play(env: Any, seed: int, agent: str, max_steps: int = 300) -> list[tuple[str, Any]]:
    """A seeded episode as ``(path, leaf)`` records: every action, obs array, reward, flag, info."""
    out: list[tuple[str, Any]] = []
    obs, info = env.reset(seed=seed)
    _flatten((obs, info), "reset", out)
    rng = np.random.default_rng(seed + 1000)
    for t in range(max_steps):
        mask = np.asarray(info["action_mask"], bool)
        valid = np.flatnonzero(mask)
        if agent == "random":
            a = int(rng.choice(valid))
        elif agent == "first":
            a = int(valid[0])
        elif agent == "last":
            a = int(valid[-1])
        elif agent == "greedy_obs":
            g = obs["pair_gain"] if "pair_gain" in obs else obs["gain"]
            open_ = np.flatnonzero(mask[: len(g)])
            a = int(open_[np.argmax(g[open_])]) if len(open_) else int(valid[-1])
        else:  # "invalid": any action, masked ones too (noop mode)
            a = int(rng.integers(0, len(mask)))
        obs, r, term, trunc, info = env.step(a)
        _flatten((a, obs, float(r), term, trunc, info), f"step{t}", out)
        if term or trunc:
            break
    return out


def _is_float(v: Any) -> bool:
    return isinstance(v, float | np.floating) or (
        isinstance(v, np.ndarray) and v.dtype.kind in "fc"
    )


def assert_same_episode(got: list[tuple[str, Any]], want: list[tuple[str, Any]]) -> None:
    """Same records in the same order (so the same length and actions); non-floats exact (type,
    dtype, shape, value), floats within ``F64_RTOL`` (float32 arrays: ``F32_RTOL``)."""
    assert [k for k, _ in got] == [k for k, _ in want]
    for (path, g), (_, w) in zip(got, want, strict=True):
        assert type(g) is type(w), (path, type(g), type(w))
        if isinstance(g, np.ndarray):
            assert (g.dtype, g.shape) == (w.dtype, w.shape), path
        if _is_float(g):
            rtol = F32_RTOL if np.asarray(g).dtype == np.float32 else F64_RTOL
            np.testing.assert_allclose(g, w, rtol=rtol, atol=0, err_msg=path)
        elif isinstance(g, np.ndarray):
            np.testing.assert_array_equal(g, w, err_msg=path)
        else:
            assert g == w, (path, g, w)


AGENTS = ("random", "first", "last", "greedy_obs", "invalid")
CL_CASES: dict[str, dict[str, Any]] = {
    "dense": {"preset": "dense", "horizon": 25},
    "benchmark": {"horizon": 12},
    "bearing_pecmv": {"preset": "dense", "horizon": 5, "fusion": "pecmv", "bearing_sigma_deg": 2.0},
    "unicycle_chain": {"preset": "dense", "horizon": 10, "model": "unicycle", "topology": "chain",
                       "fusion": "naive"},
    "paper_trace": {"preset": "paper", "horizon": 12, "objective": "trace", "relative_every": 1},
}  # fmt: skip


@pytest.mark.parametrize("case", list(CL_CASES))
def test_cl_episodes_match_the_reference(case: str) -> None:
    kw = CL_CASES[case]
    new, ref = CLSchedulingEnv(**kw), RefCLEnv(**kw)
    for agent in AGENTS:
        for seed in range(2):
            assert_same_episode(play(new, seed, agent), play(ref, seed, agent))


@pytest.mark.parametrize("seed", range(6))
def test_cl_internals_match_the_reference_on_many_states(seed: int) -> None:
    kw = [CL_CASES["dense"], CL_CASES["bearing_pecmv"], CL_CASES["unicycle_chain"]][seed % 3]
    env = CLSchedulingEnv(**kw)
    _, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        sim = env.sim
        # batched (new) vs per pair (reference): other BLAS calls, so within rtol
        np.testing.assert_allclose(env._pair_gains(), ref_pair_gains(env), rtol=1e-9, atol=0)
        assert env.objective_value() == float(np.sum(agent_objective(sim.P, env.objective)))
        np.testing.assert_array_equal(env._logdets(), agent_objective(sim.P, "logdet"))
        open_ = np.flatnonzero(env.action_masks()[:-1])
        if open_.size:  # batched Jacobians == relative_terms' (batched: within rtol)
            H_i, H_j = sim.relative_jacobians(open_)
            for k, p in enumerate(open_):
                ref_i, ref_j, _ = sim.relative_terms(int(p))
                np.testing.assert_allclose(H_i[k], ref_i, rtol=1e-9, atol=0)
                np.testing.assert_allclose(H_j[k], ref_j, rtol=1e-9, atol=0)
        twin = coop.CLSimulation(sim.problem, sim.fusion)  # the prediction from this state
        twin.x, twin.P, twin.k = sim.x.copy(), sim.P.copy(), sim.k
        if twin.k < sim.problem.config.horizon:
            ref_predict(twin)
            sim_copy = coop.CLSimulation(sim.problem, sim.fusion)
            sim_copy.x, sim_copy.P, sim_copy.k = sim.x.copy(), sim.P.copy(), sim.k
            sim_copy.predict()
            np.testing.assert_array_equal(sim_copy.x, twin.x)
            np.testing.assert_array_equal(sim_copy.P, twin.P)
        _, _, term, _, info = env.step(int(rng.choice(np.flatnonzero(info["action_mask"]))))
        if term:
            _, info = env.reset(seed=seed + 100)


def test_strapdown_helpers_match_the_previous_formulas() -> None:
    rng = np.random.default_rng(0)
    for _ in range(300):
        x = rng.standard_normal(9) * [100, 100, 100, 10, 10, 10, 0.5, 0.5, 3]
        u = rng.standard_normal(6) * [3, 3, 10, 0.1, 0.1, 0.1]
        h = float(rng.uniform(1e-3, 1.0))
        x_new, F, G = lm.propagate_with_jacobians(x, u, h)
        F_ref, G_ref = ref_propagation_jacobians(x, u, h)
        np.testing.assert_array_equal(x_new, ref_propagate(x, u, h))
        np.testing.assert_array_equal(lm.propagate(x, u, h), ref_propagate(x, u, h))
        np.testing.assert_array_equal(F, F_ref)
        np.testing.assert_array_equal(G, G_ref)
        F2, G2 = lm.propagation_jacobians(x, u, h)
        np.testing.assert_array_equal(F2, F_ref)
        np.testing.assert_array_equal(G2, G_ref)
        np.testing.assert_array_equal(lm.euler_to_dcm(x[6:9]), _ref_dcm(x[6:9]))
        np.testing.assert_array_equal(lm.euler_rate_matrix(x[6:9]), _ref_rate_matrix(x[6:9]))
        np.testing.assert_array_equal(
            lm.euler_to_dcm_derivatives(x[6:9]), _ref_dcm_derivatives(x[6:9])
        )


LANDMARK_CONFIGS: list[dict[str, Any]] = [
    {},
    {"horizon": 40, "heading_deg": -0.0},
    {"horizon": 40, "heading_deg": 0.0},
    {"horizon": 30, "legs": ((3.0, 0.0), (2.0, -4.0)), "speed": 80.0, "n_landmarks": 12},
]


@pytest.mark.parametrize("i", range(len(LANDMARK_CONFIGS)))
def test_landmark_flight_cache_matches_a_fresh_flight(i: int) -> None:
    cfg = LandmarkConfig(**LANDMARK_CONFIGS[i])
    for _ in range(2):  # first a miss (or an earlier test's entry), then a hit
        for got, want in zip(landmarks_mod._flight(cfg), ref_flight(cfg), strict=True):
            np.testing.assert_array_equal(got, want)
            assert not got.flags.writeable
    for seed in range(2):
        a = make_landmark_problem(cfg, np.random.default_rng(seed))
        np.testing.assert_array_equal(a.states, ref_flight(cfg)[0])
        np.testing.assert_array_equal(a.F_true, ref_flight(cfg)[2])


def test_landmark_flight_key_tells_signed_zero_apart() -> None:
    a = landmarks_mod._flight_key(LandmarkConfig(heading_deg=0.0))
    b = landmarks_mod._flight_key(LandmarkConfig(heading_deg=-0.0))
    assert a != b


@pytest.mark.parametrize("i", [1, 3])
def test_landmark_episodes_match_the_reference(i: int, monkeypatch: pytest.MonkeyPatch) -> None:
    kw = LANDMARK_CONFIGS[i]
    new = [play(LandmarkSelectionEnv(**kw), s, a) for a in AGENTS for s in range(2)]
    monkeypatch.setattr(landmarks_mod, "_flight", ref_flight)
    ref = [play(LandmarkSelectionEnv(**kw), s, a) for a in AGENTS for s in range(2)]
    assert len(new) == len(ref)
    for got, want in zip(new, ref, strict=True):
        assert_same_episode(got, want)


def _ref_process_noise(G: Any, accel_sigma: float, gyro_sigma: float) -> FloatArray:
    """The previous ``process_noise`` (scale vector built on every call), verbatim."""
    Ga = np.asarray(G, dtype=np.float64)
    scale = np.repeat([float(accel_sigma), float(gyro_sigma)], 3)
    Gs = Ga * scale
    Q = Gs @ Gs.T
    return 0.5 * (Q + Q.T)


@pytest.mark.parametrize(
    "sigmas", [(0.1, 0.01), (0.1, 0.01), (2.0, 3e-4), (0.0, 0.01), (-0.0, 0.01), (0.1, -0.0)]
)
def test_process_noise_cached_scale_is_bit_identical(sigmas: tuple[float, float]) -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        G = rng.standard_normal((9, 6))
        G[:, int(rng.integers(6))] = -0.0  # signed zeros must survive the cached scale
        got, want = lm.process_noise(G, *sigmas), _ref_process_noise(G, *sigmas)
        assert got.tobytes() == want.tobytes()


def test_jacobian_template_is_not_shared_with_callers() -> None:
    """``F`` comes from a cached read-only skeleton: writing into one result must not leak."""
    x, u, h = np.full(9, 0.1), np.full(6, 0.2), 0.05
    F1, _ = lm.propagation_jacobians(x, u, h)
    F1[:] = 7.0  # the caller owns its F
    F2, G2 = lm.propagation_jacobians(x, u, h)
    F_ref, G_ref = ref_propagation_jacobians(x, u, h)
    np.testing.assert_array_equal(F2, F_ref)
    np.testing.assert_array_equal(G2, G_ref)
    assert F2.flags.writeable
