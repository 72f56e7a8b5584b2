"""Does a published PPO setting learn to hop on Hopper-v5 within a million steps?

Every PPO we ran on Hopper-v5 (this suite's settings and RL Zoo3's tuned ones, study
``paper_regime``) settled on standing still, so ESA was never tested where PPO learns the
gait. This pre-check asks whether one published setting does, before a study spends 30 runs
on it. It trains plain stable-baselines3 PPO: nothing of esa runs here.

Rules, fixed and committed before the first run:

* **Setting.** cleanrl's ``ppo_continuous_action`` settings in SB3: SB3's default PPO
  (``n_steps`` 2048, ``batch_size`` 64, ``n_epochs`` 10, ``gamma`` 0.99, ``gae_lambda``
  0.95, ``clip_range`` 0.2, ``MlpPolicy`` with 64-64 tanh networks), a learning rate of
  3e-4 annealed linearly to 0 over the budget, ``VecNormalize`` on observations and rewards
  (SB3's defaults: clipped at 10, the rewards' return with the run's gamma), one env.
* **Budget** 1,000,000 steps (SB3 runs whole rollouts: 489 of 2,048, 1,001,472 steps).
* **Seeds** 0, 1, 2, all run, none dropped.
* **Evaluation.** Every 32,768 steps (16 rollouts), 3 deterministic episodes on a separate
  env with the normalization statistics frozen, the env's own returns: the curve. At the
  end, 10 deterministic episodes: the **final evaluation**, the metric of this check.
* **Decision.** The setting passes if at least 2 of the 3 seeds' final evaluations are
  above 1,400 (a Hopper that stands scores about 1,000: the alive bonus of 1,000 steps).
  A pass makes it the setting of the hopping study; a fail is reported with the numbers.
* **Outputs** in ``results/hopping_precheck/``: ``runs/s<seed>.csv`` (the curve, the final
  evaluation on its last row), ``runs/s<seed>.json`` (settings, seconds, versions),
  ``README.md`` (the table and the verdict) and ``curves.png``.

Usage (resumable: a seed whose files exist is skipped; a run cut short resumes from its last
checkpoint, saved at every evaluation of the curve outside the work tree, in ``--checkpoints``.
A resumed run continues the same model, normalization and schedule, but not the same random
stream: its JSON records where it resumed)::

    python experiments/scripts/hopping_precheck.py             # the check: 3 seeds, 1M steps
    python experiments/scripts/hopping_precheck.py --seeds 1   # one seed (a process each)
    python experiments/scripts/hopping_precheck.py --steps 4096 --eval-every 2048 \
        --out /tmp/precheck                                    # a smoke run
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium as gym
import matplotlib
import mujoco
import numpy as np
import pandas as pd
import stable_baselines3
import torch as th
import tyro
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)

RESULTS = Path(__file__).resolve().parents[1] / "results" / "hopping_precheck"
STANDING = 1_400.0
"""The final evaluation a hopping seed must beat; a standing Hopper scores about 1,000."""
SEEDS = (0, 1, 2)
"""The rules' seeds: the verdict waits for all of them."""


@dataclass(frozen=True)
class Args:
    """The pre-check's arguments; the defaults are the committed rules."""

    env: str = "Hopper-v5"
    """The gymnasium env id."""
    seeds: tuple[int, ...] = SEEDS
    """Seeds, run one after the other (one process per seed runs them side by side)."""
    steps: int = 1_000_000
    """Training budget in env steps."""
    eval_every: int = 32_768
    """Steps between the curve's evaluations."""
    eval_episodes: int = 3
    """Deterministic episodes per evaluation of the curve."""
    final_episodes: int = 10
    """Deterministic episodes of the final evaluation."""
    learning_rate: float = 3e-4
    """Initial learning rate, annealed linearly to 0."""
    out: Path = RESULTS
    """Folder of the results."""
    checkpoints: Path = Path.home() / ".cache" / "esa-experiments" / "hopping_precheck"
    """Folder of the runs' checkpoints (model, normalization, curve so far)."""


