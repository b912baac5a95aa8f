"""Angles-only UAV navigation with landmark selection (Soubaras & Chahbazian 2023, Sec. IV).

A UAV flies at about 1000 m and 50 m/s; an EKF on the state ``x = (p, v, theta)`` (9,)
propagates with a 10 Hz IMU and, at every step, may update with the angles of arrival of only
``K`` of the ``N`` ground landmarks (Algorithm 3). Models and conventions (ENU / FRD frames,
z-y-x Euler angles, the elevation sign fix of eq. 16, the error state of eq. 20) are in
:mod:`selenv.families.landmarks.models`.

**Trajectory** (a Fig. 3-like flight, deterministic): start at ``(0, 0, altitude)`` with speed
``speed`` on heading ``heading_deg``, then cycle through ``legs`` of ``(duration s, turn rate
deg/s)``: straight legs and coordinated level turns (bank ``atan(V w / g)`` reached at a
limited roll rate, no side force). The true IMU is computed by a guidance law from the true
state at each step (turn, altitude and speed hold), and the truth is the integration of
:func:`~selenv.families.landmarks.models.propagate` with that IMU, so the filter's model is
exact and only the noises differ. Default: 5 s straight, 10 s right turn at 6 deg/s, 5 s
straight, 10 s left turn (30 s = the 300-step horizon), an S-shaped track of about 1.5 km.

**Landmarks** are drawn uniformly on the ground (height in ``landmark_height``) in the track's
bounding box widened by ``landmark_margin`` (about 9 x 8 km by default), rejecting any landmark
that comes within ``min_off_nadir_deg`` of the body z axis along the true trajectory (where
the azimuth is undefined). A user layout ``landmarks=(N, 3)`` is used as given.

**Random draws** (all from the generator given to :func:`make_landmark_problem`, in this
order): the landmark layout, the IMU noise (T, 6), the measurement noise (T, N, 2) and the
initial estimation error. Every selection policy thus sees the same noise for the same seed.
Step ``k`` of the filter (``k = 0 .. T-1``) propagates with IMU sample ``k`` from ``x_k`` to
``x_{k+1}`` and may then use ``measurements[k]``, taken at the true state ``k + 1``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.crlb import pcrlb_step_covariance
from selenv.core.information import block_logdet_gains, whiten
from selenv.core.kalman import KalmanUpdate
from selenv.core.linalg import FloatArray, logdet_spd, validate_spd
from selenv.families.landmarks.batched import aoa_candidates, ekf_predict, ekf_update
from selenv.families.landmarks.flight import body_vectors_along, draw_layout, fly
from selenv.families.landmarks.models import (
    GRAVITY,
    STATE_DIM,
    aoa_angles,
    euler_to_dcm,
    measurement_jacobian,
    process_noise,
    propagation_jacobians,
    wrap_angle,
)
from selenv.scenarios.validation import (
    ArgumentTypeError,
    check_integer,
    check_real,
    check_reals,
    describe,
    interval,
)

__all__ = [
    "MAX_LANDMARKS",
    "MAX_STEPS",
    "RANGES",
    "EpisodeDraws",
    "LandmarkConfig",
    "LandmarkEKF",
    "LandmarkProblem",
    "ScenarioStatic",
    "check_selection",
    "crlb_reference",
    "draw_episodes",
    "make_landmark_problem",
    "scenario_static",
    "selection_logdet_gain",
]

_DEG = np.pi / 180.0


#: largest number of landmarks and of filter steps (every noise is drawn at reset)
MAX_LANDMARKS = 200
MAX_STEPS = 100_000
#: largest bank angle of a turn (deg): a coordinated turn at ``speed`` needs ``atan(V w / g)``
MAX_BANK_DEG = 60.0

#: valid range of every real-valued :class:`LandmarkConfig` field: ``(low, high, unit)``
RANGES: dict[str, tuple[float, float, str]] = {
    "dt": (1e-3, 1.0, "s"),
    "gyro_sigma_deg_per_h": (1e-4, 1e4, "deg/h"),
    "accel_sigma": (1e-6, 1.0, "m/s^2"),
    "altitude": (200.0, 20_000.0, "m"),
    "speed": (1.0, 340.0, "m/s"),
    "heading_deg": (-360.0, 360.0, "deg"),
    "max_roll_rate_deg": (1.0, 180.0, "deg/s"),
    "landmark_margin": (0.0, 1e5, "m"),
    "aoa_sigma_deg": (1e-4, 30.0, "deg"),
    "leg duration": (1e-2, 1e5, "s"),
    "leg turn rate": (-30.0, 30.0, "deg/s"),
    "landmark_height": (-500.0, 9000.0, "m"),
    "landmarks": (-1e6, 1e6, "m"),
}
#: valid range of each entry of ``init_sigma`` (attitude, velocity, position)
INIT_SIGMA_RANGES: tuple[tuple[float, float, str], ...] = (
    (1e-4, 30.0, "deg"),
    (1e-4, 100.0, "m/s"),
    (1e-2, 1e4, "m"),
)


def _pair(value: Any, name: str, size: int, what: str) -> list[Any]:
    """``value`` as a list of ``size`` items (a tuple, list or 1-D array)."""
    ok = isinstance(value, tuple | list) or (isinstance(value, np.ndarray) and value.ndim == 1)
    if not ok or len(value) != size:
        raise ArgumentTypeError(f"{name} must be {what}, got {describe(value)}")
    return list(value)


def _check_layout(landmarks: Any, n: int) -> FloatArray:
    """A user layout: a finite real ``(n, 3)`` array of ENU positions in ``[-1e6, 1e6]`` m."""
    low, high, unit = RANGES["landmarks"]
    try:
        raw = np.asarray(landmarks)
    except ValueError as exc:  # ragged nested sequences
        raise ValueError(
            f"landmarks must be a real (n_landmarks, 3) array, got {describe(landmarks)}"
        ) from exc
    if raw.dtype.kind not in "iuf":
        raise ArgumentTypeError(
            f"landmarks must be a real (n_landmarks, 3) array (m), got {describe(landmarks)}"
        )
    lm = raw.astype(np.float64)
    if lm.shape != (n, 3):
        raise ValueError(f"landmarks must have shape (n_landmarks, 3) = ({n}, 3), got {lm.shape}")
    bad = ~(np.isfinite(lm) & (np.abs(lm) <= high))
    if np.any(bad):
        row = int(np.argwhere(bad)[0, 0])
        raise ValueError(
            f"landmarks must be finite, in {interval(low, high)} {unit}, but landmarks[{row}] = "
            f"{lm[row].tolist()}"
        )
    return lm


@dataclass(frozen=True, kw_only=True)
class LandmarkConfig:
    """Parameters of the landmark-selection scenario (defaults: the paper's Table I).

    Every field is validated: a wrong type is a ``TypeError`` (also a ``ValueError``), a value
    outside its range (:data:`RANGES`) a ``ValueError``, naming the field and the range.

    Attributes:
        n_landmarks: number of landmarks ``N``, an int in ``[1, MAX_LANDMARKS]`` (200).
        horizon: number of filter steps ``T`` (at ``1 / dt`` Hz), in ``[1, MAX_STEPS]`` (1e5).
        dt: IMU and filter step (s), in ``[1e-3, 1]``.
        gyro_sigma_deg_per_h: gyro noise (deg/h, 1 sigma per sample), in ``[1e-4, 1e4]``.
        accel_sigma: accelerometer noise (m/s^2, 1 sigma per sample), in ``[1e-6, 1]``.
        aoa_sigma_deg: angle-of-arrival noise ``(azimuth, elevation)`` (deg), each in
            ``[1e-4, 30]``.
        init_sigma: initial error ``(attitude deg, velocity m/s, position m)``, per axis, in
            ``[1e-4, 30]``, ``[1e-4, 100]``, ``[1e-2, 1e4]``.
        altitude: initial and held altitude (m), in ``[200, 20000]``.
        speed: ground speed (m/s), in ``[1, 340]``.
        heading_deg: initial heading, clockwise from North (deg), in ``[-360, 360]``.
        legs: ``((duration s, turn rate deg/s), ...)`` cycled over the horizon (> 0: right),
            at least one; durations in ``[1e-2, 1e5]``, turn rates in ``[-30, 30]`` and
            at most a ``MAX_BANK_DEG`` (60 deg) bank at ``speed``.
        max_roll_rate_deg: roll-rate limit when entering or leaving a turn (deg/s), in
            ``[1, 180]``.
        landmark_margin: widening of the track's bounding box for the landmark layout (m), in
            ``[0, 1e5]``; without a user layout, at least :meth:`min_landmark_margin` (the
            distance from the track beyond which a landmark is ``min_off_nadir_deg`` off the
            body z axis at the largest bank of the legs), so that a layout always exists.
        landmark_height: ``(low, high)`` height range of the drawn landmarks (m), both in
            ``[-500, 9000]``, ``low <= high < altitude``.
        min_off_nadir_deg: drawn landmarks stay at least this far from the body z axis, in
            ``[0, 90)``.
        landmarks: optional user layout ``(n_landmarks, 3)`` in ENU (m), finite, coordinates in
            ``[-1e6, 1e6]``, used as given (stored as a read-only float array).
    """

    n_landmarks: int = 30
    horizon: int = 300
    dt: float = 0.1
    gyro_sigma_deg_per_h: float = 2.0
    accel_sigma: float = 1e-3
    aoa_sigma_deg: tuple[float, float] = (0.6, 0.6)
    init_sigma: tuple[float, float, float] = (0.6, 1.0, 50.0)
    altitude: float = 1000.0
    speed: float = 50.0
    heading_deg: float = 90.0
    legs: tuple[tuple[float, float], ...] = ((5.0, 0.0), (10.0, 6.0), (5.0, 0.0), (10.0, -6.0))
    max_roll_rate_deg: float = 15.0
    landmark_margin: float = 4000.0
    landmark_height: tuple[float, float] = (0.0, 100.0)
    min_off_nadir_deg: float = 5.0
    landmarks: Any = None

    def __post_init__(self) -> None:
        put = object.__setattr__
        n = check_integer(self.n_landmarks, "n_landmarks", 1, MAX_LANDMARKS)
        put(self, "n_landmarks", n)
        put(self, "horizon", check_integer(self.horizon, "horizon", 1, MAX_STEPS))
        for name in ("dt", "gyro_sigma_deg_per_h", "accel_sigma", "altitude", "speed",
                     "heading_deg", "max_roll_rate_deg", "landmark_margin"):  # fmt: skip
            low, high, unit = RANGES[name]
            put(self, name, check_real(getattr(self, name), name, low, high, unit=unit))
        low, high, unit = RANGES["aoa_sigma_deg"]
        put(self, "aoa_sigma_deg", check_reals(self.aoa_sigma_deg, "aoa_sigma_deg", 2, low, high,
                                               unit=unit))  # fmt: skip
        init = _pair(self.init_sigma, "init_sigma", 3, "3 numbers (attitude, velocity, position)")
        put(self, "init_sigma", tuple(
            check_real(v, f"init_sigma[{i}]", low, high, unit=unit)
            for i, (v, (low, high, unit)) in enumerate(zip(init, INIT_SIGMA_RANGES, strict=True))
        ))  # fmt: skip
        low, high, unit = RANGES["landmark_height"]
        lo, hi = check_reals(self.landmark_height, "landmark_height", 2, low, high, unit=unit)
        if not lo <= hi < self.altitude:
            raise ValueError(
                f"landmark_height must be (low, high) with low <= high < altitude = "
                f"{self.altitude:g} m, got {(lo, hi)}"
            )
        put(self, "landmark_height", (lo, hi))
        nadir = check_real(self.min_off_nadir_deg, "min_off_nadir_deg", 0.0, 90.0, high_open=True,
                           unit="deg")  # fmt: skip
        put(self, "min_off_nadir_deg", nadir)
        put(self, "legs", self._legs())
        if self.landmarks is not None:
            layout = _check_layout(self.landmarks, n)
            layout.setflags(write=False)
            put(self, "landmarks", layout)
        elif self.landmark_margin < (need := self.min_landmark_margin()):
            raise ValueError(
                f"landmark_margin = {self.landmark_margin:g} m leaves no room for landmarks off "
                f"nadir: at altitude {self.altitude:g} m, landmark_height low "
                f"{self.landmark_height[0]:g} m, min_off_nadir_deg {self.min_off_nadir_deg:g} "
                f"and banks up to {self.max_bank_deg():.0f} deg, landmarks must be able to lie "
                f"{need:.0f} m from the track: use landmark_margin >= {need:.0f} (or lower "
                "min_off_nadir_deg or altitude)"
            )

    def max_bank_deg(self) -> float:
        """Largest bank angle of the legs at ``speed`` (deg): ``atan(V |w| / g)``."""
        rate = max(abs(float(leg[1])) for leg in self.legs)
        return float(np.degrees(np.arctan(self.speed * rate * _DEG / GRAVITY)))

    def min_landmark_margin(self) -> float:
        """Smallest ``landmark_margin`` (m) for which a drawn layout always exists.

        ``(altitude - landmark_height[0]) tan(min(min_off_nadir_deg + max bank, 89 deg))``:
        beyond this horizontal distance from the track a landmark is ``min_off_nadir_deg`` off
        the body z axis whatever the bank.
        """
        angle = min(float(self.min_off_nadir_deg) + self.max_bank_deg(), 89.0)
        return float((self.altitude - self.landmark_height[0]) * np.tan(angle * _DEG))

    def _legs(self) -> tuple[tuple[float, float], ...]:
        """The validated legs (durations, turn rates and the bank limit at ``speed``)."""
        if not isinstance(self.legs, tuple | list) or len(self.legs) == 0:
            raise ArgumentTypeError(
                "legs must hold at least one (duration s, turn rate deg/s) pair, "
                f"got {describe(self.legs)}"
            )
        (d_lo, d_hi, d_unit), (w_lo, w_hi, w_unit) = RANGES["leg duration"], RANGES["leg turn rate"]
        out = []
        for i, leg in enumerate(self.legs):
            pair = _pair(leg, f"legs[{i}]", 2, "(duration s, turn rate deg/s)")
            duration = check_real(pair[0], f"legs[{i}] duration", d_lo, d_hi, unit=d_unit)
            rate = check_real(pair[1], f"legs[{i}] turn rate", w_lo, w_hi, unit=w_unit)
            bank = float(np.degrees(np.arctan(abs(self.speed * rate * _DEG) / GRAVITY)))
            if bank > MAX_BANK_DEG:
                raise ValueError(
                    f"legs[{i}] turn rate {rate:g} deg/s needs a bank of {bank:.0f} deg at "
                    f"speed = {self.speed:g} m/s; at most {MAX_BANK_DEG:g} deg is supported"
                )
            out.append((duration, rate))
        return tuple(out)

    @property
    def gyro_sigma(self) -> float:
        """Gyro noise in rad/s."""
        return float(self.gyro_sigma_deg_per_h) * _DEG / 3600.0

    @property
    def aoa_sigma(self) -> FloatArray:
        """``(azimuth, elevation)`` noise in rad, (2,)."""
        return np.asarray(self.aoa_sigma_deg, dtype=np.float64) * _DEG

    @property
    def P0(self) -> FloatArray:
        """Initial covariance ``diag(s_p^2 I3, s_v^2 I3, s_att^2 I3)`` in state order (9, 9)."""
        att, vel, pos = (float(s) for s in self.init_sigma)
        return np.diag(np.repeat([pos**2, vel**2, (att * _DEG) ** 2], 3))


@dataclass(frozen=True, kw_only=True, eq=False)
class LandmarkProblem:
    """One seeded realisation (all arrays read-only); ``T = horizon``, ``N = n_landmarks``.

    Attributes:
        config: the :class:`LandmarkConfig`.
        landmarks: (N, 3) ENU landmark positions (m).
        states: (T + 1, 9) true states ``x_0 .. x_T``.
        imu_true: (T, 6) true IMU ``(f_b, w_b)``, with
            ``states[k + 1] = propagate(states[k], imu_true[k], dt)``.
        imu_measured: (T, 6) ``imu_true + noise``, what the filter propagates with.
        F_true: (T, 9, 9) ``dx+/dx`` on the truth with the true IMU.
        Q: (T, 9, 9) process noise ``G imu_cov G^T`` on the truth (PSD, rank 6).
        imu_cov: (6, 6) ``diag(sa^2 I3, sg^2 I3)``.
        measurement_noise: (T, N, 2) pre-drawn AOA noise.
        measurements: (T, N, 2) ``wrap(h(states[k+1]) + measurement_noise[k])``.
        R_landmark: (2, 2) ``diag(s_az^2, s_el^2)``, one landmark's noise covariance.
        x0_hat: (9,) initial estimate, ``states[0] + e`` with ``e ~ N(0, P0)``.
        P0: (9, 9) initial covariance (Table I).
    """

    config: LandmarkConfig
    landmarks: FloatArray
    states: FloatArray
    imu_true: FloatArray
    imu_measured: FloatArray
    F_true: FloatArray
    Q: FloatArray
    imu_cov: FloatArray
    measurement_noise: FloatArray
    measurements: FloatArray
    R_landmark: FloatArray
    x0_hat: FloatArray
    P0: FloatArray

    @property
    def n_landmarks(self) -> int:
        """Number of landmarks ``N``."""
        return int(self.landmarks.shape[0])

    @property
    def horizon(self) -> int:
        """Number of filter steps ``T``."""
        return int(self.imu_true.shape[0])

    @property
    def dt(self) -> float:
        """Filter step (s)."""
        return float(self.config.dt)

    def selection_noise(self, K: int) -> FloatArray:
        """``blockdiag(R_landmark, ..., R_landmark)`` for ``K`` landmarks, (2K, 2K)."""
        return np.kron(np.eye(K), self.R_landmark).astype(np.float64, copy=False)


def _readonly(**arrays: FloatArray) -> dict[str, FloatArray]:
    for a in arrays.values():
        a.setflags(write=False)
    return arrays


#: deterministic flights by :func:`_flight_key`: (states, imu_true, F_true, Q), read-only
_FLIGHTS: dict[tuple[str, ...], tuple[FloatArray, FloatArray, FloatArray, FloatArray]] = {}
_MAX_FLIGHTS = 8


def _flight_key(cfg: LandmarkConfig) -> tuple[str, ...]:
    """Every field the true flight, its Jacobians and ``Q`` depend on (``repr``: -0.0 != 0.0)."""
    legs = tuple(repr(float(v)) for leg in cfg.legs for v in leg)
    scalars = (cfg.horizon, cfg.dt, cfg.speed, cfg.heading_deg, cfg.altitude,
               cfg.max_roll_rate_deg, cfg.accel_sigma, cfg.gyro_sigma)  # fmt: skip
    return (*(repr(float(v)) for v in scalars), "legs", *legs)


def _flight(cfg: LandmarkConfig) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """True states, IMU, ``F_true`` and ``Q`` of ``cfg``'s flight, computed once per config.

    None of them depends on the generator (the flight is a deterministic guidance law), so a
    reset reuses them (read-only arrays, shared between problems) instead of re-flying.
    """
    key = _flight_key(cfg)
    hit = _FLIGHTS.get(key)
    if hit is not None:
        return hit
    states, imu_true = fly(cfg)
    T, dt = int(cfg.horizon), float(cfg.dt)
    F_true, Q = np.empty((T, STATE_DIM, STATE_DIM)), np.empty((T, STATE_DIM, STATE_DIM))
    for k in range(T):
        F_true[k], G = propagation_jacobians(states[k], imu_true[k], dt)
        Q[k] = process_noise(G, float(cfg.accel_sigma), cfg.gyro_sigma)
    for a in (states, imu_true, F_true, Q):
        a.setflags(write=False)
    if len(_FLIGHTS) >= _MAX_FLIGHTS:
        _FLIGHTS.pop(next(iter(_FLIGHTS)))  # oldest first
    _FLIGHTS[key] = (states, imu_true, F_true, Q)
    return _FLIGHTS[key]


@dataclass(frozen=True, eq=False)
class ScenarioStatic:
    """What a config fixes for every seed, computed once (:func:`scenario_static`, read-only).

    Attributes:
        states: (T + 1, 9) true states; imu_true: (T, 6); F_true, Q: (T, 9, 9) (the flight).
        dcm: (T + 1, 3, 3) ``C_b^e`` along the true states.
        imu_sigma: (6,) ``(sa, sa, sa, sg, sg, sg)``; imu_cov: (6, 6) its square.
        aoa_sigma: (2,) angle noise (rad); R_landmark: (2, 2) ``diag(aoa_sigma^2)``.
        P0: (9, 9) initial covariance; init_std: (9,) ``sqrt(diag P0)``.
        landmarks: (N, 3) the user layout, or ``None`` (drawn per seed).
        angles: (T, N, 2) noise-free angles of the user layout along the truth, or ``None``.
    """

    states: FloatArray
    imu_true: FloatArray
    F_true: FloatArray
    Q: FloatArray
    dcm: FloatArray
    imu_sigma: FloatArray
    imu_cov: FloatArray
    aoa_sigma: FloatArray
    R_landmark: FloatArray
    P0: FloatArray
    init_std: FloatArray
    landmarks: FloatArray | None
    angles: FloatArray | None


#: :class:`ScenarioStatic` by :func:`_config_key` (oldest dropped first)
_STATIC: dict[tuple[Any, ...], ScenarioStatic] = {}


def _config_key(cfg: LandmarkConfig) -> tuple[Any, ...]:
    """Every field of ``cfg`` as a hashable key (``repr`` of floats, the layout's bytes)."""
    out: list[Any] = [*_flight_key(cfg), cfg.n_landmarks]
    for name in ("aoa_sigma_deg", "init_sigma", "landmark_height"):
        out += [name, *(repr(float(v)) for v in getattr(cfg, name))]
    out += [repr(float(cfg.landmark_margin)), repr(float(cfg.min_off_nadir_deg))]
    lm = cfg.landmarks
    out.append(None if lm is None else (lm.shape, lm.tobytes()))
    return tuple(out)


def scenario_static(cfg: LandmarkConfig) -> ScenarioStatic:
    """The seed-independent part of ``cfg``'s scenario, computed once per config (read-only).

    The flight (:func:`_flight`), ``C_b^e`` along it, the noise scales, ``P0``, and for a user
    layout the noise-free angles of arrival along the truth (then a reset only adds noise).
    """
    key = _config_key(cfg)
    hit = _STATIC.get(key)
    if hit is not None:
        return hit
    states, imu_true, F_true, Q = _flight(cfg)
    imu_sigma = np.repeat([float(cfg.accel_sigma), cfg.gyro_sigma], 3)
    P0 = cfg.P0
    dcm = euler_to_dcm(states[:, 6:9])
    landmarks = angles = None
    if cfg.landmarks is not None:
        landmarks = _check_layout(cfg.landmarks, int(cfg.n_landmarks))
        angles = aoa_angles(body_vectors_along(states[1:], landmarks, dcm[1:]))
    arrays = _readonly(
        dcm=dcm,
        imu_sigma=imu_sigma,
        imu_cov=np.diag(imu_sigma**2),
        aoa_sigma=cfg.aoa_sigma,
        R_landmark=np.diag(cfg.aoa_sigma**2),
        P0=P0,
        init_std=np.sqrt(np.diag(P0)),
    )
    if landmarks is not None and angles is not None:
        arrays.update(_readonly(landmarks=landmarks, angles=angles))
    static = ScenarioStatic(
        states=states,
        imu_true=imu_true,
        F_true=F_true,
        Q=Q,
        landmarks=arrays.pop("landmarks", None),
        angles=arrays.pop("angles", None),
        **arrays,
    )
    if len(_STATIC) >= _MAX_FLIGHTS:
        _STATIC.pop(next(iter(_STATIC)))  # oldest first
    _STATIC[key] = static
    return static


@dataclass(frozen=True, eq=False)
class EpisodeDraws:
    """The seeded part of ``g`` episodes (:func:`draw_episodes`), leading axis ``g``.

    Attributes:
        landmarks: (g, N, 3); imu_measured: (g, T, 6); measurement_noise, measurements:
            (g, T, N, 2); x0_hat: (g, 9) (see :class:`LandmarkProblem`).
    """

    landmarks: FloatArray
    imu_measured: FloatArray
    measurement_noise: FloatArray
    measurements: FloatArray
    x0_hat: FloatArray


def draw_episodes(cfg: LandmarkConfig, rngs: Sequence[np.random.Generator]) -> EpisodeDraws:
    """Draw ``g = len(rngs)`` episodes, one per generator, then finish them batched.

    Each generator is used exactly as :func:`make_landmark_problem` uses its own, in the order
    of the module docstring (layout, IMU noise (T, 6), AOA noise (T, N, 2), initial error (9,));
    the noisy IMU ``imu_true + noise``, the scaled noises, ``x0_hat = states[0] + e`` and the
    measurements ``wrap(h(states[k + 1]) + noise[k])`` are then computed for all ``g`` at once.

    Raises:
        ValueError: no feasible layout.
    """
    st = scenario_static(cfg)
    T, N, g = int(cfg.horizon), int(cfg.n_landmarks), len(rngs)
    landmarks = np.empty((g, N, 3))
    imu = np.empty((g, T, 6))
    noise = np.empty((g, T, N, 2))
    e = np.empty((g, STATE_DIM))
    for i, rng in enumerate(rngs):
        if st.landmarks is None:
            landmarks[i] = draw_layout(cfg, st.states, rng, st.dcm)
        else:
            landmarks[i] = st.landmarks
        imu[i] = rng.standard_normal((T, 6))
        noise[i] = rng.standard_normal((T, N, 2))
        e[i] = rng.standard_normal(STATE_DIM)
    imu = st.imu_true + imu * st.imu_sigma
    noise *= st.aoa_sigma
    x0_hat = st.states[0] + st.init_std * e  # P0 diagonal
    if st.angles is not None:
        h = st.angles
    else:
        h = aoa_angles(body_vectors_along(st.states[1:], landmarks, st.dcm[1:]))
    z = wrap_angle(h + noise)
    return EpisodeDraws(
        landmarks=landmarks,
        imu_measured=imu,
        measurement_noise=noise,
        measurements=z,
        x0_hat=x0_hat,
    )


def make_landmark_problem(
    config: LandmarkConfig | None, rng: np.random.Generator
) -> LandmarkProblem:
    """Fly the trajectory, draw the layout and every noise (module docstring), in that order.

    The flight and everything else that does not depend on the seed come from
    :func:`scenario_static` (computed once per config); the draws from :func:`draw_episodes`.

    Args:
        config: scenario parameters (``None``: the defaults).
        rng: the only source of randomness.

    Raises:
        ValueError: ``rng`` not a ``numpy.random.Generator``, or no feasible layout.
    """
    cfg = LandmarkConfig() if config is None else config
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    st = scenario_static(cfg)
    draws = draw_episodes(cfg, [rng])
    arrays = _readonly(
        landmarks=draws.landmarks[0],
        imu_measured=draws.imu_measured[0],
        measurement_noise=draws.measurement_noise[0],
        measurements=draws.measurements[0],
        x0_hat=draws.x0_hat[0],
    )
    return LandmarkProblem(
        config=cfg,
        states=st.states,
        imu_true=st.imu_true,
        F_true=st.F_true,
        Q=st.Q,
        imu_cov=st.imu_cov,
        R_landmark=st.R_landmark,
        P0=st.P0,
        **arrays,
    )


def check_selection(selection: Any, n_landmarks: int) -> np.ndarray:
    """Validate a selection of landmarks; return its indices (K,) as ``intp``, in given order.

    Accepts integer indices (or integral floats) in ``[0, N)`` without duplicates, or a boolean
    mask of shape ``(N,)``. ``[]`` is the empty selection.

    Raises:
        ValueError: naming ``selection``: not 1-D, NaN/inf, non-integral, out of range or
            duplicated indices, or a mask of the wrong length.
    """
    try:
        arr = np.asarray(selection)
    except ValueError as exc:
        raise ValueError(f"selection must be a 1-D array of landmark indices: {exc}") from None
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise ValueError(f"selection must be 1-D (landmark indices), got shape {arr.shape}")
    if arr.dtype == bool:
        if arr.shape != (n_landmarks,):
            raise ValueError(f"selection mask must have shape ({n_landmarks},), got {arr.shape}")
        return np.flatnonzero(arr)
    if arr.size == 0:
        return np.zeros(0, dtype=np.intp)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"selection must hold integer landmark indices, got dtype {arr.dtype}")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"selection must be finite indices, got {arr.tolist()}")
        if not np.all(arr == np.round(arr)):
            raise ValueError(f"selection must hold integer indices, got {arr.tolist()}")
    idx = arr.astype(np.intp)
    if idx.min() < 0 or idx.max() >= n_landmarks:
        raise ValueError(f"selection indices must lie in [0, {n_landmarks}), got {idx.tolist()}")
    if np.unique(idx).size != idx.size:
        raise ValueError(f"selection must not repeat a landmark, got {idx.tolist()}")
    return idx


