"""Learners that keep the ESA critic fitted and set the gate and fade (sent with the weights)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner
from ray.rllib.algorithms.sac.torch.sac_torch_learner import SACTorchLearner
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

from ..common.quadratic_head import (
    Rollout,
    critic_quality,
    fit_critic,
    normalized,
    rank_correlation,
)
from ..config import EsaConfig
from .modules import EsaModuleMixin, EsaPPOTorchRLModule, EsaSACTorchRLModule


def _unwrapped(module: Any) -> Any:
    return module.unwrapped() if hasattr(module, "unwrapped") else module


def _gate(module: EsaPPOTorchRLModule | EsaSACTorchRLModule) -> float | None:
    gate = module.esa_settings["config"].get("gate")
    return None if gate is None else float(gate)


def _set_strength(module: EsaModuleMixin, timesteps: dict[str, Any]) -> None:
    """Sets ``esa_strength``: the fade at the env steps sampled so far, of ``with_esa``'s budget."""
    settings = module.esa_settings
    budget = settings.get("budget")
    sampled = float(timesteps.get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0) or 0)
    strength = EsaConfig(**settings["config"]).strength(sampled / budget if budget else 0.0)
    with torch.no_grad():
        module.esa_strength.fill_(strength)


class EsaSACTorchLearner(SACTorchLearner):
    """SAC's learner, setting the ``esa_active`` of an ``EsaSACTorchRLModule``: ESASAC's gate.

    Every :attr:`gate_every` sampled env steps it computes :func:`sac_critic_quality` on the
    update's replay sample (RLlib's replay buffer lives elsewhere). With ``EsaConfig(gate=None)``
    ESA turns on at the first update. Logged per module: ``esa/gate_correlation``, ``esa/active``.
    """

    gate_every = 1000
    """Sampled env steps between two checks of the gate (``ESASAC.gate_every``)."""

    def build(self) -> None:
        """Builds RLlib's SAC learner and the gate's bookkeeping."""
        super().build()
        self._esa_checked_at: dict[Any, float] = {}
        self._esa_due: set[Any] = set()

    def before_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """Decides which modules check their gate on this update's batch."""
        super().before_gradient_based_update(timesteps=timesteps)
        now = float(timesteps.get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0) or 0)
        for mid, rl_module in self.module._rl_modules.items():
            module = _unwrapped(rl_module)
            if not isinstance(module, EsaSACTorchRLModule):
                continue
            _set_strength(module, timesteps)
            if _gate(module) is None:
                module.esa_active.fill_(1.0)
            elif now - self._esa_checked_at.get(mid, 0.0) >= self.gate_every:
                self._esa_due.add(mid)
                self._esa_checked_at[mid] = now

    def compute_loss_for_module(
        self, *, module_id: Any, config: Any, batch: dict[str, Any], fwd_out: dict[str, Any]
    ) -> Any:
        """SAC's loss; on a gate check, also the critic's quality on this batch (no grad)."""
        loss = super().compute_loss_for_module(
            module_id=module_id, config=config, batch=batch, fwd_out=fwd_out
        )
        module = _unwrapped(self.module[module_id])
        if not isinstance(module, EsaSACTorchRLModule):
            return loss
        gate = _gate(module)
        if module_id in self._esa_due and gate is not None:
            self._esa_due.discard(module_id)
            quality = sac_critic_quality(module, batch, config.gamma)
            module.esa_active.fill_(float(quality >= gate))
            self.metrics.log_value((module_id, "esa/gate_correlation"), quality, window=1)
        self.metrics.log_value((module_id, "esa/active"), module.esa_active.item(), window=1)
        return loss


