"""The research arms of ESASAC and ESATD3: subclasses that override what the arm changes.

The product's off-policy drop-ins find ESA's shift at the policy's sample ``a_t`` and
probe the mean of the target twins. The studies also ran the mean anchor
(:class:`MeanAnchor`: the shift found at the policy's action without its noise, the noise
kept on top), the executed probe (:class:`ExecutedProbe`: the env executes the probe, the
sinusoid as exploration) and other probed critics (:class:`ProbedCritic`). Each is a mixin
put before the drop-in in the bases; :func:`off_policy_class` composes them from a run's
stored options.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

import numpy as np
import torch as th
from esa_client.sb3 import ESASAC, ESATD3

if TYPE_CHECKING:
    # The mixins are always combined with a drop-in (:func:`off_policy_class`).
    from esa_client.sb3.off_policy import OffPolicyEsaMixin as _Base
else:
    _Base = object

PROBE_CRITICS = ("online_min", "online_mean", "target_min", "target_mean")
"""The twin critics ESA can probe: the online or the Polyak target networks, min or mean."""


class MeanAnchor(_Base):
    """ESA (or the gradient control) at ``mu``, executed as ``clip(a_t + v)``.

    The actor already maximises Q at ``mu``, so a shift that starts at ``a_t = mu + noise``
    largely points back toward ``mu`` and removes exploration (``esa/noise_cosine`` near 1);
    at ``mu`` the shift can only say where the critic sees more than the actor has learned,
    and the policy's noise is kept on top, as Optimistic Actor-Critic shifts its mean.
    """

    def _shifted(
        self,
        obs: Any,
        sampled: np.ndarray,
        mu: np.ndarray,
        sigma: np.ndarray,
        strength: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        def execute(shift: np.ndarray) -> np.ndarray:
            executed: np.ndarray = np.clip(sampled + shift, -1.0, 1.0)
            return executed

        def session() -> tuple[np.ndarray, np.ndarray]:
            shift = self._esa_step(obs, mu, sigma, strength) - mu
            return execute(shift), shift

        return self._control_shift().act(
            session,
            lambda: self._gradient_shift(obs, mu, sigma, strength),
            execute,
            self._episode_starts(),
        )


class ExecutedProbe(_Base):
    """The env executes ESA's probe ``a_t + v(t) + K sin(w t)``.

    With ``EsaConfig(learning_rate=0)``: exploration by the sinusoid alone. The probes are
    the points the step evaluates the critic at first, so :meth:`_esa_q` records them.
    """

    _esa_probes: list[np.ndarray]

    def _esa_q(self, obs: Any) -> Any:
        q_fn = super()._esa_q(obs)
        self._esa_probes = []

        def recording(actions: np.ndarray) -> np.ndarray:
            if not self._esa_probes:
                self._esa_probes.append(np.array(actions[: self.n_envs]))
            return q_fn(actions)  # type: ignore[no-any-return]

        return recording

    def _shifted(
        self,
        obs: Any,
        sampled: np.ndarray,
        mu: np.ndarray,
        sigma: np.ndarray,
        strength: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        applied = self._esa_step(obs, sampled, sigma, strength)
        # A faded (or skipped) step probes nothing: the env executes the applied action.
        probes = self._esa_probes[0] if self._esa_probes else applied
        return np.clip(probes, -1.0, 1.0), applied - sampled


class ProbedCritic(_Base):
    """ESA probes ``probe_critic``: the online or target twins, their min or mean."""

    probe_critic = "target_mean"

    def _probe_q(self, obs: Any, actions: th.Tensor) -> th.Tensor:
        online, reduce = self.probe_critic.split("_")
        critic = self.critic if online == "online" else self.critic_target
        q = th.cat(critic(obs, actions), dim=1)
        return q.min(dim=1).values if reduce == "min" else q.mean(dim=1)


FAMILIES: dict[str, type] = {"sac": ESASAC, "td3": ESATD3}


@functools.cache
def off_policy_class(
    family: str,
    anchor: str = "sample",
    execute: str = "shifted",
    probe_critic: str = "target_mean",
) -> type:
    """ESASAC or ESATD3 with the arm's anchor, executed action and probed critic.

    Raises:
        ValueError: For an unknown family, anchor, executed action or critic, or the probe
            executed with the mean anchor.
    """
    for name, value, allowed in (
        ("family", family, tuple(FAMILIES)),
        ("anchor", anchor, ("sample", "mean")),
        ("execute", execute, ("shifted", "probe")),
        ("probe_critic", probe_critic, PROBE_CRITICS),
    ):
        if value not in allowed:
            raise ValueError(f"expected {name} in {allowed}, got {value!r}")
    if anchor == "mean" and execute == "probe":
        raise ValueError("expected execute='shifted' with anchor='mean', got execute='probe'")
    parts: list[type] = []
    if anchor == "mean":
        parts.append(MeanAnchor)
    if execute == "probe":
        parts.append(ExecutedProbe)
    attributes = {}
    if probe_critic != "target_mean":
        parts.append(ProbedCritic)
        attributes["probe_critic"] = probe_critic
    base = FAMILIES[family]
    if not parts:
        return base
    name = "".join(part.__name__ for part in parts) + base.__name__
    return type(name, (*parts, base), attributes)
