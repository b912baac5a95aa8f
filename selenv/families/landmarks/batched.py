"""The step math of ``LandmarkSelection`` for ``B`` episodes at once (``B = 1``: the single env).

Both :class:`~selenv.families.landmarks.env.LandmarkSelectionEnv` (through
:class:`~selenv.families.landmarks.scenario.LandmarkEKF`, ``B = 1``) and
:class:`~selenv.families.landmarks.vector.LandmarkSelectionVectorEnv` (``B = num_envs``) call
these functions, so every equation of the filter step exists once. Shapes: ``B`` episodes,
``N`` landmarks, ``m = 2`` angles per landmark, ``d = 9`` states.

* :func:`ekf_predict`: the strapdown propagation of Algorithm 3 (eq. 2) with
  ``P <- F P F^T + Q``, ``Q = G imu_cov G^T``;
* :func:`aoa_candidates`: the angles of arrival ``h(x)`` (eqs. 16-17) and their Jacobians
  ``dh/dx`` (eq. 21 chained with ``dDelta/dx``) of every landmark;
* :func:`ekf_update`: the Joseph-form update with the selected landmarks (Algorithm 3);
* :class:`SelectionBatch`, :func:`open_selection`, :func:`add_picks`: the gain state of a
  filter step, ``Q0 = P_pred^-1`` plus the picks, with every candidate whitened in the current
  information (``Z``) and its marginal gain (the log-det gain ``log det(I + S_k)`` or the
  Woodbury downdate of another objective, :mod:`selenv.core.objectives`);
* :func:`landmark_costs`: the cost eq. (11) of posterior covariances;
* :func:`landmark_features`, :func:`write_observation`: the observation.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from selenv.core.information import block_logdet_gains
from selenv.core.kalman import KalmanUpdate
from selenv.core.linalg import FloatArray, cholesky_spd
from selenv.core.objectives import get_objective
from selenv.families.landmarks.models import (
    STATE_DIM,
    aoa_angles,
    aoa_angles_jacobian,
    dcm_batch,
    strapdown_batch,
    wrap_angle,
)

__all__ = [
    "POSITION",
    "GainSpec",
    "SelectionBatch",
    "add_picks",
    "aoa_candidates",
    "ekf_predict",
    "ekf_update",
    "inv_lower",
    "joseph_update",
    "landmark_costs",
    "landmark_features",
    "landmark_interest",
    "open_selection",
    "process_noise_batch",
    "whiten_landmarks",
    "write_observation",
]

#: indices of the position ``p`` in the EKF state ``(p, v, theta)``: what objectives that are
#: not unit-invariant (``"trace"``, ``"max_eig"``) score
POSITION: tuple[int, ...] = (0, 1, 2)
_M = 2  # angles per landmark (azimuth, elevation)
_LOG_2PI = float(np.log(2.0 * np.pi))


def landmark_interest(objective: str) -> tuple[int, ...] | None:
    """State indices an objective scores: ``None`` (all) if unit-invariant, else the position.

    ``logdet`` and ``det`` score the whole state; ``trace``, ``max_eig`` (and any registered
    objective that is not unit-invariant) :data:`POSITION`, since velocity and attitude have
    other units.

    Raises:
        TypeError, ValueError: ``objective`` not a registered name.
    """
    return None if get_objective(objective).unit_invariant else POSITION


def landmark_costs(P: FloatArray, objective: str) -> FloatArray:
    """The cost eq. (11) of posterior covariances ``P`` (B, 9, 9) -> (B,).

    ``"logdet"`` / ``"det"``: ``log det P`` or ``det P``; ``"trace"`` / ``"max_eig"`` (and any
    objective that is not unit-invariant): ``tr`` / ``lambda_max`` of the position block
    ``P[:3, :3]`` (m^2), the A- / E-optimal criteria (Kirchner et al. 2020, eqs. 6, 7).

    Raises:
        TypeError, ValueError: ``objective`` not a registered name.
    """
    idx = landmark_interest(objective)
    block = P if idx is None else P[..., : len(idx), : len(idx)]  # POSITION = (0, 1, 2)
    return get_objective(objective).value(block).reshape(P.shape[:-2])


def landmark_features(h_pred: FloatArray, k: FloatArray | int, horizon: int) -> np.ndarray:
    """Per-landmark features (..., N, 4): sin, cos of the azimuth, elevation / (pi/2), time.

    ``h_pred`` (..., N, 2) predicted (azimuth, elevation); time is ``k / horizon`` with ``k``
    an int or an array over the leading axes (e.g. (B,)).
    """
    az, el = h_pred[..., 0], h_pred[..., 1]
    t = np.broadcast_to(np.asarray(k, dtype=np.float64)[..., None] / horizon, az.shape)
    return np.stack([np.sin(az), np.cos(az), el / (np.pi / 2), t], axis=-1).astype(np.float32)


# -- the filter ----------------------------------------------------------------------------------
def ekf_predict(
    x: FloatArray, P: FloatArray, u: FloatArray, dt: float, accel_sigma: float, gyro_sigma: float
) -> tuple[FloatArray, FloatArray]:
    """Propagate ``B`` filters (eq. 2): ``x <- f(x, u)``, ``P <- F P F^T + Q``.

    ``F = dx+/dx`` and ``Q = G diag(sa^2 I3, sg^2 I3) G^T`` (``G = dx+/du``) are evaluated at the
    current estimates (:func:`~selenv.families.landmarks.models.strapdown_batch`).

    Args:
        x: (B, 9) estimates.
        P: (B, 9, 9) covariances.
        u: (B, 6) measured IMU samples.
        dt: the step (s).
        accel_sigma: accelerometer noise per sample (m/s^2).
        gyro_sigma: gyro noise per sample (rad/s).

    Returns:
        The predicted ``(x, P)``, (B, 9) and (B, 9, 9) (symmetrized), new arrays.
    """
    xp, F, G = strapdown_batch(x, u, dt)
    Pp = F @ P @ np.swapaxes(F, -1, -2) + process_noise_batch(G, accel_sigma, gyro_sigma)
    return xp, 0.5 * (Pp + np.swapaxes(Pp, -1, -2))  # P' = F P F^T + Q, symmetrized


def process_noise_batch(G: FloatArray, accel_sigma: float, gyro_sigma: float) -> FloatArray:
    """``Q = G diag(sa^2 I3, sg^2 I3) G^T`` (B, 9, 9) of ``G = dx+/du`` (B, 9, 6), as computed.

    :func:`~selenv.families.landmarks.models.process_noise` batched, without its final
    symmetrization (the callers symmetrize what they build from it).
    """
    Gs = G * _noise_scale(float(accel_sigma), float(gyro_sigma))  # G diag(sa I3, sg I3)
    return Gs @ np.swapaxes(Gs, -1, -2)


@functools.lru_cache(maxsize=8)
def _noise_scale(accel_sigma: float, gyro_sigma: float) -> FloatArray:
    """Read-only ``(sa, sa, sa, sg, sg, sg)``."""
    scale = np.repeat([accel_sigma, gyro_sigma], 3)
    scale.flags.writeable = False
    return scale


def aoa_candidates(x: FloatArray, landmarks: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Jacobians ``dh/dx`` (B, N, 2, 9) and angles ``h(x)`` (B, N, 2) of every landmark.

    ``Delta = C_e^b (p_n - p)`` (eq. 17), ``h = (atan2(D_y, D_x), atan2(-D_z, rho))`` (eq. 16
    with the sign fix of :mod:`~selenv.families.landmarks.models`), ``H = Psi dDelta/dx`` with
    ``Psi`` of eq. (21), ``dDelta/dp = -C_e^b``, ``dDelta/dv = 0`` and
    ``dDelta/dtheta_i = (dC_b^e/dtheta_i)^T (p_n - p)``.

    Args:
        x: (B, 9) estimates.
        landmarks: (B, N, 3) ENU positions (m).
    """
    B, N = landmarks.shape[:2]
    C, D = dcm_batch(x[:, 6:9])  # C_b^e (B, 3, 3), dC_b^e/dtheta_i (B, 3 angles, 3, 3)
    d = landmarks - x[:, None, 0:3]  # p_n - p, (B, N, 3)
    delta = d @ C  # Delta^T = d^T C_b^e, (B, N, 3)
    Psi = aoa_angles_jacobian(delta)  # (B, N, 2, 3)
    dD = np.stack([d @ D[:, i] for i in range(3)], axis=-1)  # (B, N, 3, 3 angles)
    H = np.zeros((B, N, _M, STATE_DIM))
    H[..., 0:3] = -(Psi @ np.swapaxes(C, -1, -2)[:, None])  # Psi dDelta/dp = -Psi C_e^b
    H[..., 6:9] = Psi @ dD
    return H, aoa_angles(delta)


