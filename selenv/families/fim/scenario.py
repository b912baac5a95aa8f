"""Heterogeneous measurement selection by Fisher information (Kirchner et al. 2020, Sec. 6).

Agents fly curved approaches around a ground vehicle and collect pools of candidate camera
(eq. 23), time-of-arrival (eq. 20) and Doppler (eq. 22) measurements; selecting ``F`` scores
eq. (9), ``log det(Q0 + sum_{k in F} Q_k) - log det Q0`` (see :mod:`selenv.core.information`).
Parameters ``theta``: ``[x, y, vx, vy, ax, ay]`` (eq. 18, at the window start), then per agent
``cT[i], cT0[i]`` (TOA receiver) and ``lambdaDf[i]`` (Doppler receiver).

Presets (:data:`PRESETS`): ``example1`` (one camera), ``example2`` (camera + Doppler) and
``example3`` (two agents, camera + Doppler each) follow the paper with a stationary target
(``x, y`` estimated); ``example1_moving``, ``example2_moving``, ``example3_moving`` are the same
pools with a moving target (the defaults of the v0 RL envs).

Modelling choices (documented defaults of :class:`FIMScenarioConfig`):

* Prior ``p(theta)``: Gaussian, diagonal, centred on the nominal target (position (0, 0),
  velocity (3, 1) m/s, curvature (0.05, -0.02) m/s^2; zeros when ``stationary``). Standard
  deviations: position 25 m, velocity 0.5 m/s, curvature 0.01 m/s^2 (the paper's values are
  not given; these keep the prior 1-sigma position error below ~45 m over a 60 s window, so the
  linearisation at the prior mean stays meaningful and the target stays in front of every
  camera), ``cT`` 1 m, ``cT0`` 1000 m, ``lambdaDf`` 300 m/s (1 ppm of the carrier).
* ``Q0 = P0^-1`` (eq. 3 for a Gaussian prior). ``theta_true`` is a draw from the prior
  (velocity and curvature exactly 0 when ``stationary``), redrawn in the rare case that it puts
  the target behind a camera; ``H`` is evaluated at the prior mean (the selector never sees the
  truth).
* TOA: symbols are sent once per candidate period ``window_s / n_candidates`` and the receiver
  removes the nominal schedule ``k c T_nom``, so ``cT`` is the period *error* (nominal 0) and
  eq. (20) holds as written; Jacobians and ``Q_k`` are unaffected by that constant shift.
  ``cT0`` and ``lambdaDf`` have nominal 0.
* Agent ``i`` spirals in on the nominal target trajectory (``spiral_path``: range
  ``start_radius_m -> end_radius_m``, bearing sweeping ``sweep_deg`` to ``90 + 360 i / n`` deg,
  at ``altitude_m``; closest at the end, Fig. 2). Cameras are gimballed onto the nominal target.
* ``randomize``: one uniform rotation of all paths about the target, a ``U(0.8, 1.2)`` range
  scale per agent, camera/Doppler times jittered within their grid cells and a random phase of
  the TOA symbol grid. Otherwise the geometry is fixed (times at cell midpoints).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.information import whiten
from selenv.core.linalg import FloatArray, as_float_array, check_finite, check_shape
from selenv.families.fim import models as km
from selenv.scenarios.validation import (
    ArgumentTypeError,
    check_bool,
    check_choice,
    check_integer,
    check_real,
    describe,
)

__all__ = [
    "MAX_AGENTS",
    "MAX_CANDIDATES",
    "PRESETS",
    "RANGES",
    "SENSOR_NAMES",
    "FIMProblem",
    "FIMProblemBatch",
    "FIMScenarioConfig",
    "ProblemConstants",
    "config_from",
    "make_problem",
    "make_problems",
    "pool_jacobian",
    "problem_constants",
]

#: sensor codes used in :attr:`FIMProblem.sensor` (index into this tuple)
SENSOR_NAMES: tuple[str, ...] = ("camera", "toa", "doppler")
CAMERA, TOA, DOPPLER = 0, 1, 2

#: largest number of sensing agents and of candidates per sensor per agent
MAX_AGENTS = 8
MAX_CANDIDATES = 5000

#: valid range of every real-valued field of :class:`FIMScenarioConfig`: ``(low, high, unit)``
RANGES: dict[str, tuple[float, float, str]] = {
    "window_s": (0.1, 3600.0, "s"),
    "camera_sigma_px": (1e-3, 1e3, "px"),
    "focal_px": (1.0, 1e5, "px"),
    "toa_sigma_m": (1e-3, 1e5, "m"),
    "doppler_sigma_mps": (1e-3, 1e5, "m/s"),
    "prior_position_m": (1e-3, 1e4, "m"),
    "prior_velocity_mps": (1e-4, 100.0, "m/s"),
    "prior_curvature_mps2": (1e-6, 10.0, "m/s^2"),
    "prior_cT_m": (1e-3, 1e5, "m"),
    "prior_cT0_m": (1e-3, 1e7, "m"),
    "prior_lambda_mps": (1e-3, 1e6, "m/s"),
    "start_radius_m": (1.0, 1e5, "m"),
    "end_radius_m": (1.0, 1e5, "m"),
    "altitude_m": (1.0, 1e5, "m"),
    "sweep_deg": (-3600.0, 3600.0, "deg"),
}


@dataclass(frozen=True, kw_only=True)
class FIMScenarioConfig:
    """Scenario parameters; every field is validated (an error naming the field and its range).

    A value of the wrong type is a ``TypeError`` (which is also a ``ValueError``), a value out
    of range a ``ValueError``. The ranges (:data:`RANGES`) keep every Fisher information and
    log det finite in float64 while spanning several decades around the defaults.

    Attributes:
        preset: name of the preset this config came from (informational).
        n_agents: number of sensing agents, an int in ``[1, MAX_AGENTS]`` (8).
        sensors: subset of ``SENSOR_NAMES`` carried by every agent (stored in canonical order).
        n_candidates: candidates per sensor per agent, an int in ``[1, MAX_CANDIDATES]`` (5000).
        window_s: estimation window length (s), in ``[0.1, 3600]``.
        camera_sigma_px, focal_px: image noise std in ``[1e-3, 1e3]`` and focal length in
            ``[1, 1e5]`` (pixels).
        toa_sigma_m: std of ``c T`` (m), in ``[1e-3, 1e5]``.
        doppler_sigma_mps: std of ``lambda F`` (m/s), in ``[1e-3, 1e5]``; default 33 ppb of the
            carrier times ``c``.
        prior_*: prior standard deviations (see the module docstring and :data:`RANGES`).
        start_radius_m, end_radius_m, altitude_m: agent path geometry (m), in ``[1, 1e5]``;
            ``sweep_deg`` in ``[-3600, 3600]``.
        stationary: target velocity and curvature are 0 and not estimated (Examples 1-3 as
            in the paper: presets ``example1..3``; only ``x, y`` and the nuisance parameters
            are estimated, e.g. d = 2 in Example 1, d = 3 with one Doppler receiver).
        randomize: draw a new geometry per problem.
    """

    preset: str = "custom"
    n_agents: int = 1
    sensors: tuple[str, ...] = ("camera", "doppler")
    n_candidates: int = 1000
    window_s: float = 60.0
    camera_sigma_px: float = 0.8
    focal_px: float = 50.0
    toa_sigma_m: float = 3.0
    doppler_sigma_mps: float = 33e-9 * km.C_LIGHT
    prior_position_m: float = 25.0
    prior_velocity_mps: float = 0.5
    prior_curvature_mps2: float = 0.01
    prior_cT_m: float = 1.0
    prior_cT0_m: float = 1000.0
    prior_lambda_mps: float = 300.0
    start_radius_m: float = 400.0
    end_radius_m: float = 60.0
    altitude_m: float = 50.0
    sweep_deg: float = 180.0
    stationary: bool = False
    randomize: bool = False

    def __post_init__(self) -> None:
        put = object.__setattr__
        if not isinstance(self.preset, str):
            raise ArgumentTypeError(f"preset must be a str, got {describe(self.preset)}")
        put(self, "n_agents", check_integer(self.n_agents, "n_agents", 1, MAX_AGENTS))
        put(self, "n_candidates", check_integer(self.n_candidates, "n_candidates", 1,
                                                MAX_CANDIDATES))  # fmt: skip
        sensors = self.sensors
        if isinstance(sensors, str) or not isinstance(sensors, tuple | list) or not sensors:
            raise ArgumentTypeError(
                f"sensors must be a non-empty tuple of distinct names from {SENSOR_NAMES}, "
                f"got {describe(sensors)}"
            )
        if any(x not in SENSOR_NAMES for x in sensors) or len(set(sensors)) < len(sensors):
            raise ValueError(f"sensors must be distinct names from {SENSOR_NAMES}, got {sensors!r}")
        put(self, "sensors", tuple(s for s in SENSOR_NAMES if s in self.sensors))
        for name, (low, high, unit) in RANGES.items():
            put(self, name, check_real(getattr(self, name), name, low, high, unit=unit))
        for name in ("stationary", "randomize"):
            put(self, name, check_bool(getattr(self, name), name))


_CD = ("camera", "doppler")

#: Scenario presets. ``example1..3`` are Examples 1-3 of Sec. 6 as the paper states them: one
#: stationary vehicle (Example 1: "a stationary vehicle"; Example 2 reuses Example 1's
#: trajectories; every figure marks a single ground-truth location), so ``theta_2 = theta_3 = 0``
#: are known (after eq. 18) and only the position (plus the sensors' nuisance parameters) is
#: estimated. ``*_moving`` are the same pools with a moving target (velocity and curvature
#: estimated too); ``example2_moving`` / ``example3_moving`` are the earlier ``example2`` /
#: ``example3``, kept as the defaults of ``FIMSelection-v1`` / ``fim_selection_v0`` so that
#: their v0 trajectories do not change.
PRESETS: dict[str, FIMScenarioConfig] = {
    "example1": FIMScenarioConfig(preset="example1", sensors=("camera",), stationary=True),
    "example2": FIMScenarioConfig(preset="example2", sensors=_CD, stationary=True),
    "example3": FIMScenarioConfig(preset="example3", n_agents=2, sensors=_CD, stationary=True),
    "example1_moving": FIMScenarioConfig(preset="example1_moving", sensors=("camera",)),
    "example2_moving": FIMScenarioConfig(preset="example2_moving", sensors=_CD),
    "example3_moving": FIMScenarioConfig(preset="example3_moving", n_agents=2, sensors=_CD),
}


def config_from(preset: str = "example2", **overrides: Any) -> FIMScenarioConfig:
    """A preset (a key of :data:`PRESETS`) with fields overridden, validated.

    Raises:
        ValueError: unknown preset or override key (lists the valid ones), or a bad value.
    """
    check_choice(preset, "preset", sorted(PRESETS))
    valid = [f.name for f in dataclasses.fields(FIMScenarioConfig) if f.name != "preset"]
    bad = sorted(set(overrides) - set(valid))
    if bad:
        raise ValueError(f"unknown config keys {bad}; valid keys: {valid}")
    return dataclasses.replace(PRESETS[preset], **overrides)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, kw_only=True)
class FIMProblem:
    """One drawn instance: prior, truth, candidate pool and its geometry (arrays read-only).

    Attributes:
        config: the scenario config.
        theta_true, theta_prior_mean: ``(d,)``.
        P0, Q0: ``(d, d)`` prior covariance and information ``Q0 = P0^-1`` (eq. 3).
        H: ``(N, m, d)`` Jacobians at the prior mean; ``m = 2`` with cameras else 1; scalar
            candidates are zero-padded (identity in ``R``).
        R: ``(N, m, m)`` noise covariances; ``G``: ``(N, m, d)`` whitened, ``G_k^T G_k = Q_k``.
        agent, sensor, rows: ``(N,)`` ints (``sensor`` indexes ``SENSOR_NAMES``; rows 1 or 2).
        times: ``(N,)`` time since the window start (s).
        positions, velocities: ``(N, 3)`` agent state at each candidate.
        camera_rotation: ``(N, 3, 3)`` world-to-camera rotations (identity for non-cameras).
        symbol: ``(N,)`` TOA symbol index ``k`` (-1 for non-TOA candidates).
        nuisance: ``(N, 2)`` columns of the candidate's nuisance parameters (-1 if none), in
            the full parameter vector.
        intrinsics: ``(3, 3)`` camera matrix ``A``.
        param_names: ``d`` names.
        free: ``(d,)`` indices of the estimated parameters in the full vector
            ``[x, y, vx, vy, ax, ay, nuisance...]``; a stationary target (``example1..3``)
            estimates only the position of the motion parameters, ``theta_2 = theta_3 = 0``
            (paper, after eq. 18), plus the nuisance parameters.
        theta_fixed: full vector holding the values of the parameters not estimated.

    Candidates are ordered agent-major, then by sensor code, then by time.
    """

    config: FIMScenarioConfig
    theta_true: FloatArray
    theta_prior_mean: FloatArray
    P0: FloatArray
    Q0: FloatArray
    H: FloatArray
    R: FloatArray
    G: FloatArray
    agent: np.ndarray
    sensor: np.ndarray
    rows: np.ndarray
    times: FloatArray
    positions: FloatArray
    velocities: FloatArray
    camera_rotation: FloatArray
    symbol: np.ndarray
    nuisance: np.ndarray
    intrinsics: FloatArray
    param_names: tuple[str, ...]
    free: np.ndarray
    theta_fixed: FloatArray

    @property
    def N(self) -> int:
        """Number of candidates."""
        return int(self.H.shape[0])

    @property
    def m(self) -> int:
        """Rows per (padded) candidate."""
        return int(self.H.shape[1])

    @property
    def d(self) -> int:
        """Number of parameters."""
        return int(self.H.shape[2])

    def full_theta(self, theta: ArrayLike) -> FloatArray:
        """Embed estimated parameters ``(d,)`` in the full vector (fixed entries filled in)."""
        return self._theta(theta)

    def _theta(self, theta: ArrayLike) -> FloatArray:
        """Validate the estimated parameters ``(d,)`` and embed them in the full vector."""
        th = check_shape(check_finite(as_float_array(theta, "theta"), "theta"), (self.d,), "theta")
        full = np.array(self.theta_fixed, dtype=np.float64)
        full[self.free] = th
        return full

    def _idx(self, idx: ArrayLike | None) -> np.ndarray:
        if idx is None:
            return np.arange(self.N)
        ix = np.asarray(idx)
        if ix.ndim != 1 or (ix.size and not np.issubdtype(ix.dtype, np.integer)):
            raise ValueError(f"idx must be a 1-D array of integer indices, got {ix!r}")
        ix = ix.astype(np.intp)
        if ix.size and (ix.min() < 0 or ix.max() >= self.N):
            raise ValueError(f"idx must lie in [0, {self.N}), got {ix.min()}..{ix.max()}")
        return ix

    def _groups(self, ix: np.ndarray) -> Iterator[tuple[Any, ...]]:
        """Per sensor in ``ix``: code, positions in ``ix``, candidates, times, p, nuisance."""
        for code in (CAMERA, TOA, DOPPLER):
            sel = np.flatnonzero(self.sensor[ix] == code)
            if sel.size:
                c = ix[sel]
                yield code, sel, c, self.times[c], self.positions[c], self.nuisance[c]

    def measurement_mean(self, theta: ArrayLike, idx: ArrayLike | None = None) -> FloatArray:
        """Means ``mu_k(theta)`` of candidates ``idx`` (all if ``None``), ``(len(idx), m)``.

        Camera rows are eq. (23), TOA eq. (20), Doppler eq. (22); scalar means are zero-padded.
        """
        th, ix = self._theta(theta), self._idx(idx)
        out = np.zeros((ix.size, self.m))
        for code, sel, c, t, p, nu in self._groups(ix):
            if code == CAMERA:
                out[sel, :2] = km.camera_mean(th, t, p, self.camera_rotation[c], self.intrinsics)
            elif code == TOA:
                out[sel, 0] = km.toa_mean(th, t, p, self.symbol[c], th[nu[:, 0]], th[nu[:, 1]])
            else:
                out[sel, 0] = km.doppler_mean(th, t, p, self.velocities[c], th[nu[:, 0]])
        return out

    def measurement_jacobian(self, theta: ArrayLike, idx: ArrayLike | None = None) -> FloatArray:
        """Jacobians ``d mu_k / d theta`` of candidates ``idx``, ``(len(idx), m, d)``."""
        th, ix = self._theta(theta), self._idx(idx)
        return pool_jacobian(
            th, self.sensor[ix], self.times[ix], self.positions[ix], self.velocities[ix],
            self.camera_rotation[ix], self.symbol[ix], self.nuisance[ix], self.intrinsics,
            self.m, self.free,
        )  # fmt: skip

    def sample_measurements(
        self, rng: np.random.Generator, idx: ArrayLike | None = None
    ) -> FloatArray:
        """Noisy measurements ``mu_k(theta_true) + L_k z`` (``R_k = L_k L_k^T``), ``(n, m)``."""
        ix = self._idx(idx)
        L = np.linalg.cholesky(self.R[ix])
        z = rng.standard_normal((ix.size, self.m))
        return self.measurement_mean(self.theta_true, ix) + np.einsum("kij,kj->ki", L, z)

    def pool(self, agent_index: int) -> np.ndarray:
        """Indices (increasing) of the candidates of agent ``agent_index``."""
        n = self.config.n_agents
        if not 0 <= agent_index < n:
            raise ValueError(f"agent_index must lie in [0, {n}), got {agent_index}")
        return np.flatnonzero(self.agent == agent_index)


# -- construction -------------------------------------------------------------------------------
def pool_jacobian(
    theta_full: FloatArray,
    sensor: np.ndarray,
    times: FloatArray,
    positions: FloatArray,
    velocities: FloatArray,
    camera_rotation: FloatArray,
    symbol: np.ndarray,
    nuisance: np.ndarray,
    intrinsics: FloatArray,
    m: int,
    free: np.ndarray,
) -> FloatArray:
    """Jacobians ``d mu_k / d theta`` ``(T, m, d)`` of ``T`` candidates at one ``theta_full``.

    Camera rows are eq. (23), TOA eq. (20), Doppler eq. (22) (:mod:`models`); the nuisance
    columns are scattered into the full vector, then the ``free`` columns kept. The candidates
    are given by their per-candidate arrays (``(T,)``, ``(T, 3)``, ``(T, 3, 3)``, ``(T, 2)``), so
    the pools of many problems can be stacked into one call.
    """
    J = np.zeros((sensor.size, m, theta_full.size))
    for code in (CAMERA, TOA, DOPPLER):
        sel = np.flatnonzero(sensor == code)
        if not sel.size:
            continue
        t, p = times[sel], positions[sel]
        if code == CAMERA:
            Jc = km.camera_jacobian(theta_full, t, p, camera_rotation[sel], intrinsics)
            J[sel, :2, : km.N_MOTION] = Jc
            continue
        if code == TOA:
            Jl = km.toa_jacobian(theta_full, t, p, symbol[sel])
        else:
            Jl = km.doppler_jacobian(theta_full, t, p, velocities[sel])
        J[sel, 0, : km.N_MOTION] = Jl[:, : km.N_MOTION]
        nu = nuisance[sel]
        for j in range(Jl.shape[1] - km.N_MOTION):  # scatter the nuisance columns
            J[sel, 0, nu[:, j]] = Jl[:, km.N_MOTION + j]
    return J if free.size == theta_full.size else J[:, :, free]


def _nominal(cfg: FIMScenarioConfig) -> tuple[FloatArray, FloatArray, list[str], np.ndarray]:
    """Prior mean, prior std devs, parameter names and per-agent nuisance columns ``(n, 3)``."""
    mean = [0.0] * 6 if cfg.stationary else [0.0, 0.0, 3.0, 1.0, 0.05, -0.02]
    std = [cfg.prior_position_m, cfg.prior_velocity_mps, cfg.prior_curvature_mps2]
    std, names = [v for v in std for _ in range(2)], ["x", "y", "vx", "vy", "ax", "ay"]
    cols = -np.ones((cfg.n_agents, 3), dtype=np.intp)  # cT, cT0, lambdaDf
    for i in range(cfg.n_agents):
        for j, name, sd, on in (
            (0, "cT", cfg.prior_cT_m, "toa"), (1, "cT0", cfg.prior_cT0_m, "toa"),
            (2, "lambdaDf", cfg.prior_lambda_mps, "doppler"),
        ):  # fmt: skip
            if on in cfg.sensors:
                cols[i, j] = len(names)
                names.append(f"{name}[{i}]")
                mean.append(0.0)  # nominal 0 (see the module docstring)
                std.append(sd)
    return np.array(mean), np.array(std), names, cols


@dataclass(frozen=True, kw_only=True)
class ProblemConstants:
    """Everything of a drawn problem that does not depend on the seed (arrays read-only).

    Computed once per config by :func:`problem_constants` (cached) and shared by every
    problem drawn from it. ``D`` is the length of the full parameter vector, ``d`` that of
    the estimated one, ``N`` the pool size, ``A`` the number of agents, ``S`` of sensors.

    Attributes:
        config: the scenario config.
        mean, std: ``(D,)`` prior mean (``= theta_fixed``) and standard deviations.
        param_names: ``d`` names of the estimated parameters; ``free`` ``(d,)`` their indices.
        agent, sensor, rows, symbol: ``(N,)`` ints; ``nuisance`` ``(N, 2)``; ``camera``
            ``(N,)`` bool (the camera candidates).
        R: ``(N, m, m)`` noise covariances; ``P0``, ``Q0`` ``(d, d)`` (eq. 3).
        intrinsics: ``(3, 3)`` camera matrix ``A``.
        fixed: without ``randomize``: the whole geometry ``times (1, N)``, ``positions``,
            ``velocities (1, N, 3)``, ``camera_rotation (1, N, 3, 3)``, ``H``, ``G``
            ``(1, N, m, d)``; ``None`` when the geometry is drawn per problem.
    """

    config: FIMScenarioConfig
    mean: FloatArray
    std: FloatArray
    param_names: tuple[str, ...]
    free: np.ndarray
    agent: np.ndarray
    sensor: np.ndarray
    rows: np.ndarray
    symbol: np.ndarray
    nuisance: np.ndarray
    camera: np.ndarray
    R: FloatArray
    P0: FloatArray
    Q0: FloatArray
    intrinsics: FloatArray
    fixed: dict[str, np.ndarray] | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(N, m, d)`` of the pool's ``G``."""
        return int(self.R.shape[0]), int(self.R.shape[1]), int(self.free.size)


