"""PPO vs ESAPPO on InvertedPendulum-v5 over a few seeds: curves, spread, cost, the studies' word.

This is what ``make demo`` runs. One seed can mislead, so the demo trains both agents on
``seeds`` seeds with identical PPO hyperparameters (the reproduction suite's: 4 envs x 256
steps, 64-64 MLPs), plots every seed and the mean, prints each seed's AUC (mean evaluation
return over training), the spread and what ESA cost in training time here, and ends with
what the studies found for the shipped defaults (``experiments/results/*/verdicts*.md``,
when the checkout has them): ``seeking`` (E2, 20 seeds) tested ESAPPO's default,
``EsaConfig.ppo()`` with the quadratic head and the decoupled objective, as its ``ppo_esa``
arm, the confirmation campaign (20 seeds) ESASAC's and ESATD3's, and ``paper_regime`` (10
seeds) ESAPPO's on a tuned PPO at a million steps. ESAPPO runs its shipped default on the
in-process engine.

Usage::

    python client-py/examples/demo.py [--seeds 3] [--total-timesteps 30720] [--out-dir demo-results]
"""

from __future__ import annotations

import dataclasses
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch as th  # noqa: E402
import tyro  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402
from stable_baselines3.common.env_util import make_vec_env  # noqa: E402
from stable_baselines3.common.evaluation import evaluate_policy  # noqa: E402
from stable_baselines3.common.vec_env import VecEnv  # noqa: E402

from esa_client.sb3 import ESAPPO  # noqa: E402


@dataclass
class Args:
    """PPO vs ESAPPO over a few seeds (every setting overridable on the command line)."""

    env_id: str = "InvertedPendulum-v5"
    """Gymnasium id of the env."""
    total_timesteps: int = 30_720
    """Env steps per training run."""
    n_envs: int = 4
    """Parallel training envs."""
    n_steps: int = 256
    """PPO rollout length per env."""
    eval_every: int = 2_048
    """Env steps between evaluations of the deterministic policy."""
    eval_episodes: int = 5
    """Episodes per evaluation."""
    threshold: float = 950.0
    """Evaluation return that counts as solved (steps-to-threshold column)."""
    seeds: int = 3
    """Seeds per agent: 0, 1, ..., seeds - 1."""
    out_dir: str = "demo-results"
    """Folder of the figure and the JSON of every run."""


RESULTS = Path(__file__).resolve().parents[2] / "experiments/results"


class StudyVerdicts(NamedTuple):
    """A committed verdict table the demo ends with, and how to read it."""

    study: str
    """The study's folder under ``experiments/results``."""
    table: str
    """Its verdict table's file name."""
    what: str
    """What the line reports, after the study's name."""
    families: tuple[str, ...]
    """The algorithm families whose rows count (``ppo``, ``sac``, ``td3``)."""
    seeds: int
    """The seeds per arm the study's rules fix: a comparison counts once it has them all."""


VERDICTS = (
    StudyVerdicts(
        "seeking",
        "verdicts_first.md",
        "envs where ESAPPO's shipped default is better, equal or worse than PPO over the "
        "first third of training",
        ("ppo",),
        20,
    ),
    StudyVerdicts("seeking", "verdicts_whole.md", "the same over the whole run", ("ppo",), 20),
    StudyVerdicts(
        "confirmation",
        "verdicts.md",
        "envs where ESASAC's and ESATD3's shipped defaults are better, equal or worse than "
        "SAC and TD3",
        ("sac", "td3"),
        20,
    ),
    StudyVerdicts(
        "paper_regime",
        "verdicts_first.md",
        "whether ESAPPO's shipped default is better, equal or worse than RL Zoo3's tuned "
        "PPO on Hopper-v5 over the first third of a million steps",
        ("ppo",),
        10,
    ),
    StudyVerdicts("paper_regime", "verdicts_whole.md", "the same over the whole run", ("ppo",), 10),
)
"""What the studies found for the shipped defaults, in the order the demo prints it."""


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


def train(name: str, seed: int, args: Args) -> dict:
    """Trains one agent on one seed with periodic evaluation; returns its curve and timings."""
    env = make_vec_env(args.env_id, n_envs=args.n_envs, seed=seed)
    eval_env = make_vec_env(args.env_id, n_envs=1, seed=seed + 1000)
    evaluation = Evaluate(eval_env, args.eval_every, args.eval_episodes)
    common = dict(
        n_steps=args.n_steps,
        batch_size=64,
        seed=seed,
        device="cpu",
        verbose=0,
        policy_kwargs=dict(net_arch=[64, 64]),
    )
    if name == "ESAPPO":
        model = ESAPPO("MlpPolicy", env, **common)  # the shipped default, EsaConfig.ppo()
    else:
        model = PPO("MlpPolicy", env, **common)
    print(f"training {name} (seed {seed}) for {args.total_timesteps} steps on {args.env_id}")
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
        "seed": seed,
        "timesteps": steps.tolist(),
        "mean_return": returns.tolist(),
        "auc": float(np.trapezoid(returns, steps) / (steps[-1] - steps[0])),
        "final_return": float(returns[-1]) if returns.size else float("nan"),
        "steps_to_threshold": int(steps[reached[0]]) if reached.size else None,
        "train_seconds": seconds,
    }


