"""How well can a head learn which actions pay, from PPO's own rollouts? (ESAPPO's critic.)

Trains plain PPO (the campaign's settings: 4 envs, 64x64, 10 epochs, batch 64) and, at
every rollout end, scores several advantage-head designs on that rollout before fitting
them on it: the rank correlation between the head's ``A(s, a) - A(s, mu)`` and the GAE
advantages (ESAPPO's gate metric, out of sample). This measurement chose ESAPPO's head,
``A(s, a) = w(s) . (a - mu) / sigma`` on an observation trunk over 4 rollouts.

Usage (prints a table; the committed outputs are in results/advantage_head_quality/):

    python experiments/scripts/advantage_head_quality.py InvertedPendulum-v5 30720 256 0
    python experiments/scripts/advantage_head_quality.py Hopper-v5 60000 512 0
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
import torch as th
import tyro
from esa_client.common.quadratic_head import rank_correlation
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from torch import nn
from torch.nn import functional as F
from tyro.conf import Positional, arg


def mlp(inputs: int, hidden: int, outputs: int, layers: int) -> nn.Sequential:
    modules: list[nn.Module] = []
    width = inputs
    for _ in range(layers):
        modules += [nn.Linear(width, hidden), nn.Tanh()]
        width = hidden
    return nn.Sequential(*modules, nn.Linear(width, outputs))


@dataclass
class Batch:
    obs: th.Tensor
    actions: th.Tensor
    mean: th.Tensor
    std: th.Tensor
    target: th.Tensor


@dataclass
class Variant:
    """One head design.

    Attributes:
        name: label.
        features: ``latent`` (PPO's detached value latent) or ``obs`` (its own trunk).
        relative: feed ``z = (a - mu) / sigma`` instead of the raw action.
        replay: how many of the latest rollouts it is fitted on.
        layers: hidden layers.
        linear: ``A = w(s) . z`` instead of an MLP of (s, action).
    """

    name: str
    features: str
    relative: bool
    replay: int
    layers: int = 1
    linear: bool = False
    epochs: int = 10
    batch_size: int = 256
    net: nn.Module | None = None
    optimizer: th.optim.Optimizer | None = None
    data: list[Batch] = field(default_factory=list)
    scores: list[float] = field(default_factory=list)

    def inputs(self, model: PPO, obs: th.Tensor) -> th.Tensor:
        if self.features == "obs":
            return obs
        with th.no_grad():
            return model.policy.mlp_extractor.forward_critic(model.policy.extract_features(obs))

    def predict(self, x: th.Tensor, b: Batch, actions: th.Tensor) -> th.Tensor:
        z = (actions - b.mean) / b.std
        assert self.net is not None
        if self.linear:
            return (self.net(x) * z).sum(1)
        return self.net(th.cat([x, z if self.relative else actions], 1)).squeeze(1)

    def score(self, model: PPO, b: Batch) -> float:
        if self.net is None:
            return float("nan")
        x = self.inputs(model, b.obs)
        with th.no_grad():
            gain = self.predict(x, b, b.actions) - self.predict(x, b, b.mean)
        return rank_correlation(gain.numpy(), b.target.numpy())

    def fit(self, model: PPO, b: Batch, rng: np.random.Generator) -> None:
        self.data = [*self.data, b][-self.replay :]
        joined = Batch(*(th.cat([getattr(d, f) for d in self.data]) for f in Batch.__annotations__))
        x = self.inputs(model, joined.obs)
        if self.net is None:
            dim = joined.actions.shape[1]
            width = x.shape[1] if self.linear else x.shape[1] + dim
            with th.random.fork_rng(devices=[]):
                th.manual_seed(123)
                self.net = mlp(width, 64, dim if self.linear else 1, self.layers)
            self.optimizer = th.optim.Adam(self.net.parameters(), lr=1e-3)
        target = (joined.target - joined.target.mean()) / (joined.target.std() + 1e-8)
        for _ in range(self.epochs):
            for idx in th.as_tensor(rng.permutation(len(target))).split(self.batch_size):
                rows = Batch(*(getattr(joined, f)[idx] for f in Batch.__annotations__))
                loss = F.mse_loss(self.predict(x[idx], rows, rows.actions), target[idx])
                assert self.optimizer is not None
                self.optimizer.zero_grad()
                loss.backward()
                self.optimizer.step()


VARIANTS = [
    Variant("latent+a, 1 rollout (first design)", "latent", False, 1),
    Variant("latent+z, 1 rollout", "latent", True, 1),
    Variant("latent+a, 4 rollouts", "latent", False, 4),
    Variant("latent+z, 4 rollouts", "latent", True, 4),
    Variant("obs+z 2x64, 4 rollouts", "obs", True, 4, layers=2),
    Variant("linear w(latent).z, 4 rollouts", "latent", True, 4, linear=True),
    Variant("linear w(obs).z 2x64, 4 rollouts (shipped)", "obs", True, 4, layers=2, linear=True),
]


class ScoreHeads(BaseCallback):
    def __init__(self) -> None:
        super().__init__()
        self.rng = np.random.default_rng(0)

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        buf = self.model.rollout_buffer
        obs = th.as_tensor(buf.observations.reshape(-1, *buf.obs_shape)).float()
        actions = th.as_tensor(buf.actions.reshape(-1, buf.action_dim)).float()
        with th.no_grad():
            dist = self.model.policy.get_distribution(obs).distribution
        n = len(obs)
        batch = Batch(
            obs,
            actions,
            dist.mean.reshape(n, -1),
            dist.stddev.reshape(n, -1),
            th.as_tensor(buf.advantages.reshape(-1)).float(),
        )
        for variant in VARIANTS:
            variant.scores.append(variant.score(self.model, batch))
            variant.fit(self.model, batch, self.rng)


@dataclass
class Args:
    """Advantage-head designs scored on plain PPO's rollouts (positional, in this order)."""

    env_id: Annotated[Positional[str], arg(metavar="ENV_ID")]
    """Gymnasium id of the env."""
    steps: Annotated[Positional[int], arg(metavar="STEPS")]
    """PPO training steps."""
    n_steps: Annotated[Positional[int], arg(metavar="N_STEPS")]
    """PPO rollout length per env (4 envs)."""
    seed: Annotated[Positional[int], arg(metavar="SEED")] = 0
    """Seed of PPO and its envs."""


def main(args: Args) -> None:
    th.set_num_threads(1)
    env = make_vec_env(args.env_id, n_envs=4, seed=args.seed)
    model = PPO(
        "MlpPolicy",
        env,
        n_steps=args.n_steps,
        batch_size=64,
        n_epochs=10,
        policy_kwargs={"net_arch": [64, 64]},
        seed=args.seed,
        device="cpu",
    )
    start = time.time()
    model.learn(args.steps, callback=ScoreHeads())
    rollouts = len(VARIANTS[0].scores)
    print(f"{args.env_id} seed {args.seed} rollouts {rollouts} time {time.time() - start:.0f}")
    for variant in VARIANTS:
        s = np.array(variant.scores[1:])
        k = len(s)
        thirds = [np.nanmean(s[i * k // 3 : (i + 1) * k // 3]) for i in range(3)]
        print(
            f"{variant.name:44s} mean {np.nanmean(s):+.3f}  thirds "
            f"{thirds[0]:+.3f} {thirds[1]:+.3f} {thirds[2]:+.3f}  frac>0.1 {np.mean(s > 0.1):.2f}"
        )


if __name__ == "__main__":
    main(tyro.cli(Args))
