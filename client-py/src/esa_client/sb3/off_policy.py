"""What ESASAC and ESATD3 share: the probed twin critic, its gate, and the shifted action."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import torch as th
from stable_baselines3.common.noise import ActionNoise

from ..common.advantage_head import rank_correlation
from ..common.runtime import SMALLEST_SCALE
from ..config import EsaConfig
from .mixin import EsaMixin, tile_obs

if TYPE_CHECKING:
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm as _Algorithm
    from stable_baselines3.common.policies import ContinuousCritic
else:
    _Algorithm = object

ProbeCritic = Literal["online_min", "online_mean", "target_min", "target_mean"]
PROBE_CRITICS: tuple[str, ...] = ("online_min", "online_mean", "target_min", "target_mean")

Shift = Literal["esc", "gradient"]
"""How the shift is found: ESA's extremum seeking, or the critic's action gradient."""
SHIFTS: tuple[str, ...] = ("esc", "gradient")

Execute = Literal["shifted", "probe"]
"""What the env executes: ``a_t + v(t)``, or the probe ``a_t + v(t) + K sin(w t)``."""
EXECUTES: tuple[str, ...] = ("shifted", "probe")


class OffPolicyEsaMixin(EsaMixin, _Algorithm):
    """ESA on an SB3 off-policy actor-critic whose critic is a twin ``Q(s, a)``.

    Works in the squashed action space [-1, 1] (the replay buffer's). Subclasses say
    where the policy's action is and how wide it is (:meth:`_policy_mean_and_std`).

    Two controls share everything but the shift, so that a gain can be credited:

    * ``esa_shift="gradient"``: the shift is ``kappa sigma u`` with ``u`` the probed
      critic's action gradient at ``a_t`` in units of sigma, normalised to length 1, and
      ``kappa`` the config's ``trust_region`` (the bound ESA's shift lives in; 1 when
      unset). Computed here with autograd; no ESA session is used.
    * ``esa_execute="probe"``: the env executes the probe itself; with
      ``EsaConfig(learning_rate=0)`` that is exploration by the sinusoid alone.
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
        **kwargs: Any,
    ) -> None:
        """Checks the off-policy ESA arguments, then creates the model.

        Raises:
            ValueError: For an unknown ``esa_probe_critic``, ``esa_shift`` or ``esa_execute``,
                an ``esa_gate_every`` below 1, or the probe executed by the gradient control.
        """
        for name, value, allowed in (
            ("esa_probe_critic", esa_probe_critic, PROBE_CRITICS),
            ("esa_shift", esa_shift, SHIFTS),
            ("esa_execute", esa_execute, EXECUTES),
        ):
            if value not in allowed:
                raise ValueError(f"expected {name} in {allowed}, got {value!r}")
        if esa_shift == "gradient" and esa_execute == "probe":
            raise ValueError(
                "expected esa_execute='shifted' with esa_shift='gradient' (the gradient "
                f"control has no probe), got esa_execute={esa_execute!r}"
            )
        if not (isinstance(esa_gate_every, int) and esa_gate_every >= 1):
            raise ValueError(f"expected esa_gate_every >= 1, got {esa_gate_every!r}")
        self.esa_probe_critic = esa_probe_critic
        self.esa_gate_every = esa_gate_every
        self.esa_shift = esa_shift
        self.esa_execute = esa_execute
        self._esa_active = False
        self._esa_gate_checked_at = 0
        super().__init__(policy, env, *args, **kwargs)

    @staticmethod
    def _default_esa() -> EsaConfig:
        return EsaConfig.off_policy()

    def _policy_mean_and_std(self, obs: Any) -> tuple[th.Tensor, th.Tensor]:
        """The policy's action and its spread sigma in [-1, 1] units, each ``(batch, D)``."""
        raise NotImplementedError

    def _policy_std(self, obs: Any, n: int) -> th.Tensor:
        """The policy's spread sigma in [-1, 1] units for ``n`` observations, ``(n, D)``."""
        return self._policy_mean_and_std(obs)[1]

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
        action, buffer_action = super()._sample_action(learning_starts, action_noise, n_envs)
        self._update_gate(learning_starts)
        if not self._esa_active:
            return action, buffer_action
        assert self._last_obs is not None and self._last_episode_starts is not None  # in rollouts
        obs, _ = self.policy.obs_to_tensor(self._last_obs)
        std = self._policy_std(obs, n_envs)
        sigma = np.maximum(std.reshape(n_envs, -1).cpu().numpy(), SMALLEST_SCALE)
        sampled = buffer_action.reshape(n_envs, -1)
        if self.esa_shift == "gradient":
            applied = self._gradient_step(obs, sampled, sigma)
        else:
            runtime = self._esa_runtime()
            execute_probe = self.esa_execute == "probe"
            applied = runtime.step(
                sampled,
                self._last_episode_starts,
                self._esa_q(obs),
                sigma,
                want_probes=execute_probe,
            )
            if execute_probe:
                assert runtime.last_probes is not None  # the step waited for its probes
                applied = np.clip(runtime.last_probes, -1.0, 1.0)
        buffer_action = applied.reshape(buffer_action.shape).astype(buffer_action.dtype)
        return self.policy.unscale_action(buffer_action), buffer_action

    def _gradient_step(self, obs: Any, sampled: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """``a_t + kappa sigma u``: the gradient control's action, clipped to [-1, 1]."""
        kappa = self.esa.trust_region if self.esa.trust_region is not None else 1.0
        actions = th.as_tensor(sampled, dtype=th.float32, device=self.device).requires_grad_(True)
        # autograd.grad, not backward: the critics' own .grad must not collect this.
        (grad,) = th.autograd.grad(self._probe_q(obs, actions).sum(), actions)
        scaled = grad.cpu().numpy().astype(np.float64) * sigma
        norm = np.linalg.norm(scaled, axis=1, keepdims=True)
        unit = np.divide(scaled, norm, out=np.zeros_like(scaled), where=norm > 0)
        self.logger.record_mean("esa/shift_over_std", float(kappa * np.abs(unit).mean()))
        applied: np.ndarray = np.clip(sampled + kappa * sigma * unit, -1.0, 1.0)
        return applied

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
