"""Ablations of PPO+ESA on InvertedPendulum-v5 (the paper's Figure 6).

(a) amplitude K in {0.05, 0.1, 0.2, 0.4} at w = 10 pi rad/s;
(b) frequency w in {2 pi, 5 pi, 10 pi, 20 pi} rad/s at K = 0.2;
(c) decay of ESA: per-episode learning-rate decay (0.99, 0.97) and the number
of episodes ESA intervenes in (``max_episodes`` 50, 200) against no decay.

The ``default`` variant (K = 0.2, w = 10 pi, no decay, unlimited episodes: the
paper's law and best setting, ``EsaConfig.paper()``) is shared by the three
panels, and plain PPO is drawn as the reference. Every other hyperparameter
is that of the ``mujoco`` study; the step budget is smaller (see ``BUDGETS``).
The shipped default (CONTRACT.md section 1b law) was chosen by ``default_search``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from esa_experiments.plotting import Panel
from esa_experiments.reporting import budget_table, rl_section
from esa_experiments.runs import RunSpec, RunStore
from esa_experiments.studies import mujoco
from esa_experiments.training import StepBudget, rl_spec, run_training

NAME = "ablation"
DESCRIPTION = "PPO+ESA on InvertedPendulum-v5: amplitude, frequency, decay / intervening episodes"
ENV = "InvertedPendulum-v5"
ENVS = (ENV,)
DEFAULT_SEEDS = "0-2"

VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "K0.05": {"amplitude": 0.05},
    "K0.1": {"amplitude": 0.1},
    "K0.4": {"amplitude": 0.4},
    "w2pi": {"frequency": 2 * math.pi},
    "w5pi": {"frequency": 5 * math.pi},
    "w20pi": {"frequency": 20 * math.pi},
    "decay0.99": {"lr_decay": 0.99},
    "decay0.97": {"lr_decay": 0.97},
    "E50": {"max_episodes": 50},
    "E200": {"max_episodes": 200},
}
"""Variant name -> ESA fields replacing the paper preset (all run PPO+ESA, paper law)."""

METHODS = ("ppo", *VARIANTS)
LABELS = {
    "ppo": "PPO (no ESA)",
    "default": "ESA default: K=0.2, w=10pi, no decay",
    "K0.05": "K=0.05",
    "K0.1": "K=0.1",
    "K0.4": "K=0.4",
    "w2pi": "w=2pi",
    "w5pi": "w=5pi",
    "w20pi": "w=20pi",
    "decay0.99": "lr decay 0.99/episode",
    "decay0.97": "lr decay 0.97/episode",
    "E50": "ESA in first 50 episodes",
    "E200": "ESA in first 200 episodes",
}
PANELS = (
    Panel("(a) amplitude K", ENV, ("ppo", "K0.05", "K0.1", "default", "K0.4")),
    Panel("(b) frequency w [rad/s]", ENV, ("ppo", "w2pi", "w5pi", "default", "w20pi")),
    Panel(
        "(c) decay / intervening episodes",
        ENV,
        ("ppo", "default", "decay0.99", "decay0.97", "E50", "E200"),
    ),
)


@dataclass(frozen=True)
class Args:
    """Arguments of the study: the step budget."""

    budget: StepBudget = field(default_factory=lambda: mujoco.BUDGETS["full"].budgets[ENV])


BUDGETS = {
    "smoke": Args(mujoco.BUDGETS["smoke"].budgets[ENV]),
    # The mujoco study's InvertedPendulum budget cut to 20 rollouts: 12 runs per
    # seed, 11 of them with ESA (~11 CPU-minutes per seed).
    "full": Args(replace(mujoco.BUDGETS["full"].budgets[ENV], on_policy=20_480)),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """One run per (variant, seed)."""
    return [
        rl_spec(NAME, ENV, method, seed, budget, args.budget)
        if method == "ppo"
        else rl_spec(
            NAME,
            ENV,
            "ppo_esa_paper",
            seed,
            budget,
            args.budget,
            variant=method,
            esa_overrides=VARIANTS[method],
        )
        for seed in seeds
        for env in envs
        for method in methods
    ]


run = run_training
"""One run: train with periodic evaluation, nothing else."""


def report(store: RunStore, args: Args) -> str:
    """Three panels (amplitude, frequency, decay) and the summary table of all variants."""
    section = rl_section(
        store,
        PANELS,
        ENVS,
        METHODS,
        labels=LABELS,
        baselines={variant: "ppo" for variant in VARIANTS},
        figure_name="ablation.png",
        ncols=3,
    )
    return f"{section}\nBudget (per run):\n\n{budget_table({ENV: args.budget})}\n"