def make_env(env_id: str, seed: int) -> VecNormalize:
    """One monitored env under ``VecNormalize`` (observations and rewards)."""
    env = DummyVecEnv([lambda: Monitor(gym.make(env_id))])
    env.seed(seed)
    return VecNormalize(env, gamma=0.99)


def evaluate(model: PPO, train_env: VecNormalize, eval_env: VecNormalize, episodes: int) -> float:
    """Mean return of ``episodes`` deterministic episodes, the normalization frozen."""
    eval_env.obs_rms = train_env.obs_rms.copy()
    returns, _ = evaluate_policy(model, eval_env, n_eval_episodes=episodes, deterministic=True)
    return float(np.mean(returns))


class Curve(BaseCallback):
    """Evaluates every ``every`` steps, prints a line and saves a checkpoint each time."""

    def __init__(
        self,
        eval_env: VecNormalize,
        every: int,
        episodes: int,
        label: str,
        checkpoint: Path,
        rows: list[dict[str, float]],
    ) -> None:
        """Holds the evaluation env and schedule, and the curve so far."""
        super().__init__()
        self.eval_env, self.every, self.episodes, self.label = eval_env, every, episodes, label
        self.checkpoint = checkpoint
        self.rows = rows
        self.started = time.monotonic()

    def _on_step(self) -> bool:
        if self.num_timesteps % self.every == 0:
            train_env = self.model.get_vec_normalize_env()
            assert train_env is not None
            value = evaluate(self.model, train_env, self.eval_env, self.episodes)  # type: ignore[arg-type]
            self.rows.append({"step": self.num_timesteps, "return_mean": value, "final": 0})
            minutes = (time.monotonic() - self.started) / 60
            print(
                f"{self.label}: step {self.num_timesteps:>9,}  return {value:8.1f}  "
                f"({minutes:.1f} min)",
                flush=True,
            )
            self.checkpoint.mkdir(parents=True, exist_ok=True)
            self.model.save(self.checkpoint / "model.zip")
            train_env.save(str(self.checkpoint / "vecnormalize.pkl"))
            (self.checkpoint / "curve.json").write_text(json.dumps(self.rows))
        return True


def run_seed(args: Args, seed: int) -> None:
    """Trains one seed and writes its CSV and JSON (atomically, at the end)."""
    th.set_num_threads(1)
    train_env = make_env(args.env, seed)
    eval_env = make_env(args.env, seed + 10_000)
    eval_env.training, eval_env.norm_reward = False, False
    checkpoint = args.checkpoints / f"s{seed}"
    schedule = {"learning_rate": lambda remaining: args.learning_rate * remaining}
    rows: list[dict[str, float]] = []
    resumed_at = None
    if (checkpoint / "curve.json").exists():
        train_env = VecNormalize.load(str(checkpoint / "vecnormalize.pkl"), train_env.venv)
        model = PPO.load(checkpoint / "model.zip", train_env, device="cpu", custom_objects=schedule)
        rows = json.loads((checkpoint / "curve.json").read_text())
        resumed_at = model.num_timesteps
        print(f"{args.env} s{seed}: resumed at step {resumed_at:,}", flush=True)
    else:
        model = PPO("MlpPolicy", train_env, seed=seed, device="cpu", **schedule)
    label = f"{args.env} s{seed}"
    curve = Curve(eval_env, args.eval_every, args.eval_episodes, label, checkpoint, rows)
    started = time.monotonic()
    # The schedule's progress is num_timesteps over the whole budget, resumed or not.
    model.learn(args.steps - model.num_timesteps, callback=curve, reset_num_timesteps=False)
    final = evaluate(model, train_env, eval_env, args.final_episodes)
    seconds = time.monotonic() - started
    rows = [*curve.rows, {"step": model.num_timesteps, "return_mean": final, "final": 1}]
    print(f"{label}: final evaluation {final:.1f} ({args.final_episodes} episodes)", flush=True)
    runs = args.out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    meta = {
        "args": {**asdict(args), "out": None, "checkpoints": None, "seeds": [seed]},
        "seconds": round(seconds, 1),
        "resumed_at": resumed_at,
        "final_evaluation": final,
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "versions": {
            "stable_baselines3": stable_baselines3.__version__,
            "gymnasium": gym.__version__,
            "mujoco": mujoco.__version__,
            "torch": th.__version__,
            "python": platform.python_version(),
        },
    }
    for suffix, text in (
        (".csv", pd.DataFrame(rows).to_csv(index=False)),
        (".json", json.dumps(meta, indent=2) + "\n"),
    ):
        tmp = runs / f"s{seed}{suffix}.tmp"
        tmp.write_text(text)
        tmp.replace(runs / f"s{seed}{suffix}")
    shutil.rmtree(checkpoint, ignore_errors=True)  # the run is done: nothing to resume


