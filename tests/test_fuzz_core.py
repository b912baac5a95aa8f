"""Property-based fuzz suite of the numerical API.

Covered: fusion (``covariance_intersection``, ``dmv_update``, ``pecmv_update``), Kalman
(``kf_predict``, ``kf_update``, ``ekf_update``, ``information_update``), the ``linalg``
helpers, the FIM solvers (``greedy``, ``swap``, ``brute_force``, ``vns``) and the clustering GA
(``GeneticClustering``, ``GAConfig``, the Table I operators, ``draw_rank``). Every function is
described once in an :class:`Api` row (a strategy of valid keyword arguments, the kind of each
argument, a check of valid results); three properties run over every row:

(a) ``test_invalid_input_is_rejected_naming_it``: one argument is replaced by an invalid value
    of its kind (wrong type, shape or ndim, NaN/inf, asymmetric / indefinite / singular,
    out of range, fractional int, ...). The call must raise ``TypeError`` or ``ValueError``
    whose message names that argument; any other exception, a ``RuntimeWarning`` (turned into
    an error) or a normal return fails.
(b) ``test_valid_input_gives_valid_output``: valid arguments must not raise, and the result
    must be finite and satisfy the function's invariants (e.g. a fused covariance is symmetric
    positive definite and no larger than the prior in log det).
(c) both of the above also check that the numpy arguments are bit-identical after the call.

``test_extreme_values_are_rejected_or_finite`` scales one argument to 1e+-200 / 1e+-300: a
clean ``ValueError`` / ``TypeError`` naming an argument, or a valid result (b), is accepted.

Profiles (``tests/conftest.py``): ``fuzz-ci`` by default, ``SELENV_FUZZ=long`` for many more
examples. Valid arrays are drawn from one numpy generator seeded by Hypothesis, so every
example is reproducible from its seed.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from conftest import fuzz_settings
from hypothesis import given, note
from hypothesis import strategies as st

from selenv.agents import fim_solvers
from selenv.agents.vns import vns
from selenv.core import fusion, kalman, linalg
from selenv.core.information import as_candidates, logdet_objective
from selenv.families.clustering import ga as ga

pytestmark = pytest.mark.fuzz

# ============================================================================ strategies

SEEDS = st.integers(0, 2**32 - 1)
SCALES = st.integers(-3, 3).map(lambda e: 10.0**e)  # valid magnitudes 1e-3 .. 1e3
EXTREMES = st.sampled_from([1e-300, 1e-200, 1e200, 1e300])


def spd(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    """A well-conditioned SPD matrix (eigenvalues in ``scale * [0.5, ~n + 3]``)."""
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + 0.5 * np.eye(n))


def contraction(rng: np.random.Generator, r: int, c: int, norm: float) -> np.ndarray:
    """An ``(r, c)`` matrix with spectral norm ``norm``."""
    C = rng.normal(size=(r, c))
    return C * (norm / max(float(np.linalg.norm(C, 2)), 1e-12))


@dataclass(frozen=True)
class Linear:
    """``h(x) = H x`` (or the constant Jacobian ``H``) with a readable repr for Hypothesis."""

    H: np.ndarray
    jacobian: bool = False

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.H.copy() if self.jacobian else self.H @ x

    def __repr__(self) -> str:
        return f"Linear(H.shape={self.H.shape}, jacobian={self.jacobian})"


@dataclass(frozen=True)
class Returns:
    """A callable returning a fixed (bad) value, for the ``h`` / ``H_jac`` / ``evaluate`` slots."""

    value: Any

    def __call__(self, *args: Any) -> Any:
        return self.value

    def __repr__(self) -> str:
        return f"Returns({self.value!r})"


# ------------------------------------------------------------ invalid values, by argument kind
# Each entry maps a label to ``f(valid_value, ctx) -> bad value``; ``ctx`` holds sizes (N, K, ...).
# Shape corruptions are accepted when the message names any argument of the shape group of the
# call (a wrong ``P_i`` size is reported as a mismatch by ``H_i``); all others must name the
# argument itself.


def _poke(v: np.ndarray, bad: float) -> np.ndarray:
    out = np.array(v, dtype=float, copy=True)
    out.flat[out.size // 2] = bad
    return out


class Opaque:
    """An arbitrary non-numeric object (stable repr, so that example labels are reproducible)."""

    def __repr__(self) -> str:
        return "Opaque()"


OPAQUE = Opaque()
#: not an array at all
NOT_ARRAY: dict[str, Callable[[Any, dict], Any]] = {
    "str": lambda v, c: "abc",
    "None": lambda v, c: None,
    "object": lambda v, c: OPAQUE,
    "object array": lambda v, c: np.full(np.shape(v), OPAQUE, dtype=object),
    "str array": lambda v, c: np.full(np.shape(v), "1.0"),
    "ragged list": lambda v, c: [[1.0, 2.0], [3.0]],
}
#: arrays of a dtype that is not real numbers
NOT_REAL: dict[str, Callable[[Any, dict], Any]] = {
    "complex array": lambda v, c: np.asarray(v, complex) + 1j,
    "bool array": lambda v, c: np.ones(np.shape(v), bool),
}
TYPE_BAD = {**NOT_ARRAY, **NOT_REAL}
VALUE_BAD: dict[str, Callable[[Any, dict], Any]] = {
    "NaN": lambda v, c: _poke(v, np.nan),
    "+inf": lambda v, c: _poke(v, np.inf),
    "-inf": lambda v, c: _poke(v, -np.inf),
}
SHAPE_BAD: dict[str, Callable[[Any, dict], Any]] = {
    "trailing axis": lambda v, c: np.stack([v, v], axis=-1),  # never a valid batch shape
    "scalar": lambda v, c: np.float64(1.0),
    "grown": lambda v, c: np.pad(np.asarray(v, float), [(0, 1)] * np.ndim(v), constant_values=1),
    "empty": lambda v, c: np.zeros((0,) * max(np.ndim(v), 1)),
}


def _asymmetric(v: np.ndarray, c: dict) -> np.ndarray:
    out = np.array(v, dtype=float, copy=True)
    out[..., 0, -1] += 0.5 * float(np.max(np.abs(v))) + 1.0
    return out


def _indefinite(v: np.ndarray, c: dict) -> np.ndarray:
    top = float(np.max(np.linalg.eigvalsh(v)))
    return v - (top + 1.0) * np.eye(v.shape[-1])


def spd_bad(v: np.ndarray) -> dict[str, Callable[[Any, dict], Any]]:
    """Symmetric-positive-definite violations applicable to ``v`` (no asymmetric 1 x 1)."""
    out: dict[str, Callable[[Any, dict], Any]] = {
        "indefinite": _indefinite,
        "non-square": lambda v, c: np.asarray(v)[..., :-1] if v.shape[-1] > 1 else np.ones((1, 2)),
    }
    if v.shape[-1] > 1:
        out["asymmetric"] = _asymmetric
    return out


SINGULAR: dict[str, Callable[[Any, dict], Any]] = {"singular": lambda v, c: np.zeros_like(v)}
VARIANCE_BAD: dict[str, Callable[[Any, dict], Any]] = {
    "negative": lambda v, c: -np.asarray(v),
    "zero": lambda v, c: np.zeros_like(v),
}


def _ints(bad: list[Any]) -> dict[str, Callable[[Any, dict], Any]]:
    return {f"{b!r}": (lambda v, c, b=b: b) for b in bad}


def _without(bad: dict[str, Any], *labels: str) -> dict[str, Any]:
    return {k: f for k, f in bad.items() if k not in labels}


#: what is invalid for each kind of argument (``ctx`` supplies the sizes of the call)
KIND_BAD: dict[str, Callable[[Any, dict], dict[str, Callable[[Any, dict], Any]]]] = {
    "spd": lambda v, c: {**TYPE_BAD, **VALUE_BAD, **SHAPE_BAD, **spd_bad(v), **SINGULAR},
    "psd": lambda v, c: {**TYPE_BAD, **VALUE_BAD, **SHAPE_BAD, **spd_bad(v)},
    "array": lambda v, c: {**TYPE_BAD, **VALUE_BAD, **SHAPE_BAD},
    "optional array": lambda v, c: _without({**TYPE_BAD, **VALUE_BAD, **SHAPE_BAD}, "None"),
    # a standalone SPD matrix of any size (cholesky, logdet): bigger or empty is still valid
    "any spd": lambda v, c: {
        **TYPE_BAD,
        **VALUE_BAD,
        **_without(SHAPE_BAD, "grown", "empty"),
        **spd_bad(v),
        **SINGULAR,
    },
    "rhs": lambda v, c: {**TYPE_BAD, **VALUE_BAD, **_without(SHAPE_BAD, "trailing axis")},
    "noise": lambda v, c: (  # R: SPD blocks, or the variances of scalar candidates
        {**TYPE_BAD, **VALUE_BAD, **SHAPE_BAD, **spd_bad(v), **SINGULAR}
        if np.ndim(v) >= 2
        else {**TYPE_BAD, **VALUE_BAD, **_without(SHAPE_BAD, "scalar"), **VARIANCE_BAD}
    ),
    "lower": lambda v, c: {
        **TYPE_BAD,
        **VALUE_BAD,
        **SINGULAR,
        "scalar": SHAPE_BAD["scalar"],
        "non-square": lambda v, c: np.ones((2, 3)),
        "1-D": lambda v, c: np.asarray(v)[0],
    },
    "any array": lambda v, c: TYPE_BAD,  # every shape and value is fine, the type is not
    "finite array": lambda v, c: {**NOT_ARRAY, **VALUE_BAD},  # bool / complex are finite
    "shaped array": lambda v, c: {**_without(NOT_ARRAY, "object array", "str array"), **SHAPE_BAD},
    "square": lambda v, c: {
        **TYPE_BAD,
        "1-D": lambda v, c: np.asarray(v)[0],
        "non-square": lambda v, c: np.ones((2, 3)),
        "scalar": lambda v, c: np.float64(1.0),
    },
    "contraction": lambda v, c: {
        **_without(TYPE_BAD, "None"),
        **VALUE_BAD,
        **SHAPE_BAD,
        "norm 2": lambda v, c: contraction(np.random.default_rng(0), *v.shape, 2.0),
    },
    "method": lambda v, c: _ints(["no-such-method", None, 1, ["optimal"], "OPTIMAL", b"fast"]),
    "unit": lambda v, c: _ints(
        [math.nan, math.inf, -0.5, 1.5, "0.5", True, [0.5], np.array([0.5, 0.5]), 0.5 + 0j]
    ),
    "budget": lambda v, c: _ints(
        [-1, c["N"] + 1, 2.5, 1.0, np.float64(1.0), True, "1", None, [1], 10**30]
    ),
    "count0": lambda v, c: _ints([-1, 2.5, 1.0, True, "3", None, [3]]),
    "count1": lambda v, c: _ints([0, -1, 2.5, 1.0, True, "3", None, [3]]),
    "optional count1": lambda v, c: _ints([0, -1, 2.5, 1.0, True, "3", [3]]),  # None is valid
    "l_max": lambda v, c: _ints([0, -1, 1.5, True, "1", c["widest"] + 1]),
    "m_l": lambda v, c: _ints([(), (0,), (2.5,), "ab", [-1], (10, None), 7.5]),
    "indices": lambda v, c: _ints(  # VNS initial: K distinct ints in [0, N)
        [[0] * (c["K"] + 1), "ab", 2.5]
        + ([[*range(c["K"] - 1), c["N"]], [-1] * c["K"], [0.0] * c["K"]] if c["K"] else [])
        + ([[True] * c["K"], [[0]] * c["K"]] if c["K"] else [])
    ),
    "rng": lambda v, c: _ints(["seed", 2.5, OPAQUE, [1.5]]),
    "flag": lambda v, c: _ints(["yes", 2.5, None]),
    "callable": lambda v, c: {
        "None": lambda v, c: None,
        "str": lambda v, c: "h",
        "wrong shape": lambda v, c: Returns(np.zeros(7)),
        "NaN": lambda v, c: Returns(np.full(np.shape(v(c["x"])), np.nan)),
        "strings": lambda v, c: Returns("abc"),
    },
}
SHAPE_LABELS = {*SHAPE_BAD, "ragged list"}
ARRAY_KINDS = (
    "spd",
    "psd",
    "array",
    "optional array",
    "noise",
    "lower",
    "contraction",
    "any spd",
    "rhs",
)


@dataclass(frozen=True)
class Api:
    """One function under test.

    Attributes:
        fn: the function (called with keyword arguments).
        valid: strategy of ``(kwargs, ctx)``: valid keyword arguments and sizes.
        kinds: the kind of each argument that may be corrupted (see ``KIND_BAD``).
        check: ``check(result, kwargs)`` asserts the invariants of a valid result.
        aliases: extra words an error message may use to name an argument.
        extreme: arguments that ``test_extreme_values_are_rejected_or_finite`` scales.
    """

    fn: Callable[..., Any]
    valid: st.SearchStrategy[tuple[dict[str, Any], dict[str, Any]]]
    kinds: dict[str, str]
    check: Callable[[Any, dict[str, Any]], None]
    aliases: dict[str, str] = field(default_factory=dict)
    extreme: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return self.fn.__name__


# ============================================================================ result checks


def _finite(*arrays: Any) -> None:
    for a in arrays:
        assert np.all(np.isfinite(np.asarray(a, dtype=float))), f"non-finite output {a!r}"


def _sym_pd(P: np.ndarray, *, semidefinite: bool = False) -> None:
    _finite(P)
    scale = max(float(np.max(np.abs(P))), 1e-300)
    assert np.allclose(P, np.swapaxes(P, -1, -2), rtol=0, atol=1e-9 * scale), "not symmetric"
    low = float(np.min(np.linalg.eigvalsh(P)))
    assert low >= -1e-9 * scale if semidefinite else low > 0, f"smallest eigenvalue {low:g}"


def _logdet(P: np.ndarray) -> float:
    sign, ld = np.linalg.slogdet(P)
    assert sign > 0
    return float(ld)


def _close(a: float, b: float, tol: float = 1e-6) -> None:
    assert abs(a - b) <= tol * max(1.0, abs(a), abs(b)), f"{a!r} != {b!r}"


# ============================================================================ fusion


@st.composite
def ci_args(draw: st.DrawFn) -> tuple[dict, dict]:
    n = draw(st.integers(1, 4))
    rng = np.random.default_rng(draw(SEEDS))
    kw = {
        "a": rng.normal(size=n),
        "A": spd(rng, n, draw(SCALES)),
        "b": rng.normal(size=n),
        "B": spd(rng, n, draw(SCALES)),
        "method": draw(st.sampled_from(fusion.CI_METHODS)),
    }
    return kw, {"n": n}


def check_ci(res: fusion.CIResult, kw: dict) -> None:
    n = kw["A"].shape[0]
    assert res.x.shape == (n,) and res.P.shape == (n, n)
    _finite(res.x, res.log_det)
    _sym_pd(res.P)
    assert 0.0 <= res.omega <= 1.0
    _close(res.log_det, _logdet(res.P))
    if kw["method"] == "optimal":  # argmin of log det P(w): no worse than either input
        _close(min(res.log_det, min(_logdet(kw["A"]), _logdet(kw["B"]))), res.log_det)


@st.composite
def pair_args(draw: st.DrawFn, method: str) -> tuple[dict, dict]:
    n_i, n_j = draw(st.integers(1, 4)), draw(st.integers(1, 4))
    m = draw(st.integers(1, min(n_i, n_j)))  # DMV: n_i >= m and rank H_j = m
    rng = np.random.default_rng(draw(SEEDS))
    kw: dict[str, Any] = {
        "P_i": spd(rng, n_i, draw(SCALES)),
        "P_j": spd(rng, n_j, draw(SCALES)),
        "H_i": rng.normal(size=(m, n_i)),
        "H_j": rng.normal(size=(m, n_j)),
        "R": spd(rng, m, draw(SCALES)),
    }
    if draw(st.booleans()):
        kw["residual"] = rng.normal(size=m)
        if draw(st.booleans()):
            kw["x_i"] = rng.normal(size=n_i)
    if method == "dmv" and draw(st.booleans()):
        kw["omega"] = draw(st.floats(0.0 if n_i == m else 1e-3, 1.0))
    if method == "pecmv":
        kw["method"] = draw(st.sampled_from(["auto", "fast"] + (["closed_form"] if m == 1 else [])))
        if draw(st.booleans()):
            kw["C"] = contraction(rng, n_i, n_j, draw(st.floats(0.0, 0.9)))
    return kw, {"n_i": n_i, "n_j": n_j, "m": m}


def _check_pair_result(res: Any, kw: dict) -> None:
    n_i, m = kw["P_i"].shape[0], kw["H_i"].shape[0]
    assert res.P.shape == (n_i, n_i) and res.K.shape == (n_i, m)
    _finite(res.K, res.log_det)
    if "residual" in kw:
        assert res.dx is not None and res.dx.shape == (n_i,)
        _finite(res.dx)
    if "x_i" in kw:
        assert res.x is not None
        _finite(res.x)


def check_dmv(res: fusion.DMVResult, kw: dict) -> None:
    _check_pair_result(res, kw)
    _sym_pd(res.P)
    assert 0.0 <= res.omega <= 1.0 and res.updated == (res.omega < 1.0)
    _close(res.log_det, _logdet(res.P))
    if "omega" not in kw:  # the optimum of eq. (6) is no worse than no update (w = 1)
        _close(min(res.log_det, _logdet(kw["P_i"])), res.log_det)


def check_pecmv(res: fusion.PECMVResult, kw: dict) -> None:
    _check_pair_result(res, kw)
    _sym_pd(res.P, semidefinite=True)
    _finite(res.X, res.C)
    assert float(np.linalg.norm(res.C, 2)) <= 1.0 + 1e-6
    if "C" not in kw:  # P+ = P_i - U S^-1 U^T <= P_i
        gap = np.linalg.eigvalsh(kw["P_i"] - res.P)
        assert gap.min() >= -1e-8 * float(np.max(np.abs(kw["P_i"])))


PAIR_KINDS = {
    "P_i": "spd",
    "P_j": "spd",
    "H_i": "array",
    "H_j": "array",
    "R": "spd",
    "x_i": "optional array",
    "residual": "optional array",
}
PAIR_ALIASES = {"H_j": r"H_j P_j H_j\^T", "H_i": r"H_i\^T"}

FUSION_APIS = [
    Api(
        fusion.covariance_intersection,
        ci_args(),
        {"a": "array", "A": "spd", "b": "array", "B": "spd", "method": "method"},
        check_ci,
        extreme=("A", "B", "a"),
    ),
    Api(
        fusion.dmv_update,
        pair_args("dmv"),
        {**PAIR_KINDS, "omega": "unit"},
        check_dmv,
        PAIR_ALIASES,
        extreme=("P_i", "P_j", "R", "H_i"),
    ),
    Api(
        fusion.pecmv_update,
        pair_args("pecmv"),
        {**PAIR_KINDS, "method": "method", "C": "contraction"},
        check_pecmv,
        PAIR_ALIASES,
        extreme=("P_i", "P_j", "R", "H_j"),
    ),
]

# ============================================================================ Kalman


@st.composite
def kalman_args(draw: st.DrawFn, which: str) -> tuple[dict, dict]:
    n, m = draw(st.integers(1, 4)), draw(st.integers(1, 3))
    B = None if which == "ekf" else draw(st.sampled_from([None, 1, 3]))
    rng = np.random.default_rng(draw(SEEDS))
    lead = () if B is None else (B,)

    def stack(make: Callable[[], np.ndarray], shared_ok: bool = True) -> np.ndarray:
        if B is None or (shared_ok and draw(st.booleans())):
            return make()
        return np.stack([make() for _ in range(B)])

    x = rng.normal(size=(*lead, n))
    P = stack(lambda: spd(rng, n, draw(SCALES)), shared_ok=False)
    ctx = {"n": n, "m": m, "B": B, "x": x}
    if which == "predict":
        Q = stack(lambda: spd(rng, n, draw(SCALES)))
        if draw(st.booleans()):
            Q = np.zeros_like(Q)  # no process noise: PSD is allowed
        return {"x": x, "P": P, "F": stack(lambda: rng.normal(size=(n, n))), "Q": Q}, ctx
    H = stack(lambda: rng.normal(size=(m, n)))
    R = stack(lambda: spd(rng, m, draw(SCALES)))
    z = rng.normal(size=(*lead, m))
    if which == "kf":
        return {"x": x, "P": P, "z": z, "H": H, "R": R}, ctx
    if which == "ekf":
        return {"x": x, "P": P, "z": z, "h": Linear(H), "H_jac": Linear(H, True), "R": R}, ctx
    Y = stack(lambda: spd(rng, n, draw(SCALES)), shared_ok=False)
    if draw(st.booleans()):
        Y = np.zeros_like(Y)  # no prior information
    return {"Y": Y, "yv": x, "z": z, "H": H, "R": R}, ctx


def check_predict(res: tuple[np.ndarray, np.ndarray], kw: dict) -> None:
    x, P = res
    assert x.shape == kw["x"].shape and P.shape == kw["P"].shape
    _finite(x)
    _sym_pd(P, semidefinite=True)


def check_update(res: kalman.KalmanUpdate, kw: dict) -> None:
    assert res.x.shape == kw["x"].shape and res.P.shape == kw["P"].shape
    _finite(res.x, res.y, res.K, res.log_likelihood)
    _sym_pd(res.P, semidefinite=True)
    _sym_pd(res.S)
    gap = np.linalg.eigvalsh(kw["P"] - res.P)  # an update never adds uncertainty
    assert gap.min() >= -1e-8 * float(np.max(np.abs(kw["P"])))


def check_information(res: tuple[np.ndarray, np.ndarray], kw: dict) -> None:
    Y, yv = res
    assert Y.shape == kw["Y"].shape and yv.shape == kw["yv"].shape
    _finite(yv)
    _sym_pd(Y, semidefinite=True)


KALMAN_APIS = [
    Api(
        kalman.kf_predict,
        kalman_args("predict"),
        {"x": "array", "P": "spd", "F": "array", "Q": "psd"},
        check_predict,
        extreme=("P", "Q", "F"),
    ),
    Api(
        kalman.kf_update,
        kalman_args("kf"),
        {"x": "array", "P": "spd", "z": "array", "H": "array", "R": "spd"},
        check_update,
        {"H": r"S = H P H\^T \+ R"},
        extreme=("P", "R", "H"),
    ),
    Api(
        kalman.ekf_update,
        kalman_args("ekf"),
        {"x": "array", "P": "spd", "z": "array", "h": "callable", "H_jac": "callable", "R": "spd"},
        check_update,
        extreme=("P", "R"),
    ),
    Api(
        kalman.information_update,
        kalman_args("information"),
        {"Y": "psd", "yv": "array", "z": "array", "H": "array", "R": "spd"},
        check_information,
        extreme=("Y", "R", "H"),
    ),
]

# ============================================================================ linalg helpers


@st.composite
def matrix_args(draw: st.DrawFn, which: str) -> tuple[dict, dict]:
    n = draw(st.integers(1, 4))
    rng = np.random.default_rng(draw(SEEDS))
    A = spd(rng, n, draw(SCALES))
    if which == "validate_spd":
        kw: dict[str, Any] = {"value": A, "name": "Mfoo"}
        kw["n"] = n
        return kw, {"n": n}
    if which == "solve_spd":
        return {
            "A": A,
            "B": rng.normal(size=draw(st.sampled_from([(n,), (n, 2)]))),
            "name": "Mfoo",
        }, {}
    if which == "inv_lower_small":
        return {"L": np.linalg.cholesky(A)}, {}
    if which in ("as_float_array", "check_finite"):
        arr = rng.normal(size=draw(st.sampled_from([(), (n,), (n, 2)])))
        return {("value" if which == "as_float_array" else "arr"): arr, "name": "Mfoo"}, {}
    if which == "check_shape":
        arr = rng.normal(size=(n, 2))
        return {"arr": arr, "shape": (n, draw(st.sampled_from([None, 2]))), "name": "Mfoo"}, {}
    if which == "symmetrize":
        return {"A": rng.normal(size=(n, n))}, {}
    return {"A": A, "name": "Mfoo"}, {}


def check_validate_spd(res: np.ndarray, kw: dict) -> None:
    assert res.dtype == np.float64 and np.array_equal(res, res.T)
    assert np.allclose(res, kw["value"], rtol=1e-12, atol=0)


def check_as_float(res: np.ndarray, kw: dict) -> None:
    assert res.dtype == np.float64 and np.array_equal(res, kw["value"])


def check_same(key: str) -> Callable[[Any, dict], None]:
    def check(res: Any, kw: dict) -> None:
        assert np.array_equal(res, kw[key])

    return check


def check_cholesky(res: np.ndarray, kw: dict) -> None:
    _finite(res)
    assert np.allclose(np.triu(res, 1), 0.0)
    assert np.allclose(res @ res.T, kw["A"], rtol=1e-10, atol=1e-12 * np.max(np.abs(kw["A"])))


def check_logdet(res: float, kw: dict) -> None:
    _finite(res)
    _close(float(res), _logdet(kw["A"]), 1e-9)


def check_solve(res: np.ndarray, kw: dict) -> None:
    _finite(res)
    assert np.allclose(kw["A"] @ res, kw["B"], rtol=1e-8, atol=1e-8 * np.max(np.abs(kw["B"])))


def check_symmetrize(res: np.ndarray, kw: dict) -> None:
    assert np.array_equal(res, res.T)


def check_inv_lower(res: np.ndarray, kw: dict) -> None:
    _finite(res)
    assert np.allclose(kw["L"] @ res, np.eye(res.shape[0]), atol=1e-8)


LINALG_APIS = [
    Api(
        linalg.validate_spd,
        matrix_args("validate_spd"),
        {"value": "spd", "n": "optional count1"},
        check_validate_spd,
        {"value": "Mfoo", "n": "Mfoo"},
        extreme=("value",),
    ),
    Api(
        linalg.as_float_array,
        matrix_args("as_float_array"),
        {"value": "any array"},
        check_as_float,
        {"value": "Mfoo"},
    ),
    Api(
        linalg.check_finite,
        matrix_args("check_finite"),
        {"arr": "finite array"},
        check_same("arr"),
        {"arr": "Mfoo"},
    ),
    Api(
        linalg.check_shape,
        matrix_args("check_shape"),
        {"arr": "shaped array"},
        check_same("arr"),
        {"arr": "Mfoo"},
    ),
    Api(
        linalg.cholesky_spd,
        matrix_args("cholesky"),
        {"A": "any spd"},
        check_cholesky,
        {"A": "Mfoo"},
        extreme=("A",),
    ),
    Api(
        linalg.cholesky_small,
        matrix_args("cholesky"),
        {"A": "any spd"},
        check_cholesky,
        {"A": "Mfoo"},
        extreme=("A",),
    ),
    Api(
        linalg.logdet_spd,
        matrix_args("logdet"),
        {"A": "any spd"},
        check_logdet,
        {"A": "Mfoo"},
        extreme=("A",),
    ),
    Api(
        linalg.solve_spd,
        matrix_args("solve_spd"),
        {"A": "any spd", "B": "rhs"},
        check_solve,
        {"A": "Mfoo"},
        extreme=("A", "B"),
    ),
    Api(linalg.symmetrize, matrix_args("symmetrize"), {"A": "square"}, check_symmetrize),
    Api(
        linalg.inv_lower_small,
        matrix_args("inv_lower_small"),
        {"L": "lower"},
        check_inv_lower,
        {"L": "triangular factor"},
    ),
]

# ============================================================================ FIM solvers


@st.composite
def pool_args(draw: st.DrawFn, solver: str) -> tuple[dict, dict]:
    d, N = draw(st.integers(1, 4)), draw(st.integers(1, 8))
    form = draw(st.sampled_from(["scalar", "block", "shared"]))
    m = 1 if form == "scalar" else draw(st.integers(1, 2))
    rng = np.random.default_rng(draw(SEEDS))
    Q0 = spd(rng, d, draw(SCALES))
    if form == "scalar":
        H, R = rng.normal(size=(N, d)), rng.uniform(0.1, 2.0, size=N)
    elif form == "block":
        H, R = rng.normal(size=(N, m, d)), np.stack([spd(rng, m) for _ in range(N)])
    else:
        H, R = rng.normal(size=(N, m, d)), spd(rng, m)
    K = draw(st.integers(0, N))
    kw: dict[str, Any] = {"Q0": Q0, "H": H, "R": R, "budget": K}
    widest = min(K, N - K)
    if solver == "swap" and draw(st.booleans()):
        kw["max_rounds"] = draw(st.integers(0, 5))
    if solver == "brute_force" and draw(st.booleans()):
        kw["max_subsets"] = draw(st.integers(math.comb(N, K), 10**6))
    if solver == "vns":
        if draw(st.booleans()):
            kw["initial"] = sorted(rng.choice(N, size=K, replace=False).tolist())
        if widest >= 1 and draw(st.booleans()):
            kw["l_max"] = draw(st.integers(1, widest))
        if draw(st.booleans()):
            kw["m_l"] = tuple(draw(st.lists(st.integers(1, 30), min_size=1, max_size=3)))
        kw["rng"] = draw(st.one_of(SEEDS, SEEDS.map(np.random.default_rng)))
        if draw(st.booleans()):
            kw["batched"] = draw(st.booleans())
    return kw, {"N": N, "K": K, "widest": widest}


def check_selection(res: fim_solvers.Selection, kw: dict) -> None:
    Q0, G = as_candidates(kw["Q0"], kw["H"], kw["R"])
    idx = res.indices
    assert len(idx) == kw["budget"] == len(set(idx))
    assert all(isinstance(k, int) and 0 <= k < G.shape[0] for k in idx)
    _finite(res.objective)
    assert res.objective >= -1e-9
    _close(res.objective, logdet_objective(Q0, G, list(idx)), 1e-8)


POOL_KINDS = {"Q0": "spd", "H": "array", "R": "noise", "budget": "budget"}

SOLVER_APIS = [
    Api(
        fim_solvers.greedy,
        pool_args("greedy"),
        POOL_KINDS,
        check_selection,
        extreme=("Q0", "H", "R"),
    ),
    Api(
        fim_solvers.swap,
        pool_args("swap"),
        {**POOL_KINDS, "max_rounds": "count0"},
        check_selection,
        extreme=("Q0", "H", "R"),
    ),
    Api(
        fim_solvers.brute_force,
        pool_args("brute_force"),
        {**POOL_KINDS, "max_subsets": "count1"},
        check_selection,
        extreme=("Q0", "H"),
    ),
    Api(
        vns,
        pool_args("vns"),
        {
            **POOL_KINDS,
            "initial": "indices",
            "l_max": "l_max",
            "m_l": "m_l",
            "rng": "rng",
            "batched": "flag",
        },
        check_selection,
        {"m_l": "M_l"},
        extreme=("Q0", "H"),
    ),
]

# ============================================================================ clustering GA


class ToyCost:
    """Batched toy cost ``(B, n) -> (B,)``: pairwise dissimilarity within clusters (finite)."""

    def __init__(self, n: int, seed: int) -> None:
        W = np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n, n))
        self.M = W + W.T

    def __call__(self, labels: np.ndarray) -> np.ndarray:
        same = labels[:, :, None] == labels[:, None, :]
        return 0.5 * np.sum(same * self.M[None], axis=(1, 2))

    def __repr__(self) -> str:
        return f"ToyCost(n={self.M.shape[0]})"


@st.composite
def ga_config_args(draw: st.DrawFn) -> tuple[dict, dict]:
    ops = draw(st.lists(st.sampled_from([0, 1]), min_size=5, max_size=5).filter(any))
    kw = {
        "population_size": draw(st.integers(2, 8)),
        "alpha": draw(st.floats(1e-3, 10.0)),
        "operators": tuple(ops),
        "max_tries": draw(st.integers(1, 5)),
        "n_labels": draw(st.one_of(st.none(), st.integers(1, 12))),
        "redraw_partner": draw(st.booleans()),
        "variant": draw(st.sampled_from(ga.VARIANTS)),
    }
    if kw["variant"] == "literal":
        kw["n_labels"] = None  # the literal O1M has no label range
    return kw, {}


@st.composite
def ga_args(draw: st.DrawFn) -> tuple[dict, dict]:
    n = draw(st.integers(1, 8))
    max_size = draw(st.integers(1, n))
    seed = draw(SEEDS)
    rng = np.random.default_rng(seed)
    labels = ga.random_feasible_clustering(n, max_size, rng)
    config = ga.GAConfig(**draw(ga_config_args())[0])
    kw = {
        "evaluate": ToyCost(n, seed),
        "initial_labels": labels,
        "max_size": max_size,
        "config": config,
        "rng": seed,
    }
    return kw, {"n": n}


def run_ga(**kw: Any) -> ga.GeneticClustering:
    g = ga.GeneticClustering(**kw)
    g.generation()
    g.generation()
    return g


def check_ga(g: ga.GeneticClustering, kw: dict) -> None:
    n, cap = len(kw["initial_labels"]), kw["max_size"]
    assert g.population.shape == (kw["config"].population_size, n)
    for labels in g.population:
        assert np.array_equal(labels, ga.canonical_labels(labels))
        assert np.bincount(labels).max() <= cap
    _finite(g.costs)
    assert np.all(np.diff(g.costs) >= 0)
    assert g.best_cost <= float(kw["evaluate"](kw["initial_labels"][None])[0]) + 1e-9


def check_ga_config(cfg: ga.GAConfig, kw: dict) -> None:
    assert cfg.operators == tuple(int(o) for o in kw["operators"])
    assert cfg.population_size == kw["population_size"] and cfg.alpha == kw["alpha"]
    assert cfg.variant == kw["variant"]


@st.composite
def operator_args(draw: st.DrawFn, op: str) -> tuple[dict, dict]:
    n = draw(st.integers(1, 8))
    max_size = draw(st.integers(1, n))
    rng = np.random.default_rng(draw(SEEDS))
    a = ga.random_feasible_clustering(n, max_size, rng)
    kw: dict[str, Any] = {
        "a": a,
        "rng": rng,
        "max_size": max_size,
        "max_tries": draw(st.integers(1, 5)),
    }
    if op.startswith(("o1c", "o2c")):
        kw["b"] = ga.random_feasible_clustering(n, max_size, rng)
    if op == "o1m":
        kw["n_labels"] = draw(st.integers(1, 2 * n))
    return kw, {"n": n}


def check_child(child: np.ndarray, kw: dict) -> None:
    assert child.shape == kw["a"].shape and child.dtype.kind == "i"
    assert child.min() >= 0 and np.bincount(child).max() <= kw["max_size"]


@st.composite
def draw_rank_args(draw: st.DrawFn) -> tuple[dict, dict]:
    kw = {
        "rng": np.random.default_rng(draw(SEEDS)),
        "alpha": draw(st.floats(1e-3, 10.0)),
        "population_size": draw(st.integers(2, 50)),
    }
    return kw, {}


def check_rank(r: int, kw: dict) -> None:
    assert isinstance(r, int) and 1 <= r <= kw["population_size"] - 1


LABEL_BAD = {
    **TYPE_BAD,
    "NaN": lambda v, c: _poke(v, np.nan),
    "fractional": lambda v, c: _poke(v, 0.5),
    "negative": lambda v, c: np.asarray(v) - 1 - int(np.max(v)),
    "2-D": lambda v, c: np.asarray(v)[None],
    "empty": lambda v, c: np.zeros(0, int),
}
KIND_BAD["labels"] = lambda v, c: LABEL_BAD
KIND_BAD["alpha"] = lambda v, c: _ints([0.0, -1.0, math.nan, math.inf, "0.1", True, 1e300])
KIND_BAD["config"] = lambda v, c: _ints([{"alpha": 0.1}, "default", 3])
KIND_BAD["evaluate"] = lambda v, c: {
    "None": lambda v, c: None,
    "str": lambda v, c: "cost",
    "wrong shape": lambda v, c: Returns(np.zeros((2, 2))),
    "NaN": lambda v, c: Returns(np.nan),
    "strings": lambda v, c: Returns("abc"),
}
KIND_BAD["operators"] = lambda v, c: _ints(
    [(0, 0, 0, 0, 0), (1, 1), (2, 0, 0, 0, 0), (0.5, 1, 1, 1, 1), "11111", None]
)
KIND_BAD["gen"] = lambda v, c: _ints([None, "rng", 3.5, OPAQUE])
KIND_BAD["size"] = lambda v, c: _ints([0, -1, 2.5, 1.0, True, "2", None, [2]])
KIND_BAD["pop"] = lambda v, c: _ints([1, 0, 2.5, True, "20", None, 10**12])
KIND_BAD["tries"] = lambda v, c: _ints([0, -1, 2.5, True, "5", None, 10**12])

GA_APIS = [
    Api(
        run_ga,
        ga_args(),
        {
            "evaluate": "evaluate",
            "initial_labels": "labels",
            "max_size": "size",
            "config": "config",
            "rng": "rng",
        },
        check_ga,
    ),
    Api(
        ga.GAConfig,
        ga_config_args(),
        {
            "population_size": "pop",
            "alpha": "alpha",
            "operators": "operators",
            "max_tries": "tries",
            "n_labels": "optional count1",
            "redraw_partner": "flag",
        },
        check_ga_config,
    ),
    *(
        Api(
            getattr(ga, op),
            operator_args(op),
            {
                "a": "labels",
                "rng": "gen",
                "max_size": "size",
                "max_tries": "tries",
                **({"b": "labels"} if op.startswith(("o1c", "o2c")) else {}),
                **({"n_labels": "count1"} if op == "o1m" else {}),
            },
            check_child,
        )
        for op in (
            "o1c",
            "o2c",
            "o1m",
            "o2m",
            "o3m",
            *(f"{o}_literal" for o in ("o1c", "o2c", "o1m", "o2m")),
        )
    ),
    Api(
        ga.draw_rank,
        draw_rank_args(),
        {"rng": "gen", "alpha": "alpha", "population_size": "pop"},
        check_rank,
    ),
]

APIS = FUSION_APIS + KALMAN_APIS + LINALG_APIS + SOLVER_APIS + GA_APIS
IDS = [api.name for api in APIS]

# ============================================================================ harness


def call(api: Api, kw: dict[str, Any]) -> Any:
    """Call ``api.fn(**kw)`` with every ``RuntimeWarning`` (overflow, invalid, ...) an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        return api.fn(**kw)


