"""SAC with ESA, cleanrl style: one file, a dataclass of arguments, gymnasium vector envs.

cleanrl's ``sac_continuous_action.py`` with three ESA lines: the vector env is wrapped in
``EsaVectorWrapper`` (one critic call per step for all envs: the mean of the target twins at
the probes and at the applied actions), the policy's standard deviation is the action scale,
and the replay buffer stores ``info["esa_action"]``, the action the envs executed.

Needs the ``sb3`` extra (for torch and gymnasium) and tyro, which reads the command line;
MuJoCo envs such as InvertedPendulum-v5 also need ``gymnasium[mujoco]``. ESA runs in this
process: no esa-server. From a clone (esa is not on PyPI yet; once it is,
``pip install "esa-client[sb3]" tyro``)::

    pip install -e "./client-py[sb3]" tyro

    python client-py/examples/cleanrl_sac_esa.py --env-id Pendulum-v1 --total-timesteps 20000
    python client-py/examples/cleanrl_sac_esa.py --ci        # a few hundred steps (CI)
    python client-py/examples/cleanrl_sac_esa.py --no-esa    # plain SAC, for comparison
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
import tyro
from torch import nn, optim

from esa_client import EsaConfig
from esa_client.vector_wrapper import EsaVectorWrapper


@dataclass
class Args:
    """SAC with ESA on a gymnasium env (``--total-timesteps 1000``, ``--no-esa``, ...)."""

    env_id: str = "Pendulum-v1"
    """Gymnasium id of the env."""
    seed: int = 1
    """Seed of python, numpy, torch and the envs."""
    num_envs: int = 2
    """Parallel envs of the vector env."""
    total_timesteps: int = 20_000
    """Env steps of the whole run, over all envs."""
    buffer_size: int = 100_000
    """Transitions the replay buffer keeps."""
    gamma: float = 0.99
    """Discount factor."""
    tau: float = 0.005
    """Soft-update rate of the target critics."""
    batch_size: int = 256
    """Transitions per gradient step."""
    learning_starts: int = 1_000
    """Random-action steps before learning starts."""
    policy_lr: float = 3e-4
    """Adam learning rate of the policy."""
    q_lr: float = 1e-3
    """Adam learning rate of the critics."""
    alpha: float = 0.2
    """Entropy coefficient (fixed)."""
    esa: bool = True
    """Improve the actions with ESA."""
    esa_amplitude: float = 0.1
    """Amplitude K of ESA's probe (``EsaConfig.amplitude``)."""
    ci: bool = False
    """A tiny budget for CI: 500 steps (one episode per env), learning from step 100."""


def parse_args(argv: list[str] | None = None) -> Args:
    """Reads ``Args`` from ``argv`` (default: the command line); ``--ci`` shrinks the budget."""
    args = tyro.cli(Args, args=argv)
    if args.ci:
        args.total_timesteps, args.learning_starts, args.batch_size = 500, 100, 32
    return args


class SoftQNetwork(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
            nn.Linear(256, 1),
        )  # fmt: skip

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, act], 1))


