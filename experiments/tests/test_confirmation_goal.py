"""The confirmation study's goal line, read off the shipped defaults' verdict rows."""

import pandas as pd
import pytest

from esa_experiments.algorithms import LABELS
from esa_experiments.studies import confirmation


def _verdicts(verdict_of: dict[tuple[str, str], str], seeds: int = 20) -> pd.DataFrame:
    """Verdict rows of every shipped default vs its baseline; ``equal`` unless named."""
    rows = [
        {
            "env": env,
            "method": LABELS[method],
            "against": "base (baseline)",
            "seeds": seeds,
            "verdict": verdict_of.get((family, env), "equal"),
        }
        for family, method in confirmation.SHIPPED.items()
        for env in confirmation.ENVS_OF[family]
    ]
    return pd.DataFrame(rows)


BETTER = "**better**"


@pytest.mark.parametrize(
    ("verdict_of", "expected"),
    [
        (
            {
                ("sac", "Quadrotor-eight"): BETTER,
                ("ppo", "Hopper-v5"): BETTER,
                ("td3", "Quadrotor-eight"): BETTER,
            },
            "reached. Better on 3, worse on 0.",
        ),
        (
            {
                ("ppo", "Hopper-v5"): BETTER,
                ("ppo", "InvertedPendulum-v5"): BETTER,
                ("sac", "Hopper-v5"): BETTER,
            },
            "not reached. Better on 3, worse on 0.",
        ),
        (
            {
                ("sac", "Quadrotor-eight"): BETTER,
                ("ppo", "Hopper-v5"): BETTER,
                ("td3", "Quadrotor-eight"): BETTER,
                ("ppo", "InvertedPendulum-v5"): "**worse**",
            },
            "not reached. Better on 3, worse on 1.",
        ),
    ],
)
def test_goal_needs_three_better_one_on_the_quadrotor_and_none_worse(verdict_of, expected):
    assert confirmation._goal(_verdicts(verdict_of)).rstrip().endswith(expected)


def test_goal_stays_open_until_every_row_has_all_seeds():
    text = confirmation._goal(_verdicts({}, seeds=19))
    assert "open (0 of 8 rows have all 20 seeds)" in text
    assert "equal (interim, 19 seeds)" in text
    assert text.rstrip().endswith("So far better on 0, worse on 0.")
    assert "not run yet" in text  # the off-policy controls' rows are missing here


def test_goal_of_no_verdicts_says_so():
    assert confirmation._goal(pd.DataFrame()).startswith("(no comparison")
