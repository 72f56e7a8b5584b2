"""Plot flown quadrotor trajectories against the target path: 3-D view and top view (PNG).

The layout follows Figure 4(b, c) of the ESA paper: the target path dashed, each flown
trajectory (e.g. PPO and PPO+ESA, or the PD reference) as a solid line, start points marked.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure


def _as_points(name: str, values: np.ndarray) -> np.ndarray:
    points = np.asarray(values, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2:
        raise ValueError(f"expected {name} of shape (n >= 2, 3), got shape {points.shape}")
    return points


def plot_tracking(
    target: np.ndarray,
    flown: Mapping[str, np.ndarray],
    out_path: str | Path,
    title: str | None = None,
) -> Path:
    """Write a PNG with a 3-D view and a top view of flown trajectories and the target path.

    Args:
        target: Target positions, shape (n, 3) [m].
        flown: Label -> flown positions of shape (m, 3) [m]; at least one.
        out_path: Where to write the PNG; parent folders are created.
        title: Figure title.

    Returns:
        The path of the written PNG.

    Raises:
        ValueError: If an array is not of shape (n >= 2, 3) or ``flown`` is empty.
    """
    target = _as_points("target", target)
    if not flown:
        raise ValueError("expected at least one flown trajectory, got none")
    curves = {label: _as_points(f"flown[{label!r}]", xyz) for label, xyz in flown.items()}

    fig = Figure(figsize=(11, 4.8), layout="constrained")
    ax3d = fig.add_subplot(1, 2, 1, projection="3d")
    ax_top = fig.add_subplot(1, 2, 2)
    ax3d.plot(*target.T, "k--", lw=1.2, label="target")
    ax_top.plot(target[:, 0], target[:, 1], "k--", lw=1.2, label="target")
    for label, xyz in curves.items():
        (line,) = ax3d.plot(*xyz.T, lw=1.6, label=label)
        ax3d.scatter(*xyz[0], color=line.get_color(), marker="o", s=18)
        ax_top.plot(xyz[:, 0], xyz[:, 1], lw=1.6, color=line.get_color(), label=label)
        ax_top.plot(*xyz[0, :2], "o", color=line.get_color(), ms=4)

    everything = np.vstack([target, *curves.values()])
    low, high = everything.min(axis=0), everything.max(axis=0)
    centre, half = (low + high) / 2.0, max(float((high - low).max()) / 2.0, 0.25) * 1.1
    # Equal scales on all axes, so a circle looks like a circle.
    ax3d.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half))
    ax3d.set_zlim(max(0.0, centre[2] - half), centre[2] + half)
    ax3d.set(xlabel="x [m]", ylabel="y [m]", zlabel="z [m]", title="3-D view")
    ax_top.set(xlabel="x [m]", ylabel="y [m]", title="top view", aspect="equal")
    ax_top.grid(alpha=0.3)
    ax_top.legend(loc="best", fontsize="small")
    if title:
        fig.suptitle(title)

    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    return out
