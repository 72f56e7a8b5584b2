"""Which of SAC's critics should ESA probe? A measurement of their steadiness.

ESA integrates the critic's local slope over tens of steps while SAC keeps training the
critic, so the probed critic should not turn between consecutive probes. Plain SAC is
trained on an env; at checkpoints, for states and near-mean actions from the replay
buffer, each candidate's paired probe response ``Q(s, a + K e_i) - Q(s, a)`` per action
dimension is taken, SAC trains on for ``--gap`` more steps, and the response is taken
again. The mean cosine similarity of the two response vectors is the candidate's
steadiness (1 = ESA would see the same slope); also reported: the share of dimensions
whose sign flipped.

Usage (writes CSV and Markdown next to the other results):

    python experiments/scripts/sac_probe_critic.py --env Hopper-v5 --steps 30000
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch as th
import tyro
from esa_client.compare.tables import to_markdown
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env

from esa_experiments.configs import algorithm_hyperparams
from esa_experiments.lab.off_policy_arms import PROBE_CRITICS
from esa_experiments.runs import EXPERIMENTS_DIR, atomic_write_text


@dataclass
class Args:
    """Steadiness of SAC's critics for ESA's probes."""

    env: str = "Hopper-v5"
    """Gymnasium id of the env."""
    steps: int = 30_000
    """SAC training steps, split evenly among the checkpoints (the gaps come on top)."""
    checkpoints: int = 6
    """Measurements, evenly spread over the training."""
    gap: int = 50
    """SAC steps between the two responses of a measurement."""
    states: int = 512
    """Replay-buffer states per measurement."""
    amplitude: float = 0.2
    """Probe amplitude K in the squashed action space."""
    seed: int = 0
    """Seed of SAC, the env and the sampled states."""


def _q(model: SAC, name: str, obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
    online, reduce = name.split("_")
    critic = model.critic if online == "online" else model.critic_target
    values = th.cat(critic(obs, actions), dim=1)
    return values.min(dim=1).values if reduce == "min" else values.mean(dim=1)


def responses(
    model: SAC, obs: th.Tensor, actions: th.Tensor, amplitude: float
) -> dict[str, th.Tensor]:
    """Per candidate critic: ``Q(s, a + K e_i) - Q(s, a)`` for every dimension i, shape (n, D)."""
    n, d = actions.shape
    probes = actions[:, None, :] + amplitude * th.eye(d)[None]  # (n, D, D)
    out = {}
    with th.no_grad():
        for name in PROBE_CRITICS:
            base = _q(model, name, obs, actions)
            tiled = obs.repeat_interleave(d, dim=0)
            probed = _q(model, name, tiled, probes.reshape(n * d, d).clamp(-1, 1)).reshape(n, d)
            out[name] = probed - base[:, None]
    return out


def main(args: Args) -> pd.DataFrame:
    th.set_num_threads(1)
    hp = algorithm_hyperparams("sac", args.env)
    hp.pop("param_noise", None)
    net_arch = hp.pop("net_arch")
    env = make_vec_env(args.env, n_envs=1, seed=args.seed)
    model = SAC("MlpPolicy", env, seed=args.seed, policy_kwargs={"net_arch": net_arch}, **hp)
    rng = np.random.default_rng(args.seed)
    rows = []
    every = args.steps // args.checkpoints
    for _ in range(args.checkpoints):
        model.learn(every, reset_num_timesteps=False)
        buffer = model.replay_buffer
        idx = rng.integers(0, buffer.size(), size=args.states)
        obs = th.as_tensor(buffer.observations[idx, 0], dtype=th.float32)
        with th.no_grad():
            mean, log_std, _ = model.actor.get_action_dist_params(obs)
            actions = th.tanh(
                mean + log_std.exp() * th.as_tensor(rng.normal(size=mean.shape), dtype=th.float32)
            )
        before = responses(model, obs, actions, args.amplitude)
        model.learn(args.gap, reset_num_timesteps=False)
        after = responses(model, obs, actions, args.amplitude)
        for name in PROBE_CRITICS:
            cosine = th.nn.functional.cosine_similarity(before[name], after[name], dim=1)
            flips = (th.sign(before[name]) != th.sign(after[name])).float().mean()
            rows.append(
                {
                    "env": args.env,
                    "step": model.num_timesteps,
                    "critic": name,
                    "cosine": float(cosine.mean()),
                    "sign_flips": float(flips),
                    "response_scale": float(before[name].abs().mean()),
                }
            )
        print(
            f"step {model.num_timesteps}: "
            + ", ".join(f"{r['critic']} {r['cosine']:.3f}" for r in rows[-len(PROBE_CRITICS) :])
        )
    return pd.DataFrame(rows)


if __name__ == "__main__":
    args = tyro.cli(Args)
    frame = main(args)
    out = EXPERIMENTS_DIR / "results" / "sac_probe_critic"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / f"{args.env}__s{args.seed}.csv", frame.to_csv(index=False))
    summary = (
        frame.groupby("critic")[["cosine", "sign_flips", "response_scale"]].mean().reset_index()
    )
    atomic_write_text(
        out / f"{args.env}__s{args.seed}.md",
        f"Steadiness of SAC's critics for ESA on {args.env} (seed {args.seed}, {args.steps} steps, "
        f"gap {args.gap} SAC steps, {args.states} states, K = {args.amplitude}); means over "
        f"{args.checkpoints} checkpoints:\n\n{to_markdown(summary.round(4))}\n",
    )
    print(summary.to_string(index=False))
