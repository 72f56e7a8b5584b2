"""esa-compare: real (tiny) runs of every arm, resuming, refusing, judging, and bad input."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from esa_client.compare import cli, report
from esa_client.compare.hyperparams import algorithm_kwargs, parse_entry, resolve

# Pendulum's 200-step episodes and 64-step PPO rollouts keep each run to seconds.
SETTINGS = """
Pendulum-v1:
  n_steps: 64
  batch_size: 64
  n_epochs: 2
  learning_rate: lin_3e-4
  policy_kwargs: "dict(net_arch=[32, 32], activation_fn=nn.Tanh)"
"""


def args(out: Path, settings: Path, *extra: str) -> list[str]:
    return [
        "--env", "Pendulum-v1", "--algo", "ppo", "--hyperparams", str(settings),
        "--seeds", "2", "--steps", "256", "--eval-every", "128", "--eval-episodes", "1",
        "--out", str(out), "--jobs", "2", *extra,
    ]  # fmt: skip


def words(text: str) -> str:
    """The text with rich's line wrapping undone."""
    return " ".join(text.split())


@pytest.fixture
def settings(tmp_path: Path) -> Path:
    path = tmp_path / "settings.yml"
    path.write_text(SETTINGS)
    return path


def test_compare_runs_every_arm_resumes_and_then_does_nothing(tmp_path, settings, capsys):
    out = tmp_path / "out"
    assert cli.main(args(out, settings)) == 0
    runs = sorted(p.name for p in (out / "runs").glob("*.csv") if p.name.count(".") == 1)
    assert runs == [
        f"Pendulum-v1__{arm}__s{seed}.csv"
        for arm in ("baseline", "esa", "placebo")
        for seed in (0, 1)
    ]
    for name in ("RESULTS.md", "learning_curves.png", "verdicts.md", "summary.md"):
        assert (out / name).is_file(), name
    page = (out / "RESULTS.md").read_text()
    assert "ESAPPO placebo (placebo control)" in page and report.TOO_FEW in page
    provenance = json.loads((out / "provenance.json").read_text())
    assert provenance["command"].startswith("esa-compare --env Pendulum-v1")
    assert provenance["versions"]["stable-baselines3"] != "not installed"

    # A lost run is redone, the others are kept as they are.
    lost = out / "runs" / "Pendulum-v1__esa__s1.csv"
    kept = out / "runs" / "Pendulum-v1__baseline__s0.csv"
    kept_mtime = kept.stat().st_mtime_ns
    lost.unlink()
    capsys.readouterr()
    assert cli.main(args(out, settings)) == 0
    assert "5 done, 1 to do" in words(capsys.readouterr().out)
    assert lost.is_file() and kept.stat().st_mtime_ns == kept_mtime

    # The same command once everything is done does nothing, and writes nothing.
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    assert cli.main(args(out, settings)) == 0
    assert "Nothing to do" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before

    # A folder that holds runs refuses other rules, and names what differs.
    assert cli.main([*args(out, settings)[:-2], "--jobs", "2", "--eval-episodes", "2"]) == 2
    assert "eval_episodes" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (["--arms", "esa,bogus"], "expected distinct --arms"),
        (["--seeds", "0"], "expected --seeds >= 1"),
        (["--seeds", "3-1"], "low <= high"),
        (["--steps", "100", "--eval-every", "200"], "expected --eval-every <= --steps"),
        (["--eval-episodes", "0"], "expected --eval-episodes >= 1"),
        (["--jobs", "0"], "expected --jobs >= 1"),
        (["--env", "NoSuchEnv-v0"], "registered gymnasium env id"),
        (["--env", "no_such_module:make"], "importable module"),
        (["--env", "os:no_such_factory"], "callable 'no_such_factory'"),
        (["--hyperparams", "missing.yml"], "existing YAML file"),
    ],
)
def test_bad_arguments_fail_clearly_and_write_nothing(tmp_path, settings, capsys, change, expected):
    out = tmp_path / "out"
    assert cli.main([*args(out, settings), *change]) == 2
    assert expected in words(capsys.readouterr().out)
    assert not out.exists()


