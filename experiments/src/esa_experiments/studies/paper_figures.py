"""The paper's Figures 5 and 4 with what ships: ESAPPO and ESASAC against the paper's baselines.

Rules, fixed and committed before the first run:

* **Question.** The paper's Figure 5 claims that ESA "accelerates learning and enhances the
  performance of both PPO and SAC, and outperforms other baselines" (parameter-space noise,
  DDPG with Ornstein-Uhlenbeck noise) on the inverted pendulum, Hopper, Walker2d and the
  quadrotor, 5 seeds each; Figure 4 that the quadrotor policy PPO+ESA learns flies its path
  visibly better than PPO's after the same steps. Does what ships do that?
* **Arms**, stored under these names:

  - ``ppo``: plain PPO with this suite's settings (``configs/algorithms.toml``, E2's);
  - ``ppo_esa``: the shipped ``ESAPPO()`` default, which is E2's ``ppo_esa`` arm (method
    ``ppo_seek_esa_quadratic`` with ``trust_region`` 1: ``EsaConfig.ppo()``, the quadratic
    head, the decoupled objective; ``algorithms.esa_class`` resolves it to the product's
    ``ESAPPO`` itself, no lab subclass);
  - ``ppo_paramnoise``: PPO with adaptive parameter-space noise (Plappert et al. 2018);
  - ``sac``: plain SAC; ``sac_esa``: the shipped ``ESASAC()`` default
    (``EsaConfig.off_policy()``, the product's class); ``sac_paramnoise``: SAC with
    parameter-space noise;
  - ``ddpg_ou``: DDPG with Ornstein-Uhlenbeck action noise (theta 0.15, sigma 0.2).
* **Envs and budgets.** InvertedPendulum-v5, Hopper-v5, Walker2d-v5 and Quadrotor-eight
  (the figure-eight path), with E2's budgets (``seeking.BUDGETS``) where E2 has the env and
  Hopper-v5's for Walker2d-v5: PPO family 30,720 / 100,352 / 100,352 / 60,416 steps, SAC and
  DDPG 50,000 on every env; E2's evaluation (5 deterministic episodes every 2,048 steps on
  InvertedPendulum-v5, 3 every 4,096 elsewhere; off-policy 3 or 5 every 2,500).
* **Reused runs.** A run whose fingerprint (env, arm name, seed and every resolved setting)
  equals a committed run of another study is read from there, not run again
  (:mod:`esa_experiments.reuse`): ``ppo`` and ``ppo_esa`` on InvertedPendulum-v5 and
  Hopper-v5 from E2 (``results/seeking``), ``sac`` and ``sac_esa`` on Hopper-v5 and
  Quadrotor-eight from the confirmation campaign (``results/confirmation``). A run the source
  lacks or holds with other settings is run here. Equal settings are not equal code: E2's
  PPO+ESA runs evaluated the quadratic head in float32 (``PROVENANCE.md`` names their
  code); main evaluates it in esa-core's float64 closed form, so main's runs of that arm
  depart from E2's within the run (seed 0 on InvertedPendulum-v5: the same curve to step
  10,240, then 90.0 against 90.2 at 12,288; ``results/seeking/PROVENANCE.md``). The report
  names the source of every run.
* **Figure 4.** ``ppo`` and ``ppo_esa`` on Quadrotor-eight are run here, not reused, because
  the figure needs the trained policies and E2 kept none: after training, each policy's mean
  (deterministic) flies one evaluation episode (reset seed ``10000 + seed``), whose
  trajectory is stored beside the run. The figure shows seed 0 of each arm (fixed in advance,
  not picked); the table gives every seed's mean position error. As the same settings ran in
  E2, the report also compares these runs with E2's on the same seeds: a measure of how far
  main re-runs E2's PPO arms.
* **Seeds** 0-4 for every arm (the paper's 5), all run, none dropped, no optional stopping;
  runs are seed-major, so a study cut short compares every arm on the seeds it finished.
* **Metric** E2's: primary, the area under the evaluation curve over the first third of the
  budget (normalized by its span); secondary, the whole-curve AUC.
* **Tests** E2's (:func:`esa_client.compare.verdicts.verdict_table`): per env, ``P(X > Y)``
  with its bootstrap CI and the two-sided Mann-Whitney U test, for ``ppo_esa`` against
  ``ppo`` and ``ppo_paramnoise``, and ``sac_esa`` against ``sac``, ``sac_paramnoise`` and
  ``ddpg_ou``; PPO's budget differs from the off-policy one, so PPO and DDPG are not
  compared. Holm within each (algorithm, env), for each metric: with 5 seeds the smallest
  two-sided exact p is 2/252 = 0.0079, so Holm over more than six tests (E2's family over
  its envs) could never reject; one panel of the figure is one claim. Better / worse at a
  corrected p < 0.05. **Power**: a first rejection needs P(X > Y) >= 0.96 (U >= 24 of 25),
  so only a large effect shows; where E2 or the confirmation campaign has 20 seeds of the
  same arms, theirs is the stronger evidence, and RESULTS.md gives both.
* **Decision, Figure 5**, per family (PPO, SAC) and env: the paper's claim **holds** when the
  ESA arm is better than its baseline on the primary metric and worse than it on neither
  metric; ESA **outperforms the other baselines** there when it is also better than each of
  them (parameter noise; for SAC also DDPG+OU) on the primary metric. Per family the claim
  is **reproduced** when it holds on at least 3 of the 4 envs, **partly** on 1 or 2, **not
  reproduced** on none; ESA worse than its baseline on any env is reported as harm.
* **Decision, Figure 4**: the claim holds when PPO+ESA's final flights have a lower mean
  position error than PPO's, two-sided Mann-Whitney p < 0.05 over the seeds (one test).
* **Runs**: 140 planned (7 arms x 4 envs x 5 seeds), 40 of them reused: 100 to run,
  ``python -m esa_experiments run paper_figures --budget full --jobs 2`` (resumable), then
  ``python -m esa_experiments plot paper_figures --budget full``. The smoke budget (CI) runs
  every arm on every env for a few hundred steps and reuses nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from esa_client.compare.evaluation import EVAL_SEED_OFFSET, ProgressFn
from esa_client.compare.plotting import Panel
from esa_client.compare.reliability import probability_of_improvement
from esa_client.compare.tables import to_markdown
from esa_client.compare.verdicts import Comparison, compact_table, verdict_table
from scipy.stats import mannwhitneyu

from esa_experiments.algorithms import LABELS
from esa_experiments.envs.quadrotor_rollout import TrackedEpisode, record_episode
from esa_experiments.envs.trajectory_plot import plot_tracking
from esa_experiments.reporting import budget_table, rl_section, verdicts_markdown, write_verdicts
from esa_experiments.reuse import Reuse, load_runs, provenance_table, rerun_table, to_run
from esa_experiments.runs import RunResult, RunSpec, RunStore, parse_seeds
from esa_experiments.studies import seeking
from esa_experiments.tasks import get_task
from esa_experiments.training import (
    SMOKE_BUDGET,
    StepBudget,
    rl_spec,
    run_training,
    trained,
)

NAME = "paper_figures"
DESCRIPTION = "Figures 5 and 4: shipped ESAPPO/ESASAC vs PPO, SAC, param noise, DDPG+OU (5 seeds)"
PENDULUM, HOPPER, WALKER, QUADROTOR = (
    "InvertedPendulum-v5",
    "Hopper-v5",
    "Walker2d-v5",
    "Quadrotor-eight",
)
ENVS = (PENDULUM, HOPPER, WALKER, QUADROTOR)
ARM_METHODS = {
    "ppo": "ppo",
    "ppo_esa": "ppo_seek_esa_quadratic",
    "ppo_paramnoise": "ppo_paramnoise",
    "sac": "sac",
    "sac_esa": "sac_esa",
    "sac_paramnoise": "sac_paramnoise",
    "ddpg_ou": "ddpg_ou",
}
"""Arm (the name its runs are stored under) -> method of :mod:`esa_experiments.algorithms`."""
ESA_OVERRIDES = {"ppo_esa": {"trust_region": 1.0}}
"""E2's ``ppo_esa`` on top of its ``seeking_ppo`` preset: ``EsaConfig.ppo()``, E1's kappa."""
METHODS = tuple(ARM_METHODS)
ON_POLICY = METHODS[:3]
OFF_POLICY = METHODS[3:]
DEFAULT_SEEDS = "0-4"
FAMILIES = {"ppo": "ppo_esa", "sac": "sac_esa"}
"""Algorithm family -> its ESA arm (the shipped default)."""
BASELINES = {"ppo_esa": "ppo", "ppo_paramnoise": "ppo", "sac_esa": "sac", "sac_paramnoise": "sac"}
COMPARISONS = (
    Comparison("ppo", "ppo_esa", "ppo", "baseline"),
    Comparison("ppo", "ppo_esa", "ppo_paramnoise", "parameter noise"),
    Comparison("sac", "sac_esa", "sac", "baseline"),
    Comparison("sac", "sac_esa", "sac_paramnoise", "parameter noise"),
    Comparison("sac", "sac_esa", "ddpg_ou", "DDPG+OU"),
)
REUSED = {
    "ppo": {PENDULUM: seeking.NAME, HOPPER: seeking.NAME},
    "ppo_esa": {PENDULUM: seeking.NAME, HOPPER: seeking.NAME},
    "sac": {HOPPER: "confirmation", QUADROTOR: "confirmation"},
    "sac_esa": {HOPPER: "confirmation", QUADROTOR: "confirmation"},
}
"""Arm -> env -> the study whose committed runs of the same settings are read, not rerun."""
FLIGHT_ARMS = ("ppo", "ppo_esa")
"""The arms whose final policies fly Figure 4 (run here: E2 kept no trained policy)."""
RERUN_CHECK = {arm: {QUADROTOR: seeking.NAME} for arm in FLIGHT_ARMS}
"""Runs made here whose settings E2 also ran: compared with E2's, seed by seed."""
PLOTTED_SEED = 0
MIN_ENVS = 3
"""Envs (of 4) on which the claim must hold for a family's "reproduced"."""


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: step budget per env (``on_policy`` for the PPO family, ``off_policy`` for
            SAC and DDPG).
        reuse: where the reused runs come from (nothing reused at the smoke budget).
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    reuse: Reuse = field(default_factory=lambda: Reuse(enabled=False))


