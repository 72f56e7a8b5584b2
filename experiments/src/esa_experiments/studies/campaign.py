"""Does the shipped ESA default help? PPO and SAC with and without ESA at real budgets.

Arms, the same on every env (no per-env tuning):

* ``ppo``: plain stable-baselines3 PPO;
* ``ppo_esa_null``: the shipped ESA wiring with learning rate 0 (v stays 0): what the
  data handling alone does (by construction, and tested, it is PPO bit for bit);
* ``ppo_esa_paper``: the paper's law and settings (``EsaConfig.paper()``);
* ``ppo_esa``: the shipped default (``EsaConfig()``, chosen by ``default_search`` on
  InvertedPendulum-v5 seeds that are not used here);
* ``sac`` and ``sac_esa`` on Hopper-v5.

Budgets: InvertedPendulum-v5 30k steps, Hopper-v5 and Walker2d-v5 100k, the quadrotor
figure eight 30k, SAC on Hopper-v5 50k; 10 seeds each (5 left the MuJoCo verdicts
undecided). Runs are ordered seed-major, so a campaign cut short still compares every
arm on the seeds it finished.
Reporting follows Agarwal et al. (NeurIPS 2021): IQM and mean of the AUC with
stratified-bootstrap 95 % CIs and the probability of improvement over the baseline
(:mod:`esa_experiments.reliability`), with every seed's curve in the figure.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from esa_experiments.plotting import Panel
from esa_experiments.reliability import reliability_section
from esa_experiments.reporting import budget_table, rl_section
from esa_experiments.runs import RunSpec, RunStore
from esa_experiments.training import SMOKE_BUDGET, StepBudget, rl_spec, run_training

NAME = "campaign"
DESCRIPTION = "the shipped ESA default vs PPO/SAC, the paper's law and learning rate 0"
ENVS = ("InvertedPendulum-v5", "Hopper-v5", "Walker2d-v5", "Quadrotor-eight")
PPO_ARMS = ("ppo", "ppo_esa_null", "ppo_esa_paper", "ppo_esa")
SAC_ARMS = ("sac", "sac_esa")
METHODS = PPO_ARMS + SAC_ARMS
DEFAULT_SEEDS = "0-9"


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: step budget per env.
        seeds: how many seeds each env gets: the first that many of the given seeds.
        sac_envs: envs that also get the SAC arms.
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    seeds: dict[str, int] = field(default_factory=dict)
    sac_envs: tuple[str, ...] = ("Hopper-v5",)


# Three PPO rollouts: the gate needs two before ESA can act on the third.
SMOKE = replace(SMOKE_BUDGET, on_policy=384)

BUDGETS = {
    "smoke": Args({env: SMOKE for env in ENVS}, {env: 1 for env in ENVS}),
    # PPO totals are whole rollouts (4 envs x 256 = 1024 steps; 4 x 512 on Hopper and
    # Walker2d). Measured on the 2-core machine, about 7 CPU-hours in all.
    "full": Args(
        {
            "InvertedPendulum-v5": StepBudget(30_720, 0, 2_048, 0, 5),
            "Hopper-v5": StepBudget(100_352, 50_000, 4_096, 2_500, 3),
            "Walker2d-v5": StepBudget(100_352, 0, 4_096, 0, 3),
            "Quadrotor-eight": StepBudget(30_720, 0, 2_048, 0, 3),
        },
        {env: 10 for env in ENVS},
    ),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The (env, method, seed) runs, seed-major: each seed compares every arm before the next."""
    return [
        rl_spec(NAME, env, method, seed, budget, args.budgets[env])
        for rank, seed in enumerate(seeds)
        for env in envs
        for method in methods
        if rank < args.seeds[env] and (method in PPO_ARMS or env in args.sac_envs)
    ]


run = run_training
"""One run: train with periodic evaluation, nothing else."""


def report(store: RunStore, args: Args) -> str:
    """Learning curves with every seed, the summary table and the rliable statistics."""
    panels = [Panel(f"{env}: PPO", env, PPO_ARMS) for env in ENVS] + [
        Panel(f"{env}: SAC", env, SAC_ARMS) for env in args.sac_envs
    ]
    section = rl_section(store, panels, ENVS, METHODS, ncols=3, per_seed=True)
    statistics = reliability_section(store, ENVS, METHODS)
    return f"{section}\n{statistics}\nBudgets (per run):\n\n{budget_table(args.budgets)}\n"