def ekf_update(
    x: FloatArray,
    P: FloatArray,
    H: FloatArray,
    h: FloatArray,
    z: FloatArray,
    R_landmark: FloatArray,
) -> KalmanUpdate:
    """Joseph-form update of ``B`` filters with ``K`` selected landmarks each (Algorithm 3).

    The innovation is angle-wrapped, ``y = wrap(z - h(x))``; then :func:`joseph_update` with
    the stacked ``H`` (B, 2K, 9) and ``R = blockdiag(R_landmark)`` (2K, 2K).

    Args:
        x: (B, 9) predicted estimates.
        P: (B, 9, 9) predicted covariances.
        H: (B, K, 2, 9) Jacobians of the selected landmarks.
        h: (B, K, 2) their predicted angles.
        z: (B, K, 2) their measurements.
        R_landmark: (2, 2) one landmark's noise covariance.

    Returns:
        The batched :class:`~selenv.core.kalman.KalmanUpdate` (``x`` (B, 9), ``P`` (B, 9, 9)).
    """
    B, K = H.shape[:2]
    H2 = H.reshape(B, K * _M, STATE_DIM)  # (B, 2K, 9)
    y = wrap_angle(z - h).reshape(B, K * _M)  # y = wrap(z - h(x))
    return joseph_update(x, P, H2, y, _selection_noise(R_landmark, K))


