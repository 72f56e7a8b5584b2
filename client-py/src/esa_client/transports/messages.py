"""The arrays a batch's round trips carry, and the critics a whole step can take in closed form."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..state import BoolArray, F64Array, I64Array


class SessionProbe(NamedTuple):
    """The probe of one step of one session (``Probe``); ``action_scale`` None for all 1."""

    session_id: str
    step: int
    action: F64Array
    episode_start: bool
    action_scale: F64Array | None


class BatchProbe(NamedTuple):
    """The probes of one step for the N sessions of a batch (``ProbeBatch``).

    ``steps`` and ``episode_starts`` are ``(N,)``, ``actions`` and ``action_scales`` (sigma,
    None for all 1) ``(N, D)``.
    """

    steps: I64Array
    actions: F64Array
    episode_starts: BoolArray
    action_scales: F64Array | None


class BatchReport(NamedTuple):
    """The reports of one step for the N sessions of a batch (``ReportBatch``), each ``(N,)``.

    ``q_values`` is Q at each probe, ``q_references`` Q at each applied action or None.
    """

    steps: I64Array
    q_values: F64Array
    q_references: F64Array | None


class LinearCritic(NamedTuple):
    """A critic linear in the action at each session's state: ``Q_i(a) = gain_i . a + offset_i``.

    An in-process engine evaluates it itself (:meth:`~esa_client.session.SessionBatch.step`).

    Attributes:
        gain: ``gain_i`` per session and dimension, shape ``(N, D)``.
        offset: ``offset_i`` per session, shape ``(N,)``.
    """

    gain: F64Array
    offset: F64Array

    def __call__(self, actions: F64Array) -> F64Array:
        """Q of ``(k N, D)`` actions for the N states tiled k times, shape ``(k N,)``."""
        points = actions.reshape(-1, *self.gain.shape)
        values: F64Array = ((points * self.gain).sum(axis=2) + self.offset).reshape(-1)
        return values


class QuadraticCritic(NamedTuple):
    """A critic concave quadratic in the action at each session's state, flat past a box.

    ``Q_i(a) = offset_i + sum_j (gain_ij x_j + curvature_ij x_j^2)`` with
    ``x = clip(a, low, high)``, the action the environment executes, and every
    ``curvature_ij <= 0`` (ESAPPO's quadratic head). An in-process engine evaluates it
    itself, as does the gRPC StepStream's step sent ahead; other transports evaluate it here.

    Attributes:
        gain: ``gain_i`` per session and dimension, shape ``(N, D)``.
        curvature: ``curvature_i`` per session and dimension, ``<= 0``, shape ``(N, D)``.
        offset: ``offset_i`` per session, shape ``(N,)``.
        low: The box's lower bounds in the actions' units, shape ``(D,)`` (``-inf`` where
            open); None with ``high`` None for no box.
        high: Its upper bounds, shape ``(D,)`` (``+inf`` where open), or None.
    """

    gain: F64Array
    curvature: F64Array
    offset: F64Array
    low: F64Array | None = None
    high: F64Array | None = None

    def __call__(self, actions: F64Array) -> F64Array:
        """Q of ``(k N, D)`` actions for the N states tiled k times, shape ``(k N,)``."""
        points = actions.reshape(-1, *self.gain.shape)
        if self.low is not None and self.high is not None:
            points = np.clip(points, self.low, self.high)
        terms = self.gain * points + self.curvature * points * points
        values: F64Array = (terms.sum(axis=2) + self.offset).reshape(-1)
        return values
