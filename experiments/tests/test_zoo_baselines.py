"""Study ``zoo_baselines`` (E3): its arms are RL Zoo3's settings, and E2's runs stay valid."""

import importlib.metadata
import importlib.util
import inspect
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from esa_client.compare.training import FrozenNormalization
from stable_baselines3 import PPO, SAC, TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from esa_experiments.algorithms import ZOO_ENTRIES, build_model, resolve_hyperparams
from esa_experiments.configs import algorithm_hyperparams
from esa_experiments.runs import RunStore
from esa_experiments.studies import seeking, zoo_baselines
from esa_experiments.tasks import get_task
from esa_experiments.training import rl_spec

CLASSES = {"ppo": PPO, "sac": SAC, "td3": TD3}
ZOO_CASES = [(arm, env) for arm, entries in ZOO_ENTRIES.items() for env in entries]


@pytest.fixture(scope="module")
def zoo_yml():
    """The installed RL Zoo3's hyperparameter files, as the zoo reads them (merge keys too)."""
    yaml = pytest.importorskip("yaml")
    spec = importlib.util.find_spec("rl_zoo3")
    if spec is None or spec.origin is None:
        pytest.skip("rl_zoo3 is not installed (client-py's zoo extra)")
    assert importlib.metadata.version("rl_zoo3") == "2.9.2", "E3's rules name RL Zoo3 2.9.2"
    folder = Path(spec.origin).parent / "hyperparams"
    return {family: yaml.safe_load((folder / f"{family}.yml").read_text()) for family in CLASSES}


def sb3_defaults(family: str, env: str) -> dict:
    """SB3's constructor defaults of the family, with the policy's default net_arch."""
    cls = CLASSES[family]
    defaults = {
        name: p.default
        for name, p in inspect.signature(cls.__init__).parameters.items()
        if p.default is not inspect.Parameter.empty
    }
    model = cls("MlpPolicy", make_vec_env(get_task(env).make, n_envs=1), device="cpu")
    defaults["net_arch"] = model.policy.net_arch
    defaults["n_envs"] = 1  # the zoo's default
    return defaults


def expected_hyperparams(entry: dict, family: str, env: str) -> dict:
    """A zoo entry in this suite's terms: the yml's keys, SB3's defaults for our tables' keys."""
    entry = dict(entry)
    assert entry.pop("policy") == "MlpPolicy"
    entry.pop("n_timesteps")  # the study's budget instead
    if "policy_kwargs" in entry:
        options = eval(entry.pop("policy_kwargs"), {"dict": dict, "nn": torch.nn})
        entry["net_arch"] = options.pop("net_arch")
        if "activation_fn" in options:
            options["activation_fn"] = options["activation_fn"].__name__
        if options:
            entry["policy_kwargs"] = options
    if "noise_type" in entry:
        assert entry.pop("noise_type") == "normal"
        entry["noise_sigma"] = entry.pop("noise_std")
    defaults = sb3_defaults(family, env)
    ours = algorithm_hyperparams(family, env)
    ours.pop("param_noise", None)
    for key in ours.keys() - entry.keys():
        entry[key] = defaults[key]
    return entry


@pytest.mark.parametrize("arm, env", ZOO_CASES)
def test_each_zoo_arm_resolves_the_yml_entry_with_the_budget_substituted(zoo_yml, arm, env):
    family = arm.removesuffix("_zoo")
    entry = zoo_yml[family][ZOO_ENTRIES[arm][env]]
    expected = expected_hyperparams(entry, family, env)
    budget = seeking.BUDGETS["full"].budgets[env]
    spec = rl_spec(zoo_baselines.NAME, env, arm, 0, "full", budget)
    assert spec.config["hyperparams"] == expected
    assert resolve_hyperparams(arm, env) == expected
    assert spec.config["total_steps"] == (
        budget.on_policy if family == "ppo" else budget.off_policy
    )
    assert entry["n_timesteps"] != spec.config["total_steps"]
    # E2's evaluation: the same interval and episodes as E2's baseline on the env.
    e2 = rl_spec(seeking.NAME, env, family, 0, "full", budget).config
    for key in ("total_steps", "eval_every", "eval_episodes"):
        assert spec.config[key] == e2[key], key


def test_the_off_policy_arms_use_the_mujoco_defaults_on_both_envs(zoo_yml):
    for family in ("sac", "td3"):
        hopper, idp = (
            resolve_hyperparams(f"{family}_zoo", env)
            for env in ("Hopper-v5", "InvertedDoublePendulum-v5")
        )
        assert hopper == idp
        assert hopper["learning_starts"] == 10_000
        assert zoo_yml[family]["Hopper-v4"] == zoo_yml[family]["HalfCheetah-v4"]  # the anchor
    td3 = resolve_hyperparams("td3_zoo", "Hopper-v5")
    assert (td3["noise_sigma"], td3["learning_rate"], td3["batch_size"], td3["net_arch"]) == (
        0.1,
        1e-3,
        256,
        [400, 300],
    )


@pytest.mark.parametrize("arm", sorted(ZOO_ENTRIES))
@pytest.mark.parametrize("env", ["InvertedPendulum-v5", "Quadrotor-eight", "Walker2d-v5"])
def test_an_env_without_a_zoo_entry_is_refused(arm, env):
    if env in ZOO_ENTRIES[arm]:
        return
    with pytest.raises(ValueError, match=r"expected one of \[.*\], got '"):
        resolve_hyperparams(arm, env)
    with pytest.raises(ValueError, match="expected one of"):
        rl_spec(
            zoo_baselines.NAME, env, arm, 0, "full", seeking.BUDGETS["full"].budgets["Hopper-v5"]
        )