def sac_critic_quality(module: EsaSACTorchRLModule, batch: dict[str, Any], gamma: float) -> float:
    """Rank correlation of ``Q(s, a) - Q(s, mu)`` with ``r + gamma^n V(s') - V(s)`` on a batch.

    ``Q`` is the probed critic, ``V(s) = Q(s, mu(s))``; ``n`` is the batch's ``n_step``
    (RLlib's n-step returns), 1 if absent.
    """
    with torch.no_grad():
        obs, nxt = batch[Columns.OBS], batch[Columns.NEXT_OBS]
        none = torch.empty(0)  # the probed critic needs no distribution inputs
        value = module.esa_q(obs, none, module.esa_mean_action(obs))
        value_next = module.esa_q(nxt, none, module.esa_mean_action(nxt))
        predicted = module.esa_q(obs, none, batch[Columns.ACTIONS]) - value
        alive = 1.0 - batch[Columns.TERMINATEDS].float()
        discount = gamma ** batch["n_step"] if "n_step" in batch else gamma
        advantage = batch[Columns.REWARDS] + discount * alive * value_next - value
    return rank_correlation(predicted.double().cpu().numpy(), advantage.double().cpu().numpy())


class EsaRolloutRecorder(ConnectorV2):
    """Learner connector piece (after GAE): ESA PPO modules' loss-masked rollouts to ``pending``."""

    def __init__(self, pending: dict[Any, Any], **kwargs: Any) -> None:
        """Writes into ``pending`` (the learner's)."""
        super().__init__(**kwargs)
        self.pending = pending

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], **kwargs: Any) -> Any:
        """Records the rollouts; returns ``batch`` unchanged."""
        for module_id, data in batch.items():
            module = _unwrapped(rl_module[module_id]) if module_id in rl_module else None
            if not isinstance(module, EsaPPOTorchRLModule) or not (
                Postprocessing.ADVANTAGES in data and Columns.ACTION_DIST_INPUTS in data
            ):
                continue

            def tensor(name: str, data: dict[str, Any] = data) -> torch.Tensor:
                value = torch.as_tensor(data[name])
                mask = data.get(Columns.LOSS_MASK)
                return value[torch.as_tensor(mask, dtype=torch.bool)] if mask is not None else value

            with torch.no_grad():
                advantages = tensor(Postprocessing.ADVANTAGES).float()
                features = module.esa_features(tensor(Columns.OBS))
                dist_inputs = tensor(Columns.ACTION_DIST_INPUTS).float()
                z = module.esa_z(dist_inputs, tensor(Columns.ACTIONS).float())
                rollout = Rollout(features, z, normalized(advantages))
            self.pending[module_id] = (rollout, advantages)
        return batch


@dataclass
class _Head:
    """One module's head training state (not checkpointed: rebuilt from the next rollouts)."""

    optimizer: torch.optim.Optimizer
    rng: np.random.Generator
    rollouts: list[Rollout] = field(default_factory=list)
    fitted: bool = False
    active: bool = False


