"""PPO vs ESAPPO on InvertedPendulum-v5: learning curves, a PNG and a small table.

This is what ``make demo`` runs. Both agents get identical PPO hyperparameters and
seeds; ESAPPO adds ESA with the shipped default ``EsaConfig()`` (and a private
esa-server it starts and stops by itself). Every ``eval_every`` steps the deterministic policy is
evaluated on separate envs.

Usage::

    python client-py/examples/demo.py [--total-timesteps 60000] [--out-dir demo-results]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402
from stable_baselines3.common.env_util import make_vec_env  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.vec_env import VecEnv  # noqa: E402

from esa_client.sb3 import ESAPPO, EsaConfig  # noqa: E402


@dataclass
class Args:
    """Demo settings (all overridable on the command line)."""

    env_id: str = "InvertedPendulum-v5"
    total_timesteps: int = 60_000
    n_envs: int = 4
    n_steps: int = 512
    eval_every: int = 5_000
    eval_episodes: int = 5
    threshold: float = 950.0
    seed: int = 0
    out_dir: str = "demo-results"


def parse_args() -> Args:
    """Reads ``Args`` from the command line (``--total-timesteps 30000`` etc.)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for field in dataclasses.fields(Args):
        flag = "--" + field.name.replace("_", "-")
        parser.add_argument(flag, type=type(field.default), default=field.default)
    return Args(**vars(parser.parse_args()))


class Evaluate(BaseCallback):
    """Evaluates the deterministic policy every ``every`` steps and once at the end."""

    def __init__(self, env: VecEnv, every: int, episodes: int) -> None:
        super().__init__()
        self.env, self.every, self.episodes = env, every, episodes
        self.timesteps: list[int] = []
        self.returns: list[float] = []
        self.seconds = 0.0

    def _evaluate(self) -> None:
        start = time.perf_counter()
        mean, _ = evaluate_policy(self.model, self.env, self.episodes, deterministic=True)
        self.seconds += time.perf_counter() - start
        self.timesteps.append(self.num_timesteps)
        self.returns.append(float(mean))

    def _on_step(self) -> bool:
        if self.num_timesteps // self.every > len(self.timesteps):
            self._evaluate()
        return True

    def _on_training_end(self) -> None:
        if not self.timesteps or self.timesteps[-1] != self.num_timesteps:
            self._evaluate()


def train(name: str, args: Args) -> dict:
    """Trains one agent with periodic evaluation; returns its curve and timings."""
    env = make_vec_env(args.env_id, n_envs=args.n_envs, seed=args.seed)
    eval_env = make_vec_env(args.env_id, n_envs=1, seed=args.seed + 1000)
    evaluation = Evaluate(eval_env, args.eval_every, args.eval_episodes)
    common = dict(n_steps=args.n_steps, batch_size=64, seed=args.seed, device="cpu", verbose=0)
    if name == "ESAPPO":
        model = ESAPPO("MlpPolicy", env, esa=EsaConfig(), **common)
    else:
        model = PPO("MlpPolicy", env, **common)
    print(f"training {name} for {args.total_timesteps} steps on {args.env_id}")
    start = time.perf_counter()
    model.learn(args.total_timesteps, callback=evaluation, progress_bar=True)
    seconds = time.perf_counter() - start - evaluation.seconds
    if isinstance(model, ESAPPO):
        model.esa_close()
    returns = np.asarray(evaluation.returns)
    steps = np.asarray(evaluation.timesteps)
    reached = np.flatnonzero(returns >= args.threshold)
    return {
        "name": name,
        "timesteps": steps.tolist(),
        "mean_return": returns.tolist(),
        "final_return": float(returns[-1]) if returns.size else float("nan"),
        "steps_to_threshold": int(steps[reached[0]]) if reached.size else None,
        "train_seconds": seconds,
    }


def plot(results: list[dict], args: Args, path: Path) -> None:
    """Writes the learning curves of all agents to ``path``."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for result in results:
        ax.plot(result["timesteps"], result["mean_return"], marker="o", label=result["name"])
    ax.axhline(args.threshold, color="gray", linestyle="--", linewidth=1, label="threshold")
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"mean eval return ({args.eval_episodes} episodes)")
    ax.set_title(f"{args.env_id}: PPO vs ESAPPO (seed {args.seed})")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_table(results: list[dict], args: Args) -> None:
    """Prints final return, steps to threshold and training time per agent."""
    to_threshold = f"steps to {args.threshold:g}"
    header = f"{'agent':<8} {'final return':>13} {to_threshold:>16} {'train time':>11}"
    print(header)
    print("-" * len(header))
    for r in results:
        steps = r["steps_to_threshold"]
        reached = "not reached" if steps is None else str(steps)
        row = f"{r['name']:<8} {r['final_return']:>13.1f} {reached:>16}"
        print(f"{row} {r['train_seconds']:>10.1f}s")


def main() -> None:
    """Trains both agents, then writes the plot and the JSON results and prints the table."""
    args = parse_args()
    # Tiny MLPs train fastest single-threaded; extra threads only contend on small machines.
    th.set_num_threads(1)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = [train(name, args) for name in ("PPO", "ESAPPO")]
    plot(results, args, out / "learning_curve.png")
    (out / "results.json").write_text(
        json.dumps({"args": dataclasses.asdict(args), "results": results}, indent=2)
    )
    print()
    print_table(results, args)
    print(f"\nlearning curve: {out / 'learning_curve.png'}; raw numbers: {out / 'results.json'}")


if __name__ == "__main__":
    main()
