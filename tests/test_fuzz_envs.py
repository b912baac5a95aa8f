"""Property-based fuzz suite of the environments: constructors and ``step()``.

Every registered id ``selenv/...`` is built through ``gymnasium.make`` and every PettingZoo
module through ``parallel_env()``. Properties:

(a) constructors: each keyword gets, one at a time, every value of a catalogue of invalid
    values for its kind (wrong type, NaN/inf, 1e+-300, fractional int, out of range, unknown
    option, wrong shape, ...): ``TypeError`` / ``ValueError`` naming the keyword, nothing else
    (``test_bad_keyword_value_is_rejected_naming_it``). Unknown keywords are ``TypeError``
    naming them. Hypothesis also throws arbitrary values at every keyword: a clean rejection
    naming it or a working env (``test_arbitrary_keyword_value_is_rejected_or_works``).
(b) valid configurations drawn across the documented ranges (bounds included) build, reset
    and step with finite rewards, finite observations inside the observation space.
(c) ``step()`` with an action outside the action space (floats, bools, strings, wrong shapes,
    out of range, NaN, ...) raises ``TypeError`` / ``ValueError`` naming the action, and
    changes nothing: the next valid step gives the same result as on a twin env that never
    saw the bad call (and a masked action with ``invalid_action="raise"`` likewise). Numpy
    integers of every dtype and shape ``()`` / ``(1,)`` arrays are valid actions.

The documented ranges live in the ``KEYWORDS`` tables below (the constructors' docstrings say
the same). Profiles: ``fuzz-ci`` by default, ``SELENV_FUZZ=long`` for more examples and the
``fuzz_long`` tests (largest sizes, long episodes).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from conftest import fuzz_settings
from hypothesis import given, note
from hypothesis import strategies as st

import selenv  # noqa: F401  (registers the ids)
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1

pytestmark = pytest.mark.fuzz

CL, FIM, LM, RC = (
    "selenv/CLScheduling-v1",
    "selenv/FIMSelection-v1",
    "selenv/LandmarkSelection-v1",
    "selenv/ReceiverClustering-v1",
)
MA_FIM, MA_RC = "fim_selection_v0", "receiver_clustering_v1"
MODULES = {MA_FIM: fim_selection_v0, MA_RC: receiver_clustering_v1}

# ============================================================================ strategies


def log_uniform(low: float, high: float) -> st.SearchStrategy[float]:
    """Floats spread over the decades of ``[low, high]`` (``low > 0``), bounds included."""
    lo, hi = math.log10(low), math.log10(high)
    inner = st.floats(lo, hi).map(lambda e: min(max(10.0**e, low), high))
    return st.one_of(st.sampled_from([low, high]), inner)


def real_in(low: float, high: float) -> st.SearchStrategy[float]:
    """Floats in ``[low, high]``, log-spread when ``low > 0``, bounds included."""
    if low > 0:
        return log_uniform(low, high)
    return st.one_of(st.sampled_from([low, high]), st.floats(low, high))


#: a valid integer as a Python int or any numpy integer type
def int_in(low: int, high: int) -> st.SearchStrategy[Any]:
    dtypes = [int, np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint64]
    return (
        st.tuples(st.integers(low, high), st.sampled_from(dtypes))
        .filter(lambda t: np.iinfo(t[1]).max >= t[0] if t[1] is not int else True)
        .map(lambda t: t[1](t[0]))
    )


class Opaque:
    def __repr__(self) -> str:
        return "Opaque()"


OPAQUE = Opaque()


# ------------------------------------------------------------ invalid values, by keyword kind
def bad_int(low: int, high: float = math.inf, optional: bool = False) -> list[Any]:
    out: list[Any] = [low - 1, 2.5, float(low), np.float64(low), True, "3", [low], 10**12, 1 + 2j]
    out += [math.nan, OPAQUE, np.array([low, low])]
    if high != math.inf:
        out += [int(high) + 1]
    return out if optional else [*out, None]


def bad_real(low: float, high: float, optional: bool = False, low_open: bool = False) -> list[Any]:
    out: list[Any] = [math.nan, math.inf, -math.inf, 1e300, -1e300, "0.5", True, 1 + 2j, OPAQUE]
    out += [[low], np.array([high, high]), high * 10 if high > 0 else high + 1]
    out += [low if low_open else (low / 10 if low > 0 else low - 1)]
    if low > 1e-300:
        out += [1e-300]
    return out if optional else [*out, None]


def bad_choice(choices: tuple[str, ...], optional: bool = False) -> list[Any]:
    out: list[Any] = ["no-such-option", 3, ["x"], np.array([1, 2]), OPAQUE, choices[0].upper()]
    return out if optional else [*out, None]


BAD_BOOL: list[Any] = ["yes", 2, 2.5, OPAQUE, np.array([True, False])]


def bad_reals(size: int, low: float, high: float) -> list[Any]:
    ok = [high] * size
    out: list[Any] = ["abc", 1.0, OPAQUE, None, ok[:-1], [*ok, high], [math.nan] * size]
    out += [[*ok[:-1], 1e300], [*ok[:-1], "x"], [[high]] * size]
    out += [[*ok[:-1], low / 10 if low > 0 else low - 1]]
    return out


@dataclass(frozen=True)
class Keyword:
    """A constructor keyword: how to draw valid values and which values are invalid.

    Attributes:
        valid: ``valid(base) -> strategy`` of valid values given the base keywords.
        invalid: ``invalid(base) -> list`` of invalid values given the base keywords.
    """

    valid: Callable[[dict[str, Any]], st.SearchStrategy[Any]]
    invalid: Callable[[dict[str, Any]], list[Any]]


def K(valid: Any, invalid: Any) -> Keyword:
    """A :class:`Keyword` from a strategy / list or from functions of the base keywords."""
    v = valid if callable(valid) and not isinstance(valid, st.SearchStrategy) else (lambda b: valid)
    i = invalid if callable(invalid) else (lambda b: invalid)
    return Keyword(v, i)


INVALID_ACTION = K(st.sampled_from(["noop", "raise", "terminate"]), bad_choice(("noop",)))
PENALTY = K(real_in(-1e6, 1e6), bad_real(-1e6, 1e6))
RENDER_MODE = K(st.sampled_from([None, "rgb_array"]), bad_choice(("rgb_array",), optional=True))
COMMON = {
    "invalid_action": INVALID_ACTION,
    "invalid_action_penalty": PENALTY,
    "render_mode": RENDER_MODE,
}

# ------------------------------------------------------------ FIMSelection-v1 / fim_selection_v0
FIM_SENSORS = ("camera", "toa", "doppler")
FIM_PRESETS = [f"example{i}{v}" for v in ("", "_moving") for i in (1, 2, 3)]  # every preset
FIM_BASE = {"preset": "example2_moving", "n_candidates": 6, "budget": 2}  # pools hold >= 2 here
FIM_SCENARIO = {
    "preset": K(st.sampled_from(FIM_PRESETS), bad_choice(("example1",))),
    "n_candidates": K(st.integers(2, 10), bad_int(1, 5000)),
    "sensors": K(
        st.one_of(st.none(), st.lists(st.sampled_from(FIM_SENSORS), min_size=1, unique=True)),
        ["camera", 5, [], ["camera", "camera"], ["lidar"], [None], OPAQUE, np.array([1])],
    ),
    "n_agents": K(st.one_of(st.none(), int_in(1, 3)), bad_int(1, 8, optional=True)),
    "randomize": K(st.booleans(), BAD_BOOL),
    **COMMON,
}
FIM_KEYWORDS = {
    **FIM_SCENARIO,
    "budget": K(int_in(1, 2), lambda b: [*bad_int(1), 10**6]),
    "camera_sigma_px": K(st.one_of(st.none(), log_uniform(1e-3, 1e3)), bad_real(1e-3, 1e3, True)),
    "toa_sigma_m": K(st.one_of(st.none(), log_uniform(1e-3, 1e5)), bad_real(1e-3, 1e5, True)),
    "doppler_sigma_mps": K(st.one_of(st.none(), log_uniform(1e-3, 1e5)), bad_real(1e-3, 1e5, True)),
}
MA_FIM_BASE = {"preset": "example3_moving", "n_candidates": 5, "budgets": 2}
MA_FIM_KEYWORDS = {
    **FIM_SCENARIO,
    "budgets": K(
        st.one_of(int_in(1, 2), st.lists(int_in(1, 2), min_size=2, max_size=2)),
        [*bad_int(1), [1], [1, 1, 1], [1, 2.5], [1, 0], [1, None], "2", 10**6],
    ),
    "mode": K(st.sampled_from(["independent", "cooperative"]), bad_choice(("cooperative",))),
}

# ------------------------------------------------------------ CLScheduling-v1
CL_BASE = {"n_agents": 2, "horizon": 3, "budget": 1, "preset": "benchmark"}
CL_KEYWORDS = {
    "preset": K(st.sampled_from(["benchmark", "dense", "paper"]), bad_choice(("benchmark",))),
    "n_agents": K(int_in(2, 4), bad_int(2, 32, optional=True)),
    "budget": K(int_in(1, 2), [*bad_int(1, optional=True), 3]),  # 2 agents: 2 pairs
    "fusion": K(
        st.sampled_from(["naive", "ci", "dmv", "pecmv"]), [*bad_choice(("dmv",)), "dead_reckoning"]
    ),
    "horizon": K(int_in(1, 4), bad_int(1, 100_000, optional=True)),
    "objective": K(st.sampled_from(["logdet", "trace"]), bad_choice(("logdet",), optional=True)),
    "topology": K(st.sampled_from(["all", "chain"]), bad_choice(("all",), optional=True)),
    "model": K(st.sampled_from(["ins", "unicycle"]), bad_choice(("ins",))),
    "dt": K(real_in(1e-3, 1.0), bad_real(1e-3, 1.0)),
    "tracks": K(
        st.lists(st.sampled_from(["rectangle", "circle", "lemniscate"]), min_size=1, max_size=3),
        ["circle", [], ["square"], [3], None, OPAQUE, 3],
    ),
    "track_size": K(real_in(0.5, 1000.0), bad_real(0.5, 1000.0)),
    "speed": K(real_in(0.01, 20.0), bad_real(0.01, 20.0)),
    "input_sigma": K(
        st.lists(st.tuples(real_in(1e-6, 100.0), real_in(1e-6, 100.0)), min_size=1, max_size=3),
        [
            [],
            "x",
            None,
            0.1,
            [(0.1,)],
            [(0.1, math.nan)],
            [(0.1, -1.0)],
            [(0.1, 1e300)],
            [(0.1, "a")],
            [(0.1, 0.2, 0.3)],
            OPAQUE,
        ],
    ),
    "beacons": K(
        st.lists(st.tuples(*[real_in(-1e5, 1e5)] * 3), max_size=3),
        [
            None,
            "x",
            3.0,
            [(1.0, 2.0)],
            [(1.0, 2.0, math.nan)],
            [(1.0, 2.0, 1e300)],
            [[1, 2, "a"]],
            OPAQUE,
            [(1.0, 2.0, 3.0, 4.0)],
        ],
    ),
    "beacon_agents": K(
        st.lists(int_in(0, 1), max_size=2),
        [None, 0, [2], [-1], [0.5], ["0"], [True], OPAQUE, [10**12]],
    ),
    "beacon_every": K(int_in(1, 5), bad_int(1, 100_000)),
    "relative_every": K(int_in(1, 3), bad_int(1, 100_000)),
    "range_sigma": K(real_in(1e-3, 100.0), bad_real(1e-3, 100.0)),
    "bearing_sigma_deg": K(st.one_of(st.none(), real_in(1e-3, 90.0)), bad_real(1e-3, 90.0, True)),
    "init_sigma": K(
        st.tuples(real_in(1e-3, 1e3), real_in(1e-4, 100.0), real_in(1e-3, 90.0)),
        bad_reals(3, 1e-3, 90.0),
    ),
    "zupt_every": K(st.one_of(st.none(), int_in(1, 5)), bad_int(1, 100_000, optional=True)),
    "zupt_sigma": K(real_in(1e-4, 10.0), bad_real(1e-4, 10.0)),
    "relative_pairs": K(
        st.lists(st.sampled_from([(0, 1), (1, 0)]), min_size=1, max_size=2),
        [[], None, [(0, 0)], [(0, 2)], [(0,)], [(0, 1.5)], [(0, "1")], "01", OPAQUE, [(-1, 0)]],
    ),
    **COMMON,
}

# ------------------------------------------------------------ LandmarkSelection-v1
LM_BASE = {"n_landmarks": 5, "k": 2, "horizon": 3}
LM_KEYWORDS = {
    "n_landmarks": K(int_in(2, 8), bad_int(1, 200)),
    "k": K(int_in(1, 2), [*bad_int(1), 6]),  # 5 landmarks
    "horizon": K(int_in(1, 4), bad_int(1, 100_000)),
    "objective": K(st.sampled_from(["logdet", "det"]), bad_choice(("logdet",))),
    "landmarks": K(
        st.none(),  # drawn layouts; explicit ones: see test_explicit_landmark_layout_is_used
        [
            "abc",
            np.zeros((4, 3)),
            np.zeros((5, 2)),
            np.full((5, 3), np.nan),
            np.full((5, 3), 1e300),
            np.zeros((5, 3), complex),
            OPAQUE,
            [[1, 2, 3]] * 5 + [[1]],
        ],
    ),
    "dt": K(real_in(1e-3, 1.0), bad_real(1e-3, 1.0)),
    "gyro_sigma_deg_per_h": K(real_in(1e-4, 1e4), bad_real(1e-4, 1e4)),
    "accel_sigma": K(real_in(1e-6, 1.0), bad_real(1e-6, 1.0)),
    "aoa_sigma_deg": K(st.tuples(*[real_in(1e-4, 30.0)] * 2), bad_reals(2, 1e-4, 30.0)),
    "init_sigma": K(
        st.tuples(real_in(1e-4, 30.0), real_in(1e-4, 100.0), real_in(1e-2, 1e4)),
        bad_reals(3, 1e-4, 30.0),
    ),
    "altitude": K(real_in(200.0, 20_000.0), bad_real(200.0, 20_000.0)),
    "speed": K(real_in(1.0, 150.0), [*bad_real(1.0, 340.0), 300.0]),  # 300 m/s: bank > 60 deg
    "heading_deg": K(real_in(-360.0, 360.0), bad_real(-360.0, 360.0)),
    "legs": K(
        st.lists(st.tuples(real_in(1e-2, 1e5), real_in(-6.0, 6.0)), min_size=1, max_size=3),
        [
            [],
            None,
            "x",
            [(5.0,)],
            [(0.0, 1.0)],
            [(5.0, math.nan)],
            [(5.0, 45.0)],
            [(1e300, 0.0)],
            [(5.0, "a")],
            OPAQUE,
            [(-1.0, 0.0)],
        ],
    ),
    "max_roll_rate_deg": K(real_in(1.0, 180.0), bad_real(1.0, 180.0)),
    "landmark_margin": K(real_in(0.0, 1e5), bad_real(0.0, 1e5)),
    "landmark_height": K(
        st.tuples(real_in(-500.0, 0.0), real_in(0.0, 90.0)),
        [
            None,
            "x",
            (1.0,),
            (100.0, 0.0),
            (0.0, math.nan),
            (0.0, 1e300),
            (0.0, 50_000.0),
            OPAQUE,
            (0.0, "a"),
        ],
    ),
    "min_off_nadir_deg": K(real_in(0.0, 30.0), [*bad_real(0.0, 90.0), 90.0]),
    **COMMON,
}

# ------------------------------------------------------------ ReceiverClustering-v1
RC_BASE = {"n_agents": 4, "horizon": 3}
RC_SCENARIO = {
    "n_agents": K(int_in(1, 6), bad_int(1, 200)),
    "n_max_states": K(
        st.one_of(st.none(), int_in(6, 30), st.just(10**30)),
        [5, 0, -1, 6.0, 2.5, True, "14", [14], np.float64(14), OPAQUE],
    ),
    "sigma": K(
        lambda b: st.one_of(
            st.none(),
            st.lists(
                st.tuples(log_uniform(1e-4, 1e3), log_uniform(1e-4, 1e3)),
                min_size=b["n_agents"],
                max_size=b["n_agents"],
            ).map(np.array),
        ),
        lambda b: [
            "x",
            3.0,
            OPAQUE,
            np.ones((b["n_agents"] + 1, 2)),
            np.ones((b["n_agents"], 3)),
            np.full((b["n_agents"], 2), np.nan),
            np.full((b["n_agents"], 2), 1e-150),
            np.full((b["n_agents"], 2), 1e300),
            -np.ones((b["n_agents"], 2)),
            np.zeros((b["n_agents"], 2)),
            np.ones((b["n_agents"], 2), complex),
            np.full((b["n_agents"], 2), "1"),
        ],
    ),
    "noise_correlation": K(real_in(0.0, 0.99), [*bad_real(0.0, 0.99), 1.0, 0.995]),
    "dt": K(real_in(1e-3, 10.0), bad_real(1e-3, 10.0)),
    "tau": K(int_in(1, 30), bad_int(1, 10_000)),
    "weights": K(
        st.tuples(*[real_in(0.0, 1e6)] * 3).filter(lambda w: any(v > 0 for v in w)),
        [*bad_reals(3, 0.0, 1e6), (0.0, 0.0, 0.0)],
    ),
    "horizon": K(int_in(1, 4), bad_int(1, 100_000)),
    "prior_std": K(st.tuples(*[log_uniform(1e-3, 1e2)] * 3), bad_reals(3, 1e-3, 1e2)),
    "initial": K(st.sampled_from(["random", "singletons"]), bad_choice(("random",))),
    "preset": K(st.sampled_from(["multipath", "paper"]), bad_choice(("paper",))),
    "p_enter": K(st.one_of(st.none(), real_in(0.0, 1.0)), bad_real(0.0, 1.0, True)),
    "p_leave": K(st.one_of(st.none(), real_in(1e-6, 1.0)), bad_real(0.0, 1.0, True, low_open=True)),
    "degraded_factor": K(st.one_of(st.none(), real_in(1.0, 100.0)), bad_real(1.0, 100.0, True)),
    **COMMON,
}
RC_KEYWORDS = {
    **RC_SCENARIO,
    "action_mode": K(st.sampled_from(["assignment", "edit"]), bad_choice(("edit",))),
}

#: every constructor: (base keywords (small, fast, valid), keyword table)
ENVS: dict[str, tuple[dict[str, Any], dict[str, Keyword]]] = {
    CL: (CL_BASE, CL_KEYWORDS),
    FIM: (FIM_BASE, FIM_KEYWORDS),
    LM: (LM_BASE, LM_KEYWORDS),
    RC: (RC_BASE, RC_KEYWORDS),
    MA_FIM: (MA_FIM_BASE, MA_FIM_KEYWORDS),
    MA_RC: (RC_BASE, RC_SCENARIO),
}


#: keyword combinations that are invalid together although each value is valid alone
def _rc_conflict(kw: dict[str, Any]) -> bool:
    # the paper preset keeps sigma fixed: no multipath parameters; sigma is (n_agents, 2)
    paper = kw.get("preset", "multipath") == "paper"
    multipath = any(kw.get(k) is not None for k in ("p_enter", "p_leave", "degraded_factor"))
    sigma = kw.get("sigma")
    return (paper and multipath) or (sigma is not None and len(sigma) != kw["n_agents"])


def _ma_fim_conflict(kw: dict[str, Any]) -> bool:
    preset = kw.get("preset", "example3_moving")
    agents = kw.get("n_agents") or (2 if preset.startswith("example3") else 1)
    budgets = kw["budgets"]
    return isinstance(budgets, list) and len(budgets) != agents


def _lm_conflict(kw: dict[str, Any]) -> bool:
    # documented: without a user layout, landmark_margin >= (altitude - low) tan(min_off_nadir_deg
    # + largest bank of the legs at speed), capped at 89 deg
    legs = kw.get("legs", ((5.0, 0.0), (10.0, 6.0), (5.0, 0.0), (10.0, -6.0)))
    bank = max(math.degrees(math.atan(kw.get("speed", 50.0) * abs(w) * math.pi / 180 / 9.81))
               for _, w in legs)  # fmt: skip
    angle = min(kw.get("min_off_nadir_deg", 5.0) + bank, 89.0)
    low = kw.get("landmark_height", (0.0, 100.0))[0]
    need = (kw.get("altitude", 1000.0) - low) * math.tan(math.radians(angle))
    return kw.get("landmark_margin", 4000.0) < need


CONFLICTS: dict[str, Callable[[dict[str, Any]], bool]] = {
    LM: _lm_conflict,
    RC: _rc_conflict,
    MA_RC: _rc_conflict,
    MA_FIM: _ma_fim_conflict,
    CL: lambda kw: (
        ("topology" in kw and "relative_pairs" in kw)
        or kw.get("budget", 1) > len(kw.get("relative_pairs", [0, 1]))
    ),
}

# ============================================================================ harness


def make(name: str, **kw: Any) -> Any:
    """Build env ``name`` (a gymnasium id or a PettingZoo module name) with ``kw``."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        warnings.filterwarnings("ignore", message=".*render_mode.*", category=UserWarning)
        if name in MODULES:
            return MODULES[name].parallel_env(**kw)
        return gym.make(name, **kw)


