"""Learning curves against baselines (the paper's Figure 5).

PPO, PPO+ESA, PPO+ParamNoise, SAC, SAC+ESA, SAC+ParamNoise and DDPG+OU on
InvertedPendulum-v5, Hopper-v5, Walker2d-v5 and the quadrotor tracking a
circle. Hyperparameters: ``configs/algorithms.toml``; ESA: the shipped ``EsaConfig()``.

Budgets are far below the paper's (millions of steps): the full budget was
sized to fit about 1.5 CPU-hours for this study on a 2-core machine, with
SAC/DDPG (one gradient step per env step, ~10x slower per step on CPU than
PPO) getting fewer steps than the PPO family. Curves of the two families are
therefore drawn in separate rows and are not comparable across rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from esa_experiments.plotting import Panel
from esa_experiments.reporting import budget_table, rl_section
from esa_experiments.runs import RunSpec, RunStore
from esa_experiments.training import SMOKE_BUDGET, StepBudget, rl_spec, run_training

NAME = "mujoco"
DESCRIPTION = "PPO/SAC with and without ESA vs parameter noise and DDPG+OU on 4 envs"
ENVS = ("InvertedPendulum-v5", "Hopper-v5", "Walker2d-v5", "Quadrotor-circle")
ON_POLICY = ("ppo", "ppo_esa", "ppo_paramnoise")
OFF_POLICY = ("sac", "sac_esa", "sac_paramnoise", "ddpg_ou")
METHODS = ON_POLICY + OFF_POLICY
DEFAULT_SEEDS = "0-4"

SMOKE = SMOKE_BUDGET


@dataclass(frozen=True)
class Args:
    """Arguments of the study: the step budget of each env."""

    budgets: dict[str, StepBudget] = field(default_factory=dict)


BUDGETS = {
    "smoke": Args({env: SMOKE for env in ENVS}),
    # Sized from measured CPU rates (steps per CPU-second, one torch thread):
    # PPO ~700, PPO+ESA ~400, PPO+ParamNoise ~700, SAC ~130, SAC+ESA ~90,
    # DDPG ~230. About 20 CPU-minutes per seed for all 28 runs. PPO totals are
    # whole rollouts (1024 or 2048 steps).
    "full": Args(
        {
            "InvertedPendulum-v5": StepBudget(30_720, 4_000, 2_048, 500, 5),
            "Hopper-v5": StepBudget(20_480, 3_000, 2_048, 500, 3),
            "Walker2d-v5": StepBudget(20_480, 3_000, 2_048, 500, 3),
            "Quadrotor-circle": StepBudget(30_720, 3_000, 2_048, 500, 3),
        }
    ),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """All (env, method, seed) runs, seed-major so partial sessions cover every cell."""
    return [
        rl_spec(NAME, env, method, seed, budget, args.budgets[env])
        for seed in seeds
        for env in envs
        for method in methods
    ]


run = run_training
"""One run: train with periodic evaluation, nothing else."""


def report(store: RunStore, args: Args) -> str:
    """Learning curves (PPO family top row, SAC/DDPG bottom row) and the summary table."""
    panels = [Panel(f"{env}: PPO family", env, ON_POLICY) for env in ENVS] + [
        Panel(f"{env}: SAC / DDPG", env, OFF_POLICY) for env in ENVS
    ]
    section = rl_section(store, panels, ENVS, METHODS, ncols=len(ENVS))
    return f"{section}\nBudgets (per run):\n\n{budget_table(args.budgets)}\n"
