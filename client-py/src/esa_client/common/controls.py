"""The controls a user judges ESA with, the same for every drop-in, and what a shift did.

A gain of ESA over its baseline may come from the critic's direction, from the mere size
and temporal correlation of the perturbation, or from more exploration. Two controls share
everything with ESA but what they test (``esa_control`` of the drop-ins), each a subclass
of :class:`EsaShift` that a drop-in builds (:func:`control_shift`) and calls each step:

- ``"placebo"`` (:class:`PlaceboShift`): ESA's shift magnitudes per dimension, its schedule
  and its correlation over time, with the direction drawn at random
  (:class:`RandomDirections`): tells direction from mere perturbation;
- ``"gradient"`` (:class:`GradientShift`): a step of the trust region's size along the
  critic's action gradient (:func:`unit_gradient`, :func:`gradient_size`), no session:
  tells extremum seeking from the analytic gradient the paper says it beats.

``shift_report`` measures, on one step in ``SHIFT_REPORT_EVERY``, how much of a shift
removes the policy's own exploration noise, how often it sits at the trust region, and how
often the env's clip undoes it. The shift's size (``esa/shift_over_std``) is the runtime's
statistic (``StepStats``), or the gradient control's own (:func:`gradient_shift_size`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, get_args

import numpy as np

Control = Literal["placebo", "gradient"]
"""A control of ESA (``esa_control``); None is ESA itself."""
CONTROLS: tuple[Control, ...] = get_args(Control)

SHIFT_REPORT_EVERY = 8
"""Shifted steps per :func:`shift_report`: its numpy costs about an actor call, a few % of a
step when run on every one."""


def check_control(control: str | None) -> Control | None:
    """Returns ``control`` if it is None, ``"placebo"`` or ``"gradient"``.

    Raises:
        ValueError: For anything else.
    """
    if control is not None and control not in CONTROLS:
        raise ValueError(f"expected esa_control None or one of {CONTROLS}, got {control!r}")
    return control


def gradient_size(strength: float, trust_region: float | None) -> float:
    """The gradient control's step in units of sigma: ``f kappa``, kappa 1 when unset.

    As large as ESA's faded bound allows at every point of training.
    """
    return strength * (trust_region if trust_region is not None else 1.0)


def gradient_shift_size(size: float, unit: np.ndarray) -> float:
    """The gradient control's mean ``|v| / sigma`` (``esa/shift_over_std``): ``size |u|``."""
    return float(size * np.abs(unit).mean())


def unit_gradient(gradient: np.ndarray) -> np.ndarray:
    """Each row of ``gradient`` (``(N, D)``, in units of sigma) scaled to length 1 (0 stays 0)."""
    norm = np.linalg.norm(gradient, axis=1, keepdims=True)
    unit: np.ndarray = np.divide(gradient, norm, out=np.zeros_like(gradient), where=norm > 0)
    return unit


class RandomDirections:
    """The placebo's shift: ESA's ``|v|`` per dimension with a random sign vector.

    Each env draws a sign vector (each element +-1 with probability 1/2) at every episode
    start and keeps it through the episode, so the placebo's shift has ESA's magnitude,
    schedule and temporal correlation, but a direction that knows nothing of the critic.

    Args:
        n_envs: The number of envs N.
        action_dim: The action dimension D.
        seed: Seed of the placebo's own generator (None: fresh entropy); it draws from no
            other generator, so the learner's random stream is untouched.
    """

    def __init__(self, n_envs: int, action_dim: int, seed: int | None) -> None:
        """Draws the first episode's signs."""
        if n_envs < 1 or action_dim < 1:
            raise ValueError(
                f"expected n_envs >= 1 and action_dim >= 1, got {n_envs} and {action_dim}"
            )
        self._rng = np.random.default_rng(seed)
        self.signs = self._draw(n_envs, action_dim)

    def _draw(self, rows: int, action_dim: int) -> np.ndarray:
        signs: np.ndarray = self._rng.choice(np.array([-1.0, 1.0]), size=(rows, action_dim))
        return signs

    def __call__(self, shift: np.ndarray, episode_starts: np.ndarray) -> np.ndarray:
        """The placebo's shift for ESA's ``shift`` ``(N, D)`` at this step.

        Args:
            shift: ESA's shift ``v(t)`` per env and dimension.
            episode_starts: True where an env starts an episode at this step: its signs are
                drawn anew.

        Returns:
            ``|shift| * signs``, float64 ``(N, D)``.
        """
        shift = np.asarray(shift, dtype=np.float64)
        if shift.shape != self.signs.shape:
            raise ValueError(f"expected a shift of shape {self.signs.shape}, got {shift.shape}")
        self.start(episode_starts)
        placebo: np.ndarray = np.abs(shift) * self.signs
        return placebo

    def start(self, episode_starts: np.ndarray) -> None:
        """Draws new signs for the envs that start an episode (True in ``episode_starts``)."""
        starts = np.asarray(episode_starts, dtype=bool).reshape(-1)
        if starts.shape != (len(self.signs),):
            raise ValueError(
                f"expected episode_starts of shape ({len(self.signs)},), got {starts.shape}"
            )
        if starts.any():
            self.signs[starts] = self._draw(int(starts.sum()), self.signs.shape[1])


