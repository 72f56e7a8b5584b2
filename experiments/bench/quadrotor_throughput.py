"""Single-threaded step throughput of esa_experiments/Quadrotor-v0 without rendering.

    python experiments/bench/quadrotor_throughput.py [--steps 100000] [--path circle]

Steps the raw env (``env.unwrapped``) and the ``gymnasium.make`` env (with its default
wrappers) with pre-drawn random actions, resetting whenever an episode ends, and prints steps
per second of wall-clock time and of process CPU time (the latter is steadier on a busy
machine). Target: >= 20,000 raw steps/s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
import tyro

from esa_experiments import QUADROTOR_ENV_ID


@dataclass(frozen=True)
class Args:
    """Quadrotor env step throughput."""

    steps: int = 100_000
    """Env steps per measurement."""
    path: Literal["circle", "eight", "hover"] = "circle"
    """Reference path of the env."""
    seed: int = 0
    """Seed of the random actions and of the first reset."""
    repeats: int = 3
    """Measurements per env; the best one is printed."""


def measure(env: gym.Env, actions: np.ndarray, seed: int) -> tuple[float, float]:
    """Return (wall, cpu) steps per second of stepping ``env`` through ``actions``."""
    env.reset(seed=seed)
    wall, cpu = time.perf_counter(), time.process_time()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return len(actions) / wall, len(actions) / cpu


def main(args: Args) -> None:
    wrapped = gym.make(QUADROTOR_ENV_ID, path=args.path)
    # Small random actions keep episodes long, so resets do not dominate the timing.
    rng = np.random.default_rng(args.seed)
    actions = rng.uniform(-0.05, 0.05, size=(args.steps, 4)).astype(np.float32)
    print(f"{QUADROTOR_ENV_ID} path={args.path}, {args.steps} steps, best of {args.repeats}")
    for label, env in (("raw env", wrapped.unwrapped), ("gymnasium.make", wrapped)):
        results = [measure(env, actions, args.seed) for _ in range(args.repeats)]
        best_wall = max(r[0] for r in results)
        best_cpu = max(r[1] for r in results)
        print(f"  {label:15s} {best_wall:9,.0f} steps/s wall   {best_cpu:9,.0f} steps/s CPU")
    wrapped.close()


if __name__ == "__main__":
    main(tyro.cli(Args))