@functools.lru_cache(maxsize=64)
def problem_constants(config: FIMScenarioConfig) -> ProblemConstants:
    """The seed-independent part of :func:`make_problem` for ``config`` (cached per config).

    Prior (eq. 3), parameter layout, candidate bookkeeping and noise ``R``; without
    ``randomize`` also the whole geometry and the whitened pool ``G`` (only the truth is then
    drawn per problem). Arrays are read-only (``flags.writeable`` is false): they are shared.
    """
    cfg = config
    mean, std, names, cols = _nominal(cfg)
    n, A = cfg.n_candidates, cfg.n_agents
    codes = np.array([SENSOR_NAMES.index(name) for name in cfg.sensors])
    S = codes.size
    agent = np.repeat(np.arange(A), S * n)  # agent-major, then sensor, then time
    sensor = np.tile(np.repeat(codes, n), A)
    symbol = np.where(sensor == TOA, np.tile(np.arange(n), A * S), -1)
    N, m = agent.size, 2 if "camera" in cfg.sensors else 1
    nuisance = -np.ones((N, 2), dtype=np.intp)
    nuisance[sensor == TOA] = cols[agent[sensor == TOA], :2]
    nuisance[sensor == DOPPLER, 0] = cols[agent[sensor == DOPPLER], 2]
    sigma = np.array([cfg.camera_sigma_px, cfg.toa_sigma_m, cfg.doppler_sigma_mps])[sensor]
    R = np.broadcast_to(np.eye(m), (N, m, m)).copy()  # identity on padding rows
    R[:, 0, 0] = sigma**2
    cam = sensor == CAMERA
    if m == 2:
        R[cam, 1, 1] = cfg.camera_sigma_px**2
    free = (
        np.setdiff1d(np.arange(mean.size), np.arange(2, 6))
        if cfg.stationary
        else np.arange(mean.size)
    )
    sf = std[free]
    arrays = {
        "mean": mean, "std": std, "free": free, "agent": agent, "sensor": sensor,
        "rows": np.where(cam, 2, 1), "symbol": symbol, "nuisance": nuisance, "camera": cam,
        "R": R, "P0": np.diag(sf**2), "Q0": np.diag(1.0 / sf**2),
        "intrinsics": km.intrinsics(cfg.focal_px),
    }  # fmt: skip
    ro: dict[str, Any] = {key: _readonly(val) for key, val in arrays.items()}
    const = ProblemConstants(config=cfg, param_names=tuple(names[i] for i in free), **ro)
    if cfg.randomize:
        return const
    shape = (1, A, S, n)
    geo = _geometry(const, np.zeros(1), np.ones((1, A)), np.full(shape, 0.5))
    fixed = {key: _readonly(val) for key, val in geo.items()}
    return dataclasses.replace(const, fixed=fixed)