def test_the_study_covers_e2s_envs_but_the_quadrotor():
    for family, envs in zoo_baselines.ENVS_OF.items():
        assert envs == tuple(e for e in seeking.ENVS_OF[family] if e != "Quadrotor-eight")
        assert set(envs) == set(ZOO_ENTRIES[f"{family}_zoo"])
    specs = zoo_baselines.specs(
        zoo_baselines.BUDGETS["full"],
        "full",
        list(zoo_baselines.SEEDS),
        zoo_baselines.ENVS,
        zoo_baselines.METHODS,
    )
    assert len(specs) == 21 and {s.seed for s in specs} == {0, 1, 2}


@pytest.mark.parametrize("env", zoo_baselines.ENVS_OF["ppo"])
def test_the_ppo_budgets_are_whole_rollouts(env):
    """No overshoot: each budget is a multiple of the rollout, ours and the zoo's."""
    budget = zoo_baselines.BUDGETS["full"].budgets[env].on_policy
    for method in ("ppo", "ppo_zoo"):
        hp = resolve_hyperparams(method, env)
        assert budget % (hp["n_steps"] * hp["n_envs"]) == 0, method


def test_the_zoo_hopper_policy_is_built_as_the_yml_says():
    env = VecNormalize(make_vec_env(get_task("Hopper-v5").make, n_envs=1, seed=0), gamma=0.999)
    model = build_model("ppo_zoo", env, 0, resolve_hyperparams("ppo_zoo", "Hopper-v5"))
    assert model.policy.activation_fn is torch.nn.ReLU
    assert model.policy.ortho_init is False
    np.testing.assert_allclose(model.policy.log_std.detach().numpy(), -2.0)
    assert model.policy.net_arch == {"pi": [256, 256], "vf": [256, 256]}
    assert (model.n_steps, model.batch_size, model.gamma, model.vf_coef) == (
        512,
        32,
        0.999,
        0.835671,
    )


def test_evaluation_sees_the_training_normalization_frozen_and_raw_rewards():
    task = get_task("InvertedPendulum-v5")
    stats = VecNormalize(make_vec_env(task.make, n_envs=1, seed=0), gamma=0.999)
    stats.reset()
    for _ in range(50):
        stats.step(np.array([[0.1]]))
    mean, var, count = stats.obs_rms.mean.copy(), stats.obs_rms.var.copy(), stats.obs_rms.count
    raw, wrapped = task.make(), FrozenNormalization(task.make(), stats)
    obs_raw, _ = raw.reset(seed=3)
    obs, _ = wrapped.reset(seed=3)
    np.testing.assert_allclose(obs, np.clip((obs_raw - mean) / np.sqrt(var + 1e-8), -10, 10))
    for _ in range(5):
        step_raw, step = raw.step(np.array([0.2])), wrapped.step(np.array([0.2]))
        assert step[1] == step_raw[1] == 1.0  # the env's own reward
        np.testing.assert_allclose(step[0], stats.normalize_obs(step_raw[0]))
    assert stats.obs_rms.count == count  # evaluation updates nothing
    np.testing.assert_array_equal(stats.obs_rms.mean, mean)


def test_the_decision_rule():
    zoo, ours = np.array([10.0, 11.0, 12.0]), np.array([5.0, 6.0, 7.0])
    difference, bound, verdict = zoo_baselines.decide(zoo, ours)
    assert difference == 5.0 and bound == pytest.approx(2 * np.sqrt(1 / 3 + 1 / 3))
    assert verdict == "**zoo beats**"
    assert zoo_baselines.decide(ours, zoo)[2] == "**zoo loses**"
    assert zoo_baselines.decide(zoo, zoo + 1.0)[2] == "equal"  # 1 < 2 * sqrt(2 / 3)
    import pandas as pd

    def table(verdicts):
        return pd.DataFrame({"env": list(verdicts), "verdict": list(verdicts.values())})

    seeds = {env: {0, 1, 2} for env in zoo_baselines.ENVS}
    ppo = dict.fromkeys(zoo_baselines.ENVS_OF["ppo"], "equal")
    assert "stand" in zoo_baselines.outcome("ppo", table(ppo), seeds)
    ppo["Hopper-v5"] = "**zoo beats**"
    assert "stand" in zoo_baselines.outcome("ppo", table(ppo), seeds)  # 1 of 3 < half
    ppo["InvertedPendulum-v5"] = "**zoo beats**"
    assert "switches" in zoo_baselines.outcome("ppo", table(ppo), seeds)
    ppo["InvertedDoublePendulum-v5"] = "**zoo loses**"
    assert "stand" in zoo_baselines.outcome("ppo", table(ppo), seeds)
    sac = {"InvertedDoublePendulum-v5": "**zoo beats**", "Hopper-v5": "equal"}
    text = zoo_baselines.outcome("sac", table(sac), {"Hopper-v5": {0, 1}})
    assert "switches" in text and "provisional" in text


def test_e2s_finished_runs_keep_their_fingerprints():
    """The zoo arms and the normalization leave E2's configs (and so its runs) as they were."""
    args = seeking.BUDGETS["full"]
    specs = seeking.specs(args, "full", [0], seeking.ENVS, seeking.METHODS)
    store = RunStore(seeking.NAME, "full")
    stored = {
        spec.label: json.loads(store.meta_path(spec).read_text())["fingerprint"]
        for spec in specs
        if store.meta_path(spec).is_file()
    }
    assert {"InvertedPendulum-v5 ppo s0", "Hopper-v5 ppo s0", "Hopper-v5 td3 s0"} <= set(stored)
    assert len(stored) >= 10
    assert {spec.label: spec.fingerprint() for spec in specs if spec.label in stored} == stored