def snapshot(kw: dict[str, Any]) -> dict[str, tuple[Any, ...]]:
    """Bit-level copy of the numpy arguments (dtype, shape, bytes)."""
    out = {}
    for k, v in kw.items():
        if isinstance(v, np.ndarray) and v.dtype != object:
            out[k] = (v.dtype, v.shape, v.tobytes())
    return out


def assert_unchanged(before: dict[str, tuple[Any, ...]], kw: dict[str, Any]) -> None:
    after = snapshot(kw)
    for k, was in before.items():
        assert after.get(k) == was, f"argument {k!r} was modified in place"


def names_pattern(names: set[str], aliases: dict[str, str]) -> str:
    words = sorted({*map(re.escape, names), *(aliases[n] for n in names if n in aliases)})
    return r"(?<![A-Za-z0-9_])(?:" + "|".join(words) + r")(?![A-Za-z0-9_])"


def rejection_failure(api: Api, kw: dict[str, Any], names: set[str]) -> str | None:
    """``None`` if the call raises TypeError/ValueError naming one of ``names`` and leaves the
    numpy arguments unchanged; otherwise what went wrong."""
    before = snapshot(kw)
    try:
        result = call(api, kw)
    except (TypeError, ValueError) as exc:
        if snapshot(kw) != before:
            return "rejected, but a numpy argument was modified in place"
        if not re.search(names_pattern(names, api.aliases), str(exc)):
            return f"{type(exc).__name__} not naming {sorted(names)}: {str(exc)[:200]}"
        return None
    except BaseException as exc:  # any other exception type is the failure tested for
        return f"{type(exc).__name__}: {str(exc)[:200]}"
    return f"accepted, returned {type(result).__name__}"