def _geometry(
    const: ProblemConstants, rot: FloatArray, scales: FloatArray, offsets: FloatArray
) -> dict[str, FloatArray]:
    """Candidate geometry, Jacobians and whitened pools of ``K`` problems in one pass.

    Args:
        const: the config's constants.
        rot: ``(K,)`` rotation of all paths about the target (rad).
        scales: ``(K, A)`` range scale per agent.
        offsets: ``(K, A, S, n)`` position of each candidate time in its grid cell, in [0, 1).

    Returns:
        ``times (K, N)``, ``positions``, ``velocities (K, N, 3)``, ``camera_rotation (K, N, 3,
        3)``, ``H`` and ``G`` ``(K, N, m, d)``: agent ``i`` spirals in on the nominal target
        (:func:`~models.spiral_path`, ending at bearing ``rot + 90 deg + 360 deg i / A``);
        ``H`` is evaluated at the prior mean, ``G_k = L_k^-1 H_k`` with ``R_k = L_k L_k^T``.
    """
    cfg = const.config
    K, A, S, n = offsets.shape
    N, m, _ = const.shape
    cell = cfg.window_s / cfg.n_candidates
    s = ((np.arange(n) + offsets) * cell).reshape(K * N)
    q, qdot = km.target_state(const.mean, s)
    bearing = rot[:, None] + np.pi / 2 + 2.0 * np.pi * np.arange(A) / A  # (K, A)
    per_candidate = (K, A, S * n)
    pos, vel = km.spiral_path(
        s, q, qdot, window_s=cfg.window_s,
        start_radius=np.broadcast_to((scales * cfg.start_radius_m)[..., None], per_candidate)
        .reshape(K * N),
        end_radius=np.broadcast_to((scales * cfg.end_radius_m)[..., None], per_candidate)
        .reshape(K * N),
        sweep_rad=np.deg2rad(cfg.sweep_deg),
        end_bearing=np.broadcast_to(bearing[..., None], per_candidate).reshape(K * N),
        altitude=cfg.altitude_m,
    )  # fmt: skip
    cam = np.tile(const.camera, K)
    rotation = np.empty((K * N, 3, 3))
    rotation[:] = np.eye(3)
    if cam.any():
        aim = np.column_stack([q[cam], np.zeros(int(cam.sum()))])
        rotation[cam] = km.look_at_rotation(pos[cam], aim)
    H = pool_jacobian(
        const.mean, np.tile(const.sensor, K), s, pos, vel, rotation, np.tile(const.symbol, K),
        np.tile(const.nuisance, (K, 1)), const.intrinsics, m, const.free,
    )  # fmt: skip
    G = _whiten_pools(const, H)
    d = const.free.size
    return {
        "times": s.reshape(K, N), "positions": pos.reshape(K, N, 3),
        "velocities": vel.reshape(K, N, 3), "camera_rotation": rotation.reshape(K, N, 3, 3),
        "H": H.reshape(K, N, m, d), "G": G.reshape(K, N, m, d),
    }  # fmt: skip


