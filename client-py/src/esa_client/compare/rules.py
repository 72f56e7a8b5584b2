"""A comparison's rules: what is run, how it is measured and how it is decided.

The rules are written to ``<out>/rules.json`` before the first run. A folder that holds
runs refuses other rules: results are never mixed across settings, and the decision
cannot be changed after the data are seen. The same rules again (the same command) go
on where the folder stopped.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any

from esa_client.compare.runs import RunFolder, RunSpec, atomic_write_text

ALGOS = ("ppo", "sac", "td3")
ARMS = ("baseline", "esa", "placebo", "gradient")
"""The arms: the plain algorithm, its ESA drop-in, and the drop-in's two controls."""

DEFAULT_ARMS = ("baseline", "esa", "placebo")

ARM_LABELS = {
    "baseline": "{ALGO}",
    "esa": "ESA{ALGO}",
    "placebo": "ESA{ALGO} placebo",
    "gradient": "ESA{ALGO} gradient control",
}

METRIC = (
    "the deterministic evaluation return's area under the curve divided by its step span "
    "(the average return over training) per run: primary over the first third of the "
    "budget (how fast it learns), secondary over the whole curve"
)
DECISION = (
    "per metric, each ESA arm against the baseline and ESA against each control on the "
    "seeds both finished: P(arm better) with its 95 % stratified-bootstrap CI (rliable) "
    "and a two-sided Mann-Whitney U test, Holm-corrected over the comparisons of the metric; "
    "better/worse when the corrected p < 0.05, in the direction of P(arm better), else "
    "equal; 'too few seeds to tell' when no outcome of that many seeds could reach "
    "p < 0.05. ESA helps on the task when it is better than both the baseline and the "
    "placebo on the primary metric"
)


@dataclass(frozen=True)
class Rules:
    """Everything that fixes a comparison's results and verdict.

    Attributes:
        env: a gymnasium id or ``module:factory``.
        algo: ``ppo``, ``sac`` or ``td3``.
        arms: the arms run, in order.
        seeds: the seeds every arm runs, all of them, none dropped.
        steps: environment steps per run.
        eval_every: environment steps between two evaluations.
        eval_episodes: deterministic episodes per evaluation.
        hyperparams: the settings (:class:`~esa_client.compare.hyperparams.Hyperparams`
            as a dict), the same for every arm.
        metric: what is measured (fixed text).
        decision: how it is decided (fixed text).
    """

    env: str
    algo: str
    arms: tuple[str, ...]
    seeds: tuple[int, ...]
    steps: int
    eval_every: int
    eval_episodes: int
    hyperparams: dict[str, Any] = field(default_factory=dict)
    metric: str = METRIC
    decision: str = DECISION

    def __post_init__(self) -> None:
        """Checks every field; a bad value raises ``ValueError`` naming it."""
        if self.algo not in ALGOS:
            raise ValueError(f"expected --algo in {ALGOS}, got {self.algo!r}")
        unknown = [arm for arm in self.arms if arm not in ARMS]
        if unknown or not self.arms or len(set(self.arms)) != len(self.arms):
            raise ValueError(f"expected distinct --arms from {ARMS}, got {list(self.arms)}")
        if len(self.seeds) < 1 or min(self.seeds) < 0:
            raise ValueError(f"expected at least one seed >= 0, got {list(self.seeds)}")
        for name in ("steps", "eval_every", "eval_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(
                    f"expected --{name.replace('_', '-')} >= 1, got {getattr(self, name)}"
                )
        if self.eval_every > self.steps:
            raise ValueError(
                f"expected --eval-every <= --steps ({self.steps}), got {self.eval_every}"
            )

    def label(self, arm: str) -> str:
        """The arm's display name (``PPO``, ``ESAPPO``, ``ESAPPO placebo``, ...)."""
        return ARM_LABELS[arm].format(ALGO=self.algo.upper())

    def to_json(self) -> str:
        """The rules as ``rules.json`` holds them."""
        return json.dumps(asdict(self), indent=2, sort_keys=True, default=list) + "\n"

    def specs(self) -> list[RunSpec]:
        """Every run, seed-major: each seed runs every arm before the next seed starts.

        A comparison cut short therefore compares every arm on the seeds it finished.
        """
        config = {
            "env": self.env,
            "algo": self.algo,
            "total_steps": self.steps,
            "eval_every": self.eval_every,
            "eval_episodes": self.eval_episodes,
            "hyperparams": self.hyperparams,
            "uses_server": False,
        }
        return [
            RunSpec("compare", self.env, arm, seed, "full", config)
            for seed in self.seeds
            for arm in self.arms
        ]


def fix_rules(rules: Rules, folder: RunFolder) -> None:
    """Writes ``rules`` to the folder, or checks them against the rules its runs were made by.

    Raises:
        ValueError: the folder holds runs made under other rules (the message names the
            fields that differ and the way out).
    """
    path = folder.dir / "rules.json"
    text = rules.to_json()
    has_runs = folder.runs_dir.is_dir() and any(folder.runs_dir.glob("*.csv"))
    if path.is_file() and has_runs:
        old = json.loads(path.read_text())
        new = json.loads(text)
        changed = sorted(key for key in set(old) | set(new) if old.get(key) != new.get(key))
        if changed:
            raise ValueError(
                f"expected the rules of the runs in {folder.dir} (rules.json), got other "
                f"{', '.join(changed)}: results under other rules go to another --out"
            )
        return
    atomic_write_text(path, text)
