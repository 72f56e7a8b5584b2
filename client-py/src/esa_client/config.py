"""Session configs: the wire-level :class:`SessionConfig` and the user-facing :class:`EsaConfig`."""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ._native import check_config
from ._proto.esa.v1 import esa_pb2

Vector = float | Sequence[float] | np.ndarray
"""A per-dimension value: a scalar (broadcast to every dimension) or one value per dimension."""


def _as_tuple(name: str, value: Vector | None) -> tuple[float, ...]:
    """``value`` as a tuple of floats; None and ``()`` (a stored unset field) mean unset."""
    if value is None:
        return ()
    array = np.asarray(value, dtype=np.float64)
    if array.size == 0:
        return ()
    if array.ndim > 1:
        raise ValueError(f"expected {name} to be a scalar or 1-D sequence, got shape {array.shape}")
    return tuple(float(x) for x in array.reshape(-1))


def _check(ok: bool, expected: str, got: object) -> None:
    if not ok:
        raise ValueError(f"expected {expected}, got {got!r}")


def _is_real(value: object) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def _is_int(value: object, bits: int) -> bool:
    """Whether ``value`` fits the contract's unsigned integer of ``bits`` bits."""
    return _is_real(value) and isinstance(value, (int, np.integer)) and 0 <= value < 2**bits


def _finite_bound(bound: Vector | None, unbounded: float) -> Vector | None:
    """A gymnasium bound in contract form: all ``unbounded`` (+-inf) = None, some = float max."""
    if bound is None:
        return None
    values = np.asarray(bound, dtype=np.float64)
    if np.all(values == unbounded):
        return None
    return np.where(values == unbounded, math.copysign(sys.float_info.max, unbounded), values)


_OPTIONAL_SCALARS = (
    "highpass_cutoff",
    "shift_limit",
    "lr_decay",
    "response_rms_rate",
    "response_clip",
    "shift_leak",
    "trust_region",
)
"""The proto3 ``optional double`` fields of ``SessionConfig`` (None = unset)."""

_VECTORS = ("amplitude", "frequency", "learning_rate", "action_low", "action_high")
"""The repeated ``double`` fields of ``SessionConfig``, stored as tuples (bounds: empty = unset)."""


@dataclass(frozen=True)
class SessionConfig:
    """The configuration of one ESA session, mirroring ``esa.v1.SessionConfig`` field for field.

    CONTRACT.md's tables (sections 1 and 1b) give each field's meaning and range; esa-core
    checks them when the config is built (``ValueError`` naming the field). A vector field
    takes a scalar (broadcast to ``action_dim`` dimensions) or one value per dimension, stored
    as a tuple of floats (an unset bound: ``()``); None leaves an optional field unset.
    """

    action_dim: int
    dt: float
    amplitude: Vector
    frequency: Vector
    learning_rate: Vector
    highpass_cutoff: float | None = None
    disable_highpass: bool = False
    action_low: Vector | None = None
    action_high: Vector | None = None
    shift_limit: float | None = None
    lr_decay: float | None = None
    max_episodes: int = 0
    normalize_response: bool = False
    response_rms_rate: float | None = None
    response_clip: float | None = None
    shift_leak: float | None = None
    trust_region: float | None = None

    def __post_init__(self) -> None:
        """Checks each field's type and stores vectors as tuples; esa-core checks the values."""
        _check(_is_int(self.action_dim, 32), "action_dim an integer", self.action_dim)
        _check(_is_int(self.max_episodes, 64), "max_episodes an integer >= 0", self.max_episodes)
        for name in ("action_dim", "max_episodes"):
            object.__setattr__(self, name, int(getattr(self, name)))
        _check(_is_real(self.dt), "dt a real number", self.dt)
        object.__setattr__(self, "dt", float(self.dt))
        for name in _VECTORS:
            object.__setattr__(self, name, _as_tuple(name, getattr(self, name)))
        for name in _OPTIONAL_SCALARS:
            value = getattr(self, name)
            if value is not None:
                _check(_is_real(value), f"{name} a real number (or None)", value)
                object.__setattr__(self, name, float(value))
        for name in ("disable_highpass", "normalize_response"):
            value = getattr(self, name)
            _check(isinstance(value, (bool, np.bool_)), f"{name} a bool", value)
            object.__setattr__(self, name, bool(value))
        check_config(self.to_proto().SerializeToString())

    def vector(self, name: str) -> np.ndarray:
        """Returns a vector field broadcast to shape ``(action_dim,)`` (empty bounds give +-inf)."""
        values: tuple[float, ...] = getattr(self, name)  # a tuple, since __post_init__
        if not values:
            fill = -np.inf if name == "action_low" else np.inf
            return np.full(self.action_dim, fill)
        return np.array(np.broadcast_to(np.asarray(values, dtype=np.float64), (self.action_dim,)))

    def to_proto(self) -> esa_pb2.SessionConfig:
        """Returns the ``esa.v1.SessionConfig`` message for this config."""
        values = {field.name: getattr(self, field.name) for field in fields(self)}
        return esa_pb2.SessionConfig(**{k: v for k, v in values.items() if v is not None})

    @classmethod
    def from_proto(cls, message: esa_pb2.SessionConfig) -> SessionConfig:
        """Builds (and validates) a config from an ``esa.v1.SessionConfig`` message."""
        values: dict[str, Any] = {}
        for field in fields(cls):
            value = getattr(message, field.name)
            if field.name in _VECTORS:
                value = tuple(value)
            elif field.name in _OPTIONAL_SCALARS and not message.HasField(field.name):
                value = None
            values[field.name] = value
        return cls(**values)