def _whiten_pools(const: ProblemConstants, H: FloatArray) -> FloatArray:
    """``G_k = L_k^-1 H_k`` (``R_k = L_k L_k^T``) of stacked pools ``H`` ``(K N, m, d)``.

    :func:`~selenv.core.information.whiten` with the config's ``R`` repeated. Every ``R_k`` of
    this family is diagonal (independent rows, identity padding), so ``L_k = diag(sqrt(R_k))``
    and the triangular solve is a product with ``1 / sqrt(R_k)``, what the LAPACK solve
    computes on a diagonal factor (to one rounding; bit for bit with OpenBLAS, tested against
    ``whiten``); a non-diagonal ``R`` goes through ``whiten``.
    """
    N, m, _ = const.shape
    K = H.shape[0] // N
    R = const.R
    if not np.count_nonzero(R - R * np.eye(m)):  # diagonal: L = sqrt(diag R)
        scale = 1.0 / np.sqrt(np.diagonal(R, axis1=1, axis2=2))  # (N, m): L^-1
        G: FloatArray = (H.reshape(K, N, m, -1) * scale[:, :, None]).reshape(H.shape)
        return G
    return whiten(H, np.broadcast_to(R, (K, N, m, m)).reshape(K * N, m, m))


def _closed_form_pools(
    const: ProblemConstants,
    rot: FloatArray,
    scales: FloatArray,
    offsets: FloatArray,
    out: FloatArray,
) -> dict[str, Any] | None:
    """Times and whitened pools ``G`` of ``K`` problems, small-matrix ops written out.

    What an episode needs of :func:`_geometry` (the rest is computed on demand,
    :class:`FIMProblemBatch`), to rounding (the tests hold the two to ``rtol = 1e-12``), on
    ``(K, A, S, n)`` arrays: one numpy op per scalar formula instead of the models' stacked
    ``(T, 3, 3)`` products and per-sensor gathers:

    * eq. (18) at the prior mean: ``q = theta1 + s theta2 + s^2/2 theta3``, ``qdot``;
    * the spiral paths (:func:`~models.spiral_path`) and, for cameras, the look-at rotation
      rows ``x, y, z`` (:func:`~models.look_at_rotation`: ``z`` towards the target,
      ``x = z x e_up / |.|``, ``y = z x x``);
    * camera rows (eq. 23): ``dI/dr = M / dd - U m / dd^2`` with ``M = [I2 0] A R_c``,
      ``m = e3^T A R_c``, ``U = M r``, ``dd = m r`` at ``r = [q; 0] - p``;
    * Doppler (eq. 22): ``-(d_q b + e bdot)`` with ``d_q = (v - (v.e) e) / rho``, ``v = [qdot;
      0] - pdot``, then 1 in its ``lambdaDf`` column; TOA (eq. 20): ``e b``, then ``k`` and 1
      in ``cT``, ``cT0``;
    * chained through ``b = (1, s, s^2/2)``, ``bdot = (0, 1, s)`` (column ``2 j + i`` is
      ``grad[i] b[j]``), the ``free`` columns kept, each row divided by its sensor's sigma
      (``G_k = L_k^-1 H_k``, ``R_k`` diagonal).

    Args:
        const: the config's constants.
        rot: ``(K,)`` rotation of all paths about the target (rad).
        scales: ``(K, A)`` range scale per agent.
        offsets: ``(K, A, S, n)`` position of each candidate time in its grid cell, in [0, 1).
        out: ``(K, N, m, d)``, receives ``G`` (zeroed here).

    Returns:
        ``times`` ``(K, N)`` and ``cameras``: ``(s, px, py, pz, mx, my, mz)`` of the camera
        slot (``(K, A, n)`` arrays or floats; ``m = e3^T A R_c``) for :func:`_camera_depths`,
        ``None`` without cameras. ``None`` instead if ``R`` is not diagonal and equal within a
        sensor or a camera looks straight down (the look-at rotation's fallback axis):
        :func:`_geometry` handles those.
    """
    cfg = const.config
    K, A, S, n = offsets.shape
    m, d = const.shape[1:]
    lay = _slot_layout(cfg)
    if not lay["diagonal"]:
        return None
    th = const.mean  # the Jacobians at the prior mean
    s = (np.arange(n) + offsets) * (cfg.window_s / cfg.n_candidates)  # (K, A, S, n)
    s2 = 0.5 * s**2
    qx, qy = th[0] + s * th[2] + s2 * th[4], th[1] + s * th[3] + s2 * th[5]
    qdx, qdy = th[2] + s * th[4], th[3] + s * th[5]
    u = s / cfg.window_s  # spiral paths: range r(u), bearing phi(u)
    r0 = (scales * cfg.start_radius_m)[:, :, None, None]
    r1 = (scales * cfg.end_radius_m)[:, :, None, None]
    r = r0 + (r1 - r0) * u
    rdot = (r1 - r0) / cfg.window_s
    sweep = np.deg2rad(cfg.sweep_deg)
    bearing = rot[:, None] + np.pi / 2 + 2.0 * np.pi * np.arange(A) / A  # (K, A)
    phi = bearing[:, :, None, None] - sweep * (1.0 - u)
    cos, sin = np.cos(phi), np.sin(phi)
    px, py, pz = qx + r * cos, qy + r * sin, cfg.altitude_m
    rx, ry, rz = qx - px, qy - py, 0.0 - pz  # [q; 0] - p
    G = out.reshape(K, A, S, n, m, d)
    G[...] = 0.0
    col, scale, nuisance = lay["col"], lay["scale"], lay["nuisance"]
    cameras = None

    def chain(j: int, a: int, gx: Any, gy: Any) -> None:
        """Row ``a`` of slot ``j``: column ``col[2 jb + i]`` gets ``g_i b_jb / sigma``."""
        for jb, b in enumerate((None, s[:, :, j], s2[:, :, j])):
            for i, g in enumerate((gx, gy)):
                if col[2 * jb + i] >= 0:
                    dst = G[:, :, j, :, a, col[2 * jb + i]]
                    np.multiply(g if b is None else g * b, scale[j, a], out=dst)

    if lay["camera"] >= 0:
        j = lay["camera"]
        zx, zy, zz = rx[:, :, j], ry[:, :, j], rz
        nz = np.sqrt(zx * zx + zy * zy + zz * zz)
        zx, zy, zz = zx / nz, zy / nz, zz / nz
        nx = np.sqrt(zy * zy + zx * zx)  # |z x e_up|
        if np.any(nx < 1e-9):
            return None
        xx, xy = zy / nx, -zx / nx  # x = z x e_up / |.|, x_z = 0
        R = ((xx, xy, None), (-zz * xy, zz * xx, zx * xy - zy * xx), (zx, zy, zz))  # y = z x x
        AR = [[_lincomb(const.intrinsics[a], [R[e][c] for e in range(3)]) for c in range(3)]
              for a in range(3)]  # fmt: skip
        rel = (rx[:, :, j], ry[:, :, j], rz)
        cameras = (s[:, :, j], px[:, :, j], py[:, :, j], pz, *AR[2])
        dd = _dot3(AR[2], rel)
        dd2 = dd**2
        for a in range(2):  # image rows u, v
            U = _dot3(AR[a], rel)
            chain(j, a, AR[a][0] / dd - U * AR[2][0] / dd2, AR[a][1] / dd - U * AR[2][1] / dd2)
    for j, code in ((lay["toa"], TOA), (lay["doppler"], DOPPLER)):
        if j < 0:
            continue
        ex, ey = rx[:, :, j], ry[:, :, j]
        rho = np.sqrt(ex * ex + ey * ey + rz * rz)
        ex, ey = ex / rho, ey / rho
        if code == TOA:
            chain(j, 0, ex, ey)
            for i in range(A):  # symbol index k in cT, 1 in cT0
                G[:, i, j, :, 0, nuisance[i, j, 0]] = np.arange(n) * scale[j, 0]
                G[:, i, j, :, 0, nuisance[i, j, 1]] = 1.0 * scale[j, 0]
            continue
        sj, cj, snj, rj = s[:, :, j], cos[:, :, j], sin[:, :, j], r[:, :, j]
        rphidot = rj * (sweep / cfg.window_s)
        vx = qdx[:, :, j] + rdot[:, :, 0] * cj + rphidot * -snj  # agent velocity
        vy = qdy[:, :, j] + rdot[:, :, 0] * snj + rphidot * cj
        wx, wy = qdx[:, :, j] - vx, qdy[:, :, j] - vy  # v = [qdot; 0] - pdot (v_z = 0)
        ve = wx * ex + wy * ey
        dqx, dqy = (wx - ve * ex) / rho, (wy - ve * ey) / rho
        for jb, (b, bd) in enumerate(((None, None), (sj, None), (s2[:, :, j], sj))):
            for i, (dq, e) in enumerate(((dqx, ex), (dqy, ey))):
                if col[2 * jb + i] < 0:
                    continue
                if b is None:  # b = 1, bdot = 0
                    value = dq
                else:  # bdot = 1 (theta2) or s (theta3)
                    value = dq * b + (e if bd is None else e * bd)
                np.multiply(value, -scale[j, 0], out=G[:, :, j, :, 0, col[2 * jb + i]])
        for i in range(A):
            G[:, i, j, :, 0, nuisance[i, j, 0]] = 1.0 * scale[j, 0]
    return {"times": s.reshape(K, -1), "cameras": cameras}


