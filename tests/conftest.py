"""Shared fixtures: random SPD matrices and candidate pools from explicit generators."""

from __future__ import annotations

import numpy as np
import pytest


def random_spd(rng: np.random.Generator, d: int, scale: float = 1.0) -> np.ndarray:
    A = rng.normal(size=(d, d))
    return scale * (A @ A.T / d + 0.5 * np.eye(d))


def random_pool(
    rng: np.random.Generator, N: int, d: int, m: int = 1, pad: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """``H (N, m, d)``, ``R (N, m, m)``; with ``pad`` every other candidate has one zero row."""
    H = rng.normal(size=(N, m, d))
    R = np.stack([random_spd(rng, m, 0.5) for _ in range(N)])
    if pad and m > 1:
        H[::2, 1:, :] = 0.0
        R[::2, 1:, :] = 0.0
        R[::2, :, 1:] = 0.0
        for k in range(0, N, 2):
            R[k, 1:, 1:] = np.eye(m - 1)
    return H, R


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
