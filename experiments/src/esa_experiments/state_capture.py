"""Saved MuJoCo states with the sampled action and ESA's shifted action (ground-truth check).

Runs a trained ``ESAPPO`` on one env with ESA switched on whatever its gate says: one
session on the model's server, the model's own advantage head as the critic, the same
paired and normalized law the model trains with. Every ``save_every``-th step (after the
first 10 of an episode, so that v has had time to move) it keeps the simulator state,
``a_t`` and ``a_t + v(t)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch as th


@dataclass(frozen=True)
class SavedState:
    """One saved state.

    Attributes:
        qpos: MuJoCo positions.
        qvel: MuJoCo velocities.
        sampled: the policy's sample a_t (env units, unclipped).
        shifted: ESA's action a_t + v(t) (env units, unclipped).
        predicted: the head's A(s, a_t + v(t)) - A(s, a_t).
        shift_over_std: mean |v| / sigma over the action dimensions.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    sampled: np.ndarray
    shifted: np.ndarray
    predicted: float
    shift_over_std: float


def capture_states(
    model: object, env: gym.Env, states: int, *, save_every: int, seed: int
) -> list[SavedState]:
    """Runs ``model`` (a trained ESAPPO) with ESA on ``env`` until ``states`` are saved."""
    m: object = model
    config = m._esa_session_config()  # type: ignore[attr-defined]
    session = m._esa_runtime().client.create_session(config)  # type: ignore[attr-defined]
    center, half_width = m._esa_scaling()  # type: ignore[attr-defined]
    paired = m.esa.paired_response  # type: ignore[attr-defined]
    generator = th.Generator().manual_seed(seed)
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
                    dist = m.policy.get_distribution(obs_t).distribution  # type: ignore[attr-defined]
                    mean, std = dist.mean, dist.stddev
                    sampled = (mean + std * th.randn(mean.shape, generator=generator)).numpy()
                scaled = (sampled - center) / half_width
                sigma = std.numpy() / half_width
                probe, applied = session.probe_applied(
                    scaled[0], episode_start=t == 0, action_scale=sigma[0]
                )
                q_fn = m._esa_q_at(m._head_features(obs_t), mean, std)  # type: ignore[attr-defined]
                q = q_fn(np.stack([probe, applied, scaled[0]]))
                session.report(q[0], q_reference=q[1] if paired else None)
                shifted = sampled[0] + (applied - scaled[0]) * half_width
                if t >= 10 and t % save_every == 0:
                    data = env.unwrapped.data  # type: ignore[attr-defined]
                    saved.append(
                        SavedState(
                            qpos=data.qpos.copy(),
                            qvel=data.qvel.copy(),
                            sampled=sampled[0].copy(),
                            shifted=shifted,
                            predicted=float(q[1] - q[2]),
                            shift_over_std=float(np.mean(np.abs(applied - scaled[0]) / sigma[0])),
                        )
                    )
                low, high = env.action_space.low, env.action_space.high
                obs, _, terminated, truncated, _ = env.step(np.clip(shifted, low, high))
                done = terminated or truncated
                t += 1
    finally:
        session.close()
    return saved
