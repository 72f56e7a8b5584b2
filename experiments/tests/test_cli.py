"""Bad command-line input gets a clear error (exit code 2) and runs nothing."""

import pytest

from esa_experiments.commands import Plot, Run, main, parse
from esa_experiments.studies import STUDY_NAMES


def run_cli(tmp_path, capsys, *argv):
    code = main(["--root", str(tmp_path), *argv])
    out = capsys.readouterr()
    return code, " ".join((out.out + out.err).split())


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["run", "nope"],
            f"expected a study in {list(STUDY_NAMES)}, got 'nope'",
        ),
        (["plot", "nope"], "expected a study in"),
        (["run", "paper_figures", "--methods", "ppo", "td3"], "unknown methods ['td3']"),
        (["run", "paper_figures", "--methods", "ppo,bogus"], "unknown methods ['bogus']"),
        (["run", "paper_figures", "--envs", "CartPole-v1"], "unknown envs ['CartPole-v1']"),
        (["run", "paper_ablations", "--envs", "Hopper-v5"], "unknown envs ['Hopper-v5']"),
        (
            ["run", "example1", "--seeds", "4-1"],
            "--seeds: expected a range low-high with low <= high",
        ),
        (["run", "example1", "--seeds", "x"], "--seeds: expected seeds like"),
        (["run", "example1", "--seeds", "-2"], "--seeds: expected seeds like"),
        (["run", "example1", "--jobs", "0"], "--jobs: expected an integer >= 1, got 0"),
        (["run", "example1", "--budget", "huge"], "--budget: expected one of ['smoke', 'full']"),
    ],
)
def test_bad_input_is_rejected(tmp_path, capsys, argv, message):
    code, out = run_cli(tmp_path, capsys, *argv)
    assert code == 2
    assert "error:" in out and message in out
    assert not (tmp_path / "results-smoke").exists() and not (tmp_path / "results").exists()


def test_plot_before_running_is_a_clear_error(tmp_path, capsys):
    code, out = run_cli(tmp_path, capsys, "plot", "paper_figures")
    assert code == 2 and "run the study first" in out


def test_dry_run_lists_the_selection(tmp_path, capsys):
    code, out = run_cli(
        tmp_path,
        capsys,
        "run",
        "paper_figures",
        "--dry-run",
        "--seeds",
        "0-1",
        "--methods",
        "ppo",
        "sac",
        "--envs",
        "Hopper-v5",
    )
    assert code == 0
    assert "4 runs, 0 done, 0 stale" in out
    assert out.count("would run") == 4
    assert "would run Hopper-v5 sac s1 (300 steps)" in out
    assert not (tmp_path / "results-smoke").exists()


def test_list_shows_every_study(tmp_path, capsys):
    code, out = run_cli(tmp_path, capsys, "list")
    assert code == 0
    for name in STUDY_NAMES:
        assert f"{name}:" in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["run", "example1", "--jobs", "x"], "--jobs"),
        (["run", "example1", "--bogus"], "--bogus"),
        (["run"], "STUDY"),
        (["nope"], "nope"),
        ([], "subcommand"),
    ],
)
def test_malformed_command_lines_exit_with_code_2(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.setenv("COLUMNS", "400")
    with pytest.raises(SystemExit) as exit_:
        run_cli(tmp_path, capsys, *argv)
    assert exit_.value.code == 2
    assert message in " ".join(capsys.readouterr().err.split())
    assert not (tmp_path / "results-smoke").exists()


def test_run_options_parse_into_the_run_command(tmp_path):
    cli = parse(
        ["--root", str(tmp_path), "run", "paper_figures", "--budget", "full", "--seeds", "0-4"]
        + ["--jobs", "2", "--methods", "ppo", "sac,td3", "--envs", "Hopper-v5", "--dry-run"]
    )
    assert cli.root == tmp_path
    assert cli.command == Run(
        study="paper_figures",
        budget="full",
        seeds="0-4",
        jobs=2,
        methods=("ppo", "sac,td3"),
        envs=("Hopper-v5",),
        dry_run=True,
    )
    assert parse(["plot", "paper_figures"]).command == Plot(study="paper_figures", budget="smoke")


def test_help_documents_every_run_option(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "400")  # one line per option, whatever the terminal
    with pytest.raises(SystemExit) as exit_:
        parse(["run", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for flag in ("--budget", "--seeds", "--jobs", "--methods", "--envs", "--dry-run"):
        assert flag in text
    assert "one of example1, confirmation" in text and "Parallel worker processes" in text
