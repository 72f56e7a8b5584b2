"""``ESAPPO``: stable-baselines3 PPO whose sampled actions are shifted by ESA."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal, cast

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import Distribution
from stable_baselines3.common.preprocessing import is_image_space, preprocess_obs
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from .._native import AdvantageMlp
from ..common.action_critics import (
    CRITIC_KINDS,
    CriticAtStep,
    CriticKind,
    fit_critic,
    make_critic,
)
from ..common.advantage_head import AdvantageHead, Rollout, critic_quality, fit, normalized
from ..common.controls import RandomDirections, shift_report
from ..common.head_fit_worker import FitJob, HeadFitWorker, PendingFit, shared_worker
from ..config import EsaConfig
from ..transports.base import SMALLEST_SCALE, HeadStep
from .esa_buffer import EsaRolloutBuffer, EsaRolloutBufferSamples
from .mixin import EsaMixin

Mode = Literal["behaviour", "target"]
"""Where ESA's shift goes: into the executed action, or into the policy update's target."""
MODES: tuple[str, ...] = ("behaviour", "target")

Shift = Literal["esc", "gradient", "placebo"]
"""How the shift is found: ESA's extremum seeking, the critic's gradient, or the placebo."""
SHIFTS: tuple[str, ...] = ("esc", "gradient", "placebo")

Objective = Literal["clip", "decoupled"]
"""PPO's clipped objective, or the decoupled one (clip around pi_old, weight b -> pi_old)."""
OBJECTIVES: tuple[str, ...] = ("clip", "decoupled")

REPORT_EVERY = 8
"""One step in this many records what the shifts did (:func:`shift_report`)."""