def _lincomb(coeffs: np.ndarray, terms: list[Any]) -> Any:
    """``sum_e coeffs[e] terms[e]`` skipping zero coefficients and ``None`` (zero) terms."""
    out: Any = 0.0
    for c, t in zip(coeffs.tolist(), terms, strict=True):
        if c != 0.0 and t is not None:
            out = out + (t if c == 1.0 else c * t)
    return out


def _dot3(a: list[Any], b: tuple[Any, ...]) -> Any:
    """``a . b`` of two 3-vectors given by components (arrays or floats)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@functools.lru_cache(maxsize=64)
def _slot_layout(config: FIMScenarioConfig) -> dict[str, Any]:
    """Where each sensor sits in the ``(A, S, n)`` candidate layout and its columns.

    ``camera`` / ``toa`` / ``doppler``: the sensor's slot ``j`` in ``S`` (-1: absent);
    ``col`` ``(6,)``: free column of each motion parameter (-1: not estimated);
    ``nuisance`` ``(A, S, 2)``: free columns of the slot's nuisance parameters.
    """
    const = problem_constants(config)
    A, S, n = config.n_agents, len(config.sensors), config.n_candidates
    full = -np.ones(const.mean.size, dtype=np.intp)
    full[const.free] = np.arange(const.free.size)
    nuisance = const.nuisance.reshape(A, S, n, 2)[:, :, 0, :]
    m = const.shape[1]
    sigma = np.sqrt(np.diagonal(const.R, axis1=1, axis2=2)).reshape(A, S, n, m)
    slots = {name: config.sensors.index(name) if name in config.sensors else -1
             for name in SENSOR_NAMES}  # fmt: skip
    return {
        **slots,
        "col": full[: km.N_MOTION].tolist(),
        "nuisance": np.where(nuisance >= 0, full[np.maximum(nuisance, 0)], -1),
        "scale": 1.0 / sigma[0, :, 0],
        "diagonal": bool(
            not np.count_nonzero(const.R - const.R * np.eye(m)) and np.all(sigma == sigma[0, :, :1])
        ),
    }


def _draw_geometry(
    const: ProblemConstants, rng: np.random.Generator
) -> tuple[float, FloatArray, FloatArray]:
    """The geometry draws of one problem from ``rng``: ``rot``, ``scales (A,)``, ``offsets``.

    ``offsets`` ``(A, S, n)``: camera and Doppler times jittered uniformly within their grid
    cells, one random phase of the TOA symbol grid per agent. Draw order (agent-major, then
    sensor) is part of the reproducibility contract.
    """
    cfg = const.config
    n = cfg.n_candidates
    rot = float(rng.uniform(0.0, 2.0 * np.pi))
    scales = rng.uniform(0.8, 1.2, cfg.n_agents)
    offsets = np.empty((cfg.n_agents, len(cfg.sensors), n))
    for i in range(cfg.n_agents):
        for j, name in enumerate(cfg.sensors):
            if name == "toa":  # regular symbol grid, random phase
                offsets[i, j] = rng.uniform(0.0, 1.0)
            else:
                offsets[i, j] = rng.uniform(0.0, 1.0, n)  # jitter within each cell
    return rot, scales, offsets


def _draw_truth(const: ProblemConstants, rng: np.random.Generator) -> FloatArray:
    """One prior draw ``theta (D,)`` from ``rng`` (velocity and curvature 0 when stationary)."""
    theta: FloatArray = const.mean + const.std * rng.standard_normal(const.mean.size)
    if const.config.stationary:
        theta[2:6] = 0.0
    return theta


def _in_front(const: ProblemConstants, theta: FloatArray, geo: dict[str, FloatArray]) -> bool:
    """Whether the target at ``theta (D,)`` is in front of every camera of one problem."""
    cam = const.camera
    depth = km.camera_depth(
        theta, geo["times"][cam], geo["positions"][cam], geo["camera_rotation"][cam],
        const.intrinsics,
    )  # fmt: skip
    return bool(np.all(depth > 0.0))


def _camera_depths(
    const: ProblemConstants, theta: FloatArray, geo: dict[str, FloatArray]
) -> FloatArray:
    """Projective depths ``(K, n_cam)`` of every camera candidate of ``K`` problems.

    :func:`~models.camera_depth` (``dd = m ([q; 0] - p)``, ``m = e3^T A R_c``, eq. 23) of
    problem ``i``'s cameras at its truth ``theta[i]`` (``theta`` ``(K, D)``; ``q`` by eq. 18),
    written out elementwise over the ``(K, n_cam)`` candidates.
    """
    if geo.get("cameras") is not None:  # the closed forms' camera slot: (K, A, n) arrays
        t, px, py, pz, mx, my, mz = geo["cameras"]
        K = t.shape[0]
        th_ = theta[:, :6, None, None]
        t2_ = 0.5 * t**2
        qx_ = th_[:, 0] + t * th_[:, 2] + t2_ * th_[:, 4]
        qy_ = th_[:, 1] + t * th_[:, 3] + t2_ * th_[:, 5]
        out: FloatArray = _dot3([mx, my, mz], (qx_ - px, qy_ - py, 0.0 - pz))
        return np.broadcast_to(out, t.shape).reshape(K, -1)
    cam = const.camera
    t = geo["times"][:, cam]
    p = geo["positions"][:, cam]
    Rc = geo["camera_rotation"][:, cam]
    A2 = const.intrinsics[2]
    m = [_lincomb(A2, [Rc[..., e, c] for e in range(3)]) for c in range(3)]
    th = theta[:, :6, None]
    t2 = 0.5 * t**2
    qx = th[:, 0] + t * th[:, 2] + t2 * th[:, 4]
    qy = th[:, 1] + t * th[:, 3] + t2 * th[:, 5]
    depth: FloatArray = _dot3(m, (qx - p[..., 0], qy - p[..., 1], 0.0 - p[..., 2]))
    return depth


def _problem_part(geo: dict[str, Any], i: int) -> dict[str, Any]:
    """Problem ``i`` of a batch's geometry (a batch of one), as :func:`_camera_depths` reads it."""
    if geo.get("cameras") is not None:
        cams = tuple(c[i : i + 1] if isinstance(c, np.ndarray) else c for c in geo["cameras"])
        return {"cameras": cams}
    return {key: geo[key][i : i + 1] for key in ("times", "positions", "camera_rotation")}


