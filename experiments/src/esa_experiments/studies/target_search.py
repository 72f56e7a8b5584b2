"""The PPO target mode's bound and loss weight, on InvertedPendulum-v5 tuning seeds only.

``ppo_esa_target`` executes the policy's own sample and pulls PPO's mean toward
``mu_old(s) + v_t`` (``ESAPPO(esa_mode="target")``). Its two settings, the trust region
kappa (how far the target may lie, in policy stds) and the loss weight, are chosen here
on a 2 x 2 grid, on seeds 100 and up that no confirmation run uses, against plain PPO
on the same seeds. The pick is the variant with the highest mean AUC; it is written
into ``esa_experiments.algorithms`` (``TARGET_TRUST_REGION``, ``TARGET_WEIGHT``) by hand,
and the gradient control ``ppo_qgrad_target`` gets the same two values.
"""

from __future__ import annotations

from dataclasses import dataclass

from esa_experiments.plotting import Panel
from esa_experiments.reliability import reliability_section
from esa_experiments.reporting import budget_table, rl_section
from esa_experiments.runs import RunSpec, RunStore
from esa_experiments.studies import campaign
from esa_experiments.training import StepBudget, rl_spec, run_training

NAME = "target_search"
DESCRIPTION = "PPO target mode: trust region x loss weight on InvertedPendulum-v5 tuning seeds"
ENV = "InvertedPendulum-v5"
ENVS = (ENV,)
DEFAULT_SEEDS = "100-103"

VARIANTS: dict[str, tuple[float, float]] = {
    "k0.25_w0.03": (0.25, 0.03),
    "k0.25_w0.3": (0.25, 0.3),
    "k1_w0.03": (1.0, 0.03),
    "k1_w0.3": (1.0, 0.3),
}
"""Variant -> (trust region kappa, loss weight)."""

METHODS = ("ppo", *VARIANTS)
LABELS = {name: f"target, kappa {k:g}, weight {w:g}" for name, (k, w) in VARIANTS.items()}


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budget: the step budget (the campaign's on InvertedPendulum-v5).
    """

    budget: StepBudget


BUDGETS = {
    "smoke": Args(campaign.SMOKE),
    "full": Args(campaign.BUDGETS["full"].budgets[ENV]),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """Plain PPO and every variant, seed-major."""
    out = []
    for seed in seeds:
        for method in methods:
            if method == "ppo":
                out.append(rl_spec(NAME, ENV, "ppo", seed, budget, args.budget))
                continue
            kappa, weight = VARIANTS[method]
            spec = rl_spec(
                NAME,
                ENV,
                "ppo_esa_target",
                seed,
                budget,
                args.budget,
                variant=method,
                esa_overrides={"trust_region": kappa},
            )
            spec.config["hyperparams"]["esa_options"]["esa_target_weight"] = weight
            out.append(spec)
    return out


run = run_training
"""One run: train with periodic evaluation."""


def report(store: RunStore, args: Args) -> str:
    """Learning curves, the summary table and each variant against plain PPO."""
    panels = [Panel(f"{ENV}: PPO target mode", ENV, METHODS)]
    baselines = {name: "ppo" for name in VARIANTS}
    section = rl_section(
        store, panels, ENVS, METHODS, labels=LABELS, baselines=baselines, per_seed=True
    )
    statistics = reliability_section(store, ENVS, METHODS, LABELS, baselines)
    return f"{section}\n{statistics}\nBudget (per run):\n\n{budget_table({ENV: args.budget})}\n"