class ESAPPO(EsaMixin, PPO):
    """PPO with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.PPO``.

    Each rollout step follows Algorithm 1 of the paper with the bounded, scale-free law
    of CONTRACT.md section 1b: the policy samples ``a_t``, ESA probes a critic around it,
    and the env executes ``a_t + v(t)``, the shift *before* this step's update. Because
    ``v(t)`` does not depend on ``a_t``, the behaviour density of the executed action is
    the policy's, translated by ``v(t)``, so the rollout stores the executed action
    unclipped (as SB3 stores its samples) with ``log pi_old(a_t)``, its exact behaviour
    log-probability: PPO's ratio ``pi_new(x) / b(x)`` is then a correct importance ratio.
    The policy's standard deviation is the action scale, so the trust region bounds the
    shift in units of it.

    The critic ESA probes (``esa_critic``), each fitted on the normalized GAE advantages
    of the last ``esa_head_rollouts`` rollouts:

    * ``"linear"`` (default): ``A(s, a) = w(s) . (a - mu) / sigma``
      (:mod:`esa_client.common.advantage_head`), evaluated by the engine itself. It has no
      extremum: ESA integrates ``w(s)`` up to its bound (``docs/guides/sb3.md``).
    * ``"quadratic"``: ``A = w(s) . z + sum_j u_j(s) (z_j^2 - 1)``, ``u <= 0``, with a maximum
      ESA converges to; ``"qnet"``: a Q-network ``Q(s, z)`` as in the paper's Algorithm 1
      (:mod:`esa_client.common.action_critics`). Both are evaluated at the action the env
      executes (clipped to the Box).

    ESA intervenes only while the critic passes ``EsaConfig.gate``: the rank correlation
    of its ``A(s, a) - A(s, mu)`` with the GAE advantages of a rollout it was not trained
    on (logged as ``esa/gate_correlation`` and ``esa/active``). ``EsaConfig.fade`` fades
    ESA over the training budget. Per rollout the logger also gets ``esa/noise_cosine``
    (``cos(v, mu - a_t)``: how much of the shift removes exploration noise),
    ``esa/at_bound``, ``esa/undone_by_clip`` and ``esa/shift_over_sigma``.

    With ``EsaConfig(learning_rate=0)`` the shift stays 0 and training is bit for bit
    plain PPO with the same seed: the executed and stored actions, their log-probabilities
    and every random draw are PPO's (the critic is initialized on a forked torch generator
    and draws its minibatches from its own numpy generator).

    ESA works in the policy's action space scaled to [-1, 1] by the Box bounds (the same
    units as SAC's), so one ``EsaConfig`` means the same on every env; it is not clipped
    there (PPO's Gaussian is unbounded, SB3 stores its samples unclipped and the env
    clips). ``squash_output`` policies are refused: shifting a squashed sample has no
    density under the squashed policy. ``predict`` is unchanged: evaluation uses the
    plain policy.

    Example::

        model = ESAPPO("MlpPolicy", "InvertedPendulum-v5")   # EsaConfig() by default
        model.learn(50_000)

    Args:
        policy: As for PPO.
        env: As for PPO.
        esa: The ESA hyperparameters (default ``EsaConfig()``), or a dict of its fields.
        esa_address: An esa-server address (``host:port`` or ``unix:/path``); None
            spawns a private server that stops with the model (or ``esa_close()``)
            when ``esa_engine`` is ``"sidecar"``.
        esa_engine: ``"inprocess"`` (esa-core in this process) or ``"sidecar"`` (an
            esa-server); None: ``esa_address``'s server when given, else in-process.
        esa_critic: ``"linear"``, ``"quadratic"`` or ``"qnet"`` (see above).
        esa_head_hidden: Hidden units of each of the critic's two layers.
        esa_head_learning_rate: Adam learning rate of the critic.
        esa_head_epochs: Passes over its data each time the critic is fitted.
        esa_head_batch_size: Minibatch size when fitting the critic.
        esa_head_rollouts: How many of the latest rollouts the critic is fitted on.
        esa_head_worker: Fit the linear head in a worker process while PPO updates the
            policy (:mod:`esa_client.common.head_fit_worker`): the same bits, about 6-8 %
            less wall-clock where a second CPU is free, and one more Python process with
            torch (about 400 MB). Off by default: ESAPPO starts no process of its own.
            Only on a CPU device and with the linear head; elsewhere the fit runs here.
        esa_mode: ``"behaviour"``: the env executes ``a_t + v(t)`` (Algorithm 1).
            ``"target"``: the env executes the policy's own sample (exact on-policy data)
            while the sessions still run on it, and a bounded auxiliary loss in PPO's
            minibatch loop pulls the policy mean toward ``mu_old(s) + v_t``, in units of
            ``sigma_old`` (dual policy iteration's improve-then-project step): ESA as an
            improvement target instead of behaviour. Box observations only.
        esa_shift: ``"esc"`` (ESA's sessions), ``"gradient"`` (the control: a shift of the
            trust region's size, faded like ESA's, along the critic's action gradient at the
            sample; no session) or ``"placebo"`` (the control: ESA's ``|v|`` per dimension,
            schedule and temporal correlation, with a random sign vector per env and
            episode; :class:`~esa_client.common.controls.RandomDirections`).
        esa_target_weight: Weight of the target mode's auxiliary loss: a Huber loss of the
            shortfall ``max(0, sign(z) (z - (mu - mu_old) / sigma_old))`` with
            ``z = v_t / sigma_old``, over the samples ESA shifted. One-sided: the mean is
            pulled at least ``v_t`` along ``v_t`` and never held back beyond it.
        esa_objective: ``"clip"``: PPO's objective, its ratio taken against the behaviour
            density. ``"decoupled"``: the decoupled objective of Hilton, Cobbe and Schulman
            (2022, "Batch size-invariance for policy optimization"): the ratio is clipped
            around the collecting policy ``pi_old`` at the executed action and weighted by
            ``min(pi_old(x) / b(x), esa_weight_cap)``, so a shift of a sizeable fraction of
            sigma does not fight the clip. Box observations only.
        esa_weight_cap: The decoupled objective's cap on ``pi_old / b`` (>= 1).
        **kwargs: Any other PPO argument.

    Raises:
        ValueError: If the action space is not a Box, the policy squashes its output, or
            an ESA setting is invalid for this env (e.g. a frequency past Nyquist).
    """

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa: EsaConfig | Mapping[str, Any] | None = None,
        esa_address: str | None = None,
        esa_critic: CriticKind = "linear",
        esa_head_hidden: int = 64,
        esa_head_learning_rate: float = 1e-3,
        esa_head_epochs: int = 5,
        esa_head_batch_size: int = 256,
        esa_head_rollouts: int = 4,
        esa_head_worker: bool = False,
        esa_mode: Mode = "behaviour",
        esa_shift: Shift = "esc",
        esa_target_weight: float = 1.0,
        esa_objective: Objective = "clip",
        esa_weight_cap: float = 2.0,
        **kwargs: Any,
    ) -> None:
        """Creates the PPO model and the critic ESA probes."""
        for option, choice, allowed in (
            ("esa_critic", esa_critic, CRITIC_KINDS),
            ("esa_mode", esa_mode, MODES),
            ("esa_shift", esa_shift, SHIFTS),
            ("esa_objective", esa_objective, OBJECTIVES),
        ):
            if choice not in allowed:
                raise ValueError(f"expected {option} in {allowed}, got {choice!r}")
        for name, number, least, rule in (
            ("esa_target_weight", esa_target_weight, np.nextafter(0.0, 1.0), "> 0"),
            ("esa_weight_cap", esa_weight_cap, 1.0, ">= 1"),
        ):
            real = isinstance(number, (int, float)) and not isinstance(number, bool)
            if not (real and np.isfinite(number) and number >= least):
                raise ValueError(f"expected {name} finite and {rule}, got {number!r}")
        for name, value in (
            ("esa_head_hidden", esa_head_hidden),
            ("esa_head_epochs", esa_head_epochs),
            ("esa_head_batch_size", esa_head_batch_size),
            ("esa_head_rollouts", esa_head_rollouts),
        ):
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"expected {name} an integer >= 1, got {value!r}")
        if not esa_head_learning_rate > 0:
            raise ValueError(f"expected esa_head_learning_rate > 0, got {esa_head_learning_rate}")
        if not isinstance(esa_head_worker, bool):
            raise ValueError(f"expected esa_head_worker True or False, got {esa_head_worker!r}")
        self.esa_critic = esa_critic
        self.esa_mode = esa_mode
        self.esa_shift = esa_shift
        self.esa_target_weight = float(esa_target_weight)
        self.esa_objective = esa_objective
        self.esa_weight_cap = float(esa_weight_cap)
        # Set before the SB3 constructor: its _setup_model builds the critic from them.
        self.esa_head_hidden = esa_head_hidden
        self.esa_head_learning_rate = esa_head_learning_rate
        self.esa_head_epochs = esa_head_epochs
        self.esa_head_batch_size = esa_head_batch_size
        self.esa_head_rollouts = esa_head_rollouts
        self.esa_head_worker = esa_head_worker
        self._esa_head_data: list[Rollout] = []
        self._esa_head_fitted = False
        self._esa_active = False
        self._esa_scale: tuple[np.ndarray, np.ndarray] | None = None
        self._esa_head_snapshot: tuple[tuple[int, ...], AdvantageMlp] | None = None
        self._esa_placebo: RandomDirections | None = None
        self._esa_steps = 0
        super().__init__(policy, env, *args, esa=esa, esa_address=esa_address, **kwargs)

    def _setup_model(self) -> None:
        box_obs = not isinstance(self.observation_space, spaces.Dict)
        if self.rollout_buffer_class is None and box_obs:
            self.rollout_buffer_class = EsaRolloutBuffer
        super()._setup_model()
        if self.policy.squash_output:
            raise ValueError(
                "expected a policy without squash_output for ESAPPO (the shifted sample "
                "must have a density under the policy), got squash_output=True"
            )
        for option, value, default in (
            ("esa_mode", self.esa_mode, "behaviour"),
            ("esa_objective", self.esa_objective, "clip"),
        ):
            if value != default and not isinstance(self.rollout_buffer, EsaRolloutBuffer):
                raise ValueError(
                    f"expected a Box observation space (ESAPPO's rollout buffer) for "
                    f"{option}={value!r}, got {self.observation_space} and "
                    f"{type(self.rollout_buffer).__name__}"
                )
        features_dim = spaces.flatdim(self.observation_space)
        action_dim = int(np.prod(self.action_space.shape or ()))
        # A forked generator: building the critic must not move PPO's random stream.
        with th.random.fork_rng(devices=[]):
            self.esa_head: nn.Module = (
                AdvantageHead(features_dim, action_dim, self.esa_head_hidden)
                if self.esa_critic == "linear"
                else make_critic(self.esa_critic, features_dim, action_dim, self.esa_head_hidden)
            )
        self.esa_head.to(self.device)
        # fused: Adam's update of all tensors in one kernel; the per-tensor kernels cost
        # as much as the head's gradients (bench/profiles/README.md). torch >= 2.4 has it on
        # the CPU and CUDA; elsewhere the default implementation.
        fused = self.device.type in ("cpu", "cuda") or None
        self.esa_head_optimizer = th.optim.Adam(
            self.esa_head.parameters(), lr=self.esa_head_learning_rate, fused=fused
        )
        self._esa_rng = np.random.default_rng(self.seed)

    def _setup_learn(self, *args: Any, **kwargs: Any) -> Any:
        # The worker starts with training, not with the model (a model loaded only to act
        # never fits), and has imported torch by the first fit a rollout later.
        self._esa_fit_worker()
        return super()._setup_learn(*args, **kwargs)

    def _esa_fit_worker(self) -> HeadFitWorker | None:
        """The process's head-fit worker if this model uses one, else None."""
        if not self.esa_head_worker or self.device.type != "cpu" or self.esa_critic != "linear":
            return None
        return shared_worker(force=True)

    def esa_close(self) -> None:
        """Closes the ESA sessions; the placebo's signs go with them (a new env, new signs)."""
        super().esa_close()
        self._esa_placebo = None

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "esa_head", "esa_head_optimizer"], variables

    def _excluded_save_params(self) -> list[str]:
        # The critic's training data are rebuilt from the next rollouts, the scaling from the
        # action space, the snapshot from the head, the placebo's signs at the next episode.
        excluded = ["_esa_head_data", "_esa_scale", "_esa_head_snapshot", "_esa_placebo"]
        return [*super()._excluded_save_params(), *excluded]

    def _esa_space(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        # PPO stores its Gaussian samples unclipped; ESA shifts them in that space too.
        return None, None

    def _esa_env_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low, high = super()._esa_env_bounds()
        return self._to_esa_units(low), self._to_esa_units(high)

    def _esa_scaling(self) -> tuple[np.ndarray, np.ndarray]:
        """Center and half-width mapping the Box to [-1, 1] (0 and 1 where a side is open)."""
        # Cached: every env step needs it, and the action space never changes.
        if self._esa_scale is None:
            box = self._esa_box()
            low, high = box.low.reshape(-1), box.high.reshape(-1)
            bounded = np.isfinite(low) & np.isfinite(high)
            self._esa_scale = (
                np.where(bounded, (high + low) / 2, 0.0),
                np.where(bounded, (high - low) / 2, 1.0),
            )
        return self._esa_scale

    def _to_esa_units(self, actions: np.ndarray) -> np.ndarray:
        center, half_width = self._esa_scaling()
        scaled: np.ndarray = (actions - center) / half_width
        return scaled

    def _head_features(self, obs: th.Tensor | dict[str, th.Tensor]) -> th.Tensor:
        """The observation as the critic sees it: preprocessed as SB3 does, flattened."""
        pre = preprocess_obs(obs, self.observation_space, self.policy.normalize_images)
        if isinstance(pre, dict):
            return th.cat([pre[key].flatten(1).float() for key in sorted(pre)], dim=1)
        return pre.flatten(1).float()

    def _step_features(self, obs: th.Tensor | dict[str, th.Tensor]) -> np.ndarray:
        """:meth:`_head_features` of one step's observations in numpy, for the head's Rust copy.

        For a Box that is not an image SB3 normalizes, its preprocessing is ``obs.float()``:
        a float32 or float64 observation is handed over as it is (``(N, F)``), and the Rust
        copy rounds float64 to float32 as torch's ``float()`` does, without a numpy cast per
        step; other observations are float32 ``(N, F)``.
        """
        space = self.observation_space
        if isinstance(obs, th.Tensor) and isinstance(space, spaces.Box):
            if not (self.policy.normalize_images and is_image_space(space)):
                host: np.ndarray = obs.cpu().numpy().reshape(len(obs), -1)
                if host.dtype in (np.float32, np.float64):
                    return host
                return host.astype(np.float32)
        return self._head_features(obs).cpu().numpy()

    def _esa_mlp(self) -> AdvantageMlp:
        """The linear head in Rust, copied again whenever its parameters changed (a fit, a load)."""
        head = cast(AdvantageHead, self.esa_head)
        version = head.version()
        if self._esa_head_snapshot is None or self._esa_head_snapshot[0] != version:
            self._esa_head_snapshot = (version, head.snapshot(*self._esa_scaling()))
        return self._esa_head_snapshot[1]

    def _critic_at(
        self, obs: th.Tensor | dict[str, th.Tensor], mean: np.ndarray, std: np.ndarray
    ) -> CriticAtStep:
        """The curved critic at the current observations, over actions in ESA units."""
        center, half_width = self._esa_scaling()
        low, high = self._esa_env_bounds()
        return CriticAtStep(
            self.esa_head,
            self._head_features(obs),
            (mean - center) / half_width,
            np.maximum(std / half_width, SMALLEST_SCALE),
            low,
            high,
        )

    def _policy_forward(
        self, obs: th.Tensor | dict[str, th.Tensor]
    ) -> tuple[Distribution, th.Tensor]:
        """The policy's action distribution and value at ``obs``.

        SB3's ``forward`` up to the sample, so that the sample draws what SB3's own would.
        """
        policy = self.policy
        features = policy.extract_features(obs)
        if policy.share_features_extractor:
            latent_pi, latent_vf = policy.mlp_extractor(features)
        else:
            pi_features, vf_features = features
            latent_pi = policy.mlp_extractor.forward_actor(pi_features)
            latent_vf = policy.mlp_extractor.forward_critic(vf_features)
        return policy._get_action_dist_from_latent(latent_pi), policy.value_net(latent_vf)

    def _esa_policy_step(
        self, obs: th.Tensor | dict[str, th.Tensor]
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, np.ndarray]:
        """SB3's ``policy(obs)`` with ESA: ``(executed, values, log pi(a_t), shift / sigma)``.

        The executed action is ``a_t + v(t)`` in the behaviour mode (the sample in the
        target mode), its log-probability still ``log pi(a_t)``; the shift in units of
        sigma is what the target mode pulls the mean toward (0 where ESA is off).
        """
        distribution, values = self._policy_forward(obs)
        actions = distribution.get_actions()
        log_prob = distribution.log_prob(actions)
        dim = self._esa_scaling()[0].size
        strength = self._esa_strength() if self._esa_active else 0.0
        if strength <= 0.0:
            return (
                actions.reshape((-1, *self._esa_box().shape)),
                values,
                log_prob,
                np.zeros((len(actions), dim)),
            )
        gaussian = _gaussian(distribution)
        # numpy views (copies on a GPU) of the sample, mean and std: SB3's Box distributions
        # give them flat, (N, D) each.
        sample = actions.cpu().numpy()
        mean, std = gaussian.mean.cpu().numpy(), gaussian.stddev.cpu().numpy()
        starts = self._last_episode_starts
        assert starts is not None  # set by SB3 before its rollouts
        shift, executed = self._esa_shift(obs, sample, mean, std, starts, strength)
        if self.esa_shift == "placebo":
            if self._esa_placebo is None:
                self._esa_placebo = RandomDirections(len(sample), dim, self.seed)
            shift = self._esa_placebo(shift, starts)
            executed = _executed(sample, shift)
        if self._esa_steps % REPORT_EVERY == 0:
            self._record_shift(sample, shift, mean, std, strength)
        self._esa_steps += 1
        if self.esa_mode == "behaviour":
            actions = th.from_numpy(executed).to(actions.device)
        return actions.reshape((-1, *self._esa_box().shape)), values, log_prob, shift / std

    def _esa_shift(
        self,
        obs: th.Tensor | dict[str, th.Tensor],
        sample: np.ndarray,
        mean: np.ndarray,
        std: np.ndarray,
        starts: np.ndarray,
        strength: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """ESA's shift (or the gradient control's) and the shifted sample: ``(shift, executed)``.

        The shift is in the Box's units, float64 ``(N, D)``; ``executed`` is the sample plus
        the shift, float32 ``(N, D)``: what the env executes in the behaviour mode.
        """
        runtime = self._esa_runtime()
        if self.esa_critic == "linear":
            mlp = self._esa_mlp()
            head_in = self._step_features(obs)
            if self.esa_shift == "gradient":
                shift = self._gradient_shift(mlp.weights(head_in), strength) * std
                return shift, _executed(sample, shift)
            head_step = HeadStep(mlp, head_in, mean, std, runtime.esa.use_policy_std, strength)
            # The engine's one call computes both (in-process at full strength).
            return runtime.step_head(sample, head_step, starts)
        critic = self._critic_at(obs, mean, std)
        center, half_width = self._esa_scaling()
        scaled = (sample - center) / half_width
        if self.esa_shift == "gradient":
            shift = self._gradient_shift(critic.gradient(scaled), strength) * std
        else:
            # The quadratic head in closed form: the engine evaluates it at the probes.
            q_fn = critic.closed_form() if self.esa_critic == "quadratic" else critic
            applied = runtime.step(scaled, starts, q_fn, critic.std, strength=strength)
            shift = (applied - scaled) * half_width
        return shift, _executed(sample, shift)

    def _gradient_shift(self, gradient: np.ndarray, strength: float) -> np.ndarray:
        """``f kappa g / |g|``: the critic's action gradient ``g`` in units of sigma as a shift.

        ``kappa`` is the trust region (1 when unset) and ``f`` the fade's strength, so the
        control's shift is as large as ESA's bound allows at every point of training.
        """
        kappa = self.esa.trust_region if self.esa.trust_region is not None else 1.0
        norm = np.linalg.norm(gradient, axis=1, keepdims=True)
        unit: np.ndarray = np.divide(gradient, norm, out=np.zeros_like(gradient), where=norm > 0)
        return strength * kappa * unit

    def _record_shift(
        self, sample: np.ndarray, shift: np.ndarray, mean: np.ndarray, std: np.ndarray, f: float
    ) -> None:
        box = self._esa_box()
        kappa = self.esa.trust_region
        report = shift_report(
            sample,
            shift,
            mean,
            std,
            box.low.reshape(-1),
            box.high.reshape(-1),
            None if kappa is None else f * kappa,
        )
        for key, value in report.items():
            self.logger.record_mean(f"esa/{key}", value)
        self.logger.record_mean("esa/strength", f)

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """SB3's ``OnPolicyAlgorithm.collect_rollouts`` with ESA's step in the policy's place.

        The env gets ``clip(a_t + v(t))``; the buffer stores ``a_t + v(t)`` unclipped with
        ``log pi(a_t)``, and (target mode) the shift in units of sigma.
        """
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        n_steps = 0
        rollout_buffer.reset()
        targets: np.ndarray | None = None
        if self.esa_mode == "target" and isinstance(rollout_buffer, EsaRolloutBuffer):
            dim = self._esa_scaling()[0].size
            targets = np.zeros(
                (rollout_buffer.buffer_size, rollout_buffer.n_envs, dim), dtype=np.float32
            )
            rollout_buffer.extras["esa_target"] = targets
        if self.use_sde:
            self.policy.reset_noise(env.num_envs)
        callback.on_rollout_start()
        while n_steps < n_rollout_steps:
            if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
                self.policy.reset_noise(env.num_envs)
            with th.no_grad():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)  # type: ignore[arg-type]
                actions_t, values, log_probs, target = self._esa_policy_step(obs_tensor)
            actions = actions_t.cpu().numpy()
            # PPO's Gaussian is unbounded: the env gets the sample clipped to its Box.
            box = self._esa_box()
            clipped_actions = np.clip(actions, box.low, box.high)
            new_obs, rewards, dones, infos = env.step(clipped_actions)
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1
            # A truncated episode bootstraps with the value of its last observation (SB3 #633).
            for idx, done in enumerate(dones):
                if (
                    done
                    and infos[idx].get("terminal_observation") is not None
                    and infos[idx].get("TimeLimit.truncated", False)
                ):
                    terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                    with th.no_grad():
                        terminal_value = self.policy.predict_values(terminal_obs)[0]
                    rewards[idx] += self.gamma * terminal_value
            if targets is not None:
                targets[rollout_buffer.pos] = target
            rollout_buffer.add(
                self._last_obs,  # type: ignore[arg-type]
                actions,
                rewards,
                self._last_episode_starts,  # type: ignore[arg-type]
                values,
                log_probs,
            )
            self._last_obs = new_obs  # type: ignore[assignment]
            self._last_episode_starts = dones
        with th.no_grad():
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device))  # type: ignore[arg-type]
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def train(self) -> None:
        """Checks the gate and fits the critic on the rollout, then PPO's update.

        SB3's ``PPO.train`` with two additions: the decoupled objective (``esa_objective``)
        and, in the target mode, the auxiliary loss that pulls the mean toward
        ``mu_old + v_t``. With neither, the same operations in the same order as SB3's.
        The critic's fit runs beside PPO's update where a worker serves
        (``esa_head_worker``), and the critic holds it when this returns.
        """
        pending = self._update_esa_head()
        try:
            self._train_policy()
        finally:
            self._finish_esa_head_fit(pending)

    def _train_policy(self) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        clip_range = self.clip_range(self._current_progress_remaining)  # type: ignore[operator]
        if self.clip_range_vf is not None:
            clip_range_vf = self.clip_range_vf(self._current_progress_remaining)  # type: ignore[operator]
        targeted = self._prepare_esa_update()
        entropy_losses, pg_losses, value_losses, clip_fractions = [], [], [], []
        target_losses: list[float] = []
        continue_training = True
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            for rollout_data in self.rollout_buffer.get(self.batch_size):
                actions = rollout_data.actions
                values, log_prob, entropy = self.policy.evaluate_actions(
                    rollout_data.observations, actions
                )
                values = values.flatten()
                advantages = rollout_data.advantages
                # Normalization does not make sense if mini batchsize == 1 (SB3 #325).
                if self.normalize_advantage and len(advantages) > 1:
                    advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
                # The decoupled objective's ratio is to the proximal policy pi_old at the
                # executed action, weighted by pi_old / b (capped); PPO's is to b itself.
                reference = rollout_data.old_log_prob
                weight: th.Tensor | float = 1.0
                if self.esa_objective == "decoupled":
                    samples = cast(EsaRolloutBufferSamples, rollout_data)
                    reference = samples.extras["proximal_log_prob"].flatten()
                    weight = th.exp(reference - rollout_data.old_log_prob).clamp(
                        max=self.esa_weight_cap
                    )
                ratio = th.exp(log_prob - reference)
                policy_loss_1 = advantages * ratio
                policy_loss_2 = advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)
                policy_loss = -(weight * th.min(policy_loss_1, policy_loss_2)).mean()
                pg_losses.append(policy_loss.item())
                clip_fraction = th.mean((th.abs(ratio - 1) > clip_range).float()).item()
                clip_fractions.append(clip_fraction)
                if self.clip_range_vf is None:
                    values_pred = values
                else:
                    values_pred = rollout_data.old_values + th.clamp(
                        values - rollout_data.old_values, -clip_range_vf, clip_range_vf
                    )
                value_loss = F.mse_loss(rollout_data.returns, values_pred)
                value_losses.append(value_loss.item())
                if entropy is None:
                    entropy_loss = -th.mean(-log_prob)
                else:
                    entropy_loss = -th.mean(entropy)
                entropy_losses.append(entropy_loss.item())
                loss = policy_loss + self.ent_coef * entropy_loss + self.vf_coef * value_loss
                # Schulman's estimator of the KL to the policy the ratio is taken against.
                with th.no_grad():
                    log_ratio = log_prob - reference
                    approx_kl_div = th.mean((th.exp(log_ratio) - 1) - log_ratio).cpu().numpy()
                    approx_kl_divs.append(approx_kl_div)
                if self.target_kl is not None and approx_kl_div > 1.5 * self.target_kl:
                    continue_training = False
                    if self.verbose >= 1:
                        print(
                            f"Early stopping at step {epoch} due to reaching max kl: "
                            f"{approx_kl_div:.2f}"
                        )
                    break
                self.policy.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                if targeted:
                    # After PPO's clipping: the target's pull is bounded by its Huber loss.
                    target_losses.extend(
                        self._target_loss(cast(EsaRolloutBufferSamples, rollout_data))
                    )
                self.policy.optimizer.step()
            self._n_updates += 1
            if not continue_training:
                break
        explained_var = explained_variance(
            self.rollout_buffer.values.flatten(), self.rollout_buffer.returns.flatten()
        )
        self.logger.record("train/entropy_loss", np.mean(entropy_losses))
        self.logger.record("train/policy_gradient_loss", np.mean(pg_losses))
        self.logger.record("train/value_loss", np.mean(value_losses))
        self.logger.record("train/approx_kl", np.mean(approx_kl_divs))
        self.logger.record("train/clip_fraction", np.mean(clip_fractions))
        self.logger.record("train/loss", loss.item())
        self.logger.record("train/explained_variance", explained_var)
        if hasattr(self.policy, "log_std"):
            self.logger.record("train/std", th.exp(self.policy.log_std).mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
        if self.clip_range_vf is not None:
            self.logger.record("train/clip_range_vf", clip_range_vf)
        if target_losses:
            self.logger.record("esa/target_loss", float(np.mean(target_losses)))

    def _prepare_esa_update(self) -> bool:
        """Fills the buffer's extras the update needs from the policy that collected it.

        Returns:
            Whether the target mode's loss runs (some sample was shifted).
        """
        buffer = self.rollout_buffer
        if not isinstance(buffer, EsaRolloutBuffer):
            return False
        targets = buffer.extras.get("esa_target")
        targeted = targets is not None and bool(np.any(targets != 0))
        if not (targeted or self.esa_objective == "decoupled"):
            return False
        flat = (buffer.buffer_size, buffer.n_envs)
        obs = buffer.to_torch(buffer.observations.reshape(-1, *buffer.obs_shape))
        with th.no_grad():
            # The policy that collected the rollout: train() has not updated it yet.
            old = self.policy.get_distribution(obs)
            if self.esa_objective == "decoupled":
                actions = buffer.to_torch(buffer.actions.reshape(-1, buffer.action_dim))
                proximal = old.log_prob(actions)
                buffer.extras["proximal_log_prob"] = proximal.cpu().numpy().reshape(flat)
            if targeted:
                gaussian = _gaussian(old)
                for name, values in (("old_mean", gaussian.mean), ("old_std", gaussian.stddev)):
                    buffer.extras[name] = values.cpu().numpy().reshape(*flat, -1)
        if targeted and targets is not None:
            shifted = np.abs(targets[np.any(targets != 0, axis=2)])
            self.logger.record("esa/target_shift_over_std", float(shifted.mean()))
        return targeted

    def _target_loss(self, samples: EsaRolloutBufferSamples) -> list[float]:
        """Back-propagates the target mode's loss on a minibatch's shifted samples.

        Returns:
            The loss (one value), or nothing when no sample of the minibatch was shifted.
        """
        z = samples.extras["esa_target"]
        shifted = (z != 0).any(dim=1)
        if not bool(shifted.any()):
            return []
        obs = samples.observations[shifted]
        mu_old = samples.extras["old_mean"][shifted]
        sigma_old = samples.extras["old_std"][shifted]
        new = _gaussian(self.policy.get_distribution(obs))
        moved = (new.mean.reshape(len(obs), -1) - mu_old) / sigma_old
        target = z[shifted]
        # One-sided: only the part of the target the mean has not yet covered. A symmetric
        # loss toward mu_old + v anchored the policy at mu_old (v is a fraction of sigma)
        # and stalled PPO: return 116 against 457 on InvertedPendulum-v5 with v ~ 0.001 sigma.
        shortfall = F.relu(th.sign(target) * (target - moved))
        loss = self.esa_target_weight * F.smooth_l1_loss(shortfall, th.zeros_like(shortfall))
        loss.backward()
        return [loss.item()]

    def _update_esa_head(self) -> PendingFit | None:
        """Checks the gate on the new rollout and sends the linear head's fit to the worker.

        Returns:
            The worker's fit, or None (the fit runs in :meth:`_finish_esa_head_fit`).
        """
        buffer = self.rollout_buffer
        obs = buffer.to_torch(buffer.observations.reshape(-1, *buffer.obs_shape))
        actions = buffer.to_torch(buffer.actions.reshape(-1, buffer.action_dim))
        advantages = buffer.to_torch(buffer.advantages.reshape(-1))
        with th.no_grad():
            # The policy that collected this rollout: train() has not updated it yet.
            distribution = _gaussian(self.policy.get_distribution(obs))
            mean = distribution.mean.reshape(len(obs), -1)
            std = distribution.stddev.reshape(len(obs), -1)
        rollout = Rollout(self._head_features(obs), (actions - mean) / std, normalized(advantages))
        gate = self.esa.gate
        if self._esa_head_fitted:
            quality = critic_quality(self.esa_head, rollout, advantages)
            self.logger.record("esa/gate_correlation", quality)
            self._esa_active = gate is None or quality >= gate
        self._esa_head_data = [*self._esa_head_data, rollout][-self.esa_head_rollouts :]
        worker = self._esa_fit_worker()
        pending = None
        if worker is not None:
            job = FitJob.of(
                cast(AdvantageHead, self.esa_head),
                self.esa_head_optimizer,
                self._esa_head_data,
                **self._esa_fit_args(),
            )
            pending = worker.submit(job)
        if not self._esa_head_fitted and gate is None:
            self._esa_active = True
        self._esa_head_fitted = True
        self.logger.record("esa/active", float(self._esa_active))
        return pending

    def _finish_esa_head_fit(self, pending: PendingFit | None) -> None:
        """Writes the worker's fit into the head, or fits the critic here; records the loss."""
        result = pending() if pending is not None else None
        if result is not None:
            self._esa_rng = result.apply(
                cast(AdvantageHead, self.esa_head), self.esa_head_optimizer
            )
            loss = result.loss
        else:
            # From the state the job copied, so the bits the worker would have given.
            data = self._esa_head_data
            if isinstance(self.esa_head, AdvantageHead):
                loss = fit(self.esa_head, self.esa_head_optimizer, data, **self._esa_fit_args())
            else:
                loss = fit_critic(
                    self.esa_head, self.esa_head_optimizer, data, **self._esa_fit_args()
                )
        self.logger.record("esa/head_loss", loss)
        self.logger.record("esa/head_fit_in_worker", float(result is not None))

    def _esa_fit_args(self) -> dict[str, Any]:
        return dict(
            rng=self._esa_rng, epochs=self.esa_head_epochs, batch_size=self.esa_head_batch_size
        )


def _executed(sample: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The sample plus the shift in float64, cast back to the policy's float32.

    ``AdvantageMlp.executed``'s bits, for the paths that have no head step.
    """
    executed: np.ndarray = (sample.astype(np.float64) + shift).astype(sample.dtype)
    return executed


def _gaussian(distribution: Distribution) -> th.distributions.Normal:
    """The torch Normal of a Box policy's action distribution.

    A Box policy without squashing (checked in ``_setup_model``) has a DiagGaussian or a gSDE
    distribution, both a ``Normal`` underneath; SB3 types the attribute for every kind.
    """
    return cast(th.distributions.Normal, distribution.distribution)