def names(keyword: str) -> str:
    return r"(?<![A-Za-z0-9_])" + re.escape(keyword) + r"(?![A-Za-z0-9_])"


def snapshot(kw: dict[str, Any]) -> dict[str, bytes]:
    return {
        k: v.tobytes() for k, v in kw.items() if isinstance(v, np.ndarray) and v.dtype != object
    }


def expect_rejected(name: str, kw: dict[str, Any], keyword: str) -> str | None:
    """``None`` if building with ``kw`` raises TypeError/ValueError naming ``keyword``, else why."""
    before = snapshot(kw)
    try:
        env = make(name, **kw)
    except (TypeError, ValueError) as exc:
        if snapshot(kw) != before:
            return "a numpy argument was modified"
        if re.search(names(keyword), str(exc)):
            return None
        return f"{type(exc).__name__} not naming {keyword!r}: {str(exc)[:300]}"
    except BaseException as exc:  # any other type is the failure tested
        return f"{type(exc).__name__}: {str(exc)[:300]}"
    env.close()
    return "accepted"


def run_episode(name: str, env: Any, seed: int, steps: int) -> None:
    """Reset and take up to ``steps`` valid (masked) actions; outputs must be finite, in space."""
    rng = np.random.default_rng(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        if name in MODULES:
            obs, infos = env.reset(seed=seed)
            for _ in range(steps):
                check_obs(obs, env.observation_space)
                if not env.agents:
                    return
                acts = {a: int(rng.choice(np.flatnonzero(env.action_mask(a)))) for a in env.agents}
                obs, rewards, terms, _, infos = env.step(acts)
                assert all(math.isfinite(r) for r in rewards.values()), rewards
                assert all(math.isfinite(i["objective"]) for i in infos.values())
            return
        obs, info = env.reset(seed=seed)
        for _ in range(steps):
            check_obs(obs, lambda _: env.observation_space)
            assert math.isfinite(info["objective"]), info["objective"]
            action = sample_valid_action(env, rng)
            obs, reward, term, trunc, info = env.step(action)
            assert math.isfinite(reward), reward
            if term or trunc:
                return


def check_obs(obs: dict[str, Any], space_of: Callable[[str], gym.spaces.Space[Any]]) -> None:
    per_agent = obs if obs and isinstance(next(iter(obs.values())), dict) else {None: obs}
    for agent, o in per_agent.items():
        space = space_of(agent)
        for key, value in o.items():
            arr = np.asarray(value)
            if arr.dtype.kind == "f":
                assert np.all(np.isfinite(arr)), f"obs[{key!r}] not finite: {arr}"
        assert space.contains(o), f"observation outside its space: {o}"


def sample_valid_action(env: Any, rng: np.random.Generator) -> Any:
    """A valid action: a masked choice for Discrete spaces, a feasible clustering otherwise."""
    u = env.unwrapped
    if isinstance(u.action_space, gym.spaces.Discrete):
        return int(rng.choice(np.flatnonzero(u.action_masks())))
    return u.bank.labels.copy()  # assignment mode: keep the (feasible) clustering


def same(a: Any, b: Any) -> bool:
    """Deep equality of step outputs (arrays bit for bit, NaN equal to NaN)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray | np.generic | float | int):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    return a == b


# ============================================================================ constructors

BAD_CASES = [
    pytest.param(name, keyword, id=f"{name.split('/')[-1]}-{keyword}")
    for name, (_, table) in ENVS.items()
    for keyword in table
]


@pytest.mark.parametrize(("name", "keyword"), BAD_CASES)
def test_bad_keyword_value_is_rejected_naming_it(name: str, keyword: str) -> None:
    """(a) Every catalogued invalid value of ``keyword`` is a TypeError/ValueError naming it."""
    base, table = ENVS[name]
    failures = []
    for value in table[keyword].invalid(base):
        why = expect_rejected(name, {**base, keyword: value}, keyword)
        if why is not None:
            failures.append(f"{keyword}={value!r:.80}: {why}")
    assert not failures, "\n".join(failures)


ANY_VALUE = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.complex_numbers(max_magnitude=1e3),
    st.text(max_size=8),
    st.lists(st.floats(-1e3, 1e3), max_size=4),
    st.lists(st.integers(-3, 40), max_size=4).map(tuple),
    st.lists(st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)), max_size=4).map(
        lambda rows: np.array(rows, dtype=float).reshape(-1, 2)
    ),
)


@pytest.mark.parametrize("name", list(ENVS))
@fuzz_settings(4.0)
@given(data=st.data())
def test_arbitrary_keyword_value_is_rejected_or_works(name: str, data: st.DataObject) -> None:
    """(a)+(b) Any value of any keyword: a rejection naming it, or an env that runs cleanly."""
    base, table = ENVS[name]
    keyword = data.draw(st.sampled_from(sorted(table)), label="keyword")
    value = data.draw(ANY_VALUE, label="value")
    kw = {**base, keyword: value}
    try:
        env = make(name, **kw)
    except (TypeError, ValueError) as exc:
        note(f"message: {exc}")
        assert re.search(names(keyword), str(exc)), f"message does not name {keyword!r}: {exc}"
        return
    run_episode(name, env, seed=0, steps=3)


@pytest.mark.parametrize("name", list(ENVS))
@fuzz_settings(4.0)
@given(data=st.data())
def test_valid_configuration_runs_cleanly(name: str, data: st.DataObject) -> None:
    """(b) Valid keywords drawn over their documented ranges: no error, finite, in space."""
    base, table = ENVS[name]
    chosen = data.draw(st.lists(st.sampled_from(sorted(table)), max_size=4, unique=True))
    kw = dict(base)
    for keyword in chosen:
        kw[keyword] = data.draw(table[keyword].valid(base), label=keyword)
    if name in CONFLICTS and CONFLICTS[name](kw):
        return
    note(f"keywords: {kw}")
    before = snapshot(kw)
    env = make(name, **kw)
    run_episode(name, env, seed=data.draw(st.integers(0, 2**31), label="seed"), steps=4)
    assert snapshot(kw) == before, "a numpy keyword was modified"


@pytest.mark.parametrize("name", list(ENVS))
@fuzz_settings(2.0)
@given(
    keyword=st.from_regex(r"[a-z][a-z_]{0,11}", fullmatch=True),
    value=st.sampled_from([1, "x", None]),
)
def test_unknown_keyword_is_a_type_error_naming_it(name: str, keyword: str, value: Any) -> None:
    base, table = ENVS[name]
    known = set(table) | set(base) | {"budgets", "k", "disable_env_checker", "max_episode_steps"}
    known |= {"autoreset", "apply_api_compatibility"}  # gymnasium.make's own keywords
    if keyword in known or keyword in _constructor_parameters(name):
        return
    with pytest.raises(TypeError, match=names(keyword)):
        make(name, **base, **{keyword: value})


@functools.cache
def _constructor_parameters(name: str) -> set[str]:
    from selenv.families.cooperative.scenario import CLConfig
    from selenv.families.landmarks.scenario import LandmarkConfig

    if name in MODULES:
        cls: Any = type(MODULES[name].parallel_env(**ENVS[name][0]))
    else:
        cls = type(gym.make(name, **ENVS[name][0]).unwrapped)
    params = set(inspect.signature(cls.__init__).parameters)
    if name == CL:
        params |= {f.name for f in dataclasses.fields(CLConfig)}
    if name == LM:
        params |= {f.name for f in dataclasses.fields(LandmarkConfig)}
    return params


def test_unknown_cl_keyword_and_bad_value_type_give_different_accurate_messages() -> None:
    """An unknown keyword is reported as unknown; a known one with a bad type by its range."""
    with pytest.raises(TypeError, match=r"got an unexpected keyword argument 'colour'") as unk:
        make(CL, **CL_BASE, colour="red")
    known = str(unk.value).split("known:")[1]
    for keyword in ("dt", "range_sigma", "preset", "budget", "fusion", "render_mode"):
        assert f"'{keyword}'" in known, f"{keyword!r} missing from the list of known keywords"
    with pytest.raises(TypeError, match=r"dt must be a real number in \[0\.001, 1\] s") as bad:
        make(CL, **CL_BASE, dt="red")
    assert "unexpected" not in str(bad.value) and "'red'" in str(bad.value)
    with pytest.raises(ValueError, match=r"dt must be a finite number in \[0\.001, 1\] s"):
        make(CL, **CL_BASE, dt=5.0)


# ============================================================================ step()


def _step_envs() -> list[tuple[str, dict[str, Any]]]:
    return [
        (CL, {**CL_BASE, "n_agents": 3, "horizon": 4, "budget": 2, "relative_every": 1}),
        (FIM, {**FIM_BASE, "budget": 4}),
        (LM, {**LM_BASE, "horizon": 4}),
        (RC, {**RC_BASE, "horizon": 4}),
        (RC, {**RC_BASE, "horizon": 4, "action_mode": "edit"}),
    ]


STEP_ENVS = _step_envs()
STEP_IDS = [f"{n.split('/')[-1]}-{kw.get('action_mode', 'default')}" for n, kw in STEP_ENVS]


def bad_discrete(n: int) -> st.SearchStrategy[Any]:
    """Actions outside ``Discrete(n)``."""
    return st.one_of(
        st.sampled_from([None, "1", b"1", 1.0, np.float32(1.0), True, np.True_, 1 + 0j, OPAQUE]),
        st.sampled_from([np.array([1, 1]), np.array([[1]]), np.array([1.0]), [1, 1], {}]),
        st.sampled_from([math.nan, math.inf, np.array(np.nan), np.array([], int)]),
        st.integers(-(2**70), -1),
        st.integers(n, 2**70),
        st.floats(allow_nan=True),
        st.integers(n, 2**15).map(np.int64),
        st.integers(-(2**15), -1).map(np.int16),
    )


def bad_assignment(n: int) -> st.SearchStrategy[Any]:
    """Actions outside ``MultiDiscrete([n] * n)``."""
    ok = np.zeros(n, int)
    return st.one_of(
        st.sampled_from([None, "0" * n, 0, 0.0, OPAQUE, list(ok[:-1]), np.zeros((n, 1), int)]),
        st.sampled_from([ok.astype(float), ok.astype(np.float32), ok.astype(bool), [0.0] * n]),
        st.sampled_from(
            [
                np.r_[ok[:-1], n],
                np.r_[ok[:-1], -1],
                np.r_[ok[:-1].astype(float), np.nan],
                np.r_[ok[:-1], 2**40],
                np.array(list("0" * n)),
            ]
        ),
    )


def pair(name: str, kw: dict[str, Any], seed: int) -> tuple[Any, Any]:
    a, b = make(name, **kw), make(name, **kw)
    a.reset(seed=seed)
    b.reset(seed=seed)
    return a, b


def assert_twins(a: Any, b: Any, rng_seed: int, steps: int = 2) -> None:
    """``a`` and ``b`` give the same outputs for the same valid actions."""
    rng = np.random.default_rng(rng_seed)
    for _ in range(steps):
        action = sample_valid_action(a, rng)
        out_a, out_b = a.step(action), b.step(action)
        assert same(out_a, out_b), f"step({action!r}) differs after the rejected call"
        if out_a[2] or out_a[3]:
            return


@pytest.mark.parametrize(("name", "kw"), STEP_ENVS, ids=STEP_IDS)
@fuzz_settings(4.0)
@given(data=st.data())
def test_out_of_space_action_is_rejected_and_changes_nothing(
    name: str, kw: dict[str, Any], data: st.DataObject
) -> None:
    """(a)+(c) A bad action raises naming it; the env then behaves as its untouched twin."""
    seed = data.draw(st.integers(0, 2**31), label="seed")
    a, b = pair(name, kw, seed)
    space = a.unwrapped.action_space
    if isinstance(space, gym.spaces.Discrete):
        bad = data.draw(bad_discrete(int(space.n)), label="action")
    else:
        bad = data.draw(bad_assignment(a.unwrapped.n), label="action")
    for _ in range(data.draw(st.integers(0, 2), label="valid steps first")):
        act = sample_valid_action(a, np.random.default_rng(seed))
        assert same(a.step(act), b.step(act))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises((TypeError, ValueError), match=names("action")):
            a.step(bad)
    assert_twins(a, b, seed)


@pytest.mark.parametrize(("name", "kw"), STEP_ENVS, ids=STEP_IDS)
@fuzz_settings(2.0)
@given(
    seed=st.integers(0, 2**31),
    dtype=st.sampled_from(
        [np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64]
    ),
    shape=st.sampled_from(["scalar", "()", "(1,)"]),
)
def test_numpy_integer_actions_are_valid(
    name: str, kw: dict[str, Any], seed: int, dtype: type, shape: str
) -> None:
    """(b) Any numpy integer dtype (and ``()`` / ``(1,)`` arrays for Discrete) is valid."""
    a, b = pair(name, kw, seed)
    action = sample_valid_action(a, np.random.default_rng(seed))
    if np.ndim(action) == 0:
        cast = {
            "scalar": dtype(action),
            "()": np.array(action, dtype),
            "(1,)": np.array([action], dtype),
        }[shape]
    else:
        cast = np.asarray(action).astype(dtype)
    assert same(a.step(cast), b.step(action))


@pytest.mark.parametrize(("name", "kw"), STEP_ENVS, ids=STEP_IDS)
@fuzz_settings(2.0)
@given(seed=st.integers(0, 2**31))
def test_masked_action_in_raise_mode_changes_nothing(
    name: str, kw: dict[str, Any], seed: int
) -> None:
    """(c) ``invalid_action="raise"``: a masked action raises naming it, the state is kept."""
    a, b = pair(name, {**kw, "invalid_action": "raise"}, seed)
    u = a.unwrapped
    if isinstance(u.action_space, gym.spaces.Discrete):
        masked = np.flatnonzero(~u.action_masks())
        if masked.size == 0:  # e.g. a fresh FIM episode: select one, then pick it again
            act = sample_valid_action(a, np.random.default_rng(seed))
            a.step(act)
            b.step(act)
            masked = np.flatnonzero(~u.action_masks())
        if masked.size == 0:
            return
        bad: Any = int(masked[0])
    else:
        if u.max_size >= u.n:
            return
        bad = np.zeros(u.n, int)  # one cluster of every receiver: over the cap
    with pytest.raises(ValueError, match=names("action")):
        a.step(bad)
    assert_twins(a, b, seed)


# ------------------------------------------------------------ PettingZoo step()


@pytest.mark.parametrize("name", list(MODULES))
@fuzz_settings(4.0)
@given(data=st.data())
def test_pettingzoo_bad_action_is_rejected_and_changes_nothing(
    name: str, data: st.DataObject
) -> None:
    """(a)+(c) One agent's bad action (or a missing / extra agent) raises naming it."""
    seed = data.draw(st.integers(0, 2**31), label="seed")
    kw = dict(ENVS[name][0])
    a, b = make(name, **kw), make(name, **kw)
    a.reset(seed=seed)
    b.reset(seed=seed)
    rng = np.random.default_rng(seed)
    acts = {ag: int(rng.choice(np.flatnonzero(a.action_mask(ag)))) for ag in a.agents}
    agent = data.draw(st.sampled_from(a.agents), label="agent")
    how = data.draw(st.sampled_from(["bad value", "missing", "extra"]), label="how")
    bad = dict(acts)
    if how == "bad value":
        bad[agent] = data.draw(bad_discrete(int(a.action_space(agent).n)), label="action")
        named = names(agent)
    elif how == "missing":
        del bad[agent]
        named = names(agent)
    else:
        bad["agent_99"] = 0
        named = names("agent_99")
    with pytest.raises((TypeError, ValueError), match=named):
        a.step(bad)
    assert same(a.step(acts), b.step(acts)), "step differs after the rejected call"


@pytest.mark.parametrize("name", list(MODULES))
@fuzz_settings(2.0)
@given(seed=st.integers(0, 2**31), dtype=st.sampled_from([np.int8, np.uint16, np.int64]))
def test_pettingzoo_numpy_integer_actions_are_valid(name: str, seed: int, dtype: type) -> None:
    kw = dict(ENVS[name][0])
    a, b = make(name, **kw), make(name, **kw)
    a.reset(seed=seed)
    b.reset(seed=seed)
    rng = np.random.default_rng(seed)
    acts = {ag: int(rng.choice(np.flatnonzero(a.action_mask(ag)))) for ag in a.agents}
    assert same(a.step({ag: dtype(v) for ag, v in acts.items()}), b.step(acts))


# ============================================================================ long-only tests


@pytest.mark.fuzz_long
@pytest.mark.parametrize(
    ("name", "kw"),
    [
        (FIM, {"n_candidates": 5000, "budget": 2, "n_agents": 8, "sensors": ["camera"]}),
        (LM, {"n_landmarks": 200, "k": 2, "horizon": 50}),
        (RC, {"n_agents": 200, "horizon": 2, "tau": 3}),
        (CL, {"n_agents": 32, "horizon": 2, "budget": 3}),
        (CL, {"horizon": 100_000, "n_agents": 2, "budget": 1, "model": "unicycle"}),
    ],
    ids=["fim-largest", "landmarks-largest", "clustering-largest", "cl-largest", "cl-longest"],
)
def test_largest_documented_sizes_run(name: str, kw: dict[str, Any]) -> None:
    """(b) The upper ends of the size ranges build, reset and step."""
    run_episode(name, make(name, **kw), seed=0, steps=2)


@pytest.mark.fuzz_long
@pytest.mark.parametrize("name", [CL, FIM, LM, RC])
@fuzz_settings(0.2)
@given(data=st.data())
def test_valid_configuration_runs_a_whole_episode(name: str, data: st.DataObject) -> None:
    """(b) Valid configurations with many keywords at once, run to the end of the episode."""
    base, table = ENVS[name]
    chosen = data.draw(st.lists(st.sampled_from(sorted(table)), min_size=3, unique=True))
    kw = dict(base)
    for keyword in chosen:
        kw[keyword] = data.draw(table[keyword].valid(base), label=keyword)
    if name in CONFLICTS and CONFLICTS[name](kw):
        return
    run_episode(name, make(name, **kw), seed=data.draw(st.integers(0, 2**31)), steps=10**6)
