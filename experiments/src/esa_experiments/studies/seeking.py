"""E2 of "ESA that seeks": learning curves of E1's candidates against baseline and controls.

Rules, fixed and committed before the first run (of the "ESA that seeks" round, which
built critics with curvature, the fade, the placebo and the decoupled objective after the
confirmation campaign found no acceleration):

* **Arms**, stored under these names (each backed by a method of
  :mod:`esa_experiments.algorithms`):

  - PPO on InvertedPendulum-v5, InvertedDoublePendulum-v5, Hopper-v5, Quadrotor-eight:
    ``ppo`` (plain PPO), ``ppo_esa`` (E1's pick: its critic and kappa, ``EsaConfig(
    trust_region=kappa, fade=SEEKING_FADE)``, the decoupled objective), ``ppo_placebo``
    (the same, the shift's direction a random sign vector per episode), ``ppo_qgrad``
    (the same, the shift along the critic's gradient at the trust region's size).
  - SAC on InvertedDoublePendulum-v5, Hopper-v5, Quadrotor-eight: ``sac``, ``sac_esa``
    (``EsaConfig.off_policy(trust_region=kappa, fade=SEEKING_FADE)``, kappa E1's pick for
    the off-policy family), ``sac_placebo``, ``sac_qgrad``, and the mean-shift arms
    ``sac_mean_esa``, ``sac_mean_qgrad`` (ESA and the gradient from the policy's mean, the
    noise kept).
  - TD3 on the same envs: ``td3``, ``td3_esa``, ``td3_placebo``, ``td3_qgrad``,
    ``td3_mean_esa``, ``td3_mean_qgrad``, and the sine lead with its matched controls:
    ``td3_sine`` (the probe's sinusoid executed, learning rate 0), ``td3_gauss_matched``
    and ``td3_pink_matched`` (Gaussian and pink action noise with the variance TD3 executes
    in ``td3_sine``).

  ``SEEKING_FADE`` = 0.5, fixed a priori (no tuning): ESA at full strength at the start,
  where the primary metric looks and the paper claims its gain, linearly gone by half of
  the budget, so the second half is the baseline algorithm.
* **E1 gates the candidates.** The ESA, placebo, gradient and mean-shift arms of a family
  run only with E1's pick for that family (``results/seeking_offline/picks.json``,
  written by E1's report). Where E1 picked nothing the family's line is closed: those
  arms are not run, and RESULTS.md says so; the baselines and TD3's sine and
  matched-noise arms do not depend on E1 and run in any case.
* **Seeds** 0-19 for every arm, all run, none dropped, no optional stopping; runs are
  ordered seed-major (PPO first, then TD3, then SAC), so a study cut short compares every
  arm on the seeds it finished, and verdicts use only seeds both arms finished.
* **Budgets** as in the confirmation campaign: PPO 30,720 (InvertedPendulum-v5), 100,352
  (InvertedDoublePendulum-v5, Hopper-v5), 60,416 (Quadrotor-eight); SAC and TD3 50,000.
* **Metric.** Primary: the area under the evaluation curve over the first third of the
  budget (normalized by its span). Secondary: the whole-curve AUC.
* **Tests.** Per env and comparison the probability of improvement ``P(X > Y)`` with its
  bootstrap CI and the two-sided Mann-Whitney U test, Holm-corrected within each family
  (all its envs and comparisons, for each metric); better / worse at a corrected p < 0.05.
  Comparisons: ``<algo>_esa`` against the baseline, the placebo and the gradient control;
  the mean-shift arms against the baseline; ``td3_sine`` against ``td3_gauss_matched`` and
  ``td3_pink_matched``.
* **Success.** A family succeeds when its ``<algo>_esa`` is better than both its baseline
  and its placebo on the primary metric on at least two envs, one of them the quadrotor,
  and its whole-curve AUC is worse than the baseline's on no env.
* **Shipping.** A family's default becomes its E2 candidate only where E2 says better and
  nowhere worse; otherwise the safest setting stays and README says so.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pandas as pd
from esa_client.compare.plotting import Panel
from esa_client.compare.verdicts import (
    Comparison,
    better_and_worse,
    compact_table,
    verdict_table,
)

from esa_experiments.algorithms import LABELS, seeking_methods
from esa_experiments.reporting import budget_table, rl_section, verdicts_markdown, write_verdicts
from esa_experiments.runs import EXPERIMENTS_DIR, RunSpec, RunStore
from esa_experiments.training import SMOKE_BUDGET, StepBudget, rl_spec, run_training

NAME = "seeking"
DESCRIPTION = "E2: E1's candidates vs baseline, placebo, gradient, mean shift, matched noise"
ENVS_OF = {
    "ppo": ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Quadrotor-eight"),
    "sac": ("InvertedDoublePendulum-v5", "Hopper-v5", "Quadrotor-eight"),
    "td3": ("InvertedDoublePendulum-v5", "Hopper-v5", "Quadrotor-eight"),
}
ENVS = ENVS_OF["ppo"]
CANDIDATE_ARMS = {
    "ppo": ("esa", "placebo", "qgrad"),
    "sac": ("esa", "placebo", "qgrad", "mean_esa", "mean_qgrad"),
    "td3": ("esa", "placebo", "qgrad", "mean_esa", "mean_qgrad"),
}
FREE_ARMS = {
    "ppo": ("ppo",),
    "sac": ("sac",),
    "td3": ("td3", "td3_sine", "td3_gauss_matched", "td3_pink_matched"),
}
ARMS = {
    family: (*FREE_ARMS[family][:1], *(f"{family}_{a}" for a in arms), *FREE_ARMS[family][1:])
    for family, arms in CANDIDATE_ARMS.items()
}
METHODS = tuple(arm for arms in ARMS.values() for arm in arms)
DEFAULT_SEEDS = "0-19"
QUADROTOR = "Quadrotor-eight"
MIN_BETTER = 2
EARLY = 1 / 3
PICKS = EXPERIMENTS_DIR / "results" / "seeking_offline" / "picks.json"
"""E1's picks: family (``ppo``, ``off_policy``) -> ``{"learner": ..., "kappa": ...}`` or null."""


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: step budget per env (``on_policy`` for PPO, ``off_policy`` for SAC/TD3).
        picks: E1's picks file.
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    picks: Path = PICKS


