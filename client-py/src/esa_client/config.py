"""Session configs: the wire-level :class:`SessionConfig` and the user-facing :class:`EsaConfig`."""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ._native import check_config
from ._proto.esa.v1 import esa_pb2

Vector = float | Sequence[float] | np.ndarray
"""A per-dimension value: a scalar (broadcast to every dimension) or one value per dimension."""


def _as_tuple(name: str, value: Vector | None) -> tuple[float, ...]:
    """Returns ``value`` as a tuple of floats (its length is esa-core's to check).

    None and an empty sequence (the stored form of an unset field) both mean unset, so a
    validated config can be rebuilt from its own fields (``dataclasses.replace``).
    """
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


def _is_int(value: object, bits: int) -> bool:
    """Whether ``value`` fits the contract's unsigned integer of ``bits`` bits."""
    return (
        isinstance(value, (int, np.integer))
        and not isinstance(value, bool)
        and 0 <= value < 2**bits
    )


def _is_real(value: object) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def _finite_bound(bound: Vector | None, unbounded: float) -> Vector | None:
    """Maps a gymnasium-style bound to the contract's finite form.

    ``unbounded`` (+-inf) marks an open side: all open = no bound, some open = float max there.
    """
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

    esa-core checks it where it is built, with the rules and words of every transport
    (CONTRACT.md sections 1 and 1b), so a bad value fails early with a ``ValueError``
    naming the field. Vector fields accept a scalar (broadcast to all ``action_dim``
    dimensions) or one value per dimension; they are stored as tuples of floats, as given.

    Attributes:
        action_dim: Action dimension D, 1 <= D <= 4096.
        dt: Seconds per environment step (finite, > 0); the perturbation phase at step t
            is ``frequency * t * dt``.
        amplitude: Perturbation amplitude K (finite, >= 0).
        frequency: Perturbation frequency w in rad/s (finite, > 0, ``w * dt < pi``).
        learning_rate: Learning rate alpha (finite, >= 0); the server maximizes Q.
        highpass_cutoff: Washout cutoff w_h in rad/s (finite, > 0); None = ``min(w) / 10``.
        disable_highpass: True makes the high-pass filter the identity.
        action_low: Lower action bounds; None = unbounded.
        action_high: Upper action bounds; None = unbounded.
        shift_limit: Bound L on every element of the shift v; None = no clamp.
        lr_decay: Per-episode learning-rate decay in (0, 1]; None = 1.
        max_episodes: Episodes after which the session passes actions through; 0 = never.
        normalize_response: Scale-free law (CONTRACT.md section 1b): the filtered response is
            divided by its running RMS, clipped to ``response_clip`` and the step scaled by the
            probe's action scale, so one learning rate fits every reward scale.
        response_rms_rate: EMA rate of the response's mean square, in (0, 1]; None = 0.05.
        response_clip: Clip of the normalized response (finite, > 0); None = 3.
        shift_leak: Leak lambda in [0, 1): ``v <- (1 - lambda) v + step``; None = 0.
        trust_region: kappa (finite, > 0): ``|v| <= kappa * action_scale`` per dimension;
            None = no bound from it.
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
        """Checks each field's type and stores vectors as tuples; esa-core checks the values.

        Raises:
            ValueError: Naming the first bad field ("expected ..., got ..."), in esa-core's
                words for a value the contract refuses (``check_config``).
        """
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
        # Every field as stored (vectors as tuples); an unset optional scalar stays unset.
        values = {field.name: getattr(self, field.name) for field in fields(self)}
        return esa_pb2.SessionConfig(**{k: v for k, v in values.items() if v is not None})

    @classmethod
    def from_proto(cls, message: esa_pb2.SessionConfig) -> SessionConfig:
        """Builds (and validates) a config from an ``esa.v1.SessionConfig`` message."""
        # Field name -> value, checked by __post_init__ like any constructor argument.
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

    ``EsaConfig()`` is the bounded, scale-free law of CONTRACT.md section 1b (normalized
    response, paired reference, trust region in units of the policy's standard deviation,
    leak), one setting for every environment (the gymnasium wrappers' default). Each
    drop-in starts from its family's preset of it: :meth:`ppo` (``ESAPPO``) and
    :meth:`off_policy` (``ESASAC``, ``ESATD3``). :meth:`paper` is the paper's law
    (section 1) with its settings. ``experiments/RESULTS.md`` says how each fares.

    Every field is checked when the config is built (``ValueError`` naming the field);
    the rules that need the environment (Nyquist for its ``dt``, one frequency per
    action dimension) are checked when a trainer or wrapper is constructed.

    On the paper's two update laws: Eq. 5 is ``v += alpha sin(w t) H[Q]``, Algorithm 1
    writes ``v += alpha K sin(w t) H[Q]``. The service implements Eq. 5 (``alpha`` here is
    Algorithm 1's ``alpha K``). Both apply ``a_t + v(t)`` to the environment (the shift
    before this step's update), which is what the trainers here apply and store.

    Attributes:
        amplitude: Perturbation amplitude K of the probe, in the units of the action space
            ESA works in (SAC: the squashed [-1, 1] space; PPO: the policy's action space).
            The probe only queries the critic; the environment gets ``a_t + v(t)``.
        frequency: Perturbation frequency w in rad/s. A scalar is spread over
            ``[w / 2, w]`` across action dimensions so every dimension has its own
            frequency (otherwise demodulation cannot tell the dimensions apart);
            a sequence gives the per-dimension frequencies exactly. None (the default)
            takes ``nyquist_fraction`` of the env's Nyquist frequency ``pi / dt``: the
            probe then has the same period in steps on every env.
        nyquist_fraction: With ``frequency=None``, w as a fraction of ``pi / dt``, in (0, 1).
        learning_rate: ESA learning rate alpha (Eq. 5). With ``normalize_response`` it is
            in units of the action scale per step; without, it multiplies Q itself.
        highpass_cutoff: Washout cutoff in rad/s; None = ``min(frequency) / 10``.
        disable_highpass: Feed the raw response to the update (ablation).
        lr_decay: Per-episode decay of the learning rate in (0, 1]; None = no decay.
        max_episodes: Episodes per environment after which ESA stops intervening; 0 = never.
        shift_limit: Bound on every element of the shift v; None = no clamp.
        normalize_response: Divide the filtered response by its running RMS (section 1b),
            so one learning rate fits every reward scale.
        response_rms_rate: EMA rate of that running mean square; None = 0.05.
        response_clip: Clip of the normalized response; None = 3.
        shift_leak: Leak lambda in [0, 1) of the shift per step; None = 0.
        trust_region: kappa: ``|v| <= kappa * sigma`` per dimension, sigma the action
            scale the trainer sends (see ``use_policy_std``); None = no bound.
        paired_response: Report ``Q(s, probe) - Q(s, a_t + v(t))`` (one more row in the
            same critic batch) instead of ``Q(s, probe)``: removes the state's own change
            of Q, which otherwise swamps the probe's.
        use_policy_std: Send the policy's standard deviation as the action scale sigma
            (else 1): the trust region and the normalized step then shrink as the policy
            converges, so ESA fades out by itself.
        gate: Minimum critic quality before ESA intervenes: the rank correlation between
            the critic's ``Q(s, a) - Q(s, mu)`` and the algorithm's own advantage estimate
            (ESAPPO: GAE on each rollout). None = ESA from the first step the critic exists.
        dt: Seconds per environment step. None reads it from the environment
            (``env.unwrapped.dt``, else ``1 / metadata["render_fps"]``); set it when the
            environment has neither, or to override it.
        fade: The paper's fading of ESA over training (its ablation on the decay of the ESA
            learning rate): the fraction of the training budget, in (0, 1], over which ESA's
            strength falls linearly from full to 0; after it the policy's samples are
            applied unchanged. The trainer sends ``f * sigma`` as each probe's action scale
            (CONTRACT.md section 1b, "Fading ESA over training"), which scales both the
            normalized step and the trust region ``kappa sigma``, so the bound itself fades
            from ``kappa`` to 0. Needs ``normalize_response`` (the section 1 step does not
            scale with sigma). None = no fade.
    """

    # The shipped default: the best setting `default_search` found on InvertedPendulum-v5
    # (tuning seeds 100-107), to two significant digits; experiments/RESULTS.md says how it
    # fares.
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
        """Checks every field that does not depend on the environment.

        Raises:
            ValueError: Naming the first bad field ("expected ..., got ...").
        """
        for name in ("paired_response", "use_policy_std", "normalize_response"):
            _check(isinstance(getattr(self, name), bool), f"{name} a bool", getattr(self, name))
        _check(
            isinstance(self.nyquist_fraction, (int, float)) and 0 < self.nyquist_fraction < 1,
            "nyquist_fraction in (0, 1)",
            self.nyquist_fraction,
        )
        if self.gate is not None:
            _check(
                isinstance(self.gate, (int, float))
                and not isinstance(self.gate, bool)
                and -1 <= self.gate <= 1,
                "gate a rank correlation in [-1, 1] (or None)",
                self.gate,
            )
        if self.dt is not None:
            _check(
                isinstance(self.dt, (int, float)) and math.isfinite(self.dt) and self.dt > 0,
                "dt finite and > 0 (or None: read from the env)",
                self.dt,
            )
        if self.fade is not None:
            _check(
                isinstance(self.fade, (int, float))
                and not isinstance(self.fade, bool)
                and 0 < self.fade <= 1,
                "fade a fraction of the training budget in (0, 1] (or None)",
                self.fade,
            )
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

        CONTRACT.md section 1 without any section 1b field: the step scales with Q's
        magnitude and the shift is unbounded. alpha = 0.05 is ours (the paper gives none).

        Args:
            **overrides: Fields to change, e.g. ``amplitude=0.1``.
        """
        # Checked by __post_init__ like any constructor argument.
        values: dict[str, Any] = dict(
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
        values.update(overrides)
        return cls(**values)

    @classmethod
    def ppo(cls, **overrides: Any) -> EsaConfig:
        """The shipped default of ``ESAPPO``: ``EsaConfig()`` bounded at 1 sigma, faded by half.

        The setting the ``seeking`` study (E2) tested as ``ppo_esa`` against PPO, a placebo
        and the gradient control on four envs: the trust region E1 picked for the quadratic
        head (1 policy standard deviation) and ESA's strength falling linearly to 0 over
        the first half of the budget of ``learn()``, so that the second half is PPO
        (``experiments/RESULTS.md`` gives E2's verdicts).

        Args:
            **overrides: Fields to change, e.g. ``fade=None`` for ESA through the whole budget.
        """
        values: dict[str, Any] = {"trust_region": PPO_TRUST_REGION, "fade": PPO_FADE, **overrides}
        return cls(**values)

    @classmethod
    def off_policy(cls, **overrides: Any) -> EsaConfig:
        """The shipped default of the off-policy drop-ins (``ESASAC``, ``ESATD3``).

        ``EsaConfig()`` with a wider trust region: an off-policy learner pays no importance
        ratio for shifted data, and its twin Q critic is steadier than PPO's fitted head. The
        bound is the pre-declared pick of the ``ground_truth`` study on SAC (tuning seeds
        100-102, InvertedPendulum-v5 and Hopper-v5): the largest bound whose
        measured Monte-Carlo return gain is above 0 with 95 % confidence on both envs
        (``experiments/RESULTS.md``).

        Args:
            **overrides: Fields to change, e.g. ``trust_region=0.25``.
        """
        values: dict[str, Any] = {"trust_region": OFF_POLICY_TRUST_REGION, **overrides}
        return cls(**values)

    def strength(self, elapsed: float) -> float:
        """ESA's strength ``f`` in [0, 1] once ``elapsed`` of the training budget has passed.

        ``1 - elapsed / fade`` clipped to [0, 1] (:attr:`fade`); always 1 without a fade.

        Args:
            elapsed: The fraction of the budget done, e.g. ``num_timesteps / total``.
        """
        if self.fade is None:
            return 1.0
        return float(min(1.0, max(0.0, 1.0 - elapsed / self.fade)))

    def frequencies(self, action_dim: int, dt: float) -> tuple[float, ...]:
        """Returns the per-dimension frequencies for ``action_dim`` dimensions and step ``dt``."""
        if self.frequency is None or np.ndim(self.frequency) == 0:
            w = (
                self.nyquist_fraction * math.pi / dt
                if self.frequency is None
                else float(np.asarray(self.frequency, dtype=np.float64))
            )
            return (
                tuple(float(x) for x in np.linspace(w, w / 2, action_dim))
                if action_dim > 1
                else (w,)
            )
        return tuple(float(x) for x in np.asarray(self.frequency, dtype=np.float64))

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

        Returns:
            The session config.

        Raises:
            ValueError: If a hyperparameter is invalid for this action space and time step.
        """
        dt = self.dt if self.dt is not None else dt
        return SessionConfig(
            action_dim=action_dim,
            dt=dt,
            amplitude=self.amplitude,
            frequency=self.frequencies(action_dim, dt),
            learning_rate=self.learning_rate,
            highpass_cutoff=self.highpass_cutoff,
            disable_highpass=self.disable_highpass,
            action_low=_finite_bound(action_low, -math.inf),
            action_high=_finite_bound(action_high, math.inf),
            shift_limit=self.shift_limit,
            lr_decay=self.lr_decay,
            max_episodes=self.max_episodes,
            normalize_response=self.normalize_response,
            response_rms_rate=self.response_rms_rate,
            response_clip=self.response_clip,
            shift_leak=self.shift_leak,
            trust_region=self.trust_region,
        )
