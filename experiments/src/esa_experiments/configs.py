"""The hyperparameter file ``experiments/configs/algorithms.toml``.

It is layered: a base table overridden by a per-env table. Resolved values are
plain dicts so they can be stored in run sidecars and fingerprinted. ESA has no
file: its presets are ``esa_client``'s own (see :mod:`esa_experiments.algorithms`).
:func:`lookup` resolves the names of the in-code tables (methods, tasks).
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from esa_experiments.runs import EXPERIMENTS_DIR

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

CONFIG_DIR = EXPERIMENTS_DIR / "configs"

_T = TypeVar("_T")


def lookup(table: Mapping[str, _T], key: str, kind: str) -> _T:
    """Returns ``table[key]``.

    Args:
        table: A table of named entries.
        key: The name.
        kind: What an entry is, with its article (``"a method"``), for the message.

    Raises:
        ValueError: for an unknown name (the message lists the known ones).
    """
    try:
        return table[key]
    except KeyError:
        raise ValueError(f"expected {kind} in {sorted(table)}, got {key!r}") from None


def _load(path: Path) -> dict[str, Any]:
    with path.open("rb") as handle:
        table: dict[str, Any] = tomllib.load(handle)
    return table


def algorithm_hyperparams(family: str, env: str, path: Path | None = None) -> dict[str, Any]:
    """Hyperparameters of an algorithm family (``ppo``, ``sac``, ``ddpg``) on ``env``.

    Raises:
        ValueError: if the family has no table in the file.
    """
    table = _load(path or CONFIG_DIR / "algorithms.toml")
    if family not in table:
        raise ValueError(f"expected a [{family}] table in algorithms.toml, got {sorted(table)}")
    base = {k: v for k, v in table[family].items() if k != "env"}
    return {**base, **table[family].get("env", {}).get(env, {})}