SMOKE = replace(SMOKE_BUDGET, on_policy=384)

BUDGETS = {
    "smoke": Args({env: SMOKE for env in ENVS}),
    "full": Args(
        {
            "InvertedPendulum-v5": StepBudget(30_720, 50_000, 2_048, 2_500, 5),
            "InvertedDoublePendulum-v5": StepBudget(100_352, 50_000, 4_096, 2_500, 3),
            "Quadrotor-eight": StepBudget(60_416, 50_000, 4_096, 2_500, 3),
            "Hopper-v5": StepBudget(100_352, 50_000, 4_096, 2_500, 3),
        }
    ),
}

E1_FAMILY = {"ppo": "ppo", "sac": "off_policy", "td3": "off_policy"}


def load_picks(path: Path) -> dict[str, dict[str, Any] | None]:
    """E1's picks, or every family closed when E1 has not reported yet."""
    if not path.is_file():
        return {"ppo": None, "off_policy": None}
    picks: dict[str, dict[str, Any] | None] = json.loads(path.read_text())
    return picks


def family_of(arm: str) -> str:
    """The family (``ppo``, ``sac``, ``td3``) an arm belongs to."""
    return arm.split("_", 1)[0]


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The runs E1's picks allow, seed-major (PPO, then TD3, then SAC within a seed)."""
    picks = load_picks(args.picks)
    out = []
    for seed in seeds:
        for family in ("ppo", "td3", "sac"):
            pick = picks.get(E1_FAMILY[family])
            for env in ENVS_OF[family]:
                if env not in envs:
                    continue
                for arm in ARMS[family]:
                    if arm not in methods:
                        continue
                    if arm in FREE_ARMS[family]:
                        out.append(rl_spec(NAME, env, arm, seed, budget, args.budgets[env]))
                    elif pick is not None:
                        method = seeking_methods(family, pick["learner"])[arm]
                        out.append(
                            rl_spec(
                                NAME,
                                env,
                                method,
                                seed,
                                budget,
                                args.budgets[env],
                                variant=arm,
                                esa_overrides={"trust_region": pick["kappa"]},
                            )
                        )
    return out


run = run_training
"""One run: train with periodic evaluation, nothing else."""

