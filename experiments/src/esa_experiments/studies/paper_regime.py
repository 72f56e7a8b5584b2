"""The paper's regime: ESA against a tuned PPO trained to a million steps on Hopper-v5.

Rules, fixed and committed before the first run:

* **Question.** The other studies' efficacy verdicts are all about PPO at 30,720-100,352
  steps with this suite's untuned settings, which RL Zoo3's tuned PPO beats (study
  ``zoo_baselines``). The paper's claim concerns standard PPO trained to convergence. Does
  ESA, as shipped, speed up a well-tuned PPO there, and does it harm it anywhere?
* **Env, settings, budget.** Hopper-v5 with RL Zoo3 2.9.2's tuned PPO settings for Hopper
  (its ``Hopper-v4`` entry, held in ``configs/algorithms.toml`` as ``ppo_zoo`` and checked
  against the zoo's yml by ``tests/test_zoo_baselines.py``), with its ``VecNormalize`` of
  observations and rewards, one env. Budget 1,000,448 steps: the zoo's ``n_timesteps``
  1e6 rounded up to whole rollouts of 512 steps (1,954), as SB3's ``learn`` does.
* **Arms**, each stored under its own name:

  - ``ppo``: the tuned PPO (method ``ppo_zoo``);
  - ``ppo_esa``: the same PPO with E2's ``ppo_esa`` arm (study ``seeking``): the quadratic
    advantage head, ``EsaConfig(trust_region=1.0, fade=0.5)`` with every other field of
    the shipped ``EsaConfig()`` of E2's runs, and the decoupled objective. The fade is a
    fraction of this study's budget: ESA at full strength at the start, gone by 500,224
    steps;
  - ``ppo_placebo``: the same schedule, the shift's direction a random sign vector per
    episode (E2's ``ppo_placebo``).

  The ESA arms' configuration is written out here (:data:`ESA_ARM`), not read from the
  shipped default, so that the runs stay valid while the product's code moves.
* **Seeds** 0-9 for every arm, all run, none dropped, no optional stopping. Runs are
  ordered seed-major (``ppo``, ``ppo_esa``, ``ppo_placebo`` within a seed), so a study cut
  short compares every arm on the seeds it finished; verdicts use only seeds both arms of a
  comparison finished.
* **Evaluation** as in E2 (3 deterministic episodes, the normalization statistics frozen,
  the env's own returns), every 16,384 steps (32 rollouts): 62 points per curve.
* **Metric.** Primary: the area under the evaluation curve over the first third of the
  budget (normalized by its span). Secondary: the whole-curve AUC.
* **Tests** E2's: per comparison the probability of improvement ``P(X > Y)`` with its
  bootstrap CI and the two-sided Mann-Whitney U test; Holm over this study's comparisons
  (``ppo_esa`` against ``ppo`` and against ``ppo_placebo``) within each metric; better /
  worse at a corrected p < 0.05.
* **Power, stated a priori.** With 10 seeds an arm and Holm's first threshold (0.025),
  the two-sided Mann-Whitney U test detects a shift of the mean of normally distributed AUCs
  by 1.6 standard deviations with 80 % power, and by 1.17 with 50 % (Monte Carlo, 20,000
  draws per size, numpy seed 0, scipy's ``mannwhitneyu``): ``P(X > Y)`` of about 0.87 and
  0.79. Anything smaller reads as "equal": this study can find a large effect or rule one
  out, not a small one.
* **Success.** ``ppo_esa`` is better than both ``ppo`` and ``ppo_placebo`` on the primary
  metric, and worse than ``ppo`` on neither metric.
* **Shipping rule.** If ``ppo_esa`` is significantly worse than the tuned ``ppo`` over the
  whole curve, the shipped default of ``ESAPPO`` must change, and README must say so.
* **Runs**: 30, ``python -m esa_experiments run paper_regime --budget full --jobs 2``,
  then ``python -m esa_experiments plot paper_regime --budget full``. The smoke budget (CI)
  runs the same arms for 384 steps with rollouts of 32.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import pandas as pd
from esa_client.compare.plotting import Panel
from esa_client.compare.verdicts import Comparison, verdict_table

from esa_experiments.reporting import budget_table, rl_section, write_verdicts
from esa_experiments.runs import RunSpec, RunStore
from esa_experiments.studies import seeking
from esa_experiments.training import SMOKE_BUDGET, StepBudget, rl_spec, run_training

NAME = "paper_regime"
DESCRIPTION = "ESA vs a tuned PPO (RL Zoo3) at 1M steps on Hopper-v5, with a placebo"
ENV = "Hopper-v5"
ENVS = (ENV,)
ARM_METHODS = {
    "ppo": "ppo_zoo",
    "ppo_esa": "ppo_zoo_seek_esa_quadratic",
    "ppo_placebo": "ppo_zoo_seek_placebo_quadratic",
}
"""Arm (the name its runs are stored under) -> method of :mod:`esa_experiments.algorithms`."""
METHODS = tuple(ARM_METHODS)
DEFAULT_SEEDS = "0-9"
ESA_ARM: dict[str, Any] = {"trust_region": 1.0}
"""E2's ``ppo_esa`` on top of the ``seeking_ppo`` preset: E1's pick of kappa."""
LABELS = {"ppo": "PPO (RL Zoo3)", "ppo_esa": "PPO+ESA", "ppo_placebo": "PPO+placebo"}
COMPARISONS = (
    Comparison("ppo", "ppo_esa", "ppo", "baseline"),
    Comparison("ppo", "ppo_esa", "ppo_placebo", "placebo"),
)


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: step budget per env (``on_policy``: every arm is PPO).
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)


BUDGETS = {
    "smoke": Args({ENV: replace(SMOKE_BUDGET, on_policy=384)}),
    "full": Args({ENV: StepBudget(1_000_448, 0, 16_384, 1, 3)}),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The runs, seed-major (``ppo``, ``ppo_esa``, ``ppo_placebo`` within a seed)."""
    step_budget = args.budgets[ENV]
    if budget == "smoke":
        # The zoo's PPO has one env: 12 rollouts of 32 steps, minibatches of a rollout.
        overrides = {"ppo": {"n_steps": 32, "batch_size": 32, "n_epochs": 2}}
        step_budget = replace(step_budget, overrides=overrides)
    return [
        rl_spec(
            NAME,
            ENV,
            ARM_METHODS[arm],
            seed,
            budget,
            step_budget,
            variant=arm,
            esa_overrides=ESA_ARM if arm != "ppo" else None,
        )
        for seed in seeds
        if ENV in envs
        for arm in METHODS
        if arm in methods
    ]


