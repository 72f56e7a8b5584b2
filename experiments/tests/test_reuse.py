"""Reused runs: read from another study only with the same fingerprint, and named as such."""

import dataclasses

import numpy as np
import pandas as pd
import pytest
from esa_client import EsaConfig
from esa_client.sb3 import ESAPPO, ESASAC

from esa_experiments.algorithms import esa_class, get_method
from esa_experiments.reuse import Reuse, load_runs, provenance_table, rerun_table, to_run
from esa_experiments.runs import RunResult, RunStore, parse_seeds
from esa_experiments.studies import paper_ablations, paper_figures, seeking

PENDULUM = paper_figures.PENDULUM


def curve(returns):
    steps = np.arange(len(returns)) * 1024
    return pd.DataFrame(
        {
            "step": steps,
            "return_mean": returns,
            "train_seconds": steps / 1000,
            "train_cpu_seconds": steps / 1000,
        }
    )


@pytest.fixture
def args(tmp_path):
    full = paper_figures.BUDGETS["full"]
    return dataclasses.replace(full, reuse=Reuse(paper_figures.REUSED, tmp_path))


def test_a_run_of_the_same_fingerprint_is_read_not_run(tmp_path, args):
    plan = paper_figures.planned(args, "full", [0, 1], (PENDULUM,), ("ppo", "ppo_esa"))
    e2 = RunStore(seeking.NAME, "full", tmp_path)
    mine = RunStore(paper_figures.NAME, "full", tmp_path)
    same = plan[0]  # ppo, seed 0: E2 holds it with these settings
    e2.write(same, RunResult(curve([1.0, 2.0])))
    other = dataclasses.replace(plan[2], config={**plan[2].config, "total_steps": 1})
    e2.write(other, RunResult(curve([5.0, 5.0])))  # ppo, seed 1: E2's settings differ
    todo = to_run(plan, args.reuse)
    assert same not in todo and plan[2] in todo and len(todo) == 3
    mine.write(plan[1], RunResult(curve([3.0, 4.0])))
    frame = load_runs(mine, plan, args.reuse)
    assert (
        sorted(zip(frame.method, frame.seed, strict=True))
        == [("ppo", 0)] * 2 + [("ppo_esa", 0)] * 2
    )
    table = provenance_table(mine, plan, args.reuse, {})
    ppo = table[table.arm == "ppo"].iloc[0]
    assert ppo["read from `seeking`"] == "0" and ppo["not run yet"] == "1"
    assert ppo.envs == PENDULUM
    assert table[table.arm == "ppo_esa"].iloc[0]["run here"] == "0"


def test_nothing_at_all_is_a_clear_error(tmp_path, args):
    plan = paper_figures.planned(args, "full", [0], (PENDULUM,), ("ppo",))
    with pytest.raises(FileNotFoundError, match="run the study first"):
        load_runs(RunStore(paper_figures.NAME, "full", tmp_path), plan, args.reuse)


def test_the_smoke_budget_reuses_nothing():
    for study in (paper_figures, paper_ablations):
        smoke = study.BUDGETS["smoke"]
        plan = study.planned(smoke, "smoke", [0], study.ENVS, study.METHODS)
        assert study.specs(smoke, "smoke", [0], study.ENVS, study.METHODS) == plan


@pytest.mark.parametrize(
    ("study", "planned", "reused"), [(paper_figures, 140, 40), (paper_ablations, 70, 10)]
)
def test_the_committed_runs_are_reused_as_the_rules_say(study, planned, reused):
    full = study.BUDGETS["full"]
    seeds = parse_seeds(study.DEFAULT_SEEDS)
    plan = study.planned(full, "full", seeds, study.ENVS, study.METHODS)
    todo = study.specs(full, "full", seeds, study.ENVS, study.METHODS)
    assert len(plan) == planned and len(plan) - len(todo) == reused
    for spec in plan:
        if spec not in todo:
            assert spec.env in study.REUSED[spec.method]


def test_every_ablation_arm_is_cut_at_the_first_third_of_ppos_budget():
    full = paper_ablations.BUDGETS["full"]
    budget = full.budgets[paper_ablations.ENV].on_policy
    steps = np.arange(0, budget + 1, 2048)
    frame = pd.concat(
        pd.DataFrame({"env": paper_ablations.ENV, "method": arm, "step": steps})
        for arm in paper_ablations.METHODS
    )
    last = paper_ablations.first_third(frame, full).groupby("method").step.max()
    assert sorted(last.index) == sorted(paper_ablations.METHODS)
    assert (last == budget // 3).all()


def test_the_budgets_are_e2s_and_walker2d_gets_hoppers():
    budgets = paper_figures.BUDGETS["full"].budgets
    e2 = seeking.BUDGETS["full"].budgets
    for env in (PENDULUM, paper_figures.HOPPER, paper_figures.QUADROTOR):
        assert budgets[env] == e2[env]
    assert budgets[paper_figures.WALKER] == e2[paper_figures.HOPPER]


def test_the_esa_arms_are_the_shipped_defaults():
    """ppo_esa is ESAPPO with EsaConfig.ppo(), sac_esa ESASAC with EsaConfig.off_policy()."""
    budget = paper_figures.BUDGETS["full"].budgets[PENDULUM]
    for arm, family, cls, config in (
        ("ppo_esa", "ppo", ESAPPO, EsaConfig.ppo()),
        ("sac_esa", "sac", ESASAC, EsaConfig.off_policy()),
    ):
        spec = paper_figures.arm_spec(arm, PENDULUM, 0, "full", budget)
        hp = spec.config["hyperparams"]
        assert get_method(spec.config["method"]).family == family
        assert esa_class(family, hp["esa_options"]) == (cls, None)
        shipped = {k: v for k, v in dataclasses.asdict(config).items() if v is not None}
        assert {k: v for k, v in hp["esa"].items() if v is not None} == shipped


def test_rerun_table_counts_identical_curves_and_departures(tmp_path):
    args = paper_figures.BUDGETS["full"]
    plan = paper_figures.planned(args, "full", [0, 1], (paper_figures.QUADROTOR,), ("ppo",))
    e2 = RunStore(seeking.NAME, "full", tmp_path)
    e2.write(plan[0], RunResult(curve([1.0, 2.0, 3.0])))
    e2.write(plan[1], RunResult(curve([1.0, 2.0, 3.0])))
    here = [curve([1.0, 2.0, 3.0]), curve([1.0, 2.5, 3.0])]
    frame = pd.concat(
        [c.assign(env=s.env, method=s.method, seed=s.seed) for c, s in zip(here, plan, strict=True)]
    )
    table = rerun_table(frame, plan, paper_figures.RERUN_CHECK, tmp_path, 1 / 3, {})
    row = table.iloc[0]
    assert row["identical curves"] == "1 of 2" and row["first departure (step)"] == "1024"
