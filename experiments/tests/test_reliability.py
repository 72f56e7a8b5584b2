"""The rliable statistics: P(X > Y) and its verdict, and the IQM curves of the figures."""

import numpy as np
import pytest
from esa_client.compare.reliability import (
    REPS,
    SEED,
    iqm_curve,
    probability_of_improvement,
    verdict,
)
from rliable import library as rly
from rliable import metrics


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


def test_iqm_curve_band_is_rliables_interval_of_the_iqm():
    aucs = np.array([3.0, 8.0, 1.0, 9.0, 4.0, 7.0])
    np.random.seed(SEED)
    point, ci = rly.get_interval_estimates(
        {"m": aucs[:, None]}, lambda x: np.array([metrics.aggregate_iqm(x)]), reps=REPS
    )
    iqm, low, high = iqm_curve(aucs[:, None])
    np.testing.assert_allclose([iqm[0], low[0], high[0]], [point["m"][0], *ci["m"][:, 0]])
    # Seeded on every call: the same scores give the same band, whatever was drawn before.
    np.random.rand(7)
    np.testing.assert_array_equal(iqm_curve(aucs[:, None])[1], low)


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
