"""E1's offline probes: what ESA, its gradient control and its placebo would do at saved states.

A trained learner runs its stochastic policy on an env; the env executes the policy's own
sample, so every branch sees the same states and none steers the others. Beside it, one
ESA session per trust region kappa (``EsaConfig(trust_region=kappa)``: the shipped
section 1b law otherwise) probes the learner's critic with the same samples. At every
saved state each kappa gives three actions, each ``a_t`` plus a shift:

* ``esc``: ESA's ``v(t)``;
* ``placebo``: ``|v(t)|`` per dimension with a random sign vector drawn per episode
  (:class:`esa_client.common.controls.RandomDirections`);
* ``gradient``: a step of the same L2 size in units of sigma along the critic's action
  gradient at ``a_t``.

:func:`branch_returns` then scores every action by Monte-Carlo: from the saved state,
execute it, follow the stochastic policy for ``horizon`` steps, ``rollouts`` times with
common random numbers (the same noise for every branch), and average the discounted
returns. All envs of one state step together, so the policy runs once per step for all.

A learner is seen through :class:`LearnerView`: its samples, mean and sigma in ESA's units
(PPO: the Box scaled to [-1, 1], unbounded; SAC: the squashed [-1, 1]), its critic over
those units, and the env's action for a point in them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import torch as th

from esa_experiments.env_state import EnvState, restore_state, save_state

if TYPE_CHECKING:
    from esa_client.sb3 import ESAPPO
    from stable_baselines3 import SAC

KAPPAS = (0.25, 0.5, 1.0)
"""The trust regions E1 compares, in policy standard deviations."""
SHIFTS = ("esc", "gradient", "placebo")
GAMMA = 0.99
MAX_EPISODES_PER_STATE = 50
"""A capture gives up (an error, never a hang) after this many episodes per wanted state."""
_SMALLEST = float(np.finfo(np.float32).tiny)


def branch_names() -> list[str]:
    """The compared actions besides the sample: ``<shift> <kappa>``."""
    return [f"{shift} {kappa:g}" for kappa in KAPPAS for shift in SHIFTS]


@dataclass
class Draw:
    """One step's policy draw in ESA's units, each ``(D,)``."""

    sample: np.ndarray
    mean: np.ndarray
    sigma: np.ndarray


class LearnerView:
    """What E1 needs of a trained learner (subclasses: :class:`PPOView`, :class:`SACView`).

    Attributes:
        low: The ESA sessions' lower bounds (None: unbounded).
        high: Their upper bounds.
    """

    low: np.ndarray | None = None
    high: np.ndarray | None = None

    def draw(self, obs: np.ndarray, noise: th.Tensor) -> Draw:
        """The policy's sample for N(0, 1) ``noise``, its mean and sigma, at ``obs``."""
        raise NotImplementedError

    def critic(self, obs: np.ndarray, draw: Draw) -> Callable[[np.ndarray], np.ndarray]:
        """The critic at ``obs`` over ``(k, D)`` actions in ESA units, ``(k,)`` values."""
        raise NotImplementedError

    def gradient(self, obs: np.ndarray, draw: Draw) -> np.ndarray:
        """The critic's action gradient at the sample, in units of sigma, ``(D,)``."""
        raise NotImplementedError

    def to_env(self, actions: np.ndarray) -> np.ndarray:
        """Points in ESA units ``(..., D)`` as the env's actions."""
        raise NotImplementedError

    def act(self, obs: np.ndarray, noise: th.Tensor) -> np.ndarray:
        """The stochastic policy's env actions for a batch of observations ``(B, ...)``."""
        raise NotImplementedError


