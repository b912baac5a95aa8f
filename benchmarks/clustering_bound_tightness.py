r"""How tight is ReceiverClustering's certified return bound, and what its refinement buys.

Reads a ``selenv bench`` JSON of ``selenv/ReceiverClustering-v2`` (the agents' per-seed returns,
episode ``e`` seeded ``seed + e``), recomputes for every seed the default bound (what the bench
reports) and the refined one (``return_bound(env, candidates=q)``: exact cluster filters around
``q`` receivers per step), and prints each agent's mean gap ``(bound - return) / |bound|`` to
both with a 95 % bootstrap CI over the seeds, and the time of each bound. Every finished seed is
kept in ``--store`` (resumable); ``--json`` gets every per-seed number (written atomically).

    .venv/bin/python benchmarks/clustering_bound_tightness.py \
        --returns docs/bench/clustering_gaps.json --candidates 2 --store /tmp/cl_bound \
        --json docs/bench/clustering_bound_tightness.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import selenv  # noqa: F401  (registers the envs)
from selenv.atomic import write_json
from selenv.bench.stats import bootstrap_ci
from selenv.families.clustering.bounds import return_bound
from selenv.parallel.store import ResultStore, task_key


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line."""
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("--returns", required=True, help="a selenv bench JSON of ReceiverClustering")
    p.add_argument("--candidates", type=int, default=2, help="receivers refined per step (>= 1)")
    p.add_argument("--store", default="", help="keep every finished seed here (resumable)")
    p.add_argument("--json", default="", help="write the per-seed numbers here")
    args = p.parse_args(argv)
    if args.candidates < 1:
        p.error(f"--candidates must be >= 1, got {args.candidates}")
    path = Path(args.returns)
    try:
        doc = json.loads(path.read_text())
        res = doc["results"][0]
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        p.error(f"--returns {path}: not a readable selenv bench JSON ({exc})")
    if not str(res.get("env_id", "")).startswith("selenv/ReceiverClustering"):
        p.error(f"--returns {path}: env {res.get('env_id')!r} is not ReceiverClustering")
    args.result = res
    return args


def bounds_of(env_id: str, kwargs: dict[str, Any], seed: int, candidates: int) -> dict[str, float]:
    """The default and refined bounds of one seed, with their compute seconds."""
    env = gym.make(env_id, **kwargs)
    try:
        env.reset(seed=seed)
        t0 = time.perf_counter()
        plain = return_bound(env.unwrapped)
        t1 = time.perf_counter()
        refined = return_bound(env.unwrapped, candidates=candidates)
        t2 = time.perf_counter()
    finally:
        env.close()
    if plain is None or refined is None:
        raise SystemExit(f"{env_id} {kwargs}: no certified bound for this configuration")
    return {
        "bound": plain.value,
        "refined": refined.value,
        "t_bound": t1 - t0,
        "t_refined": t2 - t1,
    }


def _gap(bounds: np.ndarray, returns: np.ndarray) -> dict[str, Any]:
    gaps = (bounds - returns) / np.abs(bounds)
    lo, hi = bootstrap_ci(gaps, rng=np.random.default_rng(0))
    return {"mean": float(gaps.mean()), "ci95": [lo, hi], "per_seed": gaps.tolist()}


def _pct(gap: dict[str, Any]) -> str:
    lo, hi = gap["ci95"]
    return f"{100 * gap['mean']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}]"


def main(argv: list[str] | None = None) -> int:
    """Compute every seed's bounds, print the table, write the JSON."""
    args = parse_args(argv)
    res = args.result
    env_id, kwargs, seed0 = res["env_id"], dict(res["env_kwargs"]), int(res["seed"])
    agents = {
        n: np.asarray(a["returns"], float) for n, a in res["agents"].items() if a.get("returns")
    }
    episodes = min(len(r) for r in agents.values())
    store = ResultStore(args.store) if args.store else None
    rows = []
    for e in tqdm(range(episodes), desc="bounds", unit="seed"):
        task = {
            "env_id": env_id,
            "kwargs": kwargs,
            "seed": seed0 + e,
            "candidates": args.candidates,
        }
        key = task_key(task)
        if store is not None and key in store:
            rows.append({k: float(v) for k, v in store.get(key).items()})
            continue
        t0 = time.perf_counter()
        got = bounds_of(env_id, kwargs, seed0 + e, args.candidates)
        if store is not None:
            store.write({key: {k: np.asarray(v) for k, v in got.items()}}, time.perf_counter() - t0)
        rows.append(got)
    plain = np.array([r["bound"] for r in rows])
    refined = np.array([r["refined"] for r in rows])
    out: dict[str, Any] = {
        "env_id": env_id,
        "env_kwargs": kwargs,
        "seeds": [seed0, seed0 + episodes - 1],
        "candidates": args.candidates,
        "bounds": rows,
        "agents": {},
    }
    head = f"gap to the refined bound (candidates={args.candidates})"
    print(f"| agent | gap to the bound [95 % CI] | {head} |")
    print("|---|---:|---:|")
    for name, ret in agents.items():
        g1, g2 = _gap(plain, ret[:episodes]), _gap(refined, ret[:episodes])
        out["agents"][name] = {"gap": g1, "refined_gap": g2}
        print(f"| {name} | {_pct(g1)} | {_pct(g2)} |")
    t1 = [r["t_bound"] for r in rows]
    t2 = [r["t_refined"] for r in rows]
    print(
        f"mean bound {plain.mean():.1f} ({1e3 * np.mean(t1):.0f} ms, max {1e3 * max(t1):.0f}); "
        f"refined {refined.mean():.1f} ({np.mean(t2):.1f} s, max {max(t2):.1f})"
    )
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
