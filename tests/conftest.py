"""Shared fixtures: random SPD matrices, candidate pools, and the reproduction scripts."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(name: str) -> ModuleType:
    """Import ``scripts/<name>.py`` as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load scripts/{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses and pickling look the module up by name
    spec.loader.exec_module(module)
    return module


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