def selection_logdet_gain(P_pred: ArrayLike, H_sel: ArrayLike, R: ArrayLike) -> FloatArray | float:
    """``log det P_pred - log det P_post`` of selections: ``log det(I + W)``, batched.

    ``W = G P_pred G^T`` with the whitened rows ``G = R^-1/2 H`` (``R = L L^T``, ``G = L^-1 H``,
    :func:`~selenv.core.information.whiten`), stacked over the ``K`` selected landmarks; by the
    matrix determinant lemma this is the drop of ``log det P`` of the Kalman update (eq. 11 in
    log form, with ``P`` for the CRLB as in Algorithm 3).

    Args:
        P_pred: predicted covariance (n, n), SPD.
        H_sel: Jacobians of the selected landmarks, ``(..., K, p, n)`` (e.g. ``(K, 2, 9)`` for
            one selection, ``(B, K, 2, 9)`` for ``B`` candidate selections).
        R: one landmark's noise covariance (p, p), SPD.

    Returns:
        The gain, a float for ``(K, p, n)`` input, else an array of shape ``(...)``.
    """
    P = validate_spd(P_pred, "P_pred")
    H = np.asarray(H_sel, dtype=np.float64)
    if H.ndim < 3 or H.shape[-1] != P.shape[0]:
        raise ValueError(f"H_sel must have shape (..., K, p, {P.shape[0]}), got {H.shape}")
    *batch, K, p, n = H.shape
    Rv = validate_spd(R, "R", p)
    if K == 0:
        out = np.zeros(batch)
    else:
        G = whiten(H.reshape(-1, p, n), Rv).reshape(-1, K * p, n)  # G = L^-1 H, stacked
        W = G @ P @ np.swapaxes(G, -1, -2)  # W = R^-1/2 H P H^T R^-1/2
        out = block_logdet_gains(W).reshape(batch)  # log det(I + W)
    return float(out) if out.ndim == 0 else out


