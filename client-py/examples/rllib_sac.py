"""RLlib SAC with ESA on Pendulum-v1: two env runners, progress per iteration.

Needs the ``rllib`` extra and tyro, which reads the command line; ``make setup`` has both.
In a venv of your own, from a clone (esa is not on PyPI yet; once it is,
``pip install "esa-client[rllib]" tyro``)::

    pip install -e "./client-py[rllib]" tyro

Runs on a laptop (CPU only). ``with_esa`` adds ESA to a plain ``SACConfig``: each env copy
of each EnvRunner gets an ESA session in that runner's process (no server). Each iteration
samples 1,000 env steps and prints the mean episode return, the fraction of steps on which
ESA acted (its gate opens once the critic ranks actions well) and the mean shift ``|v(t)|``.

Usage::

    .venv/bin/python client-py/examples/rllib_sac.py [--iterations 20] [--env-runners 2]
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import ray
import tyro
from ray.rllib.algorithms.sac import SACConfig

from esa_client import EsaConfig
from esa_client.rllib import with_esa


@dataclass
class Args:
    """RLlib SAC with ESA on Pendulum-v1."""

    iterations: int = 20
    """Training iterations (about 1,000 env steps each)."""
    env_runners: int = 2
    """RLlib EnvRunner actors, each with its env copies."""
    envs_per_runner: int = 2
    """Env copies per EnvRunner, each with its own ESA session."""
    seed: int = 0
    """Seed of RLlib's config."""


def main(args: Args) -> None:
    ray.init(num_cpus=args.env_runners + 1, include_dashboard=False, logging_level="ERROR")
    config = (
        SACConfig()
        .environment("Pendulum-v1")
        .env_runners(
            num_env_runners=args.env_runners,
            num_envs_per_env_runner=args.envs_per_runner,
            rollout_fragment_length=10,
        )
        .training(
            actor_lr=3e-4,
            critic_lr=3e-4,
            num_steps_sampled_before_learning_starts=1_000,
            train_batch_size_per_learner=256,
            # About one update of 256 per 4 env steps, done in rounds of ~15 between two
            # sample calls: far fewer round trips (and weight syncs) than one per step.
            training_intensity=64,
        )
        .reporting(min_sample_timesteps_per_iteration=1_000, min_time_s_per_iteration=0)
        .debugging(seed=args.seed, log_level="ERROR")
    )
    # ESA's defaults; the gate holds ESA back until the critic ranks actions well.
    algo = with_esa(config, esa=EsaConfig.off_policy()).build_algo()
    start = time.monotonic()
    print(f"{'iter':>4} {'env steps':>9} {'return':>8} {'ESA on':>6} {'|shift|':>7} {'time':>6}")
    try:
        for iteration in range(1, args.iterations + 1):
            runners = algo.train()["env_runners"]
            episode_return = runners.get("episode_return_mean")
            print(
                f"{iteration:4d} {runners.get('num_env_steps_sampled_lifetime', 0):9.0f} "
                f"{'-' if episode_return is None else f'{episode_return:.1f}':>8} "
                f"{runners.get('esa/active', 0.0):6.2f} "
                f"{runners.get('esa/mean_abs_shift', 0.0):7.3f} "
                f"{time.monotonic() - start:5.0f}s",
                flush=True,
            )
    finally:
        algo.stop()
        ray.shutdown()


if __name__ == "__main__":
    main(tyro.cli(Args))
