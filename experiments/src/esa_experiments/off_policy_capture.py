"""Saved MuJoCo states with SAC's sampled action and the shifts ESA and the gradient would make.

Runs a trained SAC policy (stochastic, as in training) on one env. Beside it, one ESA
session per trust region of ``TRUST_REGIONS`` (policy standard deviations; the shipped
``EsaConfig()`` otherwise) probes the model's target twin mean, as ``ESASAC`` does, with
the same samples. The env executes the policy's own sample, so the states are SAC's own
and no branch steers the others. Every ``save_every``-th step (after the first 10 of an
episode, so that v has had time to move) it keeps the simulator state, ``a_t`` and, per
trust region, ESA's action ``a_t + v`` and a step of the same size (in units of sigma)
along the critic's action gradient at ``a_t``: ESC's claim over the analytic gradient
(the paper's Section III) is tested at equal shift size.

All actions are in SAC's squashed space [-1, 1]; sigma is ESASAC's action scale,
``min((1 - tanh(mu)^2) std, 1)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import gymnasium as gym
import numpy as np
import torch as th

if TYPE_CHECKING:
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
    from stable_baselines3 import SAC

TRUST_REGIONS = (0.055, 0.25, 0.5, 1.0)
"""The compared bounds: the shipped PPO default and three wider ones, in policy stds."""

_SMALLEST = float(np.finfo(np.float32).tiny)

PolicyAction = Callable[[np.ndarray, th.Tensor], np.ndarray]
"""The policy the Monte-Carlo rollouts follow: (observation, N(0, 1) noise) -> env action."""


def branch_names() -> list[str]:
    """The compared actions besides the sample: ``esa <bound>`` and ``grad <bound>``."""
    return [f"{kind} {bound:g}" for bound in TRUST_REGIONS for kind in ("esa", "grad")]


@dataclass(frozen=True)
class OffPolicyState:
    """One saved state.

    Attributes:
        qpos: MuJoCo positions.
        qvel: MuJoCo velocities.
        sampled: the policy's sample a_t (squashed space).
        actions: branch name -> the compared action (squashed space, clipped to [-1, 1]).
        predicted: branch name -> the critic's Q(s, action) - Q(s, a_t).
        sizes: branch name -> the shift's mean |v| / sigma over the action dimensions.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    sampled: np.ndarray
    actions: dict[str, np.ndarray]
    predicted: dict[str, float]
    sizes: dict[str, float]


def squashed_gaussian(model: SAC, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """SAC's pre-squash mean and std at ``obs``, and ESASAC's action scale sigma."""
    mean, log_std, _ = model.actor.get_action_dist_params(obs)
    std = log_std.exp()
    sigma = ((1.0 - th.tanh(mean) ** 2) * std).clamp(min=_SMALLEST, max=1.0)
    return mean, std, sigma


def target_mean_q(model: SAC, obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
    """The target twin mean, ESASAC's default probed critic, shape ``(batch,)``."""
    return th.cat(model.critic_target(obs.expand(len(actions), -1), actions), dim=1).mean(dim=1)


def gradient_shift(model: SAC, obs: th.Tensor, action: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The critic's action gradient at ``action`` as a unit step in units of sigma.

    Returns ``u`` with ``||u||_2 = 1``: the shift ``s * sigma * u`` has size ``s`` sigma.
    """
    a = th.as_tensor(action[None], dtype=th.float32).requires_grad_(True)
    target_mean_q(model, obs, a).sum().backward()
    assert a.grad is not None  # set by backward
    scaled: np.ndarray = a.grad.numpy()[0].astype(np.float64) * sigma
    norm = float(np.linalg.norm(scaled))
    return scaled / norm if norm > 0 else scaled


def capture_off_policy_states(
    model: SAC, env: gym.Env, states: int, *, save_every: int, seed: int
) -> list[OffPolicyState]:
    """Runs ``model`` (a trained SAC) with the ESA sessions until ``states`` are saved."""
    from esa_client import EsaClient, EsaConfig

    base = cast("MujocoEnv", env.unwrapped)  # the ground-truth tasks are MuJoCo envs
    box = cast(gym.spaces.Box, env.action_space)
    dim = box.shape[0]
    ones = np.ones(dim)
    client = EsaClient.in_process()
    esa = EsaConfig()
    sessions = [
        client.create_session(EsaConfig(trust_region=k).session_config(dim, base.dt, -ones, ones))
        for k in TRUST_REGIONS
    ]
    generator = th.Generator().manual_seed(seed)
    saved: list[OffPolicyState] = []
    episode = 0
    try:
        while len(saved) < states:
            obs, _ = env.reset(seed=seed + episode)
            episode += 1
            t, done = 0, False
            while not done and len(saved) < states:
                obs_t = th.as_tensor(obs, dtype=th.float32)[None]
                with th.no_grad():
                    mean, std, sigma_t = squashed_gaussian(model, obs_t)
                    noise = th.randn(mean.shape, generator=generator)
                    sampled = th.tanh(mean + std * noise).numpy()[0].astype(np.float64)
                sigma = sigma_t.numpy()[0].astype(np.float64)
                direction = gradient_shift(model, obs_t, sampled, sigma)
                actions: dict[str, np.ndarray] = {}
                for bound, session in zip(TRUST_REGIONS, sessions, strict=True):
                    probe, applied = session.probe_applied(
                        sampled, episode_start=t == 0, action_scale=sigma
                    )
                    with th.no_grad():
                        points = th.as_tensor(np.stack([probe, applied]), dtype=th.float32)
                        q = target_mean_q(model, obs_t, points).numpy()
                    session.report(
                        float(q[0]), q_reference=float(q[1]) if esa.paired_response else None
                    )
                    size = float(np.linalg.norm((applied - sampled) / sigma))
                    actions[f"esa {bound:g}"] = applied
                    actions[f"grad {bound:g}"] = np.clip(sampled + size * sigma * direction, -1, 1)
                if t >= 10 and t % save_every == 0:
                    names = list(actions)
                    with th.no_grad():
                        points = th.as_tensor(
                            np.stack([sampled, *actions.values()]), dtype=th.float32
                        )
                        q = target_mean_q(model, obs_t, points).numpy().astype(np.float64)
                    saved.append(
                        OffPolicyState(
                            qpos=base.data.qpos.copy(),
                            qvel=base.data.qvel.copy(),
                            sampled=sampled,
                            actions=actions,
                            predicted={n: float(q[i + 1] - q[0]) for i, n in enumerate(names)},
                            sizes={
                                n: float(np.mean(np.abs(actions[n] - sampled) / sigma))
                                for n in names
                            },
                        )
                    )
                obs, _, terminated, truncated, _ = env.step(unscale(box, sampled))
                done = terminated or truncated
                t += 1
    finally:
        for session in sessions:
            session.close()
        client.close()
    return saved


def unscale(box: gym.spaces.Box, squashed: np.ndarray) -> np.ndarray:
    """A squashed action in [-1, 1] in the env's units (SB3's ``unscale_action``)."""
    return box.low + 0.5 * (squashed + 1.0) * (box.high - box.low)


def sac_policy_action(model: SAC, box: gym.spaces.Box) -> PolicyAction:
    """SAC's stochastic policy as the rollouts after the compared action follow it."""

    def act(obs: np.ndarray, noise: th.Tensor) -> np.ndarray:
        with th.no_grad():
            mean, std, _ = squashed_gaussian(model, th.as_tensor(obs, dtype=th.float32)[None])
            return unscale(box, th.tanh(mean + std * noise).numpy()[0])

    return act
