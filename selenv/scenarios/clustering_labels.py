"""Clustering label vectors: validation, canonical form, sizes, random feasible clusterings.

A clustering of ``n`` receivers is an integer label vector ``(n,)``; label vectors inducing the
same partition are the same clustering (:func:`canonical_labels` maps them to equal arrays).
Problem 1 of Greiff et al. (2022) reduces to a cap on the cluster size. Shared by the scenario,
the envs and the genetic algorithm.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from selenv.scenarios.validation import ArgumentTypeError, check_generator, describe

IntArray = NDArray[np.int64]

__all__ = [
    "IntArray",
    "as_labels",
    "canonical_labels",
    "check_int",
    "cluster_sizes",
    "is_feasible",
    "random_feasible_clustering",
]


def check_int(value: object, name: str, low: int, high: float = math.inf) -> int:
    """``value`` as an int in ``[low, high]``; an error naming ``name`` otherwise.

    Raises:
        ArgumentTypeError: not an int (a ``TypeError`` and a ``ValueError``; floats such as
            ``2.0`` and bools are refused, never truncated).
        ValueError: outside ``[low, high]``.
    """
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        raise ArgumentTypeError(f"{name} must be an int, got {describe(value)}")
    if value < low:
        raise ValueError(f"{name} must be >= {low}, got {value}")
    if value > high:
        raise ValueError(f"{name} must be <= {high:g}, got {value}")
    return int(value)


def as_labels(labels: ArrayLike, name: str) -> IntArray:
    """Validate a label vector; return a fresh int64 copy of shape ``(n,)``.

    Raises:
        ValueError: naming ``name``, unless a non-empty 1-D array of finite integers >= 0
            (integral floats are accepted).
    """
    try:
        arr = np.asarray(labels)
    except ValueError as exc:  # ragged nested sequences
        raise ValueError(f"{name} must be a 1-D label array, got {describe(labels)}") from exc
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D label array, got shape {arr.shape}")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite, got NaN or inf")
        if not np.all(arr == np.round(arr)):
            raise ValueError(f"{name} must hold integer labels, got non-integral values")
    elif arr.dtype.kind not in "iu":
        raise ValueError(f"{name} must be an integer array, got dtype {arr.dtype}")
    out = arr.astype(np.int64)
    if np.any(out < 0):
        raise ValueError(f"{name} must be >= 0, got min {int(out.min())}")
    return out


def _fits(labels: IntArray, max_size: int) -> bool:
    return bool(np.bincount(labels).max() <= max_size)


def canonical_labels(labels: ArrayLike) -> IntArray:
    """Relabel ``labels`` ``(n,)`` by order of first appearance: ``[3, 3, 1, 0] -> [0, 0, 1, 2]``.

    Equal partitions give equal ``(n,)`` int64 arrays. Raises ``ValueError`` naming ``labels``
    unless it is a non-empty 1-D array of finite integers >= 0.
    """
    x = as_labels(labels, "labels")
    _, first, inverse = np.unique(x, return_index=True, return_inverse=True)
    rank = np.empty(first.size, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(first.size)
    return rank[inverse.reshape(-1)]


def cluster_sizes(labels: ArrayLike) -> IntArray:
    """Members per label of ``labels`` ``(n,)``: ``(max(labels) + 1,)``, 0 for unused labels."""
    return np.bincount(as_labels(labels, "labels")).astype(np.int64)


def is_feasible(labels: ArrayLike, max_size: int) -> bool:
    """Whether every cluster of ``labels`` ``(n,)`` has at most ``max_size`` members."""
    return _fits(as_labels(labels, "labels"), check_int(max_size, "max_size", 1))


def random_feasible_clustering(
    n: int, max_size: int, rng: np.random.Generator, n_clusters: int | None = None
) -> IntArray:
    """Uniformly random permutation of ``n`` agents cut into ``n_clusters`` near-equal groups.

    ``n_clusters`` defaults to ``ceil(n / max_size)``. Returns ``(n,)`` canonical labels whose
    group sizes differ by at most one. Raises ``ValueError`` if ``n_clusters * max_size < n``
    or ``n_clusters > n``.
    """
    n = check_int(n, "n", 1)
    max_size = check_int(max_size, "max_size", 1)
    check_generator(rng)
    k = math.ceil(n / max_size) if n_clusters is None else check_int(n_clusters, "n_clusters", 1)
    if k > n:
        raise ValueError(f"n_clusters must be <= n={n}, got {k}")
    if k * max_size < n:
        raise ValueError(f"n_clusters={k} clusters of max_size={max_size} cannot hold n={n}")
    labels = np.empty(n, dtype=np.int64)
    labels[rng.permutation(n)] = np.arange(n) % k
    return canonical_labels(labels)