Acted = tuple[np.ndarray, np.ndarray]
"""The env's actions and the shift on top of the policy's sample they come from, ``(N, D)``."""
Session = Callable[[], Acted]
Source = Callable[[], np.ndarray]
Execute = Callable[[np.ndarray], np.ndarray]


class EsaShift:
    """ESA itself: the env executes the sessions' shift. The controls override :meth:`act`."""

    def act(
        self, session: Session, gradient: Source, execute: Execute, starts: np.ndarray
    ) -> Acted:
        """This step's actions; only the sources it needs are called.

        Args:
            session: Steps the sessions: the env's actions under ESA's shift as the drop-in
                forms them (the off-policy ones execute the sessions' own), and the shift.
            gradient: The gradient control's shift.
            execute: The env's actions for a shift.
            starts: True where an env starts an episode at this step, ``(N,)``.
        """
        return session()

    def bound(self, trust_region: float | None) -> float | None:
        """The shift's bound at full strength in units of sigma (None: no bound)."""
        return trust_region


class PlaceboShift(EsaShift):
    """ESA's shift in :class:`RandomDirections` drawn for the first step's envs from ``seed``."""

    def __init__(self, seed: int | None) -> None:
        """No directions until the first step says how many envs there are."""
        self.seed = seed
        self.directions: RandomDirections | None = None

    def act(
        self, session: Session, gradient: Source, execute: Execute, starts: np.ndarray
    ) -> Acted:
        """ESA's shift in this episode's directions; it steps the sessions."""
        _, shift = session()
        if self.directions is None:
            n_envs, action_dim = shift.shape
            self.directions = RandomDirections(n_envs, action_dim, self.seed)
        placebo = self.directions(shift, starts)
        return execute(placebo), placebo


class GradientShift(EsaShift):
    """The trust region's step along the critic's action gradient; no session steps."""

    def act(
        self, session: Session, gradient: Source, execute: Execute, starts: np.ndarray
    ) -> Acted:
        """The gradient's shift."""
        shift = gradient()
        return execute(shift), shift

    def bound(self, trust_region: float | None) -> float | None:
        """``kappa``, 1 when unset: the gradient's step is never unbounded."""
        return gradient_size(1.0, trust_region)


def control_shift(control: Control | None, seed: int | None) -> EsaShift:
    """The shift of ``esa_control`` ``control``; the placebo draws its directions from ``seed``."""
    if control == "placebo":
        return PlaceboShift(seed)
    return GradientShift() if control == "gradient" else EsaShift()


def shift_report(
    sampled: np.ndarray,
    shift: np.ndarray,
    mean: np.ndarray,
    std: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    bound: float | None,
) -> dict[str, float]:
    """What one step's shifts did, averaged over envs (and dimensions where per dimension).

    All arrays are ``(N, D)`` in one unit (ESA's), ``low``/``high`` ``(D,)``.

    Args:
        sampled: The policy's samples ``a_t``.
        shift: The shift ``v`` applied on top of them.
        mean: The policy's mean ``mu``.
        std: The policy's standard deviation sigma.
        low: The env's lower bounds (it clips the executed action to them).
        high: The env's upper bounds.
        bound: The trust region kappa in units of sigma (None: no bound).

    Returns:
        ``noise_cosine``: the mean cosine between ``v`` and ``mu - a_t`` over the envs whose
        shift is non-zero (1: the shift only pulls the sample back to the mean);
        ``at_bound``: the share of shifted elements within 1 % of ``kappa sigma``;
        ``undone_by_clip``: the share of shifted elements the env's clip turns into no change
        of the executed action.
    """
    noise = mean - sampled
    norms = np.linalg.norm(shift, axis=1) * np.linalg.norm(noise, axis=1)
    moved = norms > 0
    cosine = (shift * noise).sum(axis=1)[moved] / norms[moved] if moved.any() else np.zeros(0)
    shifted = shift != 0
    executed = np.clip(sampled + shift, low, high)
    undone = shifted & (executed == np.clip(sampled, low, high))
    at_bound = (
        shifted & (np.abs(shift) >= 0.99 * bound * std)
        if bound is not None
        else np.zeros_like(shifted)
    )
    count = max(int(shifted.sum()), 1)
    return {
        "noise_cosine": float(cosine.mean()) if cosine.size else 0.0,
        "at_bound": float(at_bound.sum() / count),
        "undone_by_clip": float(undone.sum() / count),
    }
