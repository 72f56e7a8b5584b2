"""E1 of "ESA that seeks": the offline go/no-go. Does a critic with curvature point uphill?

Rules, fixed and committed before the first run (of the "ESA that seeks" round, which
built critics with curvature, the fade, the placebo and the decoupled objective after the
confirmation campaign found no acceleration: E1 gates E2):

* **Learners.** PPO trained as ``ESAPPO`` with ``EsaConfig(learning_rate=0)`` (bit for bit
  plain PPO, its critic fitted as in training) for each critic: ``ppo_fit_linear`` (the
  shipped linear head, for comparison), ``ppo_fit_quadratic``, ``ppo_fit_qnet``; plain
  ``sac`` for SAC's critic (ESASAC's probe: the target twin's mean).
* **Envs and budgets.** InvertedPendulum-v5, InvertedDoublePendulum-v5, Hopper-v5 and
  Quadrotor-eight, the confirmation campaign's budgets (PPO 30,720 / 100,352 / 100,352 /
  60,416 steps; SAC 50,000 on every env). Checkpoints at 10, 30 and 50 % of the budget,
  where returns are below their maximum.
* **Seed.** One tuning seed, 100 (seeds 0-19 are E2's confirmation seeds and are never
  used here).
* **States.** At each checkpoint the stochastic policy runs (the env executes its own
  samples, so all branches see the same states); one state in 7 after the tenth step of
  an episode is saved, 200 per checkpoint, 600 per env and learner.
* **Branches** (:mod:`esa_experiments.seeking_probes`): for kappa in {0.25, 0.5, 1}
  policy stds, ESA's action with ``EsaConfig(trust_region=kappa)`` (the shipped section
  1b law otherwise), the placebo (ESA's ``|v|`` per dimension, a random sign vector per
  episode) and the gradient control (ESA's L2 size in units of sigma along the critic's
  action gradient at ``a_t``), each against the sample ``a_t``.
* **Measure.** From each saved state, every action is executed and the stochastic
  policy followed for 100 steps, 4 rollouts with common random numbers; the gain of a
  branch is its mean discounted (gamma 0.99) return minus the sample's. 95 % CIs by
  bootstrap over the env's 600 states (2,000 resamples, seed 0).
* **Decision.** A (critic, kappa) passes on an env when the CI of ESA's gain is above 0
  and the CI of ESA's gain minus the placebo's (paired by state) is above 0. It goes on
  to E2 only if it passes on at least 2 of the 4 envs. Per family (PPO: the three
  critics; off-policy: SAC's critic) the pick is the passing (critic, kappa) that passes
  on the most envs, ties broken by the larger mean of ESA-minus-placebo over the four
  envs. If nothing passes in a family, that closes the line for the family: its E2 arms
  are not run with a new candidate, and RESULTS.md says so. ESA minus gradient is
  reported, not used for the decision.

Budgets here are the study's own; the ``smoke`` budget only checks the machinery.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import pandas as pd
from esa_client.compare.evaluation import ProgressFn
from esa_client.compare.tables import to_markdown
from matplotlib.figure import Figure

from esa_experiments.runs import RunResult, RunSpec, RunStore, atomic_write_text
from esa_experiments.seeking_probes import (
    KAPPAS,
    LearnerView,
    PPOView,
    SACView,
    branch_names,
    branch_returns,
    capture,
)
from esa_experiments.tasks import get_task
from esa_experiments.training import SMOKE_BUDGET, StepBudget, rl_spec

if TYPE_CHECKING:
    from esa_client.sb3 import ESAPPO
    from stable_baselines3 import SAC
    from stable_baselines3.common.base_class import BaseAlgorithm

NAME = "seeking_offline"
DESCRIPTION = "E1: ESA's, the gradient's and the placebo's true return gains, per critic"
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Quadrotor-eight")
PPO_LEARNERS = ("ppo_fit_linear", "ppo_fit_quadratic", "ppo_fit_qnet")
METHODS = (*PPO_LEARNERS, "sac")
FAMILY = {**{learner: "ppo" for learner in PPO_LEARNERS}, "sac": "off_policy"}
DEFAULT_SEEDS = "100"
CHECKPOINTS = (0.1, 0.3, 0.5)
MIN_ENVS = 2
BOOTSTRAP = 2000


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: each env's full training budget (the checkpoints are fractions of it).
        states: saved states per checkpoint.
        horizon: steps of each Monte-Carlo rollout, the compared action's included.
        rollouts: Monte-Carlo rollouts per state and branch.
        save_every: save one state in this many steps.
        warmup: steps of an episode before the first saved state (so that v has moved).
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    states: int = 200
    horizon: int = 100
    rollouts: int = 4
    save_every: int = 7
    warmup: int = 10


BUDGETS = {
    "smoke": Args(
        {env: SMOKE_BUDGET for env in ENVS},
        states=3,
        horizon=5,
        rollouts=2,
        save_every=2,
        warmup=2,
    ),
    "full": Args(
        {
            "InvertedPendulum-v5": StepBudget(30_720, 50_000, 2_048, 2_500, 1),
            "InvertedDoublePendulum-v5": StepBudget(100_352, 50_000, 4_096, 2_500, 1),
            "Hopper-v5": StepBudget(100_352, 50_000, 4_096, 2_500, 1),
            "Quadrotor-eight": StepBudget(60_416, 50_000, 4_096, 2_500, 1),
        }
    ),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """One run per (env, learner, seed): train to each checkpoint and probe there."""
    check = {
        "states": args.states,
        "horizon": args.horizon,
        "rollouts": args.rollouts,
        "save_every": args.save_every,
        "warmup": args.warmup,
        "checkpoints": list(CHECKPOINTS),
        "kappas": list(KAPPAS),
    }
    out = []
    for seed in seeds:
        for env in envs:
            for method in methods:
                spec = rl_spec(NAME, env, method, seed, budget, args.budgets[env])
                out.append(RunSpec(NAME, env, method, seed, budget, {**spec.config, **check}))
    return out


def run(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains to each checkpoint in turn, saves states there and scores every branch."""
    from stable_baselines3.common.env_util import make_vec_env

    from esa_experiments.algorithms import build_model

    config = spec.config
    task = get_task(spec.env)
    hyperparams = config["hyperparams"]
    train_env = make_vec_env(task.make, n_envs=hyperparams.get("n_envs", 1), seed=spec.seed)
    env = task.make()
    branches = ["sample", *branch_names()]
    envs = [task.make() for _ in range(len(branches) * config["rollouts"])]
    model: BaseAlgorithm | None = None
    rows: list[dict[str, Any]] = []
    try:
        model = build_model(config["method"], train_env, spec.seed, hyperparams)
        for checkpoint in config["checkpoints"]:
            steps = int(checkpoint * config["total_steps"])
            model.learn(max(steps - model.num_timesteps, 0), reset_num_timesteps=False)
            progress(model.num_timesteps)
            view: LearnerView = (
                SACView(cast("SAC", model))
                if spec.method == "sac"
                else PPOView(cast("ESAPPO", model))
            )
            saved = capture(
                view,
                env,
                config["states"],
                save_every=config["save_every"],
                warmup=config["warmup"],
                seed=spec.seed,
            )
            for i, state in enumerate(saved):
                first = np.stack([state.sampled, *(state.actions[b] for b in branches[1:])])
                returns = branch_returns(
                    view,
                    envs,
                    state,
                    first,
                    rollouts=config["rollouts"],
                    horizon=config["horizon"],
                    seed=1000 * i,
                )
                row: dict[str, Any] = {
                    "checkpoint": checkpoint,
                    "steps": model.num_timesteps,
                    "state": i,
                    "return_sampled": float(returns[0]),
                }
                for b, name in enumerate(branches[1:], start=1):
                    row[f"delta {name}"] = float(returns[b] - returns[0])
                    row[f"predicted {name}"] = state.predicted[name]
                    row[f"size {name}"] = state.sizes[name]
                for kappa, cosine in state.noise_cosine.items():
                    row[f"noise_cosine {kappa}"] = cosine
                rows.append(row)
    finally:
        if model is not None and hasattr(model, "esa_close"):
            model.esa_close()
        train_env.close()
        for e in (env, *envs):
            e.close()
    return RunResult(pd.DataFrame(rows), {"checkpoints": list(config["checkpoints"])})


