"""Does ESA's shift point uphill on the true returns? A check that trusts no critic.

For each env: train PPO+ESA (the shipped default) for half the campaign's budget, then
run the trained policy with ESA switched on (gate ignored, so the shift is what ESA would
do) and save ``states`` MuJoCo states (``qpos``/``qvel``) with the sampled action ``a_t``,
ESA's action ``a_t + v(t)`` and the action ESA would take with a trust region of one
policy standard deviation (``wide``: ESA's direction, where the shipped bound keeps the
shift small; see :mod:`esa_experiments.state_capture`). From every saved state, execute
each action and then follow the stochastic policy for ``horizon`` steps, ``rollouts``
times with common random numbers for every branch, and compare the discounted
Monte-Carlo returns. A positive mean difference means ESA's shifts improved the actions
by the environment's own measure; the rank correlation of the head's predicted
``A(s, a + v) - A(s, a)`` with the measured difference says how much of it the critic knew.

For the off-policy family (method ``sac``): train plain SAC for ``off_policy_steps`` and
compare, per trust region of :data:`esa_experiments.off_policy_capture.TRUST_REGIONS`,
ESA's action with a step of the same size along the critic's action gradient (see
:mod:`esa_experiments.off_policy_capture`). It picks ``EsaConfig.off_policy()``'s bound:
the largest whose gain CI is above 0 on every env. Its seeds are tuning seeds (100 and
up), never the campaign's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import pandas as pd
import torch as th
from matplotlib.figure import Figure

from esa_experiments.evaluation import ProgressFn
from esa_experiments.off_policy_capture import (
    TRUST_REGIONS,
    PolicyAction,
    branch_names,
    capture_off_policy_states,
    sac_policy_action,
    unscale,
)
from esa_experiments.runs import RunResult, RunSpec, RunStore, atomic_write_text
from esa_experiments.state_capture import capture_states, gaussian
from esa_experiments.studies import campaign
from esa_experiments.tables import to_markdown
from esa_experiments.tasks import get_task
from esa_experiments.training import StepBudget, rl_spec, trained

if TYPE_CHECKING:
    from esa_client.sb3 import ESAPPO
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
    from stable_baselines3 import SAC
    from stable_baselines3.common.base_class import BaseAlgorithm

NAME = "ground_truth"
DESCRIPTION = "Monte-Carlo returns of a_t vs ESA's a_t + v(t) from saved MuJoCo states"
ENVS = ("InvertedPendulum-v5", "Hopper-v5", "Walker2d-v5")
METHODS = ("ppo_esa", "sac")
OFF_POLICY_ENVS = ("InvertedPendulum-v5", "Hopper-v5")
DEFAULT_SEEDS = "0"
GAMMA = 0.99


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: training budget per env (evaluated once, at the end).
        states: saved states per env.
        horizon: steps followed after the compared action.
        rollouts: Monte-Carlo rollouts per state and branch.
        save_every: save one state in this many steps (after the first 10 of an episode).
        off_policy: training budget of the ``sac`` runs.
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    states: int = 200
    horizon: int = 100
    rollouts: int = 4
    save_every: int = 7
    off_policy: StepBudget = field(default_factory=lambda: StepBudget(0, 25_000, 0, 25_000, 3))


def _half(budget: StepBudget) -> StepBudget:
    steps = budget.on_policy // 2
    return StepBudget(steps, 0, steps, 0, 1)


BUDGETS = {
    "smoke": Args(
        {env: campaign.SMOKE for env in ENVS},
        states=4,
        horizon=5,
        rollouts=2,
        off_policy=campaign.SMOKE,
    ),
    "full": Args({env: _half(campaign.BUDGETS["full"].budgets[env]) for env in ENVS}),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """One run per (env, method, seed): train, save states, compare returns."""
    check = {
        "states": args.states,
        "horizon": args.horizon,
        "rollouts": args.rollouts,
        "save_every": args.save_every,
    }
    out = []
    for seed in seeds:
        for env in envs:
            for method in methods:
                if method == "sac" and env not in OFF_POLICY_ENVS:
                    continue
                steps = args.off_policy if method == "sac" else args.budgets[env]
                spec = rl_spec(NAME, env, method, seed, budget, steps)
                out.append(RunSpec(NAME, env, method, seed, budget, {**spec.config, **check}))
    return out


def run(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains, saves states, and measures every branch's Monte-Carlo returns."""
    args = spec.config
    with trained(spec, progress) as (result, model):
        env = get_task(spec.env).make()
        try:
            rows = (_sac_rows if spec.method == "sac" else _ppo_rows)(model, env, args, spec.seed)
        finally:
            env.close()
        return RunResult(pd.DataFrame(rows), result.meta, {"training": result.frame})


