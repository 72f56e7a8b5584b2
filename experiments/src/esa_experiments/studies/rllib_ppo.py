"""RLlib runs what the drop-ins ship: RLlib's PPO with and without ``with_esa``, with a placebo.

Rules, fixed and committed before the first run:

* **Question.** ``esa_client.rllib.with_esa`` makes RLlib's PPO run what ``ESAPPO`` ships
  (the quadratic advantage head, ``EsaConfig.ppo()``, the decoupled objective). Does ESA,
  as shipped for RLlib, speed up RLlib's PPO on E2's envs and budgets, and does it harm it?
  E2 (study ``seeking``) asked this of stable-baselines3's PPO and found no acceleration;
  this study asks it of the other trainer users run.
* **Envs and budgets**: E2's. InvertedPendulum-v5, 30,720 env steps, evaluated every 2,048
  with 5 episodes; Hopper-v5, 100,352 steps, every 4,096 with 3 episodes. Both budgets are
  whole train batches (30 of 1,024 and 49 of 2,048 steps).
* **Arms**, each stored under its own name:

  - ``rllib_ppo``: RLlib's PPO (Ray 2.60's new API stack, torch) with E2's PPO settings
    (``configs/algorithms.toml`` ``[ppo]``, written out here in :data:`PPO_SETTINGS` so the
    runs stay valid while that file moves): one local EnvRunner with 4 envs and rollout
    fragments of 256 steps (512 on Hopper-v5, E2's ``n_steps`` there), so train batches of
    1,024 (2,048) steps; minibatches of 64, 10 epochs, learning rate 3e-4, gamma 0.99,
    lambda 0.95, clip 0.2, entropy coefficient 0; and what E2 took from stable-baselines3's
    PPO defaults: value loss coefficient 0.5, gradient norm clipped at 0.5, no KL penalty
    (RLlib's default adds one), no value clipping (``vf_clip_param`` 1e10), separate
    policy and value networks of [64, 64] tanh units, a state-independent log standard
    deviation starting at 0, actions not normalized and clipped to the Box by the env
    runner (stable-baselines3's handling: the policy's units are the env's).
    No remote env runners and a local learner: a run uses one core (and a local Ray
    instance, started once per worker process with one CPU).
  - ``rllib_ppo_esa``: the same config through ``with_esa(config, budget=<the run's
    steps>)``: the shipped default for RLlib's PPO (``EsaConfig.ppo()``, ESA faded out by
    half of the budget), in each EnvRunner's process (no server).
  - ``rllib_ppo_placebo``: ``with_esa(config, budget=..., control="placebo")``: the same
    schedule and shift magnitudes, the direction a random sign vector per episode.

  Differences from E2's stable-baselines3 PPO that remain, stated not corrected:
  RLlib standardizes the advantages over the whole train batch before the minibatches
  (stable-baselines3 per minibatch), so the ESA arms' decoupled objective weights
  batch-standardized advantages by ``min(pi_old / b, 2)``; RLlib's own weight
  initialization (stable-baselines3: orthogonal); Adam with torch's default epsilon.
* **Seeding.** ``config.debugging(seed=s)`` for seed ``s``: it seeds Python's, numpy's
  global and torch's generators on the EnvRunner and in the learner (the minibatch
  shuffling, the networks' initialization, the ESA module's head built on a forked torch
  generator), the envs' first reset, and the ESA head's fitting generator
  (``default_rng(s)`` in ``EsaPPOTorchLearner``), and the placebo's sign vectors:
  ``EsaModuleToEnv`` draws their seed from numpy's global generator, which the EnvRunner
  seeded with ``s`` plus its worker index before building it (the SB3 drop-in seeds them
  from the model's seed). A second smoke run of each arm must give the same evaluations.
* **Evaluation** as E2's (``esa_client.compare.evaluation.run_episodes``): the current
  RLModule's deterministic action (the mean of its Gaussian, clipped to the Box; no ESA:
  ESA is exploration only) on a separate env whose episode ``i`` is reset with seed
  ``10000 + s + i``; at step 0, at every multiple of the interval and at the end, each
  after the update of the train batch whose sampled env steps reach it (E2's callback
  evaluated before that rollout's update: here the policy has one update more at the
  same step). RLlib's env runner counts up to 3 env steps more per batch than asked (an
  env's autoreset step is not counted), never a whole batch over a budget of whole
  batches: the evaluation is stored at its point (``step``) with the steps sampled
  (``env_steps``). Training wall-clock and CPU time exclude evaluation.
* **Seeds** 0-9 for every arm, all run, none dropped, no optional stopping. Runs are
  ordered seed-major (InvertedPendulum-v5 then Hopper-v5, ``rllib_ppo``,
  ``rllib_ppo_esa``, ``rllib_ppo_placebo`` within each), so a study cut short compares
  every arm on the seeds it finished; verdicts use only seeds both arms finished.
* **Metric.** Primary: the area under the evaluation curve over the first third of the
  budget (normalized by its span). Secondary: the whole-curve AUC.
* **Tests** E2's: per env and comparison the probability of improvement ``P(X > Y)`` with
  its bootstrap CI and the two-sided Mann-Whitney U test; comparisons: each arm through
  ``with_esa`` against ``rllib_ppo`` (``rllib_ppo_esa``, ``rllib_ppo_placebo``) and
  ``rllib_ppo_esa`` against ``rllib_ppo_placebo``, on both envs: six tests,
  Holm-corrected together within each metric; better / worse at a corrected p < 0.05.
* **Success** (seeking's rule for one family): ``rllib_ppo_esa`` is better than both
  ``rllib_ppo`` and ``rllib_ppo_placebo`` on the primary metric on at least one env, and
  its whole-curve AUC is worse than ``rllib_ppo``'s on no env. Otherwise ESA is not shown
  to help RLlib's PPO; a whole-curve "worse" is reported as harm.
* **Runs**: 60, ``python -m esa_experiments run rllib_ppo --budget full --jobs 1``, then
  ``python -m esa_experiments plot rllib_ppo --budget full``. The smoke budget (CI) runs
  the same arms for 384 steps with train batches of 4 x 16 steps and 2 epochs.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any, cast

import gymnasium as gym
import numpy as np
import pandas as pd
from esa_client.compare.evaluation import EVAL_SEED_OFFSET, ProgressFn, run_episodes
from esa_client.compare.execution import start_local_ray
from esa_client.compare.plotting import Panel
from esa_client.compare.verdicts import (
    Comparison,
    better_and_worse,
    compact_table,
    verdict_table,
)

from esa_experiments.reporting import budget_table, rl_section, verdicts_markdown, write_verdicts
from esa_experiments.runs import RunResult, RunSpec, RunStore
from esa_experiments.studies import seeking
from esa_experiments.tasks import get_task
from esa_experiments.training import SMOKE_BUDGET, StepBudget

NAME = "rllib_ppo"
DESCRIPTION = "RLlib's PPO with the shipped with_esa and its placebo, at E2's budgets"
ENVS = ("InvertedPendulum-v5", "Hopper-v5")
CONTROL = {"rllib_ppo": None, "rllib_ppo_esa": "esa", "rllib_ppo_placebo": "placebo"}
"""Arm -> what ``with_esa`` adds (None: plain RLlib)."""
METHODS = tuple(CONTROL)
DEFAULT_SEEDS = "0-9"
LABELS = {
    "rllib_ppo": "RLlib PPO",
    "rllib_ppo_esa": "RLlib PPO+ESA",
    "rllib_ppo_placebo": "RLlib PPO+placebo",
}
FAMILY = "rllib_ppo"
COMPARISONS = (
    Comparison(FAMILY, "rllib_ppo_esa", "rllib_ppo", "baseline"),
    Comparison(FAMILY, "rllib_ppo_placebo", "rllib_ppo", "baseline"),
    Comparison(FAMILY, "rllib_ppo_esa", "rllib_ppo_placebo", "placebo"),
)
"""One Holm family per metric: the three comparisons on both envs."""
MIN_BETTER = 1

PPO_SETTINGS: dict[str, Any] = {
    "num_envs_per_env_runner": 4,
    "rollout_fragment_length": 256,
    "minibatch_size": 64,
    "num_epochs": 10,
    "lr": 3e-4,
    "gamma": 0.99,
    "lambda_": 0.95,
    "clip_param": 0.2,
    "entropy_coeff": 0.0,
    # Stable-baselines3's PPO defaults that E2 ran with.
    "vf_loss_coeff": 0.5,
    "grad_clip": 0.5,
    "use_kl_loss": False,
    "vf_clip_param": 1e10,  # no value clipping (clip_range_vf=None); JSON-safe, unlike inf
    "fcnet_hiddens": [64, 64],
    "fcnet_activation": "tanh",
    "free_log_std": True,
    "vf_share_layers": False,
}
"""E2's ``[ppo]`` of ``configs/algorithms.toml`` in RLlib's names (one rollout of 1,024)."""
ENV_SETTINGS: dict[str, dict[str, Any]] = {"Hopper-v5": {"rollout_fragment_length": 512}}
"""E2's per-env changes (``[ppo.env."Hopper-v5"]``: ``n_steps = 512``)."""


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: step budget per env (``on_policy``: every arm is PPO).
        overrides: settings replacing :data:`PPO_SETTINGS` in every run (the smoke
            budget's small batches).
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    overrides: dict[str, Any] = field(default_factory=dict)


SMOKE = replace(SMOKE_BUDGET, on_policy=384, off_policy=0, overrides={})

BUDGETS = {
    "smoke": Args(
        {env: SMOKE for env in ENVS},
        {"rollout_fragment_length": 16, "num_epochs": 2},
    ),
    "full": Args(
        {
            "InvertedPendulum-v5": StepBudget(30_720, 0, 2_048, 1, 5),
            "Hopper-v5": StepBudget(100_352, 0, 4_096, 1, 3),
        }
    ),
}


def settings(env: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The RLlib PPO settings of a run on ``env``."""
    return {**PPO_SETTINGS, **ENV_SETTINGS.get(env, {}), **(overrides or {})}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The runs, seed-major (envs in order, then the arms)."""
    out = []
    for seed in seeds:
        for env in ENVS:
            if env not in envs:
                continue
            step_budget = args.budgets[env]
            for arm in METHODS:
                if arm not in methods:
                    continue
                config = {
                    "trainer": "rllib",
                    "esa": CONTROL[arm],
                    "total_steps": step_budget.on_policy,
                    "eval_every": step_budget.eval_every_on,
                    "eval_episodes": step_budget.eval_episodes,
                    "hyperparams": settings(env, args.overrides),
                    "uses_server": False,
                }
                out.append(RunSpec(NAME, env, arm, seed, budget, config))
    return out


def start_ray() -> None:
    """A local Ray instance with one CPU for this worker process (RLlib needs one)."""
    import ray

    if not ray.is_initialized():
        start_local_ray(num_cpus=1)


TALLY = ("train_episodes", "train_crashes", "train_return_sum", "train_length_sum")
"""Training-episode counts, as ``PeriodicEvaluation`` keeps them (cumulative)."""


def _callbacks() -> type[Any]:
    """The RLlib callback that counts the training episodes (Ray imported on first use)."""
    from ray.rllib.callbacks.callbacks import RLlibCallback

    class EpisodeTally(RLlibCallback):
        """Sums, over the run, the training episodes, crashes, returns and lengths."""

        def on_episode_end(self, *, episode: Any, metrics_logger: Any = None, **_: Any) -> None:
            values = (1, int(episode.is_terminated), float(episode.get_return()), len(episode))
            for key, value in zip(TALLY, values, strict=True):
                metrics_logger.log_value(f"study/{key}", value, reduce="lifetime_sum")

    return EpisodeTally


def build_config(spec: RunSpec) -> Any:
    """The run's ``PPOConfig``, through ``with_esa`` for the ESA and placebo arms."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    h = spec.config["hyperparams"]
    batch = h["num_envs_per_env_runner"] * h["rollout_fragment_length"]
    config = (
        PPOConfig()
        .framework("torch")
        .environment(get_task(spec.env).gym_id, normalize_actions=False, clip_actions=True)
        .env_runners(
            num_env_runners=0,
            num_envs_per_env_runner=h["num_envs_per_env_runner"],
            rollout_fragment_length=h["rollout_fragment_length"],
        )
        .learners(num_learners=0)
        .training(
            train_batch_size_per_learner=batch,
            minibatch_size=h["minibatch_size"],
            num_epochs=h["num_epochs"],
            lr=h["lr"],
            gamma=h["gamma"],
            lambda_=h["lambda_"],
            clip_param=h["clip_param"],
            entropy_coeff=h["entropy_coeff"],
            vf_loss_coeff=h["vf_loss_coeff"],
            grad_clip=h["grad_clip"],
            grad_clip_by="global_norm",
            use_kl_loss=h["use_kl_loss"],
            vf_clip_param=h["vf_clip_param"],
        )
        .rl_module(
            model_config=DefaultModelConfig(
                fcnet_hiddens=list(h["fcnet_hiddens"]),
                fcnet_activation=h["fcnet_activation"],
                free_log_std=h["free_log_std"],
                vf_share_layers=h["vf_share_layers"],
            )
        )
        .callbacks(_callbacks())
        .debugging(seed=spec.seed)
    )
    control = spec.config["esa"]
    if control is None:
        return config
    from esa_client.rllib import with_esa

    return with_esa(
        config,
        budget=spec.config["total_steps"],
        control=None if control == "esa" else control,
    )


class DeterministicPolicy:
    """What ``run_episodes`` calls (``model.policy.predict``), over an RLModule.

    The action is the mean of the module's Gaussian (RLlib's deterministic action),
    clipped to the env's Box as stable-baselines3's ``predict`` does.
    """

    def __init__(self, module: Any, low: np.ndarray, high: np.ndarray) -> None:
        """Wraps ``module`` (read at each call: it is the one the weights sync into)."""
        self.policy = self
        self.module, self.low, self.high = module, low, high

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        """The deterministic action for one observation."""
        import torch
        from ray.rllib.core.columns import Columns

        with torch.no_grad():
            batch = {Columns.OBS: torch.as_tensor(np.asarray(obs, np.float32)[None])}
            inputs = self.module.forward_inference(batch)[Columns.ACTION_DIST_INPUTS]
        mean = inputs[0].chunk(2)[0].double().numpy()
        return np.clip(mean, self.low, self.high), None


def _log_row(step: int, result: dict[str, Any]) -> dict[str, float]:
    """One train iteration's statistics: ESA's (``esa/``) and the learner's (``train/``)."""
    from ray.rllib.core import DEFAULT_MODULE_ID

    row: dict[str, float] = {"step": float(step)}
    learner = result.get("learners", {}).get(DEFAULT_MODULE_ID, {})
    for key, value in learner.items():
        if isinstance(value, (int, float)) and key.startswith("esa/") and key != "esa/active":
            row[key] = float(value)
    for key in ("policy_loss", "vf_loss", "entropy", "vf_explained_var", "mean_kl_loss"):
        if isinstance(learner.get(key), (int, float)):
            row[f"train/{key}"] = float(learner[key])
    for key, value in result.get("env_runners", {}).items():
        if isinstance(value, (int, float)) and key.startswith("esa/"):
            row[key] = float(value)
    return row


def evaluation_point(sampled: int, every: int, total: int) -> int:
    """The last evaluation point (a multiple of ``every``, or ``total``) ``sampled`` reached.

    RLlib's env runner samples until its train batch is full and may count a few steps
    more (at most one fewer than its envs per batch: an env reset by autoreset steps
    without counting). The budgets are whole batches, so the batch that reaches a point
    is the same one as without the extra steps; its evaluation is stored at the point
    (``step``), with the steps actually sampled (``env_steps``), so every run of every
    arm is evaluated at the same steps.
    """
    return total if sampled >= total else sampled // every * every


def run(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains one arm until its sampled env steps reach the budget, evaluating as E2."""
    start_ray()
    logging.getLogger("ray.rllib").setLevel(logging.ERROR)
    total, every = spec.config["total_steps"], spec.config["eval_every"]
    episodes = spec.config["eval_episodes"]
    eval_env = get_task(spec.env).make()
    space = eval_env.action_space
    if not isinstance(space, gym.spaces.Box):
        raise ValueError(f"expected a Box action space on {spec.env}, got {space}")
    algo = build_config(spec).build_algo()
    rows: list[dict[str, float]] = []
    log: list[dict[str, float]] = []
    clock = {"train": 0.0, "cpu": 0.0, "eval": 0.0}
    tally = dict.fromkeys(TALLY, 0.0)
    with contextlib.closing(eval_env):
        try:
            policy = DeterministicPolicy(algo.get_module(), space.low, space.high)

            def evaluate(step: int, sampled: int) -> None:
                began = time.perf_counter()
                returns, lengths = run_episodes(
                    cast(Any, policy), eval_env, episodes, EVAL_SEED_OFFSET + spec.seed
                )
                clock["eval"] += time.perf_counter() - began
                rows.append(
                    {
                        "step": step,
                        "return_mean": float(returns.mean()),
                        "return_std": float(returns.std()),
                        "length_mean": float(lengths.mean()),
                        "train_seconds": clock["train"],
                        "train_cpu_seconds": clock["cpu"],
                        "eval_seconds": clock["eval"],
                        **tally,
                        "env_steps": sampled,
                    }
                )

            evaluate(0, 0)
            steps, done = 0, 0
            while steps < total:
                began, cpu = time.perf_counter(), time.process_time()
                result = algo.train()
                clock["train"] += time.perf_counter() - began
                clock["cpu"] += time.process_time() - cpu
                steps = int(result["num_env_steps_sampled_lifetime"])
                runners = result.get("env_runners", {})
                tally = {key: float(runners.get(f"study/{key}", 0.0)) for key in TALLY}
                log.append(_log_row(steps, result))
                progress(min(steps, total))
                point = evaluation_point(steps, every, total)
                if point > done:
                    evaluate(point, steps)
                    done = point
        finally:
            algo.stop()
    frame = pd.DataFrame(rows)
    # RLlib reports its statistics in the order they first appear: sorted, runs compare.
    table = pd.DataFrame(log) if log else pd.DataFrame({"step": []})
    table = table[["step", *sorted(set(table.columns) - {"step"})]]
    return RunResult(
        frame,
        meta={"final_return": float(frame.return_mean.iloc[-1])},
        tables={"log": table},
    )


def report(store: RunStore, args: Args) -> str:
    """Learning curves, the verdicts on both metrics, and the outcome."""
    frame = store.load()
    section = rl_section(
        store,
        [Panel(f"{env}: RLlib PPO", env, METHODS) for env in ENVS],
        ENVS,
        METHODS,
        labels=LABELS,
        baselines={"rllib_ppo_esa": "rllib_ppo", "rllib_ppo_placebo": "rllib_ppo"},
        ncols=2,
    )
    early = seeking.early(frame, args.budgets, family=lambda _: "ppo")
    tables = {
        "first third (primary)": verdict_table(early, ENVS, COMPARISONS, LABELS),
        "whole curve (secondary)": verdict_table(frame, ENVS, COMPARISONS, LABELS),
    }
    write_verdicts(store, *tables.values())
    text = [
        section,
        "Verdicts (P(arm better) with its 95 % CI, two-sided Mann-Whitney p Holm-corrected "
        "over the six comparisons, within each metric):\n\n"
        + verdicts_markdown(compact_table(*tables.values()))
        + "\n",
        outcome(tables["first third (primary)"], tables["whole curve (secondary)"]),
        f"Budgets (per run):\n\n{budget_table(args.budgets)}\n",
    ]
    return "\n".join(text)


def outcome(primary: pd.DataFrame, whole: pd.DataFrame) -> str:
    """The study's outcome under its success rule."""
    if primary.empty or whole.empty:
        return "Outcome: no verdict yet (no comparison has two seeds).\n"
    both, worse = better_and_worse(primary, whole, LABELS["rllib_ppo_esa"])
    success = len(both) >= MIN_BETTER and not worse
    seeds = int(primary.seeds.min())
    return (
        f"Outcome ({seeds} seeds or more per comparison; rules in `studies/rllib_ppo.py`): "
        f"{'success' if success else 'no success'}: RLlib PPO+ESA better than RLlib PPO and "
        f"its placebo early on {sorted(both) or 'no env'}; whole-curve worse than RLlib PPO "
        f"on {sorted(worse) or 'no env'}.\n"
    )