class Actor(nn.Module):
    def __init__(self, obs_dim: int, space: gym.spaces.Box) -> None:
        super().__init__()
        self.trunk = nn.Sequential(
            nn.Linear(obs_dim, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU()
        )
        act_dim = int(np.prod(space.shape))
        self.mean, self.log_std = nn.Linear(256, act_dim), nn.Linear(256, act_dim)
        self.register_buffer(
            "scale", torch.tensor((space.high - space.low) / 2, dtype=torch.float32)
        )
        self.register_buffer(
            "bias", torch.tensor((space.high + space.low) / 2, dtype=torch.float32)
        )

    def get_action(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A squashed sample, its log-probability, and the std in action units."""
        h = self.trunk(obs)
        mean, log_std = self.mean(h), torch.tanh(self.log_std(h))
        log_std = -5 + 0.5 * 7 * (log_std + 1)  # in [-5, 2]
        std = log_std.exp()
        normal = torch.distributions.Normal(mean, std)
        x = normal.rsample()
        y = torch.tanh(x)
        action = y * self.scale + self.bias
        log_prob = normal.log_prob(x) - torch.log(self.scale * (1 - y.pow(2)) + 1e-6)
        return action, log_prob.sum(1, keepdim=True), std * self.scale


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
    space = envs.single_action_space
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(space.shape))
    actor = Actor(obs_dim, space)
    qf1, qf2 = SoftQNetwork(obs_dim, act_dim), SoftQNetwork(obs_dim, act_dim)
    qf1_target, qf2_target = SoftQNetwork(obs_dim, act_dim), SoftQNetwork(obs_dim, act_dim)
    qf1_target.load_state_dict(qf1.state_dict())
    qf2_target.load_state_dict(qf2.state_dict())
    q_optimizer = optim.Adam(list(qf1.parameters()) + list(qf2.parameters()), lr=args.q_lr)
    actor_optimizer = optim.Adam(actor.parameters(), lr=args.policy_lr)

    if args.esa:

        @torch.no_grad()
        def q_fn(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
            """The mean of the target twins at M pairs: one call for all envs."""
            o = torch.as_tensor(obs, dtype=torch.float32)
            a = torch.as_tensor(actions, dtype=torch.float32)
            return ((qf1_target(o, a) + qf2_target(o, a)) / 2).squeeze(1).numpy()

        envs = EsaVectorWrapper(envs, q_fn, esa=EsaConfig.off_policy(amplitude=args.esa_amplitude))

    n = args.num_envs
    buffer = {
        "obs": np.zeros((args.buffer_size, obs_dim), np.float32),
        "next_obs": np.zeros((args.buffer_size, obs_dim), np.float32),
        "actions": np.zeros((args.buffer_size, act_dim), np.float32),
        "rewards": np.zeros(args.buffer_size, np.float32),
        "dones": np.zeros(args.buffer_size, np.float32),
    }
    size, returns, start = 0, [], time.time()
    obs, _ = envs.reset(seed=args.seed)
    for global_step in range(0, args.total_timesteps, n):
        with torch.no_grad():
            actions, _, std = actor.get_action(torch.as_tensor(obs, dtype=torch.float32))
        if global_step < args.learning_starts:
            actions = torch.as_tensor(np.stack([space.sample() for _ in range(n)]))
        if args.esa:
            envs.action_scale = std.numpy()
        next_obs, rewards, terminations, truncations, infos = envs.step(actions.numpy())
        executed = infos.get("esa_action", actions.numpy())  # what the envs executed
        real_next_obs = next_obs.copy()
        for i in np.flatnonzero(np.logical_or(terminations, truncations)):
            real_next_obs[i] = infos["final_obs"][i]
            returns.append(float(infos["episode"]["r"][i]))
        for i in range(n):
            j = size % args.buffer_size
            buffer["obs"][j], buffer["next_obs"][j] = obs[i], real_next_obs[i]
            buffer["actions"][j], buffer["rewards"][j] = executed[i], rewards[i]
            buffer["dones"][j] = terminations[i]
            size += 1
        obs = next_obs

        if global_step >= args.learning_starts:
            idx = np.random.randint(0, min(size, args.buffer_size), args.batch_size)
            b = {key: torch.as_tensor(value[idx]) for key, value in buffer.items()}
            with torch.no_grad():
                next_a, next_log_pi, _ = actor.get_action(b["next_obs"])
                target = torch.min(
                    qf1_target(b["next_obs"], next_a), qf2_target(b["next_obs"], next_a)
                )
                target = target - args.alpha * next_log_pi
                y = b["rewards"] + (1 - b["dones"]) * args.gamma * target.view(-1)
            q_loss = F.mse_loss(qf1(b["obs"], b["actions"]).view(-1), y) + F.mse_loss(
                qf2(b["obs"], b["actions"]).view(-1), y
            )
            q_optimizer.zero_grad()
            q_loss.backward()
            q_optimizer.step()
            pi, log_pi, _ = actor.get_action(b["obs"])
            actor_loss = (
                args.alpha * log_pi - torch.min(qf1(b["obs"], pi), qf2(b["obs"], pi))
            ).mean()
            actor_optimizer.zero_grad()
            actor_loss.backward()
            actor_optimizer.step()
            with torch.no_grad():
                for net, target_net in ((qf1, qf1_target), (qf2, qf2_target)):
                    for p, tp in zip(net.parameters(), target_net.parameters(), strict=True):
                        tp.mul_(1 - args.tau).add_(args.tau * p)
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
