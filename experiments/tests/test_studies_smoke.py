"""Every study's smoke budget, end to end through the real esa-server.

Runs ``python -m esa_experiments run STUDY --budget smoke --seeds 0 --jobs 2``
(``--jobs 1`` for ``rllib_ppo``: each worker starts a local Ray instance; skipped without
Ray) and ``plot STUDY`` into a temporary root, then checks that every run's CSV,
the figures and the tables exist and are sane, and that a second ``run`` is a
no-op (resumability).
"""

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from esa_client import EsaError
from esa_client.sidecar import BINARY_ENV, find_server_binary

from esa_experiments.commands import main
from esa_experiments.runs import RunStore
from esa_experiments.studies import STUDY_NAMES, load_study

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module", autouse=True)
def server_bin():
    """The real server binary (the client's lookup, no cargo build); workers get it by env."""
    try:
        path = find_server_binary(checkout=REPO_ROOT, build=False)
    except EsaError as err:
        pytest.fail(str(err))
    os.environ[BINARY_ENV] = str(path)
    return path


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("experiments")


def check_rl_run(frame: pd.DataFrame, total_steps: int, extra: tuple[str, ...] = ()) -> None:
    assert list(frame.columns) == [
        "step",
        "return_mean",
        "return_std",
        "length_mean",
        "train_seconds",
        "train_cpu_seconds",
        "eval_seconds",
        "train_episodes",
        "train_crashes",
        "train_return_sum",
        "train_length_sum",
        *extra,
    ]
    assert frame.step.iloc[0] == 0 and frame.step.iloc[-1] == total_steps
    # Training episodes are counted cumulatively; a crash is one of them.
    for column in ("train_episodes", "train_crashes", "train_length_sum"):
        assert frame[column].is_monotonic_increasing, column
    assert (frame.train_crashes <= frame.train_episodes).all()
    assert frame.train_length_sum.iloc[-1] <= total_steps * 4  # at most n_envs episodes a step
    assert frame.step.is_monotonic_increasing and frame.train_seconds.is_monotonic_increasing
    assert np.isfinite(frame.to_numpy(float)).all()
    assert (frame.length_mean >= 1).all()


def check_seeking_offline_run(frame: pd.DataFrame, config: dict, method: str) -> None:
    from esa_experiments.seeking_probes import branch_names as seeking_branches

    assert len(frame) == config["states"] * len(config["checkpoints"])
    assert sorted(set(frame.checkpoint)) == config["checkpoints"]
    for name in seeking_branches():
        for kind in ("delta", "predicted", "size"):
            assert np.isfinite(frame[f"{kind} {name}"]).all(), (kind, name)
    # The placebo's shift is ESA's in size, |v| / sigma per dimension; SAC's squashed space
    # clips it where its sign points out of [-1, 1].
    for kappa in config["kappas"]:
        placebo, esc = frame[f"size placebo {kappa:g}"], frame[f"size esc {kappa:g}"]
        if method == "sac":
            assert (placebo <= esc + 1e-12).all()
        else:
            np.testing.assert_allclose(placebo, esc)


def check_example1_run(frame: pd.DataFrame, total_steps: int, env: str, method: str) -> None:
    assert list(frame.columns) == ["t", "J", "J_probe"] and len(frame) == total_steps
    assert np.isfinite(frame.to_numpy(float)).all()
    # J at the start (2, 2): optimum (0.1, 0.5), or (0, 0) at t = 0 when time-varying.
    assert frame.J.iloc[0] == pytest.approx(8.0 if env == "timevarying" else 1.9**2 + 1.5**2)
    # Every method gets much closer to the optimum than the start.
    assert frame.J.iloc[-100:].mean() < 0.1 * frame.J.iloc[0], method


def check_rllib_run(frame: pd.DataFrame, config: dict) -> None:
    """The RLlib study's evaluation table: E2's columns and the env steps RLlib sampled."""
    check_rl_run(frame, config["total_steps"], extra=("env_steps",))
    # Evaluated where the sampled steps reached each point: RLlib's env runner counts at
    # most n_envs - 1 steps more per train batch (an env's autoreset step is not counted).
    n_envs = config["hyperparams"]["num_envs_per_env_runner"]
    batches = config["total_steps"] // (n_envs * config["hyperparams"]["rollout_fragment_length"])
    assert (frame.env_steps >= frame.step).all()
    assert (frame.env_steps - frame.step <= (n_envs - 1) * batches).all()
    assert (frame.train_length_sum <= frame.env_steps).all()