SMOKE = replace(SMOKE_BUDGET, on_policy=384)
"""E2's smoke budget: three PPO rollouts, a short off-policy warm-up."""
E2_BUDGETS = seeking.BUDGETS["full"].budgets

BUDGETS = {
    "smoke": Args({env: SMOKE for env in ENVS}),
    "full": Args(
        {
            PENDULUM: E2_BUDGETS[PENDULUM],
            HOPPER: E2_BUDGETS[HOPPER],
            WALKER: E2_BUDGETS[HOPPER],
            QUADROTOR: E2_BUDGETS[QUADROTOR],
        },
        Reuse(REUSED),
    ),
}


def arm_spec(arm: str, env: str, seed: int, budget_name: str, budget: StepBudget) -> RunSpec:
    """The spec of one run of ``arm``, stored under the arm's name."""
    return rl_spec(
        NAME,
        env,
        ARM_METHODS[arm],
        seed,
        budget_name,
        budget,
        variant=arm,
        esa_overrides=ESA_OVERRIDES.get(arm),
    )


def planned(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """Every run of the study, reused or not, seed-major."""
    return [
        arm_spec(arm, env, seed, budget, args.budgets[env])
        for seed in seeds
        for env in ENVS
        if env in envs
        for arm in METHODS
        if arm in methods
    ]


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The runs this study makes itself: the planned ones no other study holds."""
    return to_run(planned(args, budget, seeds, envs, methods), args.reuse)


def _trajectory(episode: TrackedEpisode) -> pd.DataFrame:
    columns = {"time": episode.times, "position_error": episode.position_errors}
    for i, axis in enumerate("xyz"):
        columns[axis] = episode.positions[:, i]
        columns[f"target_{axis}"] = episode.targets[:, i]
    return pd.DataFrame(columns)


def run(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """One run: train with periodic evaluation; Figure 4's arms then fly their final policy."""
    if spec.env != QUADROTOR or spec.method not in FLIGHT_ARMS:
        return run_training(spec, progress)
    with trained(spec, progress) as (result, model):
        env = get_task(spec.env).make()
        try:
            episode = record_episode(
                env,
                lambda obs: model.policy.predict(obs, deterministic=True)[0],
                seed=EVAL_SEED_OFFSET + spec.seed,
            )
        finally:
            env.close()
    result.meta.update(
        flight_return=episode.episode_return,
        flight_mean_position_error=episode.mean_position_error,
        flight_seconds=float(episode.times[-1]),
        flight_termination=episode.termination,
    )
    result.tables["trajectory"] = _trajectory(episode)
    return result


def study_seeds(store: RunStore) -> list[int]:
    """The rules' seeds 0-4 and any further seed the study has run."""
    meta = store.load_meta()
    extra = set(meta.seed.astype(int)) if not meta.empty else set()
    return sorted(set(parse_seeds(DEFAULT_SEEDS)) | extra)


def verdicts(frame: pd.DataFrame, args: Args) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The verdicts on the primary and the secondary metric, Holm within each (family, env)."""
    parts: dict[str, list[pd.DataFrame]] = {"primary": [], "whole": []}
    for env in ENVS:
        parts["primary"].append(
            verdict_table(seeking.early(frame, args.budgets), (env,), COMPARISONS, LABELS)
        )
        parts["whole"].append(verdict_table(frame, (env,), COMPARISONS, LABELS))
    primary, whole = (pd.concat(tables, ignore_index=True) for tables in parts.values())
    return primary, whole


def _verdict(table: pd.DataFrame, env: str, arm: str, reference: str) -> str | None:
    """The verdict word (better, worse, equal) of one comparison, or None if not made."""
    if table.empty:
        return None
    rows = table[
        (table.env == env)
        & (table.method == LABELS[arm])
        & table.against.str.startswith(f"{LABELS[reference]} (")
    ]
    return str(rows.verdict.iloc[0]).strip("*") if not rows.empty else None


def outcome(primary: pd.DataFrame, whole: pd.DataFrame, frame: pd.DataFrame) -> str:
    """Each family's outcome under the decision rule of Figure 5."""
    lines = ["Figure 5, outcome per family (rules in `studies/paper_figures.py`):", ""]
    for family, arm in FAMILIES.items():
        others = [c.reference for c in COMPARISONS if c.method == arm and c.kind != "baseline"]
        holds, beats, harm, open_envs = [], [], [], []
        for env in ENVS:
            early = _verdict(primary, env, arm, family)
            overall = _verdict(whole, env, arm, family)
            if early is None:
                open_envs.append(env)
                continue
            if "worse" in (early, overall):
                harm.append(env)
            if early == "better" and overall != "worse":
                holds.append(env)
                if all(_verdict(primary, env, arm, ref) == "better" for ref in others):
                    beats.append(env)
        complete = all(
            len(set(frame[(frame.env == env) & (frame.method == m)].seed)) >= 5
            for env in ENVS
            for m in (arm, family, *others)
        )
        if len(open_envs) == len(ENVS):
            lines.append(f"- **{family.upper()}**: no verdict yet (no comparison has two seeds).")
            continue
        state = "reproduced" if len(holds) >= MIN_ENVS else "partly" if holds else "not reproduced"
        provisional = "" if complete else " (provisional: not every arm has 5 seeds), so far"

        lines.append(
            f"- **{family.upper()}**{provisional}: **{state}**. Envs where {LABELS[arm]} is "
            f"better than {LABELS[family]} early and worse on neither metric: {_envs(holds)} "
            f"(of {len(ENVS)}); where it also beats "
            f"{' and '.join(LABELS[r] for r in others)}: {_envs(beats)}; where it is worse "
            f"than {LABELS[family]}: {_envs(harm)}"
            + (f"; no verdict yet: {_envs(open_envs)}" if open_envs else "")
            + "."
        )
    return "\n".join(lines) + "\n"


def _envs(names: list[str]) -> str:
    return ", ".join(names) if names else "none"


def _full_target(env_key: str) -> np.ndarray:
    """The whole target path (a hovering zero-action flight lasts the full episode)."""
    env = get_task(env_key).make()
    try:
        episode = record_episode(env, lambda obs: np.zeros(4, dtype=np.float32), seed=0)
    finally:
        env.close()
    return episode.targets


def figure4(store: RunStore) -> str:
    """Figure 4: the flown paths, each seed's final-flight error, and the pre-declared test."""
    try:
        flights = store.load("trajectory")
    except FileNotFoundError:
        return "Figure 4: no flight yet (the quadrotor's PPO arms have not run here).\n"
    errors: dict[str, pd.Series] = {}
    rows, flown = [], {}
    for arm in FLIGHT_ARMS:
        runs = flights[(flights.env == QUADROTOR) & (flights.method == arm)]
        if runs.empty:
            continue
        per_seed = runs.groupby("seed").agg(
            error=("position_error", "mean"), seconds=("time", "max")
        )
        errors[arm] = per_seed.error
        rows.append(
            {
                "arm": LABELS[arm],
                "seeds": len(per_seed),
                "mean position error [m], per seed": ", ".join(f"{e:.3f}" for e in per_seed.error),
                "mean ± SE": f"{per_seed.error.mean():.3f} ± "
                f"{per_seed.error.sem() if len(per_seed) > 1 else 0:.3f}",
                "flight duration [s]": f"{per_seed.seconds.mean():.1f}",
            }
        )
        plotted = runs[runs.seed == PLOTTED_SEED]
        if not plotted.empty:
            flown[f"{LABELS[arm]} (seed {PLOTTED_SEED})"] = plotted[["x", "y", "z"]].to_numpy()
    text = []
    if flown:
        path = store.artifact("trajectory_eight.png")
        title = f"{QUADROTOR}: final deterministic policies"
        plot_tracking(_full_target(QUADROTOR), flown, path, title=title)
        text.append(f"![{QUADROTOR}, flown]({store.relative(path)})\n")
    text.append(
        "Figure 4: each final policy's flight (one evaluation episode, after the same steps):"
        f"\n\n{to_markdown(pd.DataFrame(rows))}\n"
    )
    esa, ppo = errors.get("ppo_esa"), errors.get("ppo")
    if esa is not None and ppo is not None:
        common = esa.index.intersection(ppo.index)
        if len(common) >= 2:
            x, y = esa[common].to_numpy(float), ppo[common].to_numpy(float)
            p = float(mannwhitneyu(x, y, alternative="two-sided").pvalue)
            p_lower, low, high = probability_of_improvement(-x, -y)
            holds = p < 0.05 and x.mean() < y.mean()
            text.append(
                f"P(PPO+ESA's error lower than PPO's) = {p_lower:.2f} [{low:.2f}, {high:.2f}], "
                f"Mann-Whitney p = {p:.3f} over {len(common)} seeds: Figure 4's claim "
                f"**{'holds' if holds else 'does not hold'}**.\n"
            )
    return "\n".join(text)


def report(store: RunStore, args: Args) -> str:
    """Figure 5 (curves, verdicts, outcome), Figure 4 (flights) and where each run came from."""
    plan = planned(args, store.budget, study_seeds(store), ENVS, METHODS)
    frame = load_runs(store, plan, args.reuse)
    log = load_runs(store, plan, args.reuse, "log")
    panels = [Panel(f"{env}: PPO family", env, ON_POLICY) for env in ENVS] + [
        Panel(f"{env}: SAC / DDPG", env, OFF_POLICY) for env in ENVS
    ]
    section = rl_section(
        store,
        panels,
        ENVS,
        METHODS,
        baselines=BASELINES,
        ncols=len(ENVS),
        frame=frame,
        log=log,
        inline=False,
    )
    primary, whole = verdicts(frame, args)
    write_verdicts(store, primary, whole)
    compact = compact_table(primary, whole)
    text = [
        section,
        "Figure 5, verdicts (E2's statistics; Holm within each algorithm and env):\n\n"
        + verdicts_markdown(compact)
        + "\n",
        outcome(primary, whole, frame),
        figure4(store),
    ]
    # Only committed runs are worth comparing with (the smoke budget reuses nothing either).
    check = (
        rerun_table(frame, plan, RERUN_CHECK, args.reuse.base, seeking.EARLY, LABELS)
        if args.reuse.enabled
        else pd.DataFrame()
    )
    if not check.empty:
        text.append(
            "The same settings run from this study's code and committed by E2, seed by seed "
            f"(how far main re-runs E2's PPO arms):\n\n{to_markdown(check)}\n"
        )
    text.append(
        "Where each run comes from (reused runs: the same fingerprint, committed by another "
        "study, from that study's code):\n\n"
        f"{to_markdown(provenance_table(store, plan, args.reuse, LABELS))}\n"
    )
    text.append(f"Budgets (per run):\n\n{budget_table(args.budgets)}\n")
    return "\n".join(text)