class PPOView(LearnerView):
    """An ESAPPO (trained with learning rate 0: plain PPO) and its critic ``esa_head``."""

    def __init__(self, model: ESAPPO) -> None:
        """Reads the Box scaling and the critic kind from the model."""
        self.model = model
        frame = model.esa_frame
        self.center, self.half_width = frame.center, frame.half_width
        self.box = frame.box

    def _gaussian(self, obs: np.ndarray) -> th.distributions.Normal:
        obs_t = th.as_tensor(obs, dtype=th.float32).reshape(-1, *obs.shape[-1:])
        with th.no_grad():
            dist = self.model.policy.get_distribution(obs_t)
        return cast(th.distributions.Normal, dist.distribution)

    def draw(self, obs: np.ndarray, noise: th.Tensor) -> Draw:
        """PPO's Gaussian sample, mean and std, scaled by the Box."""
        dist = self._gaussian(obs[None])
        sample = (dist.mean + dist.stddev * noise).numpy()[0].astype(np.float64)
        mean = dist.mean.numpy()[0].astype(np.float64)
        std = dist.stddev.numpy()[0].astype(np.float64)
        return Draw(
            (sample - self.center) / self.half_width,
            (mean - self.center) / self.half_width,
            np.maximum(std / self.half_width, _SMALLEST),
        )

    def _at(self, obs: np.ndarray, draw: Draw) -> Any:
        from esa_client.common.quadratic_head import CriticAtStep

        from esa_experiments.lab.ppo_arms import LinearHead

        m = self.model
        features = m._head_features(th.as_tensor(obs, dtype=th.float32)[None])
        low, high = m.esa_frame.low, m.esa_frame.high
        if isinstance(m, LinearHead):
            # The linear head as ESAPPO probes it: at the unclipped sample.
            low, high = np.full_like(low, -np.inf), np.full_like(high, np.inf)
        return CriticAtStep(m.esa_head, features, draw.mean[None], draw.sigma[None], low, high)

    def critic(self, obs: np.ndarray, draw: Draw) -> Callable[[np.ndarray], np.ndarray]:
        """ESAPPO's critic, evaluated as ESAPPO evaluates it."""
        at = self._at(obs, draw)

        def q_fn(actions: np.ndarray) -> np.ndarray:
            values: np.ndarray = at(np.atleast_2d(actions))
            return values

        return q_fn

    def gradient(self, obs: np.ndarray, draw: Draw) -> np.ndarray:
        """``dA/dz`` at the sample (units of sigma)."""
        grad: np.ndarray = self._at(obs, draw).gradient(draw.sample[None])[0]
        return grad

    def to_env(self, actions: np.ndarray) -> np.ndarray:
        """The Box's units, clipped as SB3 clips PPO's samples."""
        env: np.ndarray = np.clip(
            self.center + self.half_width * actions, self.box.low, self.box.high
        )
        return env

    def act(self, obs: np.ndarray, noise: th.Tensor) -> np.ndarray:
        """PPO's Gaussian, clipped to the Box."""
        dist = self._gaussian(obs)
        actions: np.ndarray = np.clip(
            (dist.mean + dist.stddev * noise).numpy(), self.box.low, self.box.high
        )
        return actions


