"""The studies, one readable module each (cleanrl style).

Every study module defines:

* ``NAME``, ``DESCRIPTION``, ``ENVS`` and ``METHODS`` (what ``--envs`` and
  ``--methods`` may select) and ``DEFAULT_SEEDS``;
* ``Args``, a dataclass of the study's arguments, and ``BUDGETS``, one
  ``Args`` per budget (``smoke``, ``full``): the budgets live in the code;
* ``specs(args, budget, seeds, envs, methods) -> list[RunSpec]``;
* ``run(spec, progress) -> RunResult``: one run, in a worker process;
* ``report(store, args) -> str``: writes the study's PNGs and Markdown table
  from the finished runs and returns the Markdown section for RESULTS.md.

"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

from esa_client.compare.evaluation import ProgressFn

from esa_experiments.runs import RunResult, RunSpec, RunStore

STUDY_NAMES = (
    "example1",
    "confirmation",
    "seeking_offline",
    "seeking",
    "zoo_baselines",
    "paper_regime",
    "paper_figures",
    "paper_ablations",
    "rllib_ppo",
)
"""The live studies. Superseded ones left the tree (their code is in the history, their
committed results and provenance stay under ``results/``; RESULTS.md names both)."""


class Study(Protocol):
    """What the runner needs from a study module (see the package docstring)."""

    NAME: str
    DESCRIPTION: str
    ENVS: tuple[str, ...]
    METHODS: tuple[str, ...]
    DEFAULT_SEEDS: str
    BUDGETS: dict[str, Any]
    specs: Callable[[Any, str, list[int], tuple[str, ...], tuple[str, ...]], list[RunSpec]]
    run: Callable[[RunSpec, ProgressFn], RunResult]
    report: Callable[[RunStore, Any], str]


def load_study(name: str) -> Study:
    """Imports the study module called ``name``.

    Raises:
        ValueError: for an unknown study (the message lists the known ones).
    """
    if name not in STUDY_NAMES:
        raise ValueError(f"expected a study in {list(STUDY_NAMES)}, got {name!r}")
    module: ModuleType = importlib.import_module(f"{__name__}.{name}")
    return module


@dataclass(frozen=True)
class StudyJob:
    """The runner's :class:`~esa_client.compare.execution.Job` for the studies' runs.

    Attributes:
        base: folder holding the results folders (default: ``experiments/``).
        studies: the studies whose code the workers import when they start.
    """

    base: Path | None = None
    studies: tuple[str, ...] = field(default=())

    def folder(self, spec: RunSpec) -> RunStore:
        """The study's results folder under the run's budget."""
        return RunStore(spec.study, spec.budget, self.base)

    def prepare(self) -> None:
        """Imports the trainers and the studies' code."""
        import esa_client.sb3  # noqa: F401

        for name in self.studies:
            load_study(name)

    def run(self, spec: RunSpec, progress: ProgressFn) -> RunResult:
        """The run's study trains and evaluates it."""
        return load_study(spec.study).run(spec, progress)
