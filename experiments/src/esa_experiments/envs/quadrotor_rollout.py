"""Roll out a policy on the quadrotor env and record the flown and target trajectories."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

Policy = Callable[[np.ndarray], np.ndarray]
"""Maps an observation to an action."""


@dataclass(frozen=True)
class TrackedEpisode:
    """One episode of path tracking, sampled at every env step including the start.

    Attributes:
        times: Time of each sample [s], shape (n + 1,).
        positions: Flown positions [m], shape (n + 1, 3).
        targets: Target positions at the same times [m], shape (n + 1, 3).
        position_errors: Distance to the target [m], shape (n + 1,).
        rewards: Reward of each step, shape (n,).
        terminated: Whether the episode ended by crash, flip or leaving the arena.
        termination: The reason reported in ``info["termination"]``, or None.
    """

    times: np.ndarray
    positions: np.ndarray
    targets: np.ndarray
    position_errors: np.ndarray
    rewards: np.ndarray
    terminated: bool
    termination: str | None

    @property
    def mean_position_error(self) -> float:
        """Mean distance to the target over the episode [m]."""
        return float(self.position_errors.mean())

    @property
    def episode_return(self) -> float:
        """Sum of the rewards."""
        return float(self.rewards.sum())


def record_episode(env: gym.Env, policy: Policy, seed: int | None = None) -> TrackedEpisode:
    """Run one episode of ``policy`` on a quadrotor env until it terminates or truncates.

    Args:
        env: An ``esa_experiments/Quadrotor-v0`` env (wrapped or not).
        policy: The controller; it sees only the observation.
        seed: Seed for ``env.reset``.

    Returns:
        The recorded episode.
    """
    obs, info = env.reset(seed=seed)
    infos, rewards = [info], []
    terminated = truncated = False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        infos.append(info)
        rewards.append(reward)
    return TrackedEpisode(
        times=np.array([i["time"] for i in infos]),
        positions=np.array([i["state"][:3] for i in infos]),
        targets=np.array([i["target"][:3] for i in infos]),
        position_errors=np.array([i["position_error"] for i in infos]),
        rewards=np.array(rewards),
        terminated=bool(terminated),
        termination=info.get("termination"),
    )
