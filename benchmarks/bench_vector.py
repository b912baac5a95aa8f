"""Steps per second of the native vector envs and of single envs, each against a fair anchor.

One process, one BLAS thread (``OPENBLAS_NUM_THREADS=1`` if unset, and threadpoolctl through
:func:`selenv.threads.limit_threads`), interleaved rounds: each round times every contender of
a table once, so a change of load hits all of them alike. Times are medians over ``--rounds``;
a ratio is the median of the per-round ratios. Random masked actions are sampled outside the
timed calls; episode ends inside a block are part of the step (the vector envs autoreset) and
untimed for single envs. A ReceiverClustering-v2 step places one receiver and every
``n_agents``-th runs the filter step: its blocks are whole filter steps (:func:`cycle`), so its
time per step is the mean over one. Printed as Markdown tables:

1. **native vs SyncVectorEnv** at ``B = --batch`` (64): total steps/s of
   ``gymnasium.make_vec(id, num_envs=B)`` (the family's native vector env) and of
   ``SyncVectorEnv`` over ``B`` ``gymnasium.make(id)`` envs, default keywords. CartPole-v1's
   own ``CartPoleVectorEnv`` against its ``SyncVectorEnv`` is the reference row.
2. **sub-env step vs CartPoleVectorEnv** at the same ``B`` (``--batch`` and ``--wide``: 64 and
   256): microseconds per sub-env step of the native env and of Gymnasium's native
   ``CartPoleVectorEnv`` (``make_vec("CartPole-v1", num_envs=B,
   vectorization_mode="vector_entry_point")``), interleaved, and their ratio.
3. **single env vs CartPole-v1**: one ``gymnasium.make(id)`` step and one reset against one
   ``gymnasium.make("CartPole-v1")`` step and reset (the same wrappers on both).
4. **scaling** (``--scaling``): native steps/s for ``B = 1 .. 1024`` with CartPoleVectorEnv's at
   the same ``B``, and the time per sub-env step against the family's size parameter
   (candidates, landmarks, agents, receivers) with the fitted cost exponent ``t ~ size^p``,
   and one ``gymnasium.make`` reset at each size against a ``gymnasium.make("CartPole-v1")``
   reset (interleaved).

    .venv/bin/python benchmarks/bench_vector.py --rounds 5 --steps 20     # tables 1-3
    .venv/bin/python benchmarks/bench_vector.py --scaling --json docs/bench/vector_envs.json

``--json PATH`` writes the figures (atomically: a temporary file, then a rename).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: tiny linear algebra

import argparse
import platform
import statistics
import time
import warnings
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import selenv  # noqa: F401  (registers the ids)
from selenv.atomic import write_json as atomic_write_json
from selenv.families import FAMILIES
from selenv.families.clustering.sequential import ReceiverClusteringSequentialEnv
from selenv.threads import limit_threads

CARTPOLE = "CartPole-v1"
#: family id -> (size keyword, sizes for the scaling table, keywords that keep the scan cheap)
SIZES: dict[str, tuple[str, list[int], dict[str, Any]]] = {
    "selenv/FIMSelection-v1": ("n_candidates", [25, 50, 100, 200, 400], {}),
    "selenv/LandmarkSelection-v1": ("n_landmarks", [10, 20, 30, 60, 120, 200], {}),
    "selenv/CLScheduling-v1": ("n_agents", [3, 4, 6, 8, 12, 16], {}),
    "selenv/ReceiverClustering-v1": ("n_agents", [10, 20, 30, 60], {}),
    "selenv/ReceiverClustering-v2": ("n_agents", [10, 20, 30, 60], {}),
}
SCALING_B = (1, 4, 16, 64, 256, 1024)


def sample(masks: np.ndarray, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """One random allowed action per sub-env from ``(B, n)`` or ``(B, k * n)`` masks."""
    m = np.asarray(masks, dtype=bool).reshape(shape)
    score = rng.random(m.shape) + m  # allowed entries beat every masked one
    return np.argmax(score, axis=-1)


def _shape(space: gym.Space, batch: int) -> tuple[int, ...]:
    if isinstance(space, gym.spaces.MultiDiscrete):
        return (batch, len(space.nvec), int(space.nvec[0]))
    if isinstance(space, gym.spaces.Discrete):
        return (batch, int(space.n))
    raise ValueError(f"space: expected Discrete or MultiDiscrete, got {space}")


def _masks(venv: Any) -> np.ndarray:
    if hasattr(venv, "action_masks"):
        return np.asarray(venv.action_masks())
    return np.stack(venv.call("action_masks"))


class Runner:
    """A vector env stepped with random masked actions; :meth:`run` times ``steps`` steps."""

    def __init__(self, make: Callable[[], Any], steps: int, seed: int = 0) -> None:
        self.venv = make()
        self.steps = steps
        self.rng = np.random.default_rng(seed)
        self.venv.reset(seed=seed)
        self.num_envs = int(self.venv.num_envs)

    def actions(self) -> np.ndarray:
        """Random allowed actions for every sub-env (not timed)."""
        shape = _shape(self.venv.single_action_space, self.num_envs)
        return sample(_masks(self.venv), self.rng, shape)

    def run(self) -> float:
        """Seconds per vector step over ``self.steps`` steps (sampling excluded)."""
        spent = 0.0
        for _ in range(self.steps):
            actions = self.actions()
            t = time.perf_counter()
            self.venv.step(actions)
            spent += time.perf_counter() - t
        return spent / self.steps

    def close(self) -> None:  # noqa: D102
        self.venv.close()


class CartPoleRunner(Runner):
    """CartPole has no masks: uniform random actions."""

    def actions(self) -> np.ndarray:  # noqa: D102
        return self.rng.integers(0, 2, self.num_envs)


def cycle(env_id: str, **kw: Any) -> int:
    """Env steps per step of the dynamics: ``n_agents`` on ReceiverClustering-v2, else 1.

    A ReceiverClustering-v2 step places one receiver; every ``n_agents``-th runs the filter
    step. Blocks of whole cycles are timed, so a time per step is the mean over a cycle.
    """
    if env_id == CARTPOLE:
        return 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = gym.make(env_id, **kw)
    base = env.unwrapped
    env.close()
    return int(base.n) if isinstance(base, ReceiverClusteringSequentialEnv) else 1


def whole_cycles(steps: int, period: int) -> int:
    """``steps`` rounded up to a multiple of ``period``."""
    return -(-steps // period) * period


def vector(env_id: str, B: int, steps: int, mode: str | None = None, **kw: Any) -> Runner:
    """A runner over ``make_vec(env_id, num_envs=B)`` (``mode``: Gymnasium's vectorization)."""
    if env_id == CARTPOLE:
        mode = mode or "vector_entry_point"
        return CartPoleRunner(lambda: gym.make_vec(env_id, B, vectorization_mode=mode), steps)
    extra = {} if mode is None else {"vectorization_mode": mode}
    steps = whole_cycles(steps, cycle(env_id, **kw))
    return Runner(lambda: gym.make_vec(env_id, num_envs=B, **extra, **kw), steps)


def interleaved(blocks: dict[str, Callable[[], float]], rounds: int) -> dict[str, list[float]]:
    """Each block's seconds per call in each of ``rounds`` rounds, blocks run in turn."""
    for block in blocks.values():
        block()  # warm-up
    times: dict[str, list[float]] = {k: [] for k in blocks}
    for _ in range(rounds):
        for name, block in blocks.items():
            times[name].append(block())
    return times


def ratio(num: list[float], den: list[float]) -> float:
    """Median of the per-round ratios ``num / den``."""
    return statistics.median(a / b for a, b in zip(num, den, strict=True))


def native_vs_sync(env_id: str, B: int, steps: int, rounds: int) -> dict[str, float]:
    """Steps/s of the native vector env and of SyncVectorEnv at ``B``, and their ratio."""
    runners = {"native": vector(env_id, B, steps), "sync": vector(env_id, B, steps, "sync")}
    t = interleaved({k: r.run for k, r in runners.items()}, rounds)
    for r in runners.values():
        r.close()
    return {
        "native_steps_per_s": B / statistics.median(t["native"]),
        "sync_steps_per_s": B / statistics.median(t["sync"]),
        "ratio": ratio(t["sync"], t["native"]),
    }


def against_cartpole_vector(ids: list[str], B: int, steps: int, rounds: int) -> dict[str, Any]:
    """Seconds per sub-env step of every native env and of CartPoleVectorEnv at ``B``."""
    cart_steps = steps * 10  # a CartPole vector step is short: time more of them per round
    runners = {CARTPOLE: vector(CARTPOLE, B, cart_steps)}
    runners.update({i: vector(i, B, steps) for i in ids})
    t = interleaved({k: r.run for k, r in runners.items()}, rounds)
    for r in runners.values():
        r.close()
    out = {k: {"sub_step_s": statistics.median(v) / B} for k, v in t.items()}
    for i in ids:
        out[i]["vs_cartpole_vector"] = ratio(t[i], t[CARTPOLE])
    return out


class Single:
    """One ``gymnasium.make(env_id)`` env: blocks of random masked steps and of resets."""

    def __init__(self, env_id: str, steps: int, resets: int, seed: int = 0, **kw: Any) -> None:
        self.env = gym.make(env_id, **kw)
        self.steps, self.resets = whole_cycles(steps, cycle(env_id, **kw)), resets
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.space = self.env.action_space
        self.masked = env_id != CARTPOLE
        self._new_episode()

    def _new_episode(self) -> None:
        self.seed += 1
        _, self.info = self.env.reset(seed=self.seed)

    def _action(self) -> Any:
        if not self.masked:
            return int(self.rng.integers(2))
        a = sample(self.info["action_mask"][None], self.rng, _shape(self.space, 1))[0]
        return a if a.ndim else int(a)

    def step_block(self) -> float:
        """Seconds per ``step`` (actions and episode resets not timed)."""
        spent = 0.0
        for _ in range(self.steps):
            action = self._action()
            t = time.perf_counter()
            _, _, term, trunc, self.info = self.env.step(action)
            spent += time.perf_counter() - t
            if term or trunc:
                self._new_episode()
        return spent / self.steps

    def reset_block(self) -> float:
        """Seconds per ``reset`` with a new seed each time."""
        t = time.perf_counter()
        for _ in range(self.resets):
            self._new_episode()
        return (time.perf_counter() - t) / self.resets

    def close(self) -> None:  # noqa: D102
        self.env.close()


def single_envs(ids: list[str], steps: int, rounds: int) -> dict[str, Any]:
    """Single-env step and reset of every family against ``gymnasium.make("CartPole-v1")``."""
    envs = {CARTPOLE: Single(CARTPOLE, steps * 50, 100)}
    envs.update({i: Single(i, steps * 5, max(2, steps // 4)) for i in ids})
    blocks: dict[str, Callable[[], float]] = {}
    for k, e in envs.items():
        blocks[f"{k} step"] = e.step_block
        blocks[f"{k} reset"] = e.reset_block
    t = interleaved(blocks, rounds)
    for e in envs.values():
        e.close()
    out: dict[str, Any] = {}
    for k in envs:
        out[k] = {
            "step_s": statistics.median(t[f"{k} step"]),
            "reset_s": statistics.median(t[f"{k} reset"]),
        }
        if k != CARTPOLE:
            out[k]["vs_cartpole_step"] = ratio(t[f"{k} step"], t[f"{CARTPOLE} step"])
            out[k]["vs_cartpole_reset"] = ratio(t[f"{k} reset"], t[f"{CARTPOLE} reset"])
    return out


def scaling(env_id: str, steps: int, rounds: int) -> dict[str, Any]:
    """Steps/s vs ``B`` (with CartPoleVectorEnv's) and time per sub-env step vs the size."""
    by_b, cart_by_b, vs_cart = {}, {}, {}
    for B in SCALING_B:
        n = max(2, steps // max(1, B // 64))
        runners = {"env": vector(env_id, B, n), "cart": vector(CARTPOLE, B, n * 10)}
        t = interleaved({k: r.run for k, r in runners.items()}, max(3, rounds // 3))
        for r in runners.values():
            r.close()
        by_b[B] = B / statistics.median(t["env"])
        cart_by_b[B] = B / statistics.median(t["cart"])
        vs_cart[B] = ratio(t["env"], t["cart"])
    key, sizes, extra = SIZES[env_id]
    by_size, reset_vs_cart = {}, {}
    cart = Single(CARTPOLE, 1, 100)
    for size in sizes:
        r = vector(env_id, 64, steps, **{key: size, **extra})
        by_size[size] = statistics.median(interleaved({"n": r.run}, max(3, rounds // 3))["n"]) / 64
        r.close()
        single = Single(env_id, 1, max(2, steps // 4), **{key: size, **extra})
        t = interleaved({"env": single.reset_block, "cart": cart.reset_block}, max(3, rounds // 3))
        reset_vs_cart[size] = ratio(t["env"], t["cart"])
        single.close()
    cart.close()
    xs = np.log(np.array(list(by_size), float))
    ys = np.log(np.array(list(by_size.values())))
    return {
        "steps_per_s_by_B": by_b,
        "cartpole_vector_steps_per_s_by_B": cart_by_b,
        "vs_cartpole_vector_by_B": vs_cart,
        "size_key": key,
        "sub_step_s_by_size": by_size,
        "reset_vs_cartpole_by_size": reset_vs_cart,
        "exponent": float(np.polyfit(xs, ys, 1)[0]),
    }


def _row(cells: list[Any]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _table(head: list[str], rows: list[list[Any]]) -> None:
    print(_row(head))
    print("|---" * len(head) + "|")
    for cells in rows:
        print(_row(cells), flush=True)


def _us(seconds: float) -> str:
    return f"{seconds * 1e6:,.1f} us"


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def main() -> None:
    """Parse the flags, run the tables, print them and write the JSON."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--rounds", type=_positive, default=7, help="interleaved rounds")
    ap.add_argument("--steps", type=_positive, default=20, help="vector steps per round")
    ap.add_argument("--batch", type=_positive, default=64, help="B of table 1 and 2")
    ap.add_argument("--wide", type=_positive, default=256, help="second B of table 2")
    ap.add_argument("--ids", nargs="*", help="family ids (default: every one with a native env)")
    ap.add_argument("--scaling", action="store_true", help="also the scaling tables")
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    ids = args.ids or [f.current_id for f in FAMILIES if f.vector_class is not None]
    widths = sorted({args.batch, args.wide})
    out: dict[str, Any] = {
        "batch": args.batch, "widths": widths, "rounds": args.rounds, "steps": args.steps,
        "blas_threads": 1, "load_average_start": os.getloadavg()[0],
        "numpy": np.__version__, "gymnasium": gym.__version__, "python": platform.python_version(),
    }  # fmt: skip
    for k in [CARTPOLE, *ids]:
        out[k] = {}
    with limit_threads(blas=1, torch=1):
        print(f"## native vs SyncVectorEnv, B = {args.batch} (total steps/s)\n")
        rows = []
        for env_id in [CARTPOLE, *ids]:
            res = native_vs_sync(env_id, args.batch, args.steps, args.rounds)
            out[env_id].update(res)
            name = f"{CARTPOLE} (CartPoleVectorEnv)" if env_id == CARTPOLE else env_id
            rows.append([name, f"{res['native_steps_per_s']:,.0f}",
                         f"{res['sync_steps_per_s']:,.0f}", f"{res['ratio']:.1f}x"])  # fmt: skip
        _table(["env", "native", "sync", "native / sync"], rows)
        for B in widths:
            print(f"\n## sub-env step vs CartPoleVectorEnv at B = {B}\n")
            res = against_cartpole_vector(ids, B, args.steps, args.rounds)
            cart = res[CARTPOLE]["sub_step_s"]
            rows = [[f"{CARTPOLE} (CartPoleVectorEnv)", _us(cart), f"{1 / cart:,.0f}", "1x"]]
            for env_id in ids:
                sub = res[env_id]["sub_step_s"]
                out[env_id].setdefault("by_B", {})[B] = res[env_id]
                rows.append([env_id, _us(sub), f"{1 / sub:,.0f}",
                             f"{res[env_id]['vs_cartpole_vector']:.0f}x"])  # fmt: skip
            out[CARTPOLE].setdefault("by_B", {})[B] = res[CARTPOLE]
            _table(["env", "per sub-env step", "sub-env steps/s", "/ CartPoleVectorEnv"], rows)
        print('\n## single env (gymnasium.make) vs gymnasium.make("CartPole-v1")\n')
        res = single_envs(ids, args.steps, args.rounds)
        rows = []
        for env_id, r in res.items():
            out[env_id].update(r)
            if env_id == CARTPOLE:
                rows.append([env_id, _us(r["step_s"]), f"{1 / r['step_s']:,.0f}", "1x",
                             _us(r["reset_s"]), "1x"])  # fmt: skip
                continue
            rows.append([env_id, _us(r["step_s"]), f"{1 / r['step_s']:,.0f}",
                         f"{r['vs_cartpole_step']:.1f}x", _us(r["reset_s"]),
                         f"{r['vs_cartpole_reset']:.0f}x"])  # fmt: skip
        _table(["env", "step", "steps/s", "/ CartPole step", "reset", "/ CartPole reset"], rows)
        if args.scaling:
            for env_id in ids:
                sc = scaling(env_id, args.steps, args.rounds)
                out[env_id]["scaling"] = sc
                print(f"\n## {env_id}: scaling in B and in {sc['size_key']}\n")
                _table(
                    ["B", *map(str, sc["steps_per_s_by_B"])],
                    [
                        ["steps/s", *(f"{v:,.0f}" for v in sc["steps_per_s_by_B"].values())],
                        ["CartPoleVectorEnv steps/s",
                         *(f"{v:,.0f}" for v in sc["cartpole_vector_steps_per_s_by_B"].values())],
                        ["/ CartPoleVectorEnv",
                         *(f"{v:.0f}x" for v in sc["vs_cartpole_vector_by_B"].values())],
                    ],
                )  # fmt: skip
                print()
                _table(
                    [sc["size_key"], *map(str, sc["sub_step_s_by_size"]), "exponent"],
                    [["us per sub-env step (B = 64)",
                      *(f"{v * 1e6:.1f}" for v in sc["sub_step_s_by_size"].values()),
                      f"{sc['exponent']:.2f}"],
                     ["single reset / CartPole reset",
                      *(f"{v:.0f}x" for v in sc["reset_vs_cartpole_by_size"].values()), ""]],
                )  # fmt: skip
    out["load_average_end"] = os.getloadavg()[0]
    print(f"\nload average {out['load_average_start']:.1f} -> {out['load_average_end']:.1f}")
    if args.json:
        atomic_write_json(args.json, out)
        print(f"json: {args.json}")


if __name__ == "__main__":
    main()
