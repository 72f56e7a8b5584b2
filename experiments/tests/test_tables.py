"""Summary statistics, the report helpers' tables and the RESULTS.md section update."""

import numpy as np
import pandas as pd
import pytest
from esa_client.compare.tables import summary, to_markdown

from esa_experiments.reporting import budget_table, update_results, write_verdicts
from esa_experiments.runs import RunStore
from esa_experiments.training import StepBudget


def curve(method, seed, returns, seconds):
    steps = np.arange(len(returns)) * 100
    return pd.DataFrame(
        {
            "env": "E",
            "method": method,
            "seed": seed,
            "step": steps,
            "return_mean": returns,
            "train_seconds": np.linspace(0, seconds, len(returns)),
            "train_cpu_seconds": np.linspace(0, seconds / 2, len(returns)),
        }
    )


def test_summary_metrics():
    frame = pd.concat(
        [
            curve("ppo", 0, [0, 10, 20], 10.0),
            curve("ppo", 1, [0, 20, 40], 10.0),
            curve("ppo_esa", 0, [0, 50, 50], 15.0),
        ]
    )
    table = summary(
        frame,
        ["E"],
        ["ppo", "ppo_esa"],
        {"ppo": "PPO", "ppo_esa": "PPO+ESA"},
        {"E": 30.0},
        {"ppo_esa": "ppo"},
    )
    ppo, esa = table.iloc[0], table.iloc[1]
    assert ppo["final return"] == f"30.0 ± {np.std([20, 40], ddof=1) / np.sqrt(2):.1f}"
    # AUC = trapezoid area / step span: (0+10)/2 + (10+20)/2 = 20 -> 2000 / 200 = 10; seed 1: 20.
    assert ppo["AUC (mean return)"].startswith("15.0 ± 5.0")
    assert ppo["steps to threshold"] == "200 (1/2)"
    assert esa["steps to threshold"] == "100 (1/1)"
    column = "overhead vs base (wall / CPU)"
    assert esa[column] == "1.50x / 1.50x" and ppo[column] == ""
    assert ppo["train s (wall / CPU)"] == "10.0 / 5.0"
    assert ppo["seeds"] == 2 and ppo["steps"] == 200


def test_markdown_table():
    text = to_markdown(pd.DataFrame({"a": [1], "b": ["x"]}))
    assert text == "| a | b |\n|---|---|\n| 1 | x |"


def test_update_results_replaces_only_its_section(tmp_path):
    store = RunStore("paper_figures", "full", tmp_path)
    (tmp_path / "RESULTS.md").write_text("# Results\n\nprose stays\n")
    update_results("paper_figures", "first", store)
    update_results("example1", "other", RunStore("example1", "full", tmp_path))
    update_results("paper_figures", "second", store)
    text = (tmp_path / "RESULTS.md").read_text()
    assert "prose stays" in text and "other" in text
    assert "second" in text and "first" not in text
    assert text.count("<!-- BEGIN paper_figures -->") == 1


def test_smoke_sections_never_touch_results_md(tmp_path):
    target = update_results(
        "paper_figures", "smoke text", RunStore("paper_figures", "smoke", tmp_path)
    )
    assert target == tmp_path / "results-smoke" / "paper_figures" / "section.md"
    assert not (tmp_path / "RESULTS.md").exists()


@pytest.mark.parametrize("returns", [[5.0, 5.0]])
def test_threshold_never_reached(returns):
    table = summary(curve("ppo", 0, returns, 1.0), ["E"], ["ppo"], {}, {"E": 10.0}, {})
    assert table.iloc[0]["steps to threshold"] == "not reached (0/1)"


def test_a_pipe_inside_a_cell_is_escaped():
    text = to_markdown(pd.DataFrame({"KL(b || pi)": ["|v|"]}))
    assert text == "| KL(b \\|\\| pi) |\n|---|\n| \\|v\\| |"


def test_budget_table_shows_no_interval_for_a_family_not_trained():
    table = budget_table({"E": StepBudget(1_000_448, 0, 16_384, 1, 3)})
    assert table.splitlines()[-1] == "| E | 1,000,448 | 0 | 16,384 / - | 3 |"


def test_write_verdicts_writes_both_tables_and_says_when_one_is_empty(tmp_path):
    store = RunStore("study", "full", base=tmp_path)
    primary = pd.DataFrame({"env": ["E"], "verdict": ["equal"]})
    first, whole = write_verdicts(store, primary, pd.DataFrame())
    assert first == to_markdown(primary)
    assert whole == "(no comparison has two seeds yet)"
    assert (store.dir / "verdicts_first.md").read_text() == first + "\n"
    assert (store.dir / "verdicts_whole.md").read_text() == whole + "\n"