OFF_POLICY_TRUST_REGION = 0.5
"""``EsaConfig.off_policy()``'s trust region kappa, in policy standard deviations."""

PPO_TRUST_REGION = 1.0
"""``EsaConfig.ppo()``'s trust region kappa, in policy standard deviations."""

PPO_FADE = 0.5
"""``EsaConfig.ppo()``'s fade: ESA gone by half of the training budget."""


@dataclass
class EsaConfig:
    """ESA hyperparameters for a trainer, turned into a :class:`SessionConfig` per environment.

    ``EsaConfig()`` is CONTRACT.md section 1b's bounded, scale-free law, one setting for every
    environment (the wrappers' default); the drop-ins start from :meth:`ppo` and
    :meth:`off_policy`, and :meth:`paper` is section 1's law (``experiments/RESULTS.md`` says
    how each fares). Fields are checked when the config is built (``ValueError`` naming the field),
    those that need the environment (Nyquist for its ``dt``) when a trainer or wrapper is.
    Fields named as in :class:`SessionConfig` and not listed below go to it as they are.

    Attributes:
        amplitude: K, in the units of the action space ESA works in (SAC: squashed [-1, 1];
            PPO: the policy's); the probe only queries the critic, the env gets ``a_t + v(t)``.
        frequency: w in rad/s. A scalar is spread over ``[w / 2, w]`` across dimensions, so
            that demodulation tells them apart; a sequence gives each. None takes
            ``nyquist_fraction`` of ``pi / dt``: the same period in steps on every env.
        nyquist_fraction: With ``frequency=None``, w as a fraction of ``pi / dt``, in (0, 1).
        learning_rate: Eq. 5's alpha (Algorithm 1's ``alpha K``). With ``normalize_response``
            it is in units of the action scale per step; without, it multiplies Q itself.
        normalize_response: Divide the filtered response by its running RMS (section 1b),
            so one learning rate fits every reward scale.
        trust_region: kappa: ``|v| <= kappa * sigma`` per dimension, sigma the action
            scale the trainer sends; None = no bound.
        paired_response: Report ``Q(s, probe) - Q(s, a_t + v(t))`` instead of
            ``Q(s, probe)``, removing the state's own change of Q, which swamps the probe's.
        use_policy_std: Send the policy's standard deviation as sigma (else 1), so that ESA
            shrinks as the policy converges.
        gate: Minimum rank correlation of the critic's ``Q(s, a) - Q(s, mu)`` with the
            algorithm's own advantage estimate before ESA intervenes; None = from the start.
        dt: Seconds per environment step; None: the env's ``dt``, else ``1 / render_fps``.
        fade: The fraction of the training budget, in (0, 1], over which ESA's strength f
            falls linearly to 0: the trainer sends ``f * sigma`` as the action scale
            (CONTRACT.md section 1b's fading). Needs ``normalize_response``; None = no fade.
    """

    # default_search's best on InvertedPendulum-v5 (tuning seeds 100-107), to 2 significant digits.
    amplitude: float | Sequence[float] = 0.29
    frequency: float | Sequence[float] | None = None
    nyquist_fraction: float = 0.48
    learning_rate: float | Sequence[float] = 0.054
    highpass_cutoff: float | None = None
    disable_highpass: bool = False
    lr_decay: float | None = None
    max_episodes: int = 0
    shift_limit: float | None = None
    normalize_response: bool = True
    response_rms_rate: float | None = None
    response_clip: float | None = None
    shift_leak: float | None = 0.004
    trust_region: float | None = 0.055
    paired_response: bool = True
    use_policy_std: bool = True
    gate: float | None = 0.0
    dt: float | None = None
    fade: float | None = None

    def __post_init__(self) -> None:
        """Checks every field that does not depend on the environment."""
        for name in ("paired_response", "use_policy_std", "normalize_response"):
            _check(isinstance(getattr(self, name), bool), f"{name} a bool", getattr(self, name))
        nyquist = self.nyquist_fraction
        _check(_is_real(nyquist) and 0 < nyquist < 1, "nyquist_fraction in (0, 1)", nyquist)
        optional: list[tuple[str, Callable[[float], bool], str]] = [
            ("gate", lambda x: -1 <= x <= 1, "a rank correlation in [-1, 1] (or None)"),
            ("dt", lambda x: math.isfinite(x) and x > 0, "finite and > 0 (or None: from the env)"),
            ("fade", lambda x: 0 < x <= 1, "a fraction of the training budget in (0, 1] (or None)"),
        ]
        for name, valid, expected in optional:
            value = getattr(self, name)
            if value is not None:
                _check(_is_real(value) and valid(value), f"{name} {expected}", value)
        if self.fade is not None:
            _check(
                self.normalize_response,
                "normalize_response=True with fade (only the normalized step scales with "
                "the action scale a fading trainer sends)",
                self.normalize_response,
            )
        # The session rules, with as many dimensions as the vector fields name and (unless dt
        # is set) a time step so fine that only the environment's own dt can break Nyquist.
        vectors = (self.amplitude, self.frequency, self.learning_rate)
        dims = max([int(np.size(v)) for v in vectors if v is not None and np.ndim(v) > 0] or [1])
        self.session_config(max(dims, 1), 1e-9)

    @classmethod
    def paper(cls, **overrides: Any) -> EsaConfig:
        """The paper's law and settings: Eq. 5 on the raw Q, K = 0.2, w = 10 pi, no bounds.

        CONTRACT.md section 1 without any section 1b field; alpha = 0.05 is ours (the paper
        gives none). ``overrides`` change fields, e.g. ``amplitude=0.1``.
        """
        settings: dict[str, Any] = dict(
            amplitude=0.2,
            frequency=10 * math.pi,
            learning_rate=0.05,
            normalize_response=False,
            shift_leak=None,
            trust_region=None,
            paired_response=False,
            use_policy_std=False,
            gate=None,
        )
        return cls(**{**settings, **overrides})

    @classmethod
    def ppo(cls, **overrides: Any) -> EsaConfig:
        """The shipped default of ``ESAPPO``: ``EsaConfig()`` bounded at 1 sigma, faded by half.

        The setting the ``seeking`` study (E2) tested as ``ppo_esa``: E1's trust region for
        the quadratic head, and ESA gone by half of ``learn()``'s budget (``fade=None``: ESA
        through the whole budget).
        """
        return cls(**{"trust_region": PPO_TRUST_REGION, "fade": PPO_FADE, **overrides})

    @classmethod
    def off_policy(cls, **overrides: Any) -> EsaConfig:
        """The shipped default of the off-policy drop-ins (``ESASAC``, ``ESATD3``).

        ``EsaConfig()`` with a wider trust region (an off-policy learner pays no importance
        ratio for shifted data): the ``ground_truth`` study's pick on SAC, the largest bound
        whose Monte-Carlo return gain is above 0 with 95 % confidence on both its envs.
        ``overrides`` change fields, e.g. ``trust_region=0.25``.
        """
        return cls(**{"trust_region": OFF_POLICY_TRUST_REGION, **overrides})

    def strength(self, elapsed: float) -> float:
        """ESA's strength, ``1 - elapsed / fade`` clipped to [0, 1] (1 without a fade).

        ``elapsed`` is the fraction of the budget done, e.g. ``num_timesteps / total``.
        """
        if self.fade is None:
            return 1.0
        return float(min(1.0, max(0.0, 1.0 - elapsed / self.fade)))

    def frequencies(self, action_dim: int, dt: float) -> tuple[float, ...]:
        """Returns the per-dimension frequencies for ``action_dim`` dimensions and step ``dt``."""
        if self.frequency is None:
            w = self.nyquist_fraction * math.pi / dt
        elif np.ndim(self.frequency) == 0:
            w = float(np.asarray(self.frequency, dtype=np.float64))
        else:
            return tuple(float(x) for x in np.asarray(self.frequency, dtype=np.float64))
        return tuple(float(x) for x in np.linspace(w, w / 2, action_dim))

    def session_config(
        self,
        action_dim: int,
        dt: float,
        action_low: Vector | None = None,
        action_high: Vector | None = None,
    ) -> SessionConfig:
        """Builds the validated :class:`SessionConfig` for one environment.

        Args:
            action_dim: The action dimension.
            dt: Seconds per environment step (ignored when ``self.dt`` is set).
            action_low: Lower bounds of the action space ESA works in, or None.
            action_high: Upper bounds, or None.

        Raises:
            ValueError: If a hyperparameter is invalid for this action space and time step.
        """
        dt = self.dt if self.dt is not None else dt
        ours = {f.name for f in fields(self)} - {"dt", "frequency"}
        return SessionConfig(
            **{f.name: getattr(self, f.name) for f in fields(SessionConfig) if f.name in ours},
            action_dim=action_dim,
            dt=dt,
            frequency=self.frequencies(action_dim, dt),
            action_low=_finite_bound(action_low, -math.inf),
            action_high=_finite_bound(action_high, math.inf),
        )