def corruptions(api: Api, kw: dict[str, Any], ctx: dict[str, Any]) -> list[tuple[str, str, Any]]:
    """Every ``(argument, label, bad value)`` of the catalogue applicable to this call."""
    out = []
    for target in sorted(k for k in api.kinds if k in kw):
        options = KIND_BAD[api.kinds[target]](kw[target], ctx)
        out += [(target, label, make(kw[target], ctx)) for label, make in sorted(options.items())]
    return out


# ============================================================================ properties


@pytest.mark.parametrize("api", APIS, ids=IDS)
@fuzz_settings(0.5)
@given(data=st.data())
def test_invalid_input_is_rejected_naming_it(api: Api, data: st.DataObject) -> None:
    """(a)+(c) Each argument in turn gets every invalid value of its kind (exhaustively)."""
    kw, ctx = data.draw(api.valid, label="valid")
    ctx = {**ctx, "x": kw.get("x")}
    shape_group = {k for k in kw if api.kinds.get(k) in ARRAY_KINDS}
    failures = []
    for target, label, bad in corruptions(api, kw, ctx):
        names = shape_group | {target} if label in SHAPE_LABELS else {target}
        why = rejection_failure(api, {**kw, target: bad}, names)
        if why is not None:
            failures.append(f"{target} <- {label} ({bad!r:.60}): {why}")
    assert not failures, f"{len(failures)} invalid inputs not rejected cleanly:\n" + "\n".join(
        failures
    )