def _truth_in_front(
    const: ProblemConstants,
    rng: np.random.Generator,
    theta: FloatArray,
    part: dict[str, Any],
    args: tuple[FloatArray, FloatArray, FloatArray] | None,
    i: int,
) -> FloatArray:
    """The first of ``theta`` and its redraws from ``rng`` in front of every camera.

    Decided as :func:`make_problem`'s scalar check (:func:`_in_front` on the models'
    geometry) decides: a depth farther than :data:`_DEPTH_MARGIN` from 0 by the batched depths
    (``part``: problem ``i``'s, :func:`_problem_part`), one within it by the exact check
    (problem ``i``'s whole geometry computed for it, from ``args[.][i]`` when the batch has
    only the closed forms' part).

    Raises:
        ValueError: no truth in 100 prior draws keeps the target in front of every camera.
    """
    one: dict[str, FloatArray] | None = None
    for attempt in range(100):  # redraws from rng alone
        if attempt:
            theta = _draw_truth(const, rng)
        low = float(_camera_depths(const, theta[None], part).min())
        if low > _DEPTH_MARGIN:
            return theta
        if low < -_DEPTH_MARGIN:
            continue  # behind a camera for sure
        if one is None:
            if "positions" in part:
                one = {key: val[0] for key, val in part.items()}
            else:
                assert args is not None
                full = _geometry(const, *(a[i : i + 1] for a in args))
                one = {key: full[key][0] for key in ("times", "positions", "camera_rotation")}
        if _in_front(const, theta, one):
            return theta
    raise ValueError("prior_* std devs too wide: the true target falls behind a camera")