def _ppo_rows(
    model: BaseAlgorithm, env: gym.Env, args: dict[str, Any], seed: int
) -> list[dict[str, float]]:
    saved = capture_states(
        cast("ESAPPO", model), env, args["states"], save_every=args["save_every"], seed=seed
    )
    box = cast(gym.spaces.Box, env.action_space)
    act = _ppo_policy_action(model, box)
    rows = []
    for i, state in enumerate(saved):
        sampled, shifted, wide = (
            _mc_return(
                act, env, state.qpos, state.qvel, np.clip(a, box.low, box.high), args, 1000 * i
            )
            for a in (state.sampled, state.shifted, state.wide)
        )
        rows.append(
            {
                "state": i,
                "return_sampled": sampled,
                "return_shifted": shifted,
                "return_wide": wide,
                "delta": shifted - sampled,
                "delta_wide": wide - sampled,
                "predicted": state.predicted,
                "predicted_wide": state.predicted_wide,
                "shift_over_std": state.shift_over_std,
                "wide_shift_over_std": state.wide_shift_over_std,
            }
        )
    return rows


def _sac_rows(
    model: BaseAlgorithm, env: gym.Env, args: dict[str, Any], seed: int
) -> list[dict[str, float]]:
    sac = cast("SAC", model)  # the study's off-policy method is sac
    saved = capture_off_policy_states(
        sac, env, args["states"], save_every=args["save_every"], seed=seed
    )
    box = cast(gym.spaces.Box, env.action_space)
    act = sac_policy_action(sac, box)
    rows = []
    for i, state in enumerate(saved):

        def mc(action: np.ndarray, i: int = i, state: Any = state) -> float:
            return _mc_return(
                act, env, state.qpos, state.qvel, unscale(box, action), args, 1000 * i
            )

        base = mc(state.sampled)
        row: dict[str, float] = {"state": i, "return_sampled": base}
        for name in branch_names():
            row[f"delta {name}"] = mc(state.actions[name]) - base
            row[f"predicted {name}"] = state.predicted[name]
            row[f"size {name}"] = state.sizes[name]
        rows.append(row)
    return rows


def _ppo_policy_action(model: BaseAlgorithm, box: gym.spaces.Box) -> PolicyAction:
    """PPO's Gaussian policy, clipped to the env's bounds as SB3 does."""

    def act(obs: np.ndarray, noise: th.Tensor) -> np.ndarray:
        with th.no_grad():
            dist = gaussian(model, th.as_tensor(obs, dtype=th.float32)[None])
            action: np.ndarray = (dist.mean + dist.stddev * noise).numpy()[0]
        clipped: np.ndarray = np.clip(action, box.low, box.high)
        return clipped

    return act


def _mc_return(
    act: PolicyAction,
    env: gym.Env,
    qpos: np.ndarray,
    qvel: np.ndarray,
    action: np.ndarray,
    args: dict[str, Any],
    seed: int,
) -> float:
    """Mean discounted return of ``action`` (env units) from a state, then the policy ``act``."""
    base = cast("MujocoEnv", env.unwrapped)  # the ground-truth tasks are MuJoCo envs
    dim = cast(gym.spaces.Box, env.action_space).shape[0]
    total = 0.0
    for m in range(args["rollouts"]):
        generator = th.Generator().manual_seed(seed + m)  # the same draws for every branch
        base.set_state(qpos, qvel)
        obs, reward, terminated, _, _ = base.step(action)
        ret, discount = float(reward), GAMMA
        for _ in range(args["horizon"] - 1):
            if terminated:
                break
            obs, reward, terminated, _, _ = base.step(
                act(obs, th.randn((1, dim), generator=generator))
            )
            ret += discount * float(reward)
            discount *= GAMMA
        total += ret
    return float(total / args["rollouts"])


BRANCHES = (
    ("shipped bound", "delta", "predicted", "shift_over_std"),
    ("1 std bound", "delta_wide", "predicted_wide", "wide_shift_over_std"),
)
"""(label, return difference, critic's prediction, shift size) per compared action."""


