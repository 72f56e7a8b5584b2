"""Save and restore a MuJoCo env's simulator state, for Monte-Carlo branches from one state."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from esa_experiments.envs.quadrotor_env import QuadrotorEnv


@dataclass(frozen=True)
class EnvState:
    """What an env's next steps depend on.

    Attributes:
        qpos: MuJoCo positions.
        qvel: MuJoCo velocities.
        act: MuJoCo actuator activations (empty for most envs).
        time: MuJoCo's clock.
        step_count: the quadrotor's step counter (its target moves with it); None elsewhere.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    time: float
    step_count: int | None


def _base(env: gym.Env) -> Any:
    base = env.unwrapped
    if not hasattr(base, "data") or not hasattr(base, "model"):
        raise ValueError(f"expected a MuJoCo env (with model and data), got {type(base).__name__}")
    return base


def save_state(env: gym.Env) -> EnvState:
    """The state of ``env`` (a gymnasium MuJoCo env or the quadrotor) now."""
    base = _base(env)
    data = base.data
    step_count = base._step_count if isinstance(base, QuadrotorEnv) else None
    return EnvState(
        data.qpos.copy(), data.qvel.copy(), data.act.copy(), float(data.time), step_count
    )


def restore_state(env: gym.Env, state: EnvState) -> None:
    """Puts ``env`` back into ``state`` (any env of the same kind: the state is copied in)."""
    base = _base(env)
    data = base.data
    data.qpos[:] = state.qpos
    data.qvel[:] = state.qvel
    data.act[:] = state.act
    data.time = state.time
    mujoco.mj_forward(base.model, data)
    if state.step_count is not None:
        # The quadrotor's target and time limit run on its own step counter.
        base._step_count = state.step_count
