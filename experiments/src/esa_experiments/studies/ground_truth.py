"""Does ESA's shift point uphill on the true returns? A check that trusts no critic.

For each env: train PPO+ESA (the shipped default) for half the campaign's budget, then
run the trained policy with ESA switched on (gate ignored, so the shift is what ESA would
do) and save ``states`` MuJoCo states (``qpos``/``qvel``) with the sampled action ``a_t``,
ESA's action ``a_t + v(t)`` and the action ESA would take with a trust region of one
policy standard deviation (``wide``: ESA's direction, where the shipped bound keeps the
shift small; see :mod:`esa_experiments.state_capture`). From every saved state, execute
each action and then follow the stochastic policy for ``horizon`` steps, ``rollouts``
times with common random numbers for every branch, and compare the discounted
Monte-Carlo returns. A positive mean difference means ESA's shifts improved the actions
by the environment's own measure; the rank correlation of the head's predicted
``A(s, a + v) - A(s, a)`` with the measured difference says how much of it the critic knew.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import pandas as pd
import torch as th
from matplotlib.figure import Figure

from esa_experiments.evaluation import ProgressFn
from esa_experiments.runs import RunResult, RunSpec, RunStore, atomic_write_text
from esa_experiments.state_capture import SavedState, capture_states, gaussian
from esa_experiments.studies import campaign
from esa_experiments.tables import to_markdown
from esa_experiments.tasks import get_task
from esa_experiments.training import StepBudget, rl_spec, trained

if TYPE_CHECKING:
    from esa_client.sb3 import ESAPPO
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
    from stable_baselines3.common.base_class import BaseAlgorithm

NAME = "ground_truth"
DESCRIPTION = "Monte-Carlo returns of a_t vs ESA's a_t + v(t) from saved MuJoCo states"
ENVS = ("InvertedPendulum-v5", "Hopper-v5", "Walker2d-v5")
METHODS = ("ppo_esa",)
DEFAULT_SEEDS = "0"
GAMMA = 0.99


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: training budget per env (evaluated once, at the end).
        states: saved states per env.
        horizon: steps followed after the compared action.
        rollouts: Monte-Carlo rollouts per state and branch.
        save_every: save one state in this many steps (after the first 10 of an episode).
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    states: int = 200
    horizon: int = 100
    rollouts: int = 4
    save_every: int = 7


def _half(budget: StepBudget) -> StepBudget:
    steps = budget.on_policy // 2
    return StepBudget(steps, 0, steps, 0, 1)


BUDGETS = {
    "smoke": Args({env: campaign.SMOKE for env in ENVS}, states=4, horizon=5, rollouts=2),
    "full": Args({env: _half(campaign.BUDGETS["full"].budgets[env]) for env in ENVS}),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """One run per (env, seed): train, save states, compare returns."""
    out = []
    for seed in seeds:
        for env in envs:
            spec = rl_spec(NAME, env, "ppo_esa", seed, budget, args.budgets[env])
            check = {
                "states": args.states,
                "horizon": args.horizon,
                "rollouts": args.rollouts,
                "save_every": args.save_every,
            }
            out.append(RunSpec(NAME, env, "ppo_esa", seed, budget, {**spec.config, **check}))
    return out


def run(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains, saves states with ESA on, and measures both branches' Monte-Carlo returns."""
    args = spec.config
    with trained(spec, progress) as (result, model):
        env = get_task(spec.env).make()
        try:
            saved = capture_states(
                cast("ESAPPO", model),  # the study's only method is ppo_esa
                env,
                args["states"],
                save_every=args["save_every"],
                seed=spec.seed,
            )
            rows = []
            for i, state in enumerate(saved):
                sampled, shifted, wide = (
                    _mc_return(model, env, state, action, args, seed=1000 * i)
                    for action in (state.sampled, state.shifted, state.wide)
                )
                rows.append(
                    {
                        "state": i,
                        "return_sampled": sampled,
                        "return_shifted": shifted,
                        "return_wide": wide,
                        "delta": shifted - sampled,
                        "delta_wide": wide - sampled,
                        "predicted": state.predicted,
                        "predicted_wide": state.predicted_wide,
                        "shift_over_std": state.shift_over_std,
                        "wide_shift_over_std": state.wide_shift_over_std,
                    }
                )
        finally:
            env.close()
        return RunResult(pd.DataFrame(rows), result.meta, {"training": result.frame})