class SACView(LearnerView):
    """A trained SAC; its critic is ESASAC's default probe, the target twin's mean."""

    def __init__(self, model: SAC) -> None:
        """Reads the Box from the model."""
        self.model = model
        self.box = cast(gym.spaces.Box, model.action_space)
        dim = self.box.shape[0]
        self.low, self.high = -np.ones(dim), np.ones(dim)

    def _params(self, obs: np.ndarray) -> tuple[th.Tensor, th.Tensor]:
        obs_t = th.as_tensor(obs, dtype=th.float32).reshape(-1, *obs.shape[-1:])
        with th.no_grad():
            mean, log_std, _ = self.model.actor.get_action_dist_params(obs_t)
        return mean, log_std.exp()

    def draw(self, obs: np.ndarray, noise: th.Tensor) -> Draw:
        """SAC's squashed sample, ``tanh(mu)`` and ESASAC's sigma ``(1 - tanh(mu)^2) std``."""
        mean, std = self._params(obs[None])
        sigma = ((1.0 - th.tanh(mean) ** 2) * std).clamp(min=_SMALLEST, max=1.0)
        return Draw(
            th.tanh(mean + std * noise).numpy()[0].astype(np.float64),
            th.tanh(mean).numpy()[0].astype(np.float64),
            sigma.numpy()[0].astype(np.float64),
        )

    def _q(self, obs: np.ndarray, actions: th.Tensor) -> th.Tensor:
        obs_t = th.as_tensor(obs, dtype=th.float32)[None].expand(len(actions), -1)
        return th.cat(self.model.critic_target(obs_t, actions), dim=1).mean(dim=1)

    def critic(self, obs: np.ndarray, draw: Draw) -> Callable[[np.ndarray], np.ndarray]:
        """The target twin's mean at ``obs``."""

        def q_fn(actions: np.ndarray) -> np.ndarray:
            with th.no_grad():
                points = th.as_tensor(np.atleast_2d(actions), dtype=th.float32)
                values: np.ndarray = self._q(obs, points).numpy().astype(np.float64)
            return values

        return q_fn

    def gradient(self, obs: np.ndarray, draw: Draw) -> np.ndarray:
        """``dQ/da * sigma`` at the sample."""
        a = th.as_tensor(draw.sample[None], dtype=th.float32).requires_grad_(True)
        (grad,) = th.autograd.grad(self._q(obs, a).sum(), a)
        scaled: np.ndarray = grad.numpy()[0].astype(np.float64) * draw.sigma
        return scaled

    def to_env(self, actions: np.ndarray) -> np.ndarray:
        """SB3's ``unscale_action`` of a squashed action."""
        squashed = np.clip(actions, -1.0, 1.0)
        env: np.ndarray = self.box.low + 0.5 * (squashed + 1.0) * (self.box.high - self.box.low)
        return env

    def act(self, obs: np.ndarray, noise: th.Tensor) -> np.ndarray:
        """SAC's squashed Gaussian, in the env's units."""
        mean, std = self._params(obs)
        return self.to_env(th.tanh(mean + std * noise).numpy())


@dataclass
class SavedState:
    """One saved state of E1.

    Attributes:
        state: The simulator state.
        sampled: ``a_t`` in ESA units.
        actions: branch name -> its action in ESA units.
        predicted: branch name -> the critic's ``Q(s, action) - Q(s, a_t)``.
        sizes: branch name -> the shift's mean ``|v| / sigma`` over the dimensions.
        noise_cosine: per kappa, ``cos(v, mu - a_t)`` of ESA's shift (NaN for v = 0).
    """

    state: EnvState
    sampled: np.ndarray
    actions: dict[str, np.ndarray]
    predicted: dict[str, float]
    sizes: dict[str, float]
    noise_cosine: dict[str, float]


