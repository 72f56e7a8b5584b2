"""PPO with ESA, cleanrl style: one file, a dataclass of arguments, gymnasium vector envs.

cleanrl's ``ppo_continuous_action.py`` plus what ESA needs of an on-policy learner (as
``ESAPPO`` does it): PPO has no Q-network, so a small head quadratic in
``z = (a - mu(s)) / sigma``, ``A = w(s) . z + sum_j u_j(s) (z_j^2 - 1)`` with ``u <= 0``
(``esa_client.common.quadratic_head``), is fitted on each rollout's GAE advantages and is the
critic ESA probes: it has a maximum for ESA to seek. All envs in one call per step
(``EsaVectorWrapper``). The rollout stores
the executed action ``a_t + v(t)`` (``info["esa_action"]``) with ``log pi_old(a_t)``, its
behaviour log-probability, so the PPO ratio stays an importance ratio.

Needs the ``sb3`` extra (for torch and gymnasium) and tyro, which reads the command line;
MuJoCo envs such as InvertedPendulum-v5 also need ``gymnasium[mujoco]``. ESA runs in this
process: no esa-server. From a clone (esa is not on PyPI yet; once it is,
``pip install "esa-client[sb3]" tyro``)::

    pip install -e "./client-py[sb3]" tyro "gymnasium[mujoco]"

    python client-py/examples/cleanrl_ppo_esa.py --env-id InvertedPendulum-v5
    python client-py/examples/cleanrl_ppo_esa.py --ci        # a few hundred steps (CI)
    python client-py/examples/cleanrl_ppo_esa.py --no-esa    # plain PPO, for comparison
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import tyro
from torch import nn, optim

from esa_client import EsaConfig
from esa_client.common.quadratic_head import QuadraticHead
from esa_client.vector_wrapper import EsaVectorWrapper


@dataclass
class Args:
    """PPO with ESA on a gymnasium env (``--total-timesteps 1000``, ``--no-esa``, ...)."""

    env_id: str = "Pendulum-v1"
    """Gymnasium id of the env."""
    seed: int = 1
    """Seed of python, numpy, torch and the envs."""
    num_envs: int = 4
    """Parallel envs of the vector env."""
    total_timesteps: int = 100_000
    """Env steps of the whole run, over all envs."""
    num_steps: int = 512
    """Steps per env in each rollout."""
    learning_rate: float = 3e-4
    """Adam learning rate of the policy and value networks."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 0.95
    """Lambda of the generalized advantage estimate."""
    num_minibatches: int = 32
    """Minibatches per epoch of the PPO update."""
    update_epochs: int = 10
    """Epochs of the PPO update per rollout."""
    clip_coef: float = 0.2
    """Clipping range of the PPO ratio."""
    ent_coef: float = 0.0
    """Weight of the entropy bonus."""
    vf_coef: float = 0.5
    """Weight of the value loss."""
    max_grad_norm: float = 0.5
    """Global norm the gradients are clipped to."""
    esa: bool = True
    """Improve the actions with ESA."""
    head_epochs: int = 5
    """Epochs of the quadratic head's fit per rollout."""
    ci: bool = False
    """A tiny budget for CI: two rollouts of 2 x 128 steps."""


def parse_args(argv: list[str] | None = None) -> Args:
    """Reads ``Args`` from ``argv`` (default: the command line); ``--ci`` shrinks the budget."""
    args = tyro.cli(Args, args=argv)
    if args.ci:
        args.num_envs, args.num_steps, args.total_timesteps = 2, 128, 512
        args.num_minibatches, args.update_epochs = 4, 2
    return args


def layer(n_in: int, n_out: int, std: float = np.sqrt(2)) -> nn.Linear:
    linear = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(linear.weight, std)
    nn.init.constant_(linear.bias, 0.0)
    return linear