def joseph_update(
    x: FloatArray, P: FloatArray, H: FloatArray, y: FloatArray, R: FloatArray
) -> KalmanUpdate:
    """Kalman update of ``B`` filters in Joseph form, given the innovations ``y`` (B, m).

    The equations of :func:`~selenv.core.kalman.kf_update`: ``S = H P H^T + R`` (symmetrized),
    ``K = P H^T S^-1`` (from ``S K^T = H P`` by the Cholesky factor ``S = L L^T``),
    ``x' = x + K y``, ``P' = (I - K H) P (I - K H)^T + K R K^T`` (symmetrized) and
    ``log N(y; 0, S) = -(|L^-1 y|^2 + log det S + m log 2 pi) / 2``; batched over ``B``
    without re-validating the (internal, well-formed) arrays.

    Args:
        x: (B, n) prior means.
        P: (B, n, n) prior covariances.
        H: (B, m, n) measurement matrices.
        y: (B, m) innovations.
        R: (m, m) or (B, m, m) measurement noise.

    Raises:
        ValueError: an ``S`` that is not positive definite.
    """
    HP = H @ P  # (B, m, n)
    S = HP @ np.swapaxes(H, -1, -2) + R
    S = 0.5 * (S + np.swapaxes(S, -1, -2))  # S = H P H^T + R
    L = cholesky_spd(S, "S = H P H^T + R")
    Ly = np.linalg.solve(L, np.concatenate([HP, y[..., None]], axis=-1))  # L^-1 [H P, y]
    KT = np.linalg.solve(np.swapaxes(L, -1, -2), Ly[..., :-1])  # K^T = S^-1 H P
    w = Ly[..., -1]  # L^-1 y
    K = np.swapaxes(KT, -1, -2)
    x_post = x + (K @ y[..., None])[..., 0]  # x' = x + K y
    I_KH = np.eye(x.shape[-1]) - K @ H
    Pp = I_KH @ P @ np.swapaxes(I_KH, -1, -2) + K @ R @ KT  # Joseph form
    Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
    logdet_S = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    ll = -0.5 * (np.sum(w * w, axis=-1) + logdet_S + y.shape[-1] * _LOG_2PI)
    return KalmanUpdate(x_post, Pp, y, S, K, ll)