def crlb_reference(problem: LandmarkProblem, selections: Sequence[Any] | None = None) -> FloatArray:
    """Posterior CRLB on the true trajectory for a sequence of selections, covariance form.

    ``Pc_0 = P0`` and ``Pc_{k+1} = pcrlb_step_covariance(Pc_k, F_k, Q_k, H_{k+1}, R)`` with
    ``F_k``, ``Q_k`` on the truth (``problem.F_true``, ``problem.Q``) and ``H_{k+1}`` the exact
    Jacobians at ``states[k+1]`` of the landmarks selected at step ``k``.

    Args:
        problem: the realisation.
        selections: ``None`` (every landmark at every step) or a sequence of ``L <= T`` step
            selections, each ``None`` (all landmarks) or indices (see :func:`check_selection`).

    Returns:
        ``Pc_0 .. Pc_L``, (L + 1, 9, 9) (``L = T`` when ``selections`` is ``None``).
    """
    T, N = problem.horizon, problem.n_landmarks
    steps: Sequence[Any] = [None] * T if selections is None else selections
    if len(steps) > T:
        raise ValueError(f"selections must hold at most horizon = {T} steps, got {len(steps)}")
    everyone = np.arange(N)
    out = np.empty((len(steps) + 1, STATE_DIM, STATE_DIM))
    out[0] = problem.P0
    for k, sel in enumerate(steps):
        idx = everyone if sel is None else check_selection(sel, N)
        H = measurement_jacobian(problem.states[k + 1], problem.landmarks[idx])
        R = problem.selection_noise(idx.size)
        H2 = H.reshape(-1, STATE_DIM)
        out[k + 1] = pcrlb_step_covariance(out[k], problem.F_true[k], problem.Q[k], H2, R)
    return out


