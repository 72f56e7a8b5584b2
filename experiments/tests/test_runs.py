"""Resumable run bookkeeping: seeds, specs, done/stale/todo, atomic writes."""

import json

import pandas as pd
import pytest

from esa_experiments.runs import RunResult, RunSpec, RunStore, parse_seeds, results_root


@pytest.mark.parametrize(
    ("text", "seeds"),
    [("0-4", [0, 1, 2, 3, 4]), ("3", [3]), ("0,2,5-7", [0, 2, 5, 6, 7]), ("2,1,2", [1, 2])],
)
def test_parse_seeds(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize("text", ["", "a", "-1", "4-1", "0-", "1.5", "0..4", "0-4,x"])
def test_parse_seeds_rejects(text):
    with pytest.raises(ValueError, match="expected"):
        parse_seeds(text)


def test_results_roots(tmp_path):
    assert results_root("full", tmp_path) == tmp_path / "results"
    assert results_root("smoke", tmp_path) == tmp_path / "results-smoke"
    with pytest.raises(ValueError, match="expected budget"):
        results_root("huge", tmp_path)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"method": "a/b"},
        {"method": ""},
        {"study": "x y"},
        {"seed": -1},
        {"budget": "medium"},
    ],
)
def test_spec_rejects(kwargs):
    args = {"study": "s", "env": "E-v0", "method": "m", "seed": 0, "budget": "smoke", **kwargs}
    with pytest.raises(ValueError, match="expected"):
        RunSpec(**args)


def spec(steps=100, seed=0):
    return RunSpec("s", "esa_experiments/Quad-v0", "m", seed, "smoke", {"total_steps": steps})


def result(steps=100):
    frame = pd.DataFrame({"step": [0, steps], "return_mean": [1.0, 2.0]})
    return RunResult(frame, {"note": "x"}, {"trajectory": pd.DataFrame({"x": [0.0, 1.0]})})


def test_store_lifecycle(tmp_path):
    store = RunStore("s", "smoke", tmp_path)
    s = spec()
    assert store.status(s) == "todo"
    assert store.pending([s]) == [s]
    path = store.write(s, result())
    assert path == tmp_path / "results-smoke" / "s" / "runs" / "esa_experiments-Quad-v0__m__s0.csv"
    assert store.status(s) == "done"
    assert store.pending([s, spec(seed=1)]) == [spec(seed=1)]
    meta = json.loads(store.meta_path(s).read_text())
    assert meta["config"] == {"total_steps": 100} and meta["note"] == "x"
    # Nothing temporary is left behind.
    assert sorted(p.name for p in store.runs_dir.iterdir()) == [
        "esa_experiments-Quad-v0__m__s0.csv",
        "esa_experiments-Quad-v0__m__s0.json",
        "esa_experiments-Quad-v0__m__s0.trajectory.csv",
    ]
    loaded = store.load()
    assert list(loaded.columns[:3]) == ["env", "method", "seed"]
    assert loaded.env.iloc[0] == "esa_experiments/Quad-v0"
    assert store.load("trajectory").x.tolist() == [0.0, 1.0]


def test_run_finished_meanwhile_by_another_runner_is_not_run_again(tmp_path):
    from esa_client.compare.execution import run_one

    from esa_experiments.studies import StudyJob

    store = RunStore("s", "smoke", tmp_path)
    store.write(spec(), result())
    outcome = run_one(spec(), StudyJob(tmp_path))
    assert outcome.skipped and outcome.error is None
    # A run not done yet is run (and fails here: there is no study "s").
    other = run_one(spec(seed=1), StudyJob(tmp_path))
    assert not other.skipped and "s" in (other.error or "")


def test_changed_config_is_stale(tmp_path):
    store = RunStore("s", "smoke", tmp_path)
    store.write(spec(100), result())
    assert store.status(spec(100)) == "done"
    assert store.status(spec(200)) == "stale"
    assert store.pending([spec(200)]) == [spec(200)]


def test_csv_without_sidecar_is_stale(tmp_path):
    store = RunStore("s", "smoke", tmp_path)
    store.write(spec(), result())
    store.meta_path(spec()).unlink()
    assert store.status(spec()) == "stale"


def test_interrupted_write_leaves_run_todo(tmp_path, monkeypatch):
    store = RunStore("s", "smoke", tmp_path)

    def broken_to_csv(*args, **kwargs):
        raise KeyboardInterrupt

    res = result()
    monkeypatch.setattr(res.frame, "to_csv", broken_to_csv)
    with pytest.raises(KeyboardInterrupt):
        store.write(spec(), res)
    assert store.status(spec()) == "todo"
    assert not list(store.runs_dir.glob("*.tmp"))


def test_load_without_runs_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="run the study first"):
        RunStore("s", "full", tmp_path).load()


def test_finished_campaign_runs_stay_valid_when_esa_config_gains_a_field():
    """EsaConfig's later fields (fade) must not make the committed runs stale."""
    from esa_experiments.studies import confirmation

    args = confirmation.BUDGETS["full"]
    specs = confirmation.specs(args, "full", [0], confirmation.ENVS, confirmation.METHODS)
    store = RunStore("confirmation", "full")
    assert {spec.label: store.status(spec) for spec in specs} == {
        spec.label: "done" for spec in specs
    }


def test_seeking_offline_compares_esa_with_the_placebo_not_the_gradient():
    """E1's rule: ESA's gain CI and ESA minus placebo CI above 0 on 2 envs picks a learner."""
    import numpy as np

    from esa_experiments.studies import seeking_offline

    rng = np.random.default_rng(0)
    rows = []
    for env in ("A", "B", "C"):
        for state in range(50):
            row = {"env": env, "method": "ppo_fit_quadratic", "state": state}
            for kappa in seeking_offline.KAPPAS:
                # ESA gains, the placebo loses, the gradient gains more than ESA.
                row[f"delta esc {kappa:g}"] = 1.0 + 0.1 * rng.standard_normal()
                row[f"delta placebo {kappa:g}"] = -1.0 + 0.1 * rng.standard_normal()
                row[f"delta gradient {kappa:g}"] = 2.0 + 0.1 * rng.standard_normal()
            rows.append(row)
    table = seeking_offline.verdicts(pd.DataFrame(rows))
    assert table.passes.all()
    assert (table.esc_minus_placebo > 1.5).all() and (table.esc_minus_gradient < -0.5).all()
    picks = seeking_offline.picks(table)
    assert picks["ppo"] is not None and picks["ppo"][0] == "ppo_fit_quadratic"
    assert picks["off_policy"] is None
