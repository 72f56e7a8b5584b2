"""How ``SessionBatch.step`` runs on each transport (its BatchTransport picks the Stepper)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import numpy.typing as npt

from ..state import F64Array
from .messages import LinearCritic, QuadraticCritic

if TYPE_CHECKING:
    from ..session import SessionBatch

Critic = Callable[[F64Array], npt.ArrayLike] | LinearCritic | QuadraticCritic
"""What :meth:`~esa_client.SessionBatch.step` scores the probes with."""

CLOSED_FORM = (LinearCritic, QuadraticCritic)
"""The critics an in-process engine evaluates itself."""


class StepCall(NamedTuple):
    """The arguments of one :meth:`~esa_client.SessionBatch.step`, as it documents them."""

    actions: npt.ArrayLike
    critic: Critic
    episode_starts: npt.ArrayLike | None
    action_scales: npt.ArrayLike | None
    paired: bool


class Stepper:
    """A step as its round trips: the probe waits, and the report rides with the next probe."""

    def step(self, batch: SessionBatch, call: StepCall) -> tuple[F64Array | None, F64Array]:
        """One step of ``batch`` (see :meth:`~esa_client.SessionBatch.step`)."""
        check_critic(call.critic, batch.n, batch.action_dim)
        probes, applied = batch.probe_applied(
            call.actions, call.episode_starts, action_scales=call.action_scales
        )
        q = np.asarray(call.critic(np.concatenate([probes, applied]) if call.paired else probes))
        references = q[batch.n :] if call.paired else None
        batch.report(q[: batch.n], q_references=references, defer=True)
        return probes, applied

    def flush(self, batch: SessionBatch) -> None:
        """Reads the answer of a step in flight, raising its error (none here)."""

    def reset(self) -> None:
        """Forgets a step in flight: the batch's sessions start new episodes (none here)."""


def check_critic(critic: Critic, n: int, dim: int) -> None:
    """Checks a linear or quadratic critic for ``n`` sessions of dimension ``dim``.

    Raises:
        ValueError: A wrong shape, non-finite coefficient, positive curvature or bad bound.
    """
    if not isinstance(critic, CLOSED_FORM):
        return
    if isinstance(critic, QuadraticCritic) and (critic.low is None) != (critic.high is None):
        raise ValueError(
            f"critic: expected both bounds or neither, got {critic.low!r} and {critic.high!r}"
        )
    expected = {"gain": (n, dim), "curvature": (n, dim), "offset": (n,)}  # bounds: (dim,)
    given = {name: values for name, values in critic._asdict().items() if values is not None}
    shapes = {name: np.shape(values) for name, values in given.items()}
    if shapes != {name: expected.get(name, (dim,)) for name in given}:
        wanted = ", ".join(f"{name} of shape {expected.get(name, (dim,))}" for name in given)
        raise ValueError(f"critic: expected {wanted}, got {shapes}")
    if isinstance(critic, LinearCritic):
        return
    for name in ("gain", "curvature", "offset"):
        if not np.all(np.isfinite(given[name])):
            raise ValueError(f"critic: expected a finite {name}, got {given[name]!r}")
    if np.any(np.asarray(critic.curvature) > 0):
        raise ValueError(f"critic: expected curvature <= 0, got {critic.curvature!r}")
    low, high = critic.low, critic.high
    if low is not None and not np.all(np.asarray(low) <= np.asarray(high)):
        raise ValueError(f"critic: expected low <= high (no NaN), got {low!r} and {high!r}")