class Agent(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int) -> None:
        super().__init__()
        self.critic = nn.Sequential(
            layer(obs_dim, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, 1, 1.0)
        )
        self.actor_mean = nn.Sequential(
            layer(obs_dim, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, act_dim, 0.01)
        )
        self.actor_logstd = nn.Parameter(torch.zeros(1, act_dim))
        # ESA's critic: a head quadratic in the policy-normalized action, fitted on GAE
        # advantages.
        self.adv_head = QuadraticHead(obs_dim, act_dim)

    def dist(self, obs: torch.Tensor) -> torch.distributions.Normal:
        mean = self.actor_mean(obs)
        return torch.distributions.Normal(mean, self.actor_logstd.expand_as(mean).exp())

    def advantage(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        d = self.dist(obs)
        advantage: torch.Tensor = self.adv_head(obs, (act - d.loc.detach()) / d.scale.detach())
        return advantage


def main(args: Args) -> dict[str, Any]:
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    envs: Any = gym.make_vec(
        args.env_id,
        num_envs=args.num_envs,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP},
    )
    envs = gym.wrappers.vector.RecordEpisodeStatistics(envs)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))
    agent = Agent(obs_dim, act_dim)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    head_optimizer = optim.Adam(agent.adv_head.parameters(), lr=1e-3)

    if args.esa:

        @torch.no_grad()
        def q_fn(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
            """The quadratic head at M pairs: one call for all envs."""
            o = torch.as_tensor(obs, dtype=torch.float32)
            return agent.advantage(o, torch.as_tensor(actions, dtype=torch.float32)).numpy()

        envs = EsaVectorWrapper(envs, q_fn, esa=EsaConfig())

    n, steps = args.num_envs, args.num_steps
    obs_buf = torch.zeros((steps, n, obs_dim))
    act_buf = torch.zeros((steps, n, act_dim))
    logp_buf, rew_buf, done_buf, val_buf = (torch.zeros((steps, n)) for _ in range(4))
    returns: list[float] = []
    start = time.time()
    next_obs = torch.as_tensor(envs.reset(seed=args.seed)[0], dtype=torch.float32)
    next_done = torch.zeros(n)
    for _ in range(max(1, args.total_timesteps // (n * steps))):
        for t in range(steps):
            obs_buf[t], done_buf[t] = next_obs, next_done
            with torch.no_grad():
                d = agent.dist(next_obs)
                sampled = d.sample()
                logp_buf[t] = d.log_prob(sampled).sum(1)  # log pi_old(a_t)
                val_buf[t] = agent.critic(next_obs).flatten()
            if args.esa:
                envs.action_scale = d.scale.numpy()
            clipped = np.clip(
                sampled.numpy(), envs.single_action_space.low, envs.single_action_space.high
            )
            obs, reward, terminations, truncations, infos = envs.step(clipped)
            # The executed action a_t + v(t), stored unclipped by the policy's own clip.
            executed = (
                infos["esa_action"] + (sampled.numpy() - clipped) if args.esa else sampled.numpy()
            )
            act_buf[t] = torch.as_tensor(executed, dtype=torch.float32)
            rew_buf[t] = torch.as_tensor(reward, dtype=torch.float32)
            next_obs = torch.as_tensor(obs, dtype=torch.float32)
            next_done = torch.as_tensor(
                np.logical_or(terminations, truncations), dtype=torch.float32
            )
            for i in np.flatnonzero(infos.get("_episode", [])):
                returns.append(float(infos["episode"]["r"][i]))

        with torch.no_grad():
            next_value = agent.critic(next_obs).flatten()
            adv = torch.zeros_like(rew_buf)
            last = torch.zeros(n)
            for t in reversed(range(steps)):
                not_done = 1.0 - (next_done if t == steps - 1 else done_buf[t + 1])
                value_next = next_value if t == steps - 1 else val_buf[t + 1]
                delta = rew_buf[t] + args.gamma * value_next * not_done - val_buf[t]
                last = delta + args.gamma * args.gae_lambda * not_done * last
                adv[t] = last
            ret = adv + val_buf

        b_obs, b_act = obs_buf.reshape(-1, obs_dim), act_buf.reshape(-1, act_dim)
        b_logp, b_adv, b_ret = logp_buf.reshape(-1), adv.reshape(-1), ret.reshape(-1)
        size = b_obs.shape[0]
        minibatch = size // args.num_minibatches
        for _ in range(args.update_epochs):
            for mb in torch.randperm(size).split(minibatch):
                d = agent.dist(b_obs[mb])
                ratio = (d.log_prob(b_act[mb]).sum(1) - b_logp[mb]).exp()
                mb_adv = (b_adv[mb] - b_adv[mb].mean()) / (b_adv[mb].std() + 1e-8)
                pg_loss = torch.max(
                    -mb_adv * ratio, -mb_adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)
                ).mean()
                v_loss = 0.5 * (agent.critic(b_obs[mb]).flatten() - b_ret[mb]).pow(2).mean()
                loss = pg_loss - args.ent_coef * d.entropy().sum(1).mean() + args.vf_coef * v_loss
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
        if args.esa:  # the head ESA probes, fitted on this rollout's advantages
            for _ in range(args.head_epochs):
                for mb in torch.randperm(size).split(minibatch):
                    head_loss = (agent.advantage(b_obs[mb], b_act[mb]) - b_adv[mb]).pow(2).mean()
                    head_optimizer.zero_grad()
                    head_loss.backward()
                    head_optimizer.step()
    envs.close()
    result = {
        "steps": args.total_timesteps,
        "episodes": len(returns),
        "mean_return_last_10": float(np.mean(returns[-10:])) if returns else float("nan"),
        "seconds": time.time() - start,
    }
    print(result)
    return result


if __name__ == "__main__":
    main(parse_args())