run = run_training
"""One run: train with periodic evaluation, nothing else."""


def report(store: RunStore, args: Args) -> str:
    """Learning curves (IQM, 95 % CI), the verdicts on both metrics and the outcome."""
    frame = store.load()
    section = rl_section(
        store,
        [Panel(f"{ENV}: tuned PPO, 1M steps", ENV, METHODS)],
        ENVS,
        METHODS,
        labels=LABELS,
        baselines={"ppo_esa": "ppo", "ppo_placebo": "ppo"},
        ncols=1,
    )
    tables = {
        "first third (primary)": verdict_table(
            seeking.early(frame, args.budgets), ENVS, COMPARISONS, LABELS
        ),
        "whole curve (secondary)": verdict_table(frame, ENVS, COMPARISONS, LABELS),
    }
    text = [section]
    for name, markdown in zip(tables, write_verdicts(store, *tables.values()), strict=True):
        text.append(f"Verdicts, AUC over the {name}:\n\n{markdown}\n")
    text.append(outcome(tables["first third (primary)"], tables["whole curve (secondary)"]))
    text.append(f"Budget (per run):\n\n{budget_table(args.budgets)}\n")
    return "\n".join(text)


def outcome(primary: pd.DataFrame, whole: pd.DataFrame) -> str:
    """The study's outcome under its success and shipping rules."""
    if primary.empty or whole.empty:
        return "Outcome: no verdict yet (no comparison has two seeds).\n"

    def verdicts(table: pd.DataFrame) -> dict[str, str]:
        return {
            str(row.against).rsplit("(", 1)[1].rstrip(")"): str(row.verdict).strip("*")
            for row in table.itertuples()
        }

    def than(verdict: str | None) -> str:
        return {"better": "better than", "worse": "worse than", "equal": "equal to"}.get(
            verdict or "", "not yet compared with"
        )

    early, overall = verdicts(primary), verdicts(whole)
    success = (
        early.get("baseline") == "better"
        and early.get("placebo") == "better"
        and "worse" not in (early.get("baseline"), overall.get("baseline"))
    )
    seeds = int(primary.seeds.min())
    harm = overall.get("baseline") == "worse"
    return (
        f"Outcome ({seeds} seeds; rules in `studies/paper_regime.py`): "
        f"{'success' if success else 'no success'}. Early, PPO+ESA is "
        f"{than(early.get('baseline'))} the tuned PPO and {than(early.get('placebo'))} the "
        f"placebo; over the whole curve it is {than(overall.get('baseline'))} the tuned PPO. "
        "Shipping rule: "
        + (
            "the shipped default harms the tuned PPO, so it must change.\n"
            if harm
            else "the shipped default does not harm the tuned PPO; it stands.\n"
        )
    )