def _bootstrap_ci(values: np.ndarray, reps: int = 2000, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    means = rng.choice(values, size=(reps, len(values))).mean(axis=1)
    return float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def _branches(method: str) -> tuple[tuple[str, str, str, str], ...]:
    """(label, return difference, critic's prediction, shift size) per compared action."""
    if method == "sac":
        return tuple((n, f"delta {n}", f"predicted {n}", f"size {n}") for n in branch_names())
    return BRANCHES


def _ci_text(values: np.ndarray) -> str:
    low, high = _bootstrap_ci(values)
    return f"{values.mean():+.3f} [{low:+.3f}, {high:+.3f}]"


def off_policy_bound(frame: pd.DataFrame) -> tuple[float | None, float]:
    """The off-policy pick: the largest bound whose ESA gain CI is above 0 on every env.

    Returns:
        (that bound or None, the bound with the largest mean gain over envs as fallback).
    """
    sac = frame[frame.method == "sac"]
    passing, means = [], {}
    for bound in TRUST_REGIONS:
        key = f"delta esa {bound:g}"
        per_env = [runs[key].to_numpy(float) for _, runs in sac.groupby("env")]
        means[bound] = float(np.mean([d.mean() for d in per_env]))
        if per_env and all(_bootstrap_ci(d)[0] > 0 for d in per_env):
            passing.append(bound)
    return (max(passing) if passing else None), max(means, key=lambda b: means[b])


def report(store: RunStore, args: Args) -> str:
    """Per env and method: the mean return difference with its CI, and what the critic knew."""
    from esa_client.common.advantage_head import rank_correlation

    frame = store.load()
    rows = []
    for (env, method), runs in frame.groupby(["env", "method"], sort=False):
        for label, delta_key, predicted_key, shift_key in _branches(str(method)):
            delta = runs[delta_key].to_numpy(float)
            predicted = runs[predicted_key].to_numpy(float)
            rows.append(
                {
                    "env": env,
                    "method": method,
                    "shift": label,
                    "seeds": runs.seed.nunique(),
                    "states": len(runs),
                    "return(a + v) - return(a) [95% CI]": _ci_text(delta),
                    "share of states improved": f"{np.mean(delta > 0):.2f}",
                    "mean return(a)": f"{runs.return_sampled.mean():.2f}",
                    "mean abs(v) / sigma": f"{runs[shift_key].mean():.3f}",
                    "rank corr. (critic's prediction, measured)": (
                        f"{rank_correlation(predicted, delta):+.2f}"
                    ),
                }
            )
    table = to_markdown(pd.DataFrame(rows))
    atomic_write_text(store.artifact("table.md"), table + "\n")
    figure = _figure(frame, store.artifact("ground_truth.png"))
    text = (
        f"![ground truth]({store.relative(figure)})\n\n"
        f"Discounted (gamma {GAMMA}) Monte-Carlo returns over {args.horizon} steps, "
        f"{args.rollouts} rollouts per state and branch with common random numbers; "
        "95 % CI by bootstrap over states:\n\n"
        f"{table}\n"
    )
    if (frame.method == "sac").any():
        text += _off_policy_section(frame[frame.method == "sac"])
    return text


def _off_policy_section(sac: pd.DataFrame) -> str:
    """ESA against its gradient control at equal size, and the bound the study picks."""
    rows = []
    for env, runs in sac.groupby("env", sort=False):
        for bound in TRUST_REGIONS:
            esa, grad = (
                runs[f"delta {kind} {bound:g}"].to_numpy(float) for kind in ("esa", "grad")
            )
            rows.append(
                {
                    "env": env,
                    "bound (sigma)": f"{bound:g}",
                    "ESA gain": _ci_text(esa),
                    "gradient gain (same size)": _ci_text(grad),
                    "ESA - gradient": _ci_text(esa - grad),
                }
            )
    picked, best = off_policy_bound(sac)
    verdict = (
        f"The largest bound whose ESA gain CI is above 0 on every env: **{picked:g} sigma**."
        if picked is not None
        else "No bound's ESA gain CI is above 0 on every env: the ground truth predicts no "
        f"gain; the bound with the largest mean gain is {best:g} sigma."
    )
    table = to_markdown(pd.DataFrame(rows))
    return (
        "\nSAC: ESA's shift against a step of the same size (mean |v| / sigma, L2 in units "
        "of sigma) along the probed critic's action gradient; the difference is paired by "
        f"state:\n\n{table}\n\n{verdict}\n"
    )


def _figure(frame: pd.DataFrame, path: Path) -> Path:
    """PPO: each state's measured gain against the critic's prediction, per env.

    SAC: the mean measured gain with its CI against the bound, ESA beside its gradient
    control, per env.
    """
    ppo = frame[frame.method == "ppo_esa"]
    sac = frame[frame.method == "sac"]
    panels = [(env, "ppo") for env in dict.fromkeys(ppo.env)]
    panels += [(env, "sac") for env in dict.fromkeys(sac.env)]
    fig = Figure(figsize=(4 * len(panels), 3.6), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (env, family) in zip(axes, panels, strict=True):
        if family == "ppo":
            runs = ppo[ppo.env == env]
            for label, delta_key, predicted_key, _ in BRANCHES:
                ax.plot(runs[predicted_key], runs[delta_key], ".", alpha=0.5, label=label)
            ax.axvline(0.0, color="grey", linewidth=0.8)
            ax.set_xlabel("critic's predicted gain A(s, a + v) - A(s, a)")
            ax.set_title(f"{env}: PPO+ESA", fontsize=10)
        else:
            runs = sac[sac.env == env]
            for offset, kind in ((-0.01, "esa"), (0.01, "grad")):
                means, errors = [], []
                for bound in TRUST_REGIONS:
                    delta = runs[f"delta {kind} {bound:g}"].to_numpy(float)
                    low, high = _bootstrap_ci(delta)
                    means.append(delta.mean())
                    errors.append((delta.mean() - low, high - delta.mean()))
                x = np.log10(TRUST_REGIONS) + offset
                ax.errorbar(x, means, yerr=np.array(errors).T, marker="o", capsize=3, label=kind)
            ax.set_xticks(np.log10(TRUST_REGIONS), [f"{b:g}" for b in TRUST_REGIONS])
            ax.set_xlabel("trust region (policy stds)")
            ax.set_title(f"{env}: SAC, ESA vs gradient", fontsize=10)
        ax.axhline(0.0, color="grey", linewidth=0.8)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("measured return(a + v) - return(a)")
    fig.savefig(path, dpi=120)
    return path
