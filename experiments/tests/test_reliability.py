"""The rliable statistics and the verdicts RESULTS.md states per env."""

import numpy as np
import pandas as pd
import pytest
from rliable import metrics

from esa_experiments.reliability import iqm_curve, probability_of_improvement, statistics, verdict


def runs(method: str, env: str, aucs: list[float]) -> pd.DataFrame:
    """One flat evaluation curve per seed, so each run's AUC is the given value."""
    rows = []
    for seed, auc in enumerate(aucs):
        for step in (0, 1000, 2000):
            rows.append(
                {
                    "env": env,
                    "method": method,
                    "seed": seed,
                    "step": step,
                    "return_mean": auc,
                    "train_seconds": 1.0,
                    "train_cpu_seconds": 1.0,
                }
            )
    return pd.DataFrame(rows)


@pytest.mark.parametrize(
    "low, high, expected", [(0.6, 0.9, "better"), (0.1, 0.4, "worse"), (0.3, 0.7, "equal")]
)
def test_verdict_needs_the_ci_to_exclude_one_half(low, high, expected):
    assert verdict(low, high) == expected


def test_probability_of_improvement_of_separated_samples():
    better = np.arange(10.0, 20.0)
    worse = np.arange(0.0, 10.0)
    p, low, high = probability_of_improvement(better, worse)
    assert p == 1.0 and low == 1.0 and high == 1.0
    p, low, high = probability_of_improvement(worse, better)
    assert p == 0.0 and high == 0.0
    same = probability_of_improvement(better, better)
    assert same[0] == pytest.approx(0.5) and same[1] < 0.5 < same[2]


def test_statistics_table_compares_each_arm_with_its_baseline():
    frame = pd.concat(
        [
            runs("ppo", "E", [100, 110, 120, 130, 140]),
            runs("ppo_esa", "E", [200, 210, 220, 230, 240]),
            runs("ppo_qgrad", "E", [100, 110, 120, 130, 140]),
        ]
    )
    table = statistics(frame, ["E"], ["ppo", "ppo_esa", "ppo_qgrad"]).set_index("method")
    assert table.loc["PPO", "verdict"] == ""
    assert table.loc["PPO+ESA", "verdict"].startswith("**better**")
    assert table.loc["PPO+gradient", "verdict"].startswith("**equal**")
    assert table.loc["PPO+ESA", "IQM AUC [95% CI]"].startswith("220.0")
    # Reproducible: the bootstrap is seeded.
    again = statistics(frame, ["E"], ["ppo", "ppo_esa", "ppo_qgrad"]).set_index("method")
    pd.testing.assert_frame_equal(table, again)


def test_iqm_curve_is_the_interquartile_mean_at_every_point():
    # Four seeds: the IQM drops the lowest and the highest, so the outlier 1000 does not count.
    scores = np.array([[5.0, 0.0], [5.0, 10.0], [5.0, 20.0], [5.0, 1000.0]])
    iqm, low, high = iqm_curve(scores)
    np.testing.assert_allclose(iqm, [5.0, 15.0])
    expected = [metrics.aggregate_iqm(scores[:, point]) for point in range(scores.shape[1])]
    np.testing.assert_allclose(iqm, expected)
    # Identical seeds leave nothing to resample: the band is the point.
    assert low[0] == high[0] == 5.0
    assert 0.0 <= low[1] < 15.0 < high[1] <= 1000.0


def test_iqm_curve_band_is_the_statistics_table_confidence_interval():
    aucs = [3.0, 8.0, 1.0, 9.0, 4.0, 7.0]
    table = statistics(runs("ppo", "E", aucs), ["E"], ["ppo"])
    iqm, low, high = iqm_curve(np.array(aucs)[:, None])
    assert table["IQM AUC [95% CI]"].iloc[0] == f"{iqm[0]:.1f} [{low[0]:.1f}, {high[0]:.1f}]"
    # Seeded on every call: the same scores give the same band, whatever was drawn before.
    np.random.rand(7)
    np.testing.assert_array_equal(iqm_curve(np.array(aucs)[:, None])[1], low)


@pytest.mark.parametrize(
    ("scores", "message"),
    [
        (np.zeros((0, 3)), r"expected a non-empty array \(runs, points\), got shape \(0, 3\)"),
        (np.zeros(3), r"expected a non-empty array \(runs, points\), got shape \(3,\)"),
        (np.array([[1.0, np.nan]]), "expected finite scores, got 1 NaN or infinite value"),
    ],
)
def test_iqm_curve_rejects_what_is_not_a_finite_runs_by_points_array(scores, message):
    with pytest.raises(ValueError, match=message):
        iqm_curve(scores)