def _mc_return(
    model: BaseAlgorithm,
    env: gym.Env,
    state: SavedState,
    action: np.ndarray,
    args: dict[str, Any],
    seed: int,
) -> float:
    """Mean discounted return of ``action`` from ``state``, then the stochastic policy."""
    base = cast("MujocoEnv", env.unwrapped)  # the ground-truth tasks are MuJoCo envs
    box = cast(gym.spaces.Box, env.action_space)
    low, high = box.low, box.high
    total = 0.0
    for m in range(args["rollouts"]):
        generator = th.Generator().manual_seed(seed + m)  # the same draws for both branches
        base.set_state(state.qpos, state.qvel)
        obs, reward, terminated, _, _ = base.step(np.clip(action, low, high))
        ret, discount = float(reward), GAMMA
        for _ in range(args["horizon"] - 1):
            if terminated:
                break
            with th.no_grad():
                obs_t = th.as_tensor(obs, dtype=th.float32)[None]
                dist = gaussian(model, obs_t)
                noise = th.randn(dist.mean.shape, generator=generator)
                act = (dist.mean + dist.stddev * noise).numpy()[0]
            obs, reward, terminated, _, _ = base.step(np.clip(act, low, high))
            ret += discount * float(reward)
            discount *= GAMMA
        total += ret
    return float(total / args["rollouts"])


BRANCHES = (
    ("shipped bound", "delta", "predicted", "shift_over_std"),
    ("1 std bound", "delta_wide", "predicted_wide", "wide_shift_over_std"),
)
"""(label, return difference, critic's prediction, shift size) per compared action."""


def _bootstrap_ci(values: np.ndarray, reps: int = 2000, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    means = rng.choice(values, size=(reps, len(values))).mean(axis=1)
    return float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def report(store: RunStore, args: Args) -> str:
    """Per env: the mean return difference with its bootstrap CI, and what the critic knew."""
    from esa_client.common.advantage_head import rank_correlation

    frame = store.load()
    rows = []
    for env, runs in frame.groupby("env", sort=False):
        for label, delta_key, predicted_key, shift_key in BRANCHES:
            delta = runs[delta_key].to_numpy(float)
            low, high = _bootstrap_ci(delta)
            predicted = runs[predicted_key].to_numpy(float)
            rows.append(
                {
                    "env": env,
                    "shift": label,
                    "states": len(runs),
                    "return(a + v) - return(a) [95% CI]": (
                        f"{delta.mean():+.3f} [{low:+.3f}, {high:+.3f}]"
                    ),
                    "share of states improved": f"{np.mean(delta > 0):.2f}",
                    "mean return(a)": f"{runs.return_sampled.mean():.2f}",
                    "mean abs(v) / sigma": f"{runs[shift_key].mean():.3f}",
                    "rank corr. (critic's prediction, measured)": (
                        f"{rank_correlation(predicted, delta):+.2f}"
                    ),
                }
            )
    table = to_markdown(pd.DataFrame(rows))
    atomic_write_text(store.artifact("table.md"), table + "\n")
    figure = _figure(frame, store.artifact("ground_truth.png"))
    return (
        f"![ground truth]({store.relative(figure)})\n\n"
        f"Discounted (gamma {GAMMA}) Monte-Carlo returns over {args.horizon} steps, "
        f"{args.rollouts} rollouts per state and branch with common random numbers; "
        "95 % CI by bootstrap over states:\n\n"
        f"{table}\n"
    )


def _figure(frame: pd.DataFrame, path: Path) -> Path:
    """Per env, the measured return gain of each state against what the critic predicted."""
    envs = list(dict.fromkeys(frame.env))
    fig = Figure(figsize=(4 * len(envs), 3.6), layout="constrained")
    axes = fig.subplots(1, len(envs), squeeze=False)[0]
    for ax, env in zip(axes, envs, strict=True):
        runs = frame[frame.env == env]
        for label, delta_key, predicted_key, _ in BRANCHES:
            ax.plot(runs[predicted_key], runs[delta_key], ".", alpha=0.5, label=label)
        ax.axhline(0.0, color="grey", linewidth=0.8)
        ax.axvline(0.0, color="grey", linewidth=0.8)
        ax.set_title(env, fontsize=10)
        ax.set_xlabel("critic's predicted gain A(s, a + v) - A(s, a)")
    axes[0].set_ylabel("measured return(a + v) - return(a)")
    axes[0].legend(fontsize=8)
    fig.savefig(path, dpi=120)
    return path