def plot(results: list[dict], args: Args, path: Path) -> None:
    """Writes every seed's curve (thin) and each agent's mean over seeds (bold) to ``path``."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for color, name in (("tab:blue", "PPO"), ("tab:orange", "ESAPPO")):
        runs = [r for r in results if r["name"] == name]
        for r in runs:
            ax.plot(r["timesteps"], r["mean_return"], color=color, alpha=0.3, linewidth=1)
        mean = np.mean([r["mean_return"] for r in runs], axis=0)
        ax.plot(runs[0]["timesteps"], mean, color=color, linewidth=2.5, label=f"{name} (mean)")
    ax.axhline(args.threshold, color="gray", linestyle="--", linewidth=1, label="threshold")
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"mean eval return ({args.eval_episodes} episodes)")
    ax.set_title(f"{args.env_id}: PPO vs ESAPPO, {args.seeds} seeds (thin: each seed)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_table(results: list[dict], args: Args) -> None:
    """Prints each seed's AUC, final return and time, then each agent's mean and spread."""
    to_threshold = f"steps to {args.threshold:g}"
    header = (
        f"{'agent':<8} {'seed':>4} {'AUC':>7} {'final':>7} {to_threshold:>16} {'train time':>11}"
    )
    print(header)
    print("-" * len(header))
    for r in results:
        steps = r["steps_to_threshold"]
        reached = "not reached" if steps is None else str(steps)
        row = f"{r['name']:<8} {r['seed']:>4} {r['auc']:>7.1f} {r['final_return']:>7.1f}"
        print(f"{row} {reached:>16} {r['train_seconds']:>10.1f}s")
    print()
    for name in ("PPO", "ESAPPO"):
        auc = np.array([r["auc"] for r in results if r["name"] == name])
        print(f"{name:<8} AUC {auc.mean():.1f} (min {auc.min():.1f}, max {auc.max():.1f})")
    seconds = {
        name: np.mean([r["train_seconds"] for r in results if r["name"] == name])
        for name in ("PPO", "ESAPPO")
    }
    print(
        f"ESAPPO's training time here: {seconds['ESAPPO'] / seconds['PPO']:.2f}x PPO's (ESA acts "
        "over the first half of training; BENCHMARKS.md has the measured overhead)."
    )
    study_seeds = " or ".join(str(n) for n in sorted({v.seeds for v in VERDICTS}))
    print(
        f"With {args.seeds} seed{'s' if args.seeds > 1 else ''} a difference inside that spread "
        f"is noise; the studies below use {study_seeds} seeds per arm."
    )


def verdict_line(verdicts: StudyVerdicts) -> str:
    """One line of a study's verdicts, counted from its committed table.

    Counts the envs where each family's ESA arm (``PPO+ESA``, or ``PPO+ESA (quadratic)``
    with its critic named) is better, equal or worse than that family's baseline (``PPO``,
    or ``PPO (RL Zoo3)`` with its settings named). Only comparisons with all their seeds
    count; the others are named as in progress.
    """
    study, table, what, families, seeds = verdicts
    path = RESULTS / study / table
    if not path.is_file():
        return f"{study}: no verdicts in this checkout yet (experiments/RESULTS.md says why)."
    counts: dict[str, dict[str, int]] = {}
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) < 9:
            continue
        if cells[0] not in families:
            continue
        family = cells[0].upper()
        if not re.fullmatch(rf"{family}( \(.+\))? \(baseline\)", cells[3]) or not re.fullmatch(
            rf"{family}\+ESA( \(.+\))?", cells[2]
        ):
            continue
        word = re.sub(r"\*", "", cells[-1]) if cells[4] == str(seeds) else "in progress"
        tally = counts.setdefault(cells[2], {"better": 0, "equal": 0, "worse": 0})
        tally[word] = tally.get(word, 0) + 1
    parts = [
        f"{arm} better on {c['better']}, equal on {c['equal']}, worse on {c['worse']}"
        + (f" ({c['in progress']} more in progress)" if c.get("in progress") else "")
        for arm, c in counts.items()
    ]
    return (
        f"{study} (experiments/RESULTS.md; {what}, with all {seeds} seeds, Holm-corrected): "
        + ("; ".join(parts) if parts else "no finished comparison yet")
        + "."
    )


def main() -> None:
    """Trains both agents on every seed, writes the plot and the JSON, prints the table."""
    args = tyro.cli(Args)
    # Tiny MLPs train fastest single-threaded; extra threads only contend on small machines.
    th.set_num_threads(1)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = [train(name, seed, args) for seed in range(args.seeds) for name in ("PPO", "ESAPPO")]
    plot(results, args, out / "learning_curve.png")
    (out / "results.json").write_text(
        json.dumps({"args": dataclasses.asdict(args), "results": results}, indent=2)
    )
    print()
    print_table(results, args)
    # dict.fromkeys keeps the order and prints a study without verdicts yet once, not per table.
    for line in dict.fromkeys(map(verdict_line, VERDICTS)):
        print(line)
    print(f"\nlearning curve: {out / 'learning_curve.png'}; raw numbers: {out / 'results.json'}")


if __name__ == "__main__":
    main()
