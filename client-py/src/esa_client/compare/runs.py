"""Resumable run bookkeeping: where each run's results live and whether it is done.

One run = (study, env, method, seed) under one budget. A :class:`RunFolder` holds its
``runs/<env>__<method>__s<seed>.csv`` plus a ``.json`` sidecar with the run's full
configuration, both written atomically (temporary file in the same directory, then
``os.replace``) when the run ends, so an interrupted run leaves nothing behind and is
simply run again. A run is done when its CSV exists and its sidecar's fingerprint matches
the configuration asked for now; a CSV from a different configuration (e.g. after a
budget change) is stale and is rerun.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

BUDGETS = ("smoke", "full")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.=+-]*$")


def parse_seeds(text: str) -> list[int]:
    """Parses ``"0-4"``, ``"3"`` or ``"0,2,5-7"`` into sorted unique seeds.

    Raises:
        ValueError: on anything else, negative seeds or an empty/reversed range.
    """
    seeds: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        match = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if match is None:
            raise ValueError(
                f"expected seeds like '0-4', '3' or '0,2,5-7' (non-negative integers), got {text!r}"
            )
        first = int(match.group(1))
        last = int(match.group(2)) if match.group(2) is not None else first
        if last < first:
            raise ValueError(f"expected a range low-high with low <= high, got {part!r}")
        seeds.update(range(first, last + 1))
    return sorted(seeds)


@dataclass(frozen=True)
class RunSpec:
    """One unit of work of a study.

    Attributes:
        study: study name (``example1``, ``paper_figures``, ...).
        env: environment (or objective) name; part of the file name.
        method: method name; part of the file name.
        seed: random seed.
        budget: ``smoke`` or ``full``.
        config: everything else that determines the result (steps, eval
            settings, hyperparameters); JSON-serializable, fingerprinted.
    """

    study: str
    env: str
    method: str
    seed: int
    budget: str
    config: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self) -> None:
        """Validates the names, the seed and the budget."""
        for name in ("study", "method"):
            value = getattr(self, name)
            if not _NAME.match(value):
                raise ValueError(f"expected {name} made of [A-Za-z0-9_.=+-], got {value!r}")
        if self.seed < 0:
            raise ValueError(f"expected seed >= 0, got {self.seed}")
        if self.budget not in BUDGETS:
            raise ValueError(f"expected budget in {BUDGETS}, got {self.budget!r}")

    @property
    def name(self) -> str:
        """File stem ``<env>__<method>__s<seed>`` (``/`` in env ids becomes ``-``)."""
        return f"{self.env.replace('/', '-')}__{self.method}__s{self.seed}"

    @property
    def label(self) -> str:
        """Short human-readable label for progress displays."""
        return f"{self.env} {self.method} s{self.seed}"

    def fingerprint(self) -> str:
        """Hash of everything that determines this run's result."""
        payload = json.dumps(
            {"env": self.env, "method": self.method, "seed": self.seed, "config": self.config},
            sort_keys=True,
            default=str,
        )
        return hashlib.sha256(payload.encode()).hexdigest()[:16]


@dataclass
class RunResult:
    """What a run produces.

    Attributes:
        frame: the run's table, written as ``<name>.csv``.
        meta: extra fields for the ``.json`` sidecar.
        tables: extra tables, written as ``<name>.<key>.csv`` (e.g. a flown trajectory).
    """

    frame: pd.DataFrame
    meta: dict[str, Any] = field(default_factory=dict)
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)


class RunFolder:
    """The results folder of one study: ``runs/`` with one CSV and sidecar per run.

    Args:
        folder: the study's folder (nothing is created until a write).
    """

    def __init__(self, folder: Path) -> None:
        """Points at ``folder``."""
        self.dir = folder
        self.runs_dir = folder / "runs"

    def csv_path(self, spec: RunSpec) -> Path:
        """The run's main CSV (its presence marks the run finished)."""
        return self.runs_dir / f"{spec.name}.csv"

    def meta_path(self, spec: RunSpec) -> Path:
        """The run's JSON sidecar (configuration, fingerprint, timings)."""
        return self.runs_dir / f"{spec.name}.json"

    def status(self, spec: RunSpec) -> str:
        """``"done"``, ``"stale"`` (finished with another configuration) or ``"todo"``."""
        if not self.csv_path(spec).is_file():
            return "todo"
        try:
            meta = json.loads(self.meta_path(spec).read_text())
        except (OSError, ValueError):
            return "stale"
        return "done" if meta.get("fingerprint") == spec.fingerprint() else "stale"

    def pending(self, specs: Iterable[RunSpec]) -> list[RunSpec]:
        """The specs that are not done (todo or stale), in order."""
        return [s for s in specs if self.status(s) != "done"]

    def table_path(self, spec: RunSpec, key: str) -> Path:
        """An extra table of the run."""
        return self.runs_dir / f"{spec.name}.{key}.csv"

    def write(self, spec: RunSpec, result: RunResult) -> Path:
        """Atomically writes a finished run; the main CSV, which marks it done, comes last."""
        for key, table in result.tables.items():
            atomic_write_text(self.table_path(spec, key), table.to_csv(index=False))
        meta = {
            "study": spec.study,
            "env": spec.env,
            "method": spec.method,
            "seed": spec.seed,
            "budget": spec.budget,
            "fingerprint": spec.fingerprint(),
            "config": spec.config,
            **result.meta,
        }
        atomic_write_text(
            self.meta_path(spec), json.dumps(meta, indent=2, sort_keys=True, default=str)
        )
        atomic_write_text(self.csv_path(spec), result.frame.to_csv(index=False))
        return self.csv_path(spec)

    def load(self, table: str | None = None) -> pd.DataFrame:
        """All finished runs of the study as one long frame with env/method/seed columns.

        Args:
            table: an extra table's key instead of the main CSVs.
        """
        frames = []
        for meta_file in sorted(self.runs_dir.glob("*.json")):
            csv_file = meta_file.with_suffix(".csv")
            if not csv_file.is_file():
                continue
            if table is not None:
                csv_file = meta_file.with_suffix(f".{table}.csv")
                if not csv_file.is_file():
                    continue
            meta = json.loads(meta_file.read_text())
            frame = pd.read_csv(csv_file)
            frame.insert(0, "seed", meta["seed"])
            frame.insert(0, "method", meta["method"])
            frame.insert(0, "env", meta["env"])
            frames.append(frame)
        if not frames:
            raise FileNotFoundError(
                f"expected finished runs in {self.runs_dir}, found none: run the study first"
            )
        return pd.concat(frames, ignore_index=True)

    def load_meta(self) -> pd.DataFrame:
        """One row per finished run: its sidecar's fields (the run's config left out)."""
        rows = []
        for meta_file in sorted(self.runs_dir.glob("*.json")):
            if meta_file.with_suffix(".csv").is_file():
                meta = json.loads(meta_file.read_text())
                rows.append({k: v for k, v in meta.items() if k != "config"})
        return pd.DataFrame(rows)

    def artifact(self, name: str) -> Path:
        """Path of a study-level output (PNG, Markdown) in the study folder."""
        self.dir.mkdir(parents=True, exist_ok=True)
        return self.dir / name


def atomic_write_text(path: Path, text: str) -> None:
    """Writes ``text`` to ``path`` so readers see either the old or the whole new file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
