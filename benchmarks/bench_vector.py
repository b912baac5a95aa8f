"""Throughput of the native vector envs against Gymnasium's SyncVectorEnv and CartPole-v1.

One process, one BLAS thread, interleaved rounds (each round times every contender once, so a
load change hits all of them alike); medians of ``--rounds`` rounds; random masked actions,
sampled outside the timed calls. Printed as Markdown tables:

1. **native vs sync**: total steps/s of ``gymnasium.make_vec(id, num_envs=B)`` (the family's
   native vector env) and of ``SyncVectorEnv`` over ``B`` ``gymnasium.make(id)`` envs, default
   keywords, ``B = --batch`` (64); CartPole-v1's own native vs sync as the anchor.
2. **per sub-env step** at ``B = --wide`` (256) against one ``CartPole-v1`` step, and one
   single-env ``reset`` against ``CartPole-v1``'s.
3. **scaling** (``--scaling``): steps/s of the native env for ``B = 1 .. 1024`` and the time per
   sub-env step against the family's size parameter (candidates, landmarks, agents,
   receivers) with the fitted cost exponent ``t ~ size^p``.

    .venv/bin/python benchmarks/bench_vector.py                   # tables 1 and 2
    .venv/bin/python benchmarks/bench_vector.py --scaling --json docs/bench/vector.json
    make perf-vector                                              # all of it

``--json PATH`` writes the figures (atomically: a temporary file, then a rename).
"""

from __future__ import annotations

import argparse
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
from selenv.threads import limit_threads

#: family id -> (size keyword, sizes for the scaling table, keywords that keep the scan cheap)
SIZES: dict[str, tuple[str, list[int], dict[str, Any]]] = {
    "selenv/FIMSelection-v1": ("n_candidates", [25, 50, 100, 200, 400], {}),
    "selenv/LandmarkSelection-v1": ("n_landmarks", [10, 20, 30, 60, 120], {}),
    "selenv/CLScheduling-v1": ("n_agents", [3, 4, 6, 8, 12, 16], {}),
    "selenv/ReceiverClustering-v1": ("n_agents", [10, 20, 30, 60], {}),
}


