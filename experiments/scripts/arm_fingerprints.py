"""Digests of short training runs of the lab's arms, to tell a refactor that kept every bit.

Trains a sample of the arms of the studies (the confirmation campaign, E1 and E2: linear,
quadratic and Q-network critics, target mode, gradient controls, placebo, off-policy ESA,
the executed probe, the mean anchor) for a few rollouts on InvertedPendulum-v5, each built
as its study builds it (``esa_experiments.algorithms``), and prints a sha256 of the policy's
and critic's parameters and the evaluation table, then one of the policy and the evaluation
table alone. Run it before and after a change of the drop-ins: equal digests on the same
machine mean the change kept every bit (the second: every bit of what the policy learned,
for a change that touches only the critic).

Usage::

    python experiments/scripts/arm_fingerprints.py > before.txt
    # change the code
    python experiments/scripts/arm_fingerprints.py | diff before.txt -
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import torch as th

from esa_experiments.algorithms import seeking_methods
from esa_experiments.training import StepBudget, rl_spec, trained

ENV = "InvertedPendulum-v5"
BUDGET = StepBudget(
    on_policy=8 * 1024,
    off_policy=3_000,
    eval_every_on=4096,
    eval_every_off=1_500,
    eval_episodes=1,
    overrides={"sac": {"learning_starts": 400}, "td3": {"learning_starts": 400}},
)
"""Eight PPO rollouts and 2,600 off-policy steps after the warm-up: the faded arms of E2 and
the gated ones shift actions for a part of them (ESA starts after the critic's first gate)."""
E2_PPO = seeking_methods("ppo", "ppo_fit_quadratic")


@dataclass(frozen=True)
class Arm:
    """One arm: the method and, for E2's arms, the trust region E1 picked."""

    method: str
    kappa: float | None = None


ARMS = (
    Arm("ppo"),
    Arm("ppo_esa"),
    Arm("ppo_qgrad"),
    Arm("ppo_esa_target"),
    Arm("ppo_fit_qnet"),
    Arm(E2_PPO["ppo_esa"], 1.0),
    Arm(E2_PPO["ppo_placebo"], 1.0),
    Arm(E2_PPO["ppo_qgrad"], 1.0),
    Arm("sac"),
    Arm("sac_esa"),
    Arm("sac_qgrad"),
    Arm("sac_mean_esa"),
    Arm("td3_esa"),
    Arm("td3_sine"),
    Arm("sac_placebo"),
)


def digest(arm: Arm, seed: int = 0) -> tuple[str, str]:
    """sha256s (16 hex digits) of one short run: everything, and the policy and evaluation."""
    overrides = None if arm.kappa is None else {"trust_region": arm.kappa}
    spec = rl_spec("fingerprint", ENV, arm.method, seed, "smoke", BUDGET, esa_overrides=overrides)
    whole, policy = hashlib.sha256(), hashlib.sha256()
    with trained(spec, lambda _: None) as (result, model):
        columns = ["step", "return_mean", "length_mean", "train_episodes", "train_return_sum"]
        table = result.frame[columns].to_numpy().tobytes()
        for p in model.policy.parameters():
            for h in (whole, policy):
                h.update(p.detach().cpu().numpy().tobytes())
        head = getattr(model, "esa_head", None)
        for p in head.parameters() if head is not None else ():
            whole.update(p.detach().cpu().numpy().tobytes())
        whole.update(table)
        policy.update(table)
    return whole.hexdigest()[:16], policy.hexdigest()[:16]


def main() -> None:
    """Prints one digest per arm."""
    th.set_num_threads(1)
    for arm in ARMS:
        print(f"{arm.method:32s} {'  '.join(digest(arm))}", flush=True)


if __name__ == "__main__":
    main()
