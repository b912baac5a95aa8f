"""Speed work: the faster ``dmv_omega_batch`` and ``kf_update`` give bit-identical results.

The references below are the previous implementations' logic, kept verbatim (full-batch
safeguarded Newton evaluating every item on every pass; the Kalman update with ``np.eye`` and
``np.sum``), run on the same seeded inputs. Errors are compared with the fast validation paths
switched off (the canonical checks alone), so every message is unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from scipy.linalg.lapack import dpotrf, dpotrs, dtrtrs

import selenv.core.fusion.batch as batch_mod
import selenv.core.kalman as kalman_mod
from selenv.core.fusion import dmv_omega_batch, dmv_update
from selenv.core.fusion.batch import _sq, _tr
from selenv.core.fusion.common import root_increasing_batch, root_increasing_one
from selenv.core.fusion.dmv import _W_PROBE, _cubic
from selenv.core.kalman import kf_update

# ------------------------------------------------------------------ previous implementation


def _ref_root(g: Callable[[Any], Any], lo: Any, hi: Any, x0: Any) -> Any:
    """The previous ``root_increasing_batch``: every item evaluated on every pass."""
    xtol, maxiter = 1e-15, 200
    x, lo, hi = x0.astype(np.float64), lo.astype(np.float64), hi.astype(np.float64)
    dxold = hi - lo
    dx = dxold.copy()
    active = np.ones(x.shape, dtype=bool)
    f, df = g(x)
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(maxiter):
            active &= f != 0.0
            lo = np.where(active & (f < 0.0), x, lo)
            hi = np.where(active & (f > 0.0), x, hi)
            step = f / df
            conv = (df > 0.0) & (np.abs(step) <= xtol * np.maximum(1.0, np.abs(x)))
            newton = (x - step > lo) & (x - step < hi) & (df > 0.0)
            newton &= np.abs(2.0 * f) <= np.abs(dxold * df)
            newton |= conv
            dxold = dx
            dx = np.where(newton, step, 0.5 * (hi - lo))
            x_new = np.where(newton, x - step, lo + 0.5 * (hi - lo))
            done = conv | (x_new == x) | (np.abs(dx) <= xtol * np.maximum(1.0, np.abs(x_new)))
            x = np.where(active, x_new, x)
            active &= ~done
            if not active.any():
                break
            f, df = g(x)
    return x


def _ref_derivs(w: Any, A: Any, B: Any, R: Any, n: int) -> tuple[Any, Any]:
    m = A.shape[-1]
    wb = w[:, None, None]
    M = B + (1.0 - wb) * R
    Q = (1.0 - wb) * A + wb * B + wb * (1.0 - wb) * R
    dQ = B - A + (1.0 - 2.0 * wb) * R
    X1 = np.linalg.solve(M, R)
    X2 = np.linalg.solve(Q, np.concatenate([dQ, R], axis=-1))
    G, H = X2[..., :m], X2[..., m:]
    tr = lambda X: np.trace(X, axis1=-2, axis2=-1)  # noqa: E731
    sq = lambda X: np.einsum("...ij,...ji->...", X, X)  # noqa: E731
    return -(n - m) / w - tr(X1) - tr(G), (n - m) / w**2 - sq(X1) + sq(G) + 2.0 * tr(H)


def _ref_omega(Pi: Any, Pj: Any, Hi: Any, Hj: Any, R: Any) -> Any:
    """The previous ``dmv_omega_batch`` on valid inputs (symmetrized as its validation did)."""
    Pi, Pj = 0.5 * (Pi + Pi.transpose(0, 2, 1)), 0.5 * (Pj + Pj.transpose(0, 2, 1))
    R = 0.5 * (R + np.swapaxes(R, -1, -2))
    Bn, n, m = Pi.shape[0], Pi.shape[1], Hi.shape[1]
    Rm = np.broadcast_to(R, (Bn, m, m))
    A = np.einsum("bki,bij,blj->bkl", Hi, Pi, Hi)
    B = np.einsum("bki,bij,blj->bkl", Hj, Pj, Hj)
    if m == 1:
        r = Rm[:, 0, 0]
        a, b = A[:, 0, 0] / r, B[:, 0, 0] / r
        c3, c2, c1, c0 = (np.broadcast_to(np.asarray(c, float), a.shape) for c in _cubic(a, b, n))
        if n == 1:
            c3, c2, c1, c0 = np.zeros_like(a), c3, c2, c1

        def g(w: Any) -> tuple[Any, Any]:
            return -(((c3 * w + c2) * w + c1) * w + c0), -((3.0 * c3 * w + 2.0 * c2) * w + c1)

        ones = np.ones_like(a)
        w = _ref_root(g, 0.0 * ones, ones, 0.5 * ones)
        w = np.where((n == 1) & (c0 <= 0.0), 0.0, w)
        return np.where(a <= n * b, 1.0, w)
    trace_ratio = np.trace(np.linalg.solve(B, A), axis1=1, axis2=2)
    w = np.ones(Bn)
    todo = trace_ratio > n
    if n == m:
        zero = todo & (_ref_derivs(np.full(Bn, _W_PROBE), A, B, Rm, n)[0] >= 0.0)
        w[zero] = 0.0
        todo &= ~zero
    if todo.any():
        At, Bt, Rt = A[todo], B[todo], Rm[todo]
        k = int(todo.sum())
        w[todo] = _ref_root(
            lambda x: _ref_derivs(x, At, Bt, Rt, n), np.zeros(k), np.ones(k), np.full(k, 0.5)
        )
    return w


def _spd_stack(rng: np.random.Generator, B: int, n: int, exact: bool) -> np.ndarray:
    A = rng.normal(size=(B, n, n))
    S = np.exp(rng.normal(0.0, 1.5, size=(B, 1, 1))) * (A @ A.transpose(0, 2, 1) + 0.05 * np.eye(n))
    return 0.5 * (S + S.transpose(0, 2, 1)) if exact else S


def _problems(seed: int, B: int, n: int, m: int, shared_R: bool, exact: bool) -> list[Any]:
    rng = np.random.default_rng(seed)
    Pi, Pj = _spd_stack(rng, B, n, exact), _spd_stack(rng, B, n + 1, exact)
    Hi, Hj = rng.normal(size=(B, m, n)), rng.normal(size=(B, m, n + 1))
    R = _spd_stack(rng, 1, m, exact)[0] if shared_R else 0.3 * _spd_stack(rng, B, m, exact)
    return [Pi, Pj, Hi, Hj, R]


CASES = [
    (m, n, B, shared)
    for m in (1, 2, 3)
    for n in sorted({m, m + 1, 4})
    for B in (1, 3, 64, 160)
    for shared in (False, True)
]


def test_dmv_omega_batch_identical_to_previous_implementation() -> None:
    """>= 2000 problems (m = 1, 2, 3; n = m too): batched, and each row alone (B = 1 path)."""
    total = 0
    for k, (m, n, B, shared) in enumerate(CASES):
        p = _problems(k, B, n, m, shared, exact=k % 3 != 0)
        w = dmv_omega_batch(*p)
        assert w.tobytes() == _ref_omega(*p).tobytes(), (m, n, B, shared)
        total += B
        for r in range(min(B, 12)):
            q = [x[r : r + 1] for x in p[:4]] + [p[4] if shared else p[4][r : r + 1]]
            assert dmv_omega_batch(*q).tobytes() == _ref_omega(*q).tobytes(), (m, n, r)
            total += 1
    assert total >= 2000


def test_dmv_omega_batch_rows_agree_with_dmv_update() -> None:
    p = _problems(7, 40, 4, 2, False, exact=True)
    w = dmv_omega_batch(*p)
    for r in range(40):
        assert w[r] == pytest.approx(dmv_update(*(x[r] for x in p)).omega, abs=1e-9)


def test_root_increasing_one_matches_batch() -> None:
    rng = np.random.default_rng(3)
    c = rng.normal(size=(4, 3000))
    c[3] = -np.abs(c[3])  # g(0) < 0

    def poly(w: Any, k: Any) -> tuple[Any, Any]:
        return ((k[0] * w + k[1]) * w + k[2]) * w + k[3], (3.0 * k[0] * w + 2.0 * k[1]) * w + k[2]

    g1 = lambda w, i: poly(w, c[:, i])  # noqa: E731
    z, o, h = np.zeros(3000), np.ones(3000), np.full(3000, 0.5)
    wb = root_increasing_batch(g1, z, o, h)
    assert wb.tobytes() == _ref_root(lambda w: poly(w, c), z, o, h).tobytes()

    def one(i: int) -> Callable[[float], tuple[float, float]]:
        k = c[:, i].tolist()
        return lambda w: poly(w, k)

    for tail in (4, 100, 3000):  # finish the last items (or all, after one pass) in floats
        assert root_increasing_batch(g1, z, o, h, scalar=one, tail=tail).tobytes() == wb.tobytes()
    for i in range(3000):
        ci = c[:, i].tolist()
        assert root_increasing_one(lambda w, ci=ci: poly(w, ci), 0.0, 1.0, 0.5) == wb[i]


def test_scalar_trace_and_einsum_orders_match_numpy() -> None:
    rng = np.random.default_rng(11)
    for m in (1, 2, 3):
        X = rng.normal(size=(20000, m, 2 * m)) * np.exp(rng.normal(size=(20000, 1, 1)) * 4)
        X[::7] *= 1e-160
        G = X[..., :m]
        sq = np.einsum("...ij,...ji->...", G, G)
        tr = np.trace(G, axis1=-2, axis2=-1)
        rows = G.tolist()
        assert [_sq(g, m) for g in rows] == sq.tolist()
        assert [_tr(g, m) for g in rows] == tr.tolist()


def _outcome(fn: Callable[[], Any]) -> Any:
    try:
        out = fn()
    except (TypeError, ValueError) as exc:
        return type(exc), str(exc)
    return out


def _bad_batches() -> list[list[Any]]:
    good = _problems(1, 3, 4, 2, False, exact=True)
    bad = []
    for i in range(5):
        for value in (np.nan, np.inf, 1e120, -1.0, 1e-120):
            p = [x.copy() for x in good]
            p[i].flat[0] = value
            bad.append(p)
        p = [x.copy() for x in good]
        p[i] = p[i][..., :-1] if i != 4 else p[i][:2]
        bad.append(p)
        p = [x.copy() for x in good]
        p[i] = p[i].astype(complex)
        bad.append(p)
    asym = [x.copy() for x in good]
    asym[0][0, 0, 1] += 1e-3
    notpd = [x.copy() for x in good]
    notpd[1][1] = -notpd[1][1]
    return [*bad, asym, notpd]


def test_dmv_omega_batch_errors_unchanged(monkeypatch: pytest.MonkeyPatch) -> None:
    fast = [_outcome(lambda p=p: dmv_omega_batch(*p)) for p in _bad_batches()]
    monkeypatch.setattr(batch_mod, "_spd_fast", lambda A, B: None)
    slow = [_outcome(lambda p=p: dmv_omega_batch(*p)) for p in _bad_batches()]
    assert len(fast) == len(slow)
    for a, b in zip(fast, slow, strict=True):
        if isinstance(a, tuple):
            assert a == b
        else:
            assert np.asarray(a).tobytes() == np.asarray(b).tobytes()


# --------------------------------------------------------------------------------- kf_update


def _ref_kf(x: Any, P: Any, z: Any, H: Any, R: Any) -> tuple[Any, ...]:
    """The previous validated ``kf_update`` on valid unbatched inputs."""
    P, R = 0.5 * (P + P.T), 0.5 * (R + R.T)  # validate_spd symmetrizes
    y = z - (H @ x[..., None])[..., 0]
    n, m = x.shape[0], y.shape[0]
    HP = H @ P
    S = HP @ H.T + R
    S = 0.5 * (S + S.T)
    L, _ = dpotrf(S, lower=1, clean=1)
    KT, _ = dpotrs(L, HP, lower=1)
    K = KT.T
    x_post = x + K @ y
    I_KH = np.eye(n) - K @ H
    P_post = I_KH @ P @ I_KH.T + K @ R @ KT
    P_post = 0.5 * (P_post + P_post.T)
    w, _ = dtrtrs(L, y, lower=1)
    ll = -0.5 * (float(w @ w) + 2.0 * float(np.sum(np.log(np.diagonal(L)))) + m * np.log(2 * np.pi))
    return x_post, P_post, y, S, K, ll


def test_kf_update_identical_to_previous_implementation() -> None:
    rng = np.random.default_rng(19)
    for k in range(2000):
        n, m = int(rng.integers(1, 7)), int(rng.integers(1, 4))
        A, C = rng.normal(size=(n, n)), rng.normal(size=(m, m))
        P = A @ A.T + 0.1 * np.eye(n)
        if k % 2:
            P = 0.5 * (P + P.T)  # exactly symmetric (the fast path), else maybe not
        R = C @ C.T + 0.2 * np.eye(m)
        x, z, H = rng.normal(size=n), rng.normal(size=m), rng.normal(size=(m, n))
        r = kf_update(x, P, z, H, R)
        ref = _ref_kf(x, P, z, H, R)
        got = (r.x, r.P, r.y, r.S, r.K, r.log_likelihood)
        for a, b in zip(got, ref, strict=True):
            assert np.asarray(a).tobytes() == np.asarray(b).tobytes()


def _bad_kf() -> list[list[Any]]:
    x, P, z = np.ones(4), np.eye(4) * 2.0, np.ones(2)
    H, R = np.eye(2, 4), np.eye(2) * 0.5
    good = [x, P, z, H, R]
    bad: list[list[Any]] = []
    for i in range(5):
        for value in (np.nan, np.inf, 1e120, -1.0, 1e-120, -0.0):
            p = [np.array(v, dtype=float) for v in good]
            p[i].flat[-1] = value
            bad.append(p)
        p = [v.copy() for v in good]
        p[i] = p[i][..., :-1]
        bad.append(p)
        p = [v.copy() for v in good]
        p[i] = p[i].astype(complex)
        bad.append(p)
        p = [v.tolist() for v in good]
        p[i] = "a"
        bad.append(p)
    asym = [v.copy() for v in good]
    asym[1][0, 1] = 1e-3
    notpd = [v.copy() for v in good]
    notpd[4][0, 1] = notpd[4][1, 0] = 5.0
    lists = [v.tolist() for v in good]
    return [*bad, asym, notpd, lists, [np.ones((2, 4)), np.stack([P, P]), np.ones((2, 2)), H, R]]


def test_kf_update_errors_and_slow_path_unchanged(monkeypatch: pytest.MonkeyPatch) -> None:
    fast = [_outcome(lambda p=p: kf_update(*p)) for p in _bad_kf()]
    monkeypatch.setattr(kalman_mod, "_fast_valid_single", lambda *a: None)
    slow = [_outcome(lambda p=p: kf_update(*p)) for p in _bad_kf()]
    for a, b in zip(fast, slow, strict=True):
        if isinstance(a, tuple):
            assert a == b
        else:
            ours, ref = (a.x, a.P, a.K, a.log_likelihood), (b.x, b.P, b.K, b.log_likelihood)
            for u, v in zip(ours, ref, strict=True):
                assert np.asarray(u).tobytes() == np.asarray(v).tobytes()


def _ref_check_finite(arr: Any, name: str) -> np.ndarray:
    """The previous ``check_finite`` (``np.all(np.isfinite)`` on every call), verbatim."""
    from selenv.core.linalg import as_float_array

    if type(arr) is not np.ndarray or arr.dtype is not np.dtype(np.float64):
        arr = as_float_array(arr, name)
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"{name} must be finite, but {bad} entries are NaN or inf")
    return arr


def _finite_cases() -> list[Any]:
    rng = np.random.default_rng(7)
    big = np.full((3, 3), 1e200)  # finite, but its vdot overflows: the exact test decides
    cases: list[Any] = [np.zeros(0), np.float64(2.0), np.array(3.0), big, -big, big.T[:, ::2]]
    cases += [np.arange(6).reshape(2, 3), [1.0, 2.0], 4, np.float32([1.0, np.inf])]
    for _ in range(200):
        a = rng.standard_normal(rng.integers(1, 5, size=rng.integers(1, 3))) * 10.0 ** float(
            rng.integers(-300, 300)
        )
        if rng.random() < 0.5:  # plant NaN / +-inf somewhere
            a.flat[int(rng.integers(a.size))] = rng.choice([np.nan, np.inf, -np.inf])
        cases.append(a if rng.random() < 0.8 else a.T)
    return cases


def test_check_finite_accepts_and_rejects_exactly_as_before() -> None:
    """The one-``vdot`` test of ``check_finite`` raises iff the previous exact test raised,
    with the same message, and returns the same array (also when the ``vdot`` overflows)."""
    from selenv.core.linalg import check_finite

    n_raised = 0
    for a in _finite_cases():
        try:
            want: Any = _ref_check_finite(a, "v")
        except ValueError as exc:
            want = str(exc)
        try:
            got: Any = check_finite(a, "v")
        except ValueError as exc:
            got = str(exc)
        if isinstance(want, str):
            n_raised += 1
            assert got == want
        else:
            assert isinstance(got, np.ndarray) and got.dtype == np.float64
            assert got.tobytes() == want.tobytes() and got.shape == want.shape
    assert 50 < n_raised < 200  # both branches were exercised


@pytest.mark.parametrize(
    "lo, hi, x0", [(0.0, 1.0, 0.5), (-1.0, 1.0, 0.0), (-3.0, 5.0, 0.5), (0.0, 40.0, 20.0)]
)
def test_root_increasing_batch_tolerance_shortcut_keeps_iterates(
    lo: float, hi: float, x0: float
) -> None:
    """Inside [-1, 1] the tolerance tests compare with ``xtol`` itself (max(1, |x|) = 1);
    outside they keep ``xtol * max(1, |x|)``: the roots equal the previous iteration's bit for
    bit either way, also for roots at the ends of the bracket and far outside [-1, 1]."""
    rng = np.random.default_rng(17)
    k = 4000
    roots = rng.uniform(lo, hi, size=k)
    roots[:200] = lo  # at the ends: the shortcut's corner cases
    roots[200:400] = hi
    roots[400:600] = np.nextafter(lo, hi)
    slope = 10.0 ** rng.uniform(-3, 3, size=k)
    curv = rng.uniform(0.0, 2.0, size=k)

    def g(w: Any, s: Any) -> tuple[Any, Any]:  # increasing: slope + curvature * (w - root)^2
        d = w - roots[s]
        return slope[s] * d + curv[s] * d * d * d, slope[s] + 3.0 * curv[s] * d * d

    args = (np.full(k, lo), np.full(k, hi), np.full(k, x0))
    new = root_increasing_batch(g, *args)
    assert new.tobytes() == _ref_root(lambda w: g(w, slice(None)), *args).tobytes()
