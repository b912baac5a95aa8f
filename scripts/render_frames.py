"""Render one frame of every selenv env (default keywords) into ``docs/figures/render_*.png``.

Each env is made with ``render_mode="rgb_array"`` and played for a few steps by its greedy
agent (the frame shows picks and links), then ``env.render()`` is saved as a PNG. Usage::

    .venv/bin/python scripts/render_frames.py [--out docs/figures] [--steps 6] [--seed 0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import matplotlib.image as mpimg
import numpy as np

import selenv
from selenv.agents import make
from selenv.atomic import atomic_path

FRAMES = {
    "selenv/FIMSelection-v1": ("render_fim_selection.png", "greedy"),
    "selenv/LandmarkSelection-v1": ("render_landmark_selection.png", "greedy"),
    "selenv/CLScheduling-v1": ("render_cl_scheduling.png", "greedy"),
    "selenv/ReceiverClustering-v1": ("render_receiver_clustering.png", "greedy"),
}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", default="docs/figures", help="output folder (default: %(default)s)"
    )
    parser.add_argument(
        "--steps", type=int, default=5, help="steps before the frame (default: %(default)s)"
    )
    parser.add_argument("--seed", type=int, default=0, help="reset seed (default: %(default)s)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for env_id, (name, agent_name) in FRAMES.items():
        env = gym.make(env_id, render_mode="rgb_array")
        obs, info = env.reset(seed=args.seed)
        agent = make(agent_name, env_id)
        agent.reset(env, seed=args.seed)
        steps = 0
        # play the steps; CL: go on until a link is being processed, so the frame shows one
        none_yet = lambda info: not np.any(info.get("processed", True))  # noqa: E731
        while steps < args.steps or (none_yet(info) and steps < 10 * args.steps):
            obs, _r, terminated, truncated, info = env.step(agent.act(obs, info))
            steps += 1
            if terminated or truncated:
                break
        frame = env.render()
        with atomic_path(out / name) as temp:
            mpimg.imsave(temp, frame, format="png")
        print(f"{env_id}: {frame.shape} -> {out / name}")
        env.close()
    print(f"selenv {selenv.__version__}")


if __name__ == "__main__":
    main()