class LandmarkEKF:
    """The EKF of Algorithm 3 on one problem, split into predict / candidates / update.

    One step ``k``: :meth:`predict` (IMU sample ``k``), optionally :meth:`candidates` (cached
    for the step), then at most one :meth:`update` with the selected landmarks (an empty
    selection, or skipping the update, keeps the prediction).

    Args:
        problem: the realisation (IMU, measurements, noises, initial estimate).

    Attributes:
        x: current mean (9,); after :meth:`predict` the prediction, after :meth:`update` the
            posterior.
        P: current covariance (9, 9).
        k: number of predictions done (the time index of ``x``).
    """

    def __init__(self, problem: LandmarkProblem) -> None:
        self.problem = problem
        self.x: FloatArray = problem.x0_hat.copy()
        self.P: FloatArray = problem.P0.copy()
        self.k = 0
        self._pending = False  # a prediction awaits its (optional) update
        self._cache: tuple[FloatArray, FloatArray] | None = None  # (H, h) at the prediction
        cfg = problem.config
        self._sigmas = (float(cfg.accel_sigma), cfg.gyro_sigma)

    @property
    def logdet_P(self) -> float:
        """``log det P`` by Cholesky (the paper's cost eq. 11, in log form, with P for CRLB)."""
        return float(logdet_spd(self.P, "P"))

    @property
    def measurements(self) -> FloatArray:
        """This step's AOA measurements of every landmark (N, 2) (needs a prediction)."""
        if self.k == 0:
            raise RuntimeError("no measurement before the first predict()")
        return self.problem.measurements[self.k - 1]

    def predict(self, k: int | None = None) -> tuple[FloatArray, FloatArray]:
        """Propagate with measured IMU sample ``k`` (eq. 2): ``x <- f(x, u)``, ``P <- F P F^T + Q``.

        ``F`` and ``Q = G imu_cov G^T`` are evaluated at the current estimate.

        Args:
            k: the step to run; must equal :attr:`k` (a guard for callers); ``None``: :attr:`k`.

        Returns:
            The predicted ``(x, P)``.

        Raises:
            ValueError: ``k`` is not the current step.
            RuntimeError: the horizon is exhausted.
        """
        if k is not None and k != self.k:
            raise ValueError(f"k must be the current step {self.k}, got {k!r}")
        if self.k >= self.problem.horizon:
            raise RuntimeError(f"horizon {self.problem.horizon} reached: no IMU sample left")
        u = self.problem.imu_measured[self.k]
        x, P = ekf_predict(self.x[None], self.P[None], u[None], self.problem.dt, *self._sigmas)
        self.x, self.P = x[0], P[0]  # x <- f(x, u), P <- F P F^T + Q
        self.k += 1
        self._pending = True
        self._cache = None
        return self.x, self.P

    def candidates(self) -> tuple[FloatArray, FloatArray]:
        """Jacobians (N, 2, 9) and predicted measurements (N, 2) of every landmark at ``x``.

        Cached until the estimate changes; :meth:`update` reuses them.
        """
        if self._cache is None:
            H, h = aoa_candidates(self.x[None], self.problem.landmarks[None])
            self._cache = (H[0], h[0])
        return self._cache

    def update(self, selection: Any) -> KalmanUpdate | None:
        """Update with the selected landmarks only (Algorithm 3), Joseph form.

        The innovation is angle-wrapped, ``y = wrap(z - h(x))``, and passed to
        :func:`~selenv.core.kalman.kf_update` as ``z' = H x + y`` with the stacked ``H``
        (2K, 9) and ``R = blockdiag(R_landmark)`` (2K, 2K).

        Args:
            selection: landmark indices (see :func:`check_selection`); empty: no update.

        Returns:
            The :class:`~selenv.core.kalman.KalmanUpdate`, or ``None`` for an empty selection.

        Raises:
            ValueError: a bad ``selection`` (the filter is left unchanged).
            RuntimeError: no prediction awaits an update.
        """
        idx = check_selection(selection, self.problem.n_landmarks)
        if not self._pending:
            raise RuntimeError("call predict() before update() (one update per step)")
        self._pending = False
        if idx.size == 0:
            return None
        if self._cache is not None:
            H, hx = self._cache[0][idx], self._cache[1][idx]
        else:  # only the selected landmarks: the cheap path for small K
            Hb, hb = aoa_candidates(self.x[None], self.problem.landmarks[idx][None])
            H, hx = Hb[0], hb[0]
        z = self.measurements[idx]
        R = self.problem.R_landmark
        b = ekf_update(self.x[None], self.P[None], H[None], hx[None], z[None], R)  # B = 1
        ll = float(np.asarray(b.log_likelihood).reshape(-1)[0])
        res = KalmanUpdate(b.x[0], b.P[0], b.y[0], b.S[0], b.K[0], ll)
        self.x, self.P = res.x, res.P
        self._cache = None
        return res