def capture(
    view: LearnerView, env: gym.Env, states: int, *, save_every: int, warmup: int, seed: int
) -> list[SavedState]:
    """Runs the learner's policy on ``env`` with one ESA session per kappa until ``states``."""
    from esa_client import EsaClient, EsaConfig
    from esa_client.common.controls import RandomDirections

    box = cast(gym.spaces.Box, env.action_space)
    dim = box.shape[0]
    dt = float(env.unwrapped.dt)  # type: ignore[attr-defined]
    client = EsaClient.in_process()
    sessions = [
        client.create_session(
            EsaConfig(trust_region=kappa).session_config(dim, dt, view.low, view.high)
        )
        for kappa in KAPPAS
    ]
    paired = EsaConfig().paired_response
    placebo = RandomDirections(1, dim, seed)
    low = -np.inf if view.low is None else view.low
    high = np.inf if view.high is None else view.high
    generator = th.Generator().manual_seed(seed)
    saved: list[SavedState] = []
    episode = 0
    try:
        while len(saved) < states:
            if episode >= MAX_EPISODES_PER_STATE * states:
                raise RuntimeError(
                    f"expected {states} states within {episode} episodes, got {len(saved)}: "
                    f"the policy's episodes end before ESA has run {warmup} steps"
                )
            obs, _ = env.reset(seed=seed + episode)
            episode += 1
            t, done = 0, False
            while not done and len(saved) < states:
                draw = view.draw(obs, th.randn((1, dim), generator=generator))
                q_fn = view.critic(obs, draw)
                direction = view.gradient(obs, draw)
                norm = float(np.linalg.norm(direction))
                unit = direction / norm if norm > 0 else direction
                placebo.start(np.array([t == 0]))
                actions: dict[str, np.ndarray] = {}
                cosines: dict[str, float] = {}
                for kappa, session in zip(KAPPAS, sessions, strict=True):
                    probe, applied = session.probe_applied(
                        draw.sample, episode_start=t == 0, action_scale=draw.sigma
                    )
                    q = q_fn(np.stack([probe, applied]))
                    session.report(float(q[0]), q_reference=float(q[1]) if paired else None)
                    v = applied - draw.sample
                    size = float(np.linalg.norm(v / draw.sigma))
                    actions[f"esc {kappa:g}"] = applied
                    actions[f"placebo {kappa:g}"] = np.clip(
                        draw.sample + np.abs(v) * placebo.signs[0], low, high
                    )
                    actions[f"gradient {kappa:g}"] = np.clip(
                        draw.sample + size * draw.sigma * unit, low, high
                    )
                    noise = draw.mean - draw.sample
                    denominator = float(np.linalg.norm(v) * np.linalg.norm(noise))
                    cosines[f"{kappa:g}"] = (
                        float(v @ noise) / denominator if denominator > 0 else float("nan")
                    )
                if t >= warmup and t % save_every == 0:
                    names = list(actions)
                    q = q_fn(np.stack([draw.sample, *actions.values()]))
                    saved.append(
                        SavedState(
                            state=save_state(env),
                            sampled=draw.sample,
                            actions=actions,
                            predicted={n: float(q[i + 1] - q[0]) for i, n in enumerate(names)},
                            sizes={
                                n: float(np.mean(np.abs(actions[n] - draw.sample) / draw.sigma))
                                for n in names
                            },
                            noise_cosine=cosines,
                        )
                    )
                obs, _, terminated, truncated, _ = env.step(view.to_env(draw.sample))
                done = terminated or truncated
                t += 1
    finally:
        for session in sessions:
            session.close()
        client.close()
    return saved


def branch_returns(
    view: LearnerView,
    envs: list[gym.Env],
    saved: SavedState,
    first_actions: np.ndarray,
    *,
    rollouts: int,
    horizon: int,
    seed: int,
) -> np.ndarray:
    """Mean discounted Monte-Carlo return of each of ``B`` first actions from one state.

    Args:
        view: The learner whose stochastic policy the rollouts follow.
        envs: ``B * rollouts`` envs of the task (their state is overwritten).
        saved: The state to branch from.
        first_actions: ``(B, D)`` actions in ESA units, executed first.
        rollouts: Rollouts per branch; rollout ``m`` draws the same noise in every branch.
        horizon: Steps per rollout, the first action's included.
        seed: Seed of the rollouts' noise (common to the branches).

    Returns:
        ``(B,)`` mean discounted returns.
    """
    branches, dim = first_actions.shape
    if len(envs) != branches * rollouts:
        raise ValueError(f"expected {branches * rollouts} envs, got {len(envs)}")
    noise = th.stack(
        [
            th.randn((horizon, dim), generator=th.Generator().manual_seed(seed + m))
            for m in range(rollouts)
        ]
    )
    totals = np.zeros(len(envs))
    alive = np.ones(len(envs), dtype=bool)
    obs: list[np.ndarray | None] = [None] * len(envs)
    env_actions = view.to_env(first_actions)
    for k, env in enumerate(envs):
        restore_state(env, saved.state)
        obs[k], reward, terminated, _, _ = env.unwrapped.step(env_actions[k // rollouts])
        totals[k] = float(reward)
        alive[k] = not terminated
    discount = GAMMA
    rollout_of = np.arange(len(envs)) % rollouts
    for h in range(1, horizon):
        live = np.flatnonzero(alive)
        if live.size == 0:
            break
        batch = np.stack([obs[k] for k in live])  # type: ignore[misc]
        actions = view.act(batch, noise[rollout_of[live], h])
        for k, action in zip(live.tolist(), actions, strict=True):
            obs[k], reward, terminated, _, _ = envs[k].unwrapped.step(action)
            totals[k] += discount * float(reward)
            alive[k] = not terminated
        discount *= GAMMA
    means: np.ndarray = totals.reshape(branches, rollouts).mean(axis=1)
    return means
