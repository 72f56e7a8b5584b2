"""Command-line parsing shared by the benchmark scripts: one ``--flag`` per dataclass field."""

from __future__ import annotations

import argparse
import dataclasses
from typing import TypeVar

T = TypeVar("T")


def parse_dataclass(cls: type[T], description: str) -> T:
    """Builds ``cls`` from the command line: field ``max_pairs`` is ``--max-pairs``."""
    parser = argparse.ArgumentParser(description=description)
    for field in dataclasses.fields(cls):  # type: ignore[arg-type]
        flag = "--" + field.name.replace("_", "-")
        parser.add_argument(flag, type=type(field.default), default=field.default)
    return cls(**vars(parser.parse_args()))