#: margin (m) under which a depth of the batched front check is re-tested exactly
_DEPTH_MARGIN = 1e-6


@dataclass(frozen=True, kw_only=True)
class FIMProblemBatch:
    """``K`` problems of one config: its constants plus the drawn arrays with a batch axis.

    Attributes:
        constants: the config's :class:`ProblemConstants` (shared).
        theta_true: ``(K, d)``; ``times`` ``(K, N)``; ``G`` ``(K, N, m, d)`` (read-only).
        draws: the geometry draws ``(rot (K,), scales (K, A), offsets (K, A, S, n))`` (see
            :func:`_geometry`), ``None`` for a fixed geometry.
        geometry: the rest of the geometry once computed (``positions``, ``velocities``
            ``(K, N, 3)``, ``camera_rotation`` ``(K, N, 3, 3)``, ``H`` ``(K, N, m, d)``); an
            episode needs only ``G`` and ``times``, so these are computed from ``draws`` on
            first access (the same values as if drawn eagerly) and kept.
    """

    constants: ProblemConstants
    theta_true: FloatArray
    times: FloatArray
    G: FloatArray
    draws: tuple[FloatArray, FloatArray, FloatArray] | None = None
    geometry: dict[str, FloatArray] = dataclasses.field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return int(self.theta_true.shape[0])

    def _part(self, key: str) -> FloatArray:
        if not self.geometry:
            assert self.draws is not None
            geo = _geometry(self.constants, *self.draws)
            self.geometry.update({k: _readonly(geo[k]) for k in _LAZY})
        return self.geometry[key]

    @property
    def positions(self) -> FloatArray:
        """``(K, N, 3)`` agent positions at the candidates."""
        return self._part("positions")

    @property
    def velocities(self) -> FloatArray:
        """``(K, N, 3)`` agent velocities at the candidates."""
        return self._part("velocities")

    @property
    def camera_rotation(self) -> FloatArray:
        """``(K, N, 3, 3)`` world-to-camera rotations (identity for non-cameras)."""
        return self._part("camera_rotation")

    @property
    def H(self) -> FloatArray:
        """``(K, N, m, d)`` Jacobians at the prior mean."""
        return self._part("H")

    def problem(self, i: int) -> FIMProblem:
        """Problem ``i`` as a :class:`FIMProblem` (views of the batch, no copies)."""
        c = self.constants
        return FIMProblem(
            config=c.config, theta_true=self.theta_true[i], theta_prior_mean=c.mean[c.free],
            P0=c.P0, Q0=c.Q0, H=self.H[i], R=c.R, G=self.G[i], agent=c.agent, sensor=c.sensor,
            rows=c.rows, times=self.times[i], positions=self.positions[i],
            velocities=self.velocities[i], camera_rotation=self.camera_rotation[i],
            symbol=c.symbol, nuisance=c.nuisance, intrinsics=c.intrinsics,
            param_names=c.param_names, free=c.free, theta_fixed=c.mean,
        )  # fmt: skip


