"""The paper's Figure 6 with what ships: ablations of the ESAPPO default on InvertedPendulum-v5.

Rules, fixed and committed before the first run:

* **Question.** The paper's Figure 6 varies, on the inverted pendulum, (a) the probe's
  amplitude K (K = 0.2 best; smaller slower; larger faster at first but with more variance
  over seeds), (b) its frequency w (above 10 pi rad/s ESA helps less) and (c) the decay of
  ESA over training (it should decay, to spare a policy near its peak). How does each knob
  move the shipped ``ESAPPO()`` default?
* **Arms**: the shipped default ``ppo_esa`` (E2's arm: method ``ppo_seek_esa_quadratic``
  with ``trust_region`` 1, that is ``EsaConfig.ppo()``: K = 0.29, w = 0.48 of the Nyquist
  frequency, which on InvertedPendulum-v5 (dt 0.04 s) is 12 pi rad/s, faded linearly to 0
  by half the budget) and plain ``ppo`` as the reference curve; each variant changes one
  field of the default (:data:`VARIANTS`):

  - (a) amplitude K in {0.1, 0.2, 0.4, 0.8} (the paper's 0.1, 0.2, 0.4, and a larger one);
  - (b) frequency: ``nyquist_fraction`` in {0.08, 0.2, 0.8}, which on this env are the
    paper's 2 pi, 5 pi and 20 pi rad/s;
  - (c) decay: the fade over 0.25 or the whole of the budget, no fade, and the per-episode
    learning-rate decay the paper's text describes (``lr_decay`` 0.99 and 0.97, without the
    fade, so each decays one way). The per-episode decay is sound in esa-core (the rate is
    ``alpha * gamma^e`` with the normalized step) but depends on how often episodes end:
    a policy that falls often decays its ESA faster, so two such arms at one step have
    decayed by different amounts; the fade, tied to the budget, does not.
* **Reused runs.** ``ppo`` and ``ppo_esa`` are E2's runs of seeds 0-4 (``results/seeking``,
  the same fingerprints, from E2's code: ``PROVENANCE.md`` names it, and ``paper_figures``
  says what that means); the variants run here, from main.
* **Env and budget** E2's InvertedPendulum-v5: 30,720 steps, 5 deterministic evaluation
  episodes every 2,048 steps.
* **Seeds** 0-4 for every arm (the paper's 5), all run, none dropped, no optional stopping.
* **Metric** E2's: primary, the AUC over the first third of the budget; secondary, the
  whole-curve AUC.
* **Tests** E2's (:func:`esa_client.compare.verdicts.verdict_table`): each variant against the
  default, Holm within each panel (4, 3 and 5 tests) for each metric, better / worse at a
  corrected p < 0.05. With 5 seeds a rejection needs near-complete separation (P(X > Y) of
  0.96 or more): the ablation finds large effects only.
* **Decision.** A knob's shipped value **stands** when no variant of its panel is better than
  the default on the primary metric. A variant better than the default on the primary metric
  and worse on neither is a **candidate**, to be tested by a later pre-declared study with
  20 seeds on every env; this study ships nothing.
* **Runs**: 70 planned (14 arms x 5 seeds), 10 of them reused: 60 to run,
  ``python -m esa_experiments run paper_ablations --budget full --jobs 2``, then
  ``python -m esa_experiments plot paper_ablations --budget full``. The smoke budget (CI)
  runs every arm for a few hundred steps and reuses nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pandas as pd
from esa_client.compare.plotting import Panel
from esa_client.compare.tables import to_markdown
from esa_client.compare.verdicts import Comparison, compact_table, verdict_table

from esa_experiments.algorithms import LABELS as METHOD_LABELS
from esa_experiments.reporting import budget_table, rl_section, verdicts_markdown, write_verdicts
from esa_experiments.reuse import Reuse, load_runs, provenance_table, to_run
from esa_experiments.runs import RunSpec, RunStore
from esa_experiments.studies import paper_figures, seeking
from esa_experiments.training import StepBudget, rl_spec, run_training

NAME = "paper_ablations"
DESCRIPTION = "Figure 6: the ESAPPO default's amplitude, frequency and decay on InvertedPendulum-v5"
ENV = paper_figures.PENDULUM
ENVS = (ENV,)
DEFAULT = "ppo_esa"
METHOD = paper_figures.ARM_METHODS[DEFAULT]
DEFAULT_OVERRIDES = paper_figures.ESA_OVERRIDES[DEFAULT]
DEFAULT_SEEDS = "0-4"
SEED_COUNT = 5

PANELS_OF: dict[str, dict[str, dict[str, Any]]] = {
    "amplitude": {
        "K0.1": {"amplitude": 0.1},
        "K0.2": {"amplitude": 0.2},
        "K0.4": {"amplitude": 0.4},
        "K0.8": {"amplitude": 0.8},
    },
    "frequency": {
        "w2pi": {"nyquist_fraction": 0.08},
        "w5pi": {"nyquist_fraction": 0.2},
        "w20pi": {"nyquist_fraction": 0.8},
    },
    "decay": {
        "fade0.25": {"fade": 0.25},
        "fade1": {"fade": 1.0},
        "nofade": {"fade": None},
        "decay0.99": {"fade": None, "lr_decay": 0.99},
        "decay0.97": {"fade": None, "lr_decay": 0.97},
    },
}
"""Panel -> variant -> the ``EsaConfig`` fields it changes in the default."""
VARIANTS = {variant: fields for panel in PANELS_OF.values() for variant, fields in panel.items()}
METHODS = ("ppo", DEFAULT, *VARIANTS)
LABELS = {
    "ppo": "PPO (no ESA)",
    DEFAULT: "ESAPPO default: K 0.29, w 12pi, fade 0.5",
    "K0.1": "K = 0.1",
    "K0.2": "K = 0.2",
    "K0.4": "K = 0.4",
    "K0.8": "K = 0.8",
    "w2pi": "w = 2pi rad/s",
    "w5pi": "w = 5pi rad/s",
    "w20pi": "w = 20pi rad/s",
    "fade0.25": "fade by 1/4 of the budget",
    "fade1": "fade over the whole budget",
    "nofade": "no fade",
    "decay0.99": "lr decay 0.99 per episode, no fade",
    "decay0.97": "lr decay 0.97 per episode, no fade",
}
PANELS = tuple(
    Panel(f"({letter}) {panel}", ENV, ("ppo", DEFAULT, *variants))
    for letter, (panel, variants) in zip("abc", PANELS_OF.items(), strict=True)
)
COMPARISONS = tuple(
    Comparison(panel, variant, DEFAULT, "default")
    for panel, variants in PANELS_OF.items()
    for variant in variants
)
REUSED = {"ppo": {ENV: seeking.NAME}, DEFAULT: {ENV: seeking.NAME}}


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: the step budget (one env).
        reuse: where the reused runs come from (nothing reused at the smoke budget).
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    reuse: Reuse = field(default_factory=lambda: Reuse(enabled=False))


BUDGETS = {
    "smoke": Args({ENV: paper_figures.SMOKE}),
    "full": Args({ENV: seeking.BUDGETS["full"].budgets[ENV]}, Reuse(REUSED)),
}


def planned(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """Every run of the study, reused or not, seed-major."""
    budget_of = args.budgets[ENV]
    return [
        rl_spec(NAME, ENV, "ppo", seed, budget, budget_of)
        if arm == "ppo"
        else rl_spec(
            NAME,
            ENV,
            METHOD,
            seed,
            budget,
            budget_of,
            variant=arm,
            esa_overrides={**DEFAULT_OVERRIDES, **VARIANTS.get(arm, {})},
        )
        for seed in seeds
        if ENV in envs
        for arm in METHODS
        if arm in methods
    ]


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The runs this study makes itself: the variants (and the default where E2 lacks it)."""
    return to_run(planned(args, budget, seeds, envs, methods), args.reuse)


