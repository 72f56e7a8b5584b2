"""Quadrotor path tracking: PPO vs PPO+ESA after the same number of steps (the paper's Figure 4).

Both methods train on ``esa_experiments/Quadrotor-v0`` with the circle and
the figure-eight path for the same number of env steps; afterwards the final
deterministic policy flies one evaluation episode (seeded like the periodic
evaluations) whose trajectory is stored next to the run's CSV. The figure
shows the flown paths of seed 0 of each method (seed fixed in advance, not
picked) against the target, with the environment package's plotting helper;
the table gives the mean position error of that final flight over all seeds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from esa_experiments.algorithms import LABELS
from esa_experiments.envs.quadrotor_rollout import TrackedEpisode, record_episode
from esa_experiments.envs.trajectory_plot import plot_tracking
from esa_experiments.evaluation import EVAL_SEED_OFFSET, ProgressFn
from esa_experiments.plotting import Panel
from esa_experiments.reporting import budget_table, rl_section
from esa_experiments.runs import RunResult, RunSpec, RunStore
from esa_experiments.studies import mujoco
from esa_experiments.tables import to_markdown
from esa_experiments.tasks import get_task
from esa_experiments.training import StepBudget, rl_spec, trained

NAME = "quadrotor"
DESCRIPTION = "Quadrotor circle and figure-eight: PPO vs PPO+ESA, learning curves and flown paths"
ENVS = ("Quadrotor-circle", "Quadrotor-eight")
METHODS = ("ppo", "ppo_esa")
DEFAULT_SEEDS = "0-2"
PLOTTED_SEED = 0


@dataclass(frozen=True)
class Args:
    """Arguments of the study: the step budget (the mujoco study's quadrotor budget)."""

    budget: StepBudget = field(default_factory=lambda: mujoco.BUDGETS["full"].budgets[ENVS[0]])


BUDGETS = {
    "smoke": Args(mujoco.BUDGETS["smoke"].budgets[ENVS[0]]),
    "full": Args(mujoco.BUDGETS["full"].budgets[ENVS[0]]),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """One run per (path, method, seed)."""
    return [
        rl_spec(NAME, env, method, seed, budget, args.budget)
        for seed in seeds
        for env in envs
        for method in methods
    ]


def _trajectory(episode: TrackedEpisode) -> pd.DataFrame:
    columns = {"time": episode.times, "position_error": episode.position_errors}
    for i, axis in enumerate("xyz"):
        columns[axis] = episode.positions[:, i]
        columns[f"target_{axis}"] = episode.targets[:, i]
    return pd.DataFrame(columns)


def run(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains, evaluates, then flies the final policy once and keeps its trajectory."""
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


def _full_target(env_key: str) -> np.ndarray:
    """The whole target path (a hovering zero-action flight lasts the full episode)."""
    env = get_task(env_key).make()
    try:
        episode = record_episode(env, lambda obs: np.zeros(4, dtype=np.float32), seed=0)
    finally:
        env.close()
    return episode.targets


def report(store: RunStore, args: Args) -> str:
    """Learning curves, summary table, flown trajectories and a table of the final flights."""
    panels = [Panel(env, env, METHODS) for env in ENVS]
    section = rl_section(store, panels, ENVS, METHODS, figure_name="learning_curves.png")
    flights = store.load("trajectory")
    rows, figures = [], []
    for env in ENVS:
        flown = {}
        for method in METHODS:
            runs = flights[(flights.env == env) & (flights.method == method)]
            if runs.empty:
                continue
            per_seed = runs.groupby("seed").agg(
                error=("position_error", "mean"), seconds=("time", "max")
            )
            rows.append(
                {
                    "path": env,
                    "method": LABELS[method],
                    "seeds": len(per_seed),
                    "mean position error [m]": f"{per_seed.error.mean():.2f} ± "
                    f"{per_seed.error.sem() if len(per_seed) > 1 else 0:.2f}",
                    "flight duration [s]": f"{per_seed.seconds.mean():.1f}",
                }
            )
            plotted = runs[runs.seed == PLOTTED_SEED]
            if not plotted.empty:
                flown[f"{LABELS[method]} (seed {PLOTTED_SEED})"] = plotted[
                    ["x", "y", "z"]
                ].to_numpy()
        if flown:
            path = store.artifact(f"trajectory_{env.split('-')[-1]}.png")
            plot_tracking(
                _full_target(env), flown, path, title=f"{env}: final deterministic policies"
            )
            figures.append(f"![{env}]({store.relative(path)})")
    flight_table = to_markdown(pd.DataFrame(rows))
    return (
        f"{section}\n" + "\n".join(figures) + "\n\nFinal flight of each trained policy "
        f"(one evaluation episode, mean ± SE over seeds):\n\n{flight_table}\n\n"
        f"Budget (per run):\n\n{budget_table({env: args.budget for env in ENVS})}\n"
    )