@pytest.mark.parametrize("name", STUDY_NAMES)
def test_smoke_budget(name, root, capsys):
    jobs = "2"
    if name == "rllib_ppo":
        pytest.importorskip("ray.rllib")
        jobs = "1"
    assert (
        main(
            ["--root", str(root), "run", name, "--budget", "smoke", "--seeds", "0", "--jobs", jobs]
        )
        == 0
    )
    study = load_study(name)
    store = RunStore(name, "smoke", root)
    specs = study.specs(study.BUDGETS["smoke"], "smoke", [0], study.ENVS, study.METHODS)
    for spec in specs:
        assert store.status(spec) == "done", spec.label
        frame = pd.read_csv(store.csv_path(spec))
        if name == "example1":
            check_example1_run(frame, spec.config["total_steps"], spec.env, spec.method)
        elif name == "seeking_offline":
            check_seeking_offline_run(frame, spec.config, spec.method)
        elif name == "rllib_ppo":
            check_rllib_run(frame, spec.config)
        else:
            check_rl_run(frame, spec.config["total_steps"])

    assert main(["--root", str(root), "plot", name, "--budget", "smoke"]) == 0
    pngs = sorted(store.dir.glob("*.png"))
    assert pngs and all(p.stat().st_size > 10_000 for p in pngs)
    table = (store.dir / "table.md").read_text()
    summary_table = table.split("\n\n")[0]
    rows = [line for line in summary_table.splitlines() if line.startswith("| ")][1:]
    if name == "seeking_offline":
        # One row per learner, env and kappa; E1 writes the picks E2 reads.
        assert len(rows) == len(specs) * len(study.KAPPAS)
        assert set(json.loads((store.dir / "picks.json").read_text())) == {"ppo", "off_policy"}
    else:
        assert len(rows) == len(specs)
    section = (store.dir / "section.md").read_text()
    for png in pngs:
        assert f"results-smoke/{name}/{png.name}" in section
    assert not (root / "RESULTS.md").exists()

    # Resumable: everything is done, nothing runs again.
    mtimes = {p: p.stat().st_mtime_ns for p in store.runs_dir.iterdir()}
    capsys.readouterr()
    assert main(["--root", str(root), "run", name, "--budget", "smoke", "--seeds", "0"]) == 0
    assert f"{len(specs)} done, 0 stale" in " ".join(capsys.readouterr().out.split())
    assert {p: p.stat().st_mtime_ns for p in store.runs_dir.iterdir()} == mtimes


def test_paper_figures_smoke_flights(root):
    """Figure 4: the quadrotor's PPO arms fly their final policy (the smoke test ran them)."""
    if not RunStore("paper_figures", "smoke", root).runs_dir.is_dir():
        pytest.skip("the paper_figures smoke run was not selected")
    flights = RunStore("paper_figures", "smoke", root).load("trajectory")
    assert set(flights.env) == {"Quadrotor-eight"}
    assert set(flights.method) == {"ppo", "ppo_esa"}
    assert np.isfinite(
        flights[["x", "y", "z", "target_x", "target_y", "target_z"]].to_numpy()
    ).all()


def test_rllib_ppo_runs_e2s_ppo_settings():
    """The RLlib study's settings, written out in its module, are E2's ``[ppo]`` per env."""
    from esa_experiments.algorithms import resolve_hyperparams
    from esa_experiments.studies import rllib_ppo

    for env in rllib_ppo.ENVS:
        e2, rllib = resolve_hyperparams("ppo", env, None), rllib_ppo.settings(env)
        assert (rllib["num_envs_per_env_runner"], rllib["rollout_fragment_length"]) == (
            e2["n_envs"],
            e2["n_steps"],
        )
        pairs = {
            "minibatch_size": "batch_size",
            "num_epochs": "n_epochs",
            "lr": "learning_rate",
            "gamma": "gamma",
            "lambda_": "gae_lambda",
            "clip_param": "clip_range",
            "entropy_coeff": "ent_coef",
            "fcnet_hiddens": "net_arch",
        }
        assert {ours: rllib[ours] for ours in pairs} == {
            ours: e2[theirs] for ours, theirs in pairs.items()
        }
        budget = rllib_ppo.BUDGETS["full"].budgets[env]
        assert budget.on_policy % (e2["n_envs"] * e2["n_steps"]) == 0  # whole train batches
