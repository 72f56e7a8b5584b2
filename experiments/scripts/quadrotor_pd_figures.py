"""Fly the PD reference controller on the circle and the eight; plot the tracking (PNG).

    python experiments/scripts/quadrotor_pd_figures.py [--seed 0] [--out-dir ...]

Writes ``pd_circle.png`` and ``pd_eight.png`` (3-D and top view, like Figure 4(b, c) of the
ESA paper) and prints the mean position error of each episode.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import tyro

from esa_experiments import QUADROTOR_ENV_ID
from esa_experiments.envs.pd_controller import PDController
from esa_experiments.envs.quadrotor_rollout import record_episode
from esa_experiments.envs.trajectory_plot import plot_tracking

RESULTS = Path(__file__).resolve().parents[1] / "results" / "quadrotor"


@dataclass(frozen=True)
class Args:
    """PD controller tracking figures for esa_experiments/Quadrotor-v0."""

    seed: int = 0
    """Seed of the episodes' reset."""
    out_dir: str = str(RESULTS)
    """Folder of the PNGs."""


def main(args: Args) -> None:
    controller = PDController()
    for path in ("circle", "eight"):
        with gym.make(QUADROTOR_ENV_ID, path=path) as env:
            episode = record_episode(env, controller, seed=args.seed)
        title = (
            f"PD controller on the {path} ({episode.times[-1]:.0f} s, seed {args.seed}): "
            f"mean position error {episode.mean_position_error:.3f} m"
        )
        out = plot_tracking(
            episode.targets,
            {"PD controller": episode.positions},
            Path(args.out_dir) / f"pd_{path}.png",
            title,
        )
        print(
            f"{path:6s} mean error {episode.mean_position_error:.3f} m, "
            f"return {episode.episode_return:.1f}, terminated {episode.terminated} -> {out}"
        )


if __name__ == "__main__":
    main(tyro.cli(Args))
