"""Figures: curves of the IQM over seeds with its 95 % bootstrap CI, the verdicts' statistic."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from esa_client.compare.reliability import iqm_curve

STATISTIC = "IQM, 95% bootstrap CI"
"""What every curve and band of these figures shows (legend title)."""


@dataclass(frozen=True)
class Panel:
    """One subplot: some methods' curves on one env.

    Attributes:
        title: subplot title.
        env: env key (the ``env`` column of the runs).
        methods: methods to draw, in legend order.
    """

    title: str
    env: str
    methods: Sequence[str]


def _by_seed(runs: pd.DataFrame, x: str, y: str) -> pd.DataFrame:
    """``y`` with one row per seed and one column per ``x`` value that every seed reached."""
    return runs.pivot(index="seed", columns=x, values=y).dropna(axis="columns")


def iqm_band(ax: Axes, runs: pd.DataFrame, x: str, y: str, label: str, **style: Any) -> object:
    """Draws the IQM of ``y`` over seeds with its 95 % bootstrap CI band; returns its colour."""
    curves = _by_seed(runs, x, y)
    iqm, low, high = iqm_curve(curves.to_numpy(float))
    line = ax.plot(curves.columns, iqm, label=label, **style)[0]
    ax.fill_between(curves.columns, low, high, color=line.get_color(), alpha=0.2, linewidth=0)
    return line.get_color()


def learning_curves(
    frame: pd.DataFrame,
    panels: Sequence[Panel],
    labels: dict[str, str],
    path: Path,
    *,
    suptitle: str = "",
    ncols: int = 2,
    per_seed: bool = False,
) -> Path:
    """Evaluation return vs environment steps, one subplot per panel.

    Each method's curve is the IQM over seeds with its 95 % stratified-bootstrap CI
    (``reliability.iqm_curve``).

    Args:
        frame: finished runs (``RunStore.load``) with ``step`` and ``return_mean``.
        panels: the subplots.
        labels: method -> legend label.
        path: output PNG.
        suptitle: figure title.
        ncols: subplots per row.
        per_seed: also draw each seed's curve, thin, in the method's colour.
    """
    ncols = min(ncols, len(panels))
    nrows = math.ceil(len(panels) / ncols)
    fig = Figure(figsize=(5.5 * ncols, 3.8 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax, panel in zip(axes.flat, panels, strict=False):
        for method in panel.methods:
            runs = frame[(frame.env == panel.env) & (frame.method == method)]
            if runs.empty:
                continue
            seeds = runs.seed.nunique()
            label = f"{labels.get(method, method)} (n={seeds})"
            line = iqm_band(ax, runs, "step", "return_mean", label)
            if per_seed:
                for _, run in runs.groupby("seed"):
                    run = run.sort_values("step")
                    ax.plot(run.step, run.return_mean, color=line, alpha=0.25, linewidth=0.7)
        ax.set_title(panel.title)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("eval return (deterministic), IQM over seeds")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, title=STATISTIC, title_fontsize=7)
    for ax in list(axes.flat)[len(panels) :]:
        ax.set_visible(False)
    if suptitle:
        fig.suptitle(suptitle)
    fig.savefig(path, dpi=120)
    return path
