"""cleanrl-style command lines: a dataclass of arguments becomes an ``argparse`` parser.

Each field ``name: type = default`` becomes ``--name`` (underscores also accepted as
dashes) with that type and default; booleans get ``--name/--no-name``. The dataclass
docstring is the help text.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections.abc import Sequence
from typing import Any, TypeVar

T = TypeVar("T")


def parse_args(cls: type[T], argv: Sequence[str] | None = None) -> T:
    """Parses ``argv`` (default: ``sys.argv[1:]``) into an instance of the dataclass ``cls``.

    Raises:
        ValueError: if ``cls`` is not a dataclass or a field has no default.
    """
    if not dataclasses.is_dataclass(cls):
        raise ValueError(f"expected a dataclass, got {cls!r}")
    hints = typing.get_type_hints(cls)
    parser = argparse.ArgumentParser(description=(cls.__doc__ or "").strip())
    for field in dataclasses.fields(cls):
        if field.default is not dataclasses.MISSING:
            default: Any = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            raise ValueError(f"expected a default for field {field.name!r} of {cls.__name__}")
        flags = [f"--{field.name.replace('_', '-')}"]
        if "_" in field.name:
            flags.append(f"--{field.name}")
        kind = hints[field.name]
        if kind is bool:
            parser.add_argument(
                *flags, dest=field.name, default=default, action=argparse.BooleanOptionalAction
            )
        else:
            parser.add_argument(
                *flags, dest=field.name, default=default, type=kind, help=f"default: {default}"
            )
    return cls(**vars(parser.parse_args(argv)))
