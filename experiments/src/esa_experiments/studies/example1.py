"""Example 1 of the paper (Figure 2): ESC vs search gradient vs gradient descent.

Minimize ``J(u) = (u1 - 0.1)^2 + (u2 - 0.5)^2`` (``static``) and the moving
``J(u, t) = (u1 - 0.1 t)^2 + (u2 - 0.5 t)^2`` (``timevarying``) from
``u(0) = (2, 2)``, one update per time step of ``dt = 0.01`` s.

* ``esc``: extremum seeking THROUGH THE REAL esa-server (one session, the
  paper's ``K = 0.2``, ``w = (60, 75)`` rad/s, ``alpha = 0.25``). The server
  maximizes, so it is fed ``Q = -J``. The "action" it improves is the fixed
  start ``(2, 2)``; the shift ``v`` it learns moves the estimate
  ``u = (2, 2) + v`` (the paper's ``v(t)`` with ``v(0) = u(0)``); ``J_probe``
  is J at the oscillating probe (the paper's dotted ``u(t)`` curve). One J
  query per step.
* ``pg<N>``: search gradient / policy gradient (Wierstra et al. 2014) on a
  Gaussian ``N(mu, sigma^2 I)`` with ``sigma = K``: per step, N samples,
  ``mu += eta * mean_i (Q_i - b) (u_i - mu) / sigma^2`` with the baseline ``b``
  an exponential moving average (0.9) of earlier batch means (independent of
  the current samples, so the estimate stays unbiased). N J queries per step.
* ``gd``: gradient descent with the analytic gradient, ``u -= eta * grad J``.

Step size: ``eta = alpha * K / 2 = 0.025``, the gain of the ESC averaged
dynamics (the Appendix of the paper: ``v' ~ -(alpha K / 2) J'(v)``), so all
methods have the same nominal rate and differ only in how they estimate the
gradient. For a quadratic J the Gaussian-smoothed gradient equals the true
one, so PG follows GD in expectation and its lag is pure sampling noise.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from esa_client.compare.evaluation import ProgressFn
from esa_client.compare.plotting import STATISTIC, iqm_band
from matplotlib.figure import Figure

from esa_experiments.runs import RunResult, RunSpec, RunStore

NAME = "example1"
DESCRIPTION = "Paper Example 1 / Figure 2: ESC (via the server) vs search gradient vs GD"
ENVS = ("static", "timevarying")
METHODS = ("esc", "pg1", "pg10", "pg100", "gd")
DEFAULT_SEEDS = "0-4"
LABELS = {
    "esc": "ESC (esa-server), 1 query/step",
    "pg1": "search gradient, 1 sample/update",
    "pg10": "search gradient, 10 samples/update",
    "pg100": "search gradient, 100 samples/update",
    "gd": "gradient descent (analytic)",
}

START = (2.0, 2.0)
OPTIMUM = np.array([0.1, 0.5])


@dataclass(frozen=True)
class Args:
    """Arguments of Example 1 (the paper's values)."""

    horizon: float = 5.0
    """Simulated seconds."""
    dt: float = 0.01
    amplitude: float = 0.2
    """ESC amplitude K; also the search-gradient sigma."""
    frequency: tuple[float, float] = (60.0, 75.0)
    learning_rate: float = 0.25
    baseline_decay: float = 0.9
    """EMA coefficient of the search-gradient baseline."""

    @property
    def eta(self) -> float:
        """Step size of GD and search gradient: the ESC averaged gain alpha K / 2."""
        return self.learning_rate * self.amplitude / 2

    @property
    def steps(self) -> int:
        """Number of updates (time steps)."""
        return int(round(self.horizon / self.dt))


# Example 1 is cheap: the smoke budget is the full experiment with one seed.
BUDGETS = {"smoke": Args(), "full": Args()}


def objective(u: np.ndarray, t: float, env: str) -> np.ndarray:
    """J at inputs ``u`` (shape ``(..., 2)``) and time ``t`` (``env``: static or timevarying)."""
    optimum = OPTIMUM * t if env == "timevarying" else OPTIMUM
    cost: np.ndarray = np.sum((np.asarray(u) - optimum) ** 2, axis=-1)
    return cost


def gradient(u: np.ndarray, t: float, env: str) -> np.ndarray:
    """Analytic gradient of J."""
    optimum = OPTIMUM * t if env == "timevarying" else OPTIMUM
    slope: np.ndarray = 2 * (u - optimum)
    return slope


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """One run per (objective, method, seed); ESC and GD are deterministic but cheap."""
    config = {**asdict(args), "total_steps": args.steps}
    return [
        RunSpec(NAME, env, method, seed, budget, {**config, "uses_server": method == "esc"})
        for env in envs
        for method in methods
        for seed in seeds
    ]


def _run_esc(args: Args, env: str, progress: ProgressFn) -> pd.DataFrame:
    from esa_client import EsaClient, SessionConfig

    config = SessionConfig(
        action_dim=2,
        dt=args.dt,
        amplitude=args.amplitude,
        frequency=args.frequency,
        learning_rate=args.learning_rate,
    )
    start = np.array(START)
    rows: list[tuple[float, ...]] = []
    with EsaClient.spawn() as client:
        session = client.create_session(config)
        estimate = start
        for k in range(args.steps):
            t = k * args.dt
            rows.append((t, float(objective(estimate, t, env))))
            probe = session.probe(start, episode_start=k == 0)
            j_probe = float(objective(probe, t, env))
            estimate = session.report(-j_probe)
            rows[-1] += (j_probe,)
            progress(k + 1)
        session.close()
    return pd.DataFrame(rows, columns=["t", "J", "J_probe"])


def _run_search_gradient(
    args: Args, env: str, samples: int, seed: int, progress: ProgressFn
) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    mu = np.array(START)
    sigma = args.amplitude
    baseline: float | None = None
    rows = []
    for k in range(args.steps):
        t = k * args.dt
        u = mu + sigma * rng.standard_normal((samples, 2))
        q = -objective(u, t, env)
        b = float(q.mean()) if baseline is None else baseline
        grad = np.mean((q - b)[:, None] * (u - mu), axis=0) / sigma**2
        rows.append((t, float(objective(mu, t, env)), float(-q.mean())))
        mu = mu + args.eta * grad
        baseline = (
            float(q.mean())
            if baseline is None
            else (args.baseline_decay * baseline + (1 - args.baseline_decay) * float(q.mean()))
        )
        progress(k + 1)
    return pd.DataFrame(rows, columns=["t", "J", "J_probe"])


def _run_gradient_descent(args: Args, env: str, progress: ProgressFn) -> pd.DataFrame:
    u = np.array(START)
    rows = []
    for k in range(args.steps):
        t = k * args.dt
        j = float(objective(u, t, env))
        rows.append((t, j, j))
        u = u - args.eta * gradient(u, t, env)
        progress(k + 1)
    return pd.DataFrame(rows, columns=["t", "J", "J_probe"])


def run(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """One trajectory of one method on one objective."""
    config = {k: v for k, v in spec.config.items() if k not in ("total_steps", "uses_server")}
    config["frequency"] = tuple(config["frequency"])
    args = Args(**config)
    if spec.method == "esc":
        return RunResult(_run_esc(args, spec.env, progress), {"queries_per_step": 1})
    if spec.method == "gd":
        return RunResult(_run_gradient_descent(args, spec.env, progress), {"queries_per_step": 0})
    samples = int(spec.method.removeprefix("pg"))
    frame = _run_search_gradient(args, spec.env, samples, spec.seed, progress)
    return RunResult(frame, {"queries_per_step": samples})


def report(store: RunStore, args: Args) -> str:
    """Writes the two-panel figure and a table of J at fixed times."""
    frame = store.load()
    figure = example1_figure(frame, LABELS, store.artifact("example1.png"))
    times = [0.5, 1.0, 2.0, 4.0, args.horizon - args.dt]
    lines = [
        "| objective | method | " + " | ".join(f"J(t={t:g}s)" for t in times) + " |",
        "|---|---|" + "---|" * len(times),
    ]
    for env in ENVS:
        for method in METHODS:
            sub = frame[(frame.env == env) & (frame.method == method)]
            if sub.empty:
                continue
            cells = []
            for t in times:
                at = sub[np.isclose(sub.t, t)].J
                cells.append(f"{at.mean():.4f} ± {at.sem() if len(at) > 1 else 0:.4f}")
            lines.append(f"| {env} | {LABELS[method]} | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    store.artifact("table.md").write_text(table + "\n")
    seeds = frame.seed.nunique()
    return (
        f"![Example 1]({store.relative(figure)})\n\n"
        f"J at the estimate (ESC: (2,2)+v; PG: the Gaussian mean; GD: the iterate), "
        f"mean ± standard error over {seeds} seed(s):\n\n{table}\n"
    )


def example1_figure(frame: pd.DataFrame, labels: dict[str, str], path: Path) -> Path:
    """The two panels of the paper's Figure 2: J vs time, static and time-varying (IQM, CI)."""
    fig = Figure(figsize=(12, 4.2), layout="constrained")
    axes = fig.subplots(1, 2)
    titles = {"static": "(a) static J(u)", "timevarying": "(b) time-varying J(u, t)"}
    for ax, env in zip(axes, titles, strict=True):
        for method, label in labels.items():
            runs = frame[(frame.env == env) & (frame.method == method)]
            if runs.empty:
                continue
            iqm_band(ax, runs, "t", "J", label)
            if method == "esc":
                iqm_band(
                    ax, runs, "t", "J_probe", "ESC probe u(t)", linestyle=":", color="C0", alpha=0.6
                )
        ax.set_yscale("log")
        ax.set_title(titles[env])
        ax.set_xlabel("t [s]")
        ax.set_ylabel("J, IQM over seeds")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, title=STATISTIC, title_fontsize=7)
    fig.savefig(path, dpi=120)
    return path