run = run_training
"""One run: train with periodic evaluation, nothing else."""


def _word(table: pd.DataFrame, label: str) -> str | None:
    """The verdict (better, worse, equal) of the variant called ``label``, or None."""
    rows = table[table.method == label] if not table.empty else table
    return str(rows.verdict.iloc[0]).strip("*") if not rows.empty else None


def outcome(primary: pd.DataFrame, whole: pd.DataFrame) -> str:
    """Each knob's outcome under the decision rule."""
    lines = ["Outcome per knob (rules in `studies/paper_ablations.py`):", ""]
    for panel, variants in PANELS_OF.items():
        rows = primary[primary.family == panel] if not primary.empty else primary
        if rows.empty:
            lines.append(f"- **{panel}**: no verdict yet (no variant has two seeds).")
            continue
        seeds = int(rows.seeds.min())
        provisional = f" (provisional: {seeds} seeds)" if seeds < SEED_COUNT else ""
        better, worse, candidates = [], [], []
        for variant in variants:
            label = LABELS[variant]
            early_word = _word(primary, label)
            words = {early_word, _word(whole, label)}
            if early_word == "better":
                better.append(label)
                if "worse" not in words:
                    candidates.append(label)
            if "worse" in words:
                worse.append(label)
        state = "stands" if not better else "does not stand"
        lines.append(
            f"- **{panel}**{provisional}: the shipped value {state}; better than the default "
            f"early: {better or 'none'}; worse on either metric: {worse or 'none'}; candidates "
            "for a "
            f"new default: {candidates or 'none'}."
        )
    return "\n".join(lines) + "\n"


def first_third(frame: pd.DataFrame, args: Args) -> pd.DataFrame:
    """The rows of the primary metric, each arm cut at the first third of PPO's budget.

    Every arm is a PPO run, whatever its stored name (``K0.2``, ``fade1``).
    """
    return seeking.early(frame, args.budgets, family=lambda _arm: "ppo")


def report(store: RunStore, args: Args) -> str:
    """Three panels (amplitude, frequency, decay), the verdicts against the default, outcome."""
    plan = planned(args, store.budget, paper_figures.study_seeds(store), ENVS, METHODS)
    frame = load_runs(store, plan, args.reuse)
    log = load_runs(store, plan, args.reuse, "log")
    labels = {**METHOD_LABELS, **LABELS}
    section = rl_section(
        store,
        PANELS,
        ENVS,
        METHODS,
        labels=labels,
        baselines={arm: "ppo" for arm in METHODS[1:]},
        figure_name="ablation.png",
        ncols=3,
        frame=frame,
        log=log,
        inline=False,
    )
    primary = verdict_table(first_third(frame, args), ENVS, COMPARISONS, labels)
    whole = verdict_table(frame, ENVS, COMPARISONS, labels)
    write_verdicts(store, primary, whole)
    compact = compact_table(primary, whole)
    return "\n".join(
        [
            section,
            "Each variant against the default (E2's statistics; Holm within each panel):\n\n"
            + verdicts_markdown(compact)
            + "\n",
            outcome(primary, whole),
            "Where each run comes from:\n\n"
            f"{to_markdown(provenance_table(store, plan, args.reuse, labels))}\n",
            f"Budget (per run):\n\n{budget_table(args.budgets)}\n",
        ]
    )