class EsaPPOTorchLearner(PPOTorchLearner):
    """PPO's learner with ``ESAPPO``'s objective, fitting its quadratic head.

    The loss is PPO's with the decoupled objective (``DecoupledPPO``): the ratio against the
    proximal policy ``pi_old`` at the executed action, weighted by ``min(pi_old / b, weight_cap)``,
    ``b`` the density RLlib stored; without a shift it is RLlib's PPO loss. After each update: the
    gate (``esa/gate_correlation``, on the new rollout before the head learns it), the head's fit on
    the last :attr:`head_rollouts` (``esa/head_loss``), then ``esa_active`` and ``esa_strength``.

    One learner only (``num_learners`` 0 or 1): with more, each would fit its own head on
    its shard, outside DDP.
    """

    weight_cap = 2.0
    """The cap on ``pi_old / b`` (``DecoupledPPO.weight_cap``)."""
    head_learning_rate = 1e-3
    """Adam learning rate of the head."""
    head_epochs = 5
    """Passes over its data each time the head is fitted."""
    head_batch_size = 256
    """Minibatch size of the head's fit."""
    head_rollouts = 4
    """How many of the latest rollouts the head is fitted on."""

    def build(self) -> None:
        """Builds RLlib's PPO learner and appends the rollout recorder after its GAE."""
        if (self.config.num_learners or 0) > 1:
            raise ValueError(
                f"expected num_learners <= 1 for ESA with PPO, got {self.config.num_learners}"
            )
        super().build()
        self._esa_pending: dict[Any, tuple[Rollout, torch.Tensor]] = {}
        self._esa_heads: dict[Any, _Head] = {}
        if self._learner_connector is not None:
            self._learner_connector.append(EsaRolloutRecorder(self._esa_pending))

    def configure_optimizers_for_module(self, module_id: Any, config: Any = None) -> None:
        """RLlib's default Adam over the module's parameters, less the quadratic head's."""
        module = self.module[module_id]
        head = getattr(_unwrapped(module), "esa_head", None)
        if head is None:
            super().configure_optimizers_for_module(module_id, config)
            return
        excluded = {id(p) for p in head.parameters()}
        params = [p for p in self.get_parameters(module) if id(p) not in excluded]
        optimizer = torch.optim.Adam(params)
        self.register_optimizer(
            module_id=module_id, optimizer=optimizer, params=params, lr_or_lr_schedule=config.lr
        )

    def after_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """PPO's bookkeeping, then the gate and the head's fit on the new rollout."""
        super().after_gradient_based_update(timesteps=timesteps)
        for module_id in list(self._esa_pending):
            rollout, advantages = self._esa_pending.pop(module_id)
            module = _unwrapped(self.module[module_id])
            if module_id not in self._esa_heads:
                self._esa_heads[module_id] = _Head(
                    torch.optim.Adam(module.esa_head.parameters(), lr=self.head_learning_rate),
                    np.random.default_rng(self.config.seed),
                )
            head = self._esa_heads[module_id]
            gate = _gate(module)
            if head.fitted:
                quality = critic_quality(module.esa_head, rollout, advantages)
                self.metrics.log_value((module_id, "esa/gate_correlation"), quality, window=1)
                head.active = gate is None or quality >= gate
            head.rollouts = [*head.rollouts, rollout][-self.head_rollouts :]
            loss = fit_critic(
                module.esa_head,
                head.optimizer,
                head.rollouts,
                epochs=self.head_epochs,
                batch_size=self.head_batch_size,
                rng=head.rng,
            )
            self.metrics.log_value((module_id, "esa/head_loss"), loss, window=1)
            if not head.fitted and gate is None:
                head.active = True
            head.fitted = True
            with torch.no_grad():
                module.esa_active.fill_(float(head.active))
            _set_strength(module, timesteps)
            self.metrics.log_value((module_id, "esa/active"), float(head.active), window=1)

    def compute_loss_for_module(
        self, *, module_id: Any, config: Any, batch: dict[str, Any], fwd_out: dict[str, Any]
    ) -> Any:
        """RLlib's PPO loss with the decoupled objective for an ESA module.

        ``w min(A r, A clip(r))`` is ``min(w A r, w A clip(r))`` for ``w > 0``: RLlib's loss
        of a batch with ``ACTION_LOGP = log pi_old(x)`` and the advantages times ``w``.
        """
        module = _unwrapped(self.module[module_id])
        if isinstance(module, EsaPPOTorchRLModule):
            with torch.no_grad():
                dist_cls = module.get_exploration_action_dist_cls()
                proximal = dist_cls.from_logits(batch[Columns.ACTION_DIST_INPUTS])
                reference = proximal.logp(batch[Columns.ACTIONS])
                ratio = torch.exp(reference - batch[Columns.ACTION_LOGP])
                weight = ratio.clamp(max=self.weight_cap)
            advantages = batch[Postprocessing.ADVANTAGES] * weight
            batch = {**batch, Columns.ACTION_LOGP: reference, Postprocessing.ADVANTAGES: advantages}
        return super().compute_loss_for_module(
            module_id=module_id, config=config, batch=batch, fwd_out=fwd_out
        )
