"""What ESASAC and ESATD3 share: the probed twin critic, its gate, and the shifted action."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import torch as th
from stable_baselines3.common.noise import ActionNoise

from ..common.advantage_head import rank_correlation
from ..common.controls import RandomDirections, shift_report
from ..config import EsaConfig
from ..transports.base import SMALLEST_SCALE
from .mixin import EsaMixin, tile_obs

if TYPE_CHECKING:
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm as _Algorithm
    from stable_baselines3.common.policies import ContinuousCritic
else:
    _Algorithm = object

ProbeCritic = Literal["online_min", "online_mean", "target_min", "target_mean"]
PROBE_CRITICS: tuple[str, ...] = ("online_min", "online_mean", "target_min", "target_mean")

Shift = Literal["esc", "gradient", "placebo"]
"""How the shift is found: ESA's extremum seeking, the critic's action gradient, or ESA's
shift in a random direction (the placebo)."""
SHIFTS: tuple[str, ...] = ("esc", "gradient", "placebo")

SHIFT_REPORT_EVERY = 8
"""Shifted steps per :func:`shift_report`: its numpy costs about an actor call, a few % of an
off-policy step when run on every one."""

Anchor = Literal["sample", "mean"]
"""Where the shift is found: at the policy's sample ``a_t``, or at its mean ``mu``."""
ANCHORS: tuple[str, ...] = ("sample", "mean")

Execute = Literal["shifted", "probe"]
"""What the env executes: ``a_t + v(t)``, or the probe ``a_t + v(t) + K sin(w t)``."""
EXECUTES: tuple[str, ...] = ("shifted", "probe")