def _selection_noise(R_landmark: FloatArray, K: int) -> FloatArray:
    """``blockdiag(R_landmark, ..., R_landmark)`` (2K, 2K)."""
    return np.kron(np.eye(K), R_landmark).astype(np.float64, copy=False)


def whiten_landmarks(H: FloatArray, R_landmark: FloatArray) -> FloatArray:
    """``G_k = L^-1 H_k`` with ``R_landmark = L L^T`` (eq. 4), (..., 2, 9) -> (..., 2, 9).

    One triangular system for every landmark of every episode (``R`` is shared).
    """
    L = cholesky_spd(R_landmark, "R_landmark")
    rows = np.moveaxis(H, -2, 0)  # (2, ..., 9)
    G = np.asarray(np.linalg.solve(L, rows.reshape(_M, -1)), dtype=np.float64)
    return np.moveaxis(G.reshape(rows.shape), 0, -2)


def inv_lower(L: FloatArray) -> FloatArray:
    """``L^-1`` (B, n, n) of non-singular lower-triangular factors ``L`` (B, n, n).

    Forward substitution row by row (LAPACK ``dtrtri``'s recurrence), batched over ``B``:
    ``X[i, i] = 1 / L[i, i]`` and ``X[i, :i] = -L[i, :i] X[:i, :i] / L[i, i]``. Used where the
    inverse factor itself is propagated (``L'^-1 = C^-1 L^-1``), never to solve a system.
    """
    n = L.shape[-1]
    X = np.zeros_like(L)
    d = 1.0 / np.diagonal(L, axis1=1, axis2=2)
    X[:, 0, 0] = d[:, 0]
    for i in range(1, n):
        X[:, i, :i] = -(L[:, i : i + 1, :i] @ X[:, :i, :i])[:, 0] * d[:, i, None]
        X[:, i, i] = d[:, i]
    return X


# -- the gain state of a filter step -------------------------------------------------------------
@dataclass(frozen=True)
class GainSpec:
    """What the gain state scores: the env's ``solver_objective`` and its ``interest``.

    Attributes:
        objective: a registered objective name (``"logdet"`` or another, e.g. ``"trace"``).
        interest: state indices scored (``None``: all).
    """

    objective: str
    interest: tuple[int, ...] | None

    @property
    def logdet(self) -> bool:
        """Whether the gains are the log-det gains (eq. 9) rather than a downdate."""
        return self.objective == "logdet"


@dataclass
class SelectionBatch:
    """The gain states of ``B`` filter steps (the picks of one step, over every landmark).

    For the information ``A = Q0 + sum_{k in S} G_k^T G_k`` with ``Q0 = P_pred^-1``:

    Attributes:
        G: (B, N, 2, 9) whitened Jacobians ``R^-1/2 H``.
        Q0: (B, 9, 9) the prior information ``P_pred^-1``.
        Linv: (B, 9, 9) ``L^-1`` with ``A = L L^T`` (so ``A^-1 = L^-T L^-1``).
        Z: (B, N, 2, 9) ``G_k L^-T``: every landmark whitened in the current information.
        gains: (B, N) marginal gain of every landmark (log det, or the objective's downdate).
        selected: (B, N) bool, the landmarks picked in this step.
        objective: (B,) ``f(S)`` of the picks (eq. 9 for log det, ``c(P0) - c(P_S)`` else).
        crit0: (B,) ``c(E P_pred E^T)`` (objectives other than log det).
    """

    G: FloatArray
    Q0: FloatArray
    Linv: FloatArray
    Z: FloatArray
    gains: FloatArray
    selected: np.ndarray
    objective: FloatArray
    crit0: FloatArray

    @classmethod
    def empty(cls, B: int, N: int) -> SelectionBatch:
        """Zero-filled arrays for ``B`` episodes of ``N`` landmarks."""
        return cls(
            G=np.zeros((B, N, _M, STATE_DIM)),
            Q0=np.zeros((B, STATE_DIM, STATE_DIM)),
            Linv=np.zeros((B, STATE_DIM, STATE_DIM)),
            Z=np.zeros((B, N, _M, STATE_DIM)),
            gains=np.zeros((B, N)),
            selected=np.zeros((B, N), dtype=np.bool_),
            objective=np.zeros(B),
            crit0=np.zeros(B),
        )

    def P(self, rows: np.ndarray | slice) -> FloatArray:
        """``A^-1 = L^-T L^-1`` (g, 9, 9) of the given rows: the CRLB of the picks."""
        Linv = self.Linv[rows]
        return np.swapaxes(Linv, -1, -2) @ Linv


