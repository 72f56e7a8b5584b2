"""``ESAPPO``: stable-baselines3 PPO whose sampled actions are shifted by ESA."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
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
from stable_baselines3.common.vec_env import VecEnv

from .._native import AdvantageMlp
from ..common.advantage_head import AdvantageHead, Rollout, critic_quality, fit, normalized
from ..common.head_fit_worker import FitJob, HeadFitWorker, PendingFit, shared_worker
from ..config import EsaConfig
from ..transports.base import HeadStep, LinearCritic
from .mixin import EsaMixin

Mode = Literal["behaviour", "target"]
"""Where ESA's shift goes: into the executed action, or into the policy update's target."""
MODES: tuple[str, ...] = ("behaviour", "target")

Shift = Literal["esc", "gradient"]
"""How the shift is found: ESA's extremum seeking, or the advantage head's gradient."""
SHIFTS: tuple[str, ...] = ("esc", "gradient")


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

    The critic ESA probes is an advantage head ``A(s, a) = w(s) . (a - mu) / sigma``
    (:mod:`esa_client.common.advantage_head`), fitted on the normalized GAE advantages of
    the last ``esa_head_rollouts`` rollouts. ESA intervenes only while the head passes
    ``EsaConfig.gate``: the rank correlation of its ``A(s, a) - A(s, mu)`` with the GAE
    advantages of a rollout it was not trained on (logged as ``esa/gate_correlation``
    and ``esa/active``).

    With ``EsaConfig(learning_rate=0)`` the shift stays 0 and training is bit for bit
    plain PPO with the same seed: the executed and stored actions, their log-probabilities
    and every random draw are PPO's (the head is initialized on a forked torch generator
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
        esa_head_hidden: Hidden units of each of the advantage head's two layers.
        esa_head_learning_rate: Adam learning rate of the advantage head.
        esa_head_epochs: Passes over its data each time the head is fitted.
        esa_head_batch_size: Minibatch size when fitting the head.
        esa_head_rollouts: How many of the latest rollouts the head is fitted on.
        esa_head_worker: Fit the head in a worker process while PPO updates the policy
            (:mod:`esa_client.common.head_fit_worker`), so that the fit costs no wall-clock
            where a second CPU is free; the results are the same bits as fitting it here.
            ``None`` (default): on a CPU device with two or more CPUs available to the
            process; ``False``: never; ``True``: on a CPU device whatever the CPU count. On
            another device (a GPU) the head is fitted there, in the trainer, so that a model
            saved on a CPU host loads anywhere.
            The worker is one extra Python process with torch, shared by the process's
            models: about 400 MB of memory of its own.
        esa_mode: ``"behaviour"``: the env executes ``a_t + v(t)`` (Algorithm 1).
            ``"target"``: the env executes the policy's own sample (exact on-policy data)
            while the sessions still run on it, and a bounded auxiliary loss in PPO's
            minibatch loop pulls the policy mean toward ``mu_old(s) + v_t``, in units of
            ``sigma_old`` (dual policy iteration's improve-then-project step): ESA as an
            improvement target instead of behaviour. Box observations only.
        esa_shift: ``"esc"`` (ESA's sessions) or ``"gradient"`` (the control: a shift of the
            trust region's size, ``kappa sigma w(s) / |w(s)|``, along the head's action
            gradient; no session).
        esa_target_weight: Weight of the target mode's auxiliary loss: a Huber loss of the
            shortfall ``max(0, sign(z) (z - (mu - mu_old) / sigma_old))`` with
            ``z = v_t / sigma_old``, over the samples ESA shifted. One-sided: the mean is
            pulled at least ``v_t`` along ``v_t`` and never held back beyond it.
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
        esa_head_hidden: int = 64,
        esa_head_learning_rate: float = 1e-3,
        esa_head_epochs: int = 5,
        esa_head_batch_size: int = 256,
        esa_head_rollouts: int = 4,
        esa_head_worker: bool | None = None,
        esa_mode: Mode = "behaviour",
        esa_shift: Shift = "esc",
        esa_target_weight: float = 1.0,
        **kwargs: Any,
    ) -> None:
        """Creates the PPO model and the advantage head."""
        for option, choice, allowed in (
            ("esa_mode", esa_mode, MODES),
            ("esa_shift", esa_shift, SHIFTS),
        ):
            if choice not in allowed:
                raise ValueError(f"expected {option} in {allowed}, got {choice!r}")
        if not (isinstance(esa_target_weight, (int, float)) and esa_target_weight > 0):
            raise ValueError(f"expected esa_target_weight > 0, got {esa_target_weight!r}")
        self.esa_mode = esa_mode
        self.esa_shift = esa_shift
        self.esa_target_weight = float(esa_target_weight)
        self._esa_targets: list[np.ndarray] = []
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
        if not (esa_head_worker is None or isinstance(esa_head_worker, bool)):
            raise ValueError(
                f"expected esa_head_worker True, False or None, got {esa_head_worker!r}"
            )
        # Set before the SB3 constructor: its _setup_model builds the head from them.
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
        super().__init__(policy, env, *args, esa=esa, esa_address=esa_address, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.policy.squash_output:
            raise ValueError(
                "expected a policy without squash_output for ESAPPO (the shifted sample "
                "must have a density under the policy), got squash_output=True"
            )
        if self.esa_mode == "target" and isinstance(self.observation_space, spaces.Dict):
            raise ValueError(
                "expected a Box observation space for esa_mode='target', got "
                f"{self.observation_space}"
            )
        features_dim = spaces.flatdim(self.observation_space)
        action_dim = int(np.prod(self.action_space.shape or ()))
        # A forked generator: building the head must not move PPO's random stream.
        with th.random.fork_rng(devices=[]):
            self.esa_head = AdvantageHead(features_dim, action_dim, self.esa_head_hidden)
        self.esa_head.to(self.device)
        # fused: Adam's update of all six tensors in one kernel; the per-tensor kernels cost
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
        if self.esa_head_worker is False or self.device.type != "cpu":
            return None
        return shared_worker(force=bool(self.esa_head_worker))

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "esa_head", "esa_head_optimizer"], variables

    def _excluded_save_params(self) -> list[str]:
        # The head's training data are rebuilt from the next rollouts, the scaling from the
        # action space, the snapshot from the head.
        excluded = ["_esa_head_data", "_esa_scale", "_esa_targets", "_esa_head_snapshot"]
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
        """The observation as the head sees it: preprocessed as SB3 does, flattened."""
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
        """The head in Rust, copied again whenever its parameters changed (a fit, a load)."""
        version = self.esa_head.version()
        if self._esa_head_snapshot is None or self._esa_head_snapshot[0] != version:
            self._esa_head_snapshot = (version, self.esa_head.snapshot(*self._esa_scaling()))
        return self._esa_head_snapshot[1]

    def _esa_critic(
        self, obs: th.Tensor | dict[str, th.Tensor], mean: np.ndarray, std: np.ndarray
    ) -> LinearCritic:
        """The head at the current observations, for actions in ESA units.

        ``A = w . (a - mu) / sigma`` is linear in the action: with ``a`` in ESA units,
        ``A = g . a + b`` for ``g = w h / sigma`` and ``b = w . (c - mu) / sigma`` (``c``,
        ``h``: the Box's center and half-width), which the in-process engine evaluates
        itself. ``mean`` and ``std`` are the policy's, float32 ``(N, D)``.
        """
        return LinearCritic(*self._esa_mlp().critic(self._step_features(obs), mean, std))

    @contextlib.contextmanager
    def _esa_forward(self) -> Iterator[None]:
        """Within the block, the policy's forward pass returns ESA's executed actions.

        SB3's ``collect_rollouts`` calls ``policy(obs)`` for ``(actions, values,
        log_probs)``, clips the actions for the env and stores them unclipped: this forward
        is SB3's ``ActorCriticPolicy.forward`` with ``a_t`` replaced by ``a_t + v(t)``,
        ``log_probs`` still ``log pi(a_t)``.
        """
        policy = self.policy
        # The head changes only in train() or a load, outside a rollout: its Rust copy is
        # taken (if it changed) once per rollout, not checked at every step.
        mlp = self._esa_mlp()

        def forward(
            obs: th.Tensor, deterministic: bool = False
        ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
            features = policy.extract_features(obs)
            if policy.share_features_extractor:
                latent_pi, latent_vf = policy.mlp_extractor(features)
            else:
                pi_features, vf_features = features
                latent_pi = policy.mlp_extractor.forward_actor(pi_features)
                latent_vf = policy.mlp_extractor.forward_critic(vf_features)
            values = policy.value_net(latent_vf)
            distribution = policy._get_action_dist_from_latent(latent_pi)
            actions = distribution.get_actions(deterministic=deterministic)
            log_prob = distribution.log_prob(actions)
            if self._esa_active and not deterministic:
                gaussian = _gaussian(distribution)
                # numpy views (copies on a GPU) of the sample, mean and std: SB3's Box
                # distributions give them flat, (N, D) each.
                sample = actions.cpu().numpy()
                mean, std = gaussian.mean.cpu().numpy(), gaussian.stddev.cpu().numpy()
                head_in = self._step_features(obs)
                executed: np.ndarray | None = None
                if self.esa_shift == "gradient":
                    shift = self._gradient_shift(mlp.weights(head_in)) * std
                else:
                    starts = self._last_episode_starts
                    assert starts is not None  # set by SB3 before its rollouts
                    shift, executed = self._esa_runtime().step_head(
                        HeadStep(mlp, head_in, sample, mean, std), starts
                    )
                if self.esa_mode == "target":
                    self._esa_targets.append(shift / std)
                else:
                    if executed is None:
                        # a + shift in float64, cast back to the policy's float32 (one call).
                        executed = mlp.executed(sample, shift)
                    actions = th.from_numpy(executed).to(actions.device)
            elif self.esa_mode == "target" and not deterministic:
                self._esa_targets.append(np.zeros((len(actions), self._esa_scaling()[0].size)))
            return actions.reshape((-1, *self._esa_box().shape)), values, log_prob

        # The hook itself: an instance attribute shadows the policy's forward in this block.
        policy.forward = forward  # type: ignore[method-assign]
        try:
            yield
        finally:
            del policy.forward

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """SB3's ``collect_rollouts``, with the ESA step inside the policy's forward pass."""
        self._esa_targets = []
        with th.no_grad(), self._esa_forward():
            return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)

    def _gradient_shift(self, w: np.ndarray) -> np.ndarray:
        """``kappa w(s) / |w(s)|``: the head's action gradient as a shift in units of sigma.

        The head ``A(s, a) = w(s) . (a - mu) / sigma`` has the gradient ``w(s)`` (given, as
        its Rust copy's ``weights`` returns it) in units of sigma, so the step needs no autograd;
        kappa is the trust region (1 when unset).
        """
        kappa = self.esa.trust_region if self.esa.trust_region is not None else 1.0
        norm = np.linalg.norm(w, axis=1, keepdims=True)
        unit: np.ndarray = np.divide(w, norm, out=np.zeros_like(w), where=norm > 0)
        return kappa * unit

    def train(self) -> None:
        """Checks the gate and fits the advantage head on the rollout, runs PPO's update.

        The fit runs beside PPO's update where a worker serves (``esa_head_worker``), and
        the head holds it when this returns. In the target mode, PPO's update also pulls
        the mean toward ``mu_old + v_t``.
        """
        pending = self._update_esa_head()
        try:
            targets = self._esa_targets if self.esa_mode == "target" else []
            if not any(np.any(z != 0) for z in targets):
                super().train()
                return
            with self._esa_target_loss(np.stack(targets)):
                super().train()
        finally:
            self._finish_esa_head_fit(pending)

    @contextlib.contextmanager
    def _esa_target_loss(self, targets: np.ndarray) -> Iterator[None]:
        """Within the block, each of PPO's optimizer steps also descends the target loss.

        SB3's ``PPO.train`` has no hook for an extra loss term, so two are added for the
        block: the rollout buffer remembers the indices of the minibatch it last served,
        and the policy optimizer's ``step`` first back-propagates the target loss on
        those samples (after PPO's gradient clipping, with a Huber loss that bounds it).
        """
        buffer = self.rollout_buffer
        flatten = RolloutBuffer.swap_and_flatten
        obs = buffer.to_torch(flatten(buffer.observations))
        z = buffer.to_torch(flatten(targets.astype(np.float32)))
        shifted = (z != 0).any(dim=1)
        with th.no_grad():
            # The policy that collected the rollout: train() has not updated it yet.
            old = _gaussian(self.policy.get_distribution(obs))
            mu_old = old.mean.reshape(len(obs), -1)
            sigma_old = old.stddev.reshape(len(obs), -1)
        served: list[np.ndarray] = []
        get_samples = buffer._get_samples
        optimizer = self.policy.optimizer
        step = optimizer.step
        losses: list[float] = []

        def remembering_get_samples(batch_inds: np.ndarray, env: Any = None) -> Any:
            served[:] = [batch_inds]
            return get_samples(batch_inds, env)

        def step_with_target(*args: Any, **kwargs: Any) -> Any:
            idx = th.as_tensor(served[0], device=obs.device)
            idx = idx[shifted[idx]]
            if len(idx):
                new = _gaussian(self.policy.get_distribution(obs[idx]))
                moved = (new.mean.reshape(len(idx), -1) - mu_old[idx]) / sigma_old[idx]
                target = z[idx]
                # One-sided: only the part of the target the mean has not yet covered. A
                # symmetric loss toward mu_old + v anchored the policy at mu_old (v is a
                # fraction of sigma) and stalled PPO: return 116 against 457 on
                # InvertedPendulum-v5 with v ~ 0.001 sigma.
                shortfall = F.relu(th.sign(target) * (target - moved))
                loss = self.esa_target_weight * F.smooth_l1_loss(
                    shortfall, th.zeros_like(shortfall)
                )
                loss.backward()
                losses.append(loss.item())
            return step(*args, **kwargs)

        # Instance attributes shadow the methods for the block (as in _esa_forward).
        buffer._get_samples = remembering_get_samples  # type: ignore[method-assign]
        optimizer.step = step_with_target  # type: ignore[method-assign]
        try:
            yield
        finally:
            del buffer._get_samples
            del optimizer.step
            if losses:
                self.logger.record("esa/target_loss", float(np.mean(losses)))
            self.logger.record("esa/target_shift_over_std", float(z[shifted].abs().mean()))

    def _update_esa_head(self) -> PendingFit | None:
        """Checks the gate on the new rollout and sends the head's fit on it to the worker.

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
                self.esa_head, self.esa_head_optimizer, self._esa_head_data, **self._esa_fit_args()
            )
            pending = worker.submit(job)
        if not self._esa_head_fitted and gate is None:
            self._esa_active = True
        self._esa_head_fitted = True
        self.logger.record("esa/active", float(self._esa_active))
        return pending

    def _finish_esa_head_fit(self, pending: PendingFit | None) -> None:
        """Writes the worker's fit into the head, or fits the head here; records the loss."""
        result = pending() if pending is not None else None
        if result is None:
            # From the state the job copied, so the bits the worker would have given.
            data = self._esa_head_data
            loss = fit(self.esa_head, self.esa_head_optimizer, data, **self._esa_fit_args())
        else:
            self._esa_rng = result.apply(self.esa_head, self.esa_head_optimizer)
            loss = result.loss
        self.logger.record("esa/head_loss", loss)
        self.logger.record("esa/head_fit_in_worker", float(result is not None))

    def _esa_fit_args(self) -> dict[str, Any]:
        return dict(
            rng=self._esa_rng, epochs=self.esa_head_epochs, batch_size=self.esa_head_batch_size
        )


def _gaussian(distribution: Distribution) -> th.distributions.Normal:
    """The torch Normal of a Box policy's action distribution.

    A Box policy without squashing (checked in ``_setup_model``) has a DiagGaussian or a gSDE
    distribution, both a ``Normal`` underneath; SB3 types the attribute for every kind.
    """
    return cast(th.distributions.Normal, distribution.distribution)
