"""Matplotlib rendering: the Renderer modes and one frame of each env's drawing."""

from __future__ import annotations

import warnings

import gymnasium as gym
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import pytest

import selenv.envs  # noqa: F401  (registers the ids)
from selenv.envs.rendering import Renderer, ellipse, ellipse_label, marginal_cov
from selenv.families.clustering.rendering import draw_receiver_clustering
from selenv.families.cooperative.rendering import draw_cl_scheduling
from selenv.families.fim.rendering import draw_fim_selection
from selenv.families.landmarks.rendering import draw_landmark_selection


def first_allowed(info: dict) -> int:
    return int(np.flatnonzero(info["action_mask"])[0])


def check_frame(frame: np.ndarray | None, shape: tuple[int, int] = (480, 640)) -> np.ndarray:
    assert isinstance(frame, np.ndarray)
    assert frame.dtype == np.uint8
    assert frame.shape == (*shape, 3)
    assert np.unique(frame.reshape(-1, 3), axis=0).shape[0] > 10  # not a single colour
    return frame


@pytest.fixture
def renderer():
    r = Renderer("rgb_array", 4)
    yield r
    r.close()


# -- Renderer -------------------------------------------------------------------------------------
def test_rgb_array_is_headless_and_sized():
    before = plt.get_fignums()
    r = Renderer("rgb_array", 4, figsize=(4.0, 3.0), dpi=50)
    frame = r.render(lambda fig: fig.add_subplot().plot([0, 1], [1, 0]))
    check_frame(frame, (150, 200))
    assert plt.get_fignums() == before  # no pyplot figure, no window
    r.close()
    r.close()


def test_render_mode_none_returns_none():
    r = Renderer(None, 4)
    with pytest.warns(UserWarning, match="render_mode=None"):
        assert r.render(lambda fig: fig.add_subplot()) is None
    r.close()
    r.close()


def test_human_mode_under_agg_draws_without_error():
    plt.switch_backend("agg")
    assert matplotlib.get_backend().lower() == "agg"
    drawn = []
    r = Renderer("human", 100)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for y in (1, 2):
            assert r.render(lambda fig, y=y: drawn.append(fig.add_subplot().plot([0, y]))) is None
    assert len(drawn) == 2
    assert len(plt.get_fignums()) == 1  # one window, reused
    r.close()
    assert plt.get_fignums() == []
    r.close()


def test_bad_arguments():
    with pytest.raises(ValueError, match="render_mode"):
        Renderer("ansi", 4)
    with pytest.raises(ValueError, match="fps"):
        Renderer("rgb_array", 0)


# -- helpers --------------------------------------------------------------------------------------
def test_marginal_covariance_and_ellipse():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(5, 5))
    A = B @ B.T + np.eye(5)
    cov = marginal_cov(A, (0, 1))
    np.testing.assert_allclose(cov, np.linalg.inv(A)[:2, :2], rtol=1e-10)
    e = ellipse(np.diag([4.0, 1.0]), (1.0, 2.0), n_sigma=2.0)
    assert (e.width, e.height) == pytest.approx((8.0, 4.0))
    assert abs(np.cos(np.radians(e.angle))) == pytest.approx(1.0)  # major axis along x
    e = ellipse(np.array([[1.0, 0.0], [0.0, 9.0]]), (0.0, 0.0))
    assert (e.width, e.height) == pytest.approx((12.0, 4.0))
    assert abs(np.sin(np.radians(e.angle))) == pytest.approx(1.0)  # major axis along y


def test_ellipse_label_flags_off_scale():
    fig = matplotlib.figure.Figure()
    ax = fig.add_subplot()
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 10)
    small = ellipse(np.eye(2), (5, 5))
    big = ellipse(100 * np.eye(2), (5, 5))
    assert "exceeds view" not in ellipse_label("2σ", [small], ax)
    assert "exceeds view" in ellipse_label("2σ", [small, big], ax)
    assert "20 × 20 m" in ellipse_label("2σ", [big], ax)


# -- one frame per env ----------------------------------------------------------------------------
@pytest.mark.parametrize("preset", ["example1", "example2", "example3", "example2_moving"])
def test_fim_selection_frames(renderer, preset):
    env = gym.make("selenv/FIMSelection-v1", preset=preset).unwrapped
    _, info = env.reset(seed=0)

    def frame() -> np.ndarray:
        s = env.state
        info_matrix = s.Q0 + np.einsum("kmi,kmj->ij", s.G[s.selected], s.G[s.selected])
        np.testing.assert_allclose(info_matrix, s.information, rtol=1e-10, atol=1e-12)
        draw = lambda fig: draw_fim_selection(fig, env.problem, s.selected, s.information, "FIM")  # noqa: E731
        return check_frame(renderer.render(draw))

    f0 = frame()
    for _ in range(3):
        _, _, _, _, info = env.step(first_allowed(info))
    f1 = frame()
    assert not np.array_equal(f0, f1)


def test_landmark_selection_frames(renderer):
    env = gym.make("selenv/LandmarkSelection-v1").unwrapped
    _, info = env.reset(seed=0)

    def frame() -> np.ndarray:
        ekf = env.ekf
        draw = lambda fig: draw_landmark_selection(  # noqa: E731
            fig, env.problem, ekf.x, ekf.P, ekf.k, env.picks, env.last_selection, "Landmarks"
        )
        return check_frame(renderer.render(draw))

    f0 = frame()
    _, _, _, _, info = env.step(first_allowed(info))  # one pick, no update yet
    f1 = frame()
    assert not np.array_equal(f0, f1)
    for _ in range(3):  # two filter updates
        _, _, _, _, info = env.step(first_allowed(info))
    assert env.last_selection is not None
    f2 = frame()
    assert not np.array_equal(f1, f2)


@pytest.mark.parametrize("model", ["ins", "unicycle"])
def test_cl_scheduling_frames(renderer, model):
    # budget 2: after one pick the filter step is still open, so the link is drawn
    env = gym.make("selenv/CLScheduling-v1", model=model, budget=2).unwrapped
    _, info = env.reset(seed=0)

    def frame() -> np.ndarray:
        processed = np.flatnonzero(info["processed"]).tolist()
        draw = lambda fig: draw_cl_scheduling(fig, env.sim, env.pairs, processed, "CL")  # noqa: E731
        return check_frame(renderer.render(draw))

    f0 = frame()
    _, _, _, _, info = env.step(first_allowed(info))  # one pair processed, step still open
    assert info["processed"].any()
    f1 = frame()
    assert not np.array_equal(f0, f1)
    for _ in range(4):
        _, _, _, _, info = env.step(first_allowed(info))
    f2 = frame()
    assert not np.array_equal(f1, f2)


def test_receiver_clustering_frames(renderer):
    env = gym.make("selenv/ReceiverClustering-v1").unwrapped
    _, info = env.reset(seed=0)

    def frame() -> np.ndarray:
        bank = env.bank
        draw = lambda fig: draw_receiver_clustering(  # noqa: E731
            fig, bank.labels, env.problem.sigma, info["objective"], info["J_G"], info["J_C"],
            info["J_L"], bank.k, env.max_size, "Clustering",
        )  # fmt: skip
        return check_frame(renderer.render(draw))

    f0 = frame()
    for _ in range(3):  # same clustering: the filters converge, the cost terms change
        _, _, _, _, info = env.step(np.asarray(env.bank.labels))
    f1 = frame()
    assert not np.array_equal(f0, f1)
    singletons = np.arange(env.n)  # a different partition recolours the receivers
    _, _, _, _, info = env.step(singletons)
    f2 = frame()
    assert not np.array_equal(f1, f2)