def open_selection(
    sel: SelectionBatch,
    rows: np.ndarray | slice,
    P_pred: FloatArray,
    G: FloatArray,
    spec: GainSpec,
) -> None:
    """Start the gain states of ``rows`` at new predictions: ``Q0 = P_pred^-1``, no pick.

    ``Q0`` from the Cholesky factor of ``P_pred`` (a triangular solve, no inverse), ``L0`` its
    Cholesky factor, ``Z = G L0^-T`` and the gains of every landmark given ``P_pred``.

    Args:
        sel: the batch (written in place).
        rows: the episodes (g,) to open.
        P_pred: (g, 9, 9) predicted covariances.
        G: (g, N, 2, 9) whitened Jacobians.
        spec: what the gains score.
    """
    L = cholesky_spd(P_pred, "P_pred")
    Linv = inv_lower(L)
    Q0 = np.swapaxes(Linv, -1, -2) @ Linv  # P_pred^-1 from its Cholesky factor
    Q0 = 0.5 * (Q0 + np.swapaxes(Q0, -1, -2))
    L0 = cholesky_spd(Q0, "Q0")  # A = Q0 = L0 L0^T
    L0inv = inv_lower(L0)
    sel.G[rows] = G
    sel.Q0[rows] = Q0
    sel.Linv[rows] = L0inv
    sel.Z[rows] = G @ np.swapaxes(L0inv, -1, -2)[:, None]  # Z_k = G_k L0^-T
    sel.selected[rows] = False
    sel.objective[rows] = 0.0
    if not spec.logdet:
        sel.crit0[rows] = _criterion(P_pred, spec)
    _refresh_gains(sel, rows, spec)


def add_picks(sel: SelectionBatch, rows: np.ndarray, picks: np.ndarray, spec: GainSpec) -> None:
    """Add landmark ``picks[i]`` (not yet selected) to the gain state of episode ``rows[i]``.

    The block update through the whitened rows (:class:`~selenv.core.information.LogDetGainState`):
    with ``A = L L^T`` and ``Z_j = G_j L^-T``, ``A + G_j^T G_j = L (I + Z_j^T Z_j) L^T``, so
    ``L' = L C`` with ``C = chol(I + Z_j^T Z_j)``, ``Z' = Z C^-T``, ``L'^-1 = C^-1 L^-1``, and
    the log-det gain is ``log det(I + Z_j^T Z_j) = 2 sum log diag C`` (eq. 9).

    Args:
        sel: the batch (written in place).
        rows: (g,) distinct episodes.
        picks: (g,) their landmarks.
        spec: what the gains score.
    """
    eye = np.eye(STATE_DIM)
    Zj = sel.Z[rows, picks]  # (g, 2, 9)
    M = eye + np.swapaxes(Zj, -1, -2) @ Zj
    C = cholesky_spd(0.5 * (M + np.swapaxes(M, -1, -2)), "I + Z_j^T Z_j")
    Cinv = inv_lower(C)  # the inverse factor itself is propagated
    sel.Linv[rows] = Cinv @ sel.Linv[rows]  # L'^-1 = C^-1 L^-1
    sel.Z[rows] = sel.Z[rows] @ np.swapaxes(Cinv, -1, -2)[:, None]  # Z' = Z C^-T
    sel.selected[rows, picks] = True
    if spec.logdet:
        sel.objective[rows] += 2.0 * np.sum(np.log(np.diagonal(C, axis1=-2, axis2=-1)), -1)
    else:
        sel.objective[rows] = sel.crit0[rows] - _criterion(sel.P(rows), spec)
    _refresh_gains(sel, rows, spec)


