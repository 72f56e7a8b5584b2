"""Where the studies' runs live: ``results`` for the ``full`` budget, ``results-smoke`` else.

A study's runs are kept by :class:`esa_client.compare.runs.RunFolder` (the same
bookkeeping ``esa-compare`` uses); ``full`` budget results go to ``experiments/results``
(committed), every other budget to ``experiments/results-smoke`` (git-ignored).
"""

from __future__ import annotations

from pathlib import Path

from esa_client.compare.runs import (
    BUDGETS,
    RunFolder,
    RunResult,
    RunSpec,
    atomic_write_text,
    parse_seeds,
)

__all__ = [
    "BUDGETS",
    "EXPERIMENTS_DIR",
    "RunResult",
    "RunSpec",
    "RunStore",
    "atomic_write_text",
    "parse_seeds",
    "results_root",
]

EXPERIMENTS_DIR = Path(__file__).resolve().parents[2]
"""The ``experiments/`` folder (this package is installed editable from it)."""


def results_root(budget: str, base: Path | None = None) -> Path:
    """Where a budget's results live: ``results`` for ``full``, ``results-smoke`` otherwise."""
    if budget not in BUDGETS:
        raise ValueError(f"expected budget in {BUDGETS}, got {budget!r}")
    base = EXPERIMENTS_DIR if base is None else base
    return base / ("results" if budget == "full" else "results-smoke")


class RunStore(RunFolder):
    """The results folder of one study under one budget.

    Args:
        study: study name.
        budget: ``smoke`` or ``full``.
        base: folder holding ``results``/``results-smoke`` (default: ``experiments/``).
    """

    def __init__(self, study: str, budget: str, base: Path | None = None) -> None:
        """Points at the study's folder (nothing is created until a write)."""
        self.study = study
        self.budget = budget
        self.base = EXPERIMENTS_DIR if base is None else base
        super().__init__(results_root(budget, self.base) / study)

    def relative(self, path: Path) -> str:
        """``path`` relative to the folder holding RESULTS.md, for Markdown links."""
        return path.relative_to(self.base).as_posix()
