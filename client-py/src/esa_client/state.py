"""What all session implementations share: the state snapshot and one set of argument checks."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ._proto.esa.v1 import esa_pb2
from .config import SessionConfig

F64Array = npt.NDArray[np.float64]
"""Float64 values: actions, probes, Q-values, scales."""

I64Array = npt.NDArray[np.int64]
"""Int64 values: steps, indices."""

BoolArray = npt.NDArray[np.bool_]
"""Booleans: episode-start flags."""


@dataclass(frozen=True)
class SessionProgress:
    """What a session keeps across episodes besides its config (``esa.v1.SessionProgress``).

    Batch answers carry it; a session the server lost is recreated with the last one seen.

    Attributes:
        response_mean_square: The running mean square m (``normalize_response``); None = unset.
    """

    episodes_completed: int
    response_mean_square: float | None = None

    def __post_init__(self) -> None:
        """Checks the values as the server does."""
        if not 0 <= self.episodes_completed < 2**64:
            raise ValueError(
                f"expected episodes_completed in [0, 2**64), got {self.episodes_completed}"
            )
        m = self.response_mean_square
        if m is not None and not (np.isfinite(m) and m >= 0):
            raise ValueError(f"expected a finite response_mean_square >= 0 or None, got {m}")

    def to_proto(self) -> esa_pb2.SessionProgress:
        """The wire form, ``esa.v1.SessionProgress``."""
        message = esa_pb2.SessionProgress(episodes_completed=self.episodes_completed)
        if self.response_mean_square is not None:
            message.response_mean_square = self.response_mean_square
        return message

    @classmethod
    def from_batch_answer(
        cls, episodes: npt.ArrayLike, mean_squares: npt.ArrayLike
    ) -> list[SessionProgress]:
        """Each session's progress from a batch answer's two fields.

        ``episodes`` holds ``episodes_completed``, one per session; ``mean_squares`` holds
        ``response_mean_squares``: one per session (-1: unset), or none.
        """
        counts = np.asarray(episodes, dtype=np.uint64).tolist()
        values = np.asarray(mean_squares, dtype=np.float64).tolist() or [-1.0] * len(counts)
        if len(values) != len(counts):
            raise ValueError(
                f"expected one mean square per session ({len(counts)}), got {len(values)}"
            )
        return [cls(e, None if m < 0 else m) for e, m in zip(counts, values, strict=True)]


@dataclass(frozen=True)
class SessionState:
    """A snapshot of one session (``GetSession``).

    Attributes:
        step: Current step t inside the episode.
        shift: Current shift v, shape ``(action_dim,)``.
        probe_pending: True between a probe and its report.
        response_mean_square: The running mean square m (``normalize_response``); None until a
            non-zero response seeds it.
    """

    config: SessionConfig
    step: int
    episodes_completed: int
    shift: F64Array
    probe_pending: bool
    response_mean_square: float | None = None

    @property
    def progress(self) -> SessionProgress:
        """What the session keeps across episodes: its episode count and mean square."""
        return SessionProgress(self.episodes_completed, self.response_mean_square)

    @classmethod
    def from_proto(cls, message: esa_pb2.GetSessionResponse) -> SessionState:
        """Builds the snapshot from a ``GetSessionResponse``."""
        return cls(
            config=SessionConfig.from_proto(message.config),
            step=message.step,
            episodes_completed=message.episodes_completed,
            shift=np.array(message.shift, dtype=np.float64),
            probe_pending=message.probe_pending,
            response_mean_square=(
                message.response_mean_square if message.HasField("response_mean_square") else None
            ),
        )


def as_batch_configs(
    configs: SessionConfig | Sequence[SessionConfig], n: int | None
) -> tuple[SessionConfig, ...]:
    """Returns one config per session, checking they share one action dimension.

    Args:
        configs: One config for all sessions, or one per session.
        n: Number of sessions; required with a single config, else must match.
    """
    if isinstance(configs, SessionConfig):
        if n is None or n < 1:
            raise ValueError(f"expected n >= 1 sessions for a single config, got {n}")
        return (configs,) * n
    out = tuple(configs)
    if not out or (n is not None and n != len(out)):
        raise ValueError(f"expected {n if n is not None else '>= 1'} configs, got {len(out)}")
    dims = {c.action_dim for c in out}
    if len(dims) != 1:
        raise ValueError(f"expected one action_dim across the batch, got {sorted(dims)}")
    return out


def check_array(
    values: npt.ArrayLike,
    shape: tuple[int, ...],
    name: str,
    *,
    dtype: type[Any] = np.float64,
    finite: bool = False,
    error: Callable[[str], Exception] = ValueError,
) -> npt.NDArray[Any]:
    """Returns ``values`` as a ``dtype`` array named ``name``, checking its shape (and finiteness).

    Raises:
        Exception: ``error``'s, if the shape is wrong or (``finite``) a value is not finite.
    """
    out = np.asarray(values, dtype=dtype)
    if out.shape != shape:
        raise error(f"expected {name} of shape {shape}, got {out.shape}")
    if finite and not np.all(np.isfinite(out)):
        raise error(f"expected finite {name}, got {out!r}")
    return out


def check_indices(indices: npt.ArrayLike | None, n: int) -> I64Array:
    """Returns ``indices`` (default: all N) as an int array, checking the range."""
    if indices is None:
        return np.arange(n, dtype=np.int64)
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"expected indices in [0, {n}), got {idx.tolist()}")
    return idx