def _criterion(P: FloatArray, spec: GainSpec) -> FloatArray:
    """``c(E P E^T)`` (g,) of covariances ``P`` (g, 9, 9)."""
    idx = spec.interest
    block = P if idx is None else P[:, np.asarray(idx)[:, None], np.asarray(idx)[None, :]]
    return get_objective(spec.objective).value(block).reshape(P.shape[0])


def _refresh_gains(sel: SelectionBatch, rows: np.ndarray | slice, spec: GainSpec) -> None:
    """Marginal gains (g, N) of every landmark given the current information of ``rows``.

    Log det: ``log det(I + S_k)`` with ``S_k = Z_k Z_k^T`` (2 x 2). Other objectives: the
    Woodbury downdate of :func:`~selenv.core.objectives.criterion_gains`, with ``B_k = G_k P``,
    ``I + G_k P G_k^T = C_k C_k^T``, ``V_k = C_k^-1 B_k E^T`` and
    ``gain = c(E P E^T) - c(E P E^T - V_k^T V_k)``, clipped at 0.
    """
    if spec.logdet:
        Z = sel.Z[rows]
        g, N = Z.shape[:2]
        S = Z @ np.swapaxes(Z, -1, -2)  # S_k = Z_k Z_k^T, (g, N, 2, 2)
        sel.gains[rows] = block_logdet_gains(S.reshape(g * N, _M, _M)).reshape(g, N)
        return
    obj = get_objective(spec.objective)
    G, P = sel.G[rows], sel.P(rows)
    g, N = G.shape[:2]
    Bk = G @ P[:, None]  # G_k P, (g, N, 2, 9)
    S = Bk @ np.swapaxes(G, -1, -2)  # S_k = G_k P G_k^T
    idx = None if spec.interest is None else np.asarray(spec.interest)
    W = Bk if idx is None else Bk[..., idx]  # G_k P E^T
    Ck = np.linalg.cholesky(S + np.eye(_M))  # I + S_k = C_k C_k^T
    V = np.linalg.solve(Ck, W)  # C_k^-1 W_k
    M0 = P if idx is None else P[:, idx[:, None], idx[None, :]]
    if obj.downdate is None:  # generic: c(M0) - c(M0 - V^T V), batched
        gains = obj.downdate_gain(M0[:, None], V)
    else:  # a closed form takes one M0
        gains = np.stack([obj.downdate_gain(M0[b], V[b]) for b in range(g)])
    sel.gains[rows] = np.maximum(np.broadcast_to(gains, (g, N)), 0.0)


# -- the observation -----------------------------------------------------------------------------
def write_observation(
    out: dict[str, np.ndarray],
    rows: np.ndarray | slice,
    sel: SelectionBatch,
    budget_fraction: FloatArray,
) -> None:
    """Write the ``FIMSelection-v1`` observation of ``rows`` into ``out`` (batched arrays).

    ``gain`` (B, N) the gains with picked landmarks at 0, ``whitened`` (B, N, 18) ``Z``,
    ``selected`` / ``action_mask`` (B, N) int8, ``budget_left`` (B, 1) ``budget_fraction``
    (g,); ``features`` (B, N, 4) is written by the caller (it changes once per filter step).
    """
    selected = sel.selected[rows]
    Z = sel.Z[rows]
    out["gain"][rows] = np.where(selected, 0.0, sel.gains[rows])
    out["whitened"][rows] = Z.reshape(*Z.shape[:2], -1)
    out["selected"][rows] = selected
    out["action_mask"][rows] = ~selected
    out["budget_left"][rows, 0] = budget_fraction
