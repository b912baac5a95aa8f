"""The fast paths of FIMSelection equal the reference math they replace.

* resets: the closed-form times and whitened pools (``_closed_form_pools``, in chunks) against
  the models-based ``_geometry``, and the lazily computed rest of the geometry;
* steps: the closed-form inverse factor of the rank-``m`` pick update against a Cholesky
  factor, the gram / gains of :class:`FIMBatchState` against ``Z Z^T`` and
  ``block_logdet_gains``, and sub-envs that do not pick keeping their values bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from selenv.core.information import block_logdet_gains
from selenv.families.fim import scenario as sc
from selenv.families.fim.batched import FIMBatchState, _inverse_factor

CONFIGS: list[dict[str, Any]] = [
    {"preset": "example2_moving"},
    {"preset": "example1"},
    {"preset": "example3_moving"},
    {"preset": "example2", "sensors": ("camera", "toa", "doppler"), "n_agents": 3},
    {"preset": "example2_moving", "sensors": ("toa",)},
    {"preset": "example2_moving", "sensors": ("doppler", "toa"), "n_agents": 8},
    {"preset": "example3", "focal_px": 300.0, "sweep_deg": -700.0, "altitude_m": 1.0},
]


def _draws(const: sc.ProblemConstants, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    drawn = [sc._draw_geometry(const, np.random.default_rng(i)) for i in range(K)]
    return (
        np.array([d[0] for d in drawn]),
        np.stack([d[1] for d in drawn]),
        np.stack([d[2] for d in drawn]),
    )


@pytest.mark.parametrize("kwargs", CONFIGS)
def test_closed_form_pools_match_the_models(kwargs: dict[str, Any]) -> None:
    const = sc.problem_constants(sc.config_from(n_candidates=13, randomize=True, **kwargs))
    K = 2 * sc._CHUNK + 3  # chunks of the closed forms, one partial
    args = _draws(const, K)
    ref, fast = sc._geometry(const, *args), sc._chunked_geometry(const, args)
    np.testing.assert_array_equal(fast["times"], ref["times"])
    scale = np.abs(ref["G"]).max(axis=-1, keepdims=True)  # per row: zeros stay exact zeros
    assert np.all(np.abs(fast["G"] - ref["G"]) <= 1e-12 * scale)
    if const.camera.any():
        theta = np.stack([sc._draw_truth(const, np.random.default_rng(i)) for i in range(K)])
        np.testing.assert_allclose(
            sc._camera_depths(const, theta, fast), sc._camera_depths(const, theta, ref),
            rtol=1e-12, atol=1e-9,
        )  # fmt: skip


def test_rest_of_the_geometry_is_computed_on_demand_as_before() -> None:
    cfg = sc.config_from("example3_moving", n_candidates=11, randomize=True)
    rngs = [np.random.default_rng(i) for i in range(5)]
    batch = sc.make_problems(cfg, rngs)
    assert batch.draws is not None and not batch.geometry  # nothing computed yet
    ref = sc._geometry(batch.constants, *batch.draws)
    for key in ("positions", "velocities", "camera_rotation", "H"):
        np.testing.assert_array_equal(getattr(batch, key), ref[key])
        assert not getattr(batch, key).flags.writeable
    P = batch.problem(2)
    np.testing.assert_array_equal(P.H, P.measurement_jacobian(P.theta_prior_mean))
    fixed = sc.make_problems(sc.config_from("example1", n_candidates=11), rngs)
    assert fixed.draws is None and set(fixed.geometry) >= {"H", "positions"}


@pytest.mark.parametrize(("m", "d"), [(1, 3), (2, 7), (2, 12), (3, 5)])
def test_inverse_factor_is_the_inverse_cholesky_factor(m: int, d: int) -> None:
    rng = np.random.default_rng(m * 100 + d)
    X = rng.normal(size=(6, m, d)) * rng.uniform(0.01, 30.0, size=(6, 1, 1))
    X[0, -1] = 0.0  # a zero-padded row: identity factor
    Cinv, logdet = _inverse_factor(X)
    M = np.eye(d) + np.swapaxes(X, 1, 2) @ X
    C = np.linalg.cholesky(M)
    np.testing.assert_allclose(Cinv @ C, np.broadcast_to(np.eye(d), C.shape), atol=1e-12)
    assert np.all(np.triu(Cinv, 1) == 0.0)
    np.testing.assert_allclose(logdet, np.linalg.slogdet(M)[1], rtol=1e-13)
    with pytest.raises(ValueError, match="not finite"):
        _inverse_factor(np.full((1, m, d), np.nan))


def _state(B: int) -> tuple[FIMBatchState, np.ndarray]:
    cfg = sc.config_from("example2_moving", n_candidates=20, randomize=True)
    batch = sc.make_problems(cfg, [np.random.default_rng(i) for i in range(B)])
    core = FIMBatchState(B, batch.constants.Q0, batch.constants.shape)
    core.start(np.arange(B), batch.G)
    return core, np.asarray(batch.G)


def test_gram_and_gains_after_picks() -> None:
    core, _ = _state(5)
    rng = np.random.default_rng(0)
    for _ in range(4):
        picks = np.array([rng.choice(np.flatnonzero(~s)) for s in core.selected])
        core.add(np.arange(5), picks)
    assert core.S is not None
    S_ref = core.Z @ np.swapaxes(core.Z, 2, 3)
    np.testing.assert_allclose(core.S, S_ref, rtol=1e-12, atol=1e-12 * np.abs(S_ref).max())
    gains = block_logdet_gains(np.ascontiguousarray(core.S).reshape(-1, core.m, core.m))
    np.testing.assert_allclose(core.gains, gains.reshape(5, -1), rtol=1e-13)
    Linv = core.Linv
    np.testing.assert_allclose(core.Z, core.G @ np.swapaxes(Linv, 1, 2)[:, None], rtol=1e-12,
                               atol=1e-13 * np.abs(core.Z).max())  # fmt: skip


def test_sub_envs_that_do_not_pick_keep_their_values_bit_for_bit() -> None:
    core, G = _state(6)
    core.add(np.arange(6), np.arange(6))
    keep = {name: np.array(getattr(core, name)) for name in ("Z", "S", "gains", "Linv")}
    core.add(np.array([0, 2, 3, 5]), np.array([7, 8, 9, 10]))  # every sub-env refreshed
    core.add(np.array([2]), np.array([11]))  # only sub-env 2 (gathered)
    for name, before in keep.items():
        for b in (1, 4):
            np.testing.assert_array_equal(np.asarray(getattr(core, name))[b], before[b])
    other, _ = _state(6)  # the same picks in one sub-env at a time give the same state
    other.add(np.arange(6), np.arange(6))
    for b, j in ((0, 7), (2, 8), (3, 9), (5, 10), (2, 11)):
        other.add(np.array([b]), np.array([j]))
    for name in ("Z", "S", "gains", "Linv", "objective"):
        np.testing.assert_allclose(getattr(other, name), getattr(core, name), rtol=1e-12,
                                   atol=1e-14)  # fmt: skip


def _reference_truths(cfg: sc.FIMScenarioConfig, seeds: range) -> np.ndarray:
    """The truths of the scalar path: models' geometry, ``_in_front`` on every draw."""
    const = sc.problem_constants(cfg)
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        rot, scales, offsets = sc._draw_geometry(const, rng)
        geo = sc._geometry(const, np.array([rot]), scales[None], offsets[None])
        one = {key: val[0] for key, val in geo.items()}
        theta = sc._draw_truth(const, rng)
        while not sc._in_front(const, theta, one):
            theta = sc._draw_truth(const, rng)
        out.append(theta[const.free])
    return np.stack(out)


@pytest.mark.parametrize("preset", ["example2_moving", "example3_moving"])
def test_truths_behind_a_camera_are_redrawn_as_the_scalar_check_does(preset: str) -> None:
    cfg = sc.config_from(preset, n_candidates=30, randomize=True)
    seeds = range(600)  # about 1 in 100 first truths falls behind a camera
    batch = sc.make_problems(cfg, [np.random.default_rng(s) for s in seeds])
    ref = _reference_truths(cfg, seeds)
    const = sc.problem_constants(cfg)
    first = np.stack([sc._draw_truth(const, _after_geometry(const, s)) for s in seeds])
    assert (first[:, const.free] != ref).any(axis=1).sum() >= 2  # redraws happened
    np.testing.assert_array_equal(batch.theta_true, ref)


def _after_geometry(const: sc.ProblemConstants, seed: int) -> np.random.Generator:
    rng = np.random.default_rng(seed)
    sc._draw_geometry(const, rng)
    return rng