def sample(masks: np.ndarray, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """One random allowed action per sub-env from ``(B, n)`` or ``(B, k * n)`` masks."""
    m = np.asarray(masks, dtype=bool).reshape(shape)
    score = rng.random(m.shape) + m  # allowed entries beat every masked one
    return np.argmax(score, axis=-1)


def _shape(venv: Any) -> tuple[int, ...]:
    space = venv.single_action_space
    if isinstance(space, gym.spaces.MultiDiscrete):
        return (venv.num_envs, len(space.nvec), int(space.nvec[0]))
    return (venv.num_envs, int(space.n))


def _masks(venv: Any) -> np.ndarray:
    if hasattr(venv, "action_masks"):
        return np.asarray(venv.action_masks())
    return np.stack(venv.call("action_masks"))


class Runner:
    """A vector env stepped with random masked actions; :meth:`run` times ``steps`` steps."""

    def __init__(self, make: Callable[[], Any], seed: int = 0) -> None:
        self.venv = make()
        self.rng = np.random.default_rng(seed)
        self.venv.reset(seed=seed)
        self.shape = _shape(self.venv)
        self.masked = self.venv.single_action_space.__class__.__name__ != "Box"

    def run(self, steps: int) -> float:
        """Seconds spent inside ``step`` for ``steps`` steps (sampling excluded)."""
        spent = 0.0
        for _ in range(steps):
            actions = sample(_masks(self.venv), self.rng, self.shape)
            t = time.perf_counter()
            self.venv.step(actions)
            spent += time.perf_counter() - t
        return spent

    def close(self) -> None:  # noqa: D102
        self.venv.close()


class CartPoleRunner(Runner):
    """CartPole has no masks: uniform random actions."""

    def run(self, steps: int) -> float:  # noqa: D102
        spent = 0.0
        for _ in range(steps):
            actions = self.rng.integers(0, 2, self.venv.num_envs)
            t = time.perf_counter()
            self.venv.step(actions)
            spent += time.perf_counter() - t
        return spent


def interleaved(runners: dict[str, Runner], steps: int, rounds: int) -> dict[str, float]:
    """Median seconds per vector step of each runner over interleaved rounds."""
    times: dict[str, list[float]] = {k: [] for k in runners}
    for runner in runners.values():
        runner.run(2)  # warm-up
    for _ in range(rounds):
        for name, runner in runners.items():
            times[name].append(runner.run(steps) / steps)
    return {k: statistics.median(v) for k, v in times.items()}


def native_vs_sync(env_id: str, B: int, steps: int, rounds: int, **kw: Any) -> dict[str, float]:
    """Steps/s of the native vector env and of SyncVectorEnv at ``B``, and their ratio."""
    cls = CartPoleRunner if env_id == "CartPole-v1" else Runner
    runners = {
        "native": cls(lambda: gym.make_vec(env_id, num_envs=B, **kw)),
        "sync": cls(lambda: gym.make_vec(env_id, num_envs=B, vectorization_mode="sync", **kw)),
    }
    med = interleaved(runners, steps, rounds)
    for r in runners.values():
        r.close()
    return {
        "native_steps_per_s": B / med["native"],
        "sync_steps_per_s": B / med["sync"],
        "ratio": med["sync"] / med["native"],
    }


def single_reset_seconds(env_id: str, rounds: int) -> float:
    """Median seconds of one ``reset`` of one ``gymnasium.make(env_id)`` env (seeded anew)."""
    env = gym.make(env_id)
    env.reset(seed=0)
    ts = []
    for r in range(rounds):
        t = time.perf_counter()
        env.reset(seed=r + 1)
        ts.append(time.perf_counter() - t)
    env.close()
    return statistics.median(ts)


def cartpole_step_seconds(rounds: int, steps: int = 2000) -> float:
    """Median seconds of one ``CartPole-v1`` step (``gymnasium.make``, checker wrappers on)."""
    env = gym.make("CartPole-v1")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    ts = []
    for _ in range(rounds):
        t = time.perf_counter()
        for _ in range(steps):
            _, _, te, tr, _ = env.step(int(rng.integers(2)))
            if te or tr:
                env.reset()
        ts.append((time.perf_counter() - t) / steps)
    env.close()
    return statistics.median(ts)


def scaling(env_id: str, steps: int, rounds: int) -> dict[str, Any]:
    """Steps/s vs ``B`` and time per sub-env step vs the family's size, with the exponent."""
    by_b = {}
    for B in (1, 4, 16, 64, 256, 1024):
        r = Runner(lambda B=B: gym.make_vec(env_id, num_envs=B))
        med = interleaved({"n": r}, max(2, steps // max(1, B // 64)), max(3, rounds // 3))["n"]
        r.close()
        by_b[B] = B / med
    key, sizes, extra = SIZES[env_id]
    by_size = {}
    for size in sizes:
        kw = {key: size, **extra}
        r = Runner(lambda kw=kw: gym.make_vec(env_id, num_envs=64, **kw))
        med = interleaved({"n": r}, steps, max(3, rounds // 3))["n"]
        r.close()
        by_size[size] = med / 64
    xs = np.log(np.array(list(by_size), float))
    ys = np.log(np.array(list(by_size.values())))
    slope = float(np.polyfit(xs, ys, 1)[0])
    return {
        "steps_per_s_by_B": by_b,
        "size_key": key,
        "sub_step_s_by_size": by_size,
        "exponent": slope,
    }


def write_json(path: str, data: dict[str, Any]) -> None:
    """Write ``data`` to ``path`` atomically (:func:`selenv.atomic.write_json`)."""
    atomic_write_json(path, data)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--steps", type=int, default=20, help="vector steps per round")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--wide", type=int, default=256)
    ap.add_argument("--ids", nargs="*", help="family ids (default: every one with a native env)")
    ap.add_argument("--scaling", action="store_true", help="also the scaling tables")
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    ids = args.ids or [f.current_id for f in FAMILIES if f.vector_class is not None]
    out: dict[str, Any] = {"batch": args.batch, "wide": args.wide, "rounds": args.rounds}
    with limit_threads(blas=1, torch=1):
        cart = native_vs_sync("CartPole-v1", args.batch, args.steps * 5, args.rounds)
        cp_step = cartpole_step_seconds(args.rounds)
        cp_reset = single_reset_seconds("CartPole-v1", 200)
        out["CartPole-v1"] = {**cart, "step_s": cp_step, "reset_s": cp_reset}
        print(f"## native vs SyncVectorEnv, B = {args.batch} (total steps/s; one BLAS thread)\n")
        print("| env | native | sync | native / sync |")
        print("|---|---|---|---|")
        print(
            f"| CartPole-v1 (anchor) | {cart['native_steps_per_s']:,.0f} | "
            f"{cart['sync_steps_per_s']:,.0f} | {cart['ratio']:.1f}x |"
        )
        for env_id in ids:
            res = native_vs_sync(env_id, args.batch, args.steps, args.rounds)
            out[env_id] = dict(res)
            print(
                f"| {env_id} | {res['native_steps_per_s']:,.0f} | "
                f"{res['sync_steps_per_s']:,.0f} | {res['ratio']:.1f}x |",
                flush=True,
            )
        print(
            f"\n## per sub-env step at B = {args.wide} and one reset, vs CartPole-v1 "
            f"(step {cp_step * 1e6:.1f} us, reset {cp_reset * 1e6:.1f} us)\n"
        )
        print("| env | sub-env step | / CartPole step | single-env reset | / CartPole reset |")
        print("|---|---|---|---|---|")
        for env_id in ids:
            r = Runner(lambda env_id=env_id: gym.make_vec(env_id, num_envs=args.wide))
            med = interleaved({"n": r}, max(2, args.steps // 2), args.rounds)["n"]
            r.close()
            sub = med / args.wide
            reset = single_reset_seconds(env_id, max(5, args.rounds))
            out[env_id].update({"sub_step_s_wide": sub, "reset_s": reset})
            print(
                f"| {env_id} | {sub * 1e6:.1f} us | {sub / cp_step:.2f}x | "
                f"{reset * 1e3:.3f} ms | {reset / cp_reset:.0f}x |",
                flush=True,
            )
        if args.scaling:
            for env_id in ids:
                sc = scaling(env_id, args.steps, args.rounds)
                out[env_id]["scaling"] = sc
                print(f"\n## {env_id}: scaling\n")
                print("| B | " + " | ".join(str(b) for b in sc["steps_per_s_by_B"]) + " |")
                print("|---" * (len(sc["steps_per_s_by_B"]) + 1) + "|")
                print(
                    "| steps/s | "
                    + " | ".join(f"{v:,.0f}" for v in sc["steps_per_s_by_B"].values())
                    + " |"
                )
                print(
                    f"\n| {sc['size_key']} | "
                    + " | ".join(str(s) for s in sc["sub_step_s_by_size"])
                    + " | exponent |"
                )
                print("|---" * (len(sc["sub_step_s_by_size"]) + 2) + "|")
                print(
                    "| us per sub-env step (B = 64) | "
                    + " | ".join(f"{v * 1e6:.1f}" for v in sc["sub_step_s_by_size"].values())
                    + f" | {sc['exponent']:.2f} |",
                    flush=True,
                )
    if args.json:
        write_json(args.json, out)
        print(f"\njson: {args.json}")


if __name__ == "__main__":
    main()
