"""The learning curves draw the verdicts' statistic: the IQM over seeds and its bootstrap CI."""

import numpy as np
import pandas as pd
from esa_client.compare.plotting import Panel, iqm_band, learning_curves
from esa_client.compare.reliability import iqm_curve
from matplotlib.figure import Figure


def runs(returns_by_seed):
    return pd.DataFrame(
        [
            {"env": "E", "method": "ppo", "seed": seed, "step": 1000 * i, "return_mean": value}
            for seed, returns in enumerate(returns_by_seed)
            for i, value in enumerate(returns)
        ]
    )


def test_band_draws_the_iqm_and_its_ci_on_the_steps_every_seed_reached():
    # The last seed stopped one evaluation early: the curve ends where all four have a value.
    frame = runs([[0.0, 10.0, 50.0], [0.0, 20.0, 60.0], [0.0, 30.0, 70.0], [0.0, 900.0]])
    ax = Figure().subplots()
    iqm_band(ax, frame, "step", "return_mean", "PPO")
    line = ax.lines[0]
    np.testing.assert_array_equal(line.get_xdata(), [0, 1000])
    np.testing.assert_allclose(line.get_ydata(), [0.0, 25.0])
    _, low, high = iqm_curve(np.array([[0.0, 10.0], [0.0, 20.0], [0.0, 30.0], [0.0, 900.0]]))
    band = ax.collections[0].get_paths()[0].vertices[:, 1]
    assert set(np.round(band, 9)) == set(np.round(np.concatenate([low, high]), 9))


def test_learning_curves_say_what_they_show(tmp_path, monkeypatch):
    saved = []
    monkeypatch.setattr(Figure, "savefig", lambda figure, *args, **kwargs: saved.append(figure))
    frame = runs([[0.0, 10.0], [1.0, 20.0], [2.0, 30.0]])
    learning_curves(frame, [Panel("E", "E", ["ppo"])], {"ppo": "PPO"}, tmp_path / "c.png")
    ax = saved[0].axes[0]
    assert ax.get_legend().get_title().get_text() == "IQM, 95% bootstrap CI"
    assert "IQM over seeds" in ax.get_ylabel()
    assert [text.get_text() for text in ax.get_legend().get_texts()] == ["PPO (n=3)"]
