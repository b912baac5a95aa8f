"""Cooperative localization with occasional relative measurements (Chen & Kia 2022, Sec. IV).

``n_agents`` walkers each run a local filter on their own state (model ``"ins"``: 9 states
driven by a noisy IMU; ``"unicycle"``: 3 states driven by noisy odometry). Some agents
(``beacon_agents``) range to beacons at known positions every ``beacon_every`` steps (an EKF
update); every ``relative_every`` steps each directed pair ``(i, j)`` of ``relative_pairs``
yields a relative range (and optionally bearing) that agent ``i`` processes with agent ``j``'s
belief, *without* the cross-covariance, by one of the fusion methods:

| method | update of agent i |
|---|---|
| ``naive`` | EKF pretending the beliefs are independent (inconsistent over time) |
| ``ci`` | discorrelated bound eq. (4) with the weight minimising ``tr P`` (CI's trace criterion) |
| ``dmv`` | DMV, eqs. (4)-(6) (:func:`selenv.core.fusion.dmv_update`) |
| ``pecmv`` | PECMV, eqs. (7)-(9) (:func:`selenv.core.fusion.pecmv_update`) |
| ``ldmv`` / ``lpecmv`` | the DMV / PECMV update with omega / C predicted by the shipped surrogate |
| ``lpecmv_full`` | PECMV with the full-``C`` surrogate (method 1) instead of the diagonal one |
| ``lpecmv_objective`` | PECMV with a diagonal-``C`` surrogate trained on the objective eq. (8a) |

The learned rules use the shipped checkpoint trained for the scenario's ``n``, ``m`` and
relative noise ``R`` (:func:`check_learned_fusion`): range only (``bearing_sigma_deg=None``,
m = 1) -> ``checkpoints/ldmv.pt`` / ``lpecmv.pt``; range + bearing at the trained 2 deg
(m = 2) -> ``ldmv_m2.pt`` / ``lpecmv_m2.pt``. Any other noise (another ``range_sigma`` or
``bearing_sigma_deg``, the unicycle model) is a ``ValueError`` at construction naming
``fusion`` and ``bearing_sigma_deg`` and listing the shipped checkpoints: the features of
eq. (13) do not contain ``R``, so a network trained for another noise would be silently wrong.

with ``A = H_i P_i H_i^T``, ``B = H_j P_j H_j^T``. ``dead_reckoning`` processes nothing (the
paper's "ZUPT-only" column; ins agents still get their velocity pseudo-measurements, see
``zupt_every``). Tracks: ``rectangle`` (rounded), ``circle``, ``lemniscate``.
Truth: a guidance law turns each track into true inputs, integrated with the filter's own
model, so the models are exact and only the noises differ. Every random draw (input noise,
measurement noise, initial errors) comes from the generator of :func:`make_cl_problem`, so all
fusion methods see the same noise for the same seed.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray, logdet_spd
from selenv.families.cooperative import batched
from selenv.families.cooperative.models import MODELS, AgentModel
from selenv.families.landmarks import models as lm
from selenv.scenarios.validation import (
    ArgumentTypeError,
    check_choice,
    check_integer,
    check_real,
    check_reals,
    describe,
)

__all__ = [
    "FUSION_METHODS",
    "MAX_AGENTS",
    "MAX_STEPS",
    "TRACKS",
    "CLConfig",
    "CLProblem",
    "CLSimulation",
    "check_learned_fusion",
    "fuse_relative",
    "input_sigmas",
    "make_cl_problem",
    "relative_noise_cov",
]

FUSION_METHODS = (
    "dead_reckoning", "naive", "ci", "dmv", "pecmv", "ldmv", "lpecmv", "lpecmv_full",
    "lpecmv_objective",
)  # fmt: skip
#: the fusion methods that need a shipped learned surrogate
LEARNED_FUSIONS = ("ldmv", "lpecmv", "lpecmv_full", "lpecmv_objective")
TRACKS = ("rectangle", "circle", "lemniscate")
_DEG = np.pi / 180.0


#: largest team (``n_agents``): the env has ``n (n - 1)`` directed pairs
MAX_AGENTS = 32
#: longest episode / cadence in steps (the noise of every step is drawn at reset)
MAX_STEPS = 100_000

#: valid range of every real-valued :class:`CLConfig` field: ``(low, high, unit)``
RANGES: dict[str, tuple[float, float, str]] = {
    "dt": (1e-3, 1.0, "s"),  # IMU / odometry rates of 1 Hz to 1 kHz
    "track_size": (0.5, 1000.0, "m"),
    "speed": (0.01, 20.0, "m/s"),
    "input_sigma": (1e-6, 100.0, "(m/s^2 or m/s, deg/s)"),
    "beacons": (-1e5, 1e5, "m"),
    "range_sigma": (1e-3, 100.0, "m"),
    "bearing_sigma_deg": (1e-3, 90.0, "deg"),
    "zupt_sigma": (1e-4, 10.0, "m/s"),
}
#: valid range of each entry of ``init_sigma`` (position, velocity, attitude)
INIT_SIGMA_RANGES: tuple[tuple[float, float, str], ...] = (
    (1e-3, 1e3, "m"),
    (1e-4, 100.0, "m/s"),
    (1e-3, 90.0, "deg"),
)


def _names(value: Any, name: str, choices: Sequence[str]) -> tuple[str, ...]:
    """A non-empty tuple of names taken from ``choices``."""
    if not isinstance(value, tuple | list) or not value:
        raise ArgumentTypeError(
            f"{name} must be a non-empty tuple of names from {tuple(choices)}, "
            f"got {describe(value)}"
        )
    return tuple(check_choice(v, f"{name}[{i}]", choices) for i, v in enumerate(value))


def _rows(value: Any, name: str, width: int, what: str) -> list[Any]:
    """``value`` as a list of rows of ``width`` items (tuples, lists or 1-D arrays)."""
    rows = list(value) if isinstance(value, tuple | list | np.ndarray) else None
    if rows is None or any(
        not isinstance(r, tuple | list | np.ndarray) or len(r) != width for r in rows
    ):
        raise ArgumentTypeError(f"{name} must be a sequence of {what}, got {describe(value)}")
    return rows


@dataclass(frozen=True, kw_only=True)
class CLConfig:
    """Scenario parameters (defaults: two pedestrians, the paper's agent-1/agent-2 roles).

    Every field is validated: a wrong type is a ``TypeError`` (also a ``ValueError``), a value
    outside its range a ``ValueError``, naming the field and the range.

    Attributes:
        n_agents: number of agents, an int in ``[1, MAX_AGENTS]`` (32).
        model: ``"ins"`` (9 states) or ``"unicycle"`` (3 states).
        horizon: number of steps, an int in ``[1, MAX_STEPS]`` (100 000).
        dt: step (s), in ``[1e-3, 1]``.
        tracks: track per agent (cycled): ``rectangle``, ``circle``, ``lemniscate``.
        track_size: half-width of the tracks (m), in ``[0.5, 1000]``.
        speed: walking speed (m/s), in ``[0.01, 20]``.
        input_sigma: per-agent input noise, ``((accel m/s^2, gyro deg/s), ...)`` for ins or
            ``((speed m/s, turn rate deg/s), ...)`` for unicycle, cycled over agents; every
            entry in ``[1e-6, 100]``.
        beacons: beacon positions ``((x, y, z), ...)`` (m), coordinates in ``[-1e5, 1e5]``.
        beacon_agents: agents (ints in ``[0, n_agents)``) that range to the beacons;
            ``beacon_every``: steps between, an int in ``[1, MAX_STEPS]``.
        relative_pairs: directed pairs ``(i, j)`` of ints, ``i != j`` in ``[0, n_agents)``:
            ``i`` measures ``j``; ``relative_every``: steps between, in ``[1, MAX_STEPS]``.
        range_sigma: range noise (m), in ``[1e-3, 100]``; ``bearing_sigma_deg``: bearing noise
            (deg) in ``[1e-3, 90]``, ``None``: no bearing.
        init_sigma: initial error ``(position m, velocity m/s, attitude deg)`` (unicycle uses
            position and attitude), in ``[1e-3, 1e3]``, ``[1e-4, 100]``, ``[1e-3, 90]``.
        zupt_every: ins only: every this many steps (an int in ``[1, MAX_STEPS]``) each agent's
            filter gets a velocity pseudo-measurement (true velocity + N(0, zupt_sigma^2)),
            standing in for the zero-velocity updates of the paper's ZUPT-aided pedestrian
            INS; ``None``: none. ``zupt_sigma`` (m/s) in ``[1e-4, 10]``.
    """

    n_agents: int = 2
    model: str = "ins"
    horizon: int = 600
    dt: float = 0.1
    tracks: tuple[str, ...] = ("rectangle", "rectangle")
    track_size: float = 6.0
    speed: float = 1.0
    input_sigma: tuple[tuple[float, float], ...] = ((0.02, 0.05), (0.06, 0.2))
    beacons: tuple[tuple[float, float, float], ...] = ((-8.0, -8.0, 2.0), (8.0, 8.0, 2.0))
    beacon_agents: tuple[int, ...] = (0,)
    beacon_every: int = 10
    relative_pairs: tuple[tuple[int, int], ...] = ((1, 0), (0, 1))
    relative_every: int = 5
    range_sigma: float = 0.1
    bearing_sigma_deg: float | None = None
    init_sigma: tuple[float, float, float] = (0.5, 0.1, 0.5)
    zupt_every: int | None = 5
    zupt_sigma: float = 0.05

    def __post_init__(self) -> None:
        put = object.__setattr__
        n = check_integer(self.n_agents, "n_agents", 1, MAX_AGENTS)
        put(self, "n_agents", n)
        put(self, "model", check_choice(self.model, "model", sorted(MODELS)))
        for name in ("horizon", "beacon_every", "relative_every"):
            put(self, name, check_integer(getattr(self, name), name, 1, MAX_STEPS))
        # cadences are whole steps (NaN, 2.5 refused); None switches the ZUPTs off
        if self.zupt_every is not None:
            put(self, "zupt_every", check_integer(self.zupt_every, "zupt_every", 1, MAX_STEPS))
        for name in ("dt", "track_size", "speed", "range_sigma", "zupt_sigma"):
            low, high, unit = RANGES[name]
            put(self, name, check_real(getattr(self, name), name, low, high, unit=unit))
        if self.bearing_sigma_deg is not None:
            low, high, unit = RANGES["bearing_sigma_deg"]
            sigma = check_real(self.bearing_sigma_deg, "bearing_sigma_deg", low, high, unit=unit)
            put(self, "bearing_sigma_deg", sigma)
        put(self, "tracks", _names(self.tracks, "tracks", TRACKS))
        low, high, unit = RANGES["input_sigma"]
        rows = _rows(self.input_sigma, "input_sigma", 2, "(s1, s2) pairs")
        if not rows:
            raise ValueError("input_sigma must hold at least one (s1, s2) pair, got ()")
        put(self, "input_sigma", tuple(
            check_reals(r, f"input_sigma[{i}]", 2, low, high, unit=unit)
            for i, r in enumerate(rows)
        ))  # fmt: skip
        low, high, unit = RANGES["beacons"]
        put(self, "beacons", tuple(
            check_reals(b, f"beacons[{i}]", 3, low, high, unit=unit)
            for i, b in enumerate(_rows(self.beacons, "beacons", 3, "(x, y, z) triples"))
        ))  # fmt: skip
        if not isinstance(self.beacon_agents, tuple | list):
            got = describe(self.beacon_agents)
            raise ArgumentTypeError(f"beacon_agents must be a tuple of agent indices, got {got}")
        put(self, "beacon_agents", tuple(
            check_integer(i, "beacon_agents entry", 0, n - 1) for i in self.beacon_agents
        ))  # fmt: skip
        pairs = []
        for k, pair in enumerate(_rows(self.relative_pairs, "relative_pairs", 2, "(i, j) pairs")):
            i, j = (check_integer(a, f"relative_pairs[{k}]", 0, n - 1) for a in pair)
            if i == j:
                raise ValueError(f"relative_pairs holds {(i, j)!r}: need (i, j), i != j")
            pairs.append((i, j))
        put(self, "relative_pairs", tuple(pairs))
        init = _rows([self.init_sigma], "init_sigma", 3, "3 numbers (position, velocity, attitude)")
        put(self, "init_sigma", tuple(
            check_real(v, f"init_sigma[{i}]", low, high, unit=unit)
            for i, (v, (low, high, unit)) in enumerate(zip(init[0], INIT_SIGMA_RANGES, strict=True))
        ))  # fmt: skip

    @property
    def agent_model(self) -> AgentModel:
        """The :class:`AgentModel` of every agent."""
        return MODELS[self.model]

    def input_sigma_of(self, i: int) -> tuple[float, float]:
        """Input noise of agent ``i`` in SI units (rad for angles)."""
        a, b = self.input_sigma[i % len(self.input_sigma)]
        return float(a), float(b) * _DEG

    def P0(self) -> FloatArray:
        """Initial covariance (n, n)."""
        sp, sv, sa = self.init_sigma
        if self.model == "ins":
            return np.diag(np.repeat([sp**2, sv**2, (sa * _DEG) ** 2], 3))
        return np.diag([sp**2, sp**2, (sa * _DEG) ** 2])


@dataclass(frozen=True, kw_only=True, eq=False)
class CLProblem:
    """One seeded realisation: truth, inputs and every noise draw (arrays read-only).

    Attributes:
        config: the :class:`CLConfig`.
        states: (T + 1, A, n) true states; inputs_true / inputs: (T, A, n_input).
        beacons: (nb, 3); beacon_noise: (T, A, nb); relative_noise: (T, n_pairs, m);
        zupt_noise: (T, A, 3).
        x0_hat: (A, n) initial estimates, truth + N(0, P0).
    """

    config: CLConfig
    states: FloatArray
    inputs_true: FloatArray
    inputs: FloatArray
    beacons: FloatArray
    beacon_noise: FloatArray
    relative_noise: FloatArray
    zupt_noise: FloatArray
    x0_hat: FloatArray


#: samples of each rectangle corner arc and points of each polyline segment of :func:`_track`
_ARC_SAMPLES, _SEG_POINTS = 200, 20


def _polyline(pts: FloatArray, num: int) -> FloatArray:
    """``num`` points on each segment ``pts[s] -> pts[s + 1]`` (start included, end not).

    Vectorised ``np.concatenate([np.linspace(pts[s], pts[s + 1], num, endpoint=False) for s])``
    with the same floating-point operations (bit for bit): ``y_k = k step + start``,
    ``step = delta / num``, ``delta = pts[s + 1] - pts[s]``; where a component of ``step`` is
    zero numpy's ``linspace`` forms ``y_k = (k / num) delta + start`` instead, and so does this.
    ``pts`` (S + 1, 2) -> (S num, 2).
    """
    start, delta = pts[:-1], pts[1:] - pts[:-1]  # (S, 2)
    k = np.arange(num, dtype=np.float64)[None, :, None]  # (1, num, 1)
    step = delta / num
    y = k * step[:, None, :]
    zero = (step == 0).any(axis=1)  # linspace's denormal guard, per segment
    if zero.any():
        y[zero] = (k / num) * delta[zero][:, None, :]
    y += start[:, None, :]
    return y.reshape(-1, pts.shape[1])


@functools.lru_cache(maxsize=64)
def _track_shape(kind: str, size: float) -> tuple[FloatArray, FloatArray]:
    """``(pts (N, 2), arc (N,))``: the closed polyline of a track and its arc length (read-only).

    Seed-independent, so computed once per ``(kind, size)``.
    """
    t = np.linspace(0.0, 2 * np.pi, 4001)
    if kind == "circle":
        pts = size * np.stack([np.cos(t), np.sin(t)], -1)
    elif kind == "lemniscate":  # Gerono
        pts = size * np.stack([np.sin(t), np.sin(t) * np.cos(t)], -1)
    else:  # rectangle 2 size x 1.2 size with corner radius 0.3 size, counter-clockwise
        w, h, r = size, 0.6 * size, 0.3 * size
        corners = np.array(
            [
                (w - r, h - r, 0.0),
                (-(w - r), h - r, 0.5),
                (-(w - r), -(h - r), 1.0),
                (w - r, -(h - r), 1.5),
            ]
        )
        ang = np.pi * (corners[:, 2:3] + np.linspace(0.0, 0.5, _ARC_SAMPLES))  # (4, 200)
        segs = np.stack(
            [corners[:, 0:1] + r * np.cos(ang), corners[:, 1:2] + r * np.sin(ang)], -1
        ).reshape(-1, 2)
        pts = _polyline(np.concatenate([segs, segs[:1]]), _SEG_POINTS)
        pts = np.concatenate([pts, pts[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    pts.setflags(write=False)
    arc.setflags(write=False)
    return pts, arc


@functools.lru_cache(maxsize=64)
def _track(kind: str, n_steps: int, dt: float, size: float, speed: float, phase: float) -> Any:
    """Desired horizontal positions (n_steps + 2, 2), walked at exactly ``speed`` (arc length).

    Cached per arguments (seed-independent); the array is read-only.
    """
    pts, arc = _track_shape(kind, size)
    length = arc[-1]
    s = (phase / (2 * np.pi) * length + speed * dt * np.arange(n_steps + 2)) % length
    out = np.stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])], -1)
    out.setflags(write=False)
    return out


def _truth(cfg: CLConfig, i: int) -> tuple[FloatArray, FloatArray]:
    """True states (T + 1, n) and inputs (T, n_input) of agent ``i`` (guided tracking)."""
    model, T, dt = cfg.agent_model, int(cfg.horizon), float(cfg.dt)
    track = cfg.tracks[i % len(cfg.tracks)]
    des = _track(track, T, dt, cfg.track_size, cfg.speed, 2 * np.pi * i / max(cfg.n_agents, 1))
    vel = np.gradient(des, dt, axis=0)
    acc = np.gradient(vel, dt, axis=0)
    x = np.zeros(model.n)
    x[:2] = des[0]
    if model.name == "ins":
        x[2] = 1.0
        x[3:5] = vel[0]
        x[8] = np.arctan2(vel[0, 0], vel[0, 1])  # yaw: course clockwise from North
    else:
        x[2] = np.arctan2(vel[0, 1], vel[0, 0])
    states, inputs = np.empty((T + 1, model.n)), np.empty((T, model.n_input))
    states[0] = x
    for k in range(T):
        if model.name == "ins":
            a = np.zeros(3)
            a[:2] = acc[k] + 2.0 * (vel[k] - x[3:5]) + 1.0 * (des[k] - x[:2])
            a[2] = -1.0 * (x[2] - 1.0) - 2.0 * x[5]
            course = np.arctan2(x[3], x[4])
            rate = float(lm.wrap_angle(np.arctan2(vel[k + 1, 0], vel[k + 1, 1]) - course)) / dt
            theta_dot = np.array(
                [-2.0 * x[6], -2.0 * x[7], rate + 2.0 * float(lm.wrap_angle(course - x[8]))]
            )
            f_b = lm.euler_to_dcm(x[6:9]).T @ (a + np.array([0.0, 0.0, lm.GRAVITY]))
            u = np.concatenate([f_b, lm.body_rates_from_euler_rates(x[6:9], theta_dot)])
        else:
            aim = des[k + 1] - x[:2]
            w = float(lm.wrap_angle(np.arctan2(aim[1], aim[0]) - x[2])) / dt
            u = np.array([min(float(np.linalg.norm(aim)) / dt, 3 * cfg.speed), 0.5 * w])
        inputs[k] = u
        x = model.propagate(x, u, dt)
        states[k + 1] = x
    return states, inputs


#: the :class:`CLConfig` fields the truth depends on (:func:`_truth`)
_TRUTH_FIELDS = ("n_agents", "model", "horizon", "dt", "tracks", "track_size", "speed")


@functools.lru_cache(maxsize=16)
def _truths(key: tuple[Any, ...]) -> tuple[FloatArray, FloatArray]:
    """``(states (T + 1, A, n), inputs_true (T, A, n_input))`` of every agent, read-only.

    The truth is deterministic (no random draw), so it is computed once per value of the
    fields :data:`_TRUTH_FIELDS` (``key``, in that order) and shared by every realisation.
    """
    cfg = CLConfig(**dict(zip(_TRUTH_FIELDS, key, strict=True)), relative_pairs=())
    truths = [_truth(cfg, i) for i in range(int(cfg.n_agents))]
    states = np.stack([s for s, _ in truths], axis=1)  # (T+1, A, n)
    inputs_true = np.stack([u for _, u in truths], axis=1)
    states.setflags(write=False)
    inputs_true.setflags(write=False)
    return states, inputs_true


@dataclass(frozen=True, eq=False)
class _Static:
    """The seed-independent part of a realisation of one :class:`CLConfig` (read-only arrays).

    Attributes:
        states: (T + 1, A, n) truth; inputs_true: (T, A, n_input) true inputs.
        scale: (A, n_input) input noise std; beacons: (nb, 3); L0T: (n, n) ``chol(P0)^T``.
        m: relative measurement size; P0: (n, n); sigma: (A, 2) input noise (SI units).
    """

    states: FloatArray
    inputs_true: FloatArray
    scale: FloatArray
    beacons: FloatArray
    L0T: FloatArray
    m: int
    P0: FloatArray
    sigma: FloatArray


@functools.lru_cache(maxsize=16)
def _static(cfg: CLConfig) -> _Static:
    """:class:`_Static` of ``cfg``, computed once per configuration."""
    A = int(cfg.n_agents)
    states, inputs_true = _truths(tuple(getattr(cfg, f) for f in _TRUTH_FIELDS))
    scale = np.array(
        [np.repeat(cfg.input_sigma_of(i), cfg.agent_model.n_input // 2) for i in range(A)]
    )
    beacons = np.asarray(cfg.beacons, dtype=float).reshape(-1, 3)
    P0 = cfg.P0()
    L0T = np.asarray(np.linalg.cholesky(P0), np.float64).T
    sigma = np.array([cfg.input_sigma_of(i) for i in range(A)], dtype=np.float64)
    for arr in (scale, beacons, P0, L0T, sigma):
        arr.setflags(write=False)
    m = 1 if cfg.bearing_sigma_deg is None else 2
    return _Static(states, inputs_true, scale, beacons, L0T, m, P0, sigma)


def make_cl_problem(
    config: CLConfig | None = None, rng: np.random.Generator | None = None
) -> CLProblem:
    """Draw a realisation (truth, then input, ZUPT, beacon, relative noise and initial errors).

    The truth is deterministic (computed once per configuration); the draws come from ``rng``
    in that order.

    Args:
        config: scenario parameters (default :class:`CLConfig`).
        rng: the generator of every draw.
    """
    cfg = CLConfig() if config is None else config
    rng = np.random.default_rng() if rng is None else rng
    A, T, n = int(cfg.n_agents), int(cfg.horizon), cfg.agent_model.n
    st = _static(cfg)
    states, inputs_true, beacons = st.states, st.inputs_true, st.beacons
    inputs = inputs_true + rng.standard_normal(inputs_true.shape) * st.scale[None]
    zupt_noise = cfg.zupt_sigma * rng.standard_normal((T, A, 3))
    beacon_noise = cfg.range_sigma * rng.standard_normal((T, A, beacons.shape[0]))
    relative_noise = rng.standard_normal((T, len(cfg.relative_pairs), st.m))
    relative_noise[..., 0] *= cfg.range_sigma
    if st.m == 2:
        relative_noise[..., 1] *= float(cfg.bearing_sigma_deg) * _DEG  # type: ignore[arg-type]
    x0_hat = states[0] + rng.standard_normal((A, n)) @ st.L0T
    for arr in (inputs, beacon_noise, relative_noise, zupt_noise, x0_hat):
        arr.setflags(write=False)
    return CLProblem(
        config=cfg,
        states=states,
        inputs_true=inputs_true,
        inputs=inputs,
        beacons=beacons,
        beacon_noise=beacon_noise,
        relative_noise=relative_noise,
        zupt_noise=zupt_noise,
        x0_hat=x0_hat,
    )


def input_sigmas(config: CLConfig) -> FloatArray:
    """(A, 2) input noise of every agent in SI units (:meth:`CLConfig.input_sigma_of`; cached)."""
    return _static(config).sigma


def relative_noise_cov(config: CLConfig) -> FloatArray:
    """``R`` (m, m) of a relative measurement: ``diag(range_sigma^2[, (bearing_sigma rad)^2])``."""
    m = 1 if config.bearing_sigma_deg is None else 2
    return np.diag([config.range_sigma**2, (float(config.bearing_sigma_deg or 0) * _DEG) ** 2][:m])


def check_learned_fusion(config: CLConfig, fusion: str) -> Any:
    """The shipped surrogate a learned ``fusion`` uses on scenarios ``config`` (else ``None``).

    ``fusion``: one of :data:`LEARNED_FUSIONS`; the surrogate is the one trained for
    the scenario's ``n`` (model), ``m`` and ``R`` (:func:`relative_noise_cov`).

    Raises:
        ValueError: no shipped surrogate matches (names ``fusion``, ``bearing_sigma_deg``,
            ``range_sigma``, ``model`` and lists the shipped checkpoints).
    """
    if fusion not in LEARNED_FUSIONS:
        return None
    from selenv.core import fusion as core_fusion  # deferred: keeps scenarios importable

    R = relative_noise_cov(config)
    try:
        return core_fusion.load_surrogate(fusion, R=R, n=config.agent_model.n)
    except ValueError as exc:
        bearing = config.bearing_sigma_deg
        raise ValueError(
            f"fusion={fusion!r} needs a shipped surrogate trained for this scenario "
            f"(model={config.model!r}: n = {config.agent_model.n}; bearing_sigma_deg={bearing!r}"
            f", range_sigma={config.range_sigma!r}: m = {R.shape[0]}, R = {R.tolist()}), and "
            f"there is none: {exc}. Use the noise of a shipped one (bearing_sigma_deg=None for "
            f"range only, or the trained bearing_sigma_deg), an exact fusion ('dmv', 'pecmv') "
            + (
                f"or train one: python -m selenv.train.train_surrogate --kind "
                f"{'ldmv' if fusion == 'ldmv' else 'lpecmv'}"
                + (" --method 1" if fusion == "lpecmv_full" else "")
                + (" --objective-loss" if fusion == "lpecmv_objective" else "")
                + (f" --bearing-sigma-deg {bearing}" if bearing is not None else "")
                if config.model == "ins"
                else "(the training script generates model='ins' scenarios only)"
            )
        ) from None


def fuse_relative(
    method: str,
    x_i: FloatArray,
    P_i: FloatArray,
    P_j: FloatArray,
    H_i: FloatArray,
    H_j: FloatArray,
    R: FloatArray,
    residual: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Agent ``i``'s posterior ``(x, P)`` from a relative measurement with unknown correlation.

    One row of :func:`selenv.families.cooperative.batched.fuse` (the batched rules).

    Args:
        method: one of ``naive``, ``ci``, ``dmv``, ``pecmv`` or a learned rule (module table).
        x_i: (n,) prior mean of agent i.
        P_i: (n, n) prior covariance of agent i.
        P_j: (n, n) prior covariance of agent j.
        H_i: (m, n) Jacobian w.r.t. agent i.
        H_j: (m, n) Jacobian w.r.t. agent j.
        R: (m, m) measurement noise.
        residual: (m,) ``z - h(x_i, x_j)`` (angles wrapped).
    """
    arrays = (x_i, P_i, P_j, H_i, H_j, residual)
    x_b, P_ib, P_jb, H_ib, H_jb, r_b = (np.asarray(a, dtype=np.float64)[None] for a in arrays)
    x, P = batched.fuse(method, x_b, P_ib, P_jb, H_ib, H_jb, np.asarray(R, np.float64), r_b)
    return x[0], P[0]


class CLSimulation:
    """All agents' local filters on one :class:`CLProblem`, step by step.

    The filter math is :mod:`selenv.families.cooperative.batched` with one realisation
    (``B = 1``), the functions the vector env calls with all of its sub-envs.

    Args:
        problem: the realisation.
        fusion: one of :data:`FUSION_METHODS`; a learned one needs a shipped surrogate trained
            for the scenario's noise (:func:`check_learned_fusion`).

    Raises:
        ValueError: unknown ``fusion``, or a learned ``fusion`` without a matching surrogate.

    Attributes:
        x: (A, n) estimates; P: (A, n, n) covariances; k: steps done.
    """

    def __init__(self, problem: CLProblem, fusion: str = "dmv") -> None:
        if fusion not in FUSION_METHODS:
            raise ValueError(f"fusion must be one of {FUSION_METHODS}, got {fusion!r}")
        self.problem, self.fusion = problem, fusion
        cfg = problem.config
        self.model = cfg.agent_model
        self.x = problem.x0_hat.copy()
        self.P = np.repeat(_static(cfg).P0[None], cfg.n_agents, axis=0)
        self.k = 0
        self.R_rel = relative_noise_cov(cfg)
        self._sigma = input_sigmas(cfg)
        self._pairs = np.asarray(cfg.relative_pairs, dtype=np.intp).reshape(-1, 2)
        check_learned_fusion(cfg, fusion)  # a learned fusion without a matching network: now

    @property
    def truth(self) -> FloatArray:
        """(A, n) true states at the current step."""
        return self.problem.states[self.k]

    def predict(self) -> None:
        """Propagate every agent with its noisy input (EKF prediction); ``k += 1``."""
        cfg = self.problem.config
        u = self.problem.inputs[self.k]
        batched.predict(self.model, self.x[None], self.P[None], u[None], cfg.dt, self._sigma)
        self.k += 1

    def zupt_updates(self) -> None:
        """Velocity pseudo-measurements of every ins agent (every ``zupt_every`` steps)."""
        cfg = self.problem.config
        if cfg.model != "ins" or cfg.zupt_every is None or self.k % cfg.zupt_every:
            return
        noise = self.problem.zupt_noise[self.k - 1]
        batched.zupt_updates(
            self.x[None], self.P[None], self.truth[None, :, 3:6], noise[None], cfg.zupt_sigma
        )

    def beacon_updates(self) -> None:
        """EKF range updates of the beacon agents (every ``beacon_every`` steps)."""
        cfg = self.problem.config
        if self.fusion == "dead_reckoning" or self.k % cfg.beacon_every:
            return
        batched.beacon_updates(
            self.model,
            self.x[None],
            self.P[None],
            self.truth[None],
            cfg.beacon_agents,
            self.problem.beacons,
            self.problem.beacon_noise[self.k - 1][None],
            cfg.range_sigma,
        )

    def available(self) -> list[int]:
        """Indices into ``relative_pairs`` measured at this step."""
        cfg = self.problem.config
        if self.k % cfg.relative_every:
            return []
        return list(range(len(cfg.relative_pairs)))

    def _terms(self, ps: np.ndarray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(H_i, H_j (K, m, n), residual (K, m))`` of the relative measurements ``ps`` (K,)."""
        ij = self._pairs[ps]
        truth = self.truth
        return batched.relative_terms(
            self.model,
            self.x[ij[:, 0]],
            self.x[ij[:, 1]],
            truth[ij[:, 0]],
            truth[ij[:, 1]],
            self.problem.relative_noise[self.k - 1, ps],
            self.problem.config.bearing_sigma_deg is not None,
        )

    def relative_terms(self, p: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(H_i, H_j, residual)`` of relative measurement ``p`` at this step."""
        H_i, H_j, res = self._terms(np.array([p], dtype=np.intp))
        return H_i[0], H_j[0], res[0]

    def relative_jacobians(self, ps: Sequence[int] | np.ndarray) -> tuple[FloatArray, FloatArray]:
        """``(H_i, H_j)`` stacked ``(K, m, n)`` for the relative measurements ``ps`` now."""
        ij = self._pairs[np.asarray(ps, dtype=np.intp)]
        bearing = self.problem.config.bearing_sigma_deg is not None
        return batched.relative_jacobians(self.model, self.x[ij[:, 0]], self.x[ij[:, 1]], bearing)

    def preview(self, p: int, method: str | None = None) -> tuple[FloatArray, FloatArray]:
        """Agent ``i``'s posterior ``(x, P)`` if relative measurement ``p`` were processed now."""
        i, j = self.problem.config.relative_pairs[p]
        H_i, H_j, residual = self._terms(np.array([p], dtype=np.intp))
        x, P = batched.fuse(
            method or self.fusion,
            self.x[i : i + 1],
            self.P[i : i + 1],
            self.P[j : j + 1],
            H_i,
            H_j,
            self.R_rel,
            residual,
        )
        return x[0], P[0]

    def relative_update(self, p: int, method: str | None = None) -> float:
        """Process relative measurement ``p``; return the drop in ``log det P_i`` (nats)."""
        i = self.problem.config.relative_pairs[p][0]
        before = float(logdet_spd(self.P[i], "P_i"))
        self.apply_relative(p, method)
        return before - float(logdet_spd(self.P[i], "P_i"))

    def apply_relative(self, p: int, method: str | None = None) -> None:
        """Process relative measurement ``p`` (:meth:`relative_update` without its log dets)."""
        i = self.problem.config.relative_pairs[p][0]
        self.x[i], self.P[i] = self.preview(p, method)

    def step(self, pairs: Sequence[int] | None = None) -> None:
        """Predict, beacon updates, then the relative updates ``pairs`` (default: all available)."""
        self.predict()
        self.zupt_updates()
        self.beacon_updates()
        if self.fusion == "dead_reckoning":
            return
        for p in self.available() if pairs is None else pairs:
            self.relative_update(p)

    def position_errors(self) -> FloatArray:
        """(A,) horizontal position errors (m)."""
        return np.linalg.norm(self.x[:, :2] - self.truth[:, :2], axis=1)

    def nees_position(self) -> FloatArray:
        """(A,) NEES of the horizontal position, ``e^T P_pos^-1 e`` (2 dof)."""
        e = self.x[:, :2] - self.truth[:, :2]
        return np.einsum("ai,ai->a", e, np.linalg.solve(self.P[:, :2, :2], e[..., None])[..., 0])