COMPARISONS = tuple(
    Comparison(family, f"{family}_{arm}", reference, kind)
    for family in ARMS
    for arm, reference, kind in (
        ("esa", family, "baseline"),
        ("esa", f"{family}_placebo", "placebo"),
        ("esa", f"{family}_qgrad", "gradient control"),
        *(
            (arm, family, "baseline")
            for arm in ("mean_esa", "mean_qgrad")
            if arm in CANDIDATE_ARMS[family]
        ),
    )
) + (
    Comparison("td3", "td3_sine", "td3_gauss_matched", "matched noise"),
    Comparison("td3", "td3_sine", "td3_pink_matched", "matched noise"),
)


def early(
    frame: pd.DataFrame,
    budgets: dict[str, StepBudget],
    family: Callable[[str], str] = family_of,
) -> pd.DataFrame:
    """The evaluation rows within the first third of each run's budget.

    Args:
        frame: Evaluation rows of runs (``env``, ``method``, ``step``).
        budgets: Each env's budget.
        family: The family of a stored arm name: ``ppo`` runs PPO's budget, any other the
            off-policy one.
    """

    def limit(row: pd.Series) -> float:
        budget = budgets[str(row.env)]
        total = budget.on_policy if family(str(row.method)) == "ppo" else budget.off_policy
        return EARLY * total

    return frame[frame.step <= frame.apply(limit, axis=1)]


def report(store: RunStore, args: Args) -> str:
    """Learning curves, the verdicts on both metrics, and each family's outcome."""
    frame = store.load()
    picks = load_picks(args.picks)
    labels = arm_labels(picks)
    panels = [
        Panel(f"{env}: {family.upper()}", env, ARMS[family])
        for family, envs in ENVS_OF.items()
        for env in envs
        if not frame[(frame.env == env) & frame.method.isin(ARMS[family])].empty
    ]
    baselines = {arm: family for family, arms in ARMS.items() for arm in arms[1:]}
    section = rl_section(
        store,
        panels,
        ENVS,
        METHODS,
        labels=labels,
        baselines=baselines,
        ncols=4,
        per_seed=False,
        inline=False,
    )
    tables = {
        "first third (primary)": verdict_table(
            early(frame, args.budgets), ENVS, COMPARISONS, labels
        ),
        "whole curve (secondary)": verdict_table(frame, ENVS, COMPARISONS, labels),
    }
    write_verdicts(store, *tables.values())
    compact = compact_table(*tables.values())
    text = [
        section,
        "Verdicts (P(arm better) with its 95 % CI, two-sided Mann-Whitney p Holm-corrected "
        "within each family and metric):\n\n" + verdicts_markdown(compact) + "\n",
    ]
    text.append(
        outcomes(tables["first third (primary)"], tables["whole curve (secondary)"], labels, picks)
    )
    text.append(f"E1's picks: `{json.dumps(picks)}`.\n")
    text.append(f"Budgets (per run):\n\n{budget_table(args.budgets)}\n")
    return "\n".join(text)


def arm_labels(picks: dict[str, dict[str, Any] | None]) -> dict[str, str]:
    """Each arm's name in plots and tables; a candidate arm's names its method's critic."""
    labels = {arm: LABELS.get(arm, arm) for arm in METHODS}
    for family in ARMS:
        pick = picks.get(E1_FAMILY[family])
        if pick is not None:
            for arm, method in seeking_methods(family, pick["learner"]).items():
                labels[arm] = LABELS[method]
    return labels


def outcomes(
    primary: pd.DataFrame,
    whole: pd.DataFrame,
    labels: dict[str, str],
    picks: dict[str, dict[str, Any] | None],
) -> str:
    """Each family's outcome under the study's success rule."""
    lines = ["Outcome per family (success rule in `studies/seeking.py`):", ""]
    for family in ARMS:
        arm = labels[f"{family}_esa"]
        if picks.get(E1_FAMILY[family]) is None:
            lines.append(
                f"- **{family}**: closed by E1 (no critic and kappa passed its go/no-go), so "
                "its ESA and control arms are not run: ESA is not shown to help "
                f"{family.upper()}."
            )
            continue
        if primary.empty or arm not in set(primary.method):
            lines.append(f"- **{family}**: no verdict yet (its ESA arm has no two seeds).")
            continue
        both, worse = better_and_worse(primary, whole, arm)
        success = len(both) >= MIN_BETTER and QUADROTOR in both and not worse
        lines.append(
            f"- **{family}**: {'success' if success else 'no success'}: better than baseline "
            f"and placebo on {sorted(both) or 'no env'}; whole-curve worse than baseline on "
            f"{sorted(worse) or 'no env'}."
        )
    return "\n".join(lines) + "\n"