@pytest.mark.parametrize("api", APIS, ids=IDS)
@fuzz_settings(3.0)
@given(data=st.data())
def test_valid_input_gives_valid_output(api: Api, data: st.DataObject) -> None:
    kw, _ = data.draw(api.valid, label="valid")
    before = snapshot(kw)
    result = call(api, kw)
    assert_unchanged(before, kw)
    api.check(result, kw)


EXTREME_APIS = [api for api in APIS if api.extreme]


@pytest.mark.parametrize("api", EXTREME_APIS, ids=[a.name for a in EXTREME_APIS])
@fuzz_settings(2.0)
@given(data=st.data())
def test_extreme_values_are_rejected_or_finite(api: Api, data: st.DataObject) -> None:
    kw, _ = data.draw(api.valid, label="valid")
    target = data.draw(st.sampled_from([k for k in api.extreme if k in kw]), label="target")
    kw = {**kw, target: np.asarray(kw[target]) * data.draw(EXTREMES, label="scale")}
    before = snapshot(kw)
    try:
        result = call(api, kw)
    except (TypeError, ValueError) as exc:
        note(f"message: {exc}")
        names = {k for k in kw if k in api.kinds}
        assert re.search(names_pattern(names, api.aliases), str(exc)), f"unnamed: {exc}"
    else:
        api.check(result, kw)
    assert_unchanged(before, kw)


