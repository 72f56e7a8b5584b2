"""The environments the studies train on, by short key.

A key names a gymnasium id plus keyword arguments (the quadrotor's path), and
the return threshold used for the "steps to threshold" column of the tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym

from esa_experiments.configs import lookup


@dataclass(frozen=True)
class Task:
    """One environment configuration.

    Attributes:
        gym_id: gymnasium id.
        kwargs: keyword arguments of ``gymnasium.make``.
        threshold: evaluation return counted as "solved enough" for the
            steps-to-threshold metric (chosen for the reduced budgets, see RESULTS.md).
    """

    gym_id: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    threshold: float = float("nan")

    def make(self) -> gym.Env:
        """Creates the env (importing this package registered the quadrotor)."""
        return gym.make(self.gym_id, **self.kwargs)


TASKS: dict[str, Task] = {
    "InvertedPendulum-v5": Task("InvertedPendulum-v5", threshold=950.0),
    "Hopper-v5": Task("Hopper-v5", threshold=1000.0),
    "Walker2d-v5": Task("Walker2d-v5", threshold=500.0),
    "InvertedDoublePendulum-v5": Task("InvertedDoublePendulum-v5", threshold=5000.0),
    "Quadrotor-circle": Task("esa_experiments/Quadrotor-v0", {"path": "circle"}, threshold=450.0),
    "Quadrotor-eight": Task("esa_experiments/Quadrotor-v0", {"path": "eight"}, threshold=450.0),
}


def get_task(key: str) -> Task:
    """Returns the task for ``key``.

    Raises:
        ValueError: for an unknown key (the message lists the known ones).
    """
    return lookup(TASKS, key, "an env")
