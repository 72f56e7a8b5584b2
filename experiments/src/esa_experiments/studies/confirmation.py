"""Does ESA accelerate learning? The confirmation campaign: 20 seeds, every arm, controls.

Per algorithm family, the shipped default of that family against its baseline and its
gradient control (the same bound, normalisation and gate, with the shift along the
critic's action gradient: ESC is credited only where it beats it), on the same seeds:

* PPO (``EsaConfig()``): ``ppo``, ``ppo_esa`` (behaviour: the env executes ``a + v``)
  and its control ``ppo_qgrad``, ``ppo_esa_target`` (the env executes the sample, PPO's
  update pulls the mean toward ``mu_old + v``) and its control ``ppo_qgrad_target``; on
  InvertedPendulum-v5 (30k steps), InvertedDoublePendulum-v5 (100k), the quadrotor
  figure eight (60k) and Hopper-v5 (100k). ``ppo_qgrad`` joined after the other 640
  runs had finished (ESC is credited only where it beats its gradient control, so every
  ESA arm needs one, and the shipped PPO default had none); it runs the same seeds 0-19
  and its comparisons join the PPO family's Holm correction, which can only make that
  family's verdicts stricter.
* SAC (``EsaConfig.off_policy()``): ``sac``, ``sac_esa``, ``sac_qgrad`` on Hopper-v5 and
  the quadrotor figure eight, 50k steps.
* TD3 (``EsaConfig.off_policy()``, on top of TD3's Gaussian noise): ``td3``, ``td3_esa``,
  ``td3_qgrad``, ``td3_sine`` (the probe's sinusoid executed, learning rate 0:
  exploration by the probe alone) and ``td3_pink`` (pink action noise, a strong simple
  exploration baseline) on InvertedDoublePendulum-v5 and the quadrotor figure eight, 50k.

The seed rule, fixed before any result: seeds 0-19 for every arm, all run, no optional
stopping; the report gives all 20 and the halves 0-9 and 10-19. Runs are ordered
seed-major, so a campaign cut short (or run across sessions) compares every arm on the
seeds it finished, and finished runs combine (:class:`~esa_experiments.runs.RunStore`).

On 2 cores the whole campaign is about 30 CPU-hours. Sessions without a lent 16-core
machine run it group by group, cheapest first, each group to all 20 seeds (``--envs`` and
``--methods`` pick the group; the order was fixed by cost before any of these runs was
read): PPO on InvertedPendulum-v5, SAC on the quadrotor, then seed-major over the rest.
A verdict is only reported on the seeds both of its arms finished.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import pandas as pd
from esa_client.compare.plotting import Panel
from esa_client.compare.tables import to_markdown
from esa_client.compare.verdicts import (
    Comparison,
    aggregate_table,
    diagnostics_table,
    verdict_table,
)

from esa_experiments.algorithms import BASELINE_OF, GRADIENT_CONTROL_OF, LABELS
from esa_experiments.reporting import budget_table, rl_section
from esa_experiments.runs import RunSpec, RunStore, atomic_write_text
from esa_experiments.training import SMOKE_BUDGET, StepBudget, rl_spec, run_training

NAME = "confirmation"
DESCRIPTION = "20 seeds: each family's ESA default vs its baseline and its gradient control"
ARMS = {
    "ppo": ("ppo", "ppo_esa", "ppo_qgrad", "ppo_esa_target", "ppo_qgrad_target"),
    "sac": ("sac", "sac_esa", "sac_qgrad"),
    "td3": ("td3", "td3_esa", "td3_qgrad", "td3_sine", "td3_pink"),
}
ENVS_OF = {
    "ppo": ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Quadrotor-eight", "Hopper-v5"),
    "sac": ("Hopper-v5", "Quadrotor-eight"),
    "td3": ("InvertedDoublePendulum-v5", "Quadrotor-eight"),
}
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Quadrotor-eight", "Hopper-v5")
METHODS = tuple(method for arms in ARMS.values() for method in arms)
DEFAULT_SEEDS = "0-19"
SEED_COUNT = 20
SHIPPED = {"ppo": "ppo_esa", "sac": "sac_esa", "td3": "td3_esa"}
"""Each family's shipped default (``EsaConfig()`` / ``EsaConfig.off_policy()``): the goal's arms."""
GOAL_BETTER = 3
GOAL_ENV = "Quadrotor-eight"
HALVES = ((0, 9), (10, 19))

COMPARISONS = tuple(
    Comparison(family, method, reference, kind)
    for family, arms in ARMS.items()
    for method in arms
    for reference, kind in (
        (BASELINE_OF.get(method), "baseline"),
        (GRADIENT_CONTROL_OF.get(method), "gradient control"),
    )
    if reference is not None and reference in arms
)
"""Every ESA arm against its family's baseline, and the ESC arms against their control."""


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: step budget per env (``on_policy`` for PPO, ``off_policy`` for SAC/TD3).
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)


# Three PPO rollouts (the gate needs two before ESA acts) and a short off-policy warm-up.
SMOKE = replace(SMOKE_BUDGET, on_policy=384)