# ------------------------------------------------------------ cross-solver and extra properties


@fuzz_settings(3.0)
@given(case=pool_args("brute_force"))
def test_solvers_are_ordered_greedy_swap_optimum(case: tuple[dict, dict]) -> None:
    """``greedy <= swap <= brute_force`` and ``vns <= brute_force`` on the same pool."""
    kw, _ = case
    args = (kw["Q0"], kw["H"], kw["R"], kw["budget"])
    g = fim_solvers.greedy(*args).objective
    s = fim_solvers.swap(*args).objective
    v = vns(*args, rng=0).objective
    best = fim_solvers.brute_force(*args).objective
    tol = 1e-9 * max(1.0, abs(best))
    assert g <= s + tol and s <= best + tol and v <= best + tol


@fuzz_settings(2.0)
@given(case=pool_args("vns"), key=st.sampled_from(["nonsense", "budgets", "lmax"]))
def test_unknown_keyword_of_vns_is_a_type_error_naming_it(
    case: tuple[dict, dict], key: str
) -> None:
    kw, _ = case
    with pytest.raises(TypeError, match=key):
        vns(**kw, **{key: 1})


@pytest.mark.fuzz_long
@fuzz_settings(0.2)
@given(case=pair_args("pecmv"))
def test_pecmv_sdp_reference_agrees_with_the_fast_path(case: tuple[dict, dict]) -> None:
    """Long only (cvxpy): the SDP reference and the fast path reach the same log det."""
    kw, _ = case
    kw = {k: v for k, v in kw.items() if k not in ("method", "C")}
    fast = fusion.pecmv_update(**kw, method="fast")
    ref = fusion.pecmv_update(**kw, method="sdp")
    check_pecmv(ref, kw)
    assert abs(fast.log_det - ref.log_det) <= 1e-4 * max(1.0, abs(ref.log_det))