def bootstrap_ci(values: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """95 % percentile bootstrap CI of the mean (``BOOTSTRAP`` resamples)."""
    rng = np.random.default_rng(seed)
    means = rng.choice(values, size=(BOOTSTRAP, len(values))).mean(axis=1)
    return float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def _cell(values: np.ndarray) -> str:
    low, high = bootstrap_ci(values)
    return f"{values.mean():+.3f} [{low:+.3f}, {high:+.3f}]"


def verdicts(frame: pd.DataFrame) -> pd.DataFrame:
    """Per (learner, kappa, env): the gains, their CIs and whether the pair passes there."""
    rows = []
    for (method, env), runs in frame.groupby(["method", "env"], sort=False):
        for kappa in KAPPAS:
            esc, placebo, gradient = (
                runs[f"delta {shift} {kappa:g}"].to_numpy(float)
                for shift in ("esc", "placebo", "gradient")
            )
            rows.append(
                {
                    "learner": method,
                    "kappa": kappa,
                    "env": env,
                    "states": len(runs),
                    "esc": esc.mean(),
                    "esc_low": bootstrap_ci(esc)[0],
                    "esc_minus_placebo": (esc - placebo).mean(),
                    "esc_minus_placebo_low": bootstrap_ci(esc - placebo)[0],
                    "esc_minus_gradient": (esc - gradient).mean(),
                    "passes": bootstrap_ci(esc)[0] > 0 and bootstrap_ci(esc - placebo)[0] > 0,
                }
            )
    return pd.DataFrame(rows)


def picks(table: pd.DataFrame) -> dict[str, tuple[str, float] | None]:
    """Each family's pick (learner, kappa) by the study's decision rule, or None."""
    out: dict[str, tuple[str, float] | None] = {}
    for family in dict.fromkeys(FAMILY.values()):
        rows = table[table.learner.map(FAMILY) == family]
        best: tuple[int, float, str, float] | None = None
        for (learner, kappa), pair in rows.groupby(["learner", "kappa"], sort=False):
            passed = int(pair.passes.sum())
            if passed < MIN_ENVS:
                continue
            key = (passed, float(pair.esc_minus_placebo.mean()), str(learner), float(kappa))
            if best is None or key[:2] > best[:2]:
                best = key
        out[family] = None if best is None else (best[2], best[3])
    return out


def report(store: RunStore, args: Args) -> str:
    """The gains per learner, kappa and env, the decision, and a figure."""
    frame = store.load()
    rows = []
    for (method, env), runs in frame.groupby(["method", "env"], sort=False):
        for kappa in KAPPAS:
            esc, placebo, gradient = (
                runs[f"delta {shift} {kappa:g}"].to_numpy(float)
                for shift in ("esc", "placebo", "gradient")
            )
            cosine = runs.get(f"noise_cosine {kappa:g}")
            rows.append(
                {
                    "learner": method,
                    "kappa": f"{kappa:g}",
                    "env": env,
                    "states": len(runs),
                    "ESA gain [95% CI]": _cell(esc),
                    "placebo gain": _cell(placebo),
                    "gradient gain": _cell(gradient),
                    "ESA - placebo": _cell(esc - placebo),
                    "ESA - gradient": _cell(esc - gradient),
                    "mean abs(v)/sigma": f"{runs[f'size esc {kappa:g}'].mean():.3f}",
                    "cos(v, mu - a)": (
                        f"{np.nanmean(cosine.to_numpy(float)):+.2f}" if cosine is not None else ""
                    ),
                }
            )
    table = verdicts(frame)
    chosen = picks(table)
    passing = table[table.passes]
    lines = []
    for family, pick in chosen.items():
        if pick is None:
            lines.append(
                f"- **{family}**: no (critic, kappa) passes on {MIN_ENVS} or more envs: the line "
                "closes for this family."
            )
        else:
            envs = ", ".join(passing[(passing.learner == pick[0]) & (passing.kappa == pick[1])].env)
            lines.append(f"- **{family}**: `{pick[0]}` at kappa {pick[1]:g} (passes on {envs}).")
    atomic_write_text(store.artifact("table.md"), to_markdown(pd.DataFrame(rows)) + "\n")
    # What study `seeking` (E2) reads to build its candidate arms.
    atomic_write_text(
        store.artifact("picks.json"),
        json.dumps(
            {f: None if p is None else {"learner": p[0], "kappa": p[1]} for f, p in chosen.items()},
            indent=2,
        )
        + "\n",
    )
    figure = _figure(table, store.artifact("seeking_offline.png"))
    path = store.artifact("table.md")
    return (
        f"![E1]({store.relative(figure)})\n\n"
        "Per learner and kappa, the envs where it passes (the CIs of ESA's gain and of ESA "
        "minus placebo above 0) and the mean over the envs of the true-return gains over "
        f"the sample (discounted, gamma 0.99, {args.horizon} steps, {args.rollouts} rollouts "
        "with common random numbers); every env's gains with their 95 % bootstrap CIs over "
        f"states: [{path.name}]({store.relative(path)}).\n\n"
        f"{to_markdown(passes_table(table))}\n\n"
        "Decision (rules in `studies/seeking_offline.py`):\n\n" + "\n".join(lines) + "\n"
    )


def passes_table(table: pd.DataFrame) -> pd.DataFrame:
    """Per (learner, kappa): where it passes, and its gains averaged over the envs."""
    return pd.DataFrame(
        [
            {
                "learner": learner,
                "kappa": f"{kappa:g}",
                "passes on": ", ".join(pair[pair.passes].env) or "no env",
                "ESA gain": f"{pair.esc.mean():+.3f}",
                "ESA - placebo": f"{pair.esc_minus_placebo.mean():+.3f}",
                "ESA - gradient": f"{pair.esc_minus_gradient.mean():+.3f}",
            }
            for (learner, kappa), pair in table.groupby(["learner", "kappa"], sort=False)
        ]
    )


def _figure(table: pd.DataFrame, path: Path) -> Path:
    """ESA's gain and ESA minus placebo per learner and kappa, one panel per env."""
    envs = list(dict.fromkeys(table.env))
    fig = Figure(figsize=(4 * len(envs), 3.6), layout="constrained")
    axes = fig.subplots(1, len(envs), squeeze=False)[0]
    learners = list(dict.fromkeys(table.learner))
    width = 0.8 / max(len(learners), 1)
    for ax, env in zip(axes, envs, strict=True):
        rows = table[table.env == env]
        for i, learner in enumerate(learners):
            mine = rows[rows.learner == learner]
            x = np.arange(len(mine)) + i * width
            ax.bar(x, mine.esc, width, label=f"{learner}: ESA")
            ax.plot(x, mine.esc_minus_placebo, "k.", label=None if i else "ESA - placebo")
        ax.set_xticks(np.arange(len(KAPPAS)) + 0.4 - width / 2, [f"{k:g}" for k in KAPPAS])
        ax.set_xlabel("kappa (policy stds)")
        ax.axhline(0.0, color="grey", linewidth=0.8)
        ax.set_title(env, fontsize=10)
    axes[0].set_ylabel("mean return gain over a_t")
    axes[0].legend(fontsize=7)
    fig.savefig(path, dpi=120)
    return path
