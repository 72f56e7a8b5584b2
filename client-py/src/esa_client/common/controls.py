"""ESA's controls (``esa_control``), the same for every drop-in, and what a shift did.

``"placebo"`` (:class:`PlaceboShift`) keeps ESA's shift sizes, schedule and correlation in
random directions; ``"gradient"`` (:class:`GradientShift`) steps the trust region's size
along the critic's action gradient, with no session (the SB3 guide's "Defaults and
controls"). A drop-in builds one (:func:`control_shift`) and calls it each step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, get_args

import numpy as np

Control = Literal["placebo", "gradient"]
"""A control of ESA (``esa_control``); None is ESA itself."""
CONTROLS: tuple[Control, ...] = get_args(Control)

REPORT_EVERY = 8
"""Steps per sampled statistic (:func:`shift_report`, ``esa/improvement``): on every step
their numpy and critic calls would cost a few %."""


def check_control(control: str | None) -> Control | None:
    """Returns ``control`` if it is None or a known control, else raises ValueError."""
    if control is not None and control not in CONTROLS:
        raise ValueError(f"expected esa_control None or one of {CONTROLS}, got {control!r}")
    return control


def gradient_size(strength: float, trust_region: float | None) -> float:
    """The gradient control's step in units of sigma: ``f kappa`` (kappa 1 when unset)."""
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
    """The placebo's shift: ESA's ``|v|`` per dimension times a random sign vector.

    Each env draws its signs (+-1) at every episode start, from a generator of its own
    (``seed``; None: fresh entropy): the learner's random stream is untouched.
    """

    def __init__(self, n_envs: int, action_dim: int, seed: int | None) -> None:
        """Draws the first episode's signs for ``n_envs`` envs of ``action_dim`` dimensions."""
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
        """``|shift| * signs``, float64 ``(N, D)``, after :meth:`start` of ``episode_starts``."""
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
Arrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""What :func:`shift_report` reads of a step: ``(sampled, shift, mean, std, low, high)``."""


class EsaShift:
    """ESA itself: the env executes the sessions' shift. The controls override :meth:`act`.

    :meth:`act` gets the step's sources and calls only those it needs: ``session`` steps the
    sessions (the env's actions under ESA's shift, and the shift), ``gradient`` gives the
    gradient control's shift, ``execute`` the env's actions for a shift; ``starts`` is True
    where an env starts an episode at this step, ``(N,)``.
    """

    def act(
        self, session: Session, gradient: Source, execute: Execute, starts: np.ndarray
    ) -> Acted:
        """This step's actions and shift."""
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

    ``sampled`` (``a_t``), ``shift`` (``v``), ``mean`` (``mu``) and ``std`` (sigma) are
    ``(N, D)`` in ESA's units; ``low``/``high`` ``(D,)`` are the env's clip; ``bound`` is
    kappa in units of sigma (None: no bound).

    Returns:
        ``noise_cosine``: the mean ``cos(v, mu - a_t)`` over the envs with a shift (1: it
        only pulls the sample back to the mean); ``at_bound``: the share of shifted
        elements within 1 % of ``kappa sigma``; ``undone_by_clip``: the share the env's clip
        turns into no change.
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