def test_unknown_algo_is_a_usage_error(tmp_path, settings):
    with pytest.raises(SystemExit) as exit_info:
        cli.parse([*args(tmp_path, settings), "--algo", "dqn"])
    assert exit_info.value.code == 2


def test_zoo_settings_apply_to_the_newest_version_the_zoo_has():
    params = resolve("zoo", "Hopper-v5", "ppo")
    assert "Hopper-v4" in params.source and params.normalize == {}
    assert params.n_timesteps == 1_000_000 and params.kwargs["n_steps"] == 512


def test_a_zoo_entry_becomes_the_algorithms_arguments():
    params = parse_entry(
        {
            "normalize": "dict(norm_obs=True, norm_reward=False)",
            "learning_rate": "lin_1e-3",
            "policy_kwargs": "dict(net_arch=[8], activation_fn=nn.ReLU)",
            "noise_type": "normal",
            "noise_std": 0.2,
            "esa": {"amplitude": 0.1},
        },
        "test",
    )
    kwargs = algorithm_kwargs(params)
    assert params.normalize == {"norm_obs": True, "norm_reward": False}
    assert kwargs["learning_rate"](0.5) == pytest.approx(5e-4)
    assert kwargs["policy_kwargs"]["net_arch"] == [8]
    assert kwargs["action_noise"] == {"type": "normal", "std": 0.2}
    assert params.esa == {"amplitude": 0.1} and "esa" not in kwargs


@pytest.mark.parametrize(
    ("entry", "expected"),
    [
        ({"env_wrapper": "x"}, "no env-changing keys"),
        ({"frame_stack": 4}, "no env-changing keys"),
        ({"policy_kwargs": "dict(net_arch=__import__('os'))"}, r"a dict\(\.\.\.\) expression"),
        ({"esa": 3}, "mapping of EsaConfig fields"),
    ],
)
def test_entries_this_tool_cannot_apply_faithfully_are_refused(entry, expected):
    with pytest.raises(ValueError, match=expected):
        algorithm_kwargs(parse_entry(entry, "test"))


def test_a_file_without_the_env_says_which_entries_it_has(tmp_path, settings):
    with pytest.raises(ValueError, match=r"expected an entry for 'Hopper-v5'.*Pendulum-v1"):
        resolve(str(settings), "Hopper-v5", "ppo")


@pytest.mark.parametrize(
    ("seeds", "tests", "decidable"), [(3, 1, False), (4, 3, False), (5, 3, True), (10, 3, True)]
)
def test_too_few_seeds_is_when_no_outcome_could_be_significant(seeds, tests, decidable):
    assert report.could_decide(seeds, tests) is decidable


def test_ctrl_c_leaves_no_half_written_run(tmp_path, settings):
    out = tmp_path / "out"
    command = [sys.executable, "-m", "esa_client.compare", *args(out, settings)]
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        # As at a terminal: a test run in the background inherits SIGINT ignored, and Python
        # then raises no KeyboardInterrupt.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 120
    while not (out / "rules.json").is_file() and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(3)  # the workers are training
    process.send_signal(signal.SIGINT)
    output, _ = process.communicate(timeout=120)
    assert process.returncode == 130, output
    assert "run the same command again" in words(output)
    leftovers = [p.name for p in (out / "runs").glob("*")] if (out / "runs").exists() else []
    assert not [name for name in leftovers if name.endswith(".tmp")]
    # Whatever finished is whole: each CSV has its sidecar.
    for csv in (out / "runs").glob("*__s?.csv") if (out / "runs").exists() else []:
        assert csv.with_suffix(".json").is_file()


@pytest.mark.skipif(os.environ.get("ESA_SKIP_RAY") == "1", reason="ESA_SKIP_RAY=1")
def test_ray_runs_each_run_as_a_task(tmp_path, settings, capsys):
    out = tmp_path / "out"
    assert cli.main([*args(out, settings, "--arms", "baseline,esa", "--ray", "local")]) == 0
    assert len(list((out / "runs").glob("*__s?.csv"))) == 4
    assert (out / "learning_curves.png").is_file()
    assert "Ray:" in capsys.readouterr().out
    # The Ray it started is stopped again, so a later ray.init in this process works.
    import ray

    assert not ray.is_initialized()