def report(args: Args) -> None:
    """Writes the table, the verdict and the curves of the seeds that finished."""
    runs = sorted((args.out / "runs").glob("s*.csv"), key=lambda p: int(p.stem[1:]))
    frames = {int(p.stem[1:]): pd.read_csv(p) for p in runs}
    if not frames:
        return
    finals = {seed: float(f[f.final == 1].return_mean.iloc[0]) for seed, f in frames.items()}
    hopping = sum(value > STANDING for value in finals.values())
    if not set(SEEDS) <= set(finals):
        verdict = f"{len(finals)} of {len(SEEDS)} seeds in: no verdict yet."
    elif hopping >= 2:
        verdict = f"**Passes**: {hopping} of {len(finals)} seeds end above {STANDING:,.0f}."
    else:
        verdict = f"**Fails**: {hopping} of {len(finals)} seeds end above {STANDING:,.0f}."
    lines = [
        "# Hopping pre-check: PPO with cleanrl's settings on Hopper-v5",
        "",
        "Rules and settings: `experiments/scripts/hopping_precheck.py` (its docstring).",
        "Command: `python experiments/scripts/hopping_precheck.py`.",
        "",
        "| seed | final evaluation (10 episodes) | best curve point | minutes |",
        "|---:|---:|---:|---:|",
    ]
    for seed, frame in frames.items():
        meta = json.loads((args.out / "runs" / f"s{seed}.json").read_text())
        best = frame[frame.final == 0].return_mean.max()
        lines.append(f"| {seed} | {finals[seed]:,.0f} | {best:,.0f} | {meta['seconds'] / 60:.1f} |")
    lines += [
        "",
        verdict,
        "",
        "Minutes are each run's wall-clock; runs side by side share the host's cores, so they",
        "are not timings. The host and versions are in each run's JSON.",
        "",
        "![curves](curves.png)",
        "",
    ]
    (args.out / "README.md").write_text("\n".join(lines))
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for seed, frame in frames.items():
        curve = frame[frame.final == 0]
        ax.plot(curve.step, curve.return_mean, label=f"seed {seed}")
    ax.axhline(STANDING, color="grey", linestyle="--", linewidth=1, label="hopping threshold")
    ax.set_xlabel("env steps")
    ax.set_ylabel("evaluation return")
    ax.set_title(f"PPO (cleanrl settings) on {args.env}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "curves.png", dpi=120)
    plt.close(fig)
    print(verdict)


def main() -> None:
    """Runs the seeds that have no result yet, then reports."""
    args = tyro.cli(Args)
    for seed in args.seeds:
        if (args.out / "runs" / f"s{seed}.csv").exists():
            print(f"{args.env} s{seed}: done, skipped")
            continue
        run_seed(args, seed)
    report(args)


if __name__ == "__main__":
    main()