def make_problems(
    config: FIMScenarioConfig, rngs: Sequence[np.random.Generator]
) -> FIMProblemBatch:
    """Draw ``K = len(rngs)`` problems, problem ``i`` from ``rngs[i]`` alone.

    Each generator is consumed exactly as :func:`make_problem` consumes it (geometry first,
    if ``randomize``, then the truth), so problem ``i`` equals ``make_problem(config, rngs[i])``
    drawn from a generator in the same state. The seed-independent part comes from
    :func:`problem_constants`; the geometry, Jacobians, whitening (``G_k = L_k^-1 H_k``) and the
    camera check of the first truth draws are batched over the ``K`` problems.

    Raises:
        ValueError: if no truth in 100 prior draws keeps the target in front of every camera.
    """
    const = problem_constants(config)
    K = len(rngs)
    if K == 0:
        raise ValueError("rngs must hold at least one generator")
    args: tuple[FloatArray, FloatArray, FloatArray] | None = None
    if const.fixed is None:
        drawn = [_draw_geometry(const, rng) for rng in rngs]
        args = (
            np.array([d[0] for d in drawn]),
            np.stack([d[1] for d in drawn]),
            np.stack([d[2] for d in drawn]),
        )
        geo = _chunked_geometry(const, args)
    else:
        geo = {key: np.broadcast_to(val, (K, *val.shape[1:])) for key, val in const.fixed.items()}
    theta = np.stack([_draw_truth(const, rng) for rng in rngs])
    cam = const.camera
    if cam.any():  # camera depth of every first draw at once, each at its own truth
        depth = _camera_depths(const, theta, geo)
        for i in np.flatnonzero(depth.min(axis=1) <= _DEPTH_MARGIN).tolist():
            theta[i] = _truth_in_front(const, rngs[i], theta[i], _problem_part(geo, i), args, i)
    ro = {
        key: _readonly(val) if val.flags.writeable else val
        for key, val in geo.items()
        if key in ("times", "G", *_LAZY)
    }
    return FIMProblemBatch(
        constants=const, theta_true=_readonly(theta[:, const.free]), times=ro.pop("times"),
        G=ro.pop("G"), draws=args, geometry=ro,
    )  # fmt: skip


#: problems per pass of the closed forms (their temporaries stay in the CPU caches)
_CHUNK = 32


def _chunked_geometry(
    const: ProblemConstants, args: tuple[FloatArray, FloatArray, FloatArray]
) -> dict[str, Any]:
    """``times``, ``G`` and the camera data of ``K`` problems, :data:`_CHUNK` at a time.

    :func:`_closed_form_pools` per chunk of problems (its temporaries stay in the CPU caches),
    ``G`` written into one ``(K, N, m, d)`` array; the whole :func:`_geometry` if the closed
    forms decline.
    """
    K = args[0].shape[0]
    N, m, d = const.shape
    G = np.empty((K, N, m, d))
    times = np.empty((K, N))
    cams: list[Any] = []
    for lo in range(0, K, _CHUNK):
        rot, scales, offsets = (a[lo : lo + _CHUNK] for a in args)
        geo = _closed_form_pools(const, rot, scales, offsets, G[lo : lo + _CHUNK])
        if geo is None:
            return _geometry(const, *args)
        times[lo : lo + _CHUNK] = geo["times"]
        cams.append(geo["cameras"])
    cameras = None
    if cams[0] is not None:
        cameras = tuple(
            np.concatenate([np.broadcast_to(c[i], c[0].shape) for c in cams])
            for i in range(len(cams[0]))
        )
    return {"times": times, "G": G, "cameras": cameras}


#: the geometry of a :class:`FIMProblemBatch` computed on demand
_LAZY = ("positions", "velocities", "camera_rotation", "H")


def make_problem(config: FIMScenarioConfig, rng: np.random.Generator) -> FIMProblem:
    """Draw one problem: geometry (if ``randomize``), truth from the prior; build ``H, R, G``.

    All randomness comes from ``rng`` (geometry first, then the truth); the rest is
    :func:`problem_constants` (cached per config). The one-problem case of
    :func:`make_problems`.

    Raises:
        ValueError: if no truth in 100 prior draws keeps the target in front of every camera.
    """
    return make_problems(config, [rng]).problem(0)