class OffPolicyEsaMixin(EsaMixin, _Algorithm):
    """ESA on an SB3 off-policy actor-critic whose critic is a twin ``Q(s, a)``.

    Works in the squashed action space [-1, 1] (the replay buffer's). Subclasses say
    where the policy's action is and how wide it is (:meth:`_policy_mean_and_std`).

    Controls share everything but the shift, so that a gain can be credited:

    * ``esa_shift="gradient"``: the shift is ``kappa sigma u`` with ``u`` the probed
      critic's action gradient at the anchor in units of sigma, normalised to length 1,
      and ``kappa`` the config's ``trust_region`` (the bound ESA's shift lives in; 1 when
      unset). Computed here with autograd; no ESA session is used.
    * ``esa_shift="placebo"``: ESA's sessions run exactly as for ``"esc"``, and the env
      executes ``clip(a_t + |v| s)``: ESA's shift ``v`` per dimension with a random sign
      vector ``s`` drawn per env at each episode start
      (:class:`~esa_client.common.controls.RandomDirections`, seeded from the model's
      ``seed``). Same size, schedule and temporal correlation as ESA's shift, a direction
      that knows nothing of the critic: tells direction from mere perturbation.
    * ``esa_execute="probe"``: the env executes the probe itself; with
      ``EsaConfig(learning_rate=0)`` that is exploration by the sinusoid alone.

    ``esa_anchor`` says where the shift is found. ``"sample"``: at ``a_t``, the policy's
    sample. ``"mean"``: at ``mu``, the policy's action without its exploration noise
    (SAC's ``tanh(mean)``, TD3's actor output); ESA's session (or the critic's gradient)
    runs on ``mu`` and the env executes ``clip(a_t + v)``, so the policy's noise is kept
    on top of a shifted mean, as Optimistic Actor-Critic shifts its mean along an
    optimistic Q. Why: the actor already maximises Q at ``mu``, so a shift that starts at
    ``a_t = mu + noise`` largely points back toward ``mu`` and removes exploration
    (``esa/noise_cosine`` near 1); at ``mu`` the shift can only say where the critic
    sees more than the actor has learned.

    Under ``EsaConfig.fade`` every shift (ESC, placebo, gradient) is scaled by the same
    strength ``f``, falling from 1 to 0 over that fraction of the budget of ``learn()``
    (:meth:`EsaMixin._esa_strength`); from ``f = 0`` on the env executes ``a_t`` and no
    session steps.

    On one in ``SHIFT_REPORT_EVERY`` of the steps a shift is applied on,
    :func:`~esa_client.common.controls.shift_report` of it is averaged into the logger:
    ``esa/noise_cosine`` (``cos(v, mu - a_t)``), ``esa/at_bound`` (the share of elements
    at the faded bound ``f kappa sigma``) and ``esa/undone_by_clip`` (the share the box's
    clip turns into no change). The sample anchored ESC shift is read as ``applied - a_t``
    after the session's own clip to the box, so the clip undoes none of it there by
    construction.
    """

    critic: ContinuousCritic
    critic_target: ContinuousCritic

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa_probe_critic: ProbeCritic = "target_mean",
        esa_gate_every: int = 1000,
        esa_shift: Shift = "esc",
        esa_execute: Execute = "shifted",
        esa_anchor: Anchor = "sample",
        **kwargs: Any,
    ) -> None:
        """Checks the off-policy ESA arguments, then creates the model.

        Raises:
            ValueError: For an unknown ``esa_probe_critic``, ``esa_shift``, ``esa_execute``
                or ``esa_anchor``, an ``esa_gate_every`` below 1, or the probe executed
                by anything but ESC at the sample.
        """
        for name, value, allowed in (
            ("esa_probe_critic", esa_probe_critic, PROBE_CRITICS),
            ("esa_shift", esa_shift, SHIFTS),
            ("esa_execute", esa_execute, EXECUTES),
            ("esa_anchor", esa_anchor, ANCHORS),
        ):
            if value not in allowed:
                raise ValueError(f"expected {name} in {allowed}, got {value!r}")
        if esa_execute == "probe" and (esa_shift != "esc" or esa_anchor != "sample"):
            raise ValueError(
                "expected esa_execute='shifted' unless esa_shift='esc' and "
                "esa_anchor='sample' (the probe is ESA's own, around the sample), got "
                f"esa_execute={esa_execute!r} with esa_shift={esa_shift!r} and "
                f"esa_anchor={esa_anchor!r}"
            )
        if not (isinstance(esa_gate_every, int) and esa_gate_every >= 1):
            raise ValueError(f"expected esa_gate_every >= 1, got {esa_gate_every!r}")
        self.esa_probe_critic = esa_probe_critic
        self.esa_gate_every = esa_gate_every
        self.esa_shift = esa_shift
        self.esa_execute = esa_execute
        self.esa_anchor = esa_anchor
        self._esa_active = False
        self._esa_gate_checked_at = 0
        self._esa_placebo: RandomDirections | None = None
        self._esa_shifted_steps = 0
        super().__init__(policy, env, *args, **kwargs)

    @staticmethod
    def _default_esa() -> EsaConfig:
        return EsaConfig.off_policy()

    def _policy_mean_and_std(self, obs: Any) -> tuple[th.Tensor, th.Tensor]:
        """The policy's action and its spread sigma in [-1, 1] units, each ``(batch, D)``."""
        raise NotImplementedError

    def _policy_sample(self, obs: Any) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """What SB3's ``predict(deterministic=False)`` samples, with the mean and sigma.

        All three come from one actor call, each ``(batch, D)``: the sample as the policy's
        ``_predict`` returns it (the same random draws), and :meth:`_policy_mean_and_std`.
        """
        raise NotImplementedError

    def esa_close(self) -> None:
        """Closes the ESA sessions (:meth:`EsaMixin.esa_close`); the placebo restarts with them."""
        self._esa_placebo = None
        super().esa_close()

    def _excluded_save_params(self) -> list[str]:
        # Like the sessions, the placebo's signs belong to one run on one VecEnv.
        return [*super()._excluded_save_params(), "_esa_placebo"]

    def _esa_space(self) -> tuple[np.ndarray, np.ndarray]:
        dim = int(np.prod(self.action_space.shape or ()))
        return -np.ones(dim), np.ones(dim)

    def _esa_env_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._esa_space()

    def _probe_q(self, obs: Any, actions: th.Tensor) -> th.Tensor:
        """The probed critic at ``(obs, actions)``, shape ``(batch,)``."""
        online, reduce = self.esa_probe_critic.split("_")
        critic = self.critic if online == "online" else self.critic_target
        q = th.cat(critic(obs, actions), dim=1)
        return q.min(dim=1).values if reduce == "min" else q.mean(dim=1)

    def _esa_q(self, obs: Any) -> Any:
        def q_fn(actions: np.ndarray) -> np.ndarray:
            reps = len(actions) // self.n_envs
            with th.no_grad():
                action_tensor = th.as_tensor(actions, dtype=th.float32, device=self.device)
                return self._probe_q(tile_obs(obs, reps), action_tensor).cpu().numpy()

        return q_fn

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: ActionNoise | None = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        self._update_gate(learning_starts)
        if not self._esa_active:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        assert self._last_obs is not None  # in rollouts
        obs, _ = self.policy.obs_to_tensor(self._last_obs)
        buffer_action, mean, std = self._sampled(obs, action_noise)
        strength = self._esa_strength()
        report = strength > 0 and self._esa_shifted_steps % SHIFT_REPORT_EVERY == 0
        mu = mean.reshape(n_envs, -1).cpu().numpy().astype(np.float64)
        sigma = np.maximum(std.reshape(n_envs, -1).cpu().numpy(), SMALLEST_SCALE)
        sampled = buffer_action.reshape(n_envs, -1)
        anchor = mu if self.esa_anchor == "mean" else sampled
        executed, shift = self._shifted(obs, sampled, anchor, sigma, strength)
        if strength > 0:
            self._esa_shifted_steps += 1
        if report:
            gradient = self.esa_shift == "gradient"
            bound = self._gradient_kappa() if gradient else self.esa.trust_region
            low, high = self._esa_env_bounds()
            values = shift_report(sampled, shift, mu, strength * sigma, low, high, bound)
            for key, value in values.items():
                self.logger.record_mean(f"esa/{key}", value)
        buffer_action = executed.reshape(buffer_action.shape).astype(buffer_action.dtype)
        return self.policy.unscale_action(buffer_action), buffer_action

    def _sampled(
        self, obs: Any, action_noise: ActionNoise | None
    ) -> tuple[np.ndarray, th.Tensor, th.Tensor]:
        """SB3's exploratory action in [-1, 1] (its buffer action), the mean and sigma.

        The steps of ``OffPolicyAlgorithm._sample_action`` after the warm-up, with the
        policy called once (:meth:`_policy_sample`) instead of once for SB3's sample and
        again for ESA's mean and sigma: a per-step cost of the off-policy drop-ins. The
        sample goes through ``predict``'s unscaling and ``_sample_action``'s rescaling, so
        that its bits are SB3's.
        """
        with th.no_grad():
            actions, mean, std = self._policy_sample(obs)
        sample = actions.cpu().numpy().reshape((-1, *(self.action_space.shape or ())))
        scaled: np.ndarray = self.policy.scale_action(self.policy.unscale_action(sample))
        if action_noise is not None:
            scaled = np.clip(scaled + action_noise(), -1, 1)
        return scaled, mean, std

    def _shifted(
        self,
        obs: Any,
        sampled: np.ndarray,
        anchor: np.ndarray,
        sigma: np.ndarray,
        strength: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The env's actions and the shift on top of ``a_t`` they come from, each ``(N, D)``.

        Args:
            obs: The current observations, as the policy takes them.
            sampled: The policy's samples ``a_t`` (with TD3's noise) in [-1, 1].
            anchor: Where the shift is found: ``sampled``, or the policy's action without
                its noise (``esa_anchor="mean"``).
            sigma: The action scale.
            strength: ESA's strength under the fade, in [0, 1].
        """
        if self.esa_shift == "gradient":
            shift = self._gradient_shift(obs, anchor, sigma, strength)
        else:
            assert self._last_episode_starts is not None  # set by _setup_learn and each step
            runtime = self._esa_runtime()
            execute_probe = self.esa_execute == "probe"
            applied = runtime.step(
                anchor,
                self._last_episode_starts,
                self._esa_q(obs),
                sigma,
                want_probes=execute_probe,
                strength=strength,
            )
            if execute_probe:
                assert runtime.last_probes is not None  # the step waited for its probes
                return np.clip(runtime.last_probes, -1.0, 1.0), applied - sampled
            if self.esa_shift == "esc" and self.esa_anchor == "sample":
                # The session's own action, not a_t + (applied - a_t): the same bits as ever.
                return applied, applied - sampled
            shift = applied - anchor
            if self.esa_shift == "placebo":
                shift = self._placebo(shift)
        executed: np.ndarray = np.clip(sampled + shift, -1.0, 1.0)
        return executed, shift

    def _placebo(self, shift: np.ndarray) -> np.ndarray:
        """ESA's ``shift`` with the placebo's random signs, which live with the sessions."""
        if self._esa_placebo is None:
            n_envs, action_dim = shift.shape
            self._esa_placebo = RandomDirections(n_envs, action_dim, self.seed)
        assert self._last_episode_starts is not None  # set by _setup_learn and each step
        return self._esa_placebo(shift, self._last_episode_starts)

    def _gradient_kappa(self) -> float:
        """The gradient control's step in units of sigma: the trust region, 1 when unset."""
        return self.esa.trust_region if self.esa.trust_region is not None else 1.0

    def _gradient_shift(
        self, obs: Any, anchor: np.ndarray, sigma: np.ndarray, strength: float = 1.0
    ) -> np.ndarray:
        """``f kappa sigma u``: the gradient control's shift, ``u`` the unit gradient at ``anchor``.

        Args:
            obs: The current observations, as the policy takes them.
            anchor: Where the critic's action gradient is taken, ``(N, D)`` in [-1, 1].
            sigma: The action scale, ``(N, D)``.
            strength: ESA's strength ``f`` under the fade; at 0 no gradient is computed.
        """
        if strength <= 0:
            return np.zeros(anchor.shape)
        scale = strength * self._gradient_kappa()
        actions = th.as_tensor(anchor, dtype=th.float32, device=self.device).requires_grad_(True)
        # autograd.grad, not backward: the critics' own .grad must not collect this.
        (grad,) = th.autograd.grad(self._probe_q(obs, actions).sum(), actions)
        scaled = grad.cpu().numpy().astype(np.float64) * sigma
        norm = np.linalg.norm(scaled, axis=1, keepdims=True)
        unit = np.divide(scaled, norm, out=np.zeros_like(scaled), where=norm > 0)
        self.logger.record_mean("esa/shift_over_std", float(scale * np.abs(unit).mean()))
        shift: np.ndarray = scale * sigma * unit
        return shift

    def _update_gate(self, learning_starts: int) -> None:
        warming_up = self.num_timesteps < learning_starts and not (
            self.use_sde and self.use_sde_at_warmup
        )
        if warming_up:
            return
        if self.esa.gate is None:
            self._esa_active = True
            return
        if self.num_timesteps - self._esa_gate_checked_at < self.esa_gate_every:
            return
        assert self.replay_buffer is not None  # set up with the model
        recent = min(self.num_timesteps - self._esa_gate_checked_at, self.replay_buffer.size())
        self._esa_gate_checked_at = self.num_timesteps
        quality = self._critic_quality(recent // self.n_envs)
        self._esa_active = quality >= self.esa.gate
        self.logger.record("esa/gate_correlation", quality)
        self.logger.record("esa/active", float(self._esa_active))

    def _critic_quality(self, steps: int) -> float:
        """Rank correlation of ``Q(s, a) - Q(s, mu)`` with ``r + gamma V(s') - V(s)``.

        Over the last ``steps`` transitions of every env, read from the replay buffer
        directly (its sampler would draw from numpy's global generator).
        """
        rb = self.replay_buffer
        assert rb is not None  # set up with the model
        idx = (rb.pos - 1 - np.arange(max(steps, 2))) % rb.buffer_size

        def flat(array: np.ndarray) -> np.ndarray:
            values: np.ndarray = array[idx].reshape(len(idx) * self.n_envs, *array.shape[2:])
            return values

        def normalized_obs(array: np.ndarray) -> np.ndarray:
            # A ReplayBuffer holds array observations (dict ones live in a DictReplayBuffer).
            return cast(np.ndarray, rb._normalize_obs(flat(array), self._vec_normalize_env))

        next_obs = rb.next_observations if not rb.optimize_memory_usage else None
        if next_obs is None:
            return 0.0
        obs = rb.to_torch(normalized_obs(rb.observations))
        nxt = rb.to_torch(normalized_obs(next_obs))
        actions = rb.to_torch(flat(rb.actions))
        rewards = rb._normalize_reward(flat(rb.rewards), self._vec_normalize_env)
        alive = 1.0 - flat(rb.dones) * (1.0 - flat(rb.timeouts))
        with th.no_grad():
            mu, _ = self._policy_mean_and_std(obs)
            mu_next, _ = self._policy_mean_and_std(nxt)
            value = self._probe_q(obs, mu).cpu().numpy()
            value_next = self._probe_q(nxt, mu_next).cpu().numpy()
            predicted = self._probe_q(obs, actions).cpu().numpy() - value
        advantage = rewards + self.gamma * alive * value_next - value
        return rank_correlation(predicted, advantage)

    def _store_transition(
        self,
        replay_buffer: Any,
        buffer_action: np.ndarray,
        new_obs: Any,
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        # Off-policy SB3 does not track episode starts; ESA needs them to reset the sessions.
        self._last_episode_starts = np.asarray(dones, dtype=bool).copy()