BUDGETS = {
    "smoke": Args({env: SMOKE for env in ENVS}),
    # PPO totals are whole rollouts (4 envs x 256 steps; 4 x 512 on Hopper-v5).
    "full": Args(
        {
            "InvertedPendulum-v5": StepBudget(30_720, 0, 2_048, 0, 5),
            "InvertedDoublePendulum-v5": StepBudget(100_352, 50_000, 4_096, 2_500, 3),
            "Quadrotor-eight": StepBudget(60_416, 50_000, 4_096, 2_500, 3),
            "Hopper-v5": StepBudget(100_352, 50_000, 4_096, 2_500, 3),
        }
    ),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The (env, method, seed) runs, seed-major: each seed compares every arm before the next."""
    return [
        rl_spec(NAME, env, method, seed, budget, args.budgets[env])
        for seed in seeds
        for family, arms in ARMS.items()
        for env in ENVS_OF[family]
        for method in arms
        if env in envs and method in methods
    ]


run = run_training
"""One run: train with periodic evaluation (and the training episodes' outcomes)."""


def _verdicts(frame: pd.DataFrame, seeds: tuple[int, int] | None = None) -> pd.DataFrame:
    chosen = None if seeds is None else list(range(seeds[0], seeds[1] + 1))
    return verdict_table(frame, ENVS, COMPARISONS, LABELS, chosen)


def _markdown(verdicts: pd.DataFrame) -> str:
    return (
        to_markdown(verdicts) if not verdicts.empty else "(no comparison has two common seeds yet)"
    )


def _goal(verdicts: pd.DataFrame) -> str:
    """The campaign's goal, checked on the shipped defaults' rows of the all-seed verdicts.

    Never significantly worse than the baseline on any (family, env), significantly better
    on at least ``GOAL_BETTER`` of them, one on ``GOAL_ENV``. A row is final only with all
    ``SEED_COUNT`` seeds, and the Holm correction spans the family's envs, so the goal is
    open until every shipped-default row is final.
    """
    if verdicts.empty:
        return "(no comparison has two common seeds yet)\n"
    rows, better, worse, final = [], [], [], 0
    for family, method in SHIPPED.items():
        label = LABELS[method]
        for env in ENVS_OF[family]:
            row = {"family": family, "env": env, "shipped default": label}
            for kind in ("baseline", "gradient control"):
                hit = verdicts[
                    (verdicts.env == env)
                    & (verdicts.method == label)
                    & verdicts.against.str.endswith(f"({kind})")
                ]
                if hit.empty:
                    row[f"vs {kind}"] = "not run yet"
                    continue
                seeds, verdict = int(hit.seeds.iloc[0]), str(hit.verdict.iloc[0])
                complete = seeds >= SEED_COUNT
                # The statistic beside the verdict: mean AUCs and P(arm better) with its CI.
                detail = (
                    f": AUC {hit['mean AUC (arm / reference)'].iloc[0]}, "
                    f"P = {hit['P(arm better) [95% CI]'].iloc[0]}"
                    if "P(arm better) [95% CI]" in hit
                    else ""
                )
                state = "" if complete else f" (interim, {seeds} seeds)"
                row[f"vs {kind}"] = f"{verdict}{state}{detail}"
                if kind == "baseline":
                    final += complete
                    better += [env] if "better" in verdict else []
                    worse += [env] if "worse" in verdict else []
            rows.append(row)
    reached = len(better) >= GOAL_BETTER and GOAL_ENV in better and not worse
    state = "reached" if reached else "not reached"
    tally = f"Better on {len(better)}, worse on {len(worse)}."
    if final < len(rows):
        state = f"open ({final} of {len(rows)} rows have all {SEED_COUNT} seeds)"
        tally = f"So far better on {len(better)}, worse on {len(worse)}."
    return (
        f"{to_markdown(pd.DataFrame(rows))}\n\n"
        f"Goal (never worse; better on >= {GOAL_BETTER} pairs, one on {GOAL_ENV}): "
        f"{state}. {tally}\n"
    )


def report(store: RunStore, args: Args) -> str:
    """Curves with every seed and the goal; verdicts, halves, aggregates, diagnostics as files."""
    panels = [
        Panel(f"{env}: {family.upper()}", env, ARMS[family])
        for family in ARMS
        for env in ENVS_OF[family]
    ]
    section = rl_section(store, panels, ENVS, METHODS, ncols=4, per_seed=True, inline=False)
    frame = store.load()
    table = _verdicts(frame)
    verdicts = _markdown(table)
    atomic_write_text(store.artifact("verdicts.md"), verdicts + "\n")
    halves = "\n\n".join(
        f"Seeds {low}-{high}:\n\n{_markdown(_verdicts(frame, (low, high)))}" for low, high in HALVES
    )
    aggregate = aggregate_table(frame, ENVS_OF, COMPARISONS, LABELS)
    diagnostics = diagnostics_table(frame, store.load_meta(), ENVS, METHODS, LABELS)
    files = {
        "halves.md": "The verdicts on each half of the seeds (Holm within the half):\n\n" + halves,
        "aggregates.md": "Aggregated over each family's envs (seeds every env finished):\n\n"
        + (to_markdown(aggregate) if not aggregate.empty else "(not enough seeds yet)"),
        "diagnostics.md": "Diagnostics (means over runs; crash = a training episode ended by "
        f"termination, not the time limit):\n\n{to_markdown(diagnostics)}",
    }
    links = [f"[verdicts.md]({store.relative(store.artifact('verdicts.md'))})"]
    for name, text in files.items():
        path = store.artifact(name)
        atomic_write_text(path, text + "\n")
        links.append(f"[{name}]({store.relative(path)})")
    return (
        f"{section}\n"
        "The shipped defaults of the time against the goal (from the verdicts, all seeds: AUC; "
        "P(arm better) with its stratified-bootstrap 95 % CI; two-sided Mann-Whitney p-values "
        "Holm-corrected within each family; better / worse when the corrected p < 0.05):\n\n"
        f"{_goal(table)}\n"
        f"Every comparison, each half of the seeds, the aggregates over envs and the "
        f"diagnostics: {', '.join(links)}.\n\n"
        f"Budgets (per run):\n\n{budget_table(args.budgets)}\n"
    )
