"""Saved MuJoCo states with the sampled action and ESA's shifted action (ground-truth check).

Runs a trained ``ESAPPO`` on one env with ESA switched on whatever its gate says: a
session on the model's server with the model's own settings, the model's advantage head
as the critic. A second session, probed with the same samples, has a trust region of
``WIDE_TRUST_REGION`` policy standard deviations: the shift ESA would take if it were
allowed to, which shows ESA's direction even where the shipped bound keeps it small. The
env executes the first session's action. Every ``save_every``-th step (after the first 10
of an episode, so that v has had time to move) it keeps the simulator state, ``a_t`` and
both shifted actions.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import gymnasium as gym
import numpy as np
import torch as th

if TYPE_CHECKING:
    from esa_client.sb3 import ESAPPO
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.policies import ActorCriticPolicy

WIDE_TRUST_REGION = 1.0


@dataclass(frozen=True)
class SavedState:
    """One saved state.

    Attributes:
        qpos: MuJoCo positions.
        qvel: MuJoCo velocities.
        sampled: the policy's sample a_t (env units, unclipped).
        shifted: ESA's action a_t + v(t) with the model's settings (env units, unclipped).
        wide: ESA's action with a trust region of ``WIDE_TRUST_REGION``.
        predicted: the head's A(s, shifted) - A(s, a_t).
        predicted_wide: the head's A(s, wide) - A(s, a_t).
        shift_over_std: mean |v| / sigma over the action dimensions (model's settings).
        wide_shift_over_std: the same for ``wide``.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    sampled: np.ndarray
    shifted: np.ndarray
    wide: np.ndarray
    predicted: float
    predicted_wide: float
    shift_over_std: float
    wide_shift_over_std: float


def capture_states(
    model: ESAPPO, env: gym.Env, states: int, *, save_every: int, seed: int
) -> list[SavedState]:
    """Runs ``model`` (a trained ESAPPO) with ESA on ``env`` until ``states`` are saved."""
    from esa_client import LinearCritic

    m = model
    config = m._esa_session_config()
    wide_config = dataclasses.replace(config, trust_region=WIDE_TRUST_REGION)
    client = m._esa_runtime().client
    sessions = [client.create_session(config), client.create_session(wide_config)]
    center, half_width = m._esa_scaling()
    paired = m.esa.paired_response
    generator = th.Generator().manual_seed(seed)
    box = cast(gym.spaces.Box, env.action_space)  # the MuJoCo tasks' actions are a Box
    low, high = box.low, box.high
    saved: list[SavedState] = []
    episode = 0
    try:
        while len(saved) < states:
            obs, _ = env.reset(seed=seed + episode)
            episode += 1
            t, done = 0, False
            while not done and len(saved) < states:
                with th.no_grad():
                    obs_t = th.as_tensor(obs, dtype=th.float32)[None]
                    dist = gaussian(m, obs_t)
                    mean, std = dist.mean, dist.stddev
                    sampled = (mean + std * th.randn(mean.shape, generator=generator)).numpy()[0]
                scaled = (sampled - center) / half_width
                sigma = std.numpy()[0] / half_width
                q_fn = LinearCritic(
                    *m._esa_mlp().critic(m._step_features(obs_t), mean.numpy(), std.numpy())
                )
                shifts, gains = [], []
                for session in sessions:
                    probe, applied = session.probe_applied(
                        scaled, episode_start=t == 0, action_scale=sigma
                    )
                    q = q_fn(np.stack([probe, applied, scaled]))
                    session.report(q[0], q_reference=q[1] if paired else None)
                    shifts.append(applied - scaled)
                    gains.append(float(q[1] - q[2]))
                actions = [sampled + shift * half_width for shift in shifts]
                if t >= 10 and t % save_every == 0:
                    data = cast("MujocoEnv", env.unwrapped).data
                    saved.append(
                        SavedState(
                            qpos=data.qpos.copy(),
                            qvel=data.qvel.copy(),
                            sampled=sampled.copy(),
                            shifted=actions[0],
                            wide=actions[1],
                            predicted=gains[0],
                            predicted_wide=gains[1],
                            shift_over_std=float(np.mean(np.abs(shifts[0]) / sigma)),
                            wide_shift_over_std=float(np.mean(np.abs(shifts[1]) / sigma)),
                        )
                    )
                obs, _, terminated, truncated, _ = env.step(np.clip(actions[0], low, high))
                done = terminated or truncated
                t += 1
    finally:
        for session in sessions:
            session.close()
    return saved


def gaussian(model: BaseAlgorithm, obs: th.Tensor) -> th.distributions.Normal:
    """The torch Normal of a Box PPO policy at ``obs``.

    SB3 types ``Distribution.distribution`` for every kind of action space; a Box policy's
    (DiagGaussian, or gSDE) is a ``Normal``.
    """
    policy = cast("ActorCriticPolicy", model.policy)  # an on-policy (PPO) model's
    return cast(th.distributions.Normal, policy.get_distribution(obs).distribution)
